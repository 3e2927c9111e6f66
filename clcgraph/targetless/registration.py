"""Registration of calibration-LIDAR scans to dense mapping clouds: ensemble, scoring, per-frame refinement.

SYNOPSIS
    prob = prepare_frames(chosen, map_result, T_lidar0_sensor_guess, opts)  # dense targets + deskewed sources
    T_best, cands = ensemble(prob, T_guess, opts)     # best candidate on ALL frames (the guess stays one)
    meas = refine_per_frame(prob, T_best, opts)       # per-frame T_k (4,4) and Hessian H_k (6,6)

All clouds of one frame are expressed in the mapping LIDAR frame at the calibration
scan's stamp (the interpolated pose), so every registration directly estimates
T_lidar0_sensor.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .deskew import deskew
from .mapping import register, voxel_down

log = logging.getLogger(__name__)


@dataclass
class FrameData:
    cf: object  # CalibrationFrame
    target_pts: np.ndarray  # (M,3) dense, lidar0 frame at the scan stamp
    source_pts: np.ndarray  # (N,3) deskewed sensor points
    target: object = None  # small_gicp.PointCloud
    tree: object = None
    kdtree: object = None  # scipy cKDTree for scoring


def dense_target(mp, kid: int, T_map_lidar0: np.ndarray, o, *, max_frames: int = 40) -> np.ndarray:
    """(M,3) mapping points of the frames within +-dense_pointcloud_num_keyframes keyframes, in lidar0 at T."""
    kpos = mp.keyframe_ids.index(kid)
    lo = mp.keyframe_ids[max(0, kpos - o.dense_pointcloud_num_keyframes)]
    hi = mp.keyframe_ids[min(len(mp.keyframe_ids) - 1, kpos + o.dense_pointcloud_num_keyframes)]
    ids = np.arange(lo, hi + 1)
    if len(ids) > max_frames:
        ids = np.unique(np.r_[np.linspace(lo, hi, max_frames).round().astype(int), kid])
    Tinv = np.linalg.inv(T_map_lidar0)
    clouds = []
    for j in ids:
        f = mp.frames[j]
        T = Tinv @ f.T_map_lidar
        clouds.append(f.points @ T[:3, :3].T + T[:3, 3])
    pts = voxel_down(np.concatenate(clouds), max(o.leaf_size_dense_map, 0.02))
    r = np.linalg.norm(pts, axis=1)
    return pts[(r >= o.min_calibration_range) & (r <= o.max_calibration_range)]


def _adjoint_to_sensor(T_lidar0_sensor: np.ndarray, xi: np.ndarray) -> np.ndarray:
    import gtsam

    return gtsam.Pose3(np.linalg.inv(T_lidar0_sensor)).AdjointMap() @ xi


def prepare_frames(chosen, mp, T_guess: np.ndarray, o, *, deskew_on: bool = True, progress=None) -> list:
    """Dense targets and deskewed, cropped sources for the selected calibration frames."""
    import small_gicp
    from scipy.spatial import cKDTree

    out = []
    for cf in chosen:
        s = cf.scan
        r = np.linalg.norm(s.points, axis=1)
        m = s.valid & np.isfinite(r) & (r >= o.min_calibration_range) & (r <= o.max_calibration_range)
        xi_s = _adjoint_to_sensor(T_guess, cf.twist_lidar0)
        src = deskew(s.points[m], s.time_s[m] if (deskew_on and s.time_s is not None) else None, xi_s)
        tgt = dense_target(mp, cf.keyframe_id, cf.T_map_lidar0, o)
        if o.crop_z_calibration_pointclouds:
            zmax = (src @ T_guess[:3, :3].T + T_guess[:3, 3])[:, 2].max() + o.crop_z_calibration_pointclouds_value
            tgt = tgt[tgt[:, 2] <= zmax]
        t, tree = small_gicp.preprocess_points(np.ascontiguousarray(tgt), max(o.leaf_size_dense_map, 0.02),
                                               num_neighbors=10, num_threads=o.mapper_num_threads)
        tpts = np.asarray(t.points())[:, :3]
        out.append(FrameData(cf, tpts, src, t, tree, cKDTree(tpts)))
        if progress is not None:
            progress(1)
    return out


def score(frames, T: np.ndarray, o, *, sub: int = 4) -> float:
    """Mean truncated squared source-to-target distance over all frames (lower is better)."""
    c2 = o.calibration_eval_max_corr_distance ** 2
    tot, n = 0.0, 0
    for fd in frames:
        p = fd.source_pts[::sub] @ T[:3, :3].T + T[:3, 3]
        d, _ = fd.kdtree.query(p, distance_upper_bound=o.calibration_eval_max_corr_distance)
        d2 = np.minimum(np.where(np.isfinite(d), d * d, c2), c2)
        tot += d2.sum()
        n += len(d2)
    return tot / max(n, 1)


def _run(fd, T0, kind, corr, o, leaf):
    if kind == "VGICP":  # needs a voxel map: the raw-array overload builds it
        import small_gicp

        return small_gicp.align(fd.target_pts, fd.source_pts, T0, registration_type="VGICP", voxel_resolution=corr,
                                downsampling_resolution=leaf, max_correspondence_distance=corr,
                                num_threads=o.mapper_num_threads, max_iterations=min(o.solver_iterations, 60)).T_target_source
    r = register(fd.target, fd.tree, fd.source_pts, T0, kind=kind, max_corr=corr, iters=min(o.solver_iterations, 60),
                 threads=o.mapper_num_threads, leaf=leaf)
    return r.T_target_source


def ensemble(frames, T_guess: np.ndarray, o, *, progress=None):
    """Best T_lidar0_sensor among the guess and per-frame registrations (ICP coarse-to-fine, GICP, VGICP).

    Each registration starts from the best candidate so far; every candidate is scored
    on all frames. Returns (T_best (4,4), list of (name, frame index, score)).
    """
    best, best_s = T_guess, score(frames, T_guess, o)
    cands = [("initial guess", -1, best_s)]
    leaf = 0.1
    for i, fd in enumerate(frames):
        for name in ("ICP coarse-to-fine", "GICP", "VGICP"):
            if name == "ICP coarse-to-fine":
                T = _run(fd, best, "ICP", o.max_corr_dist_coarse, o, leaf)
                T = _run(fd, T, "ICP", o.max_corr_dist_fine, o, leaf)
                T = _run(fd, T, "ICP", o.max_corr_dist_ultra_fine, o, leaf)
            elif name == "GICP":
                T = _run(fd, best, "GICP", o.max_corr_dist_coarse, o, leaf)
                T = _run(fd, T, "GICP", o.max_corr_dist_fine, o, leaf)
            else:
                T = _run(fd, best, "VGICP", o.max_corr_dist_coarse, o, leaf)
            s = score(frames, T, o)
            cands.append((name, i, s))
            if s < best_s:
                best, best_s = T, s
        if progress is not None:
            progress(1)
    return best, cands


@dataclass
class FrameMeasurement:
    T: np.ndarray  # (4,4) T_lidar0_sensor from this frame alone
    H: np.ndarray  # (6,6) GICP Hessian, tangent [omega, v] right perturbation
    n_inliers: int
    error: float


def refine_per_frame(frames, T0: np.ndarray, o) -> list:
    """Fine GICP of each frame from T0; returns FrameMeasurement per frame."""
    out = []
    for fd in frames:
        r = register(fd.target, fd.tree, fd.source_pts, T0, kind="GICP", max_corr=o.max_corr_dist_fine,
                     iters=min(o.solver_iterations, 60), threads=o.mapper_num_threads, leaf=0.05)
        r = register(fd.target, fd.tree, fd.source_pts, r.T_target_source, kind="GICP",
                     max_corr=o.max_corr_dist_ultra_fine, iters=min(o.solver_iterations, 60),
                     threads=o.mapper_num_threads, leaf=0.05)
        out.append(FrameMeasurement(np.asarray(r.T_target_source), np.asarray(r.H), int(r.num_inliers), float(r.error)))
    return out
