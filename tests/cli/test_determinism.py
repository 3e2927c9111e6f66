"""The same inputs give the same bytes: `clcgraph solve` in fresh processes with different
PYTHONHASHSEED, BLAS/OpenMP thread counts and mrgingham ``detection.jobs`` writes a
byte-identical calibration.yaml and problem.npz (whose only difference may be the recorded
``detection.jobs`` setting itself)."""

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from clcgraph.cli import main
from clcgraph.sim.capture import DEMO_RIG

ROOT = Path(__file__).resolve().parents[2]
RIG = """
lidars:
  - {topic: /lidar/a, model: vlp16, layout: velodyne, frame_id: a, xyz: [0, 0, 1.9], rpy_deg: [0, 0, 0]}
  - {topic: /lidar/c, model: vlp16, layout: velodyne, frame_id: c, xyz: [-1.0, -0.4, 1.5], rpy_deg: [0, -3, 178]}
cameras:
  - {topic: /cam, model: front.cameramodel, encoding: mono8, frame_id: cam, xyz: [0.3, -0.2, 1.5], rpy_deg: [0, 4, -5]}
board: {corners: [10, 10], square_m: 0.1, size_m: [1.3, 1.3]}
"""


def _solve(tmp, out, *, threads: int, hashseed: str, jobs: int):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONHASHSEED": hashseed, "OMP_NUM_THREADS": str(threads),
           "OPENBLAS_NUM_THREADS": str(threads)}
    cmd = [sys.executable, "-c", "import sys; from clcgraph.cli import main; sys.exit(main())", "solve", "--bag", str(tmp / "bags" / "*.bag"),
           "--topics", "/lidar/a,/lidar/c,/cam", str(tmp / "front.cameramodel"), "--out", str(out),
           "--set", f"detection.jobs={jobs}"]
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr


def _npz_members(path):
    with zipfile.ZipFile(path) as z:
        return {n: z.read(n) for n in z.namelist()}


@pytest.mark.slow
def test_solve_is_byte_identical_across_processes_threads_and_hash_seeds(tmp_path):
    import shutil

    shutil.copy(DEMO_RIG.parent / "front.cameramodel", tmp_path / "front.cameramodel")
    (tmp_path / "rig.yaml").write_text(RIG)
    assert main(["simulate", str(tmp_path / "rig.yaml"), "--out", str(tmp_path / "bags"), "--poses", "8",
                 "--seed", "3"]) == 0
    a, b = tmp_path / "a", tmp_path / "b"
    _solve(tmp_path, a, threads=1, hashseed="0", jobs=1)
    _solve(tmp_path, b, threads=2, hashseed="4242", jobs=2)
    ya, yb = (a / "calibration.yaml").read_bytes(), (b / "calibration.yaml").read_bytes()
    assert ya == yb
    assert b"time_s" not in ya  # wall-clock timings live in timings.yaml, not in the result
    ma, mb = _npz_members(a / "problem.npz"), _npz_members(b / "problem.npz")
    assert ma.keys() == mb.keys()
    for name in ma:
        if name != "meta.npy":
            assert ma[name] == mb[name], name
    # the dump records the config it ran with: the jobs setting is its only difference
    meta_a = json.loads(str(np.load(a / "problem.npz")["meta"]))
    meta_b = json.loads(str(np.load(b / "problem.npz")["meta"]))
    assert meta_a["config"]["detection"].pop("jobs") == 1 and meta_b["config"]["detection"].pop("jobs") == 2
    assert meta_a == meta_b
