import numpy as np

from clcgraph.frontend.lidar_preprocess import infer_lidar_spacing, prepare, ring_of, static_masks
from clcgraph.sim.lidar import LidarModel, simulate_scan
from clcgraph.sim.scene import make_scene, random_board_pose, static_meshes
from clcgraph.types import BoardGeometry, LidarScan

T = np.eye(4)
T[2, 3] = 1.8


def _scans(model, n, seed=0):
    rng = np.random.default_rng(seed)
    L = LidarModel.preset(model)
    static = static_meshes(rng)
    out = []
    for _ in range(n):
        Tb = random_board_pose(rng, BoardGeometry(), T[:3, 3])
        out.append(simulate_scan(L, T, make_scene(BoardGeometry(), Tb, rng, static=static), rng)[:2])
    return out


def test_infer_lidar_spacing():
    for model, want in (("vlp16", (16, 1800)), ("os1-128", (128, 2048))):
        scans = [s for s, _ in _scans(model, 2)]
        n_rings, npoints = infer_lidar_spacing(scans)
        # rings that see nothing (sky) cannot be counted
        assert npoints == want[1] and want[0] * 0.8 <= n_rings <= want[0]


def test_rings_from_elevation_match_the_ring_field():
    scan, _ = _scans("hdl32", 1)[0]
    ringless = LidarScan(scan.topic, 0, scan.points, scan.valid)
    derived = ring_of(ringless)
    ok = scan.valid
    # the same partition of points, numbered by elevation
    pairs = np.unique(np.c_[scan.ring[ok], derived[ok]], axis=0)
    assert len(pairs) == len(np.unique(scan.ring[ok])) == len(np.unique(derived[ok]))


def test_prepare_sorts_by_ring_then_azimuth_and_drops_invalid():
    scan, _ = _scans("os1-128", 1)[0]
    R = prepare(scan, min_range_m=0.5, max_range_m=15.0)
    assert np.all(scan.valid[R.index]) and np.all((R.range >= 0.5) & (R.range <= 15.0))
    assert np.all(np.diff(R.ring) >= 0)
    same = np.diff(R.ring) == 0
    assert np.all(np.diff(R.azimuth)[same] >= 0)


def test_static_masks_keep_the_moving_board():
    scans = _scans("vlp16", 8, seed=3)
    masks = static_masks([s for s, _ in scans], npoints_per_rotation=1800, quantum_m=0.1)
    board_static = np.mean([m[h].mean() for (s, h), m in zip(scans, masks) if h.any()])
    scene_static = np.mean([m[~h & s.valid].mean() for (s, h), m in zip(scans, masks)])
    assert board_static < 0.05 and scene_static > 0.8, (board_static, scene_static)


def _wall_session(seed=0):
    """11 scans of a 16-ring LIDAR 6 m from a wall; a board 0.9 m wide is held at one spot,
    3-5 m away, in 9 of them and elsewhere in 2 (where the wall behind its usual spot shows).
    Returns (scans, board-hit masks, the 2 scans' masks of that wall patch)."""
    rng = np.random.default_rng(seed)
    npts = 1800
    el = np.radians(np.linspace(-15, 15, 16))
    az = np.radians((np.arange(npts) + 0.5) * 360 / npts - 180)
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    ring = np.repeat(np.arange(16), npts)
    wall_r = np.where(d[:, 0] > 0.3, 6.0 / np.maximum(d[:, 0], 1e-9), np.nan)  # x = 6 m
    scans, hits, patches = [], [], []
    for k in range(11):
        centre = np.radians(25.0) if k in (3, 8) else 0.0
        board_r = 3.0 + 0.22 * k
        half = 0.45 / board_r
        on_board = (np.abs(np.arctan2(d[:, 1], d[:, 0]) - centre) < half) & (np.abs(np.arcsin(d[:, 2])) < half)
        r = np.where(on_board, board_r / np.maximum(d[:, 0] * np.cos(centre) + d[:, 1] * np.sin(centre), 1e-9), wall_r)
        r = r + rng.normal(0, 0.01, r.shape)
        ok = np.isfinite(r)
        scans.append(LidarScan("/l", k, np.where(ok[:, None], d * np.nan_to_num(r)[:, None], 0.0), ok, ring=ring))
        hits.append(on_board)
        usual = (np.abs(np.arctan2(d[:, 1], d[:, 0])) < 0.8 * 0.45 / 3.5) & (np.abs(np.arcsin(d[:, 2])) < 0.8 * 0.45 / 5)
        patches.append(usual & ~on_board if k in (3, 8) else None)
    return scans, hits, patches


def test_static_masks_wall_behind_a_board_held_in_one_place():
    """The wall behind the board's usual spot is hidden in most scans, so it is never the
    common range of its cells; it still is static (the background either side along the ring
    continues behind the board), else that board-sized patch of wall looks like a board."""
    scans, hits, patches = _wall_session()
    masks = static_masks(scans, npoints_per_rotation=1800, quantum_m=0.1)
    for m, patch in zip(masks, patches):
        if patch is not None:
            assert patch.sum() > 50 and m[patch].mean() > 0.95
    assert max(m[h].mean() for m, h in zip(masks, hits)) < 0.05
    wall = [~h & s.valid for s, h in zip(scans, hits)]
    assert np.mean([m[w].mean() for m, w in zip(masks, wall)]) > 0.95


def _byteswapped(scan: LidarScan) -> LidarScan:
    """The scan as a decoder with a false is_bigendian flag sees it (float32 xyz, uint16 ring)."""
    with np.errstate(invalid="ignore"):
        p = scan.points.astype("<f4").view(">f4").astype(float)
        valid = np.isfinite(p).all(axis=1) & (p != 0).any(axis=1)
    ring = None if scan.ring is None else scan.ring.astype("<u2").view(">u2").astype(np.int64)
    return LidarScan(topic=scan.topic, stamp_ns=scan.stamp_ns, points=p, valid=valid, intensity=None,
                     ring=ring, time_s=None, shape=scan.shape)


def test_one_byteswapped_scan_does_not_spoil_the_other_scans_static_masks():
    import warnings

    scans = [s for s, _ in _scans("vlp16", 8, seed=4)]
    blank = LidarScan(topic=scans[3].topic, stamp_ns=scans[3].stamp_ns, points=scans[3].points,
                      valid=np.zeros(len(scans[3].points), bool), intensity=None, ring=scans[3].ring,
                      time_s=None, shape=scans[3].shape)
    ref = static_masks(scans[:3] + [blank] + scans[4:], npoints_per_rotation=1800, quantum_m=0.1, max_range_m=15.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning escapes either
        got = static_masks(scans[:3] + [_byteswapped(scans[3])] + scans[4:], npoints_per_rotation=1800,
                           quantum_m=0.1, max_range_m=15.0)
    for k in (0, 1, 2, 4, 5, 6, 7):
        assert ref[k].mean() > 0.3  # the walls and ground are masked
        # the garbage scan's few returns that happen to land in range may tip a handful of cells
        assert np.mean(got[k] != ref[k]) < 0.002, (k, np.mean(got[k] != ref[k]))


def test_all_nan_scan_gives_no_warning():
    import warnings

    s = _scans("vlp16", 1)[0][0]
    nan = LidarScan(topic=s.topic, stamp_ns=0, points=np.full_like(s.points, np.nan), valid=np.zeros(len(s.points), bool),
                    intensity=None, ring=None, time_s=None, shape=None)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(prepare(nan, min_range_m=0.5, max_range_m=15.0).index) == 0
        assert infer_lidar_spacing([nan]) == (0, 0)
        static_masks([nan] * 4, npoints_per_rotation=1800, quantum_m=0.1)


def _tilted_board_scan(rng, shift_rad, noise=0.01):
    """16 rings x 1800 steps, the azimuths of this rotation shifted by ``shift_rad`` (a real rotation's
    firing phase): a 1.2 m board in the plane x = 2.5 m centred at 45 deg azimuth (seen 45 deg off
    head-on), a wall at x = 8 m behind it (depth edges at the board's sides); range noise."""
    el = np.radians(np.linspace(-15, 15, 16))
    az = np.linspace(-np.pi, np.pi, 1800, endpoint=False) + shift_rad
    e, a = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    ahead = d[:, 0] > 0.1
    x = np.where(ahead, d[:, 0], 1.0)
    lam_board = np.where(ahead, 2.5 / x, 1e6)
    lam_wall = np.where(ahead, 8.0 / x, 30.0)
    hit = d * lam_board[:, None]
    on = ahead & (np.abs(hit[:, 2]) < 0.6) & (np.abs(hit[:, 1] - 2.5) < 0.6)
    lam = np.where(on, lam_board, lam_wall) + rng.normal(0, noise, len(d))
    scan = LidarScan("/l", 0, d * lam[:, None], np.ones(len(d), bool), ring=np.repeat(np.arange(16), 1800))
    return scan, on, np.array([1.0, 0.0, 0.0]), (lam_board, lam_wall)


def test_average_scans_halves_the_noise_keeps_the_plane_and_the_depth_edges():
    from clcgraph.frontend.lidar_preprocess import average_scans

    rng = np.random.default_rng(4)
    step = 2 * np.pi / 1800
    scans = [_tilted_board_scan(rng, s) for s in (0.0, 0.43 * step, 0.31 * step, 0.12 * step)]
    first, on, n, (lam_board, lam_wall) = scans[0]
    avg, count = average_scans([s[0] for s in scans])
    res_one = first.points[on] @ n - 2.5
    res_avg = avg.points[on] @ n - 2.5
    # on the tilted board the other rotations' returns are interpolated to the first's rays: no
    # bias from the azimuth shift (a return ~0.2 steps away lies ~3 mm further along a 45-deg board)
    assert on.sum() > 100 and abs(res_avg.mean()) < 1e-3
    assert np.median(count[on]) == 4
    assert 0.4 < res_avg.std() / res_one.std() < 0.6  # 1/sqrt(4) of the noise
    # the rays stay the first rotation's
    u = lambda p: p / np.linalg.norm(p, axis=1, keepdims=True)  # noqa: E731
    assert np.allclose(u(avg.points), u(first.points), atol=1e-9)
    # no return is averaged across the board's sides onto neither the board nor the wall
    r = np.linalg.norm(avg.points, axis=1)
    assert np.all((np.abs(r - lam_board) < 0.05) | (np.abs(r - lam_wall) < 0.05))
    assert np.all(count[~on & (lam_wall < 20)] >= 1)


def test_average_scans_of_one_scan_is_that_scan():
    from clcgraph.frontend.lidar_preprocess import average_scans

    scan = _tilted_board_scan(np.random.default_rng(1), 0.0)[0]
    avg, count = average_scans([scan])
    assert avg is scan and set(np.unique(count)) == {1}


def _dual_returns(scan, rng, noise_m=0.01):
    """``scan`` as a LIDAR in dual-return mode publishes it, unorganised: each ray's return, then
    (in the next block) a second return of the same ray, the same surface with its own range noise."""
    ok = np.flatnonzero(scan.valid)
    p = scan.points[ok]
    r = np.linalg.norm(p, axis=1)
    second = p * ((r + rng.normal(0, noise_m, len(r))) / r)[:, None]
    cat = lambda a, b: np.concatenate([a, b])  # noqa: E731
    return LidarScan(scan.topic, scan.stamp_ns, cat(p, second), np.ones(2 * len(ok), bool),
                     ring=cat(scan.ring[ok], scan.ring[ok]), time_s=None)


def test_a_dual_return_cloud_keeps_one_return_per_ray_and_finds_the_same_boards():
    """A second return of each ray is not a second measurement: prepare keeps the first of each
    ray in the cloud's order (not the nearer: two noisy returns of one surface would bias it toward
    the LIDAR), and the segmentation then finds the boards of the single-return scans, to the point."""
    from lidar_board_scans import board_scans

    scans, _ = board_scans(LidarModel.preset("vlp16"), 6, tilt_max_deg=40.0, distance_m=(2.5, 6.0))
    rng = np.random.default_rng(1)
    dual = [_dual_returns(s, rng) for s in scans]
    single = [LidarScan(s.topic, s.stamp_ns, s.points[s.valid], np.ones(int(s.valid.sum()), bool),
                        ring=s.ring[s.valid]) for s in scans]
    R = prepare(dual[0])
    n = len(single[0].points)
    assert len(R.index) == n and np.all(R.index < n)  # one per ray, each the first
    _assert_the_same_boards(single, dual, at_least=5)


def _assert_the_same_boards(single, dual, *, at_least: int) -> None:
    """The segmentation of the dual-return scans finds the boards of the single-return ones, to the point."""
    from clcgraph.config import Config
    from clcgraph.frontend.lidar_board import segment_many
    from clcgraph.types import LidarBoardObservation
    from lidar_board_scans import BOARD

    cfg = Config()
    a = segment_many(single, cfg.segmentation, cfg.lidar, BOARD)
    b = segment_many(dual, cfg.segmentation, cfg.lidar, BOARD)
    found = [isinstance(x, LidarBoardObservation) for x in a]
    assert sum(found) >= at_least and found == [isinstance(x, LidarBoardObservation) for x in b]
    for x, y in zip(a, b):
        if isinstance(x, LidarBoardObservation):
            np.testing.assert_array_equal(x.points, y.points)


def test_an_organised_dual_return_cloud_finds_the_boards_of_its_first_returns():
    """Dual returns kept organised (each column followed by its second returns' column, the same
    rows): one return per ray again, and the boards, their points and the averaging of a bag's
    scans are those of the single-return clouds of the same draws."""
    from dataclasses import replace

    from clcgraph.frontend.lidar_preprocess import average_scans
    from lidar_board_scans import board_scans

    model = LidarModel.preset("os1-64", npoints_per_rotation=1024)
    single, _ = board_scans(model, 5, tilt_max_deg=40.0, distance_m=(2.5, 6.0))
    dual, _ = board_scans(replace(model, dual_returns=True), 5, tilt_max_deg=40.0, distance_m=(2.5, 6.0))
    assert dual[0].shape == (64, 2048)
    R1, R2 = prepare(single[0]), prepare(dual[0])
    rows, cols = divmod(R2.index, 2048)
    assert len(R2.index) == len(R1.index) and np.all(cols % 2 == 0)  # one per ray: the first column of each pair
    np.testing.assert_array_equal(rows * 1024 + cols // 2, R1.index)
    _assert_the_same_boards(single, dual, at_least=4)
    # a bag's scans averaged: the same ranges whatever the layout
    avg1, _ = average_scans(single[:1] * 2)
    avg2, _ = average_scans(dual[:1] * 2)
    np.testing.assert_array_equal(avg2.points[R2.index], avg1.points[R1.index])


def test_a_cloud_moved_out_of_the_lidars_frame_is_refused_naming_the_topic():
    """A cloud already moved into base_link (here 1.9 m below the LIDAR) has its rings meeting
    away from its origin: the segmentation's rays from the origin would not be the LIDAR's, so
    segment_many refuses in one line; the LIDAR's own clouds measure ~0 (real Ouster clouds: 0.026 m)."""
    import dataclasses

    import pytest

    from clcgraph.config import Config
    from clcgraph.errors import DataError
    from clcgraph.frontend.lidar_board import segment_many
    from clcgraph.frontend.lidar_preprocess import origin_height_m
    from lidar_board_scans import BOARD, board_scans

    scans, _ = board_scans(LidarModel.preset("vlp16"), 3, tilt_max_deg=30.0, distance_m=(3.0, 5.0))
    assert all(abs(origin_height_m(s)) < 0.01 for s in scans)
    moved = [dataclasses.replace(s, points=s.points + [1.0, 0.0, 1.9]) for s in scans]
    assert 1.0 < origin_height_m(moved[0]) < 2.0
    cfg = Config()
    with pytest.raises(DataError, match=r"^/l: its points are not in the LIDAR's own frame: its rings meet about 1\.\d m "
                                        r"above the cloud's origin"):
        segment_many(moved, cfg.segmentation, cfg.lidar, BOARD)
    assert len(segment_many(scans, cfg.segmentation, cfg.lidar, BOARD)) == 3
