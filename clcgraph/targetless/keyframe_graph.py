"""Final extrinsic from a GTSAM graph of keyframe poses and registrations, with a Marginals covariance.

SYNOPSIS
    est = fuse(measurements, keyframes, edges)   # FrameMeasurement list, {pos: (4,4)}, KeyframeEdge list
    est.T, est.cov_rt                            # (4,4) T_lidar0_sensor, (6,6) covariance of rt_lidar0_sensor
    est.scales                                   # {"frames": s, "keyframes": s}: estimated noise scales

Variables: the extrinsic E and the map poses X_j of the keyframes whose submaps built the
calibration targets. Factors: one per selected frame (factors/map_registration.py: its
registration, linked to the keyframes of its target through how much of the registration's
information each submap gave), and registration between-factors of neighbouring keyframe
submaps (j -> j+1 and j -> j+2, so the keyframe chain has redundancy). Frames that share
submaps are thus correlated through the X_j, not treated as independent; global drift does
not enter (only relative keyframe poses appear).

A registration bias common to all frames (deskew with estimated twists, the sensors sampling
the same structures) does not show in their scatter. In the simulator, without this term the
errors were 1.6-2.7 sigma in the same direction on six seeds; with exact map poses the bias
is about half a frame's scatter. It is a variable ``beta`` shared by the frame factors, with
prior covariance ``common_mode`` x one frame's covariance, so E's marginal carries it.

GICP's Hessians have arbitrary units (regularised point covariances), so each kind of factor
has a covariance s_kind * H^-1 with s_kind estimated from the residuals by variance-component
estimation (chi^2 of the kind / its redundancy, iterated). A prior on one keyframe fixes the
map's gauge; it does not touch E.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import geometry as geo
from ..errors import DegenerateError, SolveError


@dataclass
class KeyframeEdge:
    """Registration of keyframe b's submap to keyframe a's: T_a_b and its Hessian."""
    a: int
    b: int
    T: np.ndarray  # (4,4)
    H: np.ndarray  # (6,6)


@dataclass
class Estimate:
    T: np.ndarray  # (4,4)
    cov_rt: np.ndarray  # (6,6) rt coordinates
    cov_xi: np.ndarray  # (6,6) GTSAM tangent
    scales: dict = field(default_factory=dict)  # factor kind -> estimated covariance scale
    redundancy: dict = field(default_factory=dict)  # factor kind -> degrees of freedom left
    convergence: dict = field(default_factory=dict)  # how each LM and the noise-scale iteration stopped


def _keys():
    import gtsam

    return gtsam.symbol("e", 0), gtsam.symbol("b", 0), lambda pos: gtsam.symbol("x", pos)


def _sym_inv(H):
    return np.linalg.inv(0.5 * (H + H.T))


def _build(meas, keyframes, edges, scales, common_mode):
    """Graph with the current scales; returns (graph, initial values, kind of each factor)."""
    import gtsam

    from ..factors.map_registration import map_registration_factor

    E, BIAS, X = _keys()
    g = gtsam.NonlinearFactorGraph()
    kinds = []
    v = gtsam.Values()
    v.insert(E, gtsam.Pose3(meas[0].T))
    bias = BIAS if common_mode > 0 else None
    if bias is not None:
        v.insert(BIAS, gtsam.Pose3())
        cov = common_mode * scales["frames"] * np.mean([_sym_inv(m.H) for m in meas], axis=0)
        g.add(gtsam.PriorFactorPose3(BIAS, gtsam.Pose3(), gtsam.noiseModel.Gaussian.Covariance(cov)))
        kinds.append("bias")
    for pos, T in keyframes.items():
        v.insert(X(pos), gtsam.Pose3(T))
    for m in meas:
        cov = scales["frames"] * _sym_inv(m.H)
        if m.anchor is None or m.anchor not in keyframes:
            g.add(map_registration_factor(gtsam.Pose3(m.T), cov, E, bias_key=bias))
        else:
            Xi = keyframes[m.anchor]
            links = {X(j): (gtsam.Pose3(np.linalg.inv(Xi) @ keyframes[j]), B)
                     for j, B in m.influence.items() if j in keyframes and j != m.anchor}
            g.add(map_registration_factor(gtsam.Pose3(m.T), cov, E, bias_key=bias, anchor_key=X(m.anchor), links=links))
        kinds.append("frames")
    for e in edges:
        cov = scales["keyframes"] * _sym_inv(e.H)
        g.add(gtsam.BetweenFactorPose3(X(e.a), X(e.b), gtsam.Pose3(e.T),
                                       gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov + cov.T))))
        kinds.append("keyframes")
    # one gauge prior per connected group of keyframes (the map's origin is arbitrary)
    for root in _components(keyframes, edges):
        g.add(gtsam.PriorFactorPose3(X(root), gtsam.Pose3(keyframes[root]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
        kinds.append("gauge")
    return g, v, kinds


def _components(keyframes, edges) -> list:
    """The smallest keyframe of each group connected by edges."""
    parent = {p: p for p in keyframes}

    def find(p):
        while parent[p] != p:
            parent[p] = parent[parent[p]]
            p = parent[p]
        return p

    for e in edges:
        ra, rb = find(e.a), find(e.b)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    return sorted({find(p) for p in keyframes})


def _redundancy(graph, values, kinds):
    """Per kind: (sum of whitened squared residuals, sum of redundancy numbers r_f = dim_f - tr(A_f N^-1 A_f^T))."""
    lin = graph.linearize(values)
    col, n = {}, 0
    blocks = []
    for f in range(lin.size()):
        jf = lin.at(f)
        A, b = jf.jacobian()
        keys = list(jf.keys())
        for k in keys:
            if k not in col:
                col[k] = n
                n += 6
        blocks.append((keys, A, b))
    rows = []
    for keys, A, _ in blocks:
        full = np.zeros((A.shape[0], n))
        for i, k in enumerate(keys):
            full[:, col[k]:col[k] + 6] = A[:, 6 * i:6 * i + 6]
        rows.append(full)
    Ninv = np.linalg.inv(np.concatenate(rows).T @ np.concatenate(rows))
    out = {}
    for kind, full, (_, _, b) in zip(kinds, rows, blocks):
        chi2, r = out.get(kind, (0.0, 0.0))
        out[kind] = (chi2 + float(b @ b), r + full.shape[0] - float(np.einsum("ij,jk,ik->", full, Ninv, full)))
    return out


def _optimize(g, v, max_iterations: int, stage: str):
    """(values, convergence record) of LM on the graph."""
    import gtsam

    from ..backend.convergence import optimize_lm

    p = gtsam.LevenbergMarquardtParams()
    p.setRelativeErrorTol(1e-10)
    p.setAbsoluteErrorTol(1e-12)
    p.setMaxIterations(max_iterations)
    return optimize_lm(g, v, p, stage=stage)


def fuse(meas, keyframes: dict | None = None, edges=(), *, common_mode: float = 1.0, min_frames: int = 2,
         max_cond: float = 1e6, iterations: int = 8, max_iterations: int = 100) -> Estimate:
    """Fuse the per-frame registrations (and keyframe edges) into T_lidar0_sensor; DegenerateError
    if the registrations constrain too little. ``keyframes``: position -> (4,4) map pose estimate;
    ``common_mode``: prior covariance of the shared registration bias, in units of one frame's
    covariance (0: none); ``iterations``: of the variance-component estimation; ``max_iterations``:
    of each LM. ``Estimate.convergence`` says how each stopped; SolveError when the final LM did
    not converge and its last step moved E by more than a tenth of its sigma."""
    import gtsam

    from ..backend.convergence import MAX_UNCONVERGED_STEP_SIGMA, public, step_sigma

    if len(meas) < min_frames:
        raise DegenerateError(f"only {len(meas)} usable calibration frames (< {min_frames}); "
                              "drive longer through a scene with 3-D structure")
    for m in meas:
        w = np.linalg.eigvalsh(0.5 * (m.H + m.H.T))
        if w[0] <= 0 or w[-1] / w[0] > max_cond:
            raise DegenerateError(f"a calibration registration is degenerate (Hessian condition {w[-1] / max(w[0], 1e-300):.3g}); "
                                  "the scene does not constrain all six degrees of freedom")
    keyframes = dict(keyframes or {})
    edges = [e for e in edges if e.a in keyframes and e.b in keyframes]
    # a keyframe no edge reaches has nothing to be estimated from: it stays where the map put it
    linked = {p for e in edges for p in (e.a, e.b)}
    keyframes = {p: T for p, T in keyframes.items() if p in linked}
    scales = {"frames": 1.0, "keyframes": 1.0}
    red = {}
    stages = []
    done = False
    for it in range(iterations):
        g, v, kinds = _build(meas, keyframes, edges, scales, common_mode)
        res, rec = _optimize(g, v, max_iterations, f"variance components {it}")
        stages.append(rec)
        red = _redundancy(g, res, kinds)
        new = dict(scales)
        for kind in ("frames", "keyframes"):
            chi2, r = red.get(kind, (0.0, 0.0))
            if r >= 1.0:  # too little redundancy leaves the scale as it is
                new[kind] = max(scales[kind] * chi2 / r, 1e-12)
        if "keyframes" in red and red["keyframes"][1] < 1.0:
            new["keyframes"] = new["frames"]  # same GICP model, no redundancy of its own
        done = all(abs(np.log(new[k] / scales[k])) < 0.01 for k in scales)
        scales = new
        if done:
            break
    g, v, kinds = _build(meas, keyframes, edges, scales, common_mode)
    res, final = _optimize(g, v, max_iterations, "final")
    stages.append(final)
    E = _keys()[0]
    cov = gtsam.Marginals(g, res).marginalCovariance(E)
    step = step_sigma(final["_last_step"], res, [E], cov)
    for r in stages:
        r.pop("_last_step", None)
    warnings = [f"LM {r['stage']} did not converge: {r['reason']}" for r in stages if not r["converged"]]
    if not done:
        warnings.append(f"the noise-scale (variance component) estimation did not settle in {iterations} iterations")
    if not final["converged"]:
        if not step <= MAX_UNCONVERGED_STEP_SIGMA:
            raise SolveError(f"the targetless graph did not converge ({final['reason']}) and its last step moved the "
                             f"extrinsic by {step:.2g} sigma: the result cannot be trusted")
        warnings.append(f"the final graph solve did not converge, but its last step moved the extrinsic by only "
                        f"{step:.2g} sigma (<= {MAX_UNCONVERGED_STEP_SIGMA:g}): the result stands")
    convergence = {"converged": not warnings, "final_step_sigma": step,
                   "variance_components": {"iterations": len(stages) - 1, "max": iterations, "settled": bool(done)},
                   "stages": [public(r) for r in stages], "warnings": warnings}
    T = res.atPose3(E).matrix()
    J = geo.drt_dxi(geo.rt_from_T(T))
    return Estimate(T, J @ cov @ J.T, cov, scales, {k: r for k, (_, r) in red.items()}, convergence)
