"""A sensor scan registered to a map made of keyframe submaps: the extrinsic's factor in the
targetless graph (targetless/keyframe_graph.py).

The registration of one calibration scan against a dense target gave ``Z`` = T_anchor_sensor,
with anchor = the mapping LIDAR at the scan's stamp. The target was assembled from keyframe
submaps placed with the mapping's estimates ``M_j`` = X_i^-1 X_j (i: the anchor's keyframe).
If keyframe j really sits at X_i^-1 X_j = M_j Exp(b_j), the registration shifted by
``B_j b_j`` (``B_j`` = -H^-1 H_j Ad(Z^-1 R_anchor_j), H_j the part of the registration's
information that came from submap j; targetless/registration.py computes it). So

    e = Log(Z^-1 E beta) + sum_j B_j Log(M_j^-1 X_i^-1 X_j)          (6,)

is zero at the truth; ``beta`` (optional) is a registration bias shared by all frames.
Keys ``[E, (beta), X_i, X_j...]``. Jacobians (right perturbation, rotation first), with
d0 = Z^-1 E beta: d/dE = Jr^-1(Log d0) Ad(beta^-1); d/dbeta = Jr^-1(Log d0);
d/dX_j = B_j Jr^-1(b_j); d/dX_i = -sum_j B_j Jr^-1(b_j) Ad(D_j^-1) with D_j = X_i^-1 X_j.

SYNOPSIS
    f = map_registration_factor(Z, covariance, E_key, bias_key=None, anchor_key=X_i, links={X_j: (M_j, B_j)})
"""

from __future__ import annotations

import numpy as np

from .base import make_factor


def _residual(poses, Z, links, has_bias: bool, want: bool):
    """poses = [E, (beta), (X_i, X_j...)]; links = [(M_j, B_j)...] in the order of the X_j."""
    import gtsam

    E = poses[0]
    beta = poses[1] if has_bias else gtsam.Pose3()
    rest = poses[2:] if has_bias else poses[1:]
    d0 = Z.between(E.compose(beta))
    err = gtsam.Pose3.Logmap(d0)
    J = None
    if want:
        J0 = gtsam.Pose3.LogmapDerivative(d0)
        J = [J0 @ beta.inverse().AdjointMap()] + ([J0] if has_bias else []) + ([np.zeros((6, 6))] if rest else [])
    ix = len(J) - 1 if want else 0
    for Xj, (M, B) in zip(rest[1:], links):
        D = rest[0].between(Xj)
        d = M.between(D)
        err = err + B @ gtsam.Pose3.Logmap(d)
        if want:
            Jb = B @ gtsam.Pose3.LogmapDerivative(d)
            J.append(Jb)
            J[ix] = J[ix] - Jb @ D.inverse().AdjointMap()
    return err, J


def map_registration_factor(Z, covariance: np.ndarray, E_key: int, *, bias_key: int | None = None,
                            anchor_key: int | None = None, links: dict | None = None):
    """Factor on the extrinsic E (and a shared bias, the anchor keyframe X_i, the linked keyframes X_j).

    Z: the registration result T_anchor_sensor (gtsam.Pose3); covariance (6,6) of Z's tangent;
    links: X_j key -> (M_j = X_i^-1 X_j used to build the target (gtsam.Pose3), B_j (6,6)).
    """
    import gtsam

    links = dict(links or {})
    if links and anchor_key is None:
        raise ValueError("linked keyframes need the anchor keyframe's key")
    keys = [E_key] + ([bias_key] if bias_key is not None else []) + ([anchor_key] if anchor_key is not None else []) \
        + list(links)
    lk = list(links.values())
    noise = gtsam.noiseModel.Gaussian.Covariance(0.5 * (covariance + covariance.T))
    return make_factor(keys, noise, lambda poses, want: _residual(poses, Z, lk, bias_key is not None, want))
