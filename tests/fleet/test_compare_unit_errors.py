"""`compare` of two calibrations of the same sensor units: the units' own errors e (a LIDAR ring's
range bias, ...) are the same in both captures, so the difference carries (J_A - J_B) e, J = how
each capture's solution moves with e (calibration.yaml's ``unit_errors``). Checked against
re-solves of two small simulated captures with the same e put into both.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from clcgraph import api
from clcgraph.backend import consider
from clcgraph.comparison import compare, paired_sensitivities, poses_of, unit_error_term
from clcgraph.config import Config
from clcgraph.geometry import r_from_R, rt_from_T, tangent_covariance_from_rt
from clcgraph.sim.observations import make_rig, simulate_problem

LIDAR = 1  # the 32-ring LIDAR of make_rig(2, 1)
RING_BIAS_M = 0.003  # the units' e: small enough for the re-solves to stay linear in it


def _capture(seed):
    problem, _ = simulate_problem(rig=make_rig(2, 1), n_snapshots=12, seed=seed, planned_tilts=True)
    return problem, api.calibrate(problem, Config())


@pytest.fixture(scope="module")
def captures():
    return [_capture(seed) for seed in (1, 2)]


def _with_ring_biases(problem, bias_at):
    """``problem`` with LIDAR's rings biased by ``bias_at(elevations_rad)`` (m), as the frontend leaves
    them: their point-weighted fit over the rings (consider.ring_trend_projection)."""
    elevations, counts = consider.lidar_rings(problem, LIDAR)
    P, e0 = consider.ring_trend_projection(elevations, counts)
    return consider._ring_range_moves(problem, LIDAR, e0, P @ bias_at(elevations))


def _xi(ra, rb, i):
    """The comparison's tangent of sensor i's difference: [Log(R_a^T R_b), R_a^T (t_b - t_a)]."""
    from clcgraph.geometry import T_from_rt

    Ta, Tb = T_from_rt(ra.rt_lidar0_sensor[i]), T_from_rt(rb.rt_lidar0_sensor[i])
    return np.r_[r_from_R(Ta[:3, :3].T @ Tb[:3, :3]), Ta[:3, :3].T @ (Tb[:3, 3] - Ta[:3, 3])]


def test_the_difference_moves_as_J_A_minus_J_B_when_both_captures_share_the_units_errors(captures):
    (pa, ra), (pb, rb) = captures
    ring_elevations = np.radians(np.linspace(-25, 15, 32))  # the unit's rings (make_rig's 32-ring LIDAR)
    bias = np.random.default_rng(3).normal(0, RING_BIAS_M, len(ring_elevations))

    def bias_at(elevations):
        return bias[np.argmin(np.abs(elevations[:, None] - ring_elevations[None, :]), axis=1)]

    ra2, rb2 = (api.calibrate(_with_ring_biases(p, bias_at), Config()) for p in (pa, pb))
    ua, ub = poses_of(ra).unit_errors, poses_of(rb).unit_errors
    for i in (1, 2):
        topic = ra.problem.sensors[i].topic
        union, Ja, Jb = paired_sensitivities(topic, ra.rt_lidar0_sensor[i], rb.rt_lidar0_sensor[i], ua, ub)
        e = np.array([bias_at(np.radians([at]))[0] if (s, err) == ("/lidar1", "ring range bias") else 0.0
                      for s, err, at in union])
        predicted = (Jb - Ja) @ e  # xi is B's pose less A's
        moved = _xi(ra2, rb2, i) - _xi(ra, rb, i)
        Sd = sum(tangent_covariance_from_rt(r.rt_lidar0_sensor[i], r.covariance_block(i)) for r in (ra, rb))
        sd = np.sqrt(np.diag(Sd))
        # J_B - J_A predicts the shift (the camera's too, which only the LIDAR's rings move)
        np.testing.assert_allclose(moved / sd, predicted / sd, atol=0.005 + 0.03 * np.max(np.abs(predicted) / sd))
        if i == LIDAR:  # the biased LIDAR's shift is a real share of the difference's sigma (the check can fail) ...
            assert np.max(np.abs(predicted) / sd) > 0.3, (topic, predicted / sd)
            for wrong in (Jb @ e, -Ja @ e, (Ja + Jb) @ e):  # ... and neither capture's J alone, nor their sum, predicts it
                assert np.max(np.abs(moved - wrong) / sd) > 0.1


def test_compare_adds_the_paired_term_to_the_difference_covariance(captures):
    (_, ra), (_, rb) = captures
    sigma = 0.02
    cfg = Config.from_dict({"compare": {"unit_ring_range_bias_m": sigma, "unit_ring_elevation_deg": 0,
                                        "unit_lens_field_px": 0}})
    none = Config.from_dict({"compare": {"unit_ring_range_bias_m": 0, "unit_ring_elevation_deg": 0,
                                         "unit_lens_field_px": 0}})
    c, c0 = compare(ra, rb, config=cfg), compare(ra, rb, config=none)
    ua, ub = poses_of(ra).unit_errors, poses_of(rb).unit_errors
    assert "named errors of the units paired" in c.unit_errors and "same units" in c.unit_errors
    for i in (1, 2):
        topic = ra.problem.sensors[i].topic
        rta, rtb = ra.rt_lidar0_sensor[i], rb.rt_lidar0_sensor[i]
        union, Ja, Jb = paired_sensitivities(topic, rta, rtb, ua, ub)
        ring_bias = np.array([err == "ring range bias" for _, err, _ in union])
        D = (Ja - Jb)[:, ring_bias]
        term = unit_error_term(topic, rta, rtb, ua, ub, {"ring range bias": sigma, "ring elevation": 0, "lens field": 0})
        np.testing.assert_allclose(term, sigma**2 * D @ D.T, rtol=1e-9, atol=1e-18)
        xi = _xi(ra, rb, i)
        Sd = sum(tangent_covariance_from_rt(r.rt_lidar0_sensor[i], r.covariance_block(i)) for r in (ra, rb))
        row, row0 = (next(s for s in x.sensors if s.topic == topic) for x in (c, c0))
        assert row.chi2 == pytest.approx(xi @ np.linalg.solve(Sd + term, xi), rel=1e-6)
        assert row0.chi2 == pytest.approx(xi @ np.linalg.solve(Sd, xi), rel=1e-6)
        assert row.chi2 < row0.chi2


def test_replaced_units_and_the_solves_own_terms(captures):
    """A replaced unit: independent draws, J_A S J_A^T + J_B S J_B^T; a sigma already in a solve's
    covariance is not counted twice."""
    (_, ra), (_, rb) = captures
    ua, ub = poses_of(ra).unit_errors, poses_of(rb).unit_errors
    s = {"ring range bias": 0.01, "ring elevation": 0.0, "lens field": 0.0}
    topic, rta, rtb = "/cam0", ra.rt_lidar0_sensor[2], rb.rt_lidar0_sensor[2]
    union, Ja, Jb = paired_sensitivities(topic, rta, rtb, ua, ub)
    m = np.array([err == "ring range bias" for _, err, _ in union])
    swap = unit_error_term(topic, rta, rtb, ua, ub, s, same_units=False)
    np.testing.assert_allclose(swap, 1e-4 * (Ja[:, m] @ Ja[:, m].T + Jb[:, m] @ Jb[:, m].T), rtol=1e-9, atol=1e-18)
    included = {**ua, "sigma_in_covariance": {**ua["sigma_in_covariance"], "ring range bias": 0.01}}
    np.testing.assert_allclose(unit_error_term(topic, rta, rtb, included, ub, s, same_units=False),
                               1e-4 * Jb[:, m] @ Jb[:, m].T, rtol=1e-9, atol=1e-18)
    # per LIDAR (a ring range bias measured on its boards): each error by its own LIDAR's sigma
    lidars = sorted({sensor for sensor, err, _ in union if err == "ring range bias"})
    per = {**ua, "sigma_in_covariance": {**ua["sigma_in_covariance"], "ring range bias": {t: 0.01 for t in lidars}}}
    np.testing.assert_allclose(unit_error_term(topic, rta, rtb, per, ub, s, same_units=False),
                               1e-4 * Jb[:, m] @ Jb[:, m].T, rtol=1e-9, atol=1e-18)
    one = {**ua, "sigma_in_covariance": {**ua["sigma_in_covariance"], "ring range bias": {lidars[0]: 0.01}}}
    if len(lidars) > 1:  # the other LIDAR's rings are not in A's covariance: still counted
        assert not np.allclose(unit_error_term(topic, rta, rtb, one, ub, s, same_units=False),
                               1e-4 * Jb[:, m] @ Jb[:, m].T, rtol=1e-6, atol=1e-18)


def test_unit_errors_round_trip_through_calibration_yaml_read_once(captures, tmp_path, monkeypatch):
    (_, ra), (_, rb) = captures
    from clcgraph.outputs.results import write_results

    write_results(ra, tmp_path / "a")
    write_results(rb, tmp_path / "b")
    reads = []
    real = type(tmp_path).read_text
    monkeypatch.setattr(type(tmp_path), "read_text", lambda self, *a, **k: reads.append(self.name) or real(self, *a, **k))
    files, results = compare(tmp_path / "a", tmp_path / "b"), compare(ra, rb)
    assert reads.count("calibration.yaml") == 2  # once per side
    for f, r in zip(files.sensors, results.sensors):
        assert (f.chi2 is None) == (r.chi2 is None)
        if r.chi2 is not None:
            assert f.chi2 == pytest.approx(r.chi2, rel=1e-4)
    assert files.unit_errors == results.unit_errors


def test_one_side_without_unit_errors_is_said_and_not_paired(captures):
    (_, ra), (_, rb) = captures
    pb = dataclasses.replace(poses_of(rb), unit_errors=None)
    c = compare(ra, pb)
    assert c.unit_errors.startswith("not in the test: only A names")
    none = Config.from_dict({"compare": {"unit_ring_range_bias_m": 0, "unit_ring_elevation_deg": 0,
                                         "unit_lens_field_px": 0}})
    assert [s.chi2 for s in c.sensors] == [s.chi2 for s in compare(ra, rb, config=none).sensors]
    assert "only A names" in c.table()


def test_rings_of_another_lidar_model_are_not_paired_and_said(captures):
    """B's rings 0.5 deg off A's (another LIDAR model): none paired, each side's J against zero, and the
    line suggests compare.same_units=false."""
    (_, ra), (_, rb) = captures
    pb = poses_of(rb)
    ub = {**pb.unit_errors, "errors": [(s, e, at + 0.5 if e.startswith("ring") else at) for s, e, at in pb.unit_errors["errors"]]}
    c = compare(ra, dataclasses.replace(pb, unit_errors=ub))
    assert "compare.same_units=false" in c.unit_errors
    union, Ja, Jb = paired_sensitivities("/lidar1", ra.rt_lidar0_sensor[1], rb.rt_lidar0_sensor[1], poses_of(ra).unit_errors, ub)
    ring = np.array([e.startswith("ring") for _, e, _ in union])
    assert not np.any((np.abs(Ja[:, ring]).sum(0) > 0) & (np.abs(Jb[:, ring]).sum(0) > 0))  # no ring in both
