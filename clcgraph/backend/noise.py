"""The noise model with a per-observation part, and its variance components from the data.

Real errors are correlated within one observation: a LIDAR's per-ring range bias and
beam-elevation error, a board that is not flat, mixed pixels along its edge, a corner
detector's bias for a whole board, lens-model error at the same image position. So the
1000 points of one board are not 1000 independent facts. The model (docs/uncertainty.md):

    residual = white noise (sigma per sensor, m or px)
             + the effect of D, this observation's own board-pose error

D is a Pose3 variable per (sensor, snapshot) observation (graph.effect_key) at the board's
centre, with a zero-mean prior of per-sensor sigmas: for a LIDAR its plane tilt (omega_x,
omega_y) and offset (v_z), the only DOFs a plane sees (the in-plane ones pinned at zero); for
a camera all six (board-pose jitter): its tilt (omega_x, omega_y), which trades off against a
LIDAR's plane tilt, apart from its spin (omega_z), which only the LIDAR's outline sees.
Marginalizing D gives each factor the covariance sigma^2 I + J_D Sigma_D J_D^T; keeping D as a
variable keeps the graph sparse and gtsam's Marginals exact.

The variance components (per sensor: white sigma; LIDAR tilt, offset; camera tilt, spin,
translation) are estimated by Foerstner's iterative variance-component estimation (as the
targetless graph does): sigma_c^2 <- v_c^T W_c v_c / r_c, with r_c = n_c - tr(W_c A_c Cov A_c^T)
the redundancy of group c, on the linearization at the solution, then re-solved. Its fixed
point is the restricted-likelihood (REML) estimate; a component is kept only if the REML
likelihood-ratio test against "every D at its floor" shows it (p < 0.01 per component; the
consistency checks assume those at p < 1e-3: ``without_components``), so independent noise
keeps the independent model's sigmas.

SYNOPSIS
    lin = Linearization(problem, g, values)          # per-factor Jacobians, grouped
    sig, effects, info = estimate_components(problem, lin, sig, effects)
    sig_c, effects_c = without_components(problem, lin, sig, effects, drop)  # e.g. those under LR_ASSUMED
    S, r = lin.reduced()                              # sensor-only information (Schur)
"""

from __future__ import annotations

import functools
import logging

import numpy as np

from ..two_processes import TwoProcesses
from . import graph as G

log = logging.getLogger(__name__)

# D's DOFs (board-centre tangent [omega, v]) each variance component covers
LIDAR_COMPONENTS = {"tilt_rad": (0, 1), "offset_m": (5,)}
CAMERA_COMPONENTS = {"tilt_rad": (0, 1), "spin_rad": (2,), "translation_m": (3, 4, 5)}
# The prior sigma of D's DOFs a LIDAR cannot see (in-plane): pinned at zero. Loose, they are
# not free: with the plane tilted by D, an in-plane shift of the centre moves the plane
# (second order), and a LIDAR's D wandered there (leave-one-out re-solves on the real ACFR
# run 2 moved the camera 2.4x more than the linearized jackknife said).
_UNSEEN = 1e-4
# Where VCE starts (a real board's plane is good to ~1 mrad / a few mm) and the floor: below
# these a component adds nothing to the covariance, and an exact prior would be singular.
_START = {"tilt_rad": 1e-3, "offset_m": 3e-3, "spin_rad": 1e-3, "translation_m": 3e-3}
_FLOOR = {"tilt_rad": 1e-4, "offset_m": 1e-4, "spin_rad": 1e-4, "translation_m": 1e-4}
_MIN_REDUNDANCY = 0.5  # a component the data hardly see keeps its value
# Likelihood-ratio statistic (-2 log, REML) a component must reach to be kept: a variance on
# the boundary (zero) has the null distribution 0.5 chi2_0 + 0.5 chi2_1, so 5.41 is p = 0.01
# per component. A real component dropped leaves the sigmas short (stress tails-dark-mixed: LR
# 9.1, dropped at p = 1e-3, 3.9 sigma off); one kept by chance makes them larger (1 of 94
# independent-noise trials at this level, 1.3x on its axes). The consistency checks assume only
# the components at LR_ASSUMED (p = 1e-3): one kept by chance can make a good capture look
# unverifiable, and a refusal needs the stronger evidence (docs/uncertainty.md, "The test's level").
_LR_CRITICAL = 5.41
LR_ASSUMED = 9.55
LR_ASSUMED_P = 1e-3  # LR_ASSUMED's level (calibration.yaml and the report state both)
_MAX_VCE_ITERATIONS = 40
_VCE_TOL = 0.003  # relative change of every sigma


def components(problem) -> dict:
    """{sensor: {component name: DOFs of D}}."""
    return {i: dict(LIDAR_COMPONENTS if s.is_lidar else CAMERA_COMPONENTS) for i, s in enumerate(problem.sensors)}


def initial_effects(problem) -> dict:
    """{sensor: {component: sigma}} where VCE starts."""
    return {i: {c: _START[c] for c in comp} for i, comp in components(problem).items()}


def any_kept(effects: dict | None) -> bool:
    """Whether some D component is above its floor (the data showed it)."""
    return any(s > _FLOOR[c] * (1 + 1e-9) for e in (effects or {}).values() for c, s in e.items())


def group_weights(groups, sig: np.ndarray, effects: dict, new_sig: np.ndarray, new_effects: dict) -> dict:
    """{group: weight} that turns a Linearization built with (``sig``, ``effects``) into one with
    (``new_sig``, ``new_effects``) (Linearization.reweighted, reduced): each group's old variance
    over its new one."""
    return {g: float((sig[g[1]] / new_sig[g[1]]) ** 2) if g[0] == "white"
            else float((effects[g[1]][g[2]] / new_effects[g[1]][g[2]]) ** 2) for g in groups}


def effect_sigmas(problem, effects: dict) -> np.ndarray:
    """(Nsensors,6) prior sigmas of D for graph.build from {sensor: {component: sigma}}."""
    out = np.full((len(problem.sensors), 6), _UNSEEN)
    for i, comp in components(problem).items():
        for c, dofs in comp.items():
            out[i, list(dofs)] = effects[i][c]
    return out


def _jacobi(diagonal: np.ndarray) -> np.ndarray:
    """1 / sqrt of a normal matrix's diagonal (its Jacobi scaling); LinAlgError where a diagonal
    entry is not positive and finite: such a matrix is not positive definite, as the Cholesky
    after it would say (rounding can leave a singular Schur complement slightly negative, and
    the NaN of its sqrt would pass the Cholesky and every comparison after it)."""
    if not np.all((diagonal > 0) & np.isfinite(diagonal)):
        raise np.linalg.LinAlgError("normal matrix not positive definite (a diagonal entry <= 0 or not finite)")
    return 1.0 / np.sqrt(diagonal)


def _inv(M: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite M, Jacobi-scaled (its scales span 1e-8..1e10)."""
    d = _jacobi(np.diag(M))
    return d[:, None] * np.linalg.inv(d[:, None] * M * d[None, :]) * d[None, :]


class Linearization:
    """The solve's Gauss-Newton system at ``values``, per factor and per snapshot.

    Variables: the sensors (``variable_sensors`` order, 6 each) and, per snapshot k, its local
    variables (board k and the D of its observations), which no other snapshot touches. Each
    factor is kept as terms (snapshot or None, columns, group, A^T A, A^T b, b^T b, rows) in
    gtsam's whitening at ``values``; ``weights`` rescale groups (VCE) without relinearizing.
    Groups: ("white", sensor), ("effect", sensor, component), or None (priors, fixed).
    ``rows``: per term (factor index, whitened A, b); ``factors``: per factor of ``g`` (its
    sensor, problem.reference for lidar0's, None for a prior; its snapshot or None; its columns;
    the slice of its terms), so the consider terms need not decode or relinearize it again.
    """

    def __init__(self, problem, g, values):
        self.variable_sensors = problem.variable_sensors()
        self.ns = 6 * len(self.variable_sensors)
        obs = {G.effect_key("lidar", j): o for j, o in enumerate(problem.lidar_observations)}
        obs.update({G.effect_key("camera", j): o for j, o in enumerate(problem.camera_observations)})
        self._context = ({G.sensor_key(i): 6 * a for a, i in enumerate(self.variable_sensors)},
                         {k: (o.sensor, o.snapshot) for k, o in obs.items()}, components(problem), problem.reference,
                         {})  # sensor key -> column; D key -> (sensor, snapshot); components; lidar0; decoded keys
        self.values = values
        self.local: dict[int, dict] = {}  # snapshot -> {key: column offset after the sensors}
        self.terms = []
        self.rows = []  # per term: (factor index, its whitened A, b), for with_known
        self.factors = []  # per factor: (sensor or None for a prior, snapshot or None, columns, its terms' slice)
        for f in range(g.size()):
            terms, rows, record = self._linearize(f, g.at(f), values)
            self.factors.append((*record, slice(len(self.terms), len(self.terms) + len(terms))))
            self.terms += terms
            self.rows += rows
        self.groups = sorted({t[2] for t in self.terms if t[2] is not None}, key=str)

    def _linearize(self, f: int, factor, values):
        """Factor ``f``'s terms and rows, and its (sensor, snapshot, columns); new snapshots' and
        keys' columns are added to ``local`` in the order they are met."""
        import gtsam

        sensor_col, effect_of, comp, reference, symbols = self._context
        lin = factor.linearize(values)
        A, b = lin.jacobian()
        keys = list(lin.keys())
        syms = [symbols[k] if k in symbols else symbols.setdefault(k, gtsam.Symbol(k)) for k in keys]
        chars = [chr(s.chr()) for s in syms]
        effect = next((k for k, c in zip(keys, chars) if c in "de"), None)
        snapshot = effect_of[effect][1] if effect is not None else \
            next((int(s.index()) for s, c in zip(syms, chars) if c == "b"), None)
        if snapshot is not None:
            loc = self.local.setdefault(snapshot, {})
            for k, c in zip(keys, chars):
                if c in "bde" and k not in loc:
                    loc[k] = 6 * len(loc)
        cols = np.concatenate([np.arange(6) + (sensor_col[k] if c == "s" else self.ns + self.local[snapshot][k])
                               for k, c in zip(keys, chars)])
        is_prior = "PriorFactor" in type(factor).__name__
        if effect is not None and is_prior:  # D's prior: rows are D's DOFs, one group per component
            i = effect_of[effect][0]
            rows_of = {("effect", i, c): list(d) for c, d in comp[i].items()}
            rows_of[None] = [d for d in range(6) if not any(d in x for x in comp[i].values())]
        elif effect is not None:
            rows_of = {("white", effect_of[effect][0]): None}  # None: every row (no copy of A)
        else:
            rows_of = {None: None}
        terms, rows = [], []
        for group, r in rows_of.items():
            Ar, br = (A, b) if r is None else (A[r], b[r])
            n = int(np.count_nonzero(np.any(Ar != 0, axis=1)))  # masked corners are zero rows
            terms.append((snapshot, cols, group, Ar.T @ Ar, Ar.T @ br, float(br @ br), n))
            rows.append((f, Ar if r is None else None, br if r is None else None))
        sensors = [int(s.index()) for s, c in zip(syms, chars) if c == "s"]
        sensor = None if is_prior else (sensors[0] if sensors else reference)
        return terms, rows, (sensor, snapshot, cols)

    def relinearized(self, factors: dict) -> "Linearization":
        """The system with the given factors ({index: factor} of the same graph but for those
        factors' measurements: same keys, values and noise models) in place of its own, the
        others' terms shared: what a fresh linearization of that graph gives, evaluating only them."""
        out = object.__new__(Linearization)
        out.variable_sensors, out.ns, out.local, out.groups = self.variable_sensors, self.ns, self.local, self.groups
        out._context, out.factors, out.values = self._context, self.factors, self.values
        out._layout_cache = self._layout()
        out.terms, out.rows = list(self.terms), list(self.rows)
        for f, factor in factors.items():
            terms, rows, _ = self._linearize(f, factor, self.values)
            span = self.factors[f][3]
            out.terms[span], out.rows[span] = terms, rows
        return out

    def reweighted(self, weights: dict) -> "Linearization":
        """The same system with groups rescaled (``{group: w}``, w = (old sigma / new sigma)^2):
        what a fresh linearization at the same values with the new sigmas gives, without
        evaluating the factors again."""
        out = object.__new__(Linearization)
        out.variable_sensors, out.ns, out.local, out.groups = self.variable_sensors, self.ns, self.local, self.groups
        out._context, out.factors, out.values = self._context, self.factors, self.values
        out._layout_cache = getattr(self, "_layout_cache", None)
        out.terms, out.rows = [], None if self.rows is None else []
        for t, (snapshot, cols, group, AtA, Atb, btb, rows) in enumerate(self.terms):
            w = 1.0 if group is None else weights.get(group, 1.0)
            out.terms.append((snapshot, cols, group, w * AtA, w * Atb, w * btb, rows))
            if self.rows is not None:
                f, A, b = self.rows[t]
                out.rows.append((f, None if A is None else np.sqrt(w) * A, None if b is None else np.sqrt(w) * b))
        if getattr(self, "_batch_cache", None) is not None:
            out._batch_cache = _reweighted_batches(self._batch_cache, self._weights(self._batch_cache[0], weights))
        return out

    def without(self, snapshot: int) -> "Linearization":
        """The system with ``snapshot``'s terms left out (its board and D's with them): what the
        jackknife re-estimates the variance components on."""
        out = object.__new__(Linearization)
        out.variable_sensors, out.ns, out.groups = self.variable_sensors, self.ns, self.groups
        out._context, out.values = getattr(self, "_context", None), getattr(self, "values", None)
        out.local = {k: v for k, v in self.local.items() if k != snapshot}
        keep = [t for t, term in enumerate(self.terms) if term[0] != snapshot]
        out.terms = [self.terms[t] for t in keep]
        out.rows = None if self.rows is None else [self.rows[t] for t in keep]
        out.factors = None
        return out

    def with_known(self, db: dict, m: int) -> "Linearization":
        """The system with ``m`` errors of known variance c ~ N(0, I) added as random effects
        shared by every snapshot (the consider terms: errors fixed for the capture), for the
        variance components only: ``db`` {factor index: (rows, m) change of its whitened b per
        unit c}. c is appended to the sensors' columns (global, like them) with its unit prior
        (fixed weight), so the REML and VCE give D and the white noise only what c does not
        explain; D's sigmas estimated without c take the part of a fixed error that looks
        different on each board (a ring trend tilts each board by its own amount) and the
        consider term then adds it again (docs/uncertainty.md). A factor's G scales with its
        group's weight like its A: it is whitened by the same sigma."""
        out = object.__new__(Linearization)
        ns = self.ns + m
        out.variable_sensors, out.ns, out.local, out.groups = self.variable_sensors, ns, self.local, self.groups
        out.rows = None
        c = np.arange(self.ns, ns)
        out.terms = []
        for (snapshot, cols, group, AtA, Atb, btb, n), (f, A, b) in zip(self.terms, self.rows):
            cols = np.where(cols >= self.ns, cols + m, cols)
            G = db.get(f) if A is not None else None
            if G is None:
                out.terms.append((snapshot, cols, group, AtA, Atb, btb, n))
                continue
            AtG = A.T @ G
            out.terms.append((snapshot, np.r_[cols, c], group, np.block([[AtA, AtG], [AtG.T, G.T @ G]]),
                              np.r_[Atb, G.T @ b], btb, n))
        out.terms.append((None, c, None, np.eye(m), np.zeros(m), 0.0, 0))
        return out

    def _layout(self):
        """Where _batches puts each term's numbers: (groups, {size: the snapshots}, the sensor-only
        terms, {size: (its terms, M's and v's row and group indices, btb's and rows' (group,
        snapshot) indices)}). It depends on the terms' snapshots, columns and groups only, so the
        relinearized and reweighted copies share it."""
        if getattr(self, "_layout_cache", None) is None:
            ns = self.ns
            groups = [None, *self.groups]
            gi = {g: a for a, g in enumerate(groups)}
            by_size: dict = {}
            for k in sorted(self.local):
                by_size.setdefault(len(self.local[k]), []).append(k)
            where = {k: (size, b) for size, ks in by_size.items() for b, k in enumerate(ks)}
            parts = {size: ([], [], [], [], [], []) for size in by_size}  # terms, M rows, v rows; group, size per term; snapshot
            alone = []
            for t, (snapshot, cols, group, AtA, _, _, _) in enumerate(self.terms):
                if snapshot is None:
                    alone.append(t)
                    continue
                size, b = where[snapshot]
                n = ns + 6 * size
                e = parts[size]
                e[0].append(t)
                e[1].append(((b * n + cols[:, None]) * n + cols[None, :]).ravel())
                e[2].append(b * n + cols)
                e[3].append(gi[group])
                e[4].append(len(cols))
                e[5].append(b)
            layout = {}
            for size, (ts, Mr, vr, ga, nc, bs) in parts.items():
                ga, nc = np.array(ga), np.array(nc)
                layout[size] = (ts, np.concatenate(Mr), np.repeat(ga, nc * nc), np.concatenate(vr), np.repeat(ga, nc),
                                (ga, np.array(bs)))
            self._layout_cache = (groups, by_size, alone, layout)
        return self._layout_cache

    def _batches(self):
        """The normal equations split by group, so reweighting is a weighted sum, built once:
        [(snapshots, n, M (K*n*n, G), v (K*n, G), M^T, v^T, btb (G,K), rows (G,K))] per size of the
        snapshots' locals (n = sensors + locals; M, v scipy.sparse: a group touches one
        sensor's, one board's and one D's columns), and the sensor-only (groups, M0 (G,ns,ns),
        v0 (G,ns), btb (G,), rows (G,)) of the factors no snapshot holds."""
        if getattr(self, "_batch_cache", None) is None:
            from scipy.sparse import csr_matrix

            ns = self.ns
            groups, by_size, alone, layout = self._layout()
            gi = {g: a for a, g in enumerate(groups)}
            M0, v0 = np.zeros((len(groups), ns, ns)), np.zeros((len(groups), ns))
            btb0, rows0 = np.zeros(len(groups)), np.zeros(len(groups))
            for t in alone:
                _, cols, group, AtA, Atb, bb, nrows = self.terms[t]
                a = gi[group]
                M0[a][np.ix_(cols, cols)] += AtA
                v0[a][cols] += Atb
                btb0[a] += bb
                rows0[a] += nrows
            batches = []
            for size, ks in sorted(by_size.items()):
                n = ns + 6 * size
                ts, Mr, Mg, vr, vg, at = layout[size]
                terms = [self.terms[t] for t in ts]
                M = csr_matrix((np.concatenate([x[3].ravel() for x in terms]), (Mr, Mg)),
                               shape=(len(ks) * n * n, len(groups)))  # duplicates summed
                v = csr_matrix((np.concatenate([x[4] for x in terms]), (vr, vg)), shape=(len(ks) * n, len(groups)))
                btb, rows = np.zeros((len(groups), len(ks))), np.zeros((len(groups), len(ks)))
                np.add.at(btb, at, [x[5] for x in terms])  # in the terms' order, like a loop
                np.add.at(rows, at, [x[6] for x in terms])
                batches.append((ks, n, M, v, M.T.tocsr(), v.T.tocsr(), btb, rows))  # .T once: it copies
            self._batch_cache = (groups, batches, (M0, v0, btb0, rows0))
        return self._batch_cache

    def _weights(self, groups, weights) -> np.ndarray:
        return np.array([1.0 if g is None else weights.get(g, 1.0) for g in groups])

    def _eliminate(self, M, v):
        """The snapshots' locals out of stacked (K,n,n), (K,n): (their sum of the sensor-only
        information and vector, the locals' inverses iL (K,nl,nl), B = M[:, :ns, ns:], the
        locals' log-determinants summed). Jacobi-scaled like _inv (scales span 1e-8..1e10)."""
        ns = self.ns
        L, B = M[:, ns:, ns:], M[:, :ns, ns:]
        d = _jacobi(np.diagonal(L, axis1=1, axis2=2))
        Ls = d[:, :, None] * L * d[:, None, :]
        logdet = 2 * np.sum(np.log(np.diagonal(np.linalg.cholesky(Ls), axis1=1, axis2=2)), axis=1) - 2 * np.sum(np.log(d), axis=1)
        iL = d[:, :, None] * np.linalg.inv(Ls) * d[:, None, :]
        K = B @ iL
        S_k = M[:, :ns, :ns] - K @ B.transpose(0, 2, 1)
        r_k = v[:, :ns] - np.einsum("kij,kj->ki", K, v[:, ns:])
        return S_k, r_k, iL, B, logdet

    def reduced(self, weights=None):
        """(S, r, {snapshot: (S_k, r_k)}): sensor-only normal equations S dx = r, the boards and
        D marginalized out (Schur), and each snapshot's share of them."""
        groups, batches, (M0g, v0g, _, _) = self._batches()
        wv = self._weights(groups, weights or {})
        S, r = np.einsum("g,gij->ij", wv, M0g), wv @ v0g
        parts = {}
        for ks, n, Mg, vg, *_ in batches:
            S_k, r_k, _, _, _ = self._eliminate((Mg @ wv).reshape(len(ks), n, n), (vg @ wv).reshape(len(ks), n))
            parts.update({k: (S_k[b], r_k[b]) for b, k in enumerate(ks)})
        S = S + sum((p[0] for p in parts.values()), np.zeros_like(S))
        r = r + sum((p[1] for p in parts.values()), np.zeros_like(r))
        return S, r, parts

    def solve_and_trace(self, weights, trace: bool = True):
        """(stats, m2l): per group, (n rows, v^T W v at the step's solution, tr(W A Cov A^T)) for
        VCE (the trace 0 unless ``trace``); and -2 log of the restricted (REML) likelihood of the
        weights, up to a constant: ``-sum_g n_g log w_g + log det N + v^T W v`` (N the normal
        matrix of every variable; the D's are the random effects, their priors the rows of G^-1).
        Vectorized over the snapshots (their local blocks stacked by size): per group, v^T W v
        and the trace are the group's (sparse) normal matrix against x x^T and the covariance."""
        ns = self.ns
        groups, batches, (M0g, v0g, btb0, rows0) = self._batches()
        wv = self._weights(groups, weights)
        S, r = np.einsum("g,gij->ij", wv, M0g), wv @ v0g
        logdet, solved = 0.0, []
        for ks, n, Mg, vg, *_ in batches:
            M, v = (Mg @ wv).reshape(len(ks), n, n), (vg @ wv).reshape(len(ks), n)
            S_k, r_k, iL, B, ld = self._eliminate(M, v)
            logdet += float(np.sum(ld))
            S, r = S + np.sum(S_k, axis=0), r + np.sum(r_k, axis=0)
            solved.append((v, B, iL))
        Css = _inv(S) if ns else np.zeros((0, 0))
        logdet += _logdet(S) if ns else 0.0
        dx_s = Css @ r
        q = np.einsum("gi,i->g", np.einsum("gij,j->gi", M0g, dx_s), dx_s) - 2 * v0g @ dx_s + btb0
        tr = np.einsum("gij,ij->g", M0g, Css) if trace else np.zeros(len(groups))
        nrows = rows0.copy()
        for (ks, n, _, _, MgT, vgT, btbg, rowsg), (v, B, iL) in zip(batches, solved):
            dx_l = np.einsum("kij,kj->ki", iL, v[:, ns:] - np.einsum("kji,j->ki", B, dx_s))
            x = np.concatenate([np.broadcast_to(dx_s, (len(dx_l), ns)), dx_l], axis=1)
            q = q + MgT @ (x[:, :, None] * x[:, None, :]).ravel() - 2 * (vgT @ x.ravel()) + np.sum(btbg, axis=1)
            if trace:  # each snapshot's covariance over [sensors, its locals]
                C_ls = -iL @ B.transpose(0, 2, 1) @ Css
                C = np.empty((len(ks), n, n))
                C[:, :ns, :ns], C[:, ns:, :ns], C[:, :ns, ns:] = Css, C_ls, C_ls.transpose(0, 2, 1)
                C[:, ns:, ns:] = iL - C_ls @ B @ iL
                tr = tr + MgT @ C.ravel()
            nrows = nrows + np.sum(rowsg, axis=1)
        q, tr = wv * q, wv * tr
        m2l = logdet + float(np.sum(q)) - float(np.sum(nrows[1:] * np.log(wv[1:])))
        out = {g: [int(nrows[a]), float(q[a]), float(tr[a])] for a, g in enumerate(groups) if g is not None}
        return out, m2l


def _reweighted_batches(cache, wv: np.ndarray):
    """Linearization._batches' cache with group g's columns scaled by wv[g]: the batches of the
    reweighted terms without assembling them again (the same numbers up to rounding)."""
    from scipy.sparse import diags

    groups, batches, (M0, v0, btb0, rows0) = cache
    W = diags(wv)
    out = [(ks, n, (M @ W).tocsr(), (v @ W).tocsr(), (W @ MT).tocsr(), (W @ vT).tocsr(), btb * wv[:, None], rows)
           for ks, n, M, v, MT, vT, btb, rows in batches]
    return groups, out, (M0 * wv[:, None, None], v0 * wv[:, None], btb0 * wv, rows0)


def _logdet(M: np.ndarray) -> float:
    """log det of a symmetric positive definite M, Jacobi-scaled like _inv."""
    d = _jacobi(np.diag(M))
    return float(2 * np.sum(np.log(np.diag(np.linalg.cholesky(d[:, None] * M * d[None, :])))) - 2 * np.sum(np.log(d)))


def _vce(lin: Linearization, w: dict, free: set, base: dict, floor: dict):
    """Foerstner's iteration from weights ``w`` (a REML fixed point): the white groups and the
    effect groups in ``free`` re-estimated, the others held. -> (w, redundancies, -2 log L_REML)."""
    w, red = dict(w), {}
    for _ in range(_MAX_VCE_ITERATIONS):
        stats, _ = lin.solve_and_trace(w)
        change = 0.0
        for g, (n, q, tr) in stats.items():
            red[g] = n - tr
            if (g[0] == "effect" and g not in free) or red[g] < _MIN_REDUNDANCY or q <= 0:
                continue
            w_new = min(w[g] * red[g] / q, (base[g] / floor[g]) ** 2)
            change = max(change, abs(np.sqrt(w[g] / w_new) - 1))
            w[g] = w_new
        if change < _VCE_TOL:
            break
    return w, red, lin.solve_and_trace(w)[1]


def _profile(lin: Linearization, w: dict, g, base: dict, floor: dict) -> float:
    """min over component g's sigma of -2 log L_REML, the other weights held at ``w``: on a
    log grid (3 per decade from the floor to 1000x it: 0.1 m or rad), then Foerstner's iteration
    from the best point."""
    grid = floor[g] * 10.0 ** (np.arange(1, 10) / 3.0)
    m2l = [_m2l_or_inf(lambda: lin.solve_and_trace({**w, g: (base[g] / s) ** 2}, trace=False)[1]) for s in grid]
    best = int(np.argmin(m2l))
    if best == 0 or not np.isfinite(m2l[best]):  # at the floor end (or nowhere positive definite): nothing to find
        return float(m2l[best])
    return min(float(m2l[best]), _m2l_or_inf(lambda: _vce(lin, {**w, g: (base[g] / grid[best]) ** 2}, {g}, base,
                                                           floor)[2]))


def _m2l_or_inf(evaluate) -> float:
    """-2 log L_REML from ``evaluate()``, or +inf where the normal matrix at those weights is not
    positive definite (numerically singular: a component's sigma so large that its effects
    swallow a direction of the fit, which rounding can leave with a negative diagonal: _jacobi
    raises; an infinite sigma, whose weight's log is -inf): no likelihood there, so the profile
    never picks it (a NaN would: argmin takes it)."""
    try:
        with np.errstate(divide="raise", invalid="raise"):
            return float(evaluate())
    except (np.linalg.LinAlgError, FloatingPointError):
        return float("inf")


def estimate_components(problem, lin: Linearization, sig: np.ndarray, effects: dict, *, select: bool = True):
    """REML variance components on ``lin`` (built with white sigmas ``sig`` and ``effects``):
    new (sig (Nsensors,), effects {sensor: {component: sigma}}, info {"redundancy": {group: r},
    "lr": {group: likelihood-ratio statistic of the components kept}}). ``select=False``:
    re-estimate the components above their floor, keep the others there (no tests)."""
    base, floor = _base_and_floor(problem, lin, sig, effects)
    at_floor = {g: (base[g] / floor[g]) ** 2 for g in base if g[0] == "effect"}
    # A component is kept only if the data show it: its restricted likelihood-ratio statistic
    # against the model with every D at its floor (the white sigmas re-estimated, the other
    # components held there) must reach _LR_CRITICAL. Each is tested alone, so two components
    # that explain the same thing (a LIDAR's plane tilt and a camera's board rotation, both
    # tilting the board between them) are both kept and the joint estimate shares it out
    # smoothly, where eliminating one would flip between them from one subset of boards to
    # the next. Chance values of a component that is not there only inflate the sigmas.
    lr = {}
    if select:
        w0, _, m2l0 = _vce(lin, {g: (1.0 if g[0] == "white" else at_floor[g]) for g in base}, set(), base, floor)
        stats0, _ = lin.solve_and_trace(w0)
        # d(-2 log L)/d(log sigma_g^2) = r_g - q_g: if q_g <= r_g (its chi^2 per redundancy is at
        # most 1), a larger sigma only lowers the likelihood from the floor on: nothing to find
        profiled = [g for g, (n, q, tr) in ((g, stats0[g]) for g in at_floor) if q > n - tr]
        # each profile on its own (by two processes: the solve has the second core to itself here)
        with TwoProcesses([functools.partial(_profile, lin, w0, g, base, floor) for g in profiled],
                          what="the noise components' likelihood profiles") as both:
            m2l = dict(zip(profiled, both.results()))
        lr = {g: m2l0 - m2l[g] if g in m2l else 0.0 for g in at_floor}
        free = {g for g in at_floor if lr[g] >= _LR_CRITICAL}
        log.debug("variance components' likelihood-ratio statistics (kept at >= %g): %s", _LR_CRITICAL,
                  {group_name(problem, g): round(x, 2) for g, x in lr.items()})
        w = {**w0, **{g: (base[g] / max(base[g], _START[g[2]])) ** 2 for g in free}}
    else:
        w = {g: 1.0 for g in base}
        free = {g for g in at_floor if base[g] > floor[g] * (1 + 1e-9)}
    w, red = _estimate(problem, lin, w, free, base, floor)
    sig, effects = _sigmas(base, w, sig, effects)
    return sig, effects, {"redundancy": red, "lr": {g: x for g, x in lr.items() if g in free}}


def without_components(problem, lin: Linearization, sig: np.ndarray, effects: dict, drop) -> tuple:
    """(sig, effects) of the model without the components ``drop`` (groups ("effect", sensor,
    component)): those held at their floor, the white sigmas and the other kept components
    re-estimated on ``lin`` (built with ``sig``, ``effects``)."""
    base, floor = _base_and_floor(problem, lin, sig, effects)
    w = {g: (base[g] / floor[g]) ** 2 if g in drop else 1.0 for g in base}
    free = {g for g in base if g[0] == "effect" and g not in drop and base[g] > floor[g] * (1 + 1e-9)}
    w, _ = _estimate(problem, lin, w, free, base, floor)
    return _sigmas(base, w, sig, effects)


def _estimate(problem, lin: Linearization, w: dict, free: set, base: dict, floor: dict) -> tuple[dict, dict]:
    """_vce's (weights, redundancies); a singular system while components are free names them."""
    try:
        w, red, _ = _vce(lin, w, free, base, floor)
    except np.linalg.LinAlgError:
        if not free:
            raise
        raise SingularComponents(sorted(group_name(problem, g) for g in free)) from None
    return w, red


def _base_and_floor(problem, lin: Linearization, sig: np.ndarray, effects: dict) -> tuple[dict, dict]:
    """({group: the sigma ``lin`` was built with}, {group: its floor})."""
    base = {g: sig[g[1]] if g[0] == "white" else effects[g[1]][g[2]] for g in lin.groups}
    return base, {g: (_white_floor(problem, g) if g[0] == "white" else _FLOOR[g[2]]) for g in base}


def group_name(problem, group) -> str:
    """A component group ("effect", sensor, component) in words: "/lidar1 tilt_rad"."""
    return f"{problem.sensors[group[1]].topic} {group[2]}"


def _sigmas(base: dict, w: dict, sig: np.ndarray, effects: dict) -> tuple:
    """(sig, effects) with each group's sigma base / sqrt(weight)."""
    sig = np.array(sig, float).copy()
    effects = {i: dict(e) for i, e in effects.items()}
    for g, b in base.items():
        s = b / np.sqrt(w[g])
        if g[0] == "white":
            sig[g[1]] = s
        else:
            effects[g[1]][g[2]] = s
    return sig, effects


class SingularComponents(np.linalg.LinAlgError):
    """VCE met a numerically singular system while estimating the components ``kept`` (their
    names, e.g. "/lidar1 tilt_rad"): one of them swallows a direction of the fit."""

    def __init__(self, kept: list):
        super().__init__(f"a singular system estimating {', '.join(kept)}")
        self.kept = kept


def _white_floor(problem, group) -> float:
    """The white sigma's floor (solve.py's: noise-free observations would get infinite weight)."""
    from .solve import _MIN_SIGMA_CAMERA_PX, _MIN_SIGMA_LIDAR_M

    return _MIN_SIGMA_LIDAR_M if problem.sensors[group[1]].is_lidar else _MIN_SIGMA_CAMERA_PX
