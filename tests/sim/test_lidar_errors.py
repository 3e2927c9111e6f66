"""The simulator's LIDAR errors the solver does not model (stress captures): dark squares
returning long, mixed pixels at the board's edge, heavy-tailed returns; and the person's
places and arm. Each against the same scan without the error (same draws, same rays)."""

from dataclasses import replace

import numpy as np
import pytest

from clcgraph.sim.camera import BLACK, board_shade
from clcgraph.sim.lidar import LidarModel, simulate_scan
from clcgraph.sim.scene import make_scene, random_board_pose
from clcgraph.types import BoardGeometry

BOARD = BoardGeometry.from_spec(corners=[10, 10], square_m=0.1, size_m=[1.3, 1.3])
T_LIDAR = np.eye(4)
T_LIDAR[2, 3] = 1.5
EXACT = LidarModel.preset("vlp16", range_noise_m=0.0, dropout=0.0, layout="ouster")


def _pose():
    return random_board_pose(np.random.default_rng(4), BOARD, T_LIDAR[:3, 3], tilt_max_deg=20,
                             distance_m=(4.0, 4.0), height_m=(1.5, 1.5), forward=[1, 0, 0])


def _scan(model, *, seed=0, person="none", arm=False):
    T = _pose()
    scene = make_scene(BOARD, T, np.random.default_rng(1), clutter=False, person=person, arm=arm)
    scan, hit = simulate_scan(model, T_LIDAR, scene, np.random.default_rng(seed))
    return scan, hit, T, scene


def _ranges(scan):
    return np.linalg.norm(scan.points, axis=1)


def test_dark_squares_return_long_by_the_set_bias():
    ref, hit, T, _ = _scan(EXACT)
    dark, _, _, _ = _scan(replace(EXACT, dark_range_bias_m=0.015))
    p_world = ref.points[hit] @ T_LIDAR[:3, :3].T + T_LIDAR[:3, 3]
    xy = ((p_world - T[:3, 3]) @ T[:3, :3])[:, :2]
    is_dark = board_shade(BOARD, xy) == BLACK
    d = (_ranges(dark) - _ranges(ref))[hit]
    assert 0.2 < is_dark.mean() < 0.6  # the pattern's black half, less the white border
    np.testing.assert_allclose(d[is_dark], 0.015, atol=1e-4)
    np.testing.assert_allclose(d[~is_dark], 0.0, atol=1e-4)
    assert np.all(_ranges(dark)[~hit] == _ranges(ref)[~hit])


def test_dual_returns_report_each_rays_echo_twice_column_by_column():
    one = replace(EXACT, layout="velodyne", range_noise_m=0.01)
    single, hit1, _, _ = _scan(one)
    dual, hit2, _, _ = _scan(replace(one, dual_returns=True))
    assert len(dual.points) == 2 * len(single.points) and hit2.sum() == 2 * hit1.sum()
    # per column: the first returns of its rings, then the same echoes again
    col = np.r_[0, np.flatnonzero(np.diff(dual.time_s) != 0) + 1, len(dual.time_s)]
    for a, b in zip(col[:-1], col[1:]):
        half = (b - a) // 2
        np.testing.assert_array_equal(dual.points[a:a + half], dual.points[a + half:b])
    np.testing.assert_array_equal(np.unique(dual.points, axis=0), np.unique(single.points, axis=0))


def test_mixed_pixels_only_at_each_rings_board_ends():
    ref, hit, _, _ = _scan(EXACT)
    mixed, _, _, _ = _scan(replace(EXACT, mixed_pixel_m=0.1))
    d = (_ranges(mixed) - _ranges(ref)).reshape(EXACT.n_rings, -1)
    grid = hit.reshape(EXACT.n_rings, -1)
    ends = grid & ~(np.roll(grid, 1, axis=1) & np.roll(grid, -1, axis=1))
    assert ends.sum() == 2 * np.any(grid, axis=1).sum()  # two per ring that crosses the board
    assert np.all((d[ends] >= 0) & (d[ends] <= 0.1)) and d[ends].mean() > 0.03
    assert np.all(d[~ends] == 0)


def test_heavy_tailed_returns_share_and_scale():
    noisy = replace(EXACT, range_noise_m=0.01)
    ref, hit, _, _ = _scan(EXACT)
    plain, _, _, _ = _scan(noisy)
    tails, _, _, _ = _scan(replace(noisy, heavy_tail_fraction=0.2))
    valid = _ranges(ref) > 0
    far_plain = np.mean(np.abs(_ranges(plain) - _ranges(ref))[valid] > 0.05)
    far_tails = np.mean(np.abs(_ranges(tails) - _ranges(ref))[valid] > 0.05)
    assert far_plain < 1e-4
    # 20 % of returns at sigma 0.1 m: P(|N(0, 0.1)| > 0.05) = 0.617 of them beyond 5 sigma
    assert far_tails == pytest.approx(0.2 * 0.617, abs=0.01)


@pytest.mark.parametrize("place", ["behind", "beside", "edge"])
def test_person_and_arm_across_the_board_edge(place):
    _, hit_free, _, _ = _scan(EXACT, person="none")
    scan, hit, T, scene = _scan(EXACT, person=place, arm=True)
    # the arm hides part of the board from the LIDAR: board returns lost, none gained
    assert hit.sum() < hit_free.sum() and not np.any(hit & ~hit_free)
    lost = hit_free & ~hit
    p = scan.points[lost] @ T_LIDAR[:3, :3].T + T_LIDAR[:3, 3]
    q = (p - T[:3, 3]) @ T[:3, :3]  # board frame: the occluder is just in front (z < 0)
    assert np.all((q[:, 2] < 0) & (q[:, 2] > -0.2))
    xmin, xmax, _, _ = BOARD.extent()
    from_edge = np.minimum(q[:, 0] - xmin, xmax - q[:, 0])  # across a side edge, reaching ~0.1 m in
    assert from_edge.min() < 0.05 and from_edge.max() < 0.2


def test_dual_returns_in_an_organised_cloud_are_the_next_column():
    one = replace(EXACT, range_noise_m=0.01)  # the ouster layout: organised
    single, hit1, _, _ = _scan(one)
    dual, hit2, _, _ = _scan(replace(one, dual_returns=True))
    rings, cols = single.shape
    assert dual.shape == (rings, 2 * cols) and hit2.sum() == 2 * hit1.sum()
    p1, p2 = single.points.reshape(rings, cols, 3), dual.points.reshape(rings, 2 * cols, 3)
    np.testing.assert_array_equal(p2[:, 0::2], p1)
    np.testing.assert_array_equal(p2[:, 1::2], p1)
    np.testing.assert_array_equal(dual.valid.reshape(rings, 2 * cols)[:, 1::2], single.valid.reshape(rings, cols))
