"""LIDAR board-edge factor: the board's in-plane position from where a LIDAR saw its outline.

A plane factor pins the board's tilt and offset; where the board sits within its plane only
its outline shows. Each edge interval (frontend/board_edges.py) is two rays of the LIDAR: one
that hit the board and the next one, which passed its edge, with the side of the board between
them as the LIDAR saw it (turned into the board's own side by the board's orientation when the
factor is built: ``edge_sides``). Both rays are crossed with the board's plane (from the sensor
and board poses) and expressed in the board frame as ``q_in`` and ``q_out``; the side's
coordinate ``a`` (x or y) is ``h`` there. The edge lies uniformly between the two crossings,
so the residual is

    err = (q_in[a] + q_out[a]) / 2 - h        (m)

with sigma^2 = L^2 / 12 (L = |q_out[a] - q_in[a]|, the uniform quantisation) plus the beam's
blur at the edge (``beam_rad`` times the range; the measured ranges do not enter), and a
Huber loss: an edge hidden from the LIDAR that the frontend did not catch costs little.
The quantisation is one error for all of a side's intervals where they lie side by side (the
rings crossing an upright side at the same columns, one ring pair along a level top): their
intersection, W wide, holds the side, so together they tell it to W / sqrt(12), not L /
sqrt(12 n); each side's sigmas are scaled up to that where it is less than they claim
(``edge_sigmas``; staggered intervals, W << L, keep theirs).

Jacobians (right perturbation ``T Exp([omega, v])``, rotation first): with T_bs = T_b^-1 T_s the
sensor in the board frame, a ray u leaves o = t_bs along w = R_bs u and meets the face it sees, z = f
(0, or the board's thickness from behind: graph.lidar_face), at q = o + lam w, lam = (f - o_z) / w_z.
For a change dp of o + lam w at fixed lam, dq = (I - w e3^T / w_z) dp;
dp = R_bs (dv - [lam u]x domega) for the sensor's perturbation, [q]x domega - dv for the board's.

SYNOPSIS
    keep, axis, bounds, ends, r = edge_sides(T_lidar0_sensor, T_lidar0_board, rays (E,3,3), board)  # at an estimate
    sig = edge_sigmas(ends[keep], r[keep], axis[keep], bounds[keep], beam_rad=0.0013)
    f = lidar_edge_factor(S(1), B(7), rays[keep], axis[keep], bounds[keep], sig)
    r = lidar_edge_residuals(T_lidar0_sensor, T_lidar0_board, rays, axis, bounds)   # (E,) m
"""

from __future__ import annotations

import numpy as np

from .base import make_factor

_MIN_WZ = 0.05  # |cos| of a ray's angle to the board normal below which it grazes the board
HUBER_K = 1.345  # the Huber threshold in sigmas (95 % efficiency on Gaussian errors)


def _crossings(T_sensor, T_board, rays: np.ndarray, face_m: float):
    """(q (M,3) board frame, w (M,3), lam (M,), R_bs) for the M rays ``rays`` (M,3), sensor frame,
    crossed with the board face z = ``face_m``."""
    import gtsam

    T_s = gtsam.Pose3() if T_sensor is None else T_sensor
    T_bs = T_board.between(T_s)
    R_bs, o = T_bs.rotation().matrix(), T_bs.translation()
    w = rays @ R_bs.T
    wz = np.where(np.abs(w[:, 2]) < _MIN_WZ, np.where(w[:, 2] < 0, -_MIN_WZ, _MIN_WZ), w[:, 2])
    lam = (face_m - o[2]) / wz
    q = o + lam[:, None] * w
    return q, w, wz, lam, R_bs


def _residual(T_sensor, T_board, rays: np.ndarray, axis: np.ndarray, bounds: np.ndarray, want: bool,
              face_m: float = 0.0):
    """``rays`` (E,2,3) or (E,3,3) (the side normals, unused here)."""
    E = len(axis)
    rays = rays[:, :2]
    q, w, wz, lam, R_bs = _crossings(T_sensor, T_board, rays.reshape(-1, 3), face_m)
    sel = np.repeat(axis, 2)  # per ray: the coordinate its interval bounds
    qa = q[np.arange(2 * E), sel]
    err = 0.5 * (qa[0::2] + qa[1::2]) - bounds
    if not want:
        return err, None
    # row a of (I - w e3^T / w_z): e_a - (w_a / w_z) e3
    P = np.zeros((2 * E, 3))
    P[np.arange(2 * E), sel] = 1.0
    P[:, 2] -= w[np.arange(2 * E), sel] / wz
    J_b = np.empty((2 * E, 6))
    J_b[:, :3] = np.cross(P, q)  # P . ([q]x domega) = (P x q) . domega
    J_b[:, 3:] = -P
    J_b = 0.5 * (J_b[0::2] + J_b[1::2])
    if T_sensor is None:
        return err, [J_b]
    PR = P @ R_bs  # d/dv_s
    u = rays.reshape(-1, 3)
    J_s = np.empty((2 * E, 6))
    J_s[:, :3] = -np.einsum("mi,mij->mj", PR, skew_rows(lam[:, None] * u))
    J_s[:, 3:] = PR
    J_s = 0.5 * (J_s[0::2] + J_s[1::2])
    return err, [J_s, J_b]


def skew_rows(x: np.ndarray) -> np.ndarray:
    """(M,3,3) skew matrices of the rows of ``x``."""
    S = np.zeros((len(x), 3, 3))
    S[:, 0, 1], S[:, 0, 2], S[:, 1, 2] = -x[:, 2], x[:, 1], -x[:, 0]
    S[:, 1, 0], S[:, 2, 0], S[:, 2, 1] = x[:, 2], -x[:, 1], x[:, 0]
    return S


def edge_sides(T_lidar0_sensor, T_lidar0_board, rays: np.ndarray, board, *, face_m: float = 0.0,
               min_cos: float = 0.9):
    """Which board side each interval bounds, at a pose estimate: (keep (E,) bool, axis (E,) 0 x /
    1 y, bounds (E,) m, ends (E,2) m: where its two rays cross the plane along that axis, ranges (E,) m
    to the edge). ``rays``
    (E,3,3): per interval the two rays and the outward normal of the side the LIDAR saw it leave
    (frontend/board_edges.py), all in the sensor frame. The normal, turned into the board frame by
    the estimate's rotation, names the side (only the board's orientation is used, not where it
    sits in its plane); kept where it is within acos(``min_cos``) of that side's normal and both
    rays meet the face ``face_m`` ahead."""
    rays = np.asarray(rays, float).reshape(-1, 3, 3)
    E = len(rays)
    q, _, _, lam, R_bs = _crossings(T_lidar0_sensor, T_lidar0_board, rays[:, :2].reshape(-1, 3), face_m)
    nb = rays[:, 2] @ R_bs.T  # the sides' normals in the board frame
    axis = np.argmax(np.abs(nb[:, :2]), axis=1)
    c = nb[np.arange(E), axis]
    xmin, xmax, ymin, ymax = board.extent()
    lo, hi = np.array([xmin, ymin]), np.array([xmax, ymax])
    bounds = np.where(c > 0, hi[axis], lo[axis])
    ends = np.c_[q[0::2, :2][np.arange(E), axis], q[1::2, :2][np.arange(E), axis]]
    keep = (np.abs(c) >= min_cos) & (lam[0::2] > 0) & (lam[1::2] > 0)
    return keep, axis, bounds, ends, lam[0::2]  # w is a unit vector: lam is the range to the crossing


def lidar_edge_residuals(T_lidar0_sensor, T_lidar0_board, rays, axis, bounds, face_m: float = 0.0) -> np.ndarray:
    """(E,) m: each interval's midpoint along its board side's axis minus the side's bound."""
    return _residual(T_lidar0_sensor, T_lidar0_board, np.asarray(rays, float), np.asarray(axis), np.asarray(bounds, float),
                     False, face_m)[0]


def edge_sigmas(ends: np.ndarray, ranges: np.ndarray, axis: np.ndarray, bounds: np.ndarray, *,
                beam_rad: float) -> np.ndarray:
    """(E,) m: the uniform quantisation of each interval (L / sqrt(12), L = |ends[:, 1] - ends[:, 0]|)
    and the beam's blur at the edge (``beam_rad`` x range: where along a partly covered footprint
    a return still comes from the board) in quadrature; the range noise does not enter (both rays
    are crossed with the board's plane, their measured ranges are not used). Per side (``axis``,
    ``bounds``), scaled by one factor where the intervals' common part W says less than their
    sigmas together claim: the side known to W^2 / 12 plus the blur averaged over them."""
    ends, axis, bounds = np.asarray(ends, float).reshape(-1, 2), np.asarray(axis), np.asarray(bounds, float)
    blur2 = (beam_rad * np.asarray(ranges, float)) ** 2
    var = (ends[:, 1] - ends[:, 0]) ** 2 / 12 + blur2
    lo, hi = ends.min(axis=1), ends.max(axis=1)
    # the sides as a set of Python pairs: np.unique over rows cost twice the rest (a graph is built ~20 times)
    for a, b in set(zip(axis.tolist(), bounds.tolist())):
        sel = (axis == a) & (bounds == b)
        if np.count_nonzero(sel) < 2:
            continue
        W = hi[sel].min() - lo[sel].max()
        if W <= 0:
            continue
        b2 = blur2[sel]
        shared = W**2 / 12 + (1 / np.sum(1 / b2) if np.all(b2 > 0) else 0.0)
        var[sel] *= max(1.0, shared * np.sum(1 / var[sel]))
    return np.sqrt(var)


def lidar_edge_factor(sensor_key: int | None, board_key: int, rays, axis, bounds, sigmas, *, face_m: float = 0.0):
    """The edge factor of one LIDAR observation of the board face ``face_m``: keys (sensor, board), or
    (board) for lidar0 (``sensor_key`` None); a Huber loss on sigmas ``sigmas`` (E,)."""
    import gtsam

    rays = np.array(rays, dtype=float)[:, :2].copy()
    axis = np.asarray(axis, np.int64)
    bounds = np.asarray(bounds, float)
    if sensor_key is None:
        fn = lambda poses, want: _residual(None, poses[0], rays, axis, bounds, want, face_m)  # noqa: E731
        keys = [board_key]
    else:
        fn = lambda poses, want: _residual(poses[0], poses[1], rays, axis, bounds, want, face_m)  # noqa: E731
        keys = [sensor_key, board_key]
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(HUBER_K),
                                           gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, float)))
    return make_factor(keys, noise, fn)
