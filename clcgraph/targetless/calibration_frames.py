"""Calibration frames: a calibration-LIDAR scan per keyframe with the mapping pose at its stamp.

SYNOPSIS
    kept = nearest_to_keyframes(map_result, scan_stream)   # only the scans that can be chosen
    cfs = make_calibration_frames(map_result, kept, opts)
    cfs[0].T_map_lidar0          # (4,4) mapping pose interpolated (SLERP + linear) to the scan stamp
    cfs[0].stats                 # interpolation statistics; cfs[0].accepted, cfs[0].reason
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .deskew import twist_between


@dataclass
class CalibrationFrame:
    keyframe_id: int  # index into MapResult.frames
    scan: object  # LidarScan of the calibration LIDAR
    T_map_lidar0: np.ndarray  # (4,4) at scan.stamp_ns
    twist_lidar0: np.ndarray  # (6,) mapping twist used to deskew the calibration scan
    stats: dict = field(default_factory=dict)
    accepted: bool = True
    reason: str = ""
    score: float = 0.0  # PCA information (smallest eigenvalue)


def interpolate_pose(Ta: np.ndarray, Tb: np.ndarray, s: float) -> np.ndarray:
    """(4,4) pose at fraction s in [0,1] between Ta and Tb: SLERP rotation, linear translation."""
    from scipy.spatial.transform import Rotation, Slerp

    sl = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([Ta[:3, :3], Tb[:3, :3]])))
    T = np.eye(4)
    T[:3, :3] = sl([s]).as_matrix()[0]
    T[:3, 3] = (1 - s) * Ta[:3, 3] + s * Tb[:3, 3]
    return T


def nearest_to_keyframes(mp, scans) -> list:
    """The scans (a time-ordered iterable, read once) that are the nearest in time to some keyframe:
    all that make_calibration_frames uses, without holding a whole drive in memory."""
    kt = mp.stamps_ns()[mp.keyframe_ids]
    best: dict = {}  # keyframe -> (|dt| ns, scan); the earliest wins ties, as argmin does
    for s in scans:
        j = int(np.searchsorted(kt, s.stamp_ns))
        for k in (j - 1, j):
            if 0 <= k < len(kt) and (k not in best or abs(s.stamp_ns - kt[k]) < best[k][0]):
                best[k] = (abs(s.stamp_ns - kt[k]), s)
    kept = {id(s): s for _, s in best.values()}
    return sorted(kept.values(), key=lambda s: s.stamp_ns)


def make_calibration_frames(mp, calib_scans, o, *, skip_keyframes: int | None = None) -> list:
    """One CalibrationFrame per keyframe after the first ``skip_keyframes`` (default: the
    configured ``calibration_skip_keyframes``), with statistics."""
    stamps = mp.stamps_ns()
    cs = np.array([s.stamp_ns for s in calib_scans], dtype=np.int64)
    skip = o.calibration_skip_keyframes if skip_keyframes is None else skip_keyframes
    out = []
    for kid in mp.keyframe_ids[skip:]:
        kt = stamps[kid]
        j = int(np.argmin(np.abs(cs - kt)))
        t = cs[j]
        i = int(np.searchsorted(stamps, t)) - 1
        if i < 0 or i + 1 >= len(stamps):
            continue
        fa, fb = mp.frames[i], mp.frames[i + 1]
        dt = (stamps[i + 1] - stamps[i]) * 1e-9
        s = (t - stamps[i]) * 1e-9 / dt
        T = interpolate_pose(fa.T_map_lidar, fb.T_map_lidar, s)
        nearest = fa if s < 0.5 else fb
        d_rel = np.linalg.inv(nearest.T_map_lidar) @ T
        xi = twist_between(fa.T_map_lidar, fb.T_map_lidar, dt)
        prev = mp.frames[i - 1] if i > 0 else fa
        dtp = max((fa.stamp_ns - prev.stamp_ns) * 1e-9, 1e-3)
        v_prev = np.linalg.norm(fa.T_map_lidar[:3, 3] - prev.T_map_lidar[:3, 3]) / dtp if i > 0 else np.linalg.norm(xi[3:])
        stats = {
            "time_s": abs(t - nearest.stamp_ns) * 1e-9,
            "distance_m": float(np.linalg.norm(d_rel[:3, 3])),
            "angle_deg": float(np.degrees(np.arccos(np.clip((np.trace(d_rel[:3, :3]) - 1) / 2, -1, 1)))),
            "speed_mps": float(np.linalg.norm(xi[3:])),
            "accel_mps2": float(abs(np.linalg.norm(xi[3:]) - v_prev) / dtp),
        }
        std = (stats["time_s"] <= o.max_allowed_interpolated_time
               and stats["distance_m"] <= o.max_allowed_interpolated_distance
               and stats["angle_deg"] <= o.max_allowed_interpolated_angle
               and stats["speed_mps"] <= o.max_allowed_interpolated_speed
               and stats["accel_mps2"] <= o.max_allowed_interpolated_accel)
        straight = (stats["time_s"] <= o.max_allowed_interpolated_time
                    and stats["distance_m"] <= o.max_allowed_interpolated_distance_straight
                    and stats["angle_deg"] <= o.max_allowed_interpolated_angle_straight
                    and stats["speed_mps"] <= o.max_allowed_interpolated_speed_straight
                    and stats["accel_mps2"] <= o.max_allowed_interpolated_accel_straight)
        cf = CalibrationFrame(kid, calib_scans[j], T, xi, stats)
        if not (std or straight):
            cf.accepted = False
            cf.reason = "interpolation: " + ", ".join(f"{k}={v:.3g}" for k, v in stats.items())
        out.append(cf)
    return out
