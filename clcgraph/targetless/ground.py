"""base_link-LIDAR from the ground plane: roll, pitch and height; x, y, yaw from the initial guess.

SYNOPSIS
    gp = fit_ground(points_lidar0, opts)                 # GroundPlane (unit normal up, offset) or DegenerateError
    T_base_lidar = base_from_ground(normal, d, T_base_lidar_guess)

RANSAC (clcgraph.planes, seeded) on the dense cloud around keyframes in the crop box; a plane is rejected
and its inliers removed when it has too few points / too small a share, or its normal is
further than ``base_lidar_max_cos_distance`` from the guess's up direction; repeat.
The body rolls/pitches on its suspension, so the normals of many keyframes are averaged
in the map frame and brought back with the mean attitude.
"""

from __future__ import annotations

import logging

import numpy as np

from ..errors import DegenerateError
from ..geometry import R_from_r
from ..planes import fit_plane, ransac_plane

log = logging.getLogger(__name__)


def fit_ground(points: np.ndarray, up_guess: np.ndarray, o, *, seed: int = 0):
    """(n (3,), d, inliers) of the ground plane n.p + d = 0 in the points' frame, n along up_guess."""
    lo = np.array([o.base_lidar_crop_box_min_x, o.base_lidar_crop_box_min_y, o.base_lidar_crop_box_min_z])
    hi = np.array([o.base_lidar_crop_box_max_x, o.base_lidar_crop_box_max_y, o.base_lidar_crop_box_max_z])
    p = points[np.all((points >= lo) & (points <= hi), axis=1)]
    n_all = len(p)
    up = np.asarray(up_guess, float) / np.linalg.norm(up_guess)
    while len(p) >= o.base_lidar_min_plane_points:
        inl = ransac_plane(p, o.base_lidar_max_inlier_distance, iterations=o.base_lidar_max_iterations, seed=seed)
        if not inl.any():
            break
        n, _, _ = fit_plane(p[inl])
        if n @ up < 0:
            n = -n
        count = int(inl.sum())
        ok_count = count >= o.base_lidar_min_plane_points and 100.0 * count / n_all >= o.base_lidar_min_plane_points_percentage
        if ok_count and (1.0 - n @ up) <= o.base_lidar_max_cos_distance:
            return n, float(-n @ p[inl].mean(axis=0)), count
        if not ok_count:
            break
        p = p[~inl]  # a wall or a car: remove it and look again
    raise DegenerateError("no ground plane found in the base-lidar crop box (too few inliers or normals too far from up)")


def base_from_ground(n: np.ndarray, d: float, T_base_lidar_guess: np.ndarray, *, overwrite_xy_yaw: bool = False) -> np.ndarray:
    """(4,4) T_base_lidar whose z axis is the ground normal and height d; x, y, yaw from the guess,
    or (``overwrite_xy_yaw``) zero: base_link right below the LIDAR, heading along it."""
    R0 = T_base_lidar_guess[:3, :3]
    a = R0 @ n  # ground normal in the guessed base frame
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(a, z)
    s, c = np.linalg.norm(v), a @ z
    # the minimal rotation a -> z (about a x z): keeps the heading
    Rfix = np.eye(3) if s < 1e-12 else R_from_r(v / s * np.arctan2(s, c))
    T = np.eye(4)
    T[:3, :3] = Rfix @ R0
    T[:3, 3] = [T_base_lidar_guess[0, 3], T_base_lidar_guess[1, 3], d]
    if overwrite_xy_yaw:
        # base_link right below the LIDAR, its x axis the LIDAR's x projected onto the ground
        x = T[:3, :3] @ np.array([1.0, 0.0, 0.0])
        yaw = np.arctan2(x[1], x[0])
        c, s_ = np.cos(-yaw), np.sin(-yaw)
        T[:3, :3] = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]]) @ T[:3, :3]
        T[:2, 3] = 0.0
    return T


def calibrate_base(mp, T_base_lidar_guess: np.ndarray, o, *, max_keyframes: int = 20):
    """T_base_lidar0 from ground planes around keyframes (mean normal over the attitude of the keyframes).

    The ground is fitted in the map frame on dense clouds around keyframes; each fit's
    normal and height are brought into the LIDAR frame of every frame nearby, and the
    frame-wise values averaged so the suspension roll/pitch averages out.
    """
    up0 = np.linalg.inv(T_base_lidar_guess)[:3, :3] @ np.array([0, 0, 1.0])
    kids = mp.keyframe_ids
    pick = kids if len(kids) <= max_keyframes else [kids[i] for i in np.linspace(0, len(kids) - 1, max_keyframes).round().astype(int)]
    normals, ds = [], []
    for kid in pick:
        Tk = mp.frames[kid].T_map_lidar
        near = [j for j in range(max(0, kid - 10), min(len(mp.frames), kid + 11))]
        cloud = np.concatenate([mp.frames[j].points @ (np.linalg.inv(Tk) @ mp.frames[j].T_map_lidar)[:3, :3].T
                                + (np.linalg.inv(Tk) @ mp.frames[j].T_map_lidar)[:3, 3] for j in near[::2]])
        from .mapping import voxel_down

        cloud = voxel_down(cloud, max(o.leaf_size_dense_map, 0.05))
        try:
            n, d, _ = fit_ground(cloud, up0, o)
        except DegenerateError:
            continue
        # the plane in map coordinates, then seen from every frame near the keyframe
        nm = Tk[:3, :3] @ n
        dm = d - nm @ Tk[:3, 3]
        for j in near:
            Tj = mp.frames[j].T_map_lidar
            normals.append(Tj[:3, :3].T @ nm)
            ds.append(dm + nm @ Tj[:3, 3])
    if not normals:
        raise DegenerateError(f"{mp.topic}: no ground plane found around any keyframe")
    n = np.mean(normals, axis=0)
    n /= np.linalg.norm(n)
    d = float(np.mean(ds))
    T = base_from_ground(n, d, T_base_lidar_guess, overwrite_xy_yaw=o.base_lidar_overwrite_xy_yaw)
    return T, {"n_planes": len(pick), "n_frames": len(normals)}
