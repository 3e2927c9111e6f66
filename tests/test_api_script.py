"""The Python API from a plain script (no ``if __name__ == "__main__"`` guard, even piped on
stdin): the parallel stages must not re-run or re-import the caller's script."""

import subprocess
import sys

SCRIPT = """
import numpy as np
import clcgraph
from clcgraph.sim.lidar import LidarModel, simulate_scan
from clcgraph.sim.scene import make_scene, random_board_pose, static_meshes
from clcgraph.types import BoardGeometry, LidarBoardObservation

print("script body ran", flush=True)
rng = np.random.default_rng(1)
T = np.eye(4)
T[2, 3] = 1.8
static = static_meshes(rng)
scans = [simulate_scan(LidarModel.preset("vlp16"), T,
                       make_scene(BoardGeometry(), random_board_pose(rng, BoardGeometry(), T[:3, 3]), rng,
                                  static=static), rng)[0] for _ in range(6)]
found = sum(isinstance(r, LidarBoardObservation) for r in clcgraph.segment(scans))
print("found", found)
"""


def test_api_from_a_piped_script_without_main_guard():
    out = subprocess.run([sys.executable, "-"], input=SCRIPT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.count("script body ran") == 1, out.stdout
    assert int(out.stdout.split("found")[1]) >= 4, out.stdout
