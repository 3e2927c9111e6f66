"""Organised Velodyne clouds mark missing returns as NaN: the CLI's stderr stays clean (no numpy
RuntimeWarning from casting NaN), checked in a subprocess, where warnings really reach stderr."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from clcgraph.sim.bag_writer import BagWriter
from clcgraph.types import LidarScan

ROOT = Path(__file__).resolve().parents[2]
T0 = 1_700_000_000_000_000_000


def _scan(rng, stamp_ns, topic):
    """16 x 360 returns on a sphere of 3-15 m, a fifth of them missing (NaN when written)."""
    elev = np.linspace(-0.25, 0.25, 16)[:, None]
    az = np.linspace(-np.pi, np.pi, 360, endpoint=False)[None, :]
    r = rng.uniform(3, 15, (16, 360))
    pts = np.stack([r * np.cos(elev) * np.cos(az), r * np.cos(elev) * np.sin(az),
                    r * np.sin(elev) * np.ones_like(az)], -1).reshape(-1, 3)
    return LidarScan(topic, stamp_ns, pts, rng.uniform(size=len(pts)) > 0.2, ring=np.repeat(np.arange(16), 360),
                     time_s=np.tile(np.linspace(0, 0.099, 360), 16), shape=(16, 360))


def _nan_bags(d: Path, n=5):
    rng = np.random.default_rng(1)
    for i in range(n):  # >= 4 scans: static-scene suppression runs over them
        with BagWriter(d / f"pose{i}.bag") as w:
            for t in ("/lidar0", "/lidar1"):
                w.write_pointcloud(t, _scan(rng, T0 + i * 10**10, t), frame_id=t.strip("/"), layout="velodyne",
                                   organised=True)


def _cli(*args):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "clcgraph.cli", *args], capture_output=True, text=True, env=env,
                          timeout=300)


def test_nan_points_leave_stderr_clean(tmp_path):
    _nan_bags(tmp_path)
    bags = sorted(str(p) for p in tmp_path.glob("*.bag"))
    r = _cli("segment", *bags, "--topic", "/lidar0")
    assert r.returncode == 0 and r.stderr == "", r.stderr
    assert "0/5 scans with a board" in r.stdout  # random spheres: no board, every scan decoded
    r = _cli("solve", "--bag", str(tmp_path / "*.bag"), "--topics", "/lidar0,/lidar1", "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr  # only the one-line verdict
    assert "Warning" not in r.stderr
