"""Is a solved calibration self-consistent? Checks that a number is worth writing.

A least-squares solution always exists; whether it is right is a different question. Each
check splits the data into two independent parts, estimates the sensor poses from each
(one Gauss-Newton step from the solution, on the linearized system) and asks whether the
two agree within their own uncertainty (a chi-square test):

- **leave one snapshot out**: every snapshot against all the others (a wrong plane, a board
  segmented on a wall, a mis-ordered detection: anything one snapshot says that the rest
  contradicts);
- **per sensor pair**: the boards two sensors saw together against everything else (a
  second spanning tree: the pair's link as the other sensors' chains predict it). A pair
  whose link nothing else checks (a bridge of the graph) is reported, not failed.

Every board pose is profiled out (Schur complement) within each part, so a snapshot's
board is fitted separately by the two parts. The tests are linear, so they cost one pass
over the linearized factors, no re-solve. A check fails when its p-value is below
``FAMILY_ALPHA`` divided by the number of checks (Bonferroni): a self-consistent
calibration fails one of them with probability about FAMILY_ALPHA.

The same information matrix names what is weak: each sensor's least-determined
translation and rotation, in lidar0 axes and words ("lidar0 z"), and, when the matrix is
singular, the unobservable direction (the DegenerateError the solve raises instead of
GTSAM's "Indeterminate linear system").

Units: GTSAM's Pose3 tangent [omega, v] (right perturbation T Exp(xi)) turned into lidar0
axes (R omega, R v) for naming; information is whitened by the solve's noise sigmas.

SYNOPSIS
    verdict = verify(problem, graph, values)   # linearize + check, as the solve calls it
    lin = linearize(problem, graph, values)
    verdict = check(problem, lin)          # dict for calibration.yaml; SolveError if inconsistent
    raise unobservable_error(problem, lin) # DegenerateError naming sensor and direction
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..errors import DegenerateError, SolveError
from ..types import Problem

log = logging.getLogger(__name__)

# Chance that a self-consistent calibration fails one of the checks (split by Bonferroni).
FAMILY_ALPHA = 1e-3
# Information below this (1-sigma above 1 m or 1 rad) counts as "not determined at all".
_MIN_INFORMATION = 1.0
# A "silent wrong answer": an error beyond this many reported sigmas ...
_SILENT_SIGMAS = 5.0
# ... and beyond this size (a rotation counted by how far it moves a point _LEVER_M away):
# issue 11's definition of a silent wrong answer. Smaller errors the checks cannot see are
# reported in the verdict (``unverified``) but do not refuse the calibration.
_MATERIAL_M = 0.05
_LEVER_M = 10.0


class Inconsistent(SolveError):
    """A refused calibration whose worst failure is ``snapshot``'s (None: a pair of sensors'):
    ``why`` that failure in words."""

    def __init__(self, message: str, snapshot: int | None, why: str):
        super().__init__(message)
        self.snapshot, self.why = snapshot, why


@dataclass
class _Obs:
    """One observation's normal-equation blocks: sensor (None for lidar0 or a board prior)."""

    sensor: int | None
    snapshot: int
    is_prior: bool
    Hss: np.ndarray | None  # (6,6)
    Hsb: np.ndarray | None  # (6,6)
    Hbb: np.ndarray  # (6,6)
    gs: np.ndarray | None  # (6, 1 + m): the gradient, then its change per unit of each known error
    gb: np.ndarray  # (6, 1 + m)


@dataclass
class Linearized:
    """The solve's factor graph, linearized at the solution, as small per-observation blocks.

    ``sensors``: the non-reference sensors in column order (6 columns each, GTSAM tangent);
    ``obs``: board-touching observation factors; ``H_global``/``g_global``: everything that
    touches no board (pose priors, extension factors); ``R``: (Nsensors,3,3) rotations.
    Gradients are (., 1 + m): the data's, then their change per unit of each of the m errors of
    known variance shared by every snapshot (the consider terms, ``known``), which the
    comparisons count in.
    """

    sensors: list
    obs: list
    H_global: np.ndarray
    g_global: np.ndarray
    R: np.ndarray
    topics: list  # every sensor's topic, by sensor index
    by_snapshot: dict = field(default_factory=dict)

    def col(self, i: int) -> slice:
        k = self.sensors.index(i)
        return slice(6 * k, 6 * k + 6)

    @property
    def n(self) -> int:
        return 6 * len(self.sensors)


class _Unsupported(Exception):
    """A factor the board-by-board split cannot place (an extension factor on two boards)."""


def verify(problem: Problem, graph, values, *, alpha: float = FAMILY_ALPHA, refuse: bool = True,
           known=None) -> dict:
    """linearize + check: the solve's hook. A graph the checks cannot split (an extension
    factor linking boards) is reported as unchecked, with a warning, not refused. ``refuse``
    False: a failed verdict is returned (and logged), not raised. ``known``: the consider terms'
    errors (consider.known_columns), counted in every comparison."""
    try:
        lin = linearize(problem, graph, values, known)
    except _Unsupported as e:
        log.warning("consistency checks skipped: %s", e)
        return {"passed": None, "skipped": str(e)}
    return check(problem, lin, alpha=alpha, refuse=refuse)


def linearize(problem: Problem, graph, values, known=None) -> Linearized:
    """Per-factor normal-equation blocks of ``graph`` at ``values`` (see Linearized). ``known``:
    ({factor index: (rows, m) change of its whitened b per unit of each known error}, m)
    (consider.known_columns), or None."""
    import gtsam

    sensors = problem.variable_sensors()
    n = 6 * len(sensors)
    col = {i: 6 * k for k, i in enumerate(sensors)}
    lin = graph.linearize(values)
    db, m = known or ({}, 0)
    H_global, g_global = np.zeros((n, n)), np.zeros((n, 1 + m))
    obs, effects = [], {}
    for f in range(lin.size()):
        A, b = lin.at(f).jacobian()
        b = np.c_[b, db[f]] if f in db else np.c_[b, np.zeros((len(b), m))]
        keys = [gtsam.Symbol(k) for k in lin.at(f).keys()]
        cols = {}
        for j, s in enumerate(keys):
            cols[(chr(s.chr()), int(s.index()))] = slice(6 * j, 6 * j + 6)
        effect = [key for key in cols if key[0] in "de"]
        if effect:  # an observation's own board-pose error (backend/noise.py): condensed below
            effects.setdefault(effect[0], []).append((A, b, cols))
            continue
        boards = [k for c, k in cols if c == "b"]
        sens = [k for c, k in cols if c == "s"]
        if not boards:  # priors and extension factors on sensors only
            idx = np.concatenate([np.arange(col[i], col[i] + 6) for i in sens])
            Ak = np.hstack([A[:, cols[("s", i)]] for i in sens])
            H_global[np.ix_(idx, idx)] += Ak.T @ Ak
            g_global[idx] += Ak.T @ b
            continue
        if len(boards) != 1 or len(sens) > 1:
            raise _Unsupported(f"a {type(graph.at(f)).__name__} on {len(boards)} boards and {len(sens)} sensors")
        k = boards[0]
        Ab = A[:, cols[("b", k)]]
        is_prior = "CustomFactor" not in type(graph.at(f)).__name__
        if sens:
            As = A[:, cols[("s", sens[0])]]
            obs.append(_Obs(sens[0], k, is_prior, As.T @ As, As.T @ Ab, Ab.T @ Ab, As.T @ b, Ab.T @ b))
        else:
            obs.append(_Obs(None if is_prior else problem.reference, k, is_prior, None, None, Ab.T @ Ab, None,
                            Ab.T @ b))
    for ekey, parts in effects.items():
        obs.append(_condensed(problem, ekey, parts))
    R = np.array([np.eye(3) if i == problem.reference else values.atPose3(gtsam.symbol("s", i)).rotation().matrix()
                  for i in range(len(problem.sensors))])
    out = Linearized(sensors, obs, H_global, g_global, R, [x.topic for x in problem.sensors])
    for o in obs:
        out.by_snapshot.setdefault(o.snapshot, []).append(o)
    return out


def _condensed(problem: Problem, ekey, parts) -> _Obs:
    """One observation with its own board-pose error D: its factors (on sensor, board and D)
    and D's prior summed, D eliminated (Schur complement): the observation's blocks on the
    sensor and the board, as if its noise were white plus D's share."""
    sens = sorted({k for _, _, cols in parts for c, k in cols if c == "s"})
    boards = sorted({k for _, _, cols in parts for c, k in cols if c == "b"})
    if len(boards) != 1 or len(sens) > 1:
        raise _Unsupported(f"an observation error {ekey} on {len(boards)} boards and {len(sens)} sensors")
    order = [("s", k) for k in sens] + [("b", boards[0]), ekey]
    H, g = np.zeros((6 * len(order),) * 2), np.zeros((6 * len(order), parts[0][1].shape[1]))
    for A, b, cols in parts:  # each factor's A^T A scattered into the observation's columns (no padded copy of A)
        src = np.concatenate([np.arange(cols[key].start, cols[key].stop) for key in order if key in cols])
        dst = np.concatenate([np.arange(6 * j, 6 * j + 6) for j, key in enumerate(order) if key in cols])
        As = A[:, src] if not np.array_equal(src, np.arange(A.shape[1])) else A
        H[np.ix_(dst, dst)] += As.T @ As
        g[dst] += As.T @ b
    Hxe = H[:-6, -6:]
    X = np.linalg.solve(H[-6:, -6:], np.c_[Hxe.T, g[-6:]])  # D's prior keeps H_ee positive definite
    nx = Hxe.shape[0]
    Hc, gc = H[:-6, :-6] - Hxe @ X[:, :nx], g[:-6] - Hxe @ X[:, nx:]
    if sens:
        return _Obs(sens[0], boards[0], False, Hc[:6, :6], Hc[:6, 6:], Hc[6:, 6:], gc[:6], gc[6:])
    return _Obs(problem.reference, boards[0], False, None, None, Hc, None, gc)


def _pinv_psd(H: np.ndarray, floor: float = 0.0) -> np.ndarray:
    w, V = np.linalg.eigh(0.5 * (H + H.T))
    tol = max(floor, 1e-12 * max(w[-1], 0.0))
    inv = np.where(w > tol, 1.0 / np.where(w > tol, w, 1.0), 0.0)
    return (V * inv) @ V.T


def _schur(lin: Linearized, group: list) -> tuple[np.ndarray, np.ndarray]:
    """(information (n,n), gradient (n,)) on the sensors of one board's observations
    ``group``, that board profiled out (its own copy: the group's alone)."""
    sens = sorted({o.sensor for o in group if o.Hss is not None})
    m = 6 * len(sens)
    ng = lin.g_global.shape[1]
    Hss, Hsb, gs = np.zeros((m, m)), np.zeros((m, 6)), np.zeros((m, ng))
    Hbb, gb = np.zeros((6, 6)), np.zeros((6, ng))
    for o in group:
        Hbb += o.Hbb
        gb += o.gb
        if o.Hss is not None:
            j = 6 * sens.index(o.sensor)
            Hss[j:j + 6, j:j + 6] += o.Hss
            Hsb[j:j + 6] += o.Hsb
            gs[j:j + 6] += o.gs
    P = _pinv_psd(Hbb)
    H, g = np.zeros((lin.n, lin.n)), np.zeros((lin.n, ng))
    idx = np.concatenate([np.arange(lin.col(i).start, lin.col(i).stop) for i in sens]) if sens else np.zeros(0, int)
    H[np.ix_(idx, idx)] = Hss - Hsb @ P @ Hsb.T
    g[idx] = gs - Hsb @ P @ gb
    return H, g


def information(lin: Linearized) -> tuple[np.ndarray, np.ndarray, dict]:
    """(total information (n,n), total gradient (n,), {snapshot: (info, gradient)})."""
    per = {k: _schur(lin, grp) for k, grp in lin.by_snapshot.items()}
    H = lin.H_global + sum((h for h, _ in per.values()), np.zeros((lin.n, lin.n)))
    g = lin.g_global + sum((x for _, x in per.values()), np.zeros_like(lin.g_global))
    return H, g, per


@dataclass
class Comparison:
    chi2: float
    dof: int
    sigma: float  # the normal-distribution equivalent of the p-value
    p: float
    direction: str  # the dominant disagreement, in words
    size: str  # its size, e.g. "41 mm" or "0.3 deg"


def _inverse_sqrt(H: np.ndarray) -> np.ndarray:
    """L^-1 with L L' = H (Cholesky), or a pseudo-inverse square root if H is not definite."""
    try:
        return np.linalg.inv(np.linalg.cholesky(0.5 * (H + H.T)))
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(0.5 * (H + H.T))
        ok = w > 1e-12 * max(w[-1], 1e-300)
        return (V[:, ok] / np.sqrt(w[ok])).T


def leverage(H: np.ndarray, H_k: np.ndarray, *, Li: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """(largest share in [0, 1] of the information ``H`` that ``H_k`` supplies in one
    direction, that direction in tangent coordinates): max v'H_k v / v'H v.
    ``Li``: inv(cholesky(H)), when already computed."""
    if Li is None:
        Li = _inverse_sqrt(H)
    w, V = np.linalg.eigh(Li @ H_k @ Li.T)
    v = Li.T @ V[:, -1]
    return float(np.clip(w[-1], 0.0, 1.0)), v / np.linalg.norm(v)


def undetectable(lin: Linearized, H: np.ndarray, H_k: np.ndarray, z_limit: float, *, Li=None):
    """The largest shift of the solution that an error in one snapshot (information H_k of
    the total H) can cause while its leave-one-out test stays below ``z_limit``.

    With leverage h (its share of the information along direction v, v'Hv = 1), an error
    moving the snapshot's own estimate by b moves the solution by h b and shows in the test
    as b sqrt(h (1 - h)) (1-D: both in units of the solution's sigma), so up to
    z_limit sqrt(h / (1 - h)) sigmas go unseen. Returns (sigmas, tangent shift, h).
    """
    h, v = leverage(H, H_k, Li=Li)
    v = v / np.sqrt(max(float(v @ H @ v), 1e-300))
    n_sig = z_limit * np.sqrt(h / max(1.0 - h, 1e-12))
    return float(n_sig), n_sig * v, h


def compare(lin: Linearized, H_a, g_a, H_b, g_b, *, sum_pinv: np.ndarray | None = None) -> Comparison | None:
    """Do two independent parts of the data (information, gradient at the solution) agree?

    Each part's estimate is one Gauss-Newton step, x = H^+ g; their difference is weighed
    by the parallel sum H_a (H_a + H_b)^+ H_b, which counts only directions both parts
    determine. None when they share no such direction (nothing to check).
    ``sum_pinv``: (H_a + H_b)^+, when already computed. Gradients (n, 1 + m): the errors of
    known variance shared by both parts (columns 1..m, per unit) move their estimates by
    different amounts, so the difference's covariance is M^+ + D D^T (D their effect on it),
    its weight M - M D (I + D^T M D)^-1 D^T M (Woodbury).
    """
    from scipy.special import chdtrc, ndtri  # not scipy.stats: 2 s to import

    delta = _pinv_psd(H_a, _MIN_INFORMATION) @ g_a - _pinv_psd(H_b, _MIN_INFORMATION) @ g_b
    delta, D = (delta[:, 0], delta[:, 1:]) if delta.ndim == 2 else (delta, delta[:, None][:, :0])
    M = H_a @ (_pinv_psd(H_a + H_b) if sum_pinv is None else sum_pinv) @ H_b
    if D.shape[1]:
        MD = M @ D
        M = M - MD @ np.linalg.solve(np.eye(D.shape[1]) + D.T @ MD, MD.T)
    w, V = np.linalg.eigh(0.5 * (M + M.T))
    keep = w > _MIN_INFORMATION
    if not keep.any():
        return None
    w, V = w[keep], V[:, keep]
    proj = V.T @ delta
    terms = w * proj**2
    chi2, dof = float(terms.sum()), int(keep.sum())
    p = float(chdtrc(dof, chi2))
    sigma = float(-ndtri(p / 2)) if p > 1e-300 else float(np.sqrt(chi2))
    j = int(np.argmax(terms))
    i, what, v = _dominant(lin, V[:, j] * proj[j])
    size = f"{1e3 * np.linalg.norm(v):.0f} mm" if what.startswith("t") else f"{np.degrees(np.linalg.norm(v)):.2f} deg"
    direction = f"{lin.topics[i]} {what} lidar0 {axis_words(v)}"
    return Comparison(chi2, dof, sigma, p, direction, size)


# ---------------------------------------------------------------- naming directions


def axis_words(v: np.ndarray) -> str:
    """A direction in words: "z", "-x", "0.71x+0.71y" (components below 0.3 left out)."""
    v = np.asarray(v, float) / max(np.linalg.norm(v), 1e-300)
    if np.max(np.abs(v)) > 0.95:
        j = int(np.argmax(np.abs(v)))
        return ("-" if v[j] < 0 else "") + "xyz"[j]
    parts = [f"{c:+.2f}{a}" for c, a in zip(v, "xyz") if abs(c) >= 0.3]
    return "".join(parts).lstrip("+")


def _sensor_block_lidar0(lin: Linearized, x: np.ndarray, i: int) -> tuple[np.ndarray, np.ndarray]:
    """(rotation, translation) of sensor i's part of tangent vector x, in lidar0 axes."""
    b = x[lin.col(i)]
    return lin.R[i] @ b[:3], lin.R[i] @ b[3:]


def _dominant(lin: Linearized, x: np.ndarray) -> tuple[int, str, np.ndarray]:
    """(sensor, "translation along" | "rotation about", 3-vector in lidar0 axes) carrying
    most of tangent vector x."""
    best = None
    for i in lin.sensors:
        rot, tr = _sensor_block_lidar0(lin, x, i)
        # a rotation counts by how far it moves a point _LEVER_M away
        for what, v, scale in (("translation along", tr, 1.0), ("rotation about", rot, _LEVER_M)):
            mag = float(np.linalg.norm(v)) * scale
            if best is None or mag > best[0]:
                best = (mag, i, what, v)
    return best[1], best[2], best[3]


def _shift_words(lin: Linearized, x: np.ndarray) -> tuple[int, str, str, bool]:
    """(sensor, "translation along lidar0 -z and rotation about lidar0 x", "98 mm and 0.52 deg",
    material) for the sensor carrying most of tangent shift x. Its other part is named too
    when it is at least half as large (a rotation counted at _LEVER_M): a board's plane offset
    moves a camera's height and tilts it together, and naming one would hide the other."""
    i, _, _ = _dominant(lin, x)
    rot, tr = _sensor_block_lidar0(lin, x, i)
    parts = [(float(np.linalg.norm(tr)), f"translation along lidar0 {axis_words(tr)}", f"{1e3 * np.linalg.norm(tr):.0f} mm"),
             (_LEVER_M * float(np.linalg.norm(rot)), f"rotation about lidar0 {axis_words(rot)}",
              f"{np.degrees(np.linalg.norm(rot)):.2f} deg")]
    parts.sort(key=lambda p: -p[0])
    named = [p for p in parts if p[0] >= 0.5 * parts[0][0]]
    return i, " and ".join(p[1] for p in named), " and ".join(p[2] for p in named), parts[0][0] > _MATERIAL_M


def recapture_hint(lin: Linearized, x: np.ndarray) -> str:
    """What to capture so that no single board carries tangent shift x, in the user's words.
    A LIDAR sees only the board's plane, so a translation is fixed by boards whose normals
    have a part along it: a height by boards pitched up or down, a sideways offset by boards
    turned left or right; a rotation by boards whose normals differ from each other."""
    i, _, _ = _dominant(lin, x)
    rot, tr = _sensor_block_lidar0(lin, x, i)
    if np.linalg.norm(tr) >= _LEVER_M * np.linalg.norm(rot):
        d = np.abs(tr) / max(np.linalg.norm(tr), 1e-300)
        if d[2] >= 0.5:
            how = "pitched up and down (faces toward the sky or the ground), not only upright"
        else:
            how = f"whose faces point along lidar0 {axis_words(tr).lstrip('-')} (turned left and right, near and far)"
    else:
        how = "tilted in different directions (pitched up and down, turned left and right)"
    return f"capture more boards that {lin.topics[i]} and the other sensors see together, {how}"


def weakest_directions(problem: Problem, lin: Linearized, H: np.ndarray) -> dict:
    """Per non-reference sensor: its least-determined translation and rotation (1-sigma and
    the lidar0 axis in words), from the marginal covariance H^-1."""
    C = _pinv_psd(H)
    out = {}
    for i in lin.sensors:
        c = lin.col(i)
        blk = C[c, c]
        entry = {}
        for name, part, unit in (("translation", slice(3, 6), 1e3), ("rotation", slice(0, 3), np.degrees(1.0))):
            # tangent -> lidar0 axes: Cov' = R Cov R^T
            w, V = np.linalg.eigh(lin.R[i] @ blk[part, part] @ lin.R[i].T)
            entry[name] = {"stdev": float(unit * np.sqrt(max(w[-1], 0.0))), "axis": axis_words(V[:, -1])}
        out[problem.sensors[i].topic] = {
            "weakest_translation": f"lidar0 {entry['translation']['axis']}",
            "weakest_translation_stdev_mm": entry["translation"]["stdev"],
            "weakest_rotation": f"about lidar0 {entry['rotation']['axis']}",
            "weakest_rotation_stdev_deg": entry["rotation"]["stdev"],
        }
    return out


def unobservable_error(problem: Problem, lin: Linearized) -> DegenerateError:
    """The DegenerateError naming every direction the information leaves (nearly) free."""
    H, _, _ = information(lin)
    w, V = np.linalg.eigh(0.5 * (H + H.T))
    scale = max(w[-1], 1.0)
    # GTSAM gave up, so something is (nearly) free: name what is below the floor, else the weakest
    free = [V[:, j] for j in range(len(w)) if w[j] < max(_MIN_INFORMATION, 1e-10 * scale)] or [V[:, 0]]
    parts = []
    for v in free[:3]:
        i, what, vec = _dominant(lin, v)
        vec = vec / np.linalg.norm(vec)
        vec = vec * np.sign(vec[np.argmax(np.abs(vec))])
        parts.append(f"{lin.topics[i]}: {what} lidar0 ({vec[0]:+.2f}, {vec[1]:+.2f}, {vec[2]:+.2f}) = {axis_words(vec)}")
    return DegenerateError("unobservable: " + "; ".join(parts) + " (the information matrix is singular there); "
                           "capture board poses that constrain it (tilt the board in different directions)")


# ---------------------------------------------------------------- the checks


def check(problem: Problem, lin: Linearized, *, alpha: float = FAMILY_ALPHA, refuse: bool = True) -> dict:
    """Run every check (module docstring); the verdict as a plain dict, or SolveError
    (``alpha`` <= 0: the verdict only, with a warning, never an error).

    The dict: ``passed``, ``alpha``, ``n_checks``, ``p_limit``, ``snapshots`` (the worst
    leave-one-out test, the largest single-snapshot share of the information), ``pairs``
    (per sensor pair: chi2, dof, sigma, dominant direction), ``unchecked_pairs`` (links
    nothing else checks), ``weakest`` (per sensor, weakest_directions), ``unverified``
    (directions one snapshot determines), ``failures`` and ``unverifiable`` (why refused).
    """
    from scipy.special import ndtri

    H, g, per = information(lin)
    names = problem.sensors
    snap_tests = {}
    H_pinv = _pinv_psd(H)
    for k, (Hk, gk) in sorted(per.items()):
        c = compare(lin, Hk, gk, H - Hk, g - gk, sum_pinv=H_pinv)
        if c is not None:
            snap_tests[k] = c
    pair_tests, bridges = {}, []
    seen = {k: {o.sensor for o in grp if o.sensor is not None} for k, grp in lin.by_snapshot.items()}
    nsens = len(names)
    for a in range(nsens):
        for b in range(a + 1, nsens):
            shared = [k for k, s in seen.items() if a in s and b in s]
            if not shared:
                continue
            Hg, gg = np.zeros_like(H), np.zeros_like(g)
            Hr, gr = H.copy(), g.copy()
            for k in shared:
                grp = lin.by_snapshot[k]
                mine = [o for o in grp if o.sensor in (a, b)]
                rest = [o for o in grp if o.sensor not in (a, b)]  # board priors go with the rest
                hm, gm = _schur(lin, mine + [o for o in grp if o.is_prior])
                hr, gr_ = _schur(lin, rest)
                Hg += hm
                gg += gm
                Hr += hr - per[k][0]
                gr += gr_ - per[k][1]
            c = compare(lin, Hg, gg, Hr, gr)
            key = f"{names[a].topic} - {names[b].topic}"
            if c is None:
                bridges.append(key)
            else:
                pair_tests[key] = (c, len(shared))
    m = len(snap_tests) + len(pair_tests)
    limit = (alpha if alpha > 0 else FAMILY_ALPHA) / max(m, 1)  # alpha <= 0: judge, never refuse
    verdict = {
        "passed": True,
        "alpha": alpha,
        "n_checks": m,
        "p_limit": limit,
        "snapshots": {"checked": len(snap_tests)},
        "pairs": {},
        "unchecked_pairs": bridges,
        "weakest": weakest_directions(problem, lin, H),
    }
    if snap_tests:
        k = min(snap_tests, key=lambda kk: snap_tests[kk].p)
        c = snap_tests[k]
        verdict["snapshots"].update({"worst": int(k), "worst_sigma": c.sigma, "worst_chi2": c.chi2,
                                     "worst_dof": c.dof, "worst_direction": c.direction})
    for key, (c, nshared) in pair_tests.items():
        verdict["pairs"][key] = {"shared_snapshots": nshared, "chi2": c.chi2, "dof": c.dof, "sigma": c.sigma,
                                 "direction": c.direction}
    failures = []
    z_limit = float(-ndtri(limit / 2))
    unverified, shares = [], []
    Li = _inverse_sqrt(H)
    for k, (Hk, _) in sorted(per.items()):
        if k not in snap_tests:
            continue
        n_sig, u, h = undetectable(lin, H, Hk, z_limit, Li=Li)
        shares.append(h)
        if n_sig > _SILENT_SIGMAS:
            i, what, size, material = _shift_words(lin, u)
            # no other board constrains it at all (e.g. a camera that saw 3 boards: each fixes the
            # translation along the other two's normals' cross product): any error would pass
            hidden = "an error of any size" if h > 1 - 1e-4 else f"an error of up to {size} ({n_sig:.0f} sigma)"
            unverified.append((not material, -n_sig, k, f"snapshot {k} alone carries {100 * h:.0f}% of the information on "
                                         f"{lin.topics[i]} {what}: {hidden} there would pass every check",
                               recapture_hint(lin, u)))
    verdict["snapshots"]["max_leverage"] = max(shares, default=0.0)
    unverified.sort()
    verdict["unverified"] = [why for _, _, _, why, _ in unverified]
    unverified = [u for u in unverified if not u[0]]  # the material ones refuse the result
    for k, c in snap_tests.items():
        if c.p < limit:
            who = sorted({names[o.sensor].topic for o in lin.by_snapshot[k] if o.sensor is not None})
            failures.append((c.p, f"snapshot {k} ({', '.join(who)}) disagrees with the other snapshots by "
                                  f"{c.sigma:.1f} sigma ({c.direction}, {c.size})", int(k)))
    for key, (c, nshared) in pair_tests.items():
        if c.p < limit:
            failures.append((c.p, f"the {nshared} boards {key.replace(' - ', ' and ')} saw together disagree with "
                                  f"the rest of the data by {c.sigma:.1f} sigma ({c.direction}, {c.size})", None))
    log.info("consistency: %d checks, worst snapshot %s", m, verdict["snapshots"].get("worst_sigma"))
    failures.sort(key=lambda f: f[0])
    verdict["failures"] = [why for _, why, _ in failures]
    verdict["unverifiable"] = [why for _, _, _, why, _ in unverified]
    verdict["passed"] = not failures and not unverified
    if verdict["passed"]:
        return verdict
    first = failures[0][1] if failures else unverified[0][3]
    if alpha <= 0 or not refuse:
        log.info("not self-consistent (result written with this verdict): %s", first)
        return verdict
    more = len(failures) + len(unverified) - 1
    more = f" (and {more} more)" if more else ""
    if failures:
        raise Inconsistent(f"not self-consistent, no result written: {first}{more}; a wrong board association or a "
                           "moved sensor? check the boards with `clcgraph segment`/`detect`, or leave the snapshot "
                           "out (replay --exclude); --set solve.refuse_inconsistent=false writes it with this verdict",
                           failures[0][2], failures[0][1])
    raise DegenerateError(f"not verifiable, no result written: {first}{more}; {unverified[0][4]} "
                          "(--set solve.refuse_inconsistent=false writes it with this verdict)")
