"""Pieces of one board found by different clusters can grow over the same returns while their
own noisy plane fits differ by more than the coplanarity test allows (a 32-ring LIDAR with
2.5 cm noise at 2.6 m gave "2 board-like planes (at 2.6 m, 2.6 m)"): they are one plane."""

import numpy as np

from clcgraph.frontend.lidar_board import _merge
from clcgraph.geometry import R_from_r


def test_pieces_sharing_most_returns_are_one_plane():
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-0.6, 0.6, (400, 2)), rng.normal(0, 0.025, 400)] + [0, 0, 2.6]
    n0 = np.array([0.0, 0.0, 1.0])
    tilted = R_from_r(np.radians([15.0, 0, 0])) @ n0  # a noisy piece's fit, 15 deg off
    a, b = np.arange(0, 300), np.arange(100, 400)  # 200 returns shared
    merged = _merge([(a, n0, 2.6), (b, tilted, tilted @ [0, 0, 2.6])], pts, 0.05, 1.84)
    assert len(merged) == 1 and np.array_equal(merged[0], np.arange(400))
    # a few shared returns where two different surfaces meet do not join them
    c = np.arange(290, 400)
    apart = _merge([(np.arange(0, 300), n0, 2.6), (c, tilted, tilted @ [0, 0, 2.6])], pts, 0.05, 1.84)
    assert len(apart) == 2
