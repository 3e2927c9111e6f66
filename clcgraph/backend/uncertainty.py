"""Propagate the solve's joint pose covariance to transformed points.

The solve reports ``covariance_rt``: the joint covariance of ``rt_lidar0_sensor`` over the
non-reference sensors (6(N-1) square, mrcal rt coordinates, sensor order). A point p_i in
sensor i maps to sensor j as p_j = T_j_lidar0 T_lidar0_i p_i; its covariance is J C J^T with
J the analytic Jacobian of that composition w.r.t. the rt parameters of sensors i and j.
"""

from __future__ import annotations

import numpy as np

from clcgraph.geometry import R_from_r, skew, so3_right_jacobian


def point_transform_jacobians(rt_lidar0_sensor: np.ndarray, i: int, j: int, p_i: np.ndarray):
    """p_j and its Jacobians w.r.t. rt_lidar0_sensor[i] and rt_lidar0_sensor[j].

    p_i: (...,3) in sensor i. Returns (p_j (...,3), dpj_drti (...,3,6), dpj_drtj (...,3,6)).
    When i == j the two Jacobians cancel (p_j = p_i); both are returned as computed.
    """
    rts = np.asarray(rt_lidar0_sensor, dtype=float)
    p_i = np.asarray(p_i, dtype=float)
    ri, ti = rts[i, :3], rts[i, 3:]
    rj, tj = rts[j, :3], rts[j, 3:]
    Ri, Rj = R_from_r(ri), R_from_r(rj)
    q = p_i @ Ri.T + ti  # in lidar0
    v = q - tj
    p_j = v @ Rj  # R_j^T v
    # d(R(r) p)/dr = -R [p]x Jr(r)
    dq_dri = -np.einsum("ab,...bc,cd->...ad", Ri, skew(p_i), so3_right_jacobian(ri))
    shape = p_i.shape[:-1]
    dpj_drti = np.empty(shape + (3, 6))
    dpj_drti[..., :3] = np.einsum("ba,...bc->...ac", Rj, dq_dri)
    dpj_drti[..., 3:] = Rj.T
    # R_j^T = R(-r_j): d(R(-r) v)/dr = R(-r) [v]x Jr(-r)
    dpj_drtj = np.empty(shape + (3, 6))
    dpj_drtj[..., :3] = np.einsum("ba,...bc,cd->...ad", Rj, skew(v), so3_right_jacobian(-rj))
    dpj_drtj[..., 3:] = -Rj.T
    return p_j, dpj_drti, dpj_drtj


def _variable_index(reference: int, i: int) -> int | None:
    """Block index of sensor i in covariance_rt (None for the reference)."""
    if i == reference:
        return None
    return i if i < reference else i - 1


def point_transform_covariance(
    rt_lidar0_sensor: np.ndarray, covariance_rt: np.ndarray, reference: int, i: int, j: int, p_i: np.ndarray
) -> np.ndarray:
    """Covariance (...,3,3) of p_j = T_j_lidar0 T_lidar0_i p_i for points p_i (...,3).

    Uses the joint covariance (cross terms between i and j included). Zero when i == j or when
    both are the reference.
    """
    p_i = np.asarray(p_i, dtype=float)
    if i == j:
        return np.zeros(p_i.shape[:-1] + (3, 3))
    _, Ji, Jj = point_transform_jacobians(rt_lidar0_sensor, i, j, p_i)
    blocks, jacs = [], []
    for s, Js in ((i, Ji), (j, Jj)):
        k = _variable_index(reference, s)
        if k is not None:
            blocks.append(k)
            jacs.append(Js)
    if not blocks:
        return np.zeros(p_i.shape[:-1] + (3, 3))
    C = np.asarray(covariance_rt, dtype=float)
    idx = np.concatenate([np.arange(6 * k, 6 * k + 6) for k in blocks])
    Csub = C[np.ix_(idx, idx)]
    J = np.concatenate(jacs, axis=-1)  # (...,3,6 or 12)
    return np.einsum("...ab,bc,...dc->...ad", J, Csub, J)


def worst_direction_stdev(
    rt_lidar0_sensor: np.ndarray, covariance_rt: np.ndarray, reference: int, i: int, j: int, p_i: np.ndarray
) -> np.ndarray:
    """(...,) sqrt of the largest eigenvalue of point_transform_covariance (m)."""
    V = point_transform_covariance(rt_lidar0_sensor, covariance_rt, reference, i, j, p_i)
    return np.sqrt(np.maximum(largest_eigenvalue_sym3(V), 0.0))


def largest_eigenvalue_sym3(V: np.ndarray) -> np.ndarray:
    """(...,3,3) symmetric -> (...,) largest eigenvalue, in closed form (the trigonometric
    solution of the characteristic cubic).

    Not np.linalg.eigvalsh: its LAPACK gives different last digits with the BLAS thread count
    (OMP_NUM_THREADS), and the outputs must be the same bytes on every machine.
    """
    V = np.asarray(V, dtype=float)
    q = np.trace(V, axis1=-2, axis2=-1) / 3.0
    off = V[..., 0, 1] ** 2 + V[..., 0, 2] ** 2 + V[..., 1, 2] ** 2
    d = np.diagonal(V, axis1=-2, axis2=-1) - q[..., None]
    p = np.sqrt((np.sum(d * d, axis=-1) + 2.0 * off) / 6.0)
    safe = np.where(p > 0, p, 1.0)
    B = (V - q[..., None, None] * np.eye(3)) / safe[..., None, None]
    half_det = 0.5 * (B[..., 0, 0] * (B[..., 1, 1] * B[..., 2, 2] - B[..., 1, 2] * B[..., 2, 1])
                      - B[..., 0, 1] * (B[..., 1, 0] * B[..., 2, 2] - B[..., 1, 2] * B[..., 2, 0])
                      + B[..., 0, 2] * (B[..., 1, 0] * B[..., 2, 1] - B[..., 1, 1] * B[..., 2, 0]))
    phi = np.arccos(np.clip(half_det, -1.0, 1.0)) / 3.0
    return np.where(p > 0, q + 2.0 * p * np.cos(phi), q)


def result_point_covariance(result, i: int, j: int, p_i: np.ndarray) -> np.ndarray:
    """point_transform_covariance for a types.Result: (...,3,3)."""
    return point_transform_covariance(
        result.rt_lidar0_sensor, result.covariance_rt, result.problem.reference, i, j, p_i
    )


def result_worst_stdev(result, i: int, j: int, p_i: np.ndarray) -> np.ndarray:
    """worst_direction_stdev for a types.Result: (...,) m."""
    return worst_direction_stdev(
        result.rt_lidar0_sensor, result.covariance_rt, result.problem.reference, i, j, p_i
    )
