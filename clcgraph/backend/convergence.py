"""Levenberg-Marquardt that says how it stopped, and the convergence record every solve keeps.

GTSAM's ``optimize()`` returns the same values whether it converged or ran out of iterations.
``optimize_lm`` runs GTSAM's own loop (``defaultOptimize``: iterate until the cost decrease is
below the relative or absolute tolerance, the cost below ``errorTol``, or ``maxIterations``)
one iteration at a time, so the record can say which one stopped it.

Each iteration is GTSAM's ``LevenbergMarquardtOptimizer::iterate`` (``_LM``: the same damping,
ordering, step acceptance and lambda schedule) driven from Python, so the Values every factor
is evaluated at are Python's own: GTSAM's binding hands a CustomFactor callback a *copy* of
any Values Python does not hold, so inside GTSAM's optimizer every callback copied the whole
Values, a cost of (factors x variables) per linearization (240 poses x 8 sensors: 70 % of the LM).

SYNOPSIS
    values, rec = optimize_lm(graph, initial, params, stage="range")
    rec   # {"stage": "range", "iterations": 7, "converged": True, "reason": "...", "cost_initial": .., "cost_final": ..}
    step = rec.pop("_last_step")   # gtsam.Values before the last iteration (for step-size checks)
"""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)

# An unconverged final solve is still trusted when its last step moved the poses by less than
# this many sigmas (Mahalanobis, with the reported covariance): stopping there changes the
# answer by a small part of its own uncertainty.
MAX_UNCONVERGED_STEP_SIGMA = 0.1


def optimize_lm(graph, initial, params, *, stage: str):
    """(optimized gtsam.Values, record dict); the record's ``_last_step`` holds the Values before
    the last iteration (pop it before writing the record out)."""
    import gtsam

    opt = _LM(graph, initial, params)
    rel_tol, abs_tol, err_tol = params.getRelativeErrorTol(), params.getAbsoluteErrorTol(), params.getErrorTol()
    max_it = params.getMaxIterations()
    cost0 = new = float(opt.error())
    prev = gtsam.Values(initial)
    reason = None
    if new <= err_tol:
        reason = f"cost {new:.3g} <= errorTol {err_tol:g} at the start"
    while reason is None:
        cur = new
        prev = gtsam.Values(opt.values())
        opt.iterate()
        new = float(opt.error())
        if not np.isfinite(new):
            reason = "the cost became non-finite"
            break
        dec = cur - new
        if new <= err_tol:
            reason = f"cost {new:.3g} <= errorTol {err_tol:g}"
        elif dec == 0.0:
            reason = "no step decreased the cost (at its minimum to machine precision)"
        elif dec <= abs_tol:
            reason = f"cost decrease {dec:.3g} <= absolute tolerance {abs_tol:g}"
        elif cur > 0 and dec / cur <= rel_tol:
            reason = f"relative cost decrease {dec / cur:.3g} <= relative tolerance {rel_tol:g}"
        elif opt.iterations() >= max_it:
            rec = {"stage": stage, "iterations": int(opt.iterations()), "converged": False,
                   "reason": f"stopped at max_iterations={max_it}, the cost still falling by {dec / max(cur, 1e-300):.3g} "
                             "relative per iteration",
                   "cost_initial": cost0, "cost_final": new, "_last_step": prev}
            return opt.values(), rec
    converged = np.isfinite(new)
    rec = {"stage": stage, "iterations": int(opt.iterations()), "converged": bool(converged), "reason": reason,
           "cost_initial": cost0, "cost_final": new, "_last_step": prev}
    return opt.values(), rec


class _LM:
    """GTSAM's LevenbergMarquardtOptimizer (4.3, no diagonal damping) step for step: the
    ``iterate``/``values``/``error``/``iterations`` the loop above uses. Damping: a prior of
    sigma 1/sqrt(lambda) on every variable; a step is taken when the model fidelity (cost
    decrease over the linearized decrease) exceeds 1e-3, and lambda then divided by
    lambdaFactor, else multiplied (giving up at lambdaUpperBound), as GTSAM's tryLambda."""

    _MIN_MODEL_FIDELITY = 1e-3  # GTSAM's LevenbergMarquardtParams default (not exposed in Python)

    def __init__(self, graph, initial, params):
        import gtsam

        if params.getDiagonalDamping() or not params.getUseFixedLambdaFactor():
            raise ValueError("optimize_lm: only GTSAM's default damping (fixed lambda factor, not diagonal)")
        self._gtsam, self._graph, self._params = gtsam, graph, params
        self._values = gtsam.Values(initial)
        self._error = float(graph.error(self._values))
        self._lambda, self._iterations = params.getlambdaInitial(), 0
        self._ordering = graph.orderingCOLAMD()  # EnsureHasOrdering's

    def values(self):
        return self._values

    def error(self) -> float:
        return self._error

    def iterations(self) -> int:
        return self._iterations

    def iterate(self) -> None:
        gtsam, p = self._gtsam, self._params
        linear = self._graph.linearize(self._values)
        zero = self._values.zeroVectors()
        old_linear = linear.error(zero)
        while True:
            damped = linear.clone()
            model = {}
            for k in self._values.keys():
                d = zero.at(k).shape[0]
                if d not in model:
                    model[d] = (np.eye(d), np.zeros(d), gtsam.noiseModel.Isotropic.Sigma(d, 1.0 / np.sqrt(self._lambda)))
                damped.add(gtsam.JacobianFactor(k, *model[d]))
            success = stop = False
            try:
                delta = damped.optimize(self._ordering)
            except RuntimeError:  # GTSAM's IndeterminantLinearSystemException: a larger lambda
                delta = None
            if delta is not None:
                linear_change = old_linear - linear.error(delta)
                if linear_change >= 0:
                    new_values = self._values.retract(delta)
                    new_error = float(self._graph.error(new_values))
                    cost_change = self._error - new_error
                    if linear_change > np.finfo(float).eps * old_linear:
                        success = cost_change / linear_change > self._MIN_MODEL_FIDELITY
                    stop = abs(cost_change) < p.getRelativeErrorTol() * self._error
            if success:
                self._values, self._error = new_values, new_error
                self._lambda = max(p.getlambdaLowerBound(), self._lambda / p.getlambdaFactor())
                self._iterations += 1
                return
            if stop:
                return
            self._lambda *= p.getlambdaFactor()
            if self._lambda >= p.getlambdaUpperBound():
                log.debug("LM: giving up, the cost does not decrease at the largest lambda")
                return


def step_sigma(prev, values, keys, covariance_xi: np.ndarray) -> float:
    """Mahalanobis length of the step prev -> values of the poses ``keys`` (GTSAM tangent,
    right perturbation, stacked in ``keys`` order) under their joint tangent covariance."""
    if not len(keys):
        return 0.0
    d = np.concatenate([np.asarray(prev.atPose3(k).localCoordinates(values.atPose3(k))) for k in keys])
    C = np.asarray(covariance_xi, dtype=float)
    try:
        return float(np.sqrt(max(d @ np.linalg.solve(C, d), 0.0)))
    except np.linalg.LinAlgError:
        return float("inf")


def public(rec: dict) -> dict:
    """The record without its private entries (YAML-safe)."""
    return {k: v for k, v in rec.items() if not k.startswith("_")}
