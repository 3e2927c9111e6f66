"""Every factor: zero residual at the truth, analytic Jacobians equal central differences at
random poses, the ``H is None`` path, and the whitened error GTSAM sees."""

import gtsam
import numpy as np
import pytest

from clcgraph import cameras
from clcgraph.factors.base import check_jacobians, perturb
from clcgraph.factors.board_prior import board_prior_factor
from clcgraph.factors.camera_corners import _residual as corners_fn, camera_corners_factor, camera_corners_residuals
from clcgraph.factors.lidar_plane import _residual as plane_fn, lidar_plane_factor, lidar_plane_residuals
from clcgraph.factors.lidar_range import _residual as range_fn, lidar_range_factor, lidar_range_residuals
from clcgraph.factors.pose_prior import _residual as prior_fn, pose_prior_factor
from clcgraph.types import BoardGeometry

BOARD = BoardGeometry()
S, B = gtsam.symbol("s", 1), gtsam.symbol("b", 0)


def _pose(rng, rot=0.5, trans=1.0):
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, rot, 3)), rng.normal(0, trans, 3))


def _scene(rng, face=0.0):
    """A board 4 m in front of lidar0 and a sensor 0.5 m away; points on its face z = ``face``
    (0: the pattern's; the thickness: the back) in the sensor frame."""
    T_b = gtsam.Pose3(gtsam.Rot3.Ypr(*rng.uniform(-0.4, 0.4, 3)) * gtsam.Rot3.Ypr(0, np.pi / 2, -np.pi / 2),
                      np.array([4.0, rng.uniform(-1, 1), 0.3]))
    T_s = _pose(rng, 0.2, 0.5)
    uv = rng.uniform(0, 1.0, (40, 2))
    on_board = np.c_[uv, np.full(40, face)]
    p_lidar0 = np.array([T_b.transformFrom(x) for x in on_board])
    p_sensor = np.array([T_s.transformTo(x) for x in p_lidar0])
    return T_s, T_b, p_sensor


def _values(**poses):
    v = gtsam.Values()
    for k, p in poses.items():
        v.insert({"s": S, "b": B}[k], p)
    return v


@pytest.mark.parametrize("face", [0.0, 0.012])
@pytest.mark.parametrize("fn,resid,factor", [(plane_fn, lidar_plane_residuals, lidar_plane_factor),
                                             (range_fn, lidar_range_residuals, lidar_range_factor)])
def test_lidar_factors(fn, resid, factor, face):
    rng = np.random.default_rng(1)
    for _ in range(5):
        T_s, T_b, p = _scene(rng, face)
        assert np.abs(resid(T_s, T_b, p, face)).max() < 1e-12
        if face:  # against the pattern's face the points are the thickness off
            assert np.abs(resid(T_s, T_b, p)).min() >= face - 1e-12
        p_lidar0 = np.array([T_s.transformFrom(x) for x in p])
        assert np.abs(resid(None, T_b, p_lidar0, face)).max() < 1e-12
        # Jacobians at perturbed (non-zero residual) poses, with and without a sensor variable
        Ts2, Tb2 = perturb(T_s, rng.normal(0, 0.05, 6)), perturb(T_b, rng.normal(0, 0.05, 6))
        assert check_jacobians(lambda P, w: fn(P[0], P[1], p, w, face_m=face), [Ts2, Tb2]) < 1e-6
        assert check_jacobians(lambda P, w: fn(None, P[0], p, w, face_m=face), [Tb2]) < 1e-6
        f = factor(S, B, p, 0.02, face_m=face)
        v = _values(s=Ts2, b=Tb2)
        e = resid(Ts2, Tb2, p, face)
        np.testing.assert_allclose(f.unwhitenedError(v), e, rtol=1e-12, atol=1e-15)  # H is None path
        assert f.error(v) == pytest.approx(0.5 * np.sum((e / 0.02) ** 2), rel=1e-10)
        lin = f.linearize(v)  # the H path through GTSAM
        A = lin.jacobian()[0]
        _, J = fn(Ts2, Tb2, p, True, face_m=face)
        np.testing.assert_allclose(A, np.hstack(J) / 0.02, rtol=1e-9, atol=1e-9)
        f0 = factor(None, B, p, 0.02)
        assert f0.keys() == [B]


def test_range_and_plane_agree_near_the_normal():
    rng = np.random.default_rng(2)
    T_s, T_b, p = _scene(rng)
    Tb2 = perturb(T_b, np.r_[0, 0, 0, 0, 0, 0.003])  # move the board 3 mm along its normal
    d_plane = lidar_plane_residuals(T_s, Tb2, p)
    d_range = lidar_range_residuals(T_s, Tb2, p)
    cos = np.abs((p / np.linalg.norm(p, axis=1)[:, None]) @ (T_s.rotation().matrix().T @ Tb2.rotation().matrix()[:, 2]))
    # range error = plane distance / cos(incidence), to first order
    np.testing.assert_allclose(np.abs(d_range) * cos, np.abs(d_plane), rtol=1e-3)


def test_range_clamps_grazing_rays():
    rng = np.random.default_rng(3)
    T_s, T_b, p = _scene(rng)
    n_s = T_s.rotation().matrix().T @ T_b.rotation().matrix()[:, 2]
    graze = np.cross(n_s, [0.3, 0.2, 0.9])
    graze = 5 * graze / np.linalg.norm(graze)  # exactly parallel to the plane
    err, J = range_fn(T_s, T_b, np.vstack([p, graze]), True)
    assert np.all(np.isfinite(err)) and all(np.all(np.isfinite(j)) for j in J)


LENSES = {
    "LENSMODEL_PINHOLE": [1200.0, 1210.0, 511.5, 383.5],
    "LENSMODEL_OPENCV4": [1200.0, 1210.0, 511.5, 383.5, -0.1, 0.02, 1e-3, -2e-3],
    "LENSMODEL_OPENCV5": [1200.0, 1210.0, 511.5, 383.5, -0.1, 0.02, 1e-3, -2e-3, 0.01],
    "LENSMODEL_OPENCV8": [1200.0, 1210.0, 511.5, 383.5, -0.1, 0.02, 1e-3, -2e-3, 0.01, 0.05, -0.01, 0.002],
    "LENSMODEL_OPENCV12": [1200.0, 1210.0, 511.5, 383.5, -0.1, 0.02, 1e-3, -2e-3, 0.01, 0.05, -0.01, 0.002,
                           1e-3, -1e-3, 2e-3, 5e-4],
}


def _splined():
    name = "LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=16_Ny=12_fov_x_deg=100"
    n = cameras.num_intrinsics(name)
    rng = np.random.default_rng(4)
    return name, np.r_[[600.0, 605.0, 511.5, 383.5], rng.normal(0, 0.05, n - 4)]


@pytest.mark.parametrize("lens", list(LENSES) + ["splined"])
def test_camera_corners(lens):
    name, intr = _splined() if lens == "splined" else (lens, np.array(LENSES[lens]))
    rng = np.random.default_rng(5)
    for _ in range(3):
        # camera looking along lidar0's +x (right-down-forward), board 3 m ahead of it
        T_c = gtsam.Pose3(gtsam.Rot3(np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)), np.zeros(3))
        T_c = perturb(T_c, rng.normal(0, 0.05, 6))
        T_cb = gtsam.Pose3(gtsam.Rot3.Ypr(*rng.uniform(-0.5, 0.5, 3)), np.array([-0.45, -0.45, 3.0]))
        T_b = T_c.compose(T_cb)
        p = np.array([T_cb.transformFrom(c) for c in BOARD.corners()])
        q = cameras.project(p, name, intr)
        assert np.abs(camera_corners_residuals(T_c, T_b, q, name, intr, BOARD)).max() < 1e-9
        q[3] = np.nan  # a missing corner: a zero row
        Tc2, Tb2 = perturb(T_c, rng.normal(0, 0.01, 6)), perturb(T_b, rng.normal(0, 0.01, 6))
        ok = np.all(np.isfinite(q), axis=1)
        qq = np.where(ok[:, None], q, 0)
        fn = lambda P, w: corners_fn(P[0], P[1], qq, ok, BOARD.corners(), name, intr, w)  # noqa: E731
        assert check_jacobians(fn, [Tc2, Tb2]) < 1e-5
        f = camera_corners_factor(S, B, q, name, intr, BOARD, 0.3)
        v = _values(s=Tc2, b=Tb2)
        e = camera_corners_residuals(Tc2, Tb2, q, name, intr, BOARD)
        assert np.all(e[3] == 0) and np.abs(e).max() > 0.1
        np.testing.assert_allclose(f.unwhitenedError(v), e.ravel(), atol=1e-9)
        assert f.error(v) == pytest.approx(0.5 * np.sum((e / 0.3) ** 2), rel=1e-9)


def test_pose_prior_matches_gtsam_prior_to_first_order_and_jacobians():
    rng = np.random.default_rng(6)
    nominal = _pose(rng)
    assert np.abs(prior_fn(nominal, nominal, False)[0]).max() < 1e-12
    for _ in range(5):
        T = perturb(nominal, rng.normal(0, 0.3, 6))
        assert check_jacobians(lambda P, w: prior_fn(P[0], nominal, w), [T]) < 1e-6
    small = perturb(nominal, 1e-5 * rng.normal(size=6))
    sig = np.array([0.01, 0.01, 0.01, 0.05, 0.05, 0.05])
    f = pose_prior_factor(S, nominal, sig)
    g = gtsam.PriorFactorPose3(S, nominal, gtsam.noiseModel.Diagonal.Sigmas(sig))
    v = _values(s=small)
    assert f.error(v) == pytest.approx(g.error(v), rel=1e-4)


def test_board_prior_constrains_only_in_plane_dofs():
    rng = np.random.default_rng(7)
    nominal = _pose(rng)
    f = board_prior_factor(B, nominal, 0.1, 0.2)
    for xi, expect in [([0.3, 0, 0, 0, 0, 0], 0.0), ([0, 0.3, 0, 0, 0, 0], 0.0), ([0, 0, 0, 0, 0, 5.0], 0.0),
                       ([0, 0, 0.1, 0, 0, 0], 0.5), ([0, 0, 0, 0.2, 0, 0], 0.5), ([0, 0, 0, 0, 0.2, 0], 0.5)]:
        v = gtsam.Values()
        v.insert(B, perturb(nominal, np.array(xi, float)))
        assert f.error(v) == pytest.approx(expect, abs=1e-12)


def test_small_solve_recovers_a_board_pose():
    """LM over one camera + one lidar0 observation pulls a perturbed board back to the truth."""
    rng = np.random.default_rng(8)
    name, intr = "LENSMODEL_OPENCV8", np.array(LENSES["LENSMODEL_OPENCV8"])
    T_c = gtsam.Pose3(gtsam.Rot3(np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)), np.array([0.1, 0.2, -0.1]))
    T_cb = gtsam.Pose3(gtsam.Rot3.Ypr(0.2, -0.3, 0.1), np.array([-0.45, -0.45, 3.0]))
    T_b = T_c.compose(T_cb)
    q = cameras.project(np.array([T_cb.transformFrom(c) for c in BOARD.corners()]), name, intr)
    pts = np.array([T_b.transformFrom(np.r_[u, v, 0]) for u, v in rng.uniform(0, 0.9, (30, 2))])
    g = gtsam.NonlinearFactorGraph()
    g.add(gtsam.PriorFactorPose3(S, T_c, gtsam.noiseModel.Isotropic.Sigma(6, 1e-9)))
    g.add(camera_corners_factor(S, B, q, name, intr, BOARD, 0.3))
    g.add(lidar_range_factor(None, B, pts, 0.01))
    v = _values(s=T_c, b=perturb(T_b, np.r_[0.05, -0.03, 0.04, 0.1, -0.1, 0.05]))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-20)
    out = gtsam.LevenbergMarquardtOptimizer(g, v, params).optimize()
    np.testing.assert_allclose(gtsam.Pose3.Logmap(T_b.between(out.atPose3(B))), 0, atol=1e-9)


def test_map_registration_factor_jacobians_and_zero_at_truth():
    from clcgraph.factors.map_registration import _residual as mapreg_fn, map_registration_factor

    rng = np.random.default_rng(8)
    for has_bias in (False, True):
        E, beta, Xi = _pose(rng, 0.3), _pose(rng, 0.01, 0.01), _pose(rng, 0.5, 5.0)
        Xj = [Xi.compose(_pose(rng, 0.05, 2.0)) for _ in range(3)]
        M = [perturb(Xi.between(x), rng.normal(0, 0.01, 6)) for x in Xj]  # the map's slightly wrong estimates
        B = [rng.normal(0, 0.5, (6, 6)) for _ in Xj]
        links = list(zip(M, B))
        # the measurement the model predicts at the truth: zero residual
        shift = sum(b @ gtsam.Pose3.Logmap(m.between(Xi.between(x))) for (m, b), x in zip(links, Xj))
        Z = E.compose(beta if has_bias else gtsam.Pose3()).compose(gtsam.Pose3.Expmap(shift))
        poses = [E] + ([beta] if has_bias else []) + [Xi] + Xj
        assert np.abs(mapreg_fn(poses, Z, links, has_bias, False)[0]).max() < 1e-9
        moved = [perturb(p, rng.normal(0, 0.2, 6)) for p in poses]
        assert check_jacobians(lambda P, w: mapreg_fn(P, Z, links, has_bias, w), moved) < 1e-6
        # through GTSAM: keys in order, whitened by the covariance
        keys = [gtsam.symbol("e", 0), gtsam.symbol("b", 0), gtsam.symbol("x", 0)] + [gtsam.symbol("x", j + 1) for j in range(3)]
        if not has_bias:
            keys.pop(1)
        f = map_registration_factor(Z, 4e-6 * np.eye(6), keys[0], bias_key=keys[1] if has_bias else None,
                                    anchor_key=keys[-4], links=dict(zip(keys[-3:], links)))
        v = gtsam.Values()
        for k, p in zip(keys, moved):
            v.insert(k, p)
        e = mapreg_fn(moved, Z, links, has_bias, False)[0]
        assert f.error(v) == pytest.approx(0.5 * e @ e / 4e-6, rel=1e-9)


@pytest.mark.parametrize("kind", ["plane", "range", "range-lidar0", "camera"])
def test_board_perturbed_jacobians_and_meaning(kind):
    # The per-observation board-pose error D (backend/noise.py): the factor's residual at the
    # board pose T_b C D C^-1 (C = the board centre), with Jacobians w.r.t. T_s, T_b and D.
    from clcgraph.backend.graph import board_centre
    from clcgraph.factors.base import board_perturbed
    from clcgraph.types import Problem

    rng = np.random.default_rng(21)
    C = board_centre(Problem(sensors=(), board=BOARD, lidar_observations=(), camera_observations=(),
                             snapshot_stamps_ns=np.zeros(0)))
    np.testing.assert_allclose(C.translation(), [0.45, 0.45, 0.0])  # corners 0..0.9 m, margins alike
    for _ in range(3):
        T_s, T_b, p = _scene(rng)
        D = gtsam.Pose3.Expmap(rng.normal(0, 0.02, 6))
        Ts2, Tb2 = perturb(T_s, rng.normal(0, 0.05, 6)), perturb(T_b, rng.normal(0, 0.05, 6))
        if kind == "camera":
            T_c = gtsam.Pose3(gtsam.Rot3(np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)), np.zeros(3))
            q = cameras.project(np.array([T_c.transformTo(Tb2.transformFrom(c)) for c in BOARD.corners()]),
                                "LENSMODEL_OPENCV4", np.array(LENSES["LENSMODEL_OPENCV4"])) + rng.normal(0, 0.3, (100, 2))
            ok = np.ones(100, bool)
            base = lambda P, w: corners_fn(P[0], P[1], q, ok, BOARD.corners(), "LENSMODEL_OPENCV4",  # noqa: E731
                                           np.array(LENSES["LENSMODEL_OPENCV4"]), w)
            poses, ib = [perturb(T_c, rng.normal(0, 0.01, 6)), Tb2], 1
        elif kind == "range-lidar0":
            base = lambda P, w: range_fn(None, P[0], p, w)  # noqa: E731
            poses, ib = [Tb2], 0
        else:
            f0 = plane_fn if kind == "plane" else range_fn
            base = lambda P, w, f0=f0: f0(P[0], P[1], p, w)  # noqa: E731
            poses, ib = [Ts2, Tb2], 1
        fn = board_perturbed(base, ib, C)
        assert check_jacobians(fn, [*poses, D]) < 1e-5
        # it is the plain residual at the perturbed board pose; D = identity changes nothing
        moved = list(poses)
        moved[ib] = poses[ib].compose(C).compose(D).compose(C.inverse())
        np.testing.assert_allclose(fn([*poses, D], False)[0], base(moved, False)[0], atol=1e-12)
        np.testing.assert_allclose(fn([*poses, gtsam.Pose3()], False)[0], base(poses, False)[0], atol=1e-12)


def test_lidar_board_error_d_tilts_about_the_board_centre():
    # D's offset DOF (v_z) moves every point of a board seen face-on by the same range; its
    # tilt about the board's x axis leaves the centre row of points where it was.
    from clcgraph.factors.base import board_perturbed

    T_b = gtsam.Pose3(gtsam.Rot3(np.array([[0, 0, 1.0], [1, 0, 0], [0, 1, 0]]).T), np.array([5.0, -0.45, -0.45]))
    C = gtsam.Pose3(gtsam.Rot3(), np.array([0.45, 0.45, 0.0]))
    xy = np.stack(np.meshgrid(np.linspace(0, 0.9, 5), np.linspace(0, 0.9, 5)), -1).reshape(-1, 2)
    p = np.array([T_b.transformFrom(np.r_[u, 0.0]) for u in xy])
    fn = board_perturbed(lambda P, w: plane_fn(None, P[0], p, w), 0, C)
    e_off = fn([T_b, gtsam.Pose3(gtsam.Rot3(), np.array([0, 0, 0.01]))], False)[0]
    np.testing.assert_allclose(e_off, -0.01, atol=1e-12)
    e_tilt = fn([T_b, gtsam.Pose3(gtsam.Rot3.Rx(0.01), np.zeros(3))], False)[0]
    centre_row = np.isclose(xy[:, 1], 0.45)
    assert np.abs(e_tilt[centre_row]).max() < 1e-12 and np.abs(e_tilt[~centre_row]).min() > 1e-3


def test_factor_reuses_its_last_evaluation_only_at_the_same_poses():
    # make_factor keeps its last evaluation (the solve linearizes one graph at the same values
    # several times, and LM linearizes where it last evaluated the error): the same poses give
    # the same error and Jacobians without a call, other poses a fresh evaluation, always with
    # the Jacobians (so an error-only call serves the next linearization at the same poses)
    import gtsam

    from clcgraph.factors.base import make_factor

    calls = []

    def fn(poses, want):
        calls.append(want)
        t = poses[0].translation()
        return t.copy(), ([np.c_[np.zeros((3, 3)), poses[0].rotation().matrix()]] if want else None)

    f = make_factor([gtsam.symbol("s", 1)], gtsam.noiseModel.Isotropic.Sigma(3, 0.5), fn)
    v = gtsam.Values()
    v.insert(gtsam.symbol("s", 1), gtsam.Pose3(gtsam.Rot3.Rz(0.3), np.array([1.0, 2.0, 3.0])))
    e0 = f.error(v)
    assert e0 == pytest.approx(0.5 * np.sum((np.array([1.0, 2.0, 3.0]) / 0.5) ** 2))
    assert calls == [True]
    assert f.error(v) == e0 and calls == [True]
    A, b = f.linearize(v).jacobian()
    assert calls == [True]
    A2, b2 = f.linearize(v).jacobian()
    assert calls == [True]
    np.testing.assert_array_equal(A2, A)
    np.testing.assert_array_equal(b2, b)
    np.testing.assert_allclose(A[:, 3:], 2.0 * gtsam.Rot3.Rz(0.3).matrix())  # whitened by 1/0.5
    np.testing.assert_allclose(b, -np.array([1.0, 2.0, 3.0]) / 0.5)
    w = gtsam.Values()
    w.insert(gtsam.symbol("s", 1), gtsam.Pose3(gtsam.Rot3.Rz(0.3), np.array([1.0, 2.0, 3.5])))
    assert f.error(w) == pytest.approx(0.5 * np.sum((np.array([1.0, 2.0, 3.5]) / 0.5) ** 2))
    assert calls == [True, True]
    _, b3 = f.linearize(w).jacobian()
    assert calls == [True, True]
    np.testing.assert_allclose(b3, -np.array([1.0, 2.0, 3.5]) / 0.5)
    f.linearize(v)  # back at the first poses: evaluated again
    assert calls == [True, True, True]
