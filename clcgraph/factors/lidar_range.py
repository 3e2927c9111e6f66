"""LIDAR range-difference factor: the maximum-likelihood LIDAR cost of the clc seed.

A LIDAR measures range along known rays, so its noise is along the ray, not across the
plane. For a board point ``p`` (sensor frame) the error is the measured range minus the
range at which the ray ``p/|p|`` meets the board plane::

    err = |p| - d_s |p| / (n_s . p) = |p| (1 - d_s / (n_s . p))

with the board plane in the sensor frame ``n_s . x = d_s`` (``n_s = R_s^T n``,
``d_s = n . (t_board - t_s) + f``, f the face the LIDAR sees: 0 the pattern's, the board's
thickness its back, graph.lidar_face; the seed writes it as ``|p| (1 + tbl[2] / <Rbl[2,:], p>)``).
Rays nearly parallel to the plane would divide by ~0: ``|n_s . p|`` is clamped at
``|p| cos(87 deg)`` (such points are rare, and the clamp keeps LM from jumping).

SYNOPSIS
    f = lidar_range_factor(S(1), B(7), points_sensor, sigma_m=0.015)
    r = lidar_range_residuals(T_lidar0_sensor, T_lidar0_board, points_sensor)   # (K,) m
"""

from __future__ import annotations

import numpy as np

from ..geometry import skew
from .base import lidar_board_factor

_MIN_COS = np.cos(np.radians(87.0))


def _residual(T_sensor, T_board, points: np.ndarray, want: bool, rng: np.ndarray | None = None,
              face_m: float = 0.0):
    """``rng``: the points' ranges |p|, when the caller keeps them (a factor evaluates many times)."""
    if T_sensor is None:
        R_s, t_s = np.eye(3), np.zeros(3)
    else:
        R_s, t_s = T_sensor.rotation().matrix(), T_sensor.translation()
    R_b, t_b = T_board.rotation().matrix(), T_board.translation()
    n = R_b[:, 2]
    n_s = R_s.T @ n
    rng = np.linalg.norm(points, axis=1) if rng is None else rng
    a_raw = points @ n_s
    floor = rng * _MIN_COS
    clamped = np.abs(a_raw) < floor
    any_clamped = bool(clamped.any())  # rare: skip the selects when no ray grazes
    a = np.where(clamped, np.where(a_raw < 0, -floor, floor), a_raw) if any_clamped else a_raw
    b = float(n @ (t_b - t_s)) + face_m
    err = rng * (1.0 - b / a)
    if not want:
        return err, None
    # d err = |p| (b da - a db) / a^2
    g_b = -rng / a
    g_a = -b * g_b / a
    if any_clamped:
        g_a[clamped] = 0.0
    K = len(points)
    q = points @ (R_b.T @ R_s)[:2].T  # the first two rows of R_b^T R_s p
    J_b = np.zeros((K, 6))
    # da/d omega_b = e3 x q ; db/d omega_b = e3 x (R_b^T (t_b - t_s)) ; db/d v_b = e3
    c = R_b.T @ (t_b - t_s)
    J_b[:, 0] = g_a * -q[:, 1] + g_b * -c[1]
    J_b[:, 1] = g_a * q[:, 0] + g_b * c[0]
    J_b[:, 5] = g_b
    if T_sensor is None:
        return err, [J_b]
    J_s = np.empty((K, 6))
    J_s[:, :3] = g_a[:, None] * (points @ skew(n_s))  # da/d omega_s = p x n_s (np.cross costs more)
    J_s[:, 3:] = g_b[:, None] * -n_s  # db/d v_s = -n_s
    return err, [J_s, J_b]


def lidar_range_residuals(T_lidar0_sensor, T_lidar0_board, points_sensor, face_m: float = 0.0) -> np.ndarray:
    """(K,) measured minus predicted range (to the board face ``face_m``) in m (T_lidar0_sensor None = lidar0)."""
    return _residual(T_lidar0_sensor, T_lidar0_board, np.asarray(points_sensor, float), False, face_m=face_m)[0]


def lidar_range_factor(sensor_key: int | None, board_key: int, points_sensor, sigma_m: float, *,
                       face_m: float = 0.0, effect_key: int | None = None, T_board_centre=None):
    """Range-difference factor of one LIDAR observation of the board face ``face_m``, whitened by
    ``sigma_m``; with ``effect_key``, also of that observation's board-pose error D (base.board_perturbed)."""
    rng = np.linalg.norm(np.asarray(points_sensor, dtype=float), axis=1)  # once per factor, not per evaluation
    return lidar_board_factor(lambda T_s, T_b, p, want: _residual(T_s, T_b, p, want, rng, face_m), sensor_key,
                              board_key, points_sensor, sigma_m, effect_key=effect_key, T_board_centre=T_board_centre)
