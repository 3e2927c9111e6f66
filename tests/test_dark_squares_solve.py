"""A board's dark squares ranging long in clouds without intensities (backend/dark_squares.py):
measured on the solved board poses and taken out, the answer within its sigmas; left in, it is
many sigmas off. Without such an offset nothing is taken out."""

import dataclasses

import numpy as np
import pytest

from clcgraph.backend import dark_squares
from clcgraph.backend.solve import calibrate
from clcgraph.config import SolveOptions
from clcgraph.geometry import T_from_rt
from clcgraph.sim.observations import make_rig, simulate_problem
from test_solve import _errors

LONG_M = 0.015  # the dark squares' range walk


@pytest.fixture(scope="module")
def simulated():
    problem, truth = simulate_problem(rig=make_rig(2, 1), n_snapshots=16, seed=4, sigma_lidar_m=0.01)
    lidar = []
    for o in problem.lidar_observations:  # the squares of parity 1 printed dark: their returns long
        parity, _, on = dark_squares._squares(problem, o, T_from_rt(truth.rt_lidar0_sensor[o.sensor]),
                                              truth.rt_lidar0_board[o.snapshot])
        p = np.asarray(o.points, float).copy()
        dark = on & (parity == 1)
        p[dark] *= (1 + LONG_M / np.linalg.norm(p[dark], axis=1))[:, None]
        lidar.append(dataclasses.replace(o, points=p))
    return problem, dataclasses.replace(problem, lidar_observations=tuple(lidar)), truth


def test_the_offset_is_measured_on_the_true_poses(simulated):
    problem, long, truth = simulated
    found = dark_squares.measure(long, truth.rt_lidar0_sensor, truth.rt_lidar0_board)
    assert sorted(found) == [0, 1]
    for f in found.values():
        assert f.longer == 1 and f.significant and f.offset_m == pytest.approx(LONG_M, abs=3 * f.se_m), f
    plain = dark_squares.measure(problem, truth.rt_lidar0_sensor, truth.rt_lidar0_board)
    assert not any(f.significant for f in plain.values()), plain


def test_taken_out_the_answer_is_within_its_sigmas_and_left_in_it_is_not(simulated, monkeypatch):
    _, long, truth = simulated
    r = calibrate(long, SolveOptions())
    rot, trans, z = _errors(r, truth)
    assert np.abs(z).max() < 3.5 and trans.max() < 0.003, (np.abs(z).max(), trans)
    assert all(d["taken_out"] and d["offset_mm"] == pytest.approx(1e3 * LONG_M, abs=1.5)
               for d in r.stats["dark_squares"].values()), r.stats["dark_squares"]
    monkeypatch.setattr(dark_squares, "SIGNIFICANT", np.inf)  # never taken out
    _, _, z_left = _errors(calibrate(long, SolveOptions()), truth)
    assert np.abs(z_left).max() > 5, np.abs(z_left).max()
