"""Interrupted and competing writers of an --out directory, through the real `clcgraph` command:
kill -9 mid-write, SIGINT, SIGTERM, concurrent runs, a symlinked --out, and an --out that holds
what the user recorded. Each must end in one line (exit 2, or 130 / 143 on a signal), leave
--out whole (the previous output or the new one) and leave nothing behind that a later run
does not clean up.

A slow `clcgraph simulate` (many board poses) is the writer: its temporary directory exists
for the whole simulation, so the tests signal it while bags are being written into it.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from clcgraph.cli import main
from clcgraph.errors import InputError
from clcgraph.outputs.atomic import MARKER, atomic_dir, marker_kind

ROOT = Path(__file__).resolve().parents[2]
RIG = """
lidars:
  - {topic: /lidar/a, model: vlp16, layout: velodyne, frame_id: a, xyz: [0, 0, 1.9], rpy_deg: [0, 0, 0]}
  - {topic: /lidar/b, model: vlp16, layout: ouster, frame_id: b, xyz: [1.2, 0.5, 1.2], rpy_deg: [1, 5, 20]}
cameras: []
board: {corners: [10, 10], square_m: 0.1, size_m: [1.3, 1.3]}
"""
# Generous: the CI machine is shared; a healthy run needs a few seconds.
TIMEOUT_S = 120


def _clcgraph() -> list[str]:
    # the `clcgraph` command itself (beside this Python in a venv, else on PATH): under
    # `python -m` an interrupted run exits by SIGINT (-2) instead of 130 (known, not understood)
    beside = Path(sys.executable).with_name("clcgraph")
    exe = str(beside) if beside.exists() else shutil.which("clcgraph")
    return [exe] if exe else [sys.executable, "-m", "clcgraph"]


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    return env


def _start(*args) -> subprocess.Popen:
    return subprocess.Popen([*_clcgraph(), *map(str, args)], env=_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _run(*args) -> subprocess.CompletedProcess:
    return subprocess.run([*_clcgraph(), *map(str, args)], env=_env(), capture_output=True, text=True,
                          timeout=TIMEOUT_S)


def _one_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    return lines[0]


def _temporaries(out: Path) -> list[Path]:
    return sorted(out.parent.glob(f".{out.name}.clcgraph-*"))


def _wait_for_bag_in_temporary(proc: subprocess.Popen, out: Path) -> Path:
    """The writer's temporary directory, once a bag is being written into it."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < TIMEOUT_S:
        assert proc.poll() is None, proc.communicate()
        tmp = [p for p in _temporaries(out) if f"-tmp-{proc.pid}-" in p.name]
        if tmp and any(tmp[0].glob("pose*.bag")):
            return tmp[0]
        time.sleep(0.05)
    proc.kill()
    raise AssertionError(f"no temporary directory with a bag beside {out} after {TIMEOUT_S} s")


@pytest.fixture(scope="module")
def rig(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("rig") / "rig.yaml"
    p.write_text(RIG)
    return p


@pytest.fixture(scope="module")
def session(tmp_path_factory, rig) -> Path:
    """A small simulated session (2 bags), written once and copied by the tests that need one."""
    out = tmp_path_factory.mktemp("session") / "bags"
    assert main(["-q", "simulate", str(rig), "--out", str(out), "--poses", "2", "--seed", "1"]) == 0
    return out


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _slow_simulate(rig, out):
    return _start("-q", "simulate", rig, "--out", out, "--poses", "500", "--seed", "7")


def test_kill_9_leaves_no_half_written_out_and_the_next_run_cleans_up(tmp_path, rig, session):
    out = tmp_path / "sim"
    proc = _slow_simulate(rig, out)
    tmp = _wait_for_bag_in_temporary(proc, out)
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=TIMEOUT_S)
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists() and tmp.is_dir()  # the temporary of the dead run, never a half-written --out
    # a later run into the same --out removes it (its writer's pid is gone) and writes --out whole
    assert main(["-q", "simulate", str(rig), "--out", str(out), "--poses", "1", "--seed", "3"]) == 0
    assert _temporaries(out) == [] and sorted(p.name for p in tmp_path.iterdir()) == ["sim"]
    truth = yaml.safe_load((out / "truth.yaml").read_text())
    assert [s["bag"] for s in truth["snapshots"]] == ["pose000.bag"] and (out / "pose000.bag").is_file()
    assert marker_kind(out) == "session"


def test_a_live_writers_temporary_is_not_removed(tmp_path):
    """Only temporaries of dead pids are stale: a running writer's own one is left alone."""
    out = tmp_path / "out"
    foreign = tmp_path / f".out.clcgraph-tmp-{os.getppid()}-abc"  # a live pid (our parent)
    foreign.mkdir()
    (foreign / MARKER).write_text("clcgraph-output: results\n")
    not_ours = tmp_path / ".out.clcgraph-tmp-999999999-abc"  # dead pid but no marker: not ours
    not_ours.mkdir()
    with atomic_dir(out) as t:
        (t / "a").write_text("1")
    assert foreign.is_dir() and not_ours.is_dir() and (out / "a").read_text() == "1"


@pytest.mark.parametrize("signum, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_exits_in_one_line_and_keeps_the_previous_output(tmp_path, rig, session, signum, code):
    out = _copy(session, tmp_path / "sim")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    proc = _slow_simulate(rig, out)
    _wait_for_bag_in_temporary(proc, out)
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=TIMEOUT_S)
    assert proc.returncode == code, err
    line = _one_line(err)
    assert line.startswith("clcgraph simulate: interrupted") and signal.Signals(signum).name in line, line
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # the previous output, untouched
    assert _temporaries(out) == [] and sorted(p.name for p in tmp_path.iterdir()) == ["sim"]


def test_concurrent_runs_one_wins_whole_the_others_fail_in_one_line(tmp_path, rig):
    out = tmp_path / "sim"
    procs = [_start("-q", "simulate", rig, "--out", out, "--poses", "2", "--seed", str(k)) for k in range(3)]
    results = [(p.wait(timeout=TIMEOUT_S), p.communicate()[1]) for p in procs]
    assert any(rc == 0 for rc, _ in results), results
    for rc, err in results:
        assert rc in (0, 2), (rc, err)
        if rc == 2:
            assert "another clcgraph run" in _one_line(err) and str(out) in err, err
    truth = yaml.safe_load((out / "truth.yaml").read_text())  # whole: the bags its truth names
    assert sorted(p.name for p in out.glob("*.bag")) == sorted(s["bag"] for s in truth["snapshots"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sim"]


def test_concurrent_writers_in_threads(tmp_path):
    """16 writers at once (the API from threads): the winners' outputs are whole, one after the
    other; the rest are InputErrors saying another run is writing; no FileNotFoundError."""
    out = tmp_path / "out"
    start = threading.Barrier(16)
    outcome: dict[int, object] = {}

    def writer(k):
        start.wait()
        try:
            with atomic_dir(out) as t:
                for name in ("calibration.yaml", "report.html", "problem.npz"):
                    (t / name).write_text(f"writer {k}")
                    time.sleep(0.01)
            outcome[k] = "ok"
        except Exception as e:  # noqa: BLE001 - collected and checked below
            outcome[k] = e

    threads = [threading.Thread(target=writer, args=(k,)) for k in range(16)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=TIMEOUT_S)
    won = [k for k, v in outcome.items() if v == "ok"]
    lost = [v for v in outcome.values() if v != "ok"]
    assert len(outcome) == 16 and won, outcome
    assert all(isinstance(e, InputError) and "another clcgraph run" in str(e) for e in lost), lost
    texts = {(out / n).read_text() for n in ("calibration.yaml", "report.html", "problem.npz")}
    assert len(texts) == 1 and texts.pop() in {f"writer {k}" for k in won}  # one writer's files, all of them
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_symlinked_out_writes_into_its_target_and_keeps_the_link(tmp_path, rig, session):
    target = _copy(session, tmp_path / "runs" / "sim-1")
    link = tmp_path / "latest"
    link.symlink_to(target, target_is_directory=True)
    assert main(["-q", "simulate", str(rig), "--out", str(link), "--poses", "1", "--seed", "5"]) == 0
    assert link.is_symlink() and link.resolve() == target.resolve()
    truth = yaml.safe_load((target / "truth.yaml").read_text())
    assert truth["seed"] == 5 and sorted(p.name for p in target.glob("*.bag")) == ["pose000.bag"]
    assert sorted(p.name for p in (tmp_path / "runs").iterdir()) == ["sim-1"]
    # a link to something clcgraph did not write: refused like the directory itself
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    (tmp_path / "to-mine").symlink_to(mine, target_is_directory=True)
    rc = main(["-q", "simulate", str(rig), "--out", str(tmp_path / "to-mine"), "--poses", "1"])
    assert rc == 2 and (mine / "notes.txt").read_text() == "keep" and (tmp_path / "to-mine").is_symlink()


def _write_capture(directory: Path) -> dict[str, bytes]:
    """A folder of recorded bags (and a note) the way a user keeps them."""
    from clcgraph.sim.bag_writer import BagWriter
    from clcgraph.types import LidarScan

    directory.mkdir()
    rng = np.random.default_rng(0)
    for k in range(2):
        pts = rng.uniform(-10, 10, (500, 3))
        with BagWriter(directory / f"rec{k}.bag", format="ros1") as w:
            for t in ("/lidar0", "/lidar1"):
                w.write_pointcloud(t, LidarScan(t, 10**18 + k, pts, np.ones(500, bool), ring=np.zeros(500, int),
                                                time_s=np.zeros(500)), frame_id=t[1:], layout="velodyne")
    (directory / "notes.txt").write_text("rig 7, board at 3 m")
    return {p.name: p.read_bytes() for p in directory.iterdir()}


def test_out_holding_the_recording_is_refused_and_survives(tmp_path, rig, capsys):
    capture = tmp_path / "capture"
    before = _write_capture(capture)
    # the real entry point, as in the issue: `clcgraph solve --bag 'capture/*.bag' --out capture/`
    r = _run("solve", "--bag", f"{capture}/*.bag", "--topics", "/lidar0,/lidar1", "--out", f"{capture}/")
    assert r.returncode == 2, r.stderr
    line = _one_line(r.stderr)
    assert str(capture) in line and "not a clcgraph output" in line and "--force" in line, line
    # every other command with --out, in-process (each refuses before doing its work)
    for argv in (["simulate", str(rig), "--out", str(capture), "--poses", "1"],
                 ["simulate-drive", "--out", str(capture), "--duration", "1", "--small"],
                 ["targetless", "--bag", str(capture / "rec0.bag"), "--mapping-topic", "/lidar0",
                  "--calibration-topics", "/lidar1", "--out", str(capture)],
                 ["demo", "--out", str(capture)]):
        capsys.readouterr()
        assert main(["-q", *argv]) == 2, argv
        assert str(capture) in _one_line(capsys.readouterr().err), argv
    assert {p.name: p.read_bytes() for p in capture.iterdir()} == before
    assert [p.name for p in tmp_path.iterdir()] == ["capture"]


def test_force_replaces_a_foreign_out(tmp_path, rig):
    out = tmp_path / "old"
    out.mkdir()
    (out / "junk.txt").write_text("x")
    assert main(["-q", "simulate", str(rig), "--out", str(out), "--poses", "1", "--force"]) == 0
    assert not (out / "junk.txt").exists() and (out / "truth.yaml").is_file() and marker_kind(out) == "session"
