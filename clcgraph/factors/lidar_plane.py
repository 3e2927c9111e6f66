"""LIDAR point-to-plane factor (the pre-solve cost of the clc seed).

Board points ``p`` measured by a LIDAR, moved into lidar0, lie on the board plane:
``err_k = n . (T_lidar0_sensor p_k - t_board) - f``, ``n = R_board[:, 2]``, in metres, with ``f``
the face the LIDAR sees (0 the pattern's, the board's thickness its back: graph.lidar_face). Cheap and
well-conditioned from a rough start; the range factor (lidar_range.py) replaces it for the
maximum-likelihood solve. ``sensor_key=None`` is lidar0 itself (identity pose, unary factor).

SYNOPSIS
    f = lidar_plane_factor(S(1), B(7), points_sensor, sigma_m=0.02)
    r = lidar_plane_residuals(T_lidar0_sensor, T_lidar0_board, points_sensor)   # (K,) m
"""

from __future__ import annotations

import numpy as np

from .base import lidar_board_factor

_E3 = np.array([0.0, 0.0, 1.0])


def _residual(T_sensor, T_board, points: np.ndarray, want: bool, face_m: float = 0.0):
    if T_sensor is None:
        R_s, t_s = np.eye(3), np.zeros(3)
    else:
        R_s, t_s = T_sensor.rotation().matrix(), T_sensor.translation()
    R_b, t_b = T_board.rotation().matrix(), T_board.translation()
    n = R_b[:, 2]
    v = points @ R_s.T + t_s
    err = (v - t_b) @ n - face_m
    if not want:
        return err, None
    K = len(points)
    q = (v - t_b) @ R_b  # points in the board frame (its x, y: the face's offset f is along z)
    J_b = np.zeros((K, 6))
    J_b[:, 0] = -q[:, 1]  # d/d omega_b = e3 x q
    J_b[:, 1] = q[:, 0]
    J_b[:, 5] = -1.0
    if T_sensor is None:
        return err, [J_b]
    n_s = R_s.T @ n
    J_s = np.empty((K, 6))
    J_s[:, :3] = np.cross(points, n_s)  # d/d omega_s = p x (R_s^T n)
    J_s[:, 3:] = n_s  # d/d v_s = (R_s^T n)^T
    return err, [J_s, J_b]


def lidar_plane_residuals(T_lidar0_sensor, T_lidar0_board, points_sensor, face_m: float = 0.0) -> np.ndarray:
    """(K,) signed distances in m to the board face ``face_m`` (T_lidar0_sensor None = lidar0)."""
    return _residual(T_lidar0_sensor, T_lidar0_board, np.asarray(points_sensor, float), False, face_m)[0]


def lidar_plane_factor(sensor_key: int | None, board_key: int, points_sensor, sigma_m: float, *,
                       face_m: float = 0.0, effect_key: int | None = None, T_board_centre=None):
    """Point-to-plane factor of one LIDAR observation of the board face ``face_m``, whitened by
    ``sigma_m``; with ``effect_key``, also of that observation's board-pose error D (base.board_perturbed)."""
    return lidar_board_factor(lambda T_s, T_b, p, want: _residual(T_s, T_b, p, want, face_m), sensor_key, board_key,
                              points_sensor, sigma_m, effect_key=effect_key, T_board_centre=T_board_centre)
