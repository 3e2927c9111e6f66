import numpy as np

from clcgraph.backend.sectors import sector_report, uncertainty_grid
from clcgraph.config import SectorOptions
from clcgraph.geometry import r_from_R
from clcgraph.types import BoardGeometry, Problem, Result, Sensor


def _result():
    cam = Sensor("/cam", "camera", "LENSMODEL_PINHOLE", np.array([500.0, 500, 499.5, 399.5]), (1000, 800))
    sensors = (Sensor("/l0", "lidar"), Sensor("/l1", "lidar"), cam)
    rts = np.zeros((3, 6))
    rts[1] = [0, 0, np.pi / 2, 0.0, 1.0, 0.0]  # lidar1 rotated 90 deg left
    R_l0_cam = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # camera looks along +x
    rts[2, :3] = r_from_R(R_l0_cam)
    board = BoardGeometry(corners_x=3, corners_y=3, square_m=0.5, width_m=2.0, height_m=2.0)  # centre (0.5,0.5)
    # Boards at azimuth 45 deg (two) and 135 deg (last): board centre = t + (0.5,0.5,0).
    rt_boards = np.array([
        [0, 0, 0, 4.5, 4.5, 0],
        [0, 0, 0, 2.5, 2.5, 0],
        [np.nan] * 6,
        [0, 0, 0, -5.5, 4.5, 0],
    ])
    rng = np.random.default_rng(0)
    # lidar0 sees far points only in front (azimuth ~0); lidar1 (rotated) sees, in its own
    # frame, points ahead, i.e. along lidar0's +y.
    vis0 = np.column_stack([rng.uniform(5, 20, 500), rng.uniform(-0.5, 0.5, 500), np.zeros(500)])
    vis0 = np.vstack([vis0, rng.normal(size=(500, 3)) * 0.3])  # near points, ignored
    problem = Problem(sensors, board, (), (), np.arange(4), lidar_visibility_points={0: vis0, 1: vis0[:500]})
    C = np.diag(np.r_[[1e-6] * 3, [1e-6] * 3, [4e-6] * 3, [1e-6] * 3])
    return Result(problem, rts, C, rt_boards, {}, {}, ())


def test_sector_report_known_geometry():
    res = _result()
    opts = SectorOptions(n_sectors=8, threshold_valid_lidar_range_m=1.5, threshold_valid_lidar_npoints=100,
                         uncertainty_quantification_range_m=10.0)
    rep = sector_report(res, opts)
    assert rep.n_sectors == 8
    # 45 deg centres are on the sector 0/1 border: 5,5 -> az exactly 45 -> sector 1.
    np.testing.assert_array_equal(rep.observations_per_sector, [0, 2, 0, 1, 0, 0, 0, 0])
    assert rep.isector_of_last_snapshot == 3
    vis = rep.isvisible_per_sensor_per_sector
    # lidar0 sees azimuth ~0 (sectors 0 and 7 straddle it); lidar1 sees azimuth ~90 deg.
    assert vis[0, 0] and vis[0, 7] and vis[0].sum() == 2
    assert vis[1, 1] and vis[1, 2] and vis[1].sum() == 2
    # Camera (hfov ~ 90 deg) sees the evaluation points at +-22.5 deg only.
    np.testing.assert_array_equal(vis[2], [1, 0, 0, 0, 0, 0, 0, 1])
    # Worst pair involves the camera (rotation sigma 2e-3 rad at ~10 m) everywhere.
    assert np.all(rep.isensors_pair_stdev_worst[:, 1] == 2)
    assert np.all((rep.stdev_worst_per_sector > 0.02) & (rep.stdev_worst_per_sector < 0.04))


def test_uncertainty_grid_grows_with_distance():
    res = _result()
    x, y, s = uncertainty_grid(res, 0, 2, radius=20, gridn=21)
    assert s.shape == (21, 21)
    centre = s[10, 10]
    np.testing.assert_allclose(centre, 1e-3, rtol=1e-6)  # pure camera translation sigma
    assert s[0, 0] > 10 * centre
