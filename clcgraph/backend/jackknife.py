"""The leave-one-snapshot-out (jackknife) check of the reported covariance.

Each snapshot (board pose) is left out in turn and the sensor poses re-solved by one
Gauss-Newton step from the final linearization: the snapshot's board and D variables are
marginalized out of the normal equations (noise.Linearization.reduced, a Schur complement),
so leaving snapshot k out is ``dx_k = (S - S_k)^-1 (r - r_k)`` on the sensors only: a few
small solves instead of a re-solve per snapshot. With the per-observation model, the variance
components are re-estimated without the snapshot first (VCE from the solve's values, the same
components kept) and S, r reweighted with them, as a re-solve does: on the real ACFR run 2 one
board alone carried the camera's board-translation component (4.5 mm with it, 0.65 mm
without), and the moves this re-weighting makes were half of the re-solves' spread along the
camera's lateral axis, which the fixed-weight step did not see. The spread of the answers,
``C_jk = (n-1)/n sum_k (x_k - mean)(x_k - mean)^T``, estimates the sensors' covariance
without trusting the noise model; it is compared with the model covariance along the
model's principal axes (per sensor, position in lidar0 and orientation, rt coordinates).
A ratio near 1 says the sigmas can be trusted; the largest single-snapshot move says which
board to re-take.

How near 1 it should be depends on the design: the jackknife overstates the variance of an
unbalanced design (a board of high leverage moves the answer by more than its share), and
along an axis where one board carries most of the information it is a one- or two-sample
estimate. So the model's own prediction is reported beside it: if the model is right, the
move k is linear in the independent parts of the data, ``sum_j T_kj r_j`` with
``r_j ~ N(0, S_j)``, ``T_kj = (S - S_k)^-1 - S^-1`` and ``T_kk = -S^-1``, which gives the
jackknife variance's mean and variance along each axis exactly: the ratio the model expects
(``*_ratio_expected``, ~1.1-1.2 typically) and the range it falls in 95 % of the time
(``*_ratio_expected_95``; Satterthwaite: a scaled chi^2 with ``*_jackknife_dof`` DOF).
A ratio outside that range says the model is wrong along that axis.

Where the ratio is above that range, the model is rejected along that axis and the
covariance is raised there (``raise_where_rejected``): the model variance along the axis times
``(ratio / expected)^2``, so the sigma is what the jackknife measured of the board-to-board
part (the model's own leverage correction kept). Only rejected axes move: on a capture the
model describes, ~2.5 % of the axes, by little; that is the cluster-robust estimate used as a
floor where the data show the model short, not a blanket inflation.

SYNOPSIS
    jk = jackknife(problem, lin, rt_lidar0_sensor, covariance_rt)
    cov = raise_where_rejected(covariance_rt, jk)   # jk["sensors"][i]["position_raised"]: sigma factors
    jk["sensors"][2]["position_ratio"]      # jackknife / model sigma along the 3 principal axes
    jk["sensors"][2]["position_ratio_expected_95"]  # (3,2): its 95 % range if the model is right
    jk["largest_influence"]                  # {"sensor", "snapshot", "position_mm", "orientation_deg"}
"""

from __future__ import annotations

import numpy as np

from ..geometry import drt_dxi

_MIN_SNAPSHOTS = 4  # fewer: the spread says nothing
# A snapshot is indispensable when the others hold less than this share of the information along
# some direction (leaving it out, the answer there is over 1000 sigmas loose)
_INDISPENSABLE = 1e-6


def _axes(C_model: np.ndarray, C_jk: np.ndarray, scale: float, expected_var) -> dict:
    """Per principal axis of C_model: the sigmas, their ratio, and the ratio the model expects:
    ``expected_var(V)`` gives, per column of V, (E, Var) of the jackknife variance along it."""
    from scipy.special import gammaincinv  # not scipy.stats: 1-2 s to import

    lam, V = np.linalg.eigh(C_model)
    V = V * np.sign(V[np.argmax(np.abs(V), axis=0), np.arange(3)])  # each axis' largest component positive
    model = np.sqrt(np.maximum(lam, 0.0))
    jk = np.sqrt(np.maximum(np.einsum("ia,ij,ja->a", V, C_jk, V), 0.0))
    E, var = expected_var(V)
    # Satterthwaite: the jackknife variance ~ E chi2_dof / dof (NaN where rounding left var <= 0)
    dof = np.where(var > 0, 2 * E**2 / np.where(var > 0, var, 1.0), np.nan)
    safe = np.where(model > 0, model, 1.0)
    centre = np.sqrt(np.maximum(E, 0.0)) / safe  # E < 0 is rounding, along a direction one board alone holds
    with np.errstate(invalid="ignore"):  # chi2.ppf's own formula; NaN where dof is not positive
        q = np.stack([np.where(dof > 0, 2 * gammaincinv(dof / 2, p), np.nan) for p in (0.025, 0.975)], axis=1) / dof[:, None]
    return {"axes": V.T, "model": model * scale, "jackknife": jk * scale,
            "ratio": np.where(model > 0, jk / safe, np.nan), "dof": dof,
            "expected": centre, "expected_95": centre[:, None] * np.sqrt(q)}


def kept_share(S: np.ndarray, S_rest: np.ndarray) -> float:
    """The smallest share of the information S that ``S_rest`` holds along any direction: the
    smallest generalized eigenvalue of (S_rest, S), both Jacobi-scaled first (rotations and metres
    put S's diagonal over many decades, and the share is wanted to far below 1e-6)."""
    from scipy.linalg import eigh

    d = 1 / np.sqrt(np.diag(S))
    return float(eigh(d[:, None] * S_rest * d, d[:, None] * S * d, eigvals_only=True, subset_by_index=[0, 0])[0])


def _refit_weights(problem, lin, k, components) -> dict:
    """Group weights (relative to ``lin``'s) of the variance components re-estimated without
    snapshot ``k``: ``components`` = (white sigmas, D's sigmas, the linearization VCE ran on);
    the weights held ({}) where VCE without it meets a singular system."""
    from .noise import estimate_components, group_weights

    sig, effects, on = components
    try:
        sig_k, eff_k, _ = estimate_components(problem, on.without(k), sig, effects, select=False)
    except np.linalg.LinAlgError:  # without it, a component swallows a direction the rest barely holds
        return {}
    return group_weights(lin.groups, sig, effects, sig_k, eff_k)


def jackknife(problem, lin, rt_lidar0_sensor: np.ndarray, covariance_rt: np.ndarray, known=None,
              components=None) -> dict:
    """Leave-one-snapshot-out spread vs the model covariance (module doc); {} if < 4 snapshots.
    ``known``: ``lin`` with the stated consider terms' errors (noise.Linearization.with_known):
    fixed for the capture, they still move each leave-one-out answer by its own amount (a ring
    trend tilts each board by its own b / range), so the expected ratio counts them in.
    ``components``: (white sigmas, D's sigmas, the linearization VCE estimates them on) to
    re-estimate them without each snapshot; None: the weights held. The expected ratio is the
    fixed-weight model's either way: a ratio above its range says the model, the components'
    own uncertainty included, is short along that axis."""
    S, r, parts = lin.reduced()
    if lin.ns == 0 or len(parts) < _MIN_SNAPSHOTS:
        return {}
    x_full = np.linalg.solve(S, r)
    J = np.zeros((lin.ns, lin.ns))  # tangent -> rt, per sensor
    for a, i in enumerate(lin.variable_sensors):
        J[6 * a:6 * a + 6, 6 * a:6 * a + 6] = drt_dxi(rt_lidar0_sensor[i])
    Si = np.linalg.inv(S)
    moves, A, indispensable = {}, {}, []
    for k in sorted(parts):
        S_k, r_k = parts[k]
        # without this board some sensor is not determined: the rest keep under _INDISPENSABLE of the
        # information along some direction (there the leave-one-out answer is 1/sqrt(that) sigmas
        # loose: a rounding-level share, whether Cholesky still passes depends on the machine's BLAS)
        if kept_share(S, S - S_k) < _INDISPENSABLE:
            indispensable.append(k)
            continue
        if components is None:
            moves[k] = J @ (np.linalg.solve(S - S_k, r - r_k) - x_full)
        else:  # the variance components re-estimated without the snapshot, as a re-solve would
            Sw, rw, pw = lin.reduced(_refit_weights(problem, lin, k, components))
            moves[k] = J @ (np.linalg.solve(Sw - pw[k][0], rw - pw[k][1]) - x_full)
        A[k] = np.linalg.inv(S - S_k) - Si
    ks = sorted(moves)
    X = np.array([moves[k] for k in ks])
    n = len(ks)
    if n < _MIN_SNAPSHOTS:
        return {}
    dX = X - X.mean(axis=0)
    C_jk = (n - 1) / n * dX.T @ dX
    # If the model is right, the move k is sum_j T_kj r_j over the independent parts r_j ~ N(0, S_j)
    # (every snapshot, and the rest that is never left out; they sum to S): T_kj = A_k, T_kk = -S^-1.
    # Along a tangent direction u, with b_k = u'A_k, c = u'S^-1, beta_k = b_k - mean(b) and
    # gamma_k = (b_k + c) / n, the deviation from the mean move is a_kj = beta_k + gamma_j - [j = k] n gamma_k
    # (gamma_j = 0 for the parts never left out), so cov(a_k r, a_l r) = sum_j a_kj S_j a_lj' takes
    # O(n^2) products of ns-vectors: no (n, n, ns, ns) tensor.
    A = np.array([A[k] for k in ks])  # (n, ns, ns)
    S_k = np.array([parts[k][0] for k in ks])
    # the known errors c ~ N(0, I) move leaving k out by J ((S - S_k)^-1 (dr - dr_k) - S^-1 dr) per unit
    # (dr/dc: the sensors-to-c block of the augmented normal equations); independent of the r_j
    dev_c = np.zeros((n, lin.ns, 0))
    if known is not None:
        Sa, _, pa = known.reduced()
        ns = lin.ns
        dR = Sa[:ns, ns:]
        mc = np.array([J @ (np.linalg.solve(S - parts[k][0], dR - pa[k][0][:ns, ns:]) - Si @ dR) for k in ks])
        dev_c = mc - mc.mean(axis=0)  # (n, ns, m)

    def expected_var(W):  # W (ns, a): directions in rt -> (E, Var) of the jackknife variance along each
        U = J.T @ W  # tangent
        b = np.einsum("xa,kxy->aky", U, A)  # (a, n, ns)
        c = U.T @ Si  # (a, ns)
        beta = b - b.mean(axis=1, keepdims=True)
        gamma = (b + c[:, None, :]) / n
        g = np.einsum("kxy,aky->akx", S_k, gamma)  # S_k gamma_k
        e = np.einsum("akx,akx->ak", gamma, g)
        h = g.sum(axis=1)  # sum_j S_j gamma_j, (a, ns)
        p = e.sum(axis=1)  # sum_j gamma_j S_j gamma_j
        bh = np.einsum("akx,ax->ak", beta, h)
        cross = beta @ g.transpose(0, 2, 1)  # beta_k . g_l
        cov = (beta @ S @ beta.transpose(0, 2, 1) + bh[:, :, None] + bh[:, None, :] + p[:, None, None]
               - n * (cross + cross.transpose(0, 2, 1)) - n * (e[:, :, None] + e[:, None, :])
               + n**2 * e[:, :, None] * np.eye(n))
        a_c = np.einsum("xa,kxc->akc", W, dev_c)  # the known errors' part, along each direction
        cov = (n - 1) / n * (cov + a_c @ a_c.transpose(0, 2, 1))  # of the moves' deviations along each, (a, k, l)
        return np.einsum("akk->a", cov), 2 * np.einsum("akl,alk->a", cov, cov)

    sensors, worst = {}, None
    for a, i in enumerate(lin.variable_sensors):
        blk = slice(6 * a, 6 * a + 6)
        Cm, Cj = np.asarray(covariance_rt)[blk, blk], C_jk[blk, blk]
        def along(part):
            def f(V):
                W = np.zeros((lin.ns, 3))
                W[6 * a + part.start:6 * a + part.stop] = V
                return expected_var(W)
            return f

        pos = _axes(Cm[3:, 3:], Cj[3:, 3:], 1e3, along(slice(3, 6)))
        rot = _axes(Cm[:3, :3], Cj[:3, :3], np.degrees(1.0), along(slice(0, 3)))
        dp = np.linalg.norm(X[:, 6 * a + 3:6 * a + 6], axis=1) * 1e3
        dr = np.degrees(np.linalg.norm(X[:, 6 * a:6 * a + 3], axis=1))
        m = int(np.argmax(dp))
        big = {"snapshot": int(ks[m]), "position_mm": float(dp[m]), "orientation_deg": float(dr[m])}
        sensors[i] = {"position_axes": pos["axes"], "position_model_mm": pos["model"],
                      "position_jackknife_mm": pos["jackknife"], "position_ratio": pos["ratio"],
                      "position_ratio_expected": pos["expected"], "position_ratio_expected_95": pos["expected_95"],
                      "position_jackknife_dof": pos["dof"],
                      "orientation_axes": rot["axes"], "orientation_model_deg": rot["model"],
                      "orientation_jackknife_deg": rot["jackknife"], "orientation_ratio": rot["ratio"],
                      "orientation_ratio_expected": rot["expected"], "orientation_ratio_expected_95": rot["expected_95"],
                      "orientation_jackknife_dof": rot["dof"],
                      "largest_influence": big}
        if worst is None or big["position_mm"] > worst["position_mm"]:
            worst = {"sensor": i, **big}
    method = "one-step Gauss-Newton from the final linearization, one snapshot left out at a time" + (
        "" if components is None else ", the variance components re-estimated without it")
    return {"method": method,
            "n_snapshots": n, "indispensable_snapshots": indispensable, "covariance_rt": C_jk,
            "moves_rt": {int(k): moves[k] for k in ks}, "sensors": sensors, "largest_influence": worst}


def raise_where_rejected(covariance_rt: np.ndarray, jk: dict) -> np.ndarray:
    """``covariance_rt`` raised along each principal axis whose jackknife ratio is above the
    range the model expects (module doc): its variance times (ratio / expected)^2. Records the
    sigma factor per axis in ``jk["sensors"][i]["position_raised"]`` / ``"orientation_raised"``
    (1: the model's sigma kept) and what was added in ``jk["floor_rt"]``. ``jk`` empty: the
    covariance as it is."""
    C = np.array(covariance_rt, float)
    before = C.copy()
    for a, (i, s) in enumerate(sorted(jk.get("sensors", {}).items())):
        for what, o in (("orientation", 0), ("position", 3)):
            ratio, expected = np.asarray(s[f"{what}_ratio"]), np.asarray(s[f"{what}_ratio_expected"])
            hi = np.asarray(s[f"{what}_ratio_expected_95"])[:, 1]
            with np.errstate(invalid="ignore"):
                rejected = np.isfinite(ratio) & np.isfinite(hi) & (expected > 0) & (ratio > hi)
            factor = np.where(rejected, ratio / np.where(expected > 0, expected, 1.0), 1.0)
            blk = slice(6 * a + o, 6 * a + o + 3)
            V = np.asarray(s[f"{what}_axes"])  # rows: the model's principal axes
            var = np.einsum("ax,xy,ay->a", V, C[blk, blk], V)
            C[blk, blk] += (V.T * ((factor**2 - 1) * var)) @ V
            s[f"{what}_raised"] = factor
    C = 0.5 * (C + C.T)
    if jk:
        jk["floor_rt"] = C - before
    return C
