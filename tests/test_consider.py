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


def _solver(problem, options, sigma):
    """(solve(p, start) -> (rt of the variable sensors (ns,), values), rebuild(p) -> graph) at fixed sigmas."""
    import gtsam

    active = G.Active.all(problem)
    idx = [i for i in range(len(problem.sensors)) if i != problem.reference]

    def build(p, rt_s, rt_b):
        return G.build(p, active, rt_s, rt_b, lidar="range", sigma_lidar_m=sigma, sigma_camera_px=sigma,
                       options=options)

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
    options = Config().solve
    sigma = np.array([0.015 if s.is_lidar else 0.3 for s in truth_problem.sensors])
    solve, build, idx = _solver(truth_problem, options, sigma)
    rt_b = truth.rt_lidar0_board
    x, values = solve(truth_problem, truth.rt_lidar0_sensor, rt_b)
    return truth_problem, truth, options, sigma, solve, build, idx, x, values


def _rt_columns(terms, x, idx):
    J = np.zeros((6 * len(idx), 6 * len(idx)))
    for a in range(len(idx)):
        J[6 * a:6 * a + 6, 6 * a:6 * a + 6] = drt_dxi(x[6 * a:6 * a + 6])
    return {k: J @ v for k, v in terms.items()}


@pytest.mark.parametrize("what", ["board_flatness_m", "lidar_range_offset_m"])
def test_consider_sensitivity_matches_a_resolve_of_the_moved_measurements(solved, what):
    problem, truth, options, sigma, solve, build, idx, x, values = solved
    h = 0.004
    opts = dataclasses.replace(options, **{what: h})
    rt_s = truth.rt_lidar0_sensor.copy()
    for a, i in enumerate(idx):
        rt_s[i] = x[6 * a:6 * a + 6]
    rt_b = np.array([rt_from_pose3(values.atPose3(G.board_key(k))) for k in range(len(truth.rt_lidar0_board))])
    terms = consider.consider_terms(problem, lambda p: build(p, rt_s, rt_b)[0], values, opts)
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
    problem, truth = simulate_problem(rig=make_rig(1, 1), n_snapshots=10, seed=7)
    base = Config().solve
    r0 = consider_free = __import__("clcgraph.backend.solve", fromlist=["calibrate"]).calibrate(problem, base)
    r1 = __import__("clcgraph.backend.solve", fromlist=["calibrate"]).calibrate(
        problem, dataclasses.replace(base, lidar_range_offset_m=0.01, board_flatness_m=0.003))
    t0 = r0.stats["uncertainty_terms"]
    t1 = r1.stats["uncertainty_terms"]
    assert t0["included"] == [consider.MODEL_TERM]
    assert t1["included"] == [consider.MODEL_TERM, "board flatness", "range offset /lidar0"]
    np.testing.assert_allclose(r1.rt_lidar0_sensor, consider_free.rt_lidar0_sensor)  # the estimate is unchanged
    C0, C1 = r0.covariance_block(1)[3:, 3:], r1.covariance_block(1)[3:, 3:]
    extra = np.array(t1["sigma_rt"]["range offset /lidar0"])[:, 3:]  # (m, 3): position part
    np.testing.assert_allclose(C1, C0 + extra.T @ extra + np.array(t1["sigma_rt"]["board flatness"])[:, 3:].T
                               @ np.array(t1["sigma_rt"]["board flatness"])[:, 3:], rtol=1e-9, atol=1e-15)
    share = t1["variance_share"]["/cam0"]["position"]
    assert abs(sum(share.values()) - 1) < 1e-9
    # a 1 cm common range offset is 8-12 mm of the camera's position: most of its variance here
    assert share["range offset /lidar0"] > 0.5
    assert 0.006 < np.linalg.norm(extra) < 0.012
