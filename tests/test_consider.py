"""Consider terms (backend/consider.py): errors fixed for the capture propagated into the covariance.

Each term's sensitivity J_c (one Gauss-Newton step from the final linearization) is checked
against a real nonlinear re-solve of the moved measurements; the intrinsics term against a
Monte Carlo over intrinsics drawn from the covariance an mrcal calibration gives them.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from clcgraph.backend import consider
from clcgraph.backend import graph as G
from clcgraph.config import Config
from clcgraph.geometry import drt_dxi, rt_from_pose3
from clcgraph.sim.observations import make_rig, simulate_problem


NO_RING_TERMS = dict(lidar_ring_range_bias_m=0.0, lidar_ring_elevation_deg=0.0, camera_lens_field_px=0.0,
                     # the one-step algebra against re-solves of cm-sized moves: on quadratic losses (the
                     # outline's Huber weights move with them: 3-20 % apart, docs/uncertainty.md)
                     lidar_edges=False)


def _solver(problem, options, sigma):
    """(solve(p, start) -> (rt of the variable sensors (ns,), values), build(p, rt_s, rt_b, only=None)) at fixed sigmas."""
    import gtsam

    active = G.Active.all(problem)
    idx = [i for i in range(len(problem.sensors)) if i != problem.reference]

    def build(p, rt_s, rt_b, only=None):
        return G.build(p, active, rt_s, rt_b, lidar="range", sigma_lidar_m=sigma, sigma_camera_px=sigma,
                       options=options, only=only)

    def solve(p, rt_s, rt_b):
        g, v = build(p, rt_s, rt_b)
        params = gtsam.LevenbergMarquardtParams()
        params.setRelativeErrorTol(1e-12)
        params.setAbsoluteErrorTol(1e-15)
        out = gtsam.LevenbergMarquardtOptimizer(g, v, params).optimize()
        return np.concatenate([rt_from_pose3(out.atPose3(G.sensor_key(i))) for i in idx]), out

    return solve, build, idx


@pytest.fixture(scope="module")
def solved():
    truth_problem, truth = simulate_problem(rig=make_rig(1, 2), n_snapshots=10, seed=5)
    options = dataclasses.replace(Config().solve, **NO_RING_TERMS)  # each test turns on its own term
    sigma = np.array([0.015 if s.is_lidar else 0.3 for s in truth_problem.sensors])
    solve, build, idx = _solver(truth_problem, options, sigma)
    rt_b = truth.rt_lidar0_board
    x, values = solve(truth_problem, truth.rt_lidar0_sensor, rt_b)
    return truth_problem, truth, options, sigma, solve, build, idx, x, values


def _solved_poses(truth, idx, x, values):
    """(rt_sensor, rt_board) of the fixture's solve: the variable sensors' ``x``, lidar0's truth."""
    rt_s = truth.rt_lidar0_sensor.copy()
    for a, i in enumerate(idx):
        rt_s[i] = x[6 * a:6 * a + 6]
    return rt_s, np.array([rt_from_pose3(values.atPose3(G.board_key(k))) for k in range(len(truth.rt_lidar0_board))])


def _rt_columns(terms, x, idx):
    J = np.zeros((6 * len(idx), 6 * len(idx)))
    for a in range(len(idx)):
        J[6 * a:6 * a + 6, 6 * a:6 * a + 6] = drt_dxi(x[6 * a:6 * a + 6])
    return {k: J @ v for k, v in terms.items()}


@pytest.mark.parametrize("what", ["board_flatness_m", "lidar_range_offset_m"])
def test_consider_sensitivity_matches_a_resolve_of_the_moved_measurements(solved, what):
    problem, truth, options, sigma, solve, build, idx, x, values = solved
    h = 0.004
    opts = dataclasses.replace(options, **{"board_flatness_m": 0.0, what: h})
    rt_s, rt_b = _solved_poses(truth, idx, x, values)
    terms = consider.consider_terms(problem, lambda p, only=None: build(p, rt_s, rt_b, only=only)[0], values, opts)
    cols = _rt_columns(terms, x, idx)
    name = "board flatness" if what == "board_flatness_m" else "range offset /lidar0"
    assert set(cols) == {name}
    moved = consider._bow_moves(problem, values, h) if what == "board_flatness_m" else \
        consider._range_moves(problem, 0, h)
    x_moved, _ = solve(moved, rt_s, rt_b)
    dx = x_moved - x
    pred = cols[name][:, 0]
    # the move is measurable (not zero by construction) and the one-step prediction is it to 3 %
    assert np.linalg.norm(dx[3:6]) > 2e-4 and np.linalg.norm(dx[9:12]) > 2e-4
    assert np.linalg.norm(pred - dx) < 0.03 * np.linalg.norm(dx)


def test_range_offset_moves_cameras_along_the_boards_direction(solved):
    """A LIDAR whose ranges are all 1 cm long sees every board ~1 cm farther (along lidar0 +x):
    the cameras, which see the boards where they are, move with them, and turn by < 0.15 deg."""
    problem, truth, options, sigma, solve, build, idx, x, values = solved
    moved = consider._range_moves(problem, 0, 0.01)
    rt_s, rt_b = truth.rt_lidar0_sensor, truth.rt_lidar0_board
    x_moved, _ = solve(moved, rt_s, rt_b)
    for a in range(len(idx)):
        dt = x_moved[6 * a + 3:6 * a + 6] - x[6 * a + 3:6 * a + 6]
        assert 0.006 < dt[0] < 0.012, dt
        assert np.degrees(np.linalg.norm(x_moved[6 * a:6 * a + 3] - x[6 * a:6 * a + 3])) < 0.15


def test_calibrate_adds_the_terms_and_reports_their_shares():
    problem, truth = simulate_problem(rig=make_rig(1, 1), n_snapshots=10, seed=7, planned_tilts=True)
    from clcgraph.backend.solve import calibrate

    base = Config().solve
    assert base.board_flatness_m == 0.001 and base.lidar_range_offset_m == 0.0  # the defaults (docs/uncertainty.md)
    assert base.lidar_ring_range_bias_m == base.lidar_ring_elevation_deg == base.camera_lens_field_px == 0.0
    base = dataclasses.replace(base, lidar_ring_range_bias_m=0.01, lidar_ring_elevation_deg=0.1,
                               camera_lens_field_px=0.1)  # the units' figures, as a user states them
    assert calibrate(problem, base).stats["uncertainty_terms"]["included"] == [
        consider.MODEL_TERM, "board flatness", "ring range bias /lidar0", "ring elevation /lidar0", "lens field /cam0"]
    base = dataclasses.replace(base, **NO_RING_TERMS)
    r0 = calibrate(problem, dataclasses.replace(base, board_flatness_m=0.0))
    r1 = calibrate(problem, dataclasses.replace(base, lidar_range_offset_m=0.01, board_flatness_m=0.003))
    t0 = r0.stats["uncertainty_terms"]
    t1 = r1.stats["uncertainty_terms"]
    assert t0["included"] == [consider.MODEL_TERM]
    assert t1["included"] == [consider.MODEL_TERM, "board flatness", "range offset /lidar0"]
    # the terms are in the variance components' model too (the REML knows them), so the noise
    # sigmas, and with them the estimate and the model part, move a little: here, independent
    # noise, by far less than a sigma / 1 %
    assert np.all(np.abs(r1.rt_lidar0_sensor[1] - r0.rt_lidar0_sensor[1]) < 0.01 * r0.stdev_rt(1))
    C0, C1 = r0.covariance_block(1)[3:, 3:], r1.covariance_block(1)[3:, 3:]
    extra = np.array(t1["sigma_rt"]["range offset /lidar0"])[:, 3:]  # (m, 3): position part
    np.testing.assert_allclose(C1, C0 + extra.T @ extra + np.array(t1["sigma_rt"]["board flatness"])[:, 3:].T
                               @ np.array(t1["sigma_rt"]["board flatness"])[:, 3:], rtol=0.01)
    share = t1["variance_share"]["/cam0"]["position"]
    assert abs(sum(share.values()) - 1) < 1e-9
    # a 1 cm common range offset is 8-12 mm of the camera's position: most of its variance here
    assert share["range offset /lidar0"] > 0.5
    assert 0.006 < np.linalg.norm(extra) < 0.012


def _mrcal_calibrated_model(path, rng):
    """A .cameramodel made as mrcal-calibrate-cameras makes one (optimization_inputs kept): mrcal's
    own calibration of 30 synthetic chessboard views (0.3 px noise) of a known OPENCV4 camera."""
    import mrcal
    import numpysane as nps

    lens, intr, (w, h) = "LENSMODEL_OPENCV4", np.array([800.0, 805.0, 639.5, 479.5, -0.1, 0.02, 1e-3, -1e-3]), (1280, 960)
    truth = mrcal.cameramodel(intrinsics=(lens, intr), imagersize=np.array([w, h]), extrinsics_rt_fromref=np.zeros(6))
    np.random.seed(int(rng.integers(2**31)))  # mrcal draws the board poses from numpy's global generator
    q, Rt_ref_board = mrcal.synthesize_board_observations(
        [truth], object_width_n=10, object_height_n=10, object_spacing=0.05, calobject_warp=None,
        rt_ref_boardcenter=np.array([0, 0, 0, 0, 0, 1.0]),
        rt_ref_boardcenter__noiseradius=np.array([np.radians(30)] * 3 + [0.4, 0.3, 0.3]), Nframes=30,
        which="all-cameras-must-see-full-board")
    obs = nps.glue(q + rng.normal(0, 0.3, q.shape), np.ones(q.shape[:-1] + (1,)), axis=-1)[:, 0]
    n = len(q)
    inputs = dict(lensmodel=lens, intrinsics=(intr + np.r_[5, -5, 2, -2, 0, 0, 0, 0])[None], extrinsics_rt_fromref=np.zeros((0, 6)),
                  frames_rt_toref=mrcal.rt_from_Rt(Rt_ref_board), points=None, observations_point=None,
                  indices_point_camintrinsics_camextrinsics=None, calobject_warp=None, observations_board=obs,
                  indices_frame_camintrinsics_camextrinsics=np.c_[np.arange(n), np.zeros(n), -np.ones(n)].astype(np.int32),
                  imagersizes=np.array([[w, h]], dtype=np.int32), calibration_object_spacing=0.05,
                  do_optimize_intrinsics_core=True, do_optimize_intrinsics_distortions=True, do_optimize_extrinsics=True,
                  do_optimize_frames=True, do_optimize_calobject_warp=False, do_apply_regularization=True,
                  do_apply_outlier_rejection=False)
    mrcal.optimize(**inputs)
    mrcal.cameramodel(optimization_inputs=inputs, icam_intrinsics=0).write(str(path))


def test_intrinsics_term_matches_a_monte_carlo_over_the_intrinsics(tmp_path):
    """The camera's intrinsics drawn from the covariance mrcal's calibration gives them, the
    extrinsics re-solved (same observations) each time: the spread matches J Sigma_i J^T along
    its principal axes (60 draws: the six variances within their chi2 bands, 95 % together)."""
    from clcgraph.cameras import load_camera

    rng = np.random.default_rng(11)
    _mrcal_calibrated_model(tmp_path / "cal.cameramodel", rng)
    cam = load_camera("/cam0", tmp_path / "cal.cameramodel")
    assert cam.intrinsics_covariance is not None and np.all(np.diag(cam.intrinsics_covariance) > 0)
    rig = make_rig(1, 1)
    rig = dataclasses.replace(rig, sensors=(rig.sensors[0], cam))
    problem, truth = simulate_problem(rig=rig, n_snapshots=10, seed=3)
    options = dataclasses.replace(Config().solve, board_flatness_m=0.0, **NO_RING_TERMS)
    sigma = np.array([0.015, 0.3])
    solve, build, idx = _solver(problem, options, sigma)
    x, values = solve(problem, truth.rt_lidar0_sensor, truth.rt_lidar0_board)
    rt_s = truth.rt_lidar0_sensor.copy()
    rt_s[1] = x
    rt_b = np.array([rt_from_pose3(values.atPose3(G.board_key(k))) for k in range(len(truth.rt_lidar0_board))])
    terms = consider.consider_terms(problem, lambda p, only=None: build(p, rt_s, rt_b, only=only)[0], values, options)
    assert list(terms) == ["intrinsics /cam0"]
    A = _rt_columns(terms, x, idx)["intrinsics /cam0"]
    C_pred = A @ A.T
    draws = rng.multivariate_normal(cam.intrinsics, cam.intrinsics_covariance, 60)
    X = np.array([solve(consider._intrinsics_moved(problem, 1, d - cam.intrinsics), rt_s, rt_b)[0] for d in draws])
    C_mc = np.cov(X.T)
    from scipy.stats import chi2

    lo, hi = chi2.ppf([0.025 / 6, 1 - 0.025 / 6], 59) / 59  # 95 % for the six variances together
    for part in (slice(0, 3), slice(3, 6)):
        lam, V = np.linalg.eigh(C_pred[part, part])
        ratio = np.einsum("ia,ij,ja->a", V, C_mc[part, part], V) / lam
        assert np.all((ratio > lo) & (ratio < hi)), ratio
    # and it matters: the intrinsics move the camera by more than 0.3 mm here
    assert np.sqrt(np.linalg.eigvalsh(C_pred[3:, 3:])[-1]) > 3e-4


def test_stated_sigmas_out_of_range_are_refused_naming_the_key():
    from clcgraph.config import ConfigError

    for key in ("board_flatness_m", "lidar_range_offset_m", "lidar_ring_range_bias_m", "lidar_ring_elevation_deg",
                "camera_lens_field_px"):
        with pytest.raises(ConfigError, match=rf"'solve.{key}' must be in \["):
            Config.from_dict({"solve": {key: -0.001}})


def _ring_residuals(problem, truth, sensor=0):
    """Per ring of LIDAR ``sensor``: (elevation rad, mean range beyond the true board plane, count)."""
    from clcgraph.backend.graph import residuals

    lid, _ = residuals(problem, truth.rt_lidar0_sensor, truth.rt_lidar0_board)
    e = np.concatenate([consider._elevations(o.points) for o in problem.lidar_observations if o.sensor == sensor])
    r = np.concatenate([x for o, x in zip(problem.lidar_observations, lid) if o.sensor == sensor])
    ring = np.round(np.degrees(e) / 2).astype(int)  # a VLP-16's rings are 2 deg apart
    _, ring = np.unique(ring, return_inverse=True)
    n = np.bincount(ring).astype(float)
    return np.bincount(ring, e) / n, np.bincount(ring, r) / n, n


def test_after_the_frontends_ring_correction_only_a_trend_over_elevation_is_left():
    """2 cm per-ring range biases: the frontend's correction (applied by the simulator as `solve`
    applies it) leaves a + b e over the rings' elevations, to < 1.5 mm, as the ring range term
    assumes; without it the biases are per ring (the same test sees them, >> 1.5 mm)."""
    from clcgraph.sim.observations import CorrelatedErrors

    kw = dict(rig=make_rig(1, 1), n_snapshots=12, seed=4, sigma_lidar_m=0.01)
    for correct, bound in ((True, (0.0, 1.5e-3)), (False, (5e-3, 0.05))):
        p, t = simulate_problem(errors=CorrelatedErrors(ring_range_bias_m=0.02, frontend_ring_correction=correct), **kw)
        e, m, n = _ring_residuals(p, t)
        A = np.c_[np.ones_like(e), e]
        coef = np.linalg.lstsq(A * np.sqrt(n)[:, None], m * np.sqrt(n), rcond=None)[0]
        rest = np.sqrt(np.average((m - A @ coef) ** 2, weights=n))
        assert bound[0] <= rest < bound[1], (correct, rest)
        assert len(e) >= 8


def test_rings_are_found_from_the_points_elevations():
    problem, truth = simulate_problem(rig=make_rig(2, 0), n_snapshots=8, seed=2)
    for sensor, model in make_rig(2, 0).lidars.items():
        el, counts = consider.lidar_rings(problem, sensor)
        seen = {int(r) for o in problem.lidar_observations if o.sensor == sensor
                for r in np.argmin(np.abs(consider._elevations(o.points)[:, None] - model.elevations_rad), axis=1)}
        assert len(el) == len(seen)  # every ring that met a board, none split or merged
        np.testing.assert_allclose(el, np.asarray(model.elevations_rad)[sorted(seen)], atol=1e-9)
        assert counts.sum() == sum(len(o.points) for o in problem.lidar_observations if o.sensor == sensor)


def test_ring_trend_directions_are_the_covariance_of_the_unestimable_part():
    """Draws of per-ring errors, their relative part taken out as the frontend takes it out
    (point-weighted fit over the rings' elevations): what is left has the covariance the
    directions give (2000 draws, within 10 %)."""
    rng = np.random.default_rng(3)
    el = np.radians(np.linspace(-15, 15, 16))[3:14]
    n = rng.integers(50, 900, len(el)).astype(float)
    dirs, e0 = consider.ring_trend_directions(el, n, 0.02)
    A = np.c_[np.ones_like(el), el - e0]
    b = rng.normal(0, 0.02, (2000, len(el)))
    coef = np.linalg.solve(A.T @ (n[:, None] * A), A.T @ (n[:, None] * b.T)).T
    C = np.cov(coef.T)
    scale = np.sqrt(np.outer(np.diag(C), np.diag(C)))  # correlations to 0.1, variances to 10 %
    assert np.all(np.abs(dirs.T @ dirs - C) <= 0.1 * scale), (dirs.T @ dirs, C)
    # only the trend stays: a and b are far smaller than the ring sigma's share of one ring
    assert np.sqrt(C[0, 0]) < 0.02 / np.sqrt(len(el)) * 1.5


@pytest.mark.parametrize("name", ["ring range bias /lidar0", "ring elevation /lidar0"])
def test_ring_term_sensitivity_matches_a_resolve_of_the_moved_measurements(solved, name):
    problem, truth, options, sigma, solve, build, idx, x, values = solved
    opts = dataclasses.replace(options, board_flatness_m=0.0, lidar_ring_range_bias_m=0.03 * (name[5] == "r"),
                               lidar_ring_elevation_deg=0.3 * (name[5] == "e"))
    rt_s, rt_b = _solved_poses(truth, idx, x, values)
    terms = consider.consider_terms(problem, lambda p, only=None: build(p, rt_s, rt_b, only=only)[0], values, opts)
    assert set(terms) == {name}
    cols = _rt_columns(terms, x, idx)[name]
    dirs, e0 = consider.ring_trend_directions(*consider.lidar_rings(problem, 0),
                                              0.03 if name[5] == "r" else np.radians(0.3))
    assert cols.shape[1] == len(dirs) == 2
    for d, pred in zip(dirs, cols.T):
        moved = consider._ring_range_moves(problem, 0, e0, d) if name[5] == "r" else \
            consider._ring_elevation_moves(problem, values, 0, e0, d)
        dx = solve(moved, rt_s, rt_b)[0] - x
        assert np.linalg.norm(dx[3:6]) > 1e-4  # the move is measurable
        assert np.linalg.norm(pred - dx) < 0.03 * np.linalg.norm(dx), (pred, dx)


def test_lens_field_term_in_closed_form_is_the_relinearized_one_and_a_resolve(solved):
    """The lens-field term's closed form (only b moves: the corners over sigma, through the
    Schur complement) against a relinearization per mode, and one mode against a re-solve."""
    from clcgraph.backend.noise import Linearization

    problem, truth, options, sigma, solve, build, idx, x, values = solved
    opts = dataclasses.replace(options, board_flatness_m=0.0, camera_lens_field_px=0.5)
    rt_s, rt_b = _solved_poses(truth, idx, x, values)
    rebuild = lambda p, only=None: build(p, rt_s, rt_b, only=only)[0]  # noqa: E731
    terms = consider.consider_terms(problem, rebuild, values, opts)
    assert set(terms) == {"lens field /cam0", "lens field /cam1"}
    S, r0, _ = Linearization(problem, rebuild(problem), values).reduced()
    cam = problem.sensors.index(next(s for s in problem.sensors if s.topic == "/cam1"))
    modes = consider.lens_field_modes(problem.sensors[cam].imagersize, 0.5)
    got = terms["lens field /cam1"]
    assert got.shape[1] == 2 * len(modes) >= 10
    for j in (0, 1, 2 * len(modes) - 1):
        moved = consider._lens_moves(problem, cam, modes, j // 2, j % 2, 1.0)
        want = np.linalg.solve(S, Linearization(moved, rebuild(moved), values).reduced()[1] - r0)
        np.testing.assert_allclose(got[:, j], want, rtol=1e-6, atol=1e-9 * np.abs(want).max())
    moved = consider._lens_moves(problem, cam, modes, 0, 0, 1.0)
    dx = solve(moved, rt_s, rt_b)[0] - x
    pred = _rt_columns({"m": got[:, :1]}, x, idx)["m"][:, 0]
    assert np.linalg.norm(dx) > 1e-5 and np.linalg.norm(pred - dx) < 0.03 * np.linalg.norm(dx), (pred, dx)


def test_lens_field_modes_carry_the_fields_covariance():
    """The modes' outer products against the field's kernel at random image points."""
    rng = np.random.default_rng(0)
    q = rng.uniform([0, 0], [1024, 768], (300, 2))
    F = consider.lens_field_modes((1024, 768), 0.3)(q).T
    K = 0.3**2 / 2 * consider.lens_field_kernel((q[:, None, 0] - q[None, :, 0]) / 1024) * \
        consider.lens_field_kernel((q[:, None, 1] - q[None, :, 1]) / 768)
    assert np.all(np.abs(F.T @ F - K) < 0.2 * K[0, 0]) and 0.9 < np.median(np.diag(F.T @ F) / np.diag(K)) <= 1.0


def test_a_stated_fixed_error_is_not_taken_again_by_the_observation_effects():
    """A LIDAR's ring trend (what the frontend's per-ring correction leaves: the same in every
    board) tilts and shifts each board by its own amount (b / range), so the per-observation
    model takes it for plane errors of every board. Stated as a consider term, the REML knows
    it (noise.Linearization.with_known): D keeps only what the term does not explain (here
    nothing: at its floor, as on the capture without the error), the term carries it once,
    and the consistency check counts it in (the capture passes)."""
    from clcgraph.backend.solve import calibrate

    problem, truth = simulate_problem(rig=make_rig(2, 1), n_snapshots=16, seed=5, planned_tilts=True)
    dirs, e0 = consider.ring_trend_directions(*consider.lidar_rings(problem, 1), 0.02)
    # a 1-sigma draw along the trend over elevation (at 2 sigma, 0.13 m/rad, the boards of this
    # 16-ring LIDAR tilt by up to ~2 deg and the linearized term misses part of it: snapshot 5
    # then fails its check at 4.8 sigma)
    trend = dirs[np.argmax(np.abs(dirs[:, 1]))]
    moved = consider._ring_range_moves(problem, 1, e0, trend)
    stated = dataclasses.replace(Config().solve, **{**NO_RING_TERMS, "lidar_ring_range_bias_m": 0.02},
                                 refuse_inconsistent=False)
    unstated = calibrate(moved, dataclasses.replace(stated, lidar_ring_range_bias_m=0.0))
    assert unstated.noise["observation_effects"][1]["tilt_rad"] > 4e-3  # D took it: 0.4 deg per board
    res = calibrate(moved, stated)
    effects = res.noise["observation_effects"][1]
    assert effects["tilt_rad"] < 1e-3 and effects["offset_m"] < 1e-3, effects
    assert res.stats["consistency"]["passed"], res.stats["consistency"]["failures"]
    for i in res.variable_sensors():  # the term alone accounts for the error
        z = (res.rt_lidar0_sensor[i] - truth.rt_lidar0_sensor[i]) / res.stdev_rt(i)
        assert np.all(np.abs(z) < 3.5), (i, z)


def test_a_ring_elevation_error_moves_the_outline_with_the_rays(solved):
    """The rays really leave 1 mrad higher: the points' ranges change (their directions are the
    reported ones) and the outline, crossed by the same real rays, is reported 1 mrad lower."""
    problem, truth, options, sigma, solve, build, idx, x, values = solved
    moved = consider._ring_elevation_moves(problem, values, 0, 0.0, np.array([1e-3, 0.0]))
    n = 0
    for o, m in zip(problem.lidar_observations, moved.lidar_observations):
        if o.edge_rays is None or not len(o.edge_rays):
            continue
        n += 1
        a, b = np.asarray(o.edge_rays).reshape(-1, 3, 3), np.asarray(m.edge_rays).reshape(-1, 3, 3)
        el = lambda u: np.arcsin(u[..., 2])  # noqa: E731
        np.testing.assert_allclose(el(b[:, :2]), el(a[:, :2]) - 1e-3, atol=1e-9)
        np.testing.assert_allclose(np.arctan2(b[:, :2, 1], b[:, :2, 0]), np.arctan2(a[:, :2, 1], a[:, :2, 0]), atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(b[:, :2], axis=2), 1.0, atol=1e-12)
        np.testing.assert_array_equal(b[:, 2], a[:, 2])  # the sides' normals as seen
    assert n >= 5


def test_the_ring_range_term_takes_the_spread_of_the_measured_ring_offsets():
    """A unit whose rings range 2 cm apart (sd): the frontend's correction measures their relative
    offsets on the boards and takes them out; what it cannot see (a + b e over the rings'
    elevations, in every board) is drawn from the same spread, so the ring range term gets
    that sigma with nothing stated. An exact unit's rings show none: no term, no inflation."""
    from clcgraph.sim.observations import CorrelatedErrors

    kw = dict(rig=make_rig(1, 1), n_snapshots=12, seed=4, sigma_lidar_m=0.01)
    # no poses (values) here: the board thickness term, which needs them, off
    options = dataclasses.replace(Config().solve, **NO_RING_TERMS, board_thickness_sigma_m=0.0)
    biased, _ = simulate_problem(errors=CorrelatedErrors(ring_range_bias_m=0.02), **kw)
    x = biased.lidar_ring_offsets[0]
    assert len(x) >= 8 and np.all(np.diff(x[:, 0]) > 0)  # (ring, offset) per ring the boards met
    assert 0.012 < consider.ring_range_bias_sigma(biased, 0, options) < 0.035
    wanted, _ = consider._wanted(biased, None, options)
    assert "ring range bias /lidar0" in wanted
    stated = dataclasses.replace(options, lidar_ring_range_bias_m=0.05)  # a larger stated sigma stands
    assert consider.ring_range_bias_sigma(biased, 0, stated) == 0.05
    exact, _ = simulate_problem(**kw)
    assert not exact.lidar_ring_offsets and consider.ring_range_bias_sigma(exact, 0, options) == 0.0
    assert not [n for n in consider._wanted(exact, None, options)[0] if n.startswith("ring")]


def test_a_pose_the_terms_leave_imprecise_is_refused_naming_the_term():
    """A 10 cm common range offset stated for lidar0: the cameras, which see the boards where they
    are, are known to no better than that along the boards' direction (lidar0's x), beyond
    solve.max_stdev_m: refused, naming the camera, the direction and the term, not written."""
    from clcgraph.backend.solve import calibrate
    from clcgraph.errors import DegenerateError

    problem, _ = simulate_problem(rig=make_rig(1, 1), n_snapshots=10, seed=7, planned_tilts=True)
    base = dataclasses.replace(Config().solve, **NO_RING_TERMS)
    assert calibrate(problem, dataclasses.replace(base, lidar_range_offset_m=0.01)).stdev_rt(1)[3] < 0.03
    with pytest.raises(DegenerateError, match=r"imprecise, no result written: /cam0: translation along lidar0 "
                                              r"\(.*\) = .*x.*, 1-sigma 0.\d+ m, \d+ % of its variance from range "
                                              r"offset /lidar0 \(> solve.max_stdev_m 0.03 m"):
        calibrate(problem, dataclasses.replace(base, lidar_range_offset_m=0.1))


def test_focal_length_term_matches_a_resolve_with_the_focal_length_scaled(solved):
    """A camera without an intrinsics covariance, its focal length stated to 1 %: the term's
    one-step sensitivity is a re-solve with fx, fy 1 % longer (to 3 %), and it moves that
    camera along its line of sight (the boards' distance is PnP's, proportional to f)."""
    problem, truth, options, sigma, solve, build, idx, x, values = solved
    opts = dataclasses.replace(options, board_flatness_m=0.0, camera_focal_scale_sigma=0.01)
    rt_s, rt_b = _solved_poses(truth, idx, x, values)
    cols = _rt_columns(consider.consider_terms(problem, lambda p, only=None: build(p, rt_s, rt_b, only=only)[0], values, opts), x, idx)
    cams = [i for i in idx if problem.sensors[i].is_camera]
    assert set(cols) == {f"focal length {problem.sensors[i].topic}" for i in cams}
    i = cams[0]
    d = np.zeros(len(problem.sensors[i].intrinsics))
    d[:2] = 0.01 * np.asarray(problem.sensors[i].intrinsics[:2])
    x_moved, _ = solve(consider._intrinsics_moved(problem, i, d), rt_s, rt_b)
    dx = x_moved - x
    pred = cols[f"focal length {problem.sensors[i].topic}"][:, 0]
    a = idx.index(i)
    assert np.linalg.norm(dx[6 * a + 3:6 * a + 6]) > 0.005  # centimetres for boards metres away
    assert np.linalg.norm(pred - dx) < 0.03 * np.linalg.norm(dx)
