"""Motion compensation of rotating-LIDAR scans with per-point times and a constant twist.

SYNOPSIS
    xi = twist_between(T_prev, T_cur, dt)          # (6,) [omega, v] per second, body frame
    p_stamp = deskew(points, time_s, xi)           # (N,3) in the frame at the stamp

A point measured at time tau after the stamp is in the sensor frame at tau; with the
sensor moving with body twist xi, T_stamp_tau = Exp(tau xi). Second-order expansion:
at a few deg/s over 0.1 s the neglected terms are < 1e-6 of the range.
"""

from __future__ import annotations

import numpy as np

from ..geometry import skew, xi_log


def twist_between(T_a: np.ndarray, T_b: np.ndarray, dt: float) -> np.ndarray:
    """(6,) body twist [omega, v] per second taking pose T_a to T_b in dt seconds."""
    if dt <= 0:
        return np.zeros(6)
    return xi_log(np.linalg.inv(T_a) @ T_b) / dt


def deskew(points: np.ndarray, time_s: np.ndarray | None, xi: np.ndarray) -> np.ndarray:
    """(N,3) points moved from the frame at their own time into the frame at the stamp."""
    if time_s is None:
        return np.asarray(points, float)
    p = np.asarray(points, float)
    tau = np.asarray(time_s, float)[:, None]
    # a x p with a = tau omega is tau (K p), K = skew(omega): 3x3 products instead of per-point crosses
    K = skew(xi[:3])
    v = xi[3:]
    Kp = p @ K.T
    return p + tau * (Kp + v) + (0.5 * tau * tau) * (Kp @ K.T + K @ v)
