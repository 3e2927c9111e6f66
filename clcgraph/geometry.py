"""Rigid transforms: rt (mrcal's Rodrigues + translation 6-vector), Rt (4x3), 4x4, gtsam.Pose3;
the directions of points (azimuth, elevation) and angle arithmetic.

The only place conversions live. ``T_a_b`` / ``rt_a_b`` map points in frame b into frame a:
``x_a = R x_b + t``. Functions broadcast over leading dimensions where it is cheap.
gtsam is imported lazily so that the frontend can use this module without it.

SYNOPSIS
    >>> rt_a_c = compose_rt(rt_a_b, rt_b_c)
    >>> p_a = transform(rt_a_b, p_b)
    >>> pose = pose3_from_rt(rt_a_b); rt = rt_from_pose3(pose)
"""

from __future__ import annotations

import math

import numpy as np

_SMALL = 1e-7


def contiguous_arctan2(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``np.arctan2(y, x)`` with the same bits wherever numpy's output lands, e.g. the azimuths
    ``contiguous_arctan2(p[:, 1], p[:, 0])`` of (N,3) points.

    numpy 1.24 computes arctan2 with SVML's AVX-512 kernel unless input and output overlap, and
    its overlap check spans a strided column to ``start + step * len``, past the column's last
    element: an output that malloc places right after the points looks overlapping and gets
    libm's atan2, a bit off SVML's in a third of the values. Where malloc puts it changes from
    run to run (the LIDAR frontend's points moved by up to 5e-14 m between two processes).
    Contiguous copies never look overlapping, and cost less than SVML's strided loads save.
    np.sin, np.exp, np.power and the other SVML ufuncs share the check: pass them no strided columns."""
    return np.arctan2(np.ascontiguousarray(y), np.ascontiguousarray(x))


def azimuth(p: np.ndarray) -> np.ndarray:
    """(...,3) points -> (...) azimuth atan2(y, x) [rad] in [-pi, pi] (the same bits wherever
    numpy puts the output: contiguous_arctan2)."""
    p = np.asarray(p, dtype=float)
    return contiguous_arctan2(p[..., 1], p[..., 0])


def elevation(p: np.ndarray) -> np.ndarray:
    """(...,3) points -> (...) elevation above the x-y plane [rad] in [-pi/2, pi/2]."""
    p = np.asarray(p, dtype=float)
    return contiguous_arctan2(p[..., 2], np.hypot(p[..., 0], p[..., 1]))


def wrap_angle(a):
    """Angle(s) [rad] wrapped into [-pi, pi)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


def circular_mean(a: np.ndarray) -> float:
    """The mean direction [rad] of angles ``a`` (continuous across +-pi)."""
    return float(np.arctan2(np.mean(np.sin(a)), np.mean(np.cos(a))))


def skew(v: np.ndarray) -> np.ndarray:
    """(...,3) -> (...,3,3) cross-product matrix: skew(a) @ b == cross(a, b)."""
    v = np.asarray(v, dtype=float)
    K = np.zeros(v.shape[:-1] + (3, 3))  # filled in place: np.stack costs more than the rest of R_from_r
    K[..., 0, 1], K[..., 0, 2] = -v[..., 2], v[..., 1]
    K[..., 1, 0], K[..., 1, 2] = v[..., 2], -v[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -v[..., 1], v[..., 0]
    return K


def R_from_r(r: np.ndarray) -> np.ndarray:
    """Rodrigues vector(s) (...,3) -> rotation matrices (...,3,3)."""
    r = np.asarray(r, dtype=float)
    if r.shape == (3,):
        return _R_from_one_r(r)
    th2 = np.sum(r * r, axis=-1)[..., None, None]
    th = np.sqrt(th2)
    K = skew(r)
    small = th2 < _SMALL**2
    with np.errstate(invalid="ignore"):  # non-finite r: NaN out, quietly
        a = np.where(small, 1.0 - th2 / 6.0, np.sin(th) / np.where(small, 1.0, th))
        b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(th)) / np.where(small, 1.0, th2))
    return np.eye(3) + a * K + b * (K @ K)


def _R_from_one_r(r: np.ndarray) -> np.ndarray:
    """R_from_r of one (3,) vector in scalar arithmetic: the solver converts single poses tens of
    thousands of times, where numpy's per-call overhead is most of the cost (equal to the
    vectorized form to rounding; K K = r r^T - |r|^2 I)."""
    x, y, z = r.tolist()
    th2 = x * x + y * y + z * z
    if not math.isfinite(th2):  # non-finite r: NaN out, quietly (as the vectorized form)
        return np.full((3, 3), np.nan)
    if th2 < _SMALL**2:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        th = math.sqrt(th2)
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    c = 1.0 - b * th2
    return np.array([[c + b * x * x, b * x * y - a * z, b * x * z + a * y],
                     [b * x * y + a * z, c + b * y * y, b * y * z - a * x],
                     [b * x * z - a * y, b * y * z + a * x, c + b * z * z]])


def r_from_R(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (...,3,3) -> Rodrigues vectors (...,3), angle in [0, pi]."""
    R = np.asarray(R, dtype=float)
    if R.shape == (3, 3):
        one = _r_from_one_R(R)
        if one is not None:
            return one
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s = 0.5 * np.linalg.norm(w, axis=-1)  # sin(th)
    c = np.clip(0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0), -1.0, 1.0)  # cos(th)
    th = np.arctan2(s, c)
    out = np.empty(R.shape[:-2] + (3,))
    small = s < 1e-6
    near_pi = small & (c < 0)
    regular = ~small
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.where(regular, th / np.where(regular, 2 * s, 1), 0.5 + th * th / 12.0)
    out[...] = f[..., None] * w
    if np.any(near_pi):
        # th ~ pi: R ~ 2 a a^T - I; take the axis from the largest diagonal entry.
        Rp = R[near_pi]
        B = 0.5 * (Rp + np.eye(3))
        k = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        a = B[np.arange(len(k)), :, k]
        a /= np.linalg.norm(a, axis=-1, keepdims=True)
        # choose the sign consistent with the (tiny) antisymmetric part
        sgn = np.where(np.sum(a * w[near_pi], axis=-1) < 0, -1.0, 1.0)
        out[near_pi] = a * (sgn * th[near_pi])[..., None]
    return out


def _r_from_one_R(R: np.ndarray):
    """r_from_R of one (3,3) in scalar arithmetic (see _R_from_one_r), or None near 180 deg and
    for non-finite R, where the vectorized form decides."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    w0, w1, w2 = r21 - r12, r02 - r20, r10 - r01
    s = 0.5 * math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    c = min(max(0.5 * (r00 + r11 + r22 - 1.0), -1.0), 1.0)
    if not (math.isfinite(s) and math.isfinite(c)) or (s < 1e-6 and c < 0):
        return None
    th = math.atan2(s, c)
    f = th / (2 * s) if s >= 1e-6 else 0.5 + th * th / 12.0
    return np.array([f * w0, f * w1, f * w2])


def Rt_from_rt(rt: np.ndarray) -> np.ndarray:
    """(...,6) -> (...,4,3): rotation rows stacked over the translation row (mrcal's Rt)."""
    rt = np.asarray(rt, dtype=float)
    return np.concatenate([R_from_r(rt[..., :3]), rt[..., None, 3:]], axis=-2)


def rt_from_Rt(Rt: np.ndarray) -> np.ndarray:
    Rt = np.asarray(Rt, dtype=float)
    return np.concatenate([r_from_R(Rt[..., :3, :]), Rt[..., 3, :]], axis=-1)


def T_from_rt(rt: np.ndarray) -> np.ndarray:
    """(...,6) -> (...,4,4) homogeneous matrix."""
    rt = np.asarray(rt, dtype=float)
    T = np.zeros(rt.shape[:-1] + (4, 4))
    T[..., :3, :3] = R_from_r(rt[..., :3])
    T[..., :3, 3] = rt[..., 3:]
    T[..., 3, 3] = 1.0
    return T


def rt_from_T(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    return np.concatenate([r_from_R(T[..., :3, :3]), T[..., :3, 3]], axis=-1)


def rt_from_R_t(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.concatenate([r_from_R(R), np.asarray(t, dtype=float)], axis=-1)


def compose_rt(*rts: np.ndarray) -> np.ndarray:
    """compose_rt(rt_a_b, rt_b_c, ...) -> rt_a_c."""
    T = T_from_rt(rts[0])
    for rt in rts[1:]:
        T = T @ T_from_rt(rt)
    return rt_from_T(T)


def invert_rt(rt: np.ndarray) -> np.ndarray:
    """rt_a_b -> rt_b_a."""
    rt = np.asarray(rt, dtype=float)
    R = R_from_r(rt[..., :3])
    t = -np.einsum("...ji,...j->...i", R, rt[..., 3:])
    return np.concatenate([-rt[..., :3], t], axis=-1)


def transform(rt_a_b: np.ndarray, p_b: np.ndarray) -> np.ndarray:
    """Points (N,3) in frame b -> frame a, for one rt_a_b (6,)."""
    rt_a_b = np.asarray(rt_a_b, dtype=float)
    return np.asarray(p_b, dtype=float) @ R_from_r(rt_a_b[:3]).T + rt_a_b[3:]


def invert_T(T: np.ndarray) -> np.ndarray:
    """(4,4) inverse of a rigid transform (R^T, -R^T t), exact where np.linalg.inv rounds."""
    T = np.asarray(T, dtype=float)
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


# The one rotation format for people (tables, reports, the README): roll, pitch, yaw about the
# fixed (extrinsic) axes x, then y, then z, so R = Rz(yaw) Ry(pitch) Rx(roll): URDF's <origin rpy>
# and ROS tf's convention. Machine files keep mrcal's Rodrigues rt.
RPY_LABEL = "roll, pitch, yaw [deg] (fixed axes x-y-z)"


def rpy_from_R(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (...,3,3) -> (roll, pitch, yaw) (...,3) in rad, fixed axes x-y-z:
    R = Rz(yaw) Ry(pitch) Rx(roll); pitch in [-pi/2, pi/2]. At pitch = +-pi/2 (gimbal lock)
    roll is set to 0 and yaw carries the whole rotation about z."""
    R = np.asarray(R, dtype=float)
    pitch = np.arctan2(-R[..., 2, 0], np.hypot(R[..., 0, 0], R[..., 1, 0]))
    locked = np.hypot(R[..., 0, 0], R[..., 1, 0]) < 1e-9
    roll = np.where(locked, 0.0, np.arctan2(R[..., 2, 1], R[..., 2, 2]))
    yaw = np.where(locked, np.arctan2(-R[..., 0, 1], R[..., 1, 1]), np.arctan2(R[..., 1, 0], R[..., 0, 0]))
    return np.stack([roll, pitch, yaw], axis=-1)


def R_from_rpy(rpy: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) (...,3) in rad, fixed axes x-y-z -> R = Rz(yaw) Ry(pitch) Rx(roll) (...,3,3)."""
    # the angles as contiguous rows: numpy's SVML sin/cos of a strided column fall back to libm's,
    # a bit off, where malloc puts the output right after the input (contiguous_arctan2)
    r, p, y = np.ascontiguousarray(np.moveaxis(np.asarray(rpy, dtype=float), -1, 0))
    cr, cp, cy = np.cos(r), np.cos(p), np.cos(y)
    sr, sp, sy = np.sin(r), np.sin(p), np.sin(y)
    return np.stack([
        np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
        np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
        np.stack([-sp, cp * sr, cp * cr], -1),
    ], -2)


def rpy_deg_from_R(R: np.ndarray) -> np.ndarray:
    """rpy_from_R in degrees, for printing."""
    return np.degrees(rpy_from_R(R))


def rpy_deg_from_rt(rt: np.ndarray) -> np.ndarray:
    """rt (...,6) or r (...,3) -> roll, pitch, yaw [deg] of its rotation (RPY_LABEL's convention)."""
    return rpy_deg_from_R(R_from_r(np.asarray(rt, dtype=float)[..., :3]))


def T_from_xyz_rpy(xyz, rpy_deg) -> np.ndarray:
    """(4,4) from a position [m] and roll, pitch, yaw [deg] (see rpy_from_R): how rigs are written."""
    T = np.eye(4)
    T[:3, :3] = R_from_rpy(np.radians(rpy_deg))
    T[:3, 3] = np.asarray(xyz, dtype=float)
    return T


def pose3_from_rt(rt: np.ndarray):
    """(6,) rt -> gtsam.Pose3."""
    import gtsam

    T = T_from_rt(rt)
    return gtsam.Pose3(gtsam.Rot3(T[:3, :3]), T[:3, 3])


def rt_from_pose3(pose) -> np.ndarray:
    """gtsam.Pose3 -> (6,) rt."""
    return rt_from_T(pose.matrix())


def T_exp(xi: np.ndarray) -> np.ndarray:
    """(4,4) Exp of a GTSAM Pose3 tangent xi = [omega, v]."""
    import gtsam

    return gtsam.Pose3.Expmap(np.asarray(xi, dtype=float)).matrix()


def xi_log(T: np.ndarray) -> np.ndarray:
    """(6,) GTSAM Pose3 tangent [omega, v] of a (4,4): T == T_exp(xi_log(T))."""
    import gtsam

    return np.asarray(gtsam.Pose3.Logmap(gtsam.Pose3(np.asarray(T, dtype=float))))


def so3_right_jacobian(r: np.ndarray) -> np.ndarray:
    """Jr(r), (3,3): Exp(r + dr) = Exp(r) Exp(Jr(r) dr) to first order."""
    r = np.asarray(r, dtype=float)
    th = np.linalg.norm(r)
    K = skew(r)
    if th < 1e-6:
        return np.eye(3) - 0.5 * K + (K @ K) / 6.0
    return np.eye(3) - (1.0 - np.cos(th)) / th**2 * K + (th - np.sin(th)) / th**3 * (K @ K)


def so3_right_jacobian_inverse(r: np.ndarray) -> np.ndarray:
    """Jr^{-1}(r): d Log(Exp(r) Exp(w)) / dw at w = 0, (3,3)."""
    r = np.asarray(r, dtype=float)
    th = np.linalg.norm(r)
    K = skew(r)
    if th < 1e-6:
        return np.eye(3) + 0.5 * K + (K @ K) / 12.0
    c = 1.0 / th**2 - (1.0 + np.cos(th)) / (2.0 * th * np.sin(th))
    return np.eye(3) + 0.5 * K + c * (K @ K)


def drt_dxi(rt: np.ndarray) -> np.ndarray:
    """(6,6) Jacobian of rt(T Exp(xi)) at xi = 0, xi = [omega, v] (GTSAM's Pose3 tangent).

    Maps a GTSAM Pose3 covariance into rt coordinates: Var_rt = J Var_xi J^T.
    """
    rt = np.asarray(rt, dtype=float)
    J = np.zeros((6, 6))
    J[:3, :3] = so3_right_jacobian_inverse(rt[:3])
    J[3:, 3:] = R_from_r(rt[:3])
    return J


def tangent_covariance_from_rt(rt: np.ndarray, covariance_rt: np.ndarray) -> np.ndarray:
    """Covariance in rt coordinates -> covariance of GTSAM's tangent xi = [omega, v] about the
    same poses (right perturbation ``T = T_solved Exp(xi)``: omega and v along the sensor's own
    axes). ``rt``: (6,) or (N,6) poses; ``covariance_rt``: (6N,6N) over them in that order.

    The inverse of ``drt_dxi``: Var_xi = J^-1 Var_rt J^-T, J^-1 = diag(Jr(r), R^T). Unlike the
    diagonal of Var_rt, this is not inflated by the Rodrigues chart ((th/2)/sin(th/2)
    perpendicular to the axis: 1.57x for a sensor turned 180 deg).
    """
    rts = np.asarray(rt, dtype=float).reshape(-1, 6)
    C = np.asarray(covariance_rt, dtype=float)
    Jinv = np.zeros_like(C)
    for k, x in enumerate(rts):
        Jinv[6 * k:6 * k + 3, 6 * k:6 * k + 3] = so3_right_jacobian(x[:3])
        Jinv[6 * k + 3:6 * k + 6, 6 * k + 3:6 * k + 6] = R_from_r(x[:3]).T
    out = Jinv @ C @ Jinv.T
    return 0.5 * (out + out.T)


def pose_stdevs(rt: np.ndarray, covariance_rt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis 1-sigmas of one pose from its (6,6) rt covariance, for people:
    (rotation (3,) rad about the sensor's own x, y, z: the tangent omega of ``R = R_solved Exp(omega)``,
    GTSAM's right perturbation; position (3,) m of the sensor's origin along the reference
    frame's x, y, z: the rt translation, which is linear, so exact).

    The one place orientation sigmas come from (never ``sqrt(diag(cov_rt))[:3]``, see
    tangent_covariance_from_rt).
    """
    rt = np.asarray(rt, dtype=float).reshape(6)
    C = np.asarray(covariance_rt, dtype=float).reshape(6, 6)
    Jr = so3_right_jacobian(rt[:3])
    rot = np.sqrt(np.maximum(np.diag(Jr @ C[:3, :3] @ Jr.T), 0.0))
    pos = np.sqrt(np.maximum(np.diag(C[3:, 3:]), 0.0))
    return rot, pos


def pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(rotation angle rad, translation m) of T_a^-1 T_b: how far pose b is from pose a, by
    composing (never by subtracting rt vectors, which jump by 2 pi near 180 deg). The
    translation's norm is the distance between the two origins."""
    E = np.linalg.inv(np.asarray(T_a, dtype=float)) @ np.asarray(T_b, dtype=float)
    c = np.clip(0.5 * (np.trace(E[:3, :3]) - 1.0), -1.0, 1.0)
    s = 0.5 * np.linalg.norm([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]])
    return float(np.arctan2(s, c)), float(np.linalg.norm(E[:3, 3]))

