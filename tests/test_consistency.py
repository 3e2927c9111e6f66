"""Self-consistency checks (backend/consistency.py) and the solve's refusals: the linearized
information against GTSAM's marginals, the leave-one-out statistic against its chi-square
law, corrupted captures refused instead of answered, an unobservable direction named
instead of GTSAM's "Indeterminate linear system", and cameras rolled against each other
(the seed relabels their corners)."""

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from clcgraph.backend import consistency as C
from clcgraph.backend import graph as G
from clcgraph.backend.solve import calibrate
from clcgraph.config import SolveOptions
from clcgraph.errors import ClcgraphError, DegenerateError, SolveError
from clcgraph.frontend.camera_board import canonicalize
from clcgraph.geometry import R_from_r, compose_rt, drt_dxi, rt_from_R_t
from clcgraph.sim.observations import CorrelatedErrors, Rig, SimLidar, make_rig, plane_fit, simulate_problem
from clcgraph.types import BoardGeometry, CameraBoardObservation, LidarBoardObservation, Sensor

REFUSING = SolveOptions(refuse_inconsistent=True)
# planes only (no board outline): what the checks must catch where a LIDAR sees only the board's plane
PLANES = dataclasses.replace(REFUSING, lidar_edges=False)


def _rt(ypr_deg, xyz):
    return rt_from_R_t(Rotation.from_euler("ZYX", ypr_deg, degrees=True).as_matrix(), np.array(xyz, float))


def _errors(result, truth_rt):
    """Per non-reference sensor: (rotation error deg, translation error mm, max |error| / sigma)."""
    out = {}
    for i in result.variable_sensors():
        dR = R_from_r(result.rt_lidar0_sensor[i][:3]).T @ R_from_r(truth_rt[i][:3])
        deg = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
        mm = 1e3 * np.linalg.norm(result.rt_lidar0_sensor[i][3:] - truth_rt[i][3:])
        z = np.abs(result.rt_lidar0_sensor[i] - truth_rt[i]) / result.stdev_rt(i)
        out[result.problem.sensors[i].topic] = (deg, mm, z.max())
    return out


# ---------------------------------------------------------------- the machinery


def test_axis_words():
    assert C.axis_words([0, 0, 1]) == "z"
    assert C.axis_words([0, -0.99, 0.05]) == "-y"
    assert C.axis_words([0.6, 0.0, -0.8]) == "0.60x-0.80z"


def test_information_matches_gtsam_marginals():
    """The board-profiled information of consistency.linearize inverts to the solve's covariance."""
    problem, _ = simulate_problem(rig=make_rig(2, 1), n_snapshots=20, seed=21)
    # every observation active, white noise only and no stated capture-fixed errors (their terms are
    # added to the covariance after the graph's own, backend/consider.py): the same graph is rebuilt below
    opts = SolveOptions(reject_outliers=False, observation_effects=False, board_flatness_m=0.0)
    r = calibrate(problem, opts)
    assert not [x for x in r.rejected if x.stage == "seed"]
    sig = np.array([r.noise["per_sensor"][i] for i in range(len(problem.sensors))])
    g, v = G.build(r.problem, G.Active.all(r.problem), r.rt_lidar0_sensor, r.rt_lidar0_board, lidar="range", sigma_lidar_m=sig,
                   sigma_camera_px=sig, options=SolveOptions())
    H, _, _ = C.information(C.linearize(r.problem, g, v))
    J = np.zeros_like(H)
    for a, i in enumerate(r.variable_sensors()):
        J[6 * a:6 * a + 6, 6 * a:6 * a + 6] = drt_dxi(r.rt_lidar0_sensor[i])
    cov = J @ np.linalg.inv(H) @ J.T
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), np.sqrt(np.diag(r.covariance_rt)), rtol=0.02)


def test_leave_one_out_statistic_follows_its_chi_square_law():
    """With Gaussian noise as modelled, the leave-one-snapshot-out chi-squares add up to their
    degrees of freedom (sum over 30 snapshots: sd ~ sqrt(2 dof), so 25 % is ~3 sd)."""
    problem, _ = simulate_problem(rig=make_rig(2, 1), n_snapshots=30, seed=7)
    # planes and corners: the outline's error is uniform within its interval, which its sigma bounds
    # (its whitened mean square is ~0.5 here with no beam blur stated, 0.5-0.64 on the real ACFR captures)
    opts = SolveOptions(reject_outliers=False, lidar_edges=False)
    r = calibrate(problem, opts)
    assert not [x for x in r.rejected if x.stage == "seed"]
    sig = np.array([r.noise["per_sensor"][i] for i in range(len(problem.sensors))])
    g, v = G.build(r.problem, G.Active.all(r.problem), r.rt_lidar0_sensor, r.rt_lidar0_board, lidar="range",
                   sigma_lidar_m=sig, sigma_camera_px=sig, options=opts)
    lin = C.linearize(r.problem, g, v)
    H, grad, per = C.information(lin)
    tests = [C.compare(lin, h, x, H - h, grad - x) for h, x in per.values()]
    chi2 = sum(t.chi2 for t in tests if t)
    dof = sum(t.dof for t in tests if t)
    print("sum chi2", chi2, "dof", dof)
    assert dof > 100
    assert chi2 / dof == pytest.approx(1.0, abs=0.25)
    assert r.stats["consistency"]["passed"]


def test_errors_shared_by_the_parts_are_counted_in_their_comparison():
    """Two parts of the data whose estimates an error c ~ N(0, I) shared by both moves by
    different amounts (a consider term: fixed for the capture): with c's columns the statistic
    follows its chi-square law (mean = dof), without them it is several times too large."""
    rng = np.random.default_rng(3)
    n, m, trials = 6, 2, 4000
    lin = C.Linearized([1], [], np.zeros((n, n)), np.zeros((n, 1)), np.stack([np.eye(3)] * 2), ["/l0", "/s1"])
    L_a, L_b = rng.normal(size=(n, n)), rng.normal(size=(n, n))
    H_a, H_b = 1e6 * (L_a @ L_a.T + np.eye(n)), 1e6 * (L_b @ L_b.T + np.eye(n))  # sigmas ~ 1 mm, mrad
    dg_a, dg_b = 3e3 * rng.normal(size=(n, m)), 3e3 * rng.normal(size=(n, m))  # c moves them by ~ 3 sigma
    with_c, without = [], []
    for _ in range(trials):
        c = rng.normal(size=m)
        g_a = np.linalg.cholesky(H_a) @ rng.normal(size=n) + dg_a @ c
        g_b = np.linalg.cholesky(H_b) @ rng.normal(size=n) + dg_b @ c
        with_c.append(C.compare(lin, H_a, np.c_[g_a, dg_a], H_b, np.c_[g_b, dg_b]).chi2)
        without.append(C.compare(lin, H_a, g_a, H_b, g_b).chi2)
    assert np.mean(with_c) == pytest.approx(n, rel=0.05)  # sd of the mean: sqrt(2 n / trials) / n ~ 1 %
    assert np.mean(np.array(with_c) > 16.81) == pytest.approx(0.01, abs=0.005)  # chi2_6's 99 % point
    assert np.mean(without) > 2 * n


# ---------------------------------------------------------------- item 5: 3 LIDARs, transitive links


def _three_lidar_rig() -> Rig:
    """VLP-16 front (lidar0), 64-ring roof, VLP-16 rear facing backwards."""
    vlp16 = SimLidar(np.radians(np.linspace(-15, 15, 16)))
    os64 = SimLidar(np.radians(np.linspace(-22.5, 22.5, 64)), npoints_per_rotation=1024)
    sensors = tuple(Sensor(topic=t, kind="lidar") for t in ("/front", "/roof", "/rear"))
    rts = np.array([_rt((0, 0, 0), (0, 0, 0)), _rt((2, 1, 0.5), (-1.2, 0.05, 0.9)),
                    _rt((178, -1, 1), (-2.4, -0.05, 0.05))])
    return Rig(sensors, rts, {0: vlp16, 1: os64, 2: vlp16})


def _three_lidar_problem(seed: int, n_front: int, n_rear: int = 12):
    """Front boards seen by /front and /roof, rear boards by /roof and /rear: /front and
    /rear never see a board together."""
    rig = _three_lidar_rig()
    pf, tf = simulate_problem(rig=rig, n_snapshots=n_front, seed=seed, azimuth_rad=(-0.6, 0.6), range_m=(3, 8))
    pr, _ = simulate_problem(rig=rig, n_snapshots=n_rear, seed=seed + 1000, range_m=(3, 8),
                             azimuth_rad=(np.pi - 0.6, np.pi + 0.6), origin=(-2.4, 0, 0))
    lid = [o for o in pf.lidar_observations if o.sensor != 2]
    lid += [dataclasses.replace(o, snapshot=o.snapshot + n_front) for o in pr.lidar_observations if o.sensor != 0]
    p = dataclasses.replace(pf, lidar_observations=tuple(lid),
                            snapshot_stamps_ns=np.r_[pf.snapshot_stamps_ns, pr.snapshot_stamps_ns + 10**12])
    return p, tf.rt_lidar0_sensor


def _range_bias(problem, sensor, snapshots, metres):
    """That sensor's points in those snapshots pushed ``metres`` along their rays (a board
    seen through a window, a range offset, its frame instead of its face)."""
    lid = list(problem.lidar_observations)
    for j, o in enumerate(lid):
        if o.sensor == sensor and o.snapshot in snapshots:
            pts = o.points * (1 + metres / np.linalg.norm(o.points, axis=1))[:, None]
            plane, rms = plane_fit(pts)
            lid[j] = LidarBoardObservation(o.sensor, o.snapshot, pts, plane, rms)
    return dataclasses.replace(problem, lidar_observations=tuple(lid))


@pytest.mark.parametrize("n_front", [4, 12])
def test_three_lidars_transitive_is_right_or_refused(n_front):
    """Issue 11 item 5 with default settings: every sensor within 3 sigma, or exit 2 naming a
    sensor."""
    outcomes = []
    for seed in range(3):
        p, truth = _three_lidar_problem(seed, n_front)
        try:
            e = _errors(calibrate(p, REFUSING), truth)
        except ClcgraphError as ex:
            assert ex.exit_code == 2 and ("/roof" in str(ex) or "/rear" in str(ex)) and "\n" not in str(ex)
            outcomes.append("refused")
            continue
        print(n_front, seed, e)
        # honest (the 0.1 deg / 5 mm of issue 11 needs more boards than 12 + 12: /rear's
        # 1-sigma is ~5 mm here), and nowhere near a silent wrong answer (5 cm)
        assert all(z < 3 and mm < 50 for deg, mm, z in e.values()), e
        outcomes.append("right")
    print(n_front, outcomes)
    if n_front == 4:  # 4 boards cannot check the front-roof link: every run is refused
        assert outcomes == ["refused"] * 3


def test_range_bias_in_some_rear_boards_is_refused():
    """3 of the rear LIDAR's boards 4 cm long. With white noise only and without the checks a
    silent wrong answer (/rear 35-90 mm off, 5-11 sigma; the jackknife floor, off here, brings
    it to ~4); with them exit 2 naming the snapshot
    and sensors. The default noise model gives each board its own plane-offset error, so there
    the offsets are noise it knows of: the answer is honest (within 3 sigma) or refused."""
    p, truth = _three_lidar_problem(2, n_front=12)
    rear = sorted({o.snapshot for o in p.lidar_observations if o.sensor == 2})
    bad = _range_bias(p, 2, rear[:3], 0.04)
    unchecked = calibrate(bad, SolveOptions(consistency_alpha=0.0, observation_effects=False, jackknife_floor=False))
    deg, mm, z = _errors(unchecked, truth)["/rear"]
    assert z > 5 and not unchecked.stats["consistency"]["passed"]
    with pytest.raises(SolveError, match=r"not self-consistent.*snapshot \d+ \(/rear, /roof\) disagrees") as e:
        calibrate(bad, dataclasses.replace(REFUSING, observation_effects=False))
    assert "\n" not in str(e.value)
    try:
        r = calibrate(bad, REFUSING)
    except (SolveError, DegenerateError) as e:
        assert "\n" not in str(e)
    else:
        assert all(z < 3 for _, _, z in _errors(r, truth).values()), _errors(r, truth)


def test_a_disagreeing_snapshot_is_left_out_and_the_rest_answered():
    """One rear board 4 cm long, white noise only (nothing in the model absorbs it): its snapshot
    fails its leave-one-out test; it is left out, named in the rejections and the verdict, and
    the rest answers within 3 sigma. Three such boards of 24: one in ten may go, then the
    calibration is refused as before, saying which were left out."""
    p, truth = _three_lidar_problem(2, n_front=12)
    rear = sorted({o.snapshot for o in p.lidar_observations if o.sensor == 2})
    white = dataclasses.replace(REFUSING, observation_effects=False)
    r = calibrate(_range_bias(p, 2, rear[1:2], 0.04), white)
    assert [x["snapshot"] for x in r.stats["consistency"]["left_out"]] == [rear[1]]
    why = [x for x in r.rejected if x.stage == "consistency"]
    assert len(why) == 1 and why[0].snapshot == rear[1] and why[0].reason.startswith("left out: it disagrees")
    assert not np.all(np.isfinite(r.rt_lidar0_board[rear[1]])) and r.stats["consistency"]["passed"]
    assert all(z < 3 for _, _, z in _errors(r, truth).values()), _errors(r, truth)
    from clcgraph.outputs.report import _consistency, consistency_verdict

    assert "<b>Left out</b>" in _consistency(r) and "after leaving out snapshot" in consistency_verdict(r)[3]
    with pytest.raises(SolveError, match=r"not self-consistent.*\(after leaving out snapshot \d+, snapshot \d+ that "
                                         r"disagreed with the others\)$"):
        calibrate(_range_bias(p, 2, rear[:3], 0.04), white)


def test_a_refusal_after_a_snapshot_was_left_out_is_one_line_naming_it(monkeypatch, caplog):
    """Leaving a snapshot out may leave a sensor unconnected or unobservable: the refusal keeps its
    kind and says what was left out before it, and the left-out warning (logged only once a result
    stands) does not come first: a refused command prints one line."""
    from clcgraph.backend import solve as S

    p, _ = _three_lidar_problem(2, n_front=12)
    calls = iter([C.Inconsistent("not self-consistent", 3, "disagrees with the other snapshots by 9 sigma"),
                  DegenerateError("cannot connect to lidar0 /lidar0: /lidar2 (boards seen together: 2)")])

    def refuse(problem, options, on_estimate=None):
        raise next(calls)

    monkeypatch.setattr(S, "_calibrate_once", refuse)
    with caplog.at_level("INFO"), pytest.raises(DegenerateError, match=r"^cannot connect to lidar0 /lidar0: /lidar2 "
                                                r"\(boards seen together: 2\) \(after leaving out snapshot 3 that "
                                                r"disagreed with the others\)$"):
        calibrate(p, REFUSING)
    assert not [r for r in caplog.records if r.levelname == "WARNING"]


def test_link_resting_on_one_board_is_refused():
    """4 front boards, one of them 4 cm long: the solve moves /roof ~60 mm (10 sigma) and, with
    planes alone, no leave-one-out test can see it (that board alone fixes the direction):
    refused. With the boards' outlines the other boards fix it too: answered, within 3 sigma."""
    p, truth = _three_lidar_problem(1, n_front=4)
    front = sorted({o.snapshot for o in p.lidar_observations if o.sensor == 0})
    bad = _range_bias(p, 0, front[:1], 0.04)
    # white noise only: ~60 mm, 10+ sigma (the default per-board errors widen the sigma to ~4.5)
    unchecked = calibrate(bad, SolveOptions(consistency_alpha=0.0, observation_effects=False, jackknife_floor=False))
    deg, mm, z = _errors(unchecked, truth)["/roof"]
    assert z > 5 and mm > 30
    with pytest.raises(DegenerateError, match=r"not verifiable.*snapshot \d alone carries \d+% of the information "
                                              r"on /(roof|rear) (translation along|rotation about) lidar0"):
        calibrate(bad, PLANES)
    r = calibrate(bad, dataclasses.replace(REFUSING, lidar_edges=True))
    assert all(z < 3 for _, _, z in _errors(r, truth).values()), _errors(r, truth)


# ---------------------------------------------------------------- the leverage bound


def _repeated_poses(rig, n_poses, copies, seed, *, offset_m=0.005, corner_bias_px=0.2):
    """``n_poses`` board poses, each observed ``copies`` times with fresh noise and, per copy,
    its own plane offset (all ranges) and corner shift: errors each observation's D describes."""
    exact, _ = simulate_problem(rig=rig, n_snapshots=n_poses, seed=seed, sigma_lidar_m=0.0, sigma_camera_px=0.0)
    rng = np.random.default_rng(seed + 1)
    lid, cam = [], []
    for c in range(copies):
        for o in exact.lidar_observations:
            rho = np.linalg.norm(o.points, axis=1)
            pts = o.points * (1 + (rng.normal(0, 0.015, len(rho)) + rng.normal(0, offset_m)) / rho)[:, None]
            plane, rms = plane_fit(pts)
            lid.append(LidarBoardObservation(o.sensor, o.snapshot + c * n_poses, pts, plane, rms))
        for o in exact.camera_observations:
            q = o.corners_px + rng.normal(0, 0.3, o.corners_px.shape) + rng.normal(0, corner_bias_px, 2)
            cam.append(CameraBoardObservation(o.sensor, o.snapshot + c * n_poses, q))
    stamps = np.concatenate([exact.snapshot_stamps_ns + c * 10**12 for c in range(copies)])
    return dataclasses.replace(exact, lidar_observations=tuple(lid), camera_observations=tuple(cam),
                               snapshot_stamps_ns=stamps)


@pytest.mark.parametrize("n_lidars,n_cameras,n_poses,copies", [(1, 1, 6, 3), (2, 0, 5, 4)])
def test_a_board_seen_r_times_carries_at_most_1_over_r_of_any_direction(n_lidars, n_cameras, n_poses, copies):
    """Every pose observed ``copies`` times alike: no copy can carry more than 1/copies of the
    information in any direction, whatever the poses. With each observation's own error D
    condensed (kept here: the copies' offsets differ) as without it, so the per-snapshot
    information and the total are built from the same terms (the total less one snapshot is
    the rest). The large shares of real captures are their geometry (next test)."""
    p = _repeated_poses(make_rig(n_lidars, n_cameras), n_poses, copies, seed=3)
    for effects in (False, True):
        r = calibrate(p, SolveOptions(observation_effects=effects, refuse_inconsistent=False))
        if effects:  # D is in the graph with a sigma above its floor: the condensed path is tested
            assert max(max(c.values()) for c in r.noise["observation_effects"].values()) > 1e-3
        share = r.stats["consistency"]["snapshots"]["max_leverage"]
        print(effects, share)
        assert 0.5 / copies < share <= 1.02 / copies


def _subset(parts):
    """One problem from (problem, snapshots) pairs: those snapshots, renumbered in order."""
    lid, cam, stamps = [], [], []
    for p, keep in parts:
        new = {k: len(stamps) + j for j, k in enumerate(keep)}
        lid += [dataclasses.replace(o, snapshot=new[o.snapshot]) for o in p.lidar_observations if o.snapshot in new]
        cam += [dataclasses.replace(o, snapshot=new[o.snapshot]) for o in p.camera_observations if o.snapshot in new]
        stamps += [p.snapshot_stamps_ns[0] + 10**9 * (len(stamps) + j) for j in range(len(keep))]
    return dataclasses.replace(parts[0][0], lidar_observations=tuple(lid), camera_observations=tuple(cam),
                               snapshot_stamps_ns=np.array(stamps, np.int64))


def upright_boards_and_pitched(n_pitched):
    """12 boards held upright (normals within ~4 deg of horizontal) on a 1-LIDAR + 1-camera rig
    with correlated errors, then the ``n_pitched`` most pitched of 30 tilted ones: the problem,
    the rig, and those boards' normals' vertical parts."""
    rig = make_rig(1, 1)
    err = CorrelatedErrors(board_warp_m=0.003, mixed_pixel_m=0.03, corner_bias_px=0.2)
    upright, _ = simulate_problem(rig=rig, n_snapshots=12, seed=5, vertical_only=True, vertical_jitter_deg=3.0,
                                  tilt_max_deg=40, errors=err)
    pool, pool_truth = simulate_problem(rig=rig, n_snapshots=30, seed=6, tilt_max_deg=45, errors=err)
    n_z = np.array([R_from_r(b[:3])[2, 2] for b in pool_truth.rt_lidar0_board])
    pitched = [int(k) for k in np.argsort(-np.abs(n_z))[:n_pitched]]
    return _subset([(upright, range(12)), (pool, pitched)]), rig, n_z[pitched]


@pytest.mark.parametrize("n_pitched", [1, 3])
def test_height_resting_on_one_pitched_board_is_refused(n_pitched):
    """The real ACFR run 2 in miniature: 12 boards held upright (normals within ~4 deg of
    horizontal) and ``n_pitched`` pitched ~40-47 deg. A LIDAR sees only the board's plane, so
    the camera's height relative to it comes from the plane offsets weighted by the normals'
    vertical part squared: one pitched board carries ~100 % of it and a range error there moves
    the camera's height unseen (refused, naming the height). Three carry it together: answered,
    within 3 sigma. (Planes only: the outline gives the height from every board,
    tests/factors/test_lidar_edge.py.)"""
    p, rig, n_z = upright_boards_and_pitched(n_pitched)
    assert np.all(np.abs(n_z) > 0.6)
    if n_pitched == 1:
        with pytest.raises(DegenerateError, match=r"not verifiable.*snapshot 12 alone carries (9\d|100)% of the "
                                                  r"information on /cam0 translation along lidar0 -?z") as e:
            calibrate(p, PLANES)
        assert "\n" not in str(e.value)
        # what to do about it, in the user's words: the height needs boards pitched up and down
        assert "capture more boards that /cam0 and the other sensors see together, pitched up and down" in str(e.value)
        return
    r = calibrate(p, PLANES)
    assert r.stats["consistency"]["passed"]
    truth = np.r_[[np.zeros(6)], [rig.rt_lidar0_sensor[1]]]
    assert all(z < 3 for _, _, z in _errors(r, truth).values()), _errors(r, truth)


# ---------------------------------------------------------------- item 6: never tilted


@pytest.mark.parametrize("n_lidars,n_cameras,seed", [(2, 0, 0)])
def test_indeterminate_system_names_sensor_and_direction(n_lidars, n_cameras, seed):
    """Boards exactly upright, planes only: GTSAM's marginals fail ("Indeterminate linear
    system"); the solve names the sensor and the vertical instead, in one line."""
    problem, _ = simulate_problem(rig=make_rig(n_lidars, n_cameras), n_snapshots=20, seed=seed, vertical_only=True,
                                  vertical_jitter_deg=0.0)
    with pytest.raises(DegenerateError, match=r"unobservable: /(lidar1|cam0|cam1): translation along lidar0 "
                                              r"\([+-]0\.0\d, [+-]0\.0\d, \+1\.00\) = z") as e:
        calibrate(problem, PLANES)
    assert "\n" not in str(e.value) and "Indeterminate" not in str(e.value)


# ---------------------------------------------------------------- item 12: rolled cameras


def _rolled_camera_problem(roll_deg, board=BoardGeometry(), seed=3):
    """1 LIDAR, cam0 and cam1 side by side, cam1 rolled about its optical axis; corners in
    the detector's canonical ordering (what mrgingham/OpenCV return)."""
    rig = make_rig(n_lidars=1, n_cameras=2)
    rts = rig.rt_lidar0_sensor.copy()
    rts[2] = compose_rt(rts[1], np.array([0, 0, np.radians(roll_deg), 0.2, 0.05, 0.02]))
    p, truth = simulate_problem(rig=dataclasses.replace(rig, rt_lidar0_sensor=rts), n_snapshots=30, seed=seed,
                                board=board)
    cams = tuple(dataclasses.replace(o, corners_px=canonicalize(o.corners_px, board.corners_x, board.corners_y))
                 for o in p.camera_observations)
    return dataclasses.replace(p, camera_observations=cams), truth


@pytest.mark.parametrize("roll_deg,board", [(90, BoardGeometry()), (180, BoardGeometry()),
                                            (180, BoardGeometry(corners_x=8, corners_y=6))])
def test_rolled_camera_is_relabelled_at_seeding(roll_deg, board):
    p, truth = _rolled_camera_problem(roll_deg, board)
    relabelled = sum(not np.allclose(o.corners_px, canonicalize(o.corners_px, board.corners_x, board.corners_y))
                     for o in p.camera_observations)
    assert relabelled == 0  # the detector's orderings: the rolled camera's turned by roll_deg
    shared = {o.snapshot for o in p.camera_observations if o.sensor == 1} & \
             {o.snapshot for o in p.camera_observations if o.sensor == 2}
    assert len(shared) >= 10
    from clcgraph.backend.seed import seed, sensor_poses

    assert np.array_equal(sensor_poses(p, SolveOptions()), seed(p, SolveOptions()).rt_lidar0_sensor)  # what board_regions uses
    r = calibrate(p, SolveOptions())
    whole = [x for x in r.rejected if x.stage == "seed" or (x.stage == "outlier" and "observation" in x.reason)]
    assert not whole, whole
    turned = sum(not np.array_equal(a.corners_px, b.corners_px)
                 for a, b in zip(p.camera_observations, r.problem.camera_observations))
    assert turned >= len(shared)  # one of the two cameras relabelled on every shared board
    e = _errors(r, truth.rt_lidar0_sensor)
    print(roll_deg, e)
    assert all(deg < 0.1 and mm < 10 and z < 3.5 for deg, mm, z in e.values()), e


def test_verdict_is_written_to_calibration_yaml_and_report():
    import yaml

    from clcgraph.outputs.report import report_html
    from clcgraph.outputs.results import calibration_dict

    problem, _ = simulate_problem(rig=make_rig(3, 0), n_snapshots=20, seed=31)
    r = calibrate(problem, SolveOptions())
    d = yaml.safe_load(yaml.safe_dump(calibration_dict(r)))["consistency"]
    assert d["passed"] is True and d["n_checks"] >= 20
    assert 0 <= d["snapshots"]["worst_sigma"] < 4.5 and d["p_limit"] == pytest.approx(1e-3 / d["n_checks"], rel=1e-5)  # written to 6 digits
    assert set(d["weakest"]) == {"/lidar1", "/lidar2"}
    w = d["weakest"]["/lidar1"]
    assert w["weakest_translation_stdev_mm"] == pytest.approx(1e3 * np.sqrt(np.linalg.eigvalsh(
        r.covariance_block(1)[3:, 3:])[-1]), rel=0.05)  # rt and tangent translations agree to first order
    html = report_html(r)
    assert "<h2>Consistency</h2>" in html and "self-consistent" in html
