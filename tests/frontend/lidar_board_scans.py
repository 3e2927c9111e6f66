"""Simulated LIDAR scans of the board in random poses, for the segmentation tests."""

import numpy as np

from clcgraph.sim.lidar import simulate_scan
from clcgraph.sim.scene import make_scene, random_board_pose, static_meshes
from clcgraph.types import BoardGeometry

BOARD = BoardGeometry.from_spec(corners=[10, 10], square_m=0.1, size_m=[1.3, 1.3])


def board_scans(model, n: int, *, tilt_max_deg: float, distance_m: tuple, hits: bool = False) -> tuple:
    """([LidarScan] of ``model`` 1.9 m above the ground, [T_lidar_board (4,4)]): board pose k from seed k;
    ``hits``: also the simulator's per-return hit labels, a third list."""
    T = np.eye(4)
    T[2, 3] = 1.9
    static = static_meshes(np.random.default_rng(0))
    scans, boards, labels = [], [], []
    for k in range(n):
        rng = np.random.default_rng(k)
        Tb = random_board_pose(rng, BOARD, T[:3, 3], tilt_max_deg=tilt_max_deg, distance_m=distance_m)
        scan, hit = simulate_scan(model, T, make_scene(BOARD, Tb, rng, static=static), rng, stamp_ns=k, topic="/l")
        scans.append(scan)
        labels.append(hit)
        boards.append(np.linalg.inv(T) @ Tb)
    return (scans, boards, labels) if hits else (scans, boards)
