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
