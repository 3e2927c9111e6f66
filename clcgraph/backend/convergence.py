"""Levenberg-Marquardt that says how it stopped, and the convergence record every solve keeps.

GTSAM's ``optimize()`` returns the same values whether it converged or ran out of iterations.
``optimize_lm`` runs GTSAM's own loop (``defaultOptimize``: iterate until the cost decrease is
below the relative or absolute tolerance, the cost below ``errorTol``, or ``maxIterations``)
one iteration at a time, so the record can say which one stopped it.

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

    opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
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
