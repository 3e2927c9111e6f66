"""The report's evidence that a calibration is right (outputs/evidence.py), on simulated data: numbers
against the simulator's truth, and each check shown to fail on a wrong calibration."""

from __future__ import annotations

import io

import matplotlib.image as mpimg
import numpy as np
import pytest

from clcgraph import cameras
from clcgraph.geometry import compose_rt, invert_rt, transform
from clcgraph.outputs import evidence as ev
from clcgraph.outputs import plots
from clcgraph.sim.observations import make_rig, simulate_problem


@pytest.fixture(scope="module")
def solved():
    from clcgraph.api import calibrate

    rig = make_rig(n_lidars=2, n_cameras=2)
    problem, truth = simulate_problem(rig=rig, n_snapshots=16, seed=3, planned_tilts=True)
    return calibrate(problem), truth


def test_board_outline_from_corners_matches_truth():
    # the outline fitted to the detected corners (no extrinsics) is where the true board edge projects,
    # through a distorted lens (OPENCV8) too
    rig = make_rig(n_lidars=1, n_cameras=1)
    problem, truth = simulate_problem(rig=rig, n_snapshots=6, seed=1, sigma_camera_px=0.0)
    cam = problem.sensors[1]
    for o in problem.camera_observations:
        H = ev.board_homography(o.corners_px, problem.board, cam)
        got = ev.board_outline_px(H, problem.board, cam, n_per_edge=5)
        xmin, xmax, ymin, ymax = problem.board.extent()
        c = np.array([[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax]])
        s = np.linspace(0, 1, 5, endpoint=False)[:, None]
        edge = np.concatenate([c[k] + s * (c[(k + 1) % 4] - c[k]) for k in range(4)] + [c[:1]])
        rt_c_b = compose_rt(invert_rt(truth.rt_lidar0_sensor[1]), truth.rt_lidar0_board[o.snapshot])
        want = cameras.project(transform(rt_c_b, np.c_[edge, np.zeros(len(edge))]), cam.lensmodel, cam.intrinsics)
        np.testing.assert_allclose(got, want, atol=0.05)


def test_lidar_board_points_fall_on_the_cameras_boards(solved):
    result, truth = solved
    rows = ev.lidar_board_in_images(result)
    assert len(rows) >= 16 and {r["camera"] for r in rows} == {2, 3} and {r["lidar"] for r in rows} == {0, 1}
    # within the calibration's uncertainty: no spill beyond the board's outline by more than 4 sigma
    # (each point's own pixel sigma: the extrinsics' covariance, the LIDAR's range noise, the camera's noise)
    assert max(r["spill_sigma"] for r in rows) < 4.0
    assert max(r["worst_px"] / r["sigma_px"] for r in rows) < 4.0  # this simulator's boards have no rim: every point
    assert np.median([r["spill_px"] for r in rows]) < 1.0  # in pixels: typically well under one
    assert 0.05 < np.median([r["sigma_px"] for r in rows]) < 3.0  # the sigma is a real one, not a floor
    # the truth passes the same check: the metric measures the extrinsics, not the simulator
    exact = ev.lidar_board_in_images(result, rt_lidar0_sensor=truth.rt_lidar0_sensor)
    assert max(r["spill_px"] / r["sigma_px"] for r in exact) < 4.0


def test_the_board_check_fails_on_a_wrong_calibration(solved):
    result, _ = solved
    sd = np.degrees(result.stdev_rt(2)[:3]).max()
    rt = np.array(result.rt_lidar0_sensor)
    rt[2] = compose_rt(rt[2], np.r_[0.0, np.radians(0.5), 0, 0, 0, 0])  # camera 2 turned 0.5 deg about its y
    rows = ev.lidar_board_in_images(result, rt_lidar0_sensor=rt)
    assert 0.5 > 6 * sd  # a wrong calibration, by several times its uncertainty
    cam2 = [r for r in rows if r["camera"] == 2]
    assert max(r["spill_px"] for r in cam2) > 1.5  # a row of points, not a stray one
    # the sigmas of the solved calibration turn the spill into many sigma
    good = {(r["camera"], r["lidar"], r["snapshot"]): r["sigma_px"] for r in ev.lidar_board_in_images(result)}
    assert max(r["spill_px"] / good[r["camera"], r["lidar"], r["snapshot"]] for r in cam2) > 4.0
    # the other camera is untouched
    cam3 = [r for r in rows if r["camera"] == 3]
    assert max(r["spill_px"] / good[r["camera"], r["lidar"], r["snapshot"]] for r in cam3) < 4.0


def test_image_coverage_rule():
    w, h = 800, 600
    rng = np.random.default_rng(0)
    band = [np.c_[rng.uniform(100, 750, 100), rng.uniform(250, 380, 100)] for _ in range(6)]  # the demo's wide camera
    c = ev.image_coverage(band, (w, h))
    assert c["warning"] and "top third (rows 0-200)" in c["warning"] and "bottom third (rows 400-600)" in c["warning"]
    assert c["hull_fraction"] == pytest.approx(650 * 130 / (w * h), rel=0.1)
    assert c["rows_px"][0] >= 250 and c["rows_px"][1] <= 380
    spread = [np.c_[rng.uniform(0, w, 100), rng.uniform(0, h, 100)] for _ in range(6)]
    assert ev.image_coverage(spread, (w, h))["warning"] is None
    # the rule's limit, stated: two thin diagonals (an X) pass, their hull is the whole image
    t = np.linspace(0, 1, 50)
    cx = ev.image_coverage([np.c_[t * w, t * h], np.c_[t * w, (1 - t) * h]], (w, h))
    assert cx["empty_thirds"] == [] and cx["warning"] is None and cx["hull_fraction"] > 0.9
    corner = [np.c_[rng.uniform(0, 250, 100), rng.uniform(0, 180, 100)]]  # a corner of the image only
    cc = ev.image_coverage(corner, (w, h))
    assert cc["hull_fraction"] == pytest.approx(250 * 180 / (w * h), rel=0.15)
    assert f"covers {100 * cc['hull_fraction']:.0f} % of the image (< 30 %)" in cc["warning"]
    assert "right third (columns 533-800)" in cc["warning"]
    assert ev.image_coverage([], (w, h))["warning"].startswith("no corners")


def test_moved_from_nominal(solved):
    result, _ = solved
    rt = np.asarray(result.rt_lidar0_sensor, float)
    nominal = {1: compose_rt(rt[1], np.r_[np.radians(0.5), 0, 0, 0, 0.03, 0.04]), 2: rt[2]}
    rows = {r["sensor"]: r for r in ev.moved_from_nominal(result, nominal)}
    assert set(rows) == {1, 2}
    assert rows[1]["rotation_deg"] == pytest.approx(0.5, abs=1e-9)
    assert rows[1]["translation_mm"] == pytest.approx(50.0, abs=1e-6)  # the offset is in the sensor's frame: its length
    assert rows[2]["rotation_deg"] == pytest.approx(0, abs=1e-9) and rows[2]["translation_mm"] == pytest.approx(0, abs=1e-9)
    assert rows[1]["sigma_mm"] > 0 and rows[1]["sigma_deg"] > 0


def test_residuals_next_to_their_measurements(solved):
    result, _ = solved
    p = result.problem
    geo = ev.lidar_residual_geometry(result)
    n_res = {i: int(np.sum(result.residuals["lidar_sensor"] == i)) for i in (0, 1)}
    assert {i: len(g["residual"]) for i, g in geo.items()} == n_res  # every residual placed
    o = p.lidar_observations[0]
    g = geo[o.sensor]
    k = len(o.points)
    np.testing.assert_allclose(g["range"][:k], np.linalg.norm(o.points, axis=1))
    # the simulated LIDARs' rings: residuals fall on as many elevations as the sensor has rings (or fewer)
    assert len(np.unique(np.round(geo[0]["elevation_deg"], 1))) <= 16
    vec = ev.camera_residual_vectors(result)
    for i in (2, 3):
        want = np.concatenate([o.corners_px for o in p.camera_observations if o.sensor == i])
        assert vec[i]["corners"].shape == want.shape == vec[i]["residuals"].shape
        np.testing.assert_allclose(vec[i]["corners"], want)
        # RMS of the vectors is the camera's residual RMS
        m = result.residuals["camera_sensor"] == i
        assert np.sqrt(np.mean(vec[i]["residuals"] ** 2)) == pytest.approx(np.sqrt(np.mean(result.residuals["camera_px"][m] ** 2)))


def _png(fn, *a, **k):
    b = io.BytesIO()
    fn(*a, b, **k)
    data = b.getvalue()
    img = mpimg.imread(io.BytesIO(data), format="jpeg" if data[:3] == b"\xff\xd8\xff" else "png")
    img = img / 255.0 if img.dtype == np.uint8 else img
    assert np.std(img[..., :3]) > 0.02
    return img


def test_plain_array_figures():
    rng = np.random.default_rng(0)
    # LIDAR on image: drawn into the image's own pixels, two panels side by side plus the colour bar
    q = rng.uniform(0, [640, 480], (500, 2))
    img = _png(plots.plot_lidar_on_image, [{"q": q, "range": rng.uniform(2, 20, 500), "outline": q[:5]}] * 2, (640, 480),
               image=rng.integers(0, 255, (480, 640), dtype=np.uint8))
    assert img.shape[:2] == (480 + 4 + 14, 2 * 640 + 8)
    wall = np.c_[np.full(2000, 5.0), rng.uniform(-3, 3, 2000), rng.uniform(-1, 2, 2000)]
    _png(plots.plot_cloud_overlap, {"before": {"a": wall, "b": wall + 0.05}, "after": {"a": wall, "b": wall}},
         board={"centre": [5, 0, 0.5], "normal": [1, 0, 0], "along": [0, 1, 0], "up": [0, 0, 1], "half_size": (0.6, 0.6)})
    _png(plots.plot_lidar_residuals, [{"title": "l", "residual": rng.normal(0, 0.01, 3000), "range": rng.uniform(2, 9, 3000),
                                       "elevation_deg": rng.choice(np.linspace(-15, 15, 16), 3000)}])
    _png(plots.plot_camera_residuals_and_coverage, [{"title": "c", "imagersize": (640, 480), "corners": q,
                                                     "residuals": rng.normal(0, 0.3, (500, 2)),
                                                     "coverage": ev.image_coverage([q], (640, 480))}])
    # the targetless figures
    _png(plots.plot_map_trajectory, rng.normal(0, 10, (5000, 3)), np.c_[np.arange(50.0), np.zeros(50), np.zeros(50)],
         keyframes=np.c_[np.arange(0, 50.0, 10), np.zeros(5), np.zeros(5)])
    _png(plots.plot_frame_scores, rng.uniform(0.01, 0.02, 8), rng.uniform(0.001, 0.002, 8))
    _png(plots.plot_distance_histograms, {"before": rng.uniform(0, 0.3, 1000), "after": rng.uniform(0, 0.05, 1000)}, max_m=0.3)


def test_show_aligned_crops_to_the_data():
    rng = np.random.default_rng(0)
    room = np.c_[rng.uniform(-3, 3, 5000), rng.uniform(-2, 2, 5000), rng.uniform(-1.5, 1, 5000)]
    far = np.array([[100.0, 0, 60], [-90, 50, -60]])  # a few far returns must not set the scale
    lo, hi = plots.crop_box([np.r_[room, far]])
    assert np.all(lo > [-4, -3, -2.5]) and np.all(hi < [4, 3, 2])
