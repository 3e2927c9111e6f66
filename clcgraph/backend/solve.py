"""The staged solve: seed -> LM (point-to-plane) -> LM (range + camera) -> noise
re-estimation and outlier rejection until stable -> covariance from gtsam.Marginals.

- **Noise**: the LIDAR range sigma and the camera pixel sigma are re-estimated from the
  residuals each round (robustly, by the MAD, while outliers may still be present; by the
  RMS with a degrees-of-freedom correction at the end), and the factors rebuilt with them,
  so the reported covariance reflects the data's real noise (the seed hard-codes them).
- **Outliers**: a whole observation whose RMS exceeds ``3 sigma`` (a wrong plane, a shifted
  or mis-ordered detection) is rejected, the worst one per snapshot per round, then the
  solve is redone; single points/corners beyond ``outlier_sigma`` are masked, and an
  observation left with less than half of them is rejected whole. Every
  rejection is a Rejected(stage="outlier") with the numbers.
- **Degeneracy**: a sensor whose pose the data do not determine (information singular, or a
  1-sigma beyond ``max_stdev_m`` / ``max_stdev_deg`` in some direction) is a DegenerateError
  naming the sensor and the direction, never a number (GTSAM's "Indeterminate linear
  system" included: consistency.unobservable_error names the free direction); the same
  limits with the consider terms added ("imprecise"), naming the term that makes most of it.
- **Consistency**: the final solution must pass backend/consistency.py's checks (leave one
  snapshot out, per sensor pair, no material error a single snapshot could hide), else a
  SolveError / DegenerateError naming the snapshot, sensor and direction; the verdict is
  ``Result.stats["consistency"]``.
- **Uncertainty check**: the leave-one-snapshot-out jackknife (backend/jackknife.py); along
  an axis where it rejects the model, the covariance is raised to the jackknife's spread.

SYNOPSIS
    result = calibrate(problem, Config().solve)      # -> types.Result
"""

from __future__ import annotations

import logging
import time
from typing import Callable

import numpy as np

from ..errors import DegenerateError, SolveError
from ..geometry import R_from_r, drt_dxi, pose3_from_rt, rt_from_pose3, tangent_covariance_from_rt
from ..two_processes import TwoProcesses
from ..types import Problem, Rejected, Result
from . import board_check, consider, consistency, dark_squares
from . import graph as G
from . import noise as N
from .convergence import MAX_UNCONVERGED_STEP_SIGMA, optimize_lm, public, step_sigma
from .jackknife import jackknife, raise_where_rejected
from .replay import without_snapshots
from .seed import seed as make_seed

log = logging.getLogger(__name__)

# No sensor is better than this: noise-free (simulated, or duplicated) observations would
# otherwise get infinite weight and an indeterminate covariance.
_MIN_SIGMA_LIDAR_M = 1e-3
_MIN_SIGMA_CAMERA_PX = 1e-2
_WHOLE_OBS_FACTOR = 3.0  # reject an observation whose RMS exceeds this many sigmas
_MAX_ROUNDS = 8
_MIN_INLIER_SHARE = 0.5  # ... or whose points/corners are mostly beyond outlier_sigma
_MAX_EFFECT_ROUNDS = 3  # solve <-> variance components of the per-observation errors
# The cost is ~ half the number of residuals: 1e-7 of it is far below what moves a pose by
# a fraction of its sigma (a cost change of 0.5). (LM crept while a LIDAR D's in-plane DOFs
# were loose: noise._UNSEEN.)
_EFFECT_TOL = 1e-7
_TIE_RATIO = 1.5  # deleted residuals this close cannot tell the culprit apart
# A sensor's outliers are judged by its own robust sigma where that is this many times its kind's
# other sensors': beyond what a minority of bad observations does to a median (a third of them
# moves it at most to the 75th percentile of the good residuals, 1.7x), over this many observations
_OWN_SCALE_RATIO = 2.0
_MIN_ROBUST_OBSERVATIONS = 3


def _lm(problem, active, rt_sensor, rt_board, lidar, sigma, options, nominal, stage, effects=None,
        effect_values=None, relative_tol=1e-10):
    """LM from the given poses; ``sigma``: per-sensor noise (m for LIDARs, px for cameras);
    ``effects``: per-observation board-pose error sigmas (graph.build), None = white only.
    Returns (rt_sensor, rt_board, convergence record of ``stage``, (graph, values))."""
    import gtsam

    g, v = G.build(problem, active, rt_sensor, rt_board, lidar=lidar, sigma_lidar_m=sigma,
                   sigma_camera_px=sigma, options=options, board_nominal=nominal, effects=effects,
                   effect_values=effect_values)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(options.max_iterations)
    params.setRelativeErrorTol(relative_tol)
    params.setAbsoluteErrorTol(1e-15)
    try:
        out, rec = optimize_lm(g, v, params, stage=stage)
    except RuntimeError:  # GTSAM's IndeterminantLinearSystemException: name the free direction
        raise consistency.unobservable_error(problem, consistency.linearize(problem, g, v)) from None
    rt_sensor = rt_sensor.copy()
    rt_board = np.full_like(rt_board, np.nan)
    for i in range(len(problem.sensors)):
        if i != problem.reference:
            rt_sensor[i] = rt_from_pose3(out.atPose3(G.sensor_key(i)))
    used, _ = active.boards(problem)
    for k in used:
        rt_board[k] = rt_from_pose3(out.atPose3(G.board_key(k)))
    return rt_sensor, rt_board, rec, (g, out)


def _mad_sigma(r: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(r))) if len(r) else float("nan")


def _robust_sigmas(problem, active, per: dict, options) -> np.ndarray:
    """Per sensor, the robust sigma (MAD) of the residuals ``per`` that its outliers are judged
    against: its kind's, pooled (a sensor pulled by its own bad observations cannot raise the scale
    they are judged by), unless its own MAD is more than _OWN_SCALE_RATIO x that of the other
    sensors of its kind over three or more observations: rigs mix a sharp camera with a dim noisy
    one, a quiet LIDAR with a noisy one, and the pooled scale threw out the noisier one's boards."""
    is_lidar = [s.is_lidar for s in problem.sensors]
    n_obs = np.zeros(len(problem.sensors), int)
    for o, m in [*zip(problem.lidar_observations, active.lidar), *zip(problem.camera_observations, active.camera)]:
        n_obs[o.sensor] += m is not None

    def mad(ids, default):
        r = [per[i] for i in ids if len(per.get(i, ()))]
        return _mad_sigma(np.concatenate(r)) if r else default

    out = np.zeros(len(problem.sensors))
    for i, lidar in enumerate(is_lidar):
        kind = [j for j in range(len(is_lidar)) if is_lidar[j] == lidar]
        default = options.sigma_lidar_m if lidar else options.sigma_camera_px
        out[i] = mad(kind, default)
        if n_obs[i] >= _MIN_ROBUST_OBSERVATIONS and len(kind) > 1 and len(per.get(i, ())):
            own = _mad_sigma(per[i])
            if own > _OWN_SCALE_RATIO * mad([j for j in kind if j != i], own):
                out[i] = own
    return out


def _dof(problem, active, n_l: int, n_c: int) -> tuple[float, float]:
    """Parameters attributable to the LIDAR and camera residuals (for an unbiased sigma)."""
    used, cam = active.boards(problem)
    p = 6 * (len(problem.sensors) - 1) + 6 * len(used) - 3 * len(used - cam)
    n = max(n_l + n_c, 1)
    return p * n_l / n, p * n_c / n


def _per_sensor_residuals(problem, lid, cam, active) -> dict:
    """{sensor: its active residuals (m or px)}."""
    out: dict = {}
    for o, r, m in zip(problem.lidar_observations, lid, active.lidar):
        if m is not None and r is not None:
            out.setdefault(o.sensor, []).append(r[m])
    for o, r, m in zip(problem.camera_observations, cam, active.camera):
        if m is not None and r is not None:
            out.setdefault(o.sensor, []).append(r[m].ravel())
    return {i: np.concatenate(v) for i, v in out.items()}


def _reestimate(problem, active, per: dict, sig: np.ndarray, lidars: list, per_sensor: bool) -> np.ndarray:
    """Sigmas from the residuals, unbiased by the parameters they determine (shared out by
    residual count); per sensor, or pooled per kind (LIDAR, camera)."""
    n_l = sum(len(per[i]) for i in per if i in lidars)
    n_c = sum(len(per[i]) for i in per if i not in lidars)
    p_l, p_c = _dof(problem, active, n_l, n_c)
    out = sig.copy()
    groups = [[i] for i in per] if per_sensor else [[i for i in per if i in lidars], [i for i in per if i not in lidars]]
    for ids in groups:
        if not ids:
            continue
        is_lidar = ids[0] in lidars
        n = sum(len(per[i]) for i in ids)
        p = (p_l * n / max(n_l, 1)) if is_lidar else (p_c * n / max(n_c, 1))
        ss = sum(float(np.sum(per[i] ** 2)) for i in ids)
        value = max(float(np.sqrt(ss / max(n - p, 1))), _MIN_SIGMA_LIDAR_M if is_lidar else _MIN_SIGMA_CAMERA_PX)
        out[ids] = value
    return out


def _active_residuals(lid, cam, active):
    rl = [r[m] for r, m in zip(lid, active.lidar) if m is not None and r is not None]
    rc = [r[m].ravel() for r, m in zip(cam, active.camera) if m is not None and r is not None]
    return (np.concatenate(rl) if rl else np.zeros(0)), (np.concatenate(rc) if rc else np.zeros(0))


def _reject(problem, active, lid, cam, sig, options, rt_sensor, rt_board) -> list[Rejected]:
    """Mark outliers in ``active`` (in place) against each sensor's robust sigma ``sig`` (per sensor, m
    or px); return the new whole-observation rejections.

    Whole observations first, the worst per snapshot, and nothing else that round: one bad
    observation drags its board and so the residuals of the good ones. Only once no
    observation stands out are single points/corners masked (recomputed from scratch each
    round, so a point masked while the solution was still pulled comes back).
    """
    new = []
    members: dict[int, list] = {}  # snapshot -> [(kind, j, joint z)]
    for kind, obs, res, masks in (("lidar", problem.lidar_observations, lid, active.lidar),
                                  ("camera", problem.camera_observations, cam, active.camera)):
        for j, (o, r, m) in enumerate(zip(obs, res, masks)):
            if m is None or r is None or not m.any():
                continue
            rr = r[m] if kind == "lidar" else r[m].ravel()
            members.setdefault(o.snapshot, []).append((kind, j, float(np.sqrt(np.mean(rr**2)) / G.sigma_of(sig, o.sensor))))
    for k, group in members.items():
        if max(z for _, _, z in group) <= _WHOLE_OBS_FACTOR:
            continue
        if len(group) <= 2:  # two sensors disagree: nothing tells which one is wrong
            for kind, j, z in group:
                _deactivate(active, kind, j)
                o = (problem.lidar_observations if kind == "lidar" else problem.camera_observations)[j]
                new.append(Rejected(f"the {len(group)} observations of this board disagree ({kind} RMS {z:.1f} sigma)",
                                    "outlier", o.sensor, k))
            continue
        # the culprit is the one the others predict worst (its "deleted residual")
        scored = [(_deleted_z(problem, active, rt_sensor, rt_board, k, kind, j, sig, options), kind, j)
                  for kind, j, _ in group]
        scored.sort(reverse=True)
        z, kind, j = scored[0]
        if z <= _WHOLE_OBS_FACTOR:
            continue
        # two observations that each contradict the rest about equally (two cameras that
        # disagree on a board the LIDARs only see as a plane): nothing tells which is wrong
        tied = [x for x in scored[1:] if x[0] > _WHOLE_OBS_FACTOR and x[0] > z / _TIE_RATIO]
        for z_, kind_, j_ in [scored[0], *tied]:
            _deactivate(active, kind_, j_)
            o = (problem.lidar_observations if kind_ == "lidar" else problem.camera_observations)[j_]
            why = "; another observation of this board is as far off, so both are dropped" if tied else ""
            new.append(Rejected(f"{kind_} observation {z_:.1f} sigma off the board pose the other sensors see "
                                f"(> {_WHOLE_OBS_FACTOR:g}): wrong plane or bad detection{why}", "outlier", o.sensor, k))
    if new:
        return new
    for j, (o, r, m) in enumerate(zip(problem.lidar_observations, lid, active.lidar)):
        if m is not None and r is not None:
            active.lidar[j] = np.abs(r) <= options.outlier_sigma * G.sigma_of(sig, o.sensor)
    for j, (o, r, m) in enumerate(zip(problem.camera_observations, cam, active.camera)):
        if m is not None and r is not None:
            lim = options.outlier_sigma * G.sigma_of(sig, o.sensor)
            active.camera[j] = np.all(np.isfinite(o.corners_px), axis=1) & np.all(np.abs(r) <= lim, axis=1)
    # an observation that lost most of its points is wrong as a whole
    for kind, obs, masks in (("lidar", problem.lidar_observations, active.lidar),
                             ("camera", problem.camera_observations, active.camera)):
        for j, (o, m) in enumerate(zip(obs, masks)):
            if m is not None and m.mean() < _MIN_INLIER_SHARE:
                masks[j] = None
                new.append(Rejected(f"{kind} observation: {int((~m).sum())} of {len(m)} "
                                    f"{'points' if kind == 'lidar' else 'corners'} beyond {options.outlier_sigma:g} sigma",
                                    "outlier", o.sensor, o.snapshot))
    return new


def _mask_signature(active) -> int:
    return hash(tuple(None if m is None else m.tobytes() for m in [*active.lidar, *active.camera]))


def _deactivate(active, kind: str, j: int) -> None:
    (active.lidar if kind == "lidar" else active.camera)[j] = None


def _deleted_z(problem, active, rt_sensor, rt_board, k, kind, j, sig, options) -> float:
    """RMS/sigma of observation (kind, j) of snapshot k at the board pose fitted to the
    snapshot's OTHER observations, with the sensor poses held."""
    import gtsam

    sub = G.Active([None] * len(active.lidar), [None] * len(active.camera))
    for o_j, (o, m) in enumerate(zip(problem.lidar_observations, active.lidar)):
        if o.snapshot == k and m is not None and not (kind == "lidar" and o_j == j):
            sub.lidar[o_j] = m
    for o_j, (o, m) in enumerate(zip(problem.camera_observations, active.camera)):
        if o.snapshot == k and m is not None and not (kind == "camera" and o_j == j):
            sub.camera[o_j] = m
    g, v = G.build(problem, sub, rt_sensor, rt_board, lidar="range", sigma_lidar_m=sig, sigma_camera_px=sig,
                   options=options)
    held = gtsam.noiseModel.Isotropic.Sigma(6, 1e-9)
    for i in range(len(problem.sensors)):
        if i != problem.reference:
            g.add(gtsam.PriorFactorPose3(G.sensor_key(i), v.atPose3(G.sensor_key(i)), held))
    try:
        out = gtsam.LevenbergMarquardtOptimizer(g, v).optimize()
    except RuntimeError:
        return float("inf")
    b = rt_board.copy()
    b[k] = rt_from_pose3(out.atPose3(G.board_key(k)))
    poses = [None if i == problem.reference else pose3_from_rt(rt_sensor[i]) for i in range(len(problem.sensors))]
    r = G.residual_of(problem, kind, j, poses, b)  # this observation's alone: not every snapshot's
    if kind == "lidar":
        r = r[active.lidar[j]]
        return float(np.sqrt(np.mean(r**2)) / G.sigma_of(sig, problem.lidar_observations[j].sensor))
    r = r[active.camera[j]].ravel()
    return float(np.sqrt(np.mean(r**2)) / G.sigma_of(sig, problem.camera_observations[j].sensor))


def _unit_errors(problem, rebuild, values, nominal, rt_sensor, options) -> dict:
    """What `compare` needs to pair two calibrations of the same units (comparison.py): the named
    errors of the sensor units, d rt_lidar0_sensor / d error per unit of each (rt coordinates, the
    variable sensors' order, like the covariance), and the sigmas of them already in the covariance."""
    from ..geometry import drt_dxi

    errors, J = consider.unit_error_sensitivities(problem, rebuild, values, nominal)
    idx = problem.variable_sensors()
    for a, i in enumerate(idx):
        J[6 * a:6 * a + 6] = drt_dxi(rt_sensor[i]) @ J[6 * a:6 * a + 6]
    return {"errors": errors, "sensitivity_rt": J,
            "sigma_in_covariance": {"ring range bias": {s.topic: consider.ring_range_bias_sigma(problem, i, options)
                                                        for i, s in enumerate(problem.sensors) if s.is_lidar},
                                    "ring elevation": float(np.radians(options.lidar_ring_elevation_deg)),
                                    "lens field": options.camera_lens_field_px}}


def _final_step_sigma(problem, prev, values, rt_sensor, cov_rt) -> float:
    """How far the final LM's last iteration moved the sensor poses, in sigmas (see convergence.step_sigma)."""
    idx = problem.variable_sensors()
    cov_xi = tangent_covariance_from_rt(np.asarray(rt_sensor)[idx], cov_rt) if idx else np.zeros((0, 0))
    return step_sigma(prev, values, [G.sensor_key(i) for i in idx], cov_xi)


def _solve_with_effects(problem, active, rt_sensor, rt_board, sig, options, nominal):
    """Solve with each observation's own board-pose error D (noise.py): the variance components
    (white sigmas, D's sigmas) by VCE on the linearization at the current solution, then LM
    with them; again from there until they are stable. Returns (rt_sensor, rt_board, sig,
    effects, (g, values), the LMs' convergence records, the noise.Linearization at (g, values) or
    None if the last round moved the values, {kept component group: its likelihood-ratio statistic}
    (noise.estimate_components' "lr", decided in the first round))."""
    import gtsam

    effects = N.initial_effects(problem)
    values, iters, lin, lr = None, [], None, {}
    for rnd in range(_MAX_EFFECT_ROUNDS):
        edges = G.lidar_edge_factors(problem, active, rt_sensor, rt_board, options)  # (rebuild remakes the moved)
        g, v = G.build(problem, active, rt_sensor, rt_board, lidar="range", sigma_lidar_m=sig, sigma_camera_px=sig,
                       options=options, board_nominal=nominal, effects=N.effect_sigmas(problem, effects),
                       effect_values=values, edge_factors=edges)
        # which components the data show is decided once, on the first linearization
        at = N.Linearization(problem, g, v)

        def rebuild(p, only=None, rt_sensor=rt_sensor, rt_board=rt_board, sig=sig, effects=effects, values=values,
                    edges=edges):
            return G.build(p, active, rt_sensor, rt_board, lidar="range", sigma_lidar_m=sig, sigma_camera_px=sig,
                           options=options, board_nominal=nominal, effects=N.effect_sigmas(problem, effects),
                           effect_values=values, edge_factors=G.lidar_edge_factors(p, active, rt_sensor, rt_board,
                                                                                   options, reuse=(problem, edges)),
                           only=only)[0]

        # the consider terms' errors are in the data too: D and the white noise get what they leave
        known = consider.known_columns(problem, at, g, rebuild, options)
        try:
            new_sig, new_effects, info = N.estimate_components(problem, at.with_known(*known) if known else at, sig,
                                                               effects, select=rnd == 0)
        except np.linalg.LinAlgError as e:
            raise _singular(e, f"round {rnd}") from None
        lr = info["lr"] if rnd == 0 else lr
        change = max([float(np.max(np.abs(new_sig / sig - 1)))]
                     + [abs(new_effects[i][c] / effects[i][c] - 1) for i in effects for c in effects[i]])
        if change < 0.03 and values is not None:  # weights within 3 %: the estimate stands; the graph
            # gets them, at the same values: its linearization is this one reweighted
            lin = at.reweighted(N.group_weights(at.groups, sig, effects, new_sig, new_effects))
            sig, effects = new_sig, new_effects
            g, values = G.build(problem, active, rt_sensor, rt_board, lidar="range", sigma_lidar_m=sig,
                                sigma_camera_px=sig, options=options, board_nominal=nominal,
                                effects=N.effect_sigmas(problem, effects), effect_values=values, edge_factors=edges)
            break
        sig, effects = new_sig, new_effects
        rt_sensor, rt_board, rec, (g, values) = _lm(problem, active, rt_sensor, rt_board, "range", sig, options,
                                                   nominal, f"observation effects round {rnd}",
                                                   N.effect_sigmas(problem, effects), values, _EFFECT_TOL)
        iters.append(rec)
    log.debug("observation effects: %s", effects)
    return rt_sensor, rt_board, sig, effects, (g, values), iters, lin, lr


def _singular(e: np.linalg.LinAlgError, where: str) -> SolveError:
    """The one-line refusal for a variance-component estimate that met a singular system."""
    cause = (f"one of the per-observation components {', '.join(e.kept)} swallows a direction of the fit"
             if isinstance(e, N.SingularComponents) else "with every per-observation component at its floor")
    return SolveError(f"the noise model's variance components ({where}) met a numerically singular system: "
                      f"{cause}; --set solve.observation_effects=false solves with independent noise")


def _covariance(problem: Problem, g, values, rt_sensor, options) -> np.ndarray:
    """Joint covariance of the non-reference sensors in rt coordinates; DegenerateError if undetermined."""
    import gtsam

    idx = problem.variable_sensors()
    if not idx:
        return np.zeros((0, 0))
    keys = [G.sensor_key(i) for i in idx]
    try:
        marg = gtsam.Marginals(g, values)
    except RuntimeError:  # GTSAM's "Indeterminate linear system": name the free direction
        raise consistency.unobservable_error(problem, consistency.linearize(problem, g, values)) from None
    jm = marg.jointMarginalCovariance(gtsam.KeyVector(keys))
    n = len(keys)
    C = np.zeros((6 * n, 6 * n))
    for a, ka in enumerate(keys):
        for b, kb in enumerate(keys):
            C[6 * a:6 * a + 6, 6 * b:6 * b + 6] = jm.at(ka, kb)
    bad = _beyond_max_stdev(problem, rt_sensor, C, options)
    if bad:
        raise DegenerateError("unobservable: " + "; ".join(f"{b[0]}, 1-sigma {b[1]}" for b in bad)
                              + "; capture board poses that constrain it (tilt the board in different directions)")
    J = np.zeros_like(C)
    for a, i in enumerate(idx):
        J[6 * a:6 * a + 6, 6 * a:6 * a + 6] = drt_dxi(rt_sensor[i])
    C = J @ C @ J.T
    return 0.5 * (C + C.T)


def _beyond_max_stdev(problem: Problem, rt_sensor: np.ndarray, C: np.ndarray, options) -> list:
    """[(sensor and direction in words, its 1-sigma, (6 ns,) the direction in C's tangent)] where a
    sensor's 1-sigma (C: GTSAM's tangent, per-axis angles and metres, the variable sensors in
    order) exceeds ``max_stdev_deg`` / ``max_stdev_m``: the worst direction of each part, turned
    from the sensor's axes into lidar0's."""
    idx = problem.variable_sensors()
    bad = []
    for a, i in enumerate(idx):
        blk = C[6 * a:6 * a + 6, 6 * a:6 * a + 6]
        R = R_from_r(rt_sensor[i][:3])
        for o, lim, what in ((0, np.radians(options.max_stdev_deg), "rotation about"),
                             (3, options.max_stdev_m, "translation along")):
            w, V = np.linalg.eigh(blk[o:o + 3, o:o + 3])
            sd = np.sqrt(max(w[-1], 0.0))
            if sd > lim:
                ax = R @ V[:, -1]
                ax = ax * np.sign(ax[np.argmax(np.abs(ax))])
                unit = f"{sd:.2g} m" if what.startswith("t") else f"{np.degrees(sd):.2g} deg"
                direction = np.zeros(len(C))
                direction[6 * a + o:6 * a + o + 3] = V[:, -1]
                bad.append((f"{problem.sensors[i].topic}: {what} lidar0 ({ax[0]:+.2f}, {ax[1]:+.2f}, {ax[2]:+.2f}) = "
                            f"{consistency.axis_words(ax)}", unit, direction))
    return bad


def _refuse_non_finite(problem: Problem, cov_rt: np.ndarray) -> None:
    """SolveError naming the sensors whose covariance is not finite: every check after it compares
    sigmas (a NaN passes them all), and a pose without its uncertainty is not a result."""
    idx = problem.variable_sensors()
    bad = [problem.sensors[i].topic for a, i in enumerate(idx) if not np.all(np.isfinite(cov_rt[6 * a:6 * a + 6]))]
    if bad:
        raise SolveError(f"{', '.join(bad)}: the pose's covariance is not finite (a numerically singular "
                         "uncertainty computation); no result written")


def _refuse_imprecise(problem: Problem, rt_sensor: np.ndarray, cov_rt: np.ndarray, record: dict, options) -> None:
    """DegenerateError where a sensor's 1-sigma with the consider terms (``cov_rt``, rt coordinates;
    ``record``: consider.add_terms') exceeds max_stdev_m / max_stdev_deg, naming the term that
    makes most of it: the capture does not determine the pose to a usable accuracy."""
    idx = problem.variable_sensors()
    Jinv = np.zeros_like(cov_rt)
    for a, i in enumerate(idx):
        Jinv[6 * a:6 * a + 6, 6 * a:6 * a + 6] = np.linalg.inv(drt_dxi(rt_sensor[i]))
    C = Jinv @ cov_rt @ Jinv.T
    bad = _beyond_max_stdev(problem, rt_sensor, C, options)
    if not bad:
        return
    parts = []
    for words, unit, v in bad:
        var = float(v @ C @ v)
        shares = {name: float(np.sum((np.asarray(cols) @ Jinv.T @ v) ** 2)) / var
                  for name, cols in record["sigma_rt"].items()}
        shares[consider.MODEL_TERM] = 1.0 - sum(shares.values())
        top = max(shares, key=shares.get)
        parts.append(f"{words}, 1-sigma {unit}, {100 * shares[top]:.0f} % of its variance from {top}")
    raise DegenerateError(f"imprecise, no result written: {'; '.join(parts)} (> solve.max_stdev_m "
                          f"{options.max_stdev_m:g} m / max_stdev_deg {options.max_stdev_deg:g} deg: the capture does "
                          f"not determine it to a usable accuracy; --set solve.max_stdev_m=... writes it)")


def calibrate(problem: Problem, options, *, on_estimate: Callable[[Result], None] | None = None) -> Result:
    """Solve ``problem`` with config.SolveOptions ``options`` -> types.Result (module docstring).

    A snapshot that disagrees with the others beyond the consistency check's limit (a wrong
    plane taken for the board, a board that moved during its bag) is left out and the rest solved
    and checked again, up to one snapshot in ten of those used (at least one): each left out is
    tested at the check's family-wise level, so a consistent capture loses one with probability
    ``consistency_alpha``. Each is named in ``rejected`` and the verdict (``left_out``); beyond
    that many, or where a pair of sensors disagrees, the calibration is refused as before.
    """
    left_out: list[tuple[int, str]] = []
    used = len(G.Active.all(problem).boards(problem)[0])
    while True:
        try:
            result = _calibrate_once(problem, options, on_estimate=on_estimate)
        except consistency.Inconsistent as e:
            if e.snapshot is None or len(left_out) >= max(1, used // 10):
                if left_out:
                    raise SolveError(f"{e} (after leaving out {_left_out_words(left_out)})") from None
                raise
            log.info("solve: left out snapshot %d: %s", e.snapshot, e.why)
            left_out.append((e.snapshot, e.why))
            problem = without_snapshots(problem, [e.snapshot], "left out: it " + e.why.split(") ", 1)[-1], "consistency")
            continue
        except (DegenerateError, SolveError) as e:  # the refusal names what was left out before it, on its one line
            if left_out:
                kind = DegenerateError if isinstance(e, DegenerateError) else SolveError
                raise kind(f"{e} (after leaving out {_left_out_words(left_out)})") from None
            raise
        for k, why in left_out:  # warned once answered: a refusal is one line
            log.warning("solve: left out snapshot %d: %s", k, why)
        if left_out:
            result.stats["consistency"]["left_out"] = [{"snapshot": k, "why": why} for k, why in left_out]
        return result


def _left_out_words(left_out) -> str:
    return ", ".join(f"snapshot {k}" for k, _ in left_out) + " that disagreed with the others"


def _calibrate_once(problem: Problem, options, *, on_estimate: Callable[[Result], None] | None = None) -> Result:
    """One solve of ``problem`` (calibrate's, which leaves out disagreeing snapshots around it).

    ``on_estimate(estimate)``: called once the poses, board poses, noise sigmas, residuals and
    rejections are final, before the covariance, jackknife and consistency checks (the last
    second of a solve): ``estimate`` is a Result with those fields as the returned one will have
    them (rejections' reasons aside: api.explain_not_found) and an empty ``covariance_rt``, no
    sectors, stats or jackknife. The solve may still fail after it."""
    t0 = time.perf_counter()
    times, iters = {}, {}
    s = make_seed(problem, options)
    problem = s.problem  # camera corners relabelled where a camera saw the grid turned
    times["seed"] = time.perf_counter() - t0
    rt_sensor, rt_board = s.rt_lidar0_sensor.copy(), s.rt_lidar0_board.copy()
    nominal = s.rt_lidar0_board.copy()
    active = G.Active.all(problem, s.dropped)
    rejected = list(problem.rejected) + list(s.rejected)
    lidars = [i for i, x in enumerate(problem.sensors) if x.kind == "lidar"]
    # one noise sigma per sensor (m for LIDARs, px for cameras): rigs mix LIDAR models
    sig = np.array([options.sigma_lidar_m if x.kind == "lidar" else options.sigma_camera_px for x in problem.sensors],
                   float)

    t = time.perf_counter()
    stages = []  # the convergence record of every LM, in order
    rt_sensor, rt_board, rec, _ = _lm(problem, active, rt_sensor, rt_board, "plane", sig, options, nominal,
                                      "point-to-plane")
    stages.append(rec)
    rt_sensor, rt_board, rec, (g, values) = _lm(problem, active, rt_sensor, rt_board, "range", sig, options,
                                                nominal, "range + camera")
    stages.append(rec)
    iters["plane"], iters["range"] = stages[0]["iterations"], stages[1]["iterations"]
    # the boards' dark squares ranging long where segmentation could not take it out (no
    # intensities): measured on these board poses, taken out; the rounds below solve again
    dark = dark_squares.measure(problem, rt_sensor, rt_board)
    if any(f.significant for f in dark.values()):
        problem = dark_squares.corrected(problem, dark, rt_sensor, rt_board)
        log.info("the boards' dark squares range long: %s; taken out", ", ".join(
            f"{problem.sensors[i].topic} {1e3 * f.offset_m:.1f} mm (+-{1e3 * f.se_m:.1f})"
            for i, f in dark.items() if f.significant))
    times["lm"] = time.perf_counter() - t
    t = time.perf_counter()
    iters["rounds"] = 0
    stable = False
    for rnd in range(_MAX_ROUNDS):
        lid, cam = G.residuals(problem, rt_sensor, rt_board)
        new, before = [], _mask_signature(active)
        if options.reject_outliers:
            robust = _robust_sigmas(problem, active, _per_sensor_residuals(problem, lid, cam, active), options)
            new = _reject(problem, active, lid, cam, robust, options, rt_sensor, rt_board)
            rejected += new
        old = sig.copy()
        if options.reestimate_noise:
            sig = _reestimate(problem, active, _per_sensor_residuals(problem, lid, cam, active), sig, lidars,
                              options.noise_per_sensor)
        stable = not new and _mask_signature(active) == before and np.all(np.abs(sig / old - 1) < 0.01)
        rt_sensor, rt_board, rec, (g, values) = _lm(problem, active, rt_sensor, rt_board, "range", sig, options,
                                                    nominal, f"noise/outlier round {rnd}")
        stages.append(rec)
        iters["rounds"] += 1
        iters[f"round{rnd}"] = rec["iterations"]
        if stable:
            break
    times["noise_and_outliers"] = time.perf_counter() - t
    warnings = [f"LM {r['stage']} did not converge: {r['reason']}" for r in stages if not r["converged"]]
    if stable:
        rounds = {"count": iters["rounds"], "max": _MAX_ROUNDS, "settled": True,
                  "reason": "no new rejections, the same masks and every noise sigma within 1%"}
    else:
        rounds = {"count": iters["rounds"], "max": _MAX_ROUNDS, "settled": False,
                  "reason": f"stopped after {_MAX_ROUNDS} rounds with rejections or noise sigmas still changing"}
        warnings.append(f"the noise re-estimation / outlier rounds did not settle in {_MAX_ROUNDS} rounds "
                        "(the last round's noise and rejections are used)")

    effects, lin, lr = None, None, {}
    if options.observation_effects:
        t = time.perf_counter()
        rt_sensor, rt_board, sig, effects, (g, values), recs, lin, lr = _solve_with_effects(
            problem, active, rt_sensor, rt_board, sig, options, nominal)
        stages += recs
        iters["effects"] = [r["iterations"] for r in recs]
        times["noise_components"] = time.perf_counter() - t

    # the poses, the noise and the masks are final from here on: the residuals and the estimate
    # the final linearization (the noise components' own when it is at these values): the white residuals, the checks
    lin = lin or N.Linearization(problem, g, values)
    lid, cam = G.residuals(problem, rt_sensor, rt_board)
    rl, rc = _active_residuals(lid, cam, active)
    for j, (o, m) in enumerate(zip(problem.lidar_observations, active.lidar)):
        if m is not None and not m.all():
            rejected.append(Rejected(f"{int((~m).sum())} of {len(m)} LIDAR points beyond "
                                     f"{options.outlier_sigma:g} sigma", "outlier", o.sensor, o.snapshot))
    for j, (o, m) in enumerate(zip(problem.camera_observations, active.camera)):
        ok = np.all(np.isfinite(o.corners_px), axis=1)
        if m is not None and not m[ok].all():
            rejected.append(Rejected(f"{int((~m[ok]).sum())} of {int(ok.sum())} corners beyond "
                                     f"{options.outlier_sigma:g} sigma", "outlier", o.sensor, o.snapshot))
    total = g.error(values)
    prior = sum(g.at(f).error(values) for f in range(g.size()) if "PriorFactor" in type(g.at(f)).__name__)
    per = _per_sensor_residuals(problem, lid, cam, active)
    if effects is None:
        z2 = np.concatenate([per[i] / sig[i] for i in sorted(per)]) ** 2 if per else np.zeros(0)
        normalized = float(np.sqrt(np.mean(z2))) if len(z2) else float("nan")
    else:  # white residuals: at each observation's own board pose (its D applied)
        white = [(t[5], t[6]) for t in lin.terms if t[2] is not None and t[2][0] == "white"]
        normalized = float(np.sqrt(sum(q for q, _ in white) / max(sum(n for _, n in white), 1)))
    rms = {"normalized": normalized,
           "lidar_m": float(np.sqrt(np.mean(rl**2))) if len(rl) else float("nan"),
           "camera_px": float(np.sqrt(np.mean(rc**2))) if len(rc) else float("nan")}
    def pooled(ids):  # the sigma of all of one kind's residuals together
        n = np.array([len(per.get(i, ())) for i in ids], float)
        return float(np.sqrt(np.sum(n * sig[ids] ** 2) / n.sum())) if len(ids) and n.sum() else float("nan")

    cams = [i for i in range(len(sig)) if i not in lidars]
    noise = {"lidar_m": pooled(lidars), "camera_px": pooled(cams),
             "per_sensor": {i: float(sig[i]) for i in sorted(per)},
             # per sensor, the sigmas of each observation's own board-pose error (noise.py)
             "observation_effects": {} if effects is None else {i: dict(effects[i]) for i in sorted(per)}}
    if not np.all(np.isfinite(rt_sensor)):
        raise SolveError("the solve produced non-finite sensor poses")
    if on_estimate is not None:  # e.g. the report's pictures of the estimate start drawing (api.calibrate_bags)
        on_estimate(Result(problem=problem, rt_lidar0_sensor=rt_sensor.copy(), covariance_rt=np.zeros((0, 0)),
                           rt_lidar0_board=rt_board.copy(), noise=noise, rms=rms, rejected=tuple(rejected),
                           residuals=_residual_arrays(problem, lid, cam, active)))

    effect_sig = None if effects is None else N.effect_sigmas(problem, effects)
    # made once: a move remakes only those of the observations whose edge rays it moves (a ring
    # elevation's, of one LIDAR)
    edges = G.lidar_edge_factors(problem, active, rt_sensor, rt_board, options)

    def rebuilder(sig, effect_sig):
        def rebuild(p, only=None):  # the final graph of p: the same masks, sigmas and D, other measurements
            return G.build(p, active, rt_sensor, rt_board, lidar="range", sigma_lidar_m=sig, sigma_camera_px=sig,
                           options=options, board_nominal=nominal, effects=effect_sig, effect_values=values,
                           edge_factors=G.lidar_edge_factors(p, active, rt_sensor, rt_board, options,
                                                             reuse=(problem, edges)), only=only)[0]
        return rebuild

    rebuild = rebuilder(sig, effect_sig)
    # what `compare` needs, the units' error sensitivities, by a second process meanwhile (the checks
    # below do not need them; a refusal stops it)
    with TwoProcesses([lambda: _unit_errors(problem, rebuild, values, (g, lin), rt_sensor, options)],
                      what="the units' error sensitivities") as unit_work:
        # a board described otherwise than the sensors see it is named as such, before the checks below
        # blame the capture for its effects
        t = time.perf_counter()
        # the squares first: a pattern printed scaled moves every board along its view, which the
        # board check (which has no scale unknown) would read partly as an offset
        board_check.check_scale(problem, board_check.scale_seen(problem, active, rt_sensor, s.rt_camera_board), options)
        if options.lidar_edges:
            board_check.check_board(problem, board_check.board_seen(problem, g, lin))
        times["board_checks"] = time.perf_counter() - t
        t = time.perf_counter()
        cov = _covariance(problem, g, values, rt_sensor, options)
        times["covariance"] = time.perf_counter() - t
        t = time.perf_counter()

        # the consider terms' errors as columns of the final linearization: the jackknife's expected
        # ratio and the consistency checks count them in
        known = consider.known_columns(problem, lin, g, rebuild, options)
        # the jackknife judges the board-to-board part: it cannot see the common part of errors fixed for the capture
        with_known = lin.with_known(*known) if known else None
        # the components re-estimated without each snapshot where some D is kept: the white sigmas
        # alone rest on thousands of points, one board changes them by nothing
        jk = jackknife(problem, lin, rt_sensor, cov, known=with_known,
                       components=(sig, effects, with_known or lin) if N.any_kept(effects) else None)
        if options.jackknife_floor:  # where the jackknife rejects the model, its spread
            cov = raise_where_rejected(cov, jk)
        times["jackknife"] = time.perf_counter() - t
        t = time.perf_counter()

        terms = consider.consider_terms(problem, rebuild, values, options, nominal=(g, lin))
        cov, uncertainty_terms = consider.add_terms(problem, rt_sensor, cov, terms)
        times["consider"] = time.perf_counter() - t
        _refuse_non_finite(problem, cov)
        _refuse_imprecise(problem, rt_sensor, cov, uncertainty_terms, options)
        final = stages[-1]
        step = _final_step_sigma(problem, final.pop("_last_step"), values, rt_sensor, cov)
        for r in stages:
            r.pop("_last_step", None)
        if not final["converged"]:
            if not step <= MAX_UNCONVERGED_STEP_SIGMA:
                raise SolveError(f"the final solve did not converge ({final['reason']}) and its last step moved the "
                                 f"sensor poses by {step:.2g} sigma: the result cannot be trusted; raise "
                                 f"solve.max_iterations (now {options.max_iterations})")
            warnings.append(f"the final solve did not converge, but its last step moved the sensor poses by only "
                            f"{step:.2g} sigma (<= {MAX_UNCONVERGED_STEP_SIGMA:g}): the result stands")
        convergence = {"converged": not warnings, "final_step_sigma": step, "rounds": rounds,
                       "stages": [public(r) for r in stages], "warnings": warnings}
        t = time.perf_counter()
        # the checks assume only the components shown at p = 1e-3: one kept at 0.01 widens the sigmas,
        # but a refusal needs the stronger evidence (noise.LR_ASSUMED)
        weak = {grp: x for grp, x in lr.items() if x < N.LR_ASSUMED}
        g_c, known_c = g, known
        if weak:
            try:  # estimated as the noise rounds estimated the model's: the consider terms' errors in the data
                sig_c, effects_c = N.without_components(problem, with_known or lin, sig, effects, set(weak))
            except np.linalg.LinAlgError as e:
                raise _singular(e, "without those under the checks' level") from None
            rebuild_c = rebuilder(sig_c, N.effect_sigmas(problem, effects_c))
            g_c = rebuild_c(problem)
            lin_c = lin.reweighted(N.group_weights(lin.groups, sig, effects, sig_c, effects_c))  # the same values
            known_c = consider.known_columns(problem, lin_c, g_c, rebuild_c, options)
        verdict = consistency.verify(problem, g_c, values, alpha=options.consistency_alpha,
                                     refuse=options.refuse_inconsistent, known=known_c)
        verdict["components_not_assumed"] = {N.group_name(problem, grp): round(float(x), 2)
                                             for grp, x in sorted(weak.items())}
        verdict["components_assumed_from"] = {"lr_statistic": N.LR_ASSUMED, "p": N.LR_ASSUMED_P}
        times["consistency"] = time.perf_counter() - t
        t = time.perf_counter()  # the wait for them
        unit_errors = unit_work.results()[0]
        times["unit_error_sensitivities"] = time.perf_counter() - t
    if warnings:  # one line on stderr, once the result stands (a refusal is its own one line); every
        # stage's record is in calibration.yaml and the report
        log.warning("solve: not converged everywhere: %s", "; ".join(warnings))

    times["total"] = time.perf_counter() - t0
    stats = {"stage": "solve", "iterations": iters, "convergence": convergence, "time_s": times, "regularization_share": float(prior / max(total, 1e-300)),
             "n_outlier_points": int(sum(int((~m).sum()) for m in active.lidar if m is not None)),
             "n_rejected_observations": sum(1 for r in rejected if r.stage in ("outlier", "seed")),
             "consistency": verdict, "uncertainty_terms": uncertainty_terms, "unit_errors": unit_errors,
             "dark_squares": {problem.sensors[i].topic: {"offset_mm": 1e3 * f.offset_m, "se_mm": 1e3 * f.se_m,
                                                         "taken_out": f.significant} for i, f in dark.items()}}
    log.info("solve: %d rounds, sigma LIDAR %.4f m, camera %.3f px, %.2f s", iters["rounds"], noise["lidar_m"],
             noise["camera_px"], times["total"])
    return Result(problem=problem, rt_lidar0_sensor=rt_sensor, covariance_rt=cov, rt_lidar0_board=rt_board,
                  noise=noise, rms=rms, rejected=tuple(rejected), stats=stats,
                  residuals=_residual_arrays(problem, lid, cam, active), jackknife=jk)


def _residual_arrays(problem, lid, cam, active) -> dict:
    """Flat residual arrays for the plots (outputs/plots.py)."""
    L = {"lidar_m": [], "lidar_sensor": [], "lidar_snapshot": [], "lidar_outlier": []}
    for o, r, m in zip(problem.lidar_observations, lid, active.lidar):
        if r is None:
            continue
        L["lidar_m"].append(r)
        L["lidar_sensor"].append(np.full(len(r), o.sensor))
        L["lidar_snapshot"].append(np.full(len(r), o.snapshot))
        L["lidar_outlier"].append(np.ones(len(r), bool) if m is None else ~m)
    C = {"camera_px": [], "camera_sensor": [], "camera_snapshot": [], "camera_outlier": []}
    for o, r, m in zip(problem.camera_observations, cam, active.camera):
        if r is None:
            continue
        ok = np.all(np.isfinite(o.corners_px), axis=1)
        rr = r[ok].ravel()
        C["camera_px"].append(rr)
        C["camera_sensor"].append(np.full(len(rr), o.sensor))
        C["camera_snapshot"].append(np.full(len(rr), o.snapshot))
        C["camera_outlier"].append(np.repeat(np.ones(ok.sum(), bool) if m is None else ~m[ok], 2))
    out = {}
    for d, dtypes in ((L, (float, int, int, bool)), (C, (float, int, int, bool))):
        for (k, v), dt in zip(d.items(), dtypes):
            out[k] = np.concatenate(v).astype(dt) if v else np.zeros(0, dt)
    return out
