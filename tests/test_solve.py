"""The backend solve against simulated truth (sim.observations): exactness, accuracy with
realistic noise, honest sigmas, transitive connections, vertical boards, corrupted
observations and degenerate inputs."""

import dataclasses

import numpy as np
import pytest

from clcgraph.backend.solve import calibrate
from clcgraph.config import SolveOptions
from clcgraph.errors import DegenerateError
from clcgraph.geometry import R_from_r, pose_stdevs, r_from_R
from clcgraph.sim.observations import make_rig, simulate_problem


def _errors(result, truth):
    """Per sensor: rotation error (deg), translation error (m), and the error normalized by the
    reported per-axis sigmas (geometry.pose_stdevs: rotation about the sensor's axes composed as
    R_true^T R, position along lidar0's axes)."""
    rt, rt_true = np.asarray(result.rt_lidar0_sensor), truth.rt_lidar0_sensor
    e = rt - rt_true
    w = np.array([r_from_R(R_from_r(b[:3]).T @ R_from_r(a[:3])) for a, b in zip(rt, rt_true)])
    rot = np.degrees(np.linalg.norm(w, axis=1))
    idx = result.variable_sensors()
    z = np.array([np.r_[w[i], e[i, 3:]] / np.r_[pose_stdevs(rt[i], result.covariance_block(i))] for i in idx])
    return rot, np.linalg.norm(e[:, 3:], axis=1), z


def test_noise_free_is_exact():
    problem, truth = simulate_problem(n_snapshots=16, seed=2, sigma_lidar_m=0.0, sigma_camera_px=0.0)
    # exactness, not the verdict; planes and corners (the outline is quantised by the rays even without noise)
    opts = SolveOptions(reestimate_noise=False, reject_outliers=False, consistency_alpha=0.0, lidar_edges=False)
    r = calibrate(problem, opts)
    e = np.asarray(r.rt_lidar0_sensor) - truth.rt_lidar0_sensor
    assert np.abs(e[:, :3]).max() < 1e-6 and np.abs(e[:, 3:]).max() < 1e-6, e


def test_realistic_noise_accuracy_and_honest_sigmas():
    problem, truth = simulate_problem(n_snapshots=40, seed=7, sigma_lidar_m=0.015, sigma_camera_px=0.3)
    r = calibrate(problem, SolveOptions())
    rot, trans, z = _errors(r, truth)
    print("deg", rot.round(4), "mm", (1e3 * trans).round(2), "z", np.abs(z).max().round(2))
    assert rot.max() < 0.05 and trans.max() < 0.005
    assert np.abs(z).max() < 3.0
    assert r.noise["lidar_m"] == pytest.approx(0.015, rel=0.10)
    assert r.noise["camera_px"] == pytest.approx(0.3, rel=0.10)
    assert r.rms["normalized"] == pytest.approx(1.0, abs=0.1)
    assert not [x for x in r.rejected if x.stage == "outlier" and "observation" in x.reason]


def test_lidar_only_transitive_chain():
    """3 LIDARs; lidar2 never sees a board together with lidar0, only with lidar1."""
    rig = make_rig(n_lidars=3, n_cameras=0)
    problem, truth = simulate_problem(rig=rig, n_snapshots=40, seed=4)
    keep = [o for o in problem.lidar_observations
            if not (o.sensor == 2 and o.snapshot % 2 == 0) and not (o.sensor == 0 and o.snapshot % 2 == 1)]
    problem = dataclasses.replace(problem, lidar_observations=tuple(keep))
    shared = {o.snapshot for o in keep if o.sensor == 0} & {o.snapshot for o in keep if o.sensor == 2}
    assert not shared
    r = calibrate(problem, SolveOptions())
    rot, trans, z = _errors(r, truth)
    print("deg", rot.round(4), "mm", (1e3 * trans).round(2))
    assert rot.max() < 0.1 and trans.max() < 0.01
    assert np.abs(z).max() < 3.5


def test_one_lidar_and_cameras():
    rig = make_rig(n_lidars=1, n_cameras=2)
    problem, truth = simulate_problem(rig=rig, n_snapshots=30, seed=5)
    r = calibrate(problem, SolveOptions())
    rot, trans, z = _errors(r, truth)
    assert rot.max() < 0.1 and trans.max() < 0.01 and np.abs(z).max() < 3.5


def test_upright_boards_leave_the_vertical_weak_and_it_is_reported():
    """Boards held upright (pitch jitter 2 deg): the vertical offset of the other LIDARs is
    poorly constrained; the reported sigma says so and covers the error."""
    rig = make_rig(n_lidars=2, n_cameras=0)
    problem, truth = simulate_problem(rig=rig, n_snapshots=30, seed=8, vertical_only=True, vertical_jitter_deg=2.0)
    r = calibrate(problem, SolveOptions())
    sd = r.stdev_rt(1)
    print("stdev rt lidar1", sd)
    assert sd[5] > 5 * max(sd[3], sd[4])  # z is the weak direction
    e = np.asarray(r.rt_lidar0_sensor[1]) - truth.rt_lidar0_sensor[1]
    assert np.all(np.abs(e) < 3.5 * sd)


def test_exactly_vertical_boards_are_degenerate_for_planes_and_the_outline_gives_the_height():
    rig = make_rig(n_lidars=2, n_cameras=0)
    problem, truth = simulate_problem(rig=rig, n_snapshots=20, seed=9, vertical_only=True, vertical_jitter_deg=0.0)
    with pytest.raises(DegenerateError, match=r"/lidar1: translation along lidar0 \([+-]0\.00, [+-]0\.00, \+1\.00\)"):
        calibrate(problem, SolveOptions(lidar_edges=False))
    r = calibrate(problem, SolveOptions(lidar_edges=True))  # the top and bottom edges: where the rings leave the boards
    sd = r.stdev_rt(1)
    e = np.asarray(r.rt_lidar0_sensor[1]) - truth.rt_lidar0_sensor[1]
    assert sd[5] < 0.01 and abs(e[5]) < 3.5 * sd[5], (e, sd)


def test_corrupted_observations_are_rejected():
    clean_p, truth = simulate_problem(n_snapshots=40, seed=10)
    bad_p, bad_truth = simulate_problem(n_snapshots=40, seed=10, corrupt_fraction=0.10)
    assert len(bad_truth.corrupted) >= 6
    clean = calibrate(clean_p, SolveOptions())
    bad = calibrate(bad_p, SolveOptions())
    rot_c, tr_c, _ = _errors(clean, truth)
    rot_b, tr_b, z = _errors(bad, truth)
    print("clean deg/mm", rot_c.max(), 1e3 * tr_c.max(), "corrupted", rot_b.max(), 1e3 * tr_b.max())
    assert rot_b.max() <= 2 * rot_c.max() + 0.005 and tr_b.max() <= 2 * tr_c.max() + 0.0005
    whole = {(x.sensor, x.snapshot) for x in bad.rejected
             if x.stage == "seed" or (x.stage == "outlier" and "observation" in x.reason)}
    # every corrupted observation is rejected; the only others rejected are partners in the
    # same snapshot that contradicted it as strongly (then nothing tells which one is wrong)
    assert set(bad_truth.corrupted) <= whole, set(bad_truth.corrupted) - whole
    bad_snaps = {k for _, k in bad_truth.corrupted}
    assert all(k in bad_snaps for _, k in whole - set(bad_truth.corrupted))
    assert len(whole) <= 2 * len(bad_truth.corrupted)
    assert not [x for x in clean.rejected if x.stage in ("seed",) or "observation" in x.reason]
    assert np.abs(z).max() < 3.5


def test_disconnected_sensor_is_named():
    problem, _ = simulate_problem(n_snapshots=20, seed=11)
    cam = [o for o in problem.camera_observations if o.sensor != 3]
    lid = [o for o in problem.lidar_observations]
    # camera 3 keeps only two boards: fewer than min_shared_snapshots with anyone
    cam += [o for o in problem.camera_observations if o.sensor == 3][:2]
    problem = dataclasses.replace(problem, camera_observations=tuple(cam), lidar_observations=tuple(lid))
    with pytest.raises(DegenerateError, match="/cam1") as e:
        calibrate(problem, SolveOptions())
    assert "\n" not in str(e.value)


def test_noise_is_estimated_per_sensor():
    """Two LIDARs of different range noise (1 and 3 cm): each gets its own sigma (within 10 %)."""
    rig = make_rig(n_lidars=2, n_cameras=1)
    problem, truth = simulate_problem(rig=rig, n_snapshots=30, seed=12, sigma_lidar_m=[0.01, 0.03])
    r = calibrate(problem, SolveOptions())
    per = r.noise["per_sensor"]
    assert abs(per[0] / 0.01 - 1) < 0.1 and abs(per[1] / 0.03 - 1) < 0.1, per
    assert abs(per[2] / 0.3 - 1) < 0.1, per
    rot, tr, z = _errors(r, truth)
    assert np.all(z < 3.5), z


def test_a_noisier_camera_beside_a_sharp_one_keeps_its_boards():
    """Cameras of different corner noise (a sharp mono camera at 0.1 px, a dim noisy one at 0.6 px):
    outliers are judged against each camera's own scale, so the noisy one's boards are not thrown
    out as 'off the board pose the other sensors see' against the sharp one's residuals."""
    rig = make_rig(n_lidars=1, n_cameras=2)
    problem, truth = simulate_problem(rig=rig, n_snapshots=24, seed=5, sigma_camera_px=[0.1, 0.6])
    r = calibrate(problem, SolveOptions())
    noisy = [x for x in r.rejected if x.stage == "outlier" and x.sensor == 2]
    assert len(noisy) <= 1, [x.reason for x in noisy]
    per = r.noise["per_sensor"]
    assert abs(per[1] / 0.1 - 1) < 0.15 and abs(per[2] / 0.6 - 1) < 0.15, per
    rot, tr, z = _errors(r, truth)
    assert np.all(z < 3.5), z


def test_the_estimate_when_the_last_noise_round_moved_the_poses(monkeypatch):
    """The noise components' last round may move the poses (then it hands back no linearization at
    them): the estimate's normalized RMS is taken from a fresh one, as when it did not."""
    from clcgraph.backend import solve as S

    problem, truth = simulate_problem(n_snapshots=12, seed=3)
    settled = calibrate(problem, SolveOptions())
    real = S._solve_with_effects

    def without_lin(*a, **k):  # (..., lin, lr): no linearization handed back
        *head, _, lr = real(*a, **k)
        return (*head, None, lr)

    monkeypatch.setattr(S, "_solve_with_effects", without_lin)
    moved = calibrate(problem, SolveOptions())
    assert moved.rms["normalized"] == pytest.approx(settled.rms["normalized"], rel=1e-6)
    np.testing.assert_allclose(moved.covariance_rt, settled.covariance_rt, rtol=1e-6, atol=1e-14)
