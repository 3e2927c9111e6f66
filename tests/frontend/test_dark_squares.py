"""Real LIDARs range a chessboard's dark squares 1-2 cm long (weak returns, range walk): the
board's plane would sit ~40 % of that behind the board a camera sees. Segmentation sees the
pattern in the intensities and moves the weak returns back by the offset it measures."""

import numpy as np

import clcgraph
from clcgraph.frontend.lidar_board import dark_square_correction
from clcgraph.sim.lidar import LidarModel
from clcgraph.types import LidarBoardObservation
from lidar_board_scans import BOARD, board_scans


def _planes(model, n=8):
    scans, boards = board_scans(model, n, tilt_max_deg=30, distance_m=(3.0, 6.0))
    truth = [(-T_lb[:3, 2], -T_lb[:3, 2] @ T_lb[:3, 3]) for T_lb in boards]  # n toward the sensor, d
    found = clcgraph.segment(scans, board=BOARD)
    assert all(isinstance(o, LidarBoardObservation) for o in found), [getattr(o, "reason", "") for o in found]
    return np.array([o.plane[3] - d for o, (n, d) in zip(found, truth)])  # offset error (m), + = nearer


def test_dark_square_range_walk_is_measured_and_removed():
    model = LidarModel.preset("os1-64", range_noise_m=0.005, dark_range_bias_m=0.015)
    err = _planes(model)
    assert np.all(np.abs(err) < 0.0015), err * 1e3  # uncorrected: ~ -5 mm (36 % of the board dark)


def test_the_few_dark_returns_of_a_board_whose_dark_squares_mostly_return_nothing_are_moved_back_too():
    """9 in 10 of the dark squares' returns lost: the weak ones left are ~5 % of the board's."""
    rng = np.random.default_rng(5)
    pts = rng.normal(0, 1, (600, 3)) * [0.4, 0.4, 0.003] + [0, 0, 5.0]
    weak = rng.uniform(size=600) < 0.05
    r = np.linalg.norm(pts, axis=1)
    long = pts * np.where(weak, (r + 0.015) / r, 1.0)[:, None]
    out, offset = dark_square_correction(long, np.where(weak, 20.0, 180.0))
    assert weak.sum() >= 20 and abs(offset - 0.015) < 0.002
    assert np.abs(np.linalg.norm(out, axis=1) - r).max() < 0.002
    # ... but not a handful: their offset's standard error means nothing yet
    few = np.flatnonzero(weak)[5:]
    out, offset = dark_square_correction(np.delete(long, few, axis=0), np.delete(np.where(weak, 20.0, 180.0), few))
    assert offset == 0.0


def test_without_a_pattern_in_the_intensities_nothing_changes():
    rng = np.random.default_rng(3)
    pts = rng.normal(0, 1, (500, 3)) * [0.4, 0.4, 0.005] + [0, 0, 5.0]
    for intensity in (np.full(500, 180.0), rng.uniform(50, 200, 500)):  # flat; smooth spread
        out, offset = dark_square_correction(pts, intensity)
        assert offset == 0.0 and out is pts
    # a pattern in the intensities but no range difference: not significant, nothing changes
    weak = rng.uniform(size=500) < 0.4
    out, offset = dark_square_correction(pts, np.where(weak, 20.0, 180.0))
    assert offset == 0.0
    # the same returns with the weak ones 15 mm long along their rays: measured, moved back
    r = np.linalg.norm(pts, axis=1)
    long = pts * np.where(weak, (r + 0.015) / r, 1.0)[:, None]
    out, offset = dark_square_correction(long, np.where(weak, 20.0, 180.0))
    assert abs(offset - 0.015) < 0.002 and np.abs(np.linalg.norm(out, axis=1) - r).max() < 0.002
