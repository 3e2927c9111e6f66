import mrcal
import numpy as np
import pytest

from clcgraph import geometry as g


@pytest.fixture
def rts():
    rng = np.random.default_rng(0)
    rt = rng.normal(size=(50, 6))
    rt[:, :3] *= 1.0
    rt[0, :3] = 0
    rt[1, :3] = [1e-9, -2e-9, 0]
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    rt[2, :3] = axis * (np.pi - 1e-9)
    rt[3, :3] = axis * (np.pi - 1e-4)
    return rt


def test_R_matches_mrcal(rts):
    for rt in rts:
        np.testing.assert_allclose(g.R_from_r(rt[:3]), mrcal.R_from_r(rt[:3]), atol=1e-12)


def test_round_trips(rts):
    for rt in rts:
        T = g.T_from_rt(rt)
        np.testing.assert_allclose(g.T_from_rt(g.rt_from_T(T)), T, atol=1e-12)
        np.testing.assert_allclose(g.rt_from_Rt(g.Rt_from_rt(rt)), g.rt_from_T(T), atol=1e-12)
        np.testing.assert_allclose(g.T_from_rt(g.rt_from_pose3(g.pose3_from_rt(rt))), T, atol=1e-12)


def test_vectorized_agrees(rts):
    np.testing.assert_allclose(g.T_from_rt(rts), np.stack([g.T_from_rt(r) for r in rts]), atol=1e-14)
    np.testing.assert_allclose(g.r_from_R(g.R_from_r(rts[:, :3])), np.stack([g.r_from_R(g.R_from_r(r[:3])) for r in rts]), atol=1e-14)


def test_compose_invert_match_mrcal(rts):
    rng = np.random.default_rng(1)
    for rt in rts:
        rt2 = rng.normal(size=6)
        a, b = rt, rt2
        np.testing.assert_allclose(g.T_from_rt(g.compose_rt(a, b)), g.T_from_rt(mrcal.compose_rt(a, b)), atol=1e-12)
        np.testing.assert_allclose(g.T_from_rt(g.invert_rt(a)), g.T_from_rt(mrcal.invert_rt(a)), atol=1e-12)
        p = rng.normal(size=(5, 3))
        np.testing.assert_allclose(g.transform(a, p), mrcal.transform_point_rt(a, p), atol=1e-12)


def test_drt_dxi_matches_finite_differences():
    rng = np.random.default_rng(2)
    for _ in range(10):
        rt = rng.normal(size=6)
        pose = g.pose3_from_rt(rt)
        J = g.drt_dxi(rt)
        h = 1e-6
        Jn = np.zeros((6, 6))
        for k in range(6):
            d = np.zeros(6)
            d[k] = h
            Jn[:, k] = (g.rt_from_pose3(pose.retract(d)) - g.rt_from_pose3(pose.retract(-d))) / (2 * h)
        np.testing.assert_allclose(J, Jn, atol=1e-7)
        # gtsam's retract is right-perturbation with [omega, v]: confirm the convention.
        d = np.array([0, 0, 0, 1e-3, 0, 0])
        np.testing.assert_allclose(
            pose.retract(d).translation(), pose.translation() + pose.rotation().matrix() @ d[3:], atol=1e-12
        )


def test_rpy_is_urdf_fixed_axes_and_round_trips():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    rpy = np.c_[rng.uniform(-np.pi, np.pi, 200), rng.uniform(-1.5, 1.5, 200), rng.uniform(-np.pi, np.pi, 200)]
    R = g.R_from_rpy(rpy)
    # URDF: R = Rz(yaw) Ry(pitch) Rx(roll), composed from elementary rotations independently of our code
    want = np.stack([Rotation.from_euler("z", y).as_matrix() @ Rotation.from_euler("y", p).as_matrix()
                     @ Rotation.from_euler("x", r).as_matrix() for r, p, y in rpy])
    np.testing.assert_allclose(R, want, atol=1e-12)
    np.testing.assert_allclose(g.rpy_from_R(R), rpy, atol=1e-9)
    # a pure yaw of 30 deg reads as (0, 0, 30); the label says which convention
    np.testing.assert_allclose(g.rpy_deg_from_rt(np.r_[0, 0, np.radians(30), 1, 2, 3]), [0, 0, 30], atol=1e-12)
    assert "fixed axes x-y-z" in g.RPY_LABEL
    # gimbal lock: pitch +90 deg still reproduces the rotation
    R_lock = g.R_from_rpy(np.r_[0.3, np.pi / 2, -0.2])
    np.testing.assert_allclose(g.R_from_rpy(g.rpy_from_R(R_lock)), R_lock, atol=1e-9)


def test_one_pose_fast_paths_equal_the_vectorized_forms():
    # R_from_r / r_from_R take a scalar path for one (3,) / (3,3) (the solver's hot case): it
    # must give the vectorized form's numbers at every scale, near 180 deg and for NaN
    rng = np.random.default_rng(4)
    axes = rng.normal(size=(50, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    r = np.concatenate([rng.normal(size=(50, 3)) * s for s in (0.0, 1e-9, 1e-7, 1e-4, 0.3, 3.0)]
                       + [axes * (np.pi - e) for e in (0.0, 1e-9, 1e-5, 1e-2)])
    R_all = g.R_from_r(r)
    R_one = np.array([g.R_from_r(x) for x in r])
    np.testing.assert_allclose(R_one, R_all, rtol=0, atol=2e-15)
    np.testing.assert_allclose(np.array([g.r_from_R(x) for x in R_all]), g.r_from_R(R_all), rtol=0, atol=1e-15)
    # the rotation survives the round trip (angle in [0, pi]) on both paths
    np.testing.assert_allclose(g.R_from_r(np.array([g.r_from_R(x) for x in R_one])), R_all, atol=1e-9)
    assert np.isnan(g.R_from_r(np.array([np.nan, 0, 0]))).all()
    assert np.isnan(g.R_from_r(np.array([np.inf, 0, 0]))).all()
    assert np.isnan(g.r_from_R(np.full((3, 3), np.nan))).all()
