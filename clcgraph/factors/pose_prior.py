"""Nominal-pose prior on a sensor (CAD drawing, /tf_static): the worked example of the
factor contract (factors/base.py, docs/extending.md).

Residual in mrcal rt coordinates of the pose error ``T_err = T_nominal^-1 T_lidar0_sensor``:
``[r_err (Rodrigues, rad), t_err (m)]``, whitened per component by ``sigma_rt``. With the right
perturbation ``T Exp([w, v])``: ``d r_err/dw = Jr^-1(r_err)``, ``d t_err/dv = R_err``.

SYNOPSIS
    f = pose_prior_factor(S(1), T_lidar0_sensor_nominal, sigma_rt=[0.02]*3 + [0.05]*3)
    r = pose_prior_residual(T_lidar0_sensor, T_lidar0_sensor_nominal)   # (6,)
"""

from __future__ import annotations

import numpy as np

from ..geometry import r_from_R, so3_right_jacobian_inverse
from .base import make_factor


def _residual(T, T_nominal, want: bool):
    E = T_nominal.between(T)
    R_e = E.rotation().matrix()
    r = r_from_R(R_e)
    err = np.concatenate([r, E.translation()])
    if not want:
        return err, None
    J = np.zeros((6, 6))
    J[:3, :3] = so3_right_jacobian_inverse(r)
    J[3:, 3:] = R_e
    return err, [J]


def pose_prior_residual(T_lidar0_sensor, T_lidar0_sensor_nominal) -> np.ndarray:
    """(6,) rt of T_nominal^-1 T (rad, m)."""
    return _residual(T_lidar0_sensor, T_lidar0_sensor_nominal, False)[0]


def pose_prior_factor(sensor_key: int, T_lidar0_sensor_nominal, sigma_rt):
    """Prior pulling a sensor's pose toward a nominal one with sigmas [r (rad) x3, t (m) x3]."""
    import gtsam

    sigma = np.asarray(sigma_rt, dtype=float).reshape(6)
    nominal = gtsam.Pose3(T_lidar0_sensor_nominal.matrix())
    fn = lambda poses, want: _residual(poses[0], nominal, want)  # noqa: E731
    return make_factor([sensor_key], gtsam.noiseModel.Diagonal.Sigmas(sigma), fn)
