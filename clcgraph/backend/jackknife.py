"""The leave-one-snapshot-out (jackknife) check of the reported covariance.

Each snapshot (board pose) is left out in turn and the sensor poses re-solved by one
Gauss-Newton step from the final linearization: the snapshot's board and D variables are
marginalized out of the normal equations (noise.Linearization.reduced, a Schur complement),
so leaving snapshot k out is ``dx_k = (S - S_k)^-1 (r - r_k)`` on the sensors only: a few
small solves instead of a re-solve per snapshot. The spread of the answers,
``C_jk = (n-1)/n sum_k (x_k - mean)(x_k - mean)^T``, estimates the sensors' covariance
without trusting the noise model; it is compared with the model covariance along the
model's principal axes (per sensor, position in lidar0 and orientation, rt coordinates).
A ratio near 1 says the sigmas can be trusted; the largest single-snapshot move says which
board to re-take.

SYNOPSIS
    jk = jackknife(problem, lin, rt_lidar0_sensor, covariance_rt)
    jk["sensors"][2]["position_ratio"]      # jackknife / model sigma along the 3 principal axes
    jk["largest_influence"]                  # {"sensor", "snapshot", "position_mm", "orientation_deg"}
"""

from __future__ import annotations

import numpy as np

from ..geometry import drt_dxi

_MIN_SNAPSHOTS = 4  # fewer: the spread says nothing


def _axes(C_model: np.ndarray, C_jk: np.ndarray, scale: float) -> dict:
    lam, V = np.linalg.eigh(C_model)
    V = V * np.sign(V[np.argmax(np.abs(V), axis=0), np.arange(3)])  # each axis' largest component positive
    model = np.sqrt(np.maximum(lam, 0.0))
    jk = np.sqrt(np.maximum(np.einsum("ia,ij,ja->a", V, C_jk, V), 0.0))
    return {"axes": V.T, "model": model * scale, "jackknife": jk * scale,
            "ratio": np.where(model > 0, jk / np.where(model > 0, model, 1.0), np.nan)}


def jackknife(problem, lin, rt_lidar0_sensor: np.ndarray, covariance_rt: np.ndarray) -> dict:
    """Leave-one-snapshot-out spread vs the model covariance (module doc); {} if < 4 snapshots."""
    S, r, parts = lin.reduced()
    if lin.ns == 0 or len(parts) < _MIN_SNAPSHOTS:
        return {}
    x_full = np.linalg.solve(S, r)
    J = np.zeros((lin.ns, lin.ns))  # tangent -> rt, per sensor
    for a, i in enumerate(lin.variable_sensors):
        J[6 * a:6 * a + 6, 6 * a:6 * a + 6] = drt_dxi(rt_lidar0_sensor[i])
    moves, indispensable = {}, []
    for k in sorted(parts):
        S_k, r_k = parts[k]
        try:
            np.linalg.cholesky(S - S_k)
        except np.linalg.LinAlgError:  # without this board some sensor is not determined
            indispensable.append(k)
            continue
        moves[k] = J @ (np.linalg.solve(S - S_k, r - r_k) - x_full)
    ks = sorted(moves)
    X = np.array([moves[k] for k in ks])
    n = len(ks)
    if n < _MIN_SNAPSHOTS:
        return {}
    dX = X - X.mean(axis=0)
    C_jk = (n - 1) / n * dX.T @ dX
    sensors, worst = {}, None
    for a, i in enumerate(lin.variable_sensors):
        blk = slice(6 * a, 6 * a + 6)
        Cm, Cj = np.asarray(covariance_rt)[blk, blk], C_jk[blk, blk]
        pos = _axes(Cm[3:, 3:], Cj[3:, 3:], 1e3)
        rot = _axes(Cm[:3, :3], Cj[:3, :3], np.degrees(1.0))
        dp = np.linalg.norm(X[:, 6 * a + 3:6 * a + 6], axis=1) * 1e3
        dr = np.degrees(np.linalg.norm(X[:, 6 * a:6 * a + 3], axis=1))
        m = int(np.argmax(dp))
        big = {"snapshot": int(ks[m]), "position_mm": float(dp[m]), "orientation_deg": float(dr[m])}
        sensors[i] = {"position_axes": pos["axes"], "position_model_mm": pos["model"],
                      "position_jackknife_mm": pos["jackknife"], "position_ratio": pos["ratio"],
                      "orientation_axes": rot["axes"], "orientation_model_deg": rot["model"],
                      "orientation_jackknife_deg": rot["jackknife"], "orientation_ratio": rot["ratio"],
                      "largest_influence": big}
        if worst is None or big["position_mm"] > worst["position_mm"]:
            worst = {"sensor": i, **big}
    return {"method": "one-step Gauss-Newton from the final linearization, one snapshot left out at a time",
            "n_snapshots": n, "indispensable_snapshots": indispensable, "covariance_rt": C_jk,
            "moves_rt": {int(k): moves[k] for k in ks}, "sensors": sensors, "largest_influence": worst}
