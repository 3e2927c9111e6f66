"""The registration ensemble's early stop (issue 16): a frame 'agrees' when its registrations lie
within its own point-to-plane uncertainty of the best pose, and the ensemble stops registering
frames one by one after a few agreeing frames in a row."""

import numpy as np
from clcgraph.config import Config
from clcgraph.targetless.registration import FrameData, agrees

O = Config().targetless


def _corner_of_a_room(rng, n, sigma):
    """Points on a floor and two walls (every direction constrained), with Gaussian noise."""
    u, v = rng.uniform(0.5, 4.0, (2, n))
    planes = [np.c_[u, v, np.zeros(n)], np.c_[np.zeros(n), u, v], np.c_[u, np.zeros(n), v]]
    return np.concatenate(planes) + rng.normal(0, sigma, (3 * n, 3))


def _pose(omega, v):
    from clcgraph.geometry import T_exp as exp

    return exp(np.r_[omega, v])


def test_agreement_follows_the_frames_own_uncertainty():
    rng = np.random.default_rng(0)
    sigma = 0.005
    target = _corner_of_a_room(rng, 3000, sigma)
    fd = FrameData.make(None, target, _corner_of_a_room(rng, 1000, sigma))
    # 1000 source points per plane at ~7 mm residuals: ~0.2 mm and ~0.1 mrad of 1-sigma per axis
    assert agrees(fd, np.eye(4), [np.eye(4), _pose([0, 0, 2e-5], [5e-5, -5e-5, 0])], O)
    assert not agrees(fd, np.eye(4), [np.eye(4), _pose([0, 0, 0], [0.005, 0, 0])], O)  # 5 mm: 25 sigma
    assert not agrees(fd, np.eye(4), [_pose([0.002, 0, 0], [0, 0, 0])], O)  # 2 mrad about x


def test_a_frame_without_correspondences_never_agrees():
    rng = np.random.default_rng(1)
    target = _corner_of_a_room(rng, 500, 0.005)
    far = target + [100.0, 0, 0]  # nothing within the correspondence distance
    fd = FrameData.make(None, target, far)
    assert not agrees(fd, np.eye(4), [np.eye(4)], O)


def test_covariances_on_a_shared_kdtree_are_the_clouds_own():
    """FrameData keeps one KD-tree and builds the GICP covariances on another PointCloud of the
    same points (gicp.prepared(..., tree=)): the same covariances and registration as its own tree."""
    import small_gicp

    from clcgraph.targetless import gicp

    rng = np.random.default_rng(2)
    pts = _corner_of_a_room(rng, 2000, 0.005)
    own, own_tree = gicp.prepared(pts, threads=1)
    shared_tree = small_gicp.KdTree(small_gicp.PointCloud(pts), num_threads=1)
    other, _ = gicp.prepared(small_gicp.PointCloud(pts), threads=2, tree=shared_tree)
    assert np.array_equal(np.asarray(own.covs()), np.asarray(other.covs()))
    src, _ = gicp.preprocess(_corner_of_a_room(rng, 800, 0.005), 0.1, threads=1)
    T0 = _pose([0.01, -0.02, 0.01], [0.03, 0.02, -0.01])
    kw = dict(init_T_target_source=T0, registration_type="GICP", max_correspondence_distance=0.5, max_iterations=30)
    a = gicp.align(own, src, own_tree, **kw).T_target_source
    b = gicp.align(other, src, shared_tree, **kw).T_target_source
    assert np.array_equal(a, b)
    assert np.linalg.norm(a[:3, 3]) < 2e-3  # and it registered (the truth is the identity)


def test_frame_normals_are_the_planes():
    rng = np.random.default_rng(3)
    n = 1500
    target = _corner_of_a_room(rng, n, 0.002)  # floor (z), wall x = 0, wall y = 0
    fd = FrameData.make(None, target, target[:10])
    idx = np.array([5, n + 5, 2 * n + 5, 5])
    nrm = fd.normals_at(idx)
    assert np.allclose(np.abs(nrm[:3]), np.eye(3)[[2, 0, 1]], atol=0.05)
    assert np.array_equal(nrm[0], nrm[3])  # computed once, then looked up

