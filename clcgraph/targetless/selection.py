"""Selection of calibration frames: lost-frame proximity, PCA information, greedy spacing + budget.

SYNOPSIS
    chosen = select_frames(cfs, map_result, opts)   # subset of accepted CalibrationFrames
"""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)


def pca_information(points: np.ndarray) -> float:
    """Smallest eigenvalue of the (3,3) covariance of (N,3) points (higher = more 3-D structure)."""
    if len(points) < 4:
        return 0.0
    return float(np.linalg.eigvalsh(np.cov(points.T))[0])


def select_frames(cfs, mp, o) -> list:
    """Greedy selection by PCA score with ``calibration_min_distance_between_frames`` spacing."""
    lost = [k for k, f in enumerate(mp.frames) if f.lost]
    kpos = {k: i for i, k in enumerate(mp.keyframe_ids)}
    for cf in cfs:
        if not cf.accepted:
            continue
        ki = kpos[cf.keyframe_id]
        lo = mp.keyframe_ids[max(0, ki - o.dense_pointcloud_num_keyframes)]
        hi = mp.keyframe_ids[min(len(mp.keyframe_ids) - 1, ki + o.dense_pointcloud_num_keyframes)]
        if any(lo <= k <= hi for k in lost):
            cf.accepted, cf.reason = False, "near a lost frame"
            continue
        if o.calibration_use_only_stopped and not mp.frames[cf.keyframe_id].stopped:
            cf.accepted, cf.reason = False, "not a stopped frame"
            continue
        s = cf.scan
        r = np.linalg.norm(s.points, axis=1)
        m = s.valid & (r >= o.min_calibration_range) & (r <= o.max_calibration_range)
        if m.sum() < o.min_calibration_pointcloud_size:
            cf.accepted, cf.reason = False, f"{m.sum()} points < min_calibration_pointcloud_size"
            continue
        cf.score = pca_information(s.points[m])
        if cf.score < o.calibration_min_pca_eigenvalue:
            cf.accepted, cf.reason = False, f"PCA eigenvalue {cf.score:.3g} < calibration_min_pca_eigenvalue"
    cand = [cf for cf in cfs if cf.accepted]
    if o.calibration_use_only_last_frames:  # the end of the drive only (e.g. a dedicated calibration loop)
        cand = sorted(cand, key=lambda c: c.keyframe_id)[-2 * o.lidar_calibration_max_frames:]
    cand = sorted(cand, key=lambda c: -c.score)
    chosen = []
    for cf in cand:
        p = cf.T_map_lidar0[:3, 3]
        if any(np.linalg.norm(p - c.T_map_lidar0[:3, 3]) < o.calibration_min_distance_between_frames for c in chosen):
            cf.reason = "too close to a selected frame"
            continue
        chosen.append(cf)
        if len(chosen) >= o.lidar_calibration_max_frames:
            break
    return sorted(chosen, key=lambda c: c.keyframe_id)
