import numpy as np

from clcgraph.backend import uncertainty as U
from clcgraph.geometry import compose_rt, invert_rt, transform


def _pj(rts, i, j, p):
    return transform(compose_rt(invert_rt(rts[j]), rts[i]), p)


def test_jacobians_match_central_differences():
    rng = np.random.default_rng(1)
    rts = rng.normal(size=(3, 6)) * [0.7, 0.7, 0.7, 2, 2, 2]
    p = rng.normal(size=(5, 3)) * 5
    for i, j in ((1, 2), (2, 0), (0, 1)):
        pj, Ji, Jj = U.point_transform_jacobians(rts, i, j, p)
        np.testing.assert_allclose(pj, _pj(rts, i, j, p), atol=1e-12)
        for s, J in ((i, Ji), (j, Jj)):
            num = np.zeros_like(J)
            for k in range(6):
                h = 1e-6
                a, b = rts.copy(), rts.copy()
                a[s, k] += h
                b[s, k] -= h
                num[..., k] = (_pj(a, i, j, p) - _pj(b, i, j, p)) / (2 * h)
            np.testing.assert_allclose(J, num, rtol=1e-6, atol=1e-7)


def test_covariance_matches_sampling():
    # Linear propagation vs sampling with a small covariance: agree to a few percent.
    rng = np.random.default_rng(2)
    rts = np.zeros((3, 6))
    rts[1] = [0.1, -0.2, 0.3, 1, 0.5, 0.2]
    rts[2] = [-0.3, 0.1, 1.2, -0.4, 2, 0.1]
    A = rng.normal(size=(12, 12)) * 1e-3
    C = A @ A.T
    p = np.array([[10.0, 2.0, 0.0], [0.0, -8.0, 1.0]])
    V = U.point_transform_covariance(rts, C, 0, 1, 2, p)
    d = rng.multivariate_normal(np.zeros(12), C, size=20000)
    samples = []
    for dd in d[:4000]:
        r = rts.copy()
        r[1] += dd[:6]
        r[2] += dd[6:]
        samples.append(_pj(r, 1, 2, p))
    S = np.array(samples)
    for k in range(2):
        emp = np.cov(S[:, k].T)
        np.testing.assert_allclose(np.sqrt(np.diag(emp)), np.sqrt(np.diag(V[k])), rtol=0.06)


def test_reference_and_identity_cases():
    rts = np.zeros((2, 6))
    rts[1] = [0, 0, 0.5, 1, 0, 0]
    C = np.diag([1e-4] * 3 + [1e-6] * 3)
    p = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    assert np.all(U.point_transform_covariance(rts, C, 0, 1, 1, p) == 0)
    # From the reference to sensor 1 at the origin of lidar0: only rotation of sensor 1's
    # frame plus translation matter: lever arm 9 m from sensor 1, rotation sigma 1e-2 rad.
    s = U.worst_direction_stdev(rts, C, 0, 0, 1, p)
    assert s.shape == (2,)
    assert s[1] > s[0]
    np.testing.assert_allclose(s[1], np.hypot(9 * 1e-2, 1e-3), rtol=0.05)
    # A grid of points vectorizes.
    g = np.zeros((4, 5, 3))
    assert U.worst_direction_stdev(rts, C, 0, 1, 0, g).shape == (4, 5)
