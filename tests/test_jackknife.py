"""The jackknife's own prediction (backend/jackknife.py): the mean and variance of the
jackknife variance along each axis if the model is right, against a Monte Carlo of that
model (the moves are linear in independent parts r_j ~ N(0, S_j))."""

from __future__ import annotations

import numpy as np

from clcgraph.backend.jackknife import jackknife
from clcgraph.geometry import drt_dxi


class _Lin:
    """The part of noise.Linearization the jackknife reads: sensor-only normal equations."""

    def __init__(self, S, r, parts):
        self.ns, self.variable_sensors, self._out = len(S), [1, 2], (S, r, parts)

    def reduced(self):
        return self._out


def _spd(rng, ns, rank, scale):
    A = rng.normal(size=(rank, ns)) * scale
    return A.T @ A


def test_expected_jackknife_variance_matches_monte_carlo():
    rng = np.random.default_rng(3)
    ns, n_snap = 12, 9
    # unequal snapshots (one of high leverage), each rank-deficient like a real board's share
    S_parts = [_spd(rng, ns, 6, 1.0 + 3.0 * (k == 0)) for k in range(n_snap)]
    S_rest = _spd(rng, ns, ns, 0.3)
    S = sum(S_parts) + S_rest
    rt = np.zeros((3, 6))
    rt[1:] = rng.normal(size=(2, 6)) * 0.3
    J = np.zeros((ns, ns))
    for a in range(2):
        J[6 * a:6 * a + 6, 6 * a:6 * a + 6] = drt_dxi(rt[a + 1])
    cov = J @ np.linalg.inv(S) @ J.T
    r_parts = [rng.multivariate_normal(np.zeros(ns), Sk) for Sk in S_parts]
    parts = {k: (S_parts[k], r_parts[k]) for k in range(n_snap)}
    jk = jackknife(None, _Lin(S, sum(r_parts), parts), rt, cov)
    assert jk["n_snapshots"] == n_snap

    # Monte Carlo of the model: r_j ~ N(0, S_j), the rest too; moves by the exact one-step formula
    draws = 4000
    Ls = [np.linalg.cholesky(Sk + 1e-12 * np.eye(ns)) for Sk in S_parts]
    r = np.stack([rng.normal(size=(draws, ns)) @ L.T for L in Ls], axis=1)  # (draws, k, ns)
    r_rest = rng.normal(size=(draws, ns)) @ np.linalg.cholesky(S_rest).T
    R = r.sum(axis=1) + r_rest
    Si = np.linalg.inv(S)
    x = np.stack([np.linalg.solve(S - S_parts[k], (R - r[:, k]).T).T for k in range(n_snap)], axis=1) - (R @ Si)[:, None]
    moves = x @ J.T  # rt
    dev = moves - moves.mean(axis=1, keepdims=True)
    for a, i in enumerate((1, 2)):
        s = jk["sensors"][i]
        for part, key in ((slice(3, 6), "position"), (slice(0, 3), "orientation")):
            scale = 1e3 if key == "position" else np.degrees(1.0)
            axes = s[f"{key}_axes"]  # (3, 3): rows are the model's principal axes
            along = np.einsum("dkx,ax->dka", dev[:, :, 6 * a:6 * a + 6][:, :, part], axes)
            var_jk = (n_snap - 1) / n_snap * np.sum(along**2, axis=1)  # (draws, 3)
            ratio_mc = np.sqrt(var_jk) * scale / s[f"{key}_model_{'mm' if key == 'position' else 'deg'}"]
            # E[ratio^2] is what "expected" squares; its Monte Carlo error is ~ sqrt(2/dof/draws)
            se = np.sqrt(np.var(ratio_mc**2, axis=0) / draws)
            np.testing.assert_array_less(np.abs(np.mean(ratio_mc**2, axis=0) - s[f"{key}_ratio_expected"] ** 2), 4 * se)
            # the Satterthwaite range holds about 95 % of the draws
            lo, hi = s[f"{key}_ratio_expected_95"].T
            inside = np.mean((ratio_mc >= lo) & (ratio_mc <= hi), axis=0)
            assert np.all((inside > 0.90) & (inside < 0.99)), inside


def _capture(rng, ns=12, n_snap=10):
    """A random design: (S, parts S_k, rt, J)."""
    S_parts = [_spd(rng, ns, 6, 1.0) for _ in range(n_snap)]
    S = sum(S_parts) + _spd(rng, ns, ns, 0.3)
    rt = np.zeros((3, 6))
    rt[1:] = rng.normal(size=(2, 6)) * 0.3
    J = np.zeros((ns, ns))
    for a in range(2):
        J[6 * a:6 * a + 6, 6 * a:6 * a + 6] = drt_dxi(rt[a + 1])
    return S, S_parts, rt, J


def test_covariance_raised_only_where_the_jackknife_rejects_the_model():
    from clcgraph.backend.jackknife import raise_where_rejected

    rng = np.random.default_rng(11)
    raised, axes, back = {"right": 0, "too small": 0}, 0, []
    for trial in range(20):
        S, S_parts, rt, J = _capture(rng)
        model = J @ np.linalg.inv(S) @ J.T
        axes += 12
        # the data's errors as the model says, and 5x its variance (its sigmas 0.45x the truth)
        for scale, label in ((1.0, "right"), (5.0, "too small")):
            draws = [rng.multivariate_normal(np.zeros(len(S)), scale * Sk) for Sk in S_parts]
            parts = {k: (Sk, d) for k, (Sk, d) in enumerate(zip(S_parts, draws))}
            jk = jackknife(None, _Lin(S, sum(draws), parts), rt, model)
            cov = raise_where_rejected(model, jk)
            assert np.all(np.linalg.eigvalsh(cov - model) > -1e-12 * np.abs(model).max())  # only raised
            for a, i in enumerate((1, 2)):
                s = jk["sensors"][i]
                for what, o in (("orientation", 0), ("position", 3)):
                    V, f = np.asarray(s[f"{what}_axes"]), np.asarray(s[f"{what}_raised"])
                    blk = slice(6 * a + o, 6 * a + o + 3)
                    before = np.einsum("ax,xy,ay->a", V, model[blk, blk], V)
                    after = np.einsum("ax,xy,ay->a", V, cov[blk, blk], V)
                    np.testing.assert_allclose(after, f**2 * before, rtol=1e-9)
                    rejected = np.asarray(s[f"{what}_ratio"]) > np.asarray(s[f"{what}_ratio_expected_95"])[:, 1]
                    assert np.all((f > 1) == rejected)
                    # raised, the sigma is the jackknife's over the ratio the model expects
                    np.testing.assert_allclose(f[rejected], (s[f"{what}_ratio"] / s[f"{what}_ratio_expected"])[rejected])
                    raised[label] += int(rejected.sum())
                    if label == "too small":
                        back += list(after[rejected] / (scale * before[rejected]))
    # the model right: an axis is raised about 2.5 % of the time (its ratio above the 97.5 % point)
    assert raised["right"] <= 0.07 * axes, (raised, axes)
    # the sigmas 0.45x the truth: most axes are caught, and raised to about the true variance
    assert raised["too small"] >= 0.6 * axes, (raised, axes)
    assert 0.7 < np.median(back) < 1.5, np.median(back)


def test_a_snapshot_holding_all_but_a_rounding_share_of_a_direction_is_indispensable():
    """Whether the rest's normal matrix still passes Cholesky depends on the machine; the share it keeps
    does not: under 1e-6 of a direction's information left, the snapshot is indispensable."""
    from clcgraph.backend.jackknife import _INDISPENSABLE, kept_share

    rng = np.random.default_rng(0)
    Q = np.linalg.qr(rng.normal(size=(6, 6)))[0]
    D = np.diag(10.0 ** np.array([3, 3, 3, -1, -1, -2]))  # rad and m: the diagonal over decades
    S = D @ Q @ np.diag([10.0, 5, 3, 2, 1.5, 1]) @ Q.T @ D
    u = np.linalg.solve(D, Q[:, 5])  # a direction the snapshot holds all of but a share eps
    u /= np.sqrt(u @ S @ u)
    for eps, indispensable in ((1e-9, True), (1e-3, False)):
        S_k = (1 - eps) * np.outer(S @ u, S @ u)  # its information along u, all of S's but eps
        share = kept_share(S, S - S_k)
        assert abs(share - eps) < 1e-3 * eps, share
        assert (share < _INDISPENSABLE) == indispensable
