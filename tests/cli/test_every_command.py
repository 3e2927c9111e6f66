"""Every `clcgraph` command end to end through its real entry point, on one small simulated
session (2 LIDARs + a camera, 8 board poses) shared by the module: exit code 0, the files it
writes, and nothing on stderr that looks like a traceback or an error.

`simulate`, `solve`, `replay` and `show-bag` run as real subprocesses (the installed console
script); the rest through ``clcgraph.cli.main`` (same parser and error handling, no interpreter
start-up). `simulate-drive`, `targetless`, `demo`, `compare` and `fleet` are run in the tests named in COVERED.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from clcgraph.cli import build_parser, main
from clcgraph.outputs.atomic import marker_kind
from clcgraph.sim.capture import DEMO_RIG

ROOT = Path(__file__).resolve().parents[2]
TOPICS = ("/lidar/a", "/lidar/b", "/cam/front")
RIG = """
lidars:
  - {topic: /lidar/a, model: vlp16, layout: velodyne, frame_id: a, xyz: [0, 0, 1.9], rpy_deg: [0, 0, 0]}
  - {topic: /lidar/b, model: vlp16, layout: ouster, frame_id: b, xyz: [1.2, 0.5, 1.2], rpy_deg: [1, 5, 20]}
cameras:
  - {topic: /cam/front, model: front.cameramodel, encoding: mono8, frame_id: cam, xyz: [0.6, -0.2, 1.5],
     rpy_deg: [0, 4, -5]}
board: {corners: [10, 10], square_m: 0.1, size_m: [1.3, 1.3]}
"""

# command -> where it runs end to end (this module unless named)
COVERED = {
    "show-bag": "test_show_bag_subprocess", "segment": "test_lidar_tools", "detect": "test_detect",
    "infer-lidar-spacing": "test_lidar_tools", "solve": "session", "replay": "test_replay_subprocess",
    "format-for-ros": "test_format_for_ros", "show-aligned": "test_show_aligned_and_uncertainty",
    "show-uncertainty": "test_show_aligned_and_uncertainty", "config": "test_config_dump_and_check",
    "simulate": "session",
    "simulate-drive": "tests/test_targetless_units.py::test_cli_simulate_drive_writes_a_bag_to_try_targetless_on",
    "targetless": "tests/test_targetless_pipeline.py::test_cli_targetless_prints_the_table_and_writes_outputs",
    "demo": "tests/cli/test_demo.py::test_demo",
    "compare": "tests/fleet/test_compare.py::test_compare_command_table_yaml_and_exit_codes",
    "fleet": "tests/fleet/test_fleet_runs.py::test_resume_keeps_complete_vehicles_and_reruns_the_failed_one",
}


def _clcgraph(*args, timeout=600) -> subprocess.CompletedProcess:
    exe = shutil.which("clcgraph")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    cmd = [exe] if exe else [sys.executable, "-m", "clcgraph.cli"]
    return subprocess.run([*cmd, "-q", *map(str, args)], env=env, capture_output=True, text=True, timeout=timeout)


def _clean(err: str) -> None:
    assert "Traceback" not in err and "error" not in err.lower(), err


def _ok(capsys, argv) -> str:
    rc = main(["-q", *map(str, argv)])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    _clean(cap.err)
    return cap.out


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """(bags dir, camera model, calibration dir): `clcgraph simulate`, then `clcgraph solve`."""
    d = tmp_path_factory.mktemp("session")
    model = d / "front.cameramodel"
    shutil.copy(DEMO_RIG.parent / "front.cameramodel", model)
    (d / "rig.yaml").write_text(RIG)
    r = _clcgraph("simulate", d / "rig.yaml", "--out", d / "bags", "--poses", "8", "--seed", "2", "--planned-tilts")
    assert r.returncode == 0, r.stderr
    _clean(r.stderr)
    assert "wrote 8 board poses of 3 sensors" in r.stdout
    r = _clcgraph("solve", "--bag", f"{d}/bags/*.bag", "--topics", ",".join(TOPICS), model, "--out", d / "calib")
    assert r.returncode == 0, r.stderr
    _clean(r.stderr)
    assert all(t in r.stdout for t in TOPICS) and "wrote" in r.stdout.splitlines()[-1]
    return d / "bags", model, d / "calib"


def test_solve_report_shows_the_data(session):
    """`clcgraph solve`'s report.html: one file, the LIDAR scans drawn on the camera's image with the solved
    and the nominal (/tf_static) extrinsics, the run's record, the check's verdict at the top."""
    import re

    bags, model, calib = session
    text = (calib / "report.html").read_text()
    assert all(src.startswith(("data:image/png;base64,", "data:image/jpeg;base64,"))
               for src in re.findall(r"src='([^']+)'", text))
    assert not [p.name for p in calib.glob("*.png")]
    assert "/cam/front, snapshot" in text and "whole scans" in text  # the camera's own picture
    assert "right picture: nominal /tf_static extrinsics" in text
    verdict = re.search(r"LIDAR board points on the cameras' boards: [^\n]*", text)
    assert verdict and "<b>on the board</b>" in verdict.group(0), verdict and verdict.group(0)
    assert verdict.start() < text.index("<h2>Poses</h2>")
    assert "pose000.bag" in text and "8 bag(s)" in text and str(model) in text
    assert "process: " in text and " solve --bag " in text  # the command line as run
    assert "effective settings (config.resolved.yaml)" in text


def test_api_report_is_the_clis(session, tmp_path):
    """A Python user's read_problem + calibrate + write_outputs (no report_inputs) gets the report `clcgraph
    solve` writes: the same figures (the LIDAR scans on the camera's own image, solved beside nominal), the
    same verdicts, the bags and the settings recorded; not board points on a grey canvas and no record."""
    import glob
    import re

    import clcgraph

    bags, model, calib = session
    problem = clcgraph.read_problem(sorted(glob.glob(f"{bags}/*.bag")), TOPICS, [model])
    clcgraph.write_outputs(clcgraph.calibrate(problem), tmp_path / "api")
    api, cli = ((d / "report.html").read_text() for d in (tmp_path / "api", calib))
    alts = lambda t: re.findall(r"alt='([^']+)'", t)  # noqa: E731
    heads = lambda t: re.findall(r"<h2>([^<]+)</h2>", t)  # noqa: E731
    verdicts = lambda t: re.findall(r"<div class='verdict[^']*'>([^:]+): <b>([^<]+)</b>", t)  # noqa: E731
    assert alts(api) == alts(cli) and "lidar-on-camera-2.jpg" in alts(api)
    assert heads(api) == heads(cli) and verdicts(api) == verdicts(cli)
    assert "whole scans" in api and "board points only" not in api
    assert "right picture: nominal /tf_static extrinsics" in api
    assert "pose000.bag" in api and "8 bag(s)" in api and "No record of the bags" not in api
    assert "clcgraph.write_outputs(result, " in api and "effective settings (config.resolved.yaml)" in api


def test_every_command_is_covered():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert set(sub.choices) == set(COVERED)
    for cmd, where in COVERED.items():
        if "::" in where:
            path, name = where.split("::")
            text = (ROOT / path).read_text()
            assert f"def {name}(" in text and f'"{cmd}"' in text, (cmd, where)


def test_solve_outputs(session):
    bags, _, calib = session
    names = {p.name for p in calib.iterdir()}
    assert {"calibration.yaml", "config.resolved.yaml", "problem.npz", "report.html",
            "sensor0-mounted.cameramodel", "sensor2-mounted.cameramodel", ".clcgraph-output"} <= names
    assert marker_kind(calib) == "results" and marker_kind(bags) == "session"
    truth = yaml.safe_load((bags / "truth.yaml").read_text())
    cal = yaml.safe_load((calib / "calibration.yaml").read_text())
    want = {s["topic"]: np.asarray(s["rt_lidar0_sensor"]) for s in truth["sensors"]}
    for s in cal["sensors"]:  # a sanity bound, not the accuracy test (test_end_to_end has that)
        assert np.abs(np.asarray(s["rt_lidar0_sensor"])[3:] - want[s["topic"]][3:]).max() < 0.03, s["topic"]


def test_show_bag_subprocess(session):
    bags, _, _ = session
    r = _clcgraph("show-bag", bags / "pose000.bag")
    assert r.returncode == 0, r.stderr
    _clean(r.stderr)
    assert all(t in r.stdout for t in TOPICS) and "PointCloud2 1 x" in r.stdout and "PointCloud2 16 x" in r.stdout


def test_replay_subprocess(session):
    """The issue's bug: replay printed the poses, then a TypeError on the per-sensor noise."""
    _, _, calib = session
    dump = calib / "problem.npz"
    plain = _clcgraph("replay", dump)
    assert plain.returncode == 0, plain.stderr
    _clean(plain.stderr)
    lines = plain.stdout.splitlines()
    assert [ln.split(":")[0] for ln in lines[:3]] == list(TOPICS)
    per_sensor = next(ln for ln in lines if ln.startswith("noise per_sensor:"))
    assert all(t in per_sensor for t in TOPICS), per_sensor
    cal = yaml.safe_load((calib / "calibration.yaml").read_text())
    rt_b = np.array(lines[1].split("[")[1].split("]")[0].split(), float)
    np.testing.assert_allclose(rt_b, cal["sensors"][1]["rt_lidar0_sensor"], atol=2e-6)  # replay = the solve
    # board 2 out leaves every direction checked (3 or 7 out leaves /cam/front's height on one board: refused)
    for extra in (["--exclude", "2"], ["--inject-noise", "--seed", "1"]):
        r = _clcgraph("replay", dump, *extra)
        assert r.returncode == 0, (extra, r.stderr)
        _clean(r.stderr)
        other = np.array(r.stdout.splitlines()[1].split("[")[1].split("]")[0].split(), float)
        assert np.abs(other - rt_b).max() > 1e-7, extra  # a different problem, a different answer
        assert np.abs(other - rt_b).max() < 0.05, extra


def test_lidar_tools(session, capsys, tmp_path):
    bags, _, _ = session
    out = _ok(capsys, ["infer-lidar-spacing", *sorted(bags.glob("*.bag"))[:2], "--topic", "/lidar/b"])
    from clcgraph.sim.lidar import LidarModel

    vlp16 = LidarModel.preset("vlp16")  # /lidar/b: an organised (Ouster-layout) VLP-16
    assert out.strip() == f"/lidar/b: {len(vlp16.elevations_deg)} rings, Npoints_per_rotation {vlp16.npoints_per_rotation}"
    out = _ok(capsys, ["segment", *sorted(bags.glob("*.bag")), "--topic", "/lidar/a", "--png", tmp_path / "seg",
                       "--dump", tmp_path / "seg.npz"])
    found = int(out.splitlines()[-1].split("/")[0])
    assert found >= 6 and out.splitlines()[-1].endswith("/8 scans with a board"), out
    names = [b.name for b in sorted(bags.glob("*.bag"))]
    assert [line.split()[0] for line in out.splitlines()[:-1]] == names  # each scan named by its bag
    assert len(list((tmp_path / "seg").glob("*.png"))) == 8 and "scan0_segments" in np.load(tmp_path / "seg.npz")


def test_detect(session, capsys, tmp_path):
    bags, _, _ = session
    out = _ok(capsys, ["detect", *sorted(bags.glob("*.bag")), "--topic", "/cam/front", "--png", tmp_path / "det"])
    truth = yaml.safe_load((bags / "truth.yaml").read_text())
    seen = sum("/cam/front" in s["corners_px"] for s in truth["snapshots"])  # the board in the image
    assert out.splitlines()[-1] == f"{out.count('found 100 corners')}/8 images with a chessboard"
    assert out.count("found 100 corners") >= seen - 1 >= 1, out
    assert [line.split()[0] for line in out.splitlines()[:-1]] == [b.name for b in sorted(bags.glob("*.bag"))]
    assert len(list((tmp_path / "det").glob("*.png"))) == 8


def test_format_for_ros(session, capsys, tmp_path):
    bags, _, calib = session
    ros = tmp_path / "ros"
    for _ in range(2):  # the second run replaces the first's output
        _ok(capsys, ["format-for-ros", bags / "pose000.bag", "--calibration", calib, "--out", ros])
    names = sorted(p.name for p in ros.iterdir())
    assert "ros-transforms.yaml" in names and "sensors.urdf.xml" in names and marker_kind(ros) == "ros"
    assert yaml.safe_load((ros / "ros-transforms.yaml").read_text())["transforms"]
    # never over the calibration it reads
    before = sorted(p.name for p in calib.iterdir())
    assert main(["-q", "format-for-ros", str(bags / "pose000.bag"), "--calibration", str(calib),
                 "--out", str(calib)]) == 2
    assert "calibration results" in capsys.readouterr().err and sorted(p.name for p in calib.iterdir()) == before


def test_show_aligned_and_uncertainty(session, capsys, tmp_path):
    import matplotlib.image

    bags, _, calib = session
    out = _ok(capsys, ["show-aligned", bags / "pose000.bag", "--calibration", calib, "--png", tmp_path / "a.png"])
    assert out.strip() == f"wrote {tmp_path / 'a.png'}" and matplotlib.image.imread(tmp_path / "a.png").shape[1] > 500
    out = _ok(capsys, ["show-uncertainty", calib, "--sensors", "0,1", "--gridn", "11", "--png", tmp_path / "u.png"])
    lo, hi = (float(v) for v in out.split("stdev ")[1].split(" mm")[0].split(" .. "))
    assert 0 < lo <= hi < 100, out  # mm at up to 20 m from a rig calibrated to mm / 0.0x deg
    assert (tmp_path / "u.png").stat().st_size > 1000


def test_config_dump_and_check(capsys, tmp_path):
    from clcgraph.config import Config

    text = _ok(capsys, ["config", "dump", "--set", "solve.outlier_sigma=4.5"])
    (tmp_path / "c.yaml").write_text(text)
    assert Config.from_yaml(tmp_path / "c.yaml") == Config().replace(solve={"outlier_sigma": 4.5})
    assert _ok(capsys, ["config", "check", "--config", tmp_path / "c.yaml"]).strip() == f"{tmp_path / 'c.yaml'}: OK"
