"""The factor contract: how a measurement becomes a GTSAM factor in clcgraph.

A factor module provides two things:

1. a pure-numpy residual function of the poses it touches,
   ``residual_fn(poses: list[gtsam.Pose3], want_jacobians: bool) -> (err (m,), [J_k (m,6)] | None)``,
   unwhitened, in the measurement's units (m, px, rad), with the Jacobians w.r.t. GTSAM's
   right perturbation ``T * Exp([omega, v])`` of each pose (rotation first), vectorized
   over all points of one (sensor, snapshot) observation;
2. a constructor ``<name>_factor(keys..., measurement..., sigma...) -> gtsam.CustomFactor``
   that binds the measurement and wraps the residual with ``make_factor`` and an isotropic
   (or diagonal) noise model of the measurement's current sigma. The solver rebuilds
   factors when it re-estimates sigmas or drops outlier points, so factors stay immutable.

Every factor is tested with ``check_jacobians`` (central differences) at random poses,
at zero residual at the truth, and through the ``H is None`` path.
See docs/extending.md for a worked example (factors/pose_prior.py).

SYNOPSIS
    f = make_factor([key_a, key_b], gtsam.noiseModel.Isotropic.Sigma(m, sigma), residual_fn)
    err = check_jacobians(residual_fn, [pose_a, pose_b])   # max relative Jacobian error
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

ResidualFn = Callable[[list, bool], tuple]


def make_factor(keys: Sequence[int], noise_model, residual_fn: ResidualFn):
    """A gtsam.CustomFactor on Pose3 ``keys`` whose unwhitened error is ``residual_fn``."""
    import gtsam

    keys = [int(k) for k in keys]
    # The last evaluation, by the exact poses it was made at: the solve linearizes the same
    # graph at the same values several times (Marginals, the consistency checks, the final
    # cost), and a residual is a pure function of its poses. The Jacobians are made with every
    # evaluation, even when only the error is asked for: LM evaluates the error at its trial
    # point and, the step accepted (nearly always), linearizes there next.
    last = {"at": None, "err": None, "jac": None}

    def error(this, values, H):
        poses = [values.atPose3(k) for k in keys]
        at = b"".join(p.matrix().tobytes() for p in poses)
        if at != last["at"]:
            err, jac = residual_fn(poses, True)
            last["at"], last["err"] = at, np.asarray(err, dtype=float)
            last["jac"] = [np.ascontiguousarray(J, dtype=float) for J in jac]
        if H is not None:
            for i, J in enumerate(last["jac"]):
                H[i] = J
        return last["err"]

    return gtsam.CustomFactor(noise_model, gtsam.KeyVector(keys), error)


def board_perturbed(residual_fn: ResidualFn, board_index: int, T_board_centre) -> ResidualFn:
    """``residual_fn`` with one more pose, a per-observation perturbation D of the board.

    The wrapped function evaluates ``residual_fn`` at the board pose ``T_b C D C^-1`` (C =
    ``T_board_centre``, the board centre in the board frame, so D tilts about the centre)
    instead of ``T_b``, and takes D as its last pose: the random effect of
    backend/noise.py (one observation's own board-pose error: a LIDAR's plane offset and
    tilt, a camera's board-pose jitter). Jacobians by the right-perturbation identities
    ``T Exp(xi) M = T M Exp(Ad(M^-1) xi)`` and ``C D Exp(xi) C^-1 = C D C^-1 Exp(Ad(C) xi)``.
    """
    C = T_board_centre
    Ad_C = C.AdjointMap()

    def fn(poses, want):
        *head, D = poses
        M = C.compose(D).compose(C.inverse())
        head = list(head)
        head[board_index] = head[board_index].compose(M)
        err, jac = residual_fn(head, want)
        if not want:
            return err, None
        J_b = jac[board_index]
        jac = list(jac)
        jac[board_index] = J_b @ M.inverse().AdjointMap()
        return err, [*jac, J_b @ Ad_C]

    return fn


def lidar_board_factor(residual, sensor_key: int | None, board_key: int, points_sensor, sigma_m: float, *,
                       effect_key: int | None = None, T_board_centre=None):
    """The factor of one LIDAR observation of the board (K points in the sensor's frame) for a LIDAR
    residual ``residual(T_sensor or None, T_board, points (K,3), want_jacobians) -> (err (K,), [H])``:
    keys (sensor, board), or (board) alone for lidar0 (``sensor_key`` None), whitened by ``sigma_m``;
    with ``effect_key``, also of that observation's board-pose error D (board_perturbed)."""
    pts = np.array(points_sensor, dtype=float)
    if sensor_key is None:
        fn = lambda poses, want: residual(None, poses[0], pts, want)  # noqa: E731
        keys = [board_key]
    else:
        fn = lambda poses, want: residual(poses[0], poses[1], pts, want)  # noqa: E731
        keys = [sensor_key, board_key]
    if effect_key is not None:  # this observation's own board-pose error
        fn = board_perturbed(fn, len(keys) - 1, T_board_centre)
        keys = [*keys, effect_key]
    return make_factor(keys, isotropic(len(pts), sigma_m), fn)


def isotropic(dim: int, sigma: float):
    """An isotropic Gaussian noise model of ``dim`` rows and std ``sigma``."""
    import gtsam

    return gtsam.noiseModel.Isotropic.Sigma(int(dim), float(sigma))


def perturb(pose, xi: np.ndarray):
    """``pose * Exp(xi)``: GTSAM's right perturbation, xi = [omega, v]."""
    import gtsam

    return pose.compose(gtsam.Pose3.Expmap(np.asarray(xi, dtype=float)))


def numerical_jacobians(residual_fn: ResidualFn, poses: list, eps: float = 1e-6) -> list[np.ndarray]:
    """Central-difference Jacobians (m,6) of ``residual_fn`` w.r.t. each pose's right perturbation."""
    out = []
    for i in range(len(poses)):
        cols = []
        for j in range(6):
            d = np.zeros(6)
            d[j] = eps
            plus = list(poses)
            minus = list(poses)
            plus[i] = perturb(poses[i], d)
            minus[i] = perturb(poses[i], -d)
            cols.append((residual_fn(plus, False)[0] - residual_fn(minus, False)[0]) / (2 * eps))
        out.append(np.stack(cols, axis=-1))
    return out


def check_jacobians(residual_fn: ResidualFn, poses: list, eps: float = 1e-6) -> float:
    """Max relative difference between analytic and central-difference Jacobians (all poses)."""
    _, analytic = residual_fn(list(poses), True)
    numeric = numerical_jacobians(residual_fn, list(poses), eps)
    worst = 0.0
    for A, N in zip(analytic, numeric):
        scale = max(np.abs(N).max(), 1e-12)
        worst = max(worst, float(np.abs(A - N).max() / scale))
    return worst
