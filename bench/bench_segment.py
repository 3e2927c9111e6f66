"""LIDAR board segmentation time per scan on one core: VLP-16 (16 x 1800), HDL-32 (32 x 1800)
and OS1-128 (128 x 2048), on simulated scans of a cluttered site with a board at 2-12 m.
Targets (issue 4): 30, 50 and 250 ms, static-scene suppression (per scan of a session) included.
"found" counts boards found, whether or not 3 rings crossed them. Times are CPU time
(time.process_time: the machine may be shared) per scan, after one scan segmented untimed (the
imports of the first call are not a scan's cost); "ratio" is total / target."""

from __future__ import annotations

import time

import numpy as np

TARGET_MS = {"vlp16": 30, "hdl32": 50, "os1-128": 250}
N_SCANS = 12


def main() -> str:
    from clcgraph.config import LidarOptions, SegmentationOptions
    from clcgraph.frontend.lidar_board import segment_board
    from clcgraph.frontend.lidar_preprocess import static_masks
    from clcgraph.sim.lidar import LidarModel, simulate_scan
    from clcgraph.sim.scene import make_scene, random_board_pose, static_meshes
    from clcgraph.types import BoardGeometry, LidarBoardObservation

    board = BoardGeometry()
    T = np.eye(4)
    T[2, 3] = 1.8
    rows = [f"{'LIDAR':10s} {'points':>8s} {'segment ms':>10s} {'static ms':>10s} {'total ms':>9s} {'target':>7s} "
            f"{'ratio':>6s} {'found':>6s}"]
    for model, target in TARGET_MS.items():
        rng = np.random.default_rng(0)
        L = LidarModel.preset(model)
        static = static_meshes(rng)
        scans = []
        for _ in range(N_SCANS):
            Tb = random_board_pose(rng, board, T[:3, 3], distance_m=(2, 12))
            scans.append(simulate_scan(L, T, make_scene(board, Tb, rng, static=static), rng)[0])
        t0 = time.process_time()
        masks = static_masks(scans, npoints_per_rotation=L.npoints_per_rotation, quantum_m=0.1)
        t_static = (time.process_time() - t0) / N_SCANS

        def segment(s, m):
            return segment_board(s, SegmentationOptions(), LidarOptions(), board, exclude=m,
                                 npoints_per_rotation=L.npoints_per_rotation)

        segment(scans[0], masks[0])  # warm-up
        t0 = time.process_time()
        found = sum(isinstance(segment(s, m), LidarBoardObservation) for s, m in zip(scans, masks))
        dt = (time.process_time() - t0) / N_SCANS
        total = (dt + t_static) * 1e3
        rows.append(f"{model:10s} {len(scans[0].points):8d} {dt * 1e3:10.0f} {t_static * 1e3:10.0f} "
                    f"{total:9.0f} {target:7d} {total / target:6.2f} {found:3d}/{N_SCANS}")
    return "\n".join(rows)
