"""Result files: calibration.yaml schema, cameramodels in mrcal, atomic writes, plots."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from clcgraph.config import Config
from clcgraph.errors import DataError, InputError
from clcgraph.geometry import R_from_r, T_from_rt, compose_rt, invert_rt, r_from_R, transform
from clcgraph.outputs.atomic import marker_kind
from clcgraph.outputs.results import load_result, write_results
from clcgraph.types import (BoardGeometry, CameraBoardObservation, LidarBoardObservation, Problem, Rejected, Result,
                            SectorReport, Sensor)

LIDAR1_RT = np.array([0.01, -0.02, 0.3, -0.5, 0.8, 0.1])
# camera right-down-forward looking along lidar0's +x, slightly offset
_R_cam = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # columns: cam axes in lidar0
CAMERA_RT = compose_rt(np.r_[0, 0, 0, 0.3, -0.2, -0.1], np.r_[r_from_R(_R_cam), 0, 0, 0])


def make_result(seed: int = 0, *, n_snapshots: int = 8) -> Result:
    """A hand-built 3-sensor Result (lidar0, lidar1, camera) with consistent observations."""
    rng = np.random.default_rng(seed)
    board = BoardGeometry(corners_x=8, corners_y=6, square_m=0.1, width_m=1.0, height_m=0.8)
    cam = Sensor("/cam/image", "camera", lensmodel="LENSMODEL_OPENCV4",
                 intrinsics=np.array([600.0, 600.0, 640.0, 400.0, 0.01, -0.01, 0.0, 0.0]), imagersize=(1280, 800))
    sensors = (Sensor("/lidar/front/points", "lidar"), Sensor("/lidar/rear/points", "lidar"), cam)
    rt_sensor = np.array([np.zeros(6), LIDAR1_RT, CAMERA_RT])
    rt_board = np.full((n_snapshots, 6), np.nan)
    lidar_obs, cam_obs = [], []
    from clcgraph.cameras import project

    for k in range(n_snapshots):
        if k == 3:
            continue  # an unused snapshot
        yaw = rng.uniform(-0.6, 0.6)
        # board facing lidar0 (board z toward -x), 3..6 m ahead
        R = np.array([[0, 0, -1], [1, 0, 0], [0, -1, 0]], float)
        R = R_from_r(np.r_[0, 0, yaw]) @ R
        c = R_from_r(np.r_[0, 0, yaw]) @ np.r_[rng.uniform(3, 6), 0, 0]
        rt_board[k] = np.r_[r_from_R(R), c + np.r_[0, -0.35, 0.25]]
        pts_l0 = transform(rt_board[k], board.corners())
        for i in (0, 1):
            p = transform(invert_rt(rt_sensor[i]), pts_l0)
            n = (R @ np.r_[0, 0, 1.0])
            lidar_obs.append(LidarBoardObservation(i, k, p, np.r_[n, 0.0], 0.01))
        q = project(transform(invert_rt(rt_sensor[2]), pts_l0), cam.lensmodel, cam.intrinsics)
        cam_obs.append(CameraBoardObservation(2, k, q))
    problem = Problem(sensors, board, tuple(lidar_obs), tuple(cam_obs),
                      np.arange(n_snapshots, dtype=np.int64) * 10**9,
                      rejected=(Rejected("board not found", "segmentation", 1, 3),),
                      snapshot_bags=tuple(f"/data/capture/pose{k:03d}.bag" for k in range(n_snapshots)))
    A = rng.normal(size=(12, 12)) * 1e-3
    cov = A @ A.T + np.eye(12) * 1e-6
    nl, nc = 4000, 3000
    residuals = {
        "lidar_m": rng.normal(0, 0.012, nl), "lidar_sensor": rng.integers(0, 2, nl),
        "lidar_snapshot": rng.choice([0, 1, 2, 4, 5, 6, 7], nl),
        "camera_px": rng.normal(0, 0.4, nc), "camera_sensor": np.full(nc, 2),
        "camera_snapshot": rng.choice([0, 1, 2, 4, 5, 6, 7], nc),
    }
    sectors = SectorReport(
        n_sectors=12, observations_per_sector=np.array([3, 2, 1, 0, 0, 0, 0, 0, 0, 0, 1, 2]),
        isvisible_per_sensor_per_sector=np.ones((3, 12), bool),
        stdev_worst_per_sector=np.linspace(0.002, 0.05, 12),
        isensors_pair_stdev_worst=np.tile([0, 2], (12, 1)), isector_of_last_snapshot=1,
    )
    return Result(problem=problem, rt_lidar0_sensor=rt_sensor, covariance_rt=cov, rt_lidar0_board=rt_board,
                  noise={"lidar_m": 0.012, "camera_px": 0.4}, rms={"normalized": 1.01, "lidar_m": 0.012, "camera_px": 0.4},
                  rejected=problem.rejected + (Rejected("residual 8.1 sigma", "outlier", 2, 5),),
                  sectors=sectors, residuals=residuals)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    result = make_result()
    out = tmp_path_factory.mktemp("res") / "out"
    dumped = []

    def dump(problem, path):
        dumped.append(problem)
        np.savez(path, n=len(problem.sensors))

    names = write_results(result, out, config=Config(), problem_dump=dump, extra_files={"notes.txt": "hi"})
    return result, out, names, dumped


def test_calibration_yaml_schema(written):
    result, out, names, dumped = written
    d = yaml.safe_load((out / "calibration.yaml").read_text())
    for key in ("reference", "sensors", "covariance_rt_lidar0_sensor", "rms", "noise", "snapshots", "sectors"):
        assert key in d
    assert d["reference"] == "/lidar/front/points"
    assert [s["topic"] for s in d["sensors"]] == ["/lidar/front/points", "/lidar/rear/points", "/cam/image"]
    assert [s["kind"] for s in d["sensors"]] == ["lidar", "lidar", "camera"]
    for i, s in enumerate(d["sensors"]):
        assert len(s["rt_lidar0_sensor"]) == 6 and len(s["stdev_rt"]) == 6
        T = np.array(s["T_lidar0_sensor"])
        assert T.shape == (4, 4)
        np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
        np.testing.assert_allclose(T, T_from_rt(result.rt_lidar0_sensor[i]), atol=1e-12)
        # T really maps sensor points to lidar0: R orthonormal, same as transform()
        p = np.array([[1.0, 2.0, 3.0]])
        np.testing.assert_allclose(T[:3, :3] @ p[0] + T[:3, 3], transform(s["rt_lidar0_sensor"], p)[0], atol=1e-12)
        np.testing.assert_allclose(s["stdev_rt"], result.stdev_rt(i), rtol=1e-12)
        np.testing.assert_allclose(s["stdev_position_mm"], 1e3 * result.stdev_rt(i)[3:], rtol=1e-12)
    np.testing.assert_array_equal(d["sensors"][0]["stdev_rt"], np.zeros(6))
    C = np.array(d["covariance_rt_lidar0_sensor"])
    assert C.shape == (12, 12)
    np.testing.assert_allclose(C, C.T, atol=0)
    np.testing.assert_allclose(C, result.covariance_rt, rtol=1e-15)
    assert d["rms"] == {"normalized": 1.01, "lidar_m": 0.012, "camera_px": 0.4}
    assert d["noise"] == {"lidar_m": 0.012, "camera_px": 0.4}
    assert d["snapshots"]["used"] == 7
    rej = d["snapshots"]["rejected"]
    assert {"index": 3, "bag": "pose003.bag", "sensor": "/lidar/rear/points", "stage": "segmentation",
            "reason": "board not found"} in rej
    # every snapshot by index, bag and stamp; the unused one (3) marked
    listed = d["snapshots"]["list"]
    assert [e["bag"] for e in listed] == [f"pose{k:03d}.bag" for k in range(8)]
    assert [e["stamp_ns"] for e in listed] == [k * 10**9 for k in range(8)]
    assert [e["index"] for e in listed if not e["used"]] == [3]
    assert rej[1]["index"] == 5 and rej[1]["sensor"] == "/cam/image"
    assert d["sectors"]["n_sectors"] == 12 and len(d["sectors"]["stdev_worst_per_sector_m"]) == 12
    assert d["sectors"]["isector_of_last_snapshot"] == 1
    assert d["clcgraph_version"]



def test_calibration_yaml_is_the_python_emitters_text(written):
    # calibration.yaml is written by libyaml's emitter (config.CSafeDumperNoAliases): the same bytes as
    # PyYAML's own, a unicode topic and a note wider than the line included
    from clcgraph.config import CSafeDumperNoAliases, SafeDumperNoAliases
    from clcgraph.outputs.results import calibration_dict

    result, out, _, _ = written
    cal = calibration_dict(result)
    cal["extra"] = {"topic": "/caméra/ü", "note": "x " * 150, "same": cal["sensors"][0]["stdev_rt"], "nan": float("nan")}
    cal["again"] = cal["extra"]["same"]  # used twice: written out twice, no alias
    kw = dict(sort_keys=False, default_flow_style=None, width=200)
    c = yaml.dump(cal, Dumper=CSafeDumperNoAliases, **kw)
    assert c == yaml.dump(cal, Dumper=SafeDumperNoAliases, **kw) and "&" not in c
    assert (out / "calibration.yaml").read_text().endswith(yaml.dump(calibration_dict(result), Dumper=SafeDumperNoAliases, **kw))

def test_load_result_roundtrip_and_validation(written, tmp_path):
    result, out, _, _ = written
    cal = load_result(out)
    np.testing.assert_allclose(cal["sensors"][1]["rt_lidar0_sensor"], LIDAR1_RT, atol=1e-15)
    assert cal["covariance_rt_lidar0_sensor"].shape == (12, 12)
    bad = yaml.safe_load((out / "calibration.yaml").read_text())
    bad["sensors"][1]["T_lidar0_sensor"][0][3] += 0.1
    (tmp_path / "calibration.yaml").write_text(yaml.safe_dump(bad))
    with pytest.raises(DataError, match="disagrees"):
        load_result(tmp_path)
    del bad["noise"]
    (tmp_path / "calibration.yaml").write_text(yaml.safe_dump(bad))
    with pytest.raises(DataError, match="noise"):
        load_result(tmp_path)
    with pytest.raises(InputError, match="nothere"):
        load_result(tmp_path / "nothere")


def test_cameramodels_load_in_mrcal(written):
    import mrcal

    result, out, names, _ = written
    for i, s in enumerate(result.problem.sensors):
        m = mrcal.cameramodel(str(out / f"sensor{i}-mounted.cameramodel"))
        # mrcal extrinsics are rt_cam_ref with ref = lidar0
        np.testing.assert_allclose(m.extrinsics_rt_fromref(), invert_rt(result.rt_lidar0_sensor[i]), atol=1e-9)
        np.testing.assert_allclose(m.extrinsics_rt_toref(), result.rt_lidar0_sensor[i], atol=1e-9)
        if s.is_camera:
            assert m.intrinsics()[0] == "LENSMODEL_OPENCV4"
            np.testing.assert_allclose(m.intrinsics()[1], s.intrinsics)
            assert tuple(m.imagersize()) == (1280, 800)
        else:
            assert m.intrinsics()[0] == "LENSMODEL_PINHOLE"


def test_other_files(written):
    result, out, names, dumped = written
    assert Config.from_yaml(out / "config.resolved.yaml") == Config()
    assert dumped and dumped[0] is result.problem and (out / "problem.npz").is_file()
    assert (out / "notes.txt").read_text() == "hi"
    assert all(p.exists() for p in names.values())
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # no temp dirs left


def test_atomic_failure_leaves_nothing(tmp_path):
    result = make_result()
    out = tmp_path / "out"

    def dump(problem, path):
        Path(path).write_text("partial")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        write_results(result, out, config=Config(), problem_dump=dump)
    assert list(tmp_path.iterdir()) == []


def test_atomic_failure_keeps_previous_results(tmp_path):
    result = make_result()
    out = tmp_path / "out"
    write_results(result, out)
    before = sorted(p.name for p in out.iterdir())

    def bad(path):
        raise OSError(28, "No space left")

    with pytest.raises(OSError):
        write_results(result, out, extra_files={"report.html": bad})
    assert sorted(p.name for p in out.iterdir()) == before
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_rewrite_replaces_a_previous_output_whole(tmp_path):
    out = tmp_path / "out"
    write_results(make_result(), out)
    assert marker_kind(out) == "results"
    (out / "stale.txt").write_text("from the previous run")  # a file only the old output had
    write_results(make_result(1), out)
    assert not (out / "stale.txt").exists() and (out / "calibration.yaml").is_file()
    assert marker_kind(out) == "results"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_a_directory_clcgraph_did_not_write_is_refused(tmp_path):
    out = tmp_path / "capture"
    out.mkdir()
    (out / "note.txt").write_text("mine")
    with pytest.raises(InputError, match=rf"{out}: .*not a clcgraph output.*--force"):
        write_results(make_result(), out)
    assert [p.name for p in out.iterdir()] == ["note.txt"] and (out / "note.txt").read_text() == "mine"
    assert [p.name for p in tmp_path.iterdir()] == ["capture"]  # no temporary, no lock file left


def test_force_replaces_a_foreign_directory_and_empty_is_fine(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "note.txt").write_text("mine")
    write_results(make_result(), out, force=True)
    assert not (out / "note.txt").exists() and (out / "calibration.yaml").is_file()
    empty = tmp_path / "empty"
    empty.mkdir()
    write_results(make_result(), empty)
    assert (empty / "calibration.yaml").is_file()


def test_a_calibration_never_replaces_simulated_bags(tmp_path):
    from clcgraph.outputs.atomic import atomic_dir

    with atomic_dir(tmp_path / "sim", kind="session") as tmp:
        (tmp / "pose000.bag").write_bytes(b"bag")
    with pytest.raises(InputError, match="simulated bags, not calibration results"):
        write_results(make_result(), tmp_path / "sim")
    assert (tmp_path / "sim" / "pose000.bag").read_bytes() == b"bag"


def test_unwritable_dir_is_input_error(tmp_path):
    # a parent that is a file cannot hold a directory, for root too
    blocker = tmp_path / "blocker"
    blocker.write_text("x")
    with pytest.raises(InputError, match=str(blocker / "out")):
        write_results(make_result(), blocker / "out")
    if os.geteuid() != 0:  # permissions only bind non-root users
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o555)
        try:
            with pytest.raises(InputError, match=str(ro / "out")):
                write_results(make_result(), ro / "out")
            assert list(ro.iterdir()) == []
        finally:
            ro.chmod(0o755)


def test_out_is_a_file_is_input_error(tmp_path):
    f = tmp_path / "out"
    f.write_text("x")
    with pytest.raises(InputError, match="not a directory"):
        write_results(make_result(), f)
    assert f.read_text() == "x"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_covariance_symmetrized(tmp_path):
    import dataclasses

    r = make_result()
    C = r.covariance_rt.copy()
    C[0, 1] += 1e-12  # rounding-level asymmetry from a solver
    write_results(dataclasses.replace(r, covariance_rt=C), tmp_path / "o")
    got = load_result(tmp_path / "o")["covariance_rt_lidar0_sensor"]
    np.testing.assert_array_equal(got, got.T)
    np.testing.assert_allclose(got, C, atol=1e-12)


def test_calibrate_bags_refuses_a_foreign_out_before_reading_any_bag(tmp_path):
    """The issue's case: a note in --out was gone after calibrate_bags(..., out=...)."""
    from clcgraph.api import calibrate_bags

    out = tmp_path / "out"
    out.mkdir()
    (out / "note.txt").write_text("mine")
    missing = str(tmp_path / "no-such-*.bag")
    with pytest.raises(InputError, match=rf"{out}: exists and is not a clcgraph output"):
        calibrate_bags([missing], ["/l0", "/l1"], out=out)  # refused first: the bags are never looked at
    with pytest.raises(InputError, match="no such bag"):  # force passes the check; the work then fails
        calibrate_bags([missing], ["/l0", "/l1"], out=out, force=True)
    assert [p.name for p in out.iterdir()] == ["note.txt"] and (out / "note.txt").read_text() == "mine"


def test_summary_table_says_its_conventions_and_names_bags():
    from clcgraph.api import summary_table
    from clcgraph.geometry import pose_stdevs, rpy_deg_from_rt

    result = make_result()
    text = summary_table(result)
    header, *rows = text.splitlines()
    assert "roll, pitch, yaw [deg] (fixed axes x-y-z)" in header
    assert "1-sigma x, y, z [mm]" in header and "1-sigma about own x, y, z [deg]" in header
    cam = next(r for r in rows if r.startswith("/cam/image"))
    # every axis's number, not the worst one alone
    sd_rot, sd_pos = pose_stdevs(CAMERA_RT, result.covariance_block(2))
    assert " ".join(f"{v:.2f}" for v in 1e3 * sd_pos) in cam
    assert " ".join(f"{v:.3f}" for v in np.degrees(sd_rot)) in cam
    assert " ".join(f"{v:+.3f}" for v in rpy_deg_from_rt(CAMERA_RT)) in cam
    assert "snapshot 3 (pose003.bag @3.000 s): /lidar/rear/points: board not found" in text


def test_an_output_file_never_replaces_what_clcgraph_did_not_write(tmp_path):
    """--png / --dump / --yaml files (outputs.atomic.check_out_file): a user's file of another kind,
    a directory, a missing directory or another type's name are one-line InputErrors naming the
    option; a file clcgraph wrote (its signature) may be replaced; --force replaces anything."""
    from clcgraph.outputs.atomic import check_out_file, check_out_folder

    notes = tmp_path / "notes.png"
    notes.write_text("my notes")
    (tmp_path / "pics").mkdir()
    cases = {(notes, ".png"): "exists and is not a .png file clcgraph wrote",
             (tmp_path / "pics", ".png"): "a directory",
             (tmp_path / "new" / "x.png", ".png"): "does not exist",
             (tmp_path / "x.txt", ".png"): "name the file *.png",
             (tmp_path / "x.png", ".npz"): "name the file *.npz"}
    for (path, suffix), words in cases.items():
        with pytest.raises(InputError, match="--out-file") as e:
            check_out_file(path, suffix, flag="--out-file")
        assert words in str(e.value) and "\n" not in str(e.value)
    assert notes.read_text() == "my notes"
    assert check_out_file(notes, ".png", flag="--png", force=True) == notes
    png = tmp_path / "mine.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(20))
    yml = tmp_path / "c.yaml"
    yml.write_text("# clcgraph comparison\na: 1\n")
    npz = tmp_path / "d.npz"
    np.savez(npz, a=np.zeros(2))
    for path, suffix in ((png, ".png"), (yml, ".yaml"), (npz, ".npz")):
        assert check_out_file(path, suffix, flag="--x") == path
    # the API functions that write such files check them first (before reading their inputs)
    from clcgraph import api

    for call in (lambda: api.show_aligned(tmp_path / "no.bag", tmp_path / "no-calib", png=notes),
                 lambda: api.uncertainty_grid_png(tmp_path / "no-dump", notes),
                 lambda: api.write_comparison_yaml(None, tmp_path / "notes.png")):
        with pytest.raises(InputError, match="--(png|yaml) .*notes.png"):
            call()
    assert notes.read_text() == "my notes"
    with pytest.raises(InputError, match="a file; name a directory"):
        check_out_folder(notes, flag="--png")
    assert check_out_folder(tmp_path / "a" / "b", flag="--png") == tmp_path / "a" / "b"
    assert not (tmp_path / "a").exists()  # made when the first picture is written
    with pytest.raises(InputError, match="not a writable directory"):
        check_out_folder(notes / "sub", flag="--png")
    from clcgraph.outputs.atomic import make_out_folder

    assert make_out_folder(tmp_path / "a" / "b", flag="--png").is_dir()
    if os.path.isdir("/proc"):  # root may "write" /proc by access(), but no directory can be made there
        with pytest.raises(InputError, match="--png /proc/nope: cannot make the directory"):
            make_out_folder("/proc/nope", flag="--png")
