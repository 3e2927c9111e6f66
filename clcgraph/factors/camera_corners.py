"""Chessboard-corner reprojection factor through any mrcal lens model.

``err = q_observed - project(T_camera_board * corners)`` (2 per corner, pixels), with
``T_camera_board = T_lidar0_camera^-1 T_lidar0_board`` and the projection and its gradient
``dq/dp`` from mrcal (clcgraph.cameras), so every lens model (pinhole, OPENCVn,
SPLINED_STEREOGRAPHIC, ...) works. Corners given as NaN (not detected) contribute a zero
row. Points behind a camera are not special-cased: mrcal's projection decides; a seeded
solve never gets there.

SYNOPSIS
    f = camera_corners_factor(S(2), B(7), corners_px, lensmodel, intrinsics, board, sigma_px=0.3)
    r = camera_corners_residuals(T_lidar0_camera, T_lidar0_board, corners_px, lensmodel, intrinsics, board)  # (K,2)
"""

from __future__ import annotations

import functools

import numpy as np

from .. import cameras
from .base import board_perturbed, isotropic, make_factor


def _residual(T_cam, T_board, q_obs, ok, corners_b, lensmodel, intrinsics, want: bool):
    R_c, t_c = T_cam.rotation().matrix(), T_cam.translation()
    R_b, t_b = T_board.rotation().matrix(), T_board.translation()
    R_cb = R_c.T @ R_b
    p = corners_b @ R_cb.T + R_c.T @ (t_b - t_c)  # corners in the camera frame
    if want:
        q, dq_dp, _ = cameras.project(p, lensmodel, intrinsics, get_gradients=True)
    else:
        q = cameras.project(p, lensmodel, intrinsics)
    err = q_obs - q
    err[~ok] = 0.0
    err = err.reshape(-1)
    if not want:
        return err, None
    # d p / d xi_c = [[p]x, -I], d p / d xi_b = [-R_cb [c]x, R_cb]; with D = dq/dp (K,2,3),
    # err = -q: rows D_i [p]x = D_i x p, and D R_cb [c]x likewise on G = D R_cb
    K = len(p)
    G_b = dq_dp @ R_cb
    J_c, J_b = np.empty((K, 2, 6)), np.empty((K, 2, 6))
    _cross_into(J_c, p[:, None, :], dq_dp)  # -(D_i x p)
    J_c[:, :, 3:] = dq_dp
    _cross_into(J_b, G_b, corners_b[:, None, :])  # (G_i x c) = G_i [c]x
    J_b[:, :, 3:] = -G_b
    J_c[~ok], J_b[~ok] = 0.0, 0.0
    return err, [J_c.reshape(2 * K, 6), J_b.reshape(2 * K, 6)]


def _cross_into(out: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    """out[..., :3] = a x b over the last axis, broadcast (np.cross and np.stack cost more for these stacks)."""
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


@functools.lru_cache(maxsize=16)
def _board_corners(board) -> np.ndarray:
    """board.corners(), read-only, once per board (a solve builds thousands of factors)."""
    c = board.corners()
    c.setflags(write=False)
    return c


def _prepare(corners_px, board):
    q = np.array(corners_px, dtype=float).reshape(-1, 2)
    ok = np.all(np.isfinite(q), axis=1)
    corners_b = _board_corners(board)
    if len(corners_b) != len(q):
        raise ValueError(f"{len(q)} corners given for a {board.corners_x}x{board.corners_y} board")
    return np.where(ok[:, None], q, 0.0), ok, corners_b


def camera_corners_residuals(T_lidar0_camera, T_lidar0_board, corners_px, lensmodel: str,
                             intrinsics, board) -> np.ndarray:
    """(K,2) observed minus projected corners in px (zero rows where corners_px is NaN)."""
    q, ok, c = _prepare(corners_px, board)
    err, _ = _residual(T_lidar0_camera, T_lidar0_board, q, ok, c, lensmodel, np.asarray(intrinsics, float), False)
    return err.reshape(-1, 2)


def camera_corners_factor(sensor_key: int, board_key: int, corners_px, lensmodel: str, intrinsics,
                          board, sigma_px: float, *, effect_key: int | None = None, T_board_centre=None):
    """Reprojection factor of one camera's chessboard detection, whitened by ``sigma_px``;
    with ``effect_key``, also of that observation's board-pose error D (base.board_perturbed)."""
    q, ok, c = _prepare(corners_px, board)
    intr = np.array(intrinsics, dtype=float)
    fn = lambda poses, want: _residual(poses[0], poses[1], q, ok, c, lensmodel, intr, want)  # noqa: E731
    keys = [sensor_key, board_key]
    if effect_key is not None:
        fn = board_perturbed(fn, 1, T_board_centre)
        keys.append(effect_key)
    return make_factor(keys, isotropic(2 * len(q), sigma_px), fn)
