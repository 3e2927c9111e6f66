"""Final extrinsic from a GTSAM graph of per-frame registrations, with a Marginals covariance.

SYNOPSIS
    est = fuse(measurements)      # measurements: list[FrameMeasurement]
    est.T, est.cov_rt             # (4,4) T_lidar0_sensor, (6,6) covariance of rt_lidar0_sensor

One Pose3 variable (the extrinsic) with one factor per selected frame: the frame's
registration result with covariance s * H_k^-1. GICP's Hessian has arbitrary units
(regularised point covariances), so the common scale s is estimated from the
scatter of the per-frame results about the fused estimate (chi^2 / dof = 1), and the
covariance is not allowed to be smaller than the spread of the frames implies.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import geometry as geo
from ..errors import DegenerateError


@dataclass
class Estimate:
    T: np.ndarray  # (4,4)
    cov_rt: np.ndarray  # (6,6) rt coordinates
    cov_xi: np.ndarray  # (6,6) GTSAM tangent
    scale: float
    chi2_per_dof: float


def _solve(meas, scale):
    import gtsam

    X = gtsam.symbol("x", 0)
    g = gtsam.NonlinearFactorGraph()
    for m in meas:
        cov = scale * np.linalg.inv(0.5 * (m.H + m.H.T))
        g.add(gtsam.PriorFactorPose3(X, gtsam.Pose3(m.T), gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov + cov.T))))
    v = gtsam.Values()
    v.insert(X, gtsam.Pose3(meas[0].T))
    res = gtsam.LevenbergMarquardtOptimizer(g, v).optimize()
    P = res.atPose3(X)
    cov = gtsam.Marginals(g, res).marginalCovariance(X)
    return P, cov, g.error(res)


def fuse(meas, *, min_frames: int = 2, max_cond: float = 1e6) -> Estimate:
    """Fuse per-frame T_lidar0_sensor estimates; DegenerateError if the registrations constrain too little."""
    if len(meas) < min_frames:
        raise DegenerateError(f"only {len(meas)} usable calibration frames (< {min_frames}); "
                              "drive longer through a scene with 3-D structure")
    for m in meas:
        w = np.linalg.eigvalsh(0.5 * (m.H + m.H.T))
        if w[0] <= 0 or w[-1] / w[0] > max_cond:
            raise DegenerateError(f"a calibration registration is degenerate (Hessian condition {w[-1] / max(w[0], 1e-300):.3g}); "
                                  "the scene does not constrain all six degrees of freedom")
    P, _, err = _solve(meas, 1.0)
    dof = 6 * (len(meas) - 1)
    chi2 = 2.0 * err / max(dof, 1)
    P, cov, err2 = _solve(meas, max(chi2, 1e-12))
    # The frames share one map (drift, interpolation): their errors are correlated, so the
    # independent-factor Marginals are too optimistic by up to K. Report the conservative bound.
    cov = cov * len(meas)
    T = P.matrix()
    rt = geo.rt_from_T(T)
    J = geo.drt_dxi(rt)
    return Estimate(T, J @ cov @ J.T, cov, chi2, 2.0 * err2 / max(dof, 1))
