"""The registration ensemble's early stop (issue 16): a frame 'agrees' when its registrations lie
within its own point-to-plane uncertainty of the best pose, and the ensemble stops registering
frames one by one after a few agreeing frames in a row."""

import numpy as np
from scipy.spatial import cKDTree

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
    fd = FrameData(None, target, _corner_of_a_room(rng, 1000, sigma), kdtree=cKDTree(target))
    # 1000 source points per plane at ~7 mm residuals: ~0.2 mm and ~0.1 mrad of 1-sigma per axis
    assert agrees(fd, np.eye(4), [np.eye(4), _pose([0, 0, 2e-5], [5e-5, -5e-5, 0])], O)
    assert not agrees(fd, np.eye(4), [np.eye(4), _pose([0, 0, 0], [0.005, 0, 0])], O)  # 5 mm: 25 sigma
    assert not agrees(fd, np.eye(4), [_pose([0.002, 0, 0], [0, 0, 0])], O)  # 2 mrad about x


def test_a_frame_without_correspondences_never_agrees():
    rng = np.random.default_rng(1)
    target = _corner_of_a_room(rng, 500, 0.005)
    far = target + [100.0, 0, 0]  # nothing within the correspondence distance
    fd = FrameData(None, target, far, kdtree=cKDTree(target))
    assert not agrees(fd, np.eye(4), [np.eye(4)], O)
