"""Selection of calibration frames: lost-frame proximity, PCA information, greedy spacing + budget.

SYNOPSIS
    plan = adapt_to_drive(map_result, opts)          # skipped keyframes and spacing for this drive
    chosen = select_frames(cfs, map_result, opts, spacing_m=plan.spacing_m)   # accepted CalibrationFrames

The seed's settings (skip the first 5 keyframes, 5 m between calibration frames) leave a
short drive with one frame or none; ``adapt_to_drive`` scales both to the drive.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)


def pca_information(points: np.ndarray) -> float:
    """Smallest eigenvalue of the (3,3) covariance of (N,3) points (higher = more 3-D structure)."""
    if len(points) < 4:
        return 0.0
    return float(np.linalg.eigvalsh(np.cov(points.T))[0])


@dataclass(frozen=True)
class FramePlan:
    """How calibration frames are taken from this drive (written to calibration.yaml)."""

    skip_keyframes: int  # first keyframes left out (configured: calibration_skip_keyframes)
    spacing_m: float  # least distance between chosen frames (configured: ..._min_distance_between_frames)
    drive_length_m: float  # path length over the keyframes after the skipped ones
    keyframes: int

    def as_dict(self) -> dict:
        return {"skip_keyframes": self.skip_keyframes, "spacing_m": self.spacing_m,
                "drive_length_m": self.drive_length_m, "keyframes": self.keyframes}


def adapt_to_drive(mp, o) -> FramePlan:
    """Skipped keyframes and frame spacing for this drive's map.

    Skip at most as many keyframes as the drive has beyond ``lidar_calibration_max_frames``
    (skipping never costs a frame the budget could use); space the frames at
    min(``calibration_min_distance_between_frames``, length / max frames), but never closer
    than ``new_keyframe_min_distance``: frames nearer than keyframes share their map data.
    """
    kf = list(mp.keyframe_ids)
    skip = int(min(o.calibration_skip_keyframes, max(0, len(kf) - o.lidar_calibration_max_frames)))
    P = np.array([mp.frames[k].T_map_lidar[:3, 3] for k in kf[skip:]]).reshape(-1, 3)
    length = float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum()) if len(P) > 1 else 0.0
    spacing = min(o.calibration_min_distance_between_frames,
                  max(o.new_keyframe_min_distance, length / max(1, o.lidar_calibration_max_frames)))
    plan = FramePlan(skip, float(spacing), length, len(kf))
    log.info("a %.1f m drive (%d keyframes): %d keyframes skipped, calibration frames %.2f m apart "
             "(configured: skip %d, %.2f m)", length, len(kf), skip, spacing, o.calibration_skip_keyframes,
             o.calibration_min_distance_between_frames)
    return plan


def select_frames(cfs, mp, o, *, spacing_m: float | None = None) -> list:
    """Greedy selection by PCA score, frames at least ``spacing_m`` apart (default: the configured
    ``calibration_min_distance_between_frames``)."""
    spacing = o.calibration_min_distance_between_frames if spacing_m is None else spacing_m
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
        if any(np.linalg.norm(p - c.T_map_lidar0[:3, 3]) < spacing for c in chosen):
            cf.reason = "too close to a selected frame"
            continue
        chosen.append(cf)
        if len(chosen) >= o.lidar_calibration_max_frames:
            break
    return sorted(chosen, key=lambda c: c.keyframe_id)
