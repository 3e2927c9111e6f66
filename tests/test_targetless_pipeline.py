"""Targetless calibration end to end on a simulated drive (bag round trip, truth comparison)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

import clcgraph
from clcgraph import geometry as geo
from clcgraph.config import Config
from clcgraph.errors import DegenerateError
from clcgraph.sim.drive import DrivePlan, simulate_drive, write_drive_bag
from clcgraph.targetless.pipeline import calibrate_targetless, calibrate_targetless_scans

TOP, SIDE = "/top/points", "/side/points"


def _cfg():
    # a 15 s test drive has ~9 keyframes: skip fewer, space selected frames closer than the seed's 5 m
    return Config().replace(targetless=dict(calibration_skip_keyframes=1, calibration_min_distance_between_frames=1.0))


def _T(res, topic):
    """The result's (4,4) T_lidar0_sensor of a topic."""
    return geo.T_from_rt(res.rt_lidar0_sensor[res.sensor_index(topic)])


def _err(T_true, T):
    e = geo.rt_from_T(np.linalg.inv(T_true) @ T)
    return np.degrees(np.linalg.norm(e[:3])), np.linalg.norm(e[3:])


@pytest.fixture(scope="module")
def drive():
    return simulate_drive(DrivePlan.small(duration_s=15.0), seed=0)


@pytest.mark.slow
def test_targetless_from_bag_accuracy_covariance_outputs(drive, tmp_path_factory):
    d = tmp_path_factory.mktemp("tl")
    write_drive_bag(drive, d / "drive.bag")
    res = calibrate_targetless([d / "drive.bag"], mapping_topic=TOP, calibration_topics=[SIDE], base_frame="base_link",
                               config=_cfg())
    T_true = drive.T_lidar0_lidar(SIDE, TOP)
    g_deg, g_m = _err(T_true, res.targetless.T_lidar0_sensor_guess[SIDE])
    assert g_deg == pytest.approx(2.0, abs=1e-3) and g_m == pytest.approx(0.2, abs=1e-3)  # the perturbed guess
    e_deg, e_m = _err(T_true, _T(res, SIDE))
    assert e_deg <= 0.02 and e_m <= 0.003, (e_deg, e_m)
    # covariance consistent: the error composed (about the sensor's axes, along lidar0's) within
    # 3 of the per-axis sigmas
    T = _T(res, SIDE)
    err = np.r_[geo.r_from_R(T_true[:3, :3].T @ T[:3, :3]), T[:3, 3] - T_true[:3, 3]]
    sd = np.r_[geo.pose_stdevs(geo.rt_from_T(T), res.covariance_block(SIDE))]
    assert np.all(np.abs(err) <= 3 * sd), (err, sd)
    assert np.all(sd < np.r_[np.radians([0.05] * 3), [0.005] * 3])  # and not uselessly large
    # base_link: roll/pitch from the ground while the body rolls/pitches 0.5 deg
    Tb = res.T_base_sensor[TOP]
    Tt = drive.T_base_lidar[TOP]
    R = Tt[:3, :3].T @ Tb[:3, :3]
    up_err = np.degrees(np.arccos(np.clip((Tb[:3, :3].T @ [0, 0, 1]) @ (Tt[:3, :3].T @ [0, 0, 1]), -1, 1)))
    assert up_err <= 0.1, up_err
    assert abs(Tb[2, 3] - Tt[2, 3]) <= 0.005
    assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) < 0.2  # guess yaw kept (zero for the reference)
    # outputs: the one output path of both methods
    assert res.method == "targetless"
    out = d / "out"
    clcgraph.write_outputs(res, out)
    cal = yaml.safe_load((out / "calibration.yaml").read_text())
    assert cal["reference"] == TOP and [s["topic"] for s in cal["sensors"]] == [TOP, SIDE]
    assert np.allclose(np.array(cal["sensors"][1]["T_lidar0_sensor"]), _T(res, SIDE))
    assert np.array(cal["covariance_rt_lidar0_sensor"]).shape == (6, 6)  # the reference excluded, as solve writes it
    loaded = clcgraph.load_result(out)  # the same loader as for `clcgraph solve`
    assert np.allclose(loaded["sensors"][1]["T_lidar0_sensor"], _T(res, SIDE))
    assert np.allclose(loaded["covariance_rt_lidar0_sensor"], res.covariance_block(SIDE))
    assert loaded.method == "targetless" and np.allclose(loaded.T_lidar0_sensor(SIDE), _T(res, SIDE))
    assert loaded["base_link"][0]["T_base_link_sensor"].shape == (4, 4)
    g = cal["graph"][SIDE]  # the final graph: keyframe poses linked by submap registrations
    assert g["keyframes"] >= 3 and g["keyframe_edges"] >= g["keyframes"] - 1 and g["frames"] >= 2
    assert cal["base_link"][0]["topic"] == TOP
    assert cal["convergence"][SIDE]["converged"] and cal["convergence"][SIDE]["stages"][-1]["stage"] == "final"
    assert "timings_s" not in cal and "mapping" in yaml.safe_load((out / "timings.yaml").read_text())["timings_s"]
    assert np.allclose(geo.T_from_rt(np.array(cal["base_link"][1]["rt_base_link_sensor"])),
                       np.array(cal["base_link"][1]["T_base_link_sensor"]))
    # tf under base_link (the ground plane's), the reference's own pose included, nothing base <- base
    tf_lines = (out / "ros" / "static_tf_ros2.sh").read_text().splitlines()
    assert len(tf_lines) == 2 and all("static_transform_publisher" in ln and "--frame-id base_link" in ln
                                      for ln in tf_lines)
    assert "--child-frame-id side_lidar" in tf_lines[1]
    assert '<child link="side_lidar"/>' in (out / "ros" / "sensors.urdf.xml").read_text()
    html = (out / "report.html").read_text()
    for png in ("map_top.png", "scores_side_points.png", "aligned_side_points.png", "distances_side_points.png"):
        assert f"alt='{png}'" in html and not (out / png).exists()  # embedded, not beside it
    assert html.count("data:image/png;base64,") == 4


@pytest.mark.slow
@pytest.mark.slow
def test_a_drive_recorded_in_split_files_gives_the_whole_bags_answer(drive, tmp_path):
    """`rosbag record --split`: the files read as one drive, in any order given, the last one
    without one LIDAR's messages (the recording ended between its scan and the other's); the
    answer is the single bag's, to the bit."""
    from clcgraph.frontend.bag import bag_info
    from clcgraph.sim.bag_writer import split_ros1_bag

    write_drive_bag(drive, tmp_path / "drive.bag")
    whole = calibrate_targetless([tmp_path / "drive.bag"], mapping_topic=TOP, calibration_topics=[SIDE], config=_cfg())
    info = bag_info(tmp_path / "drive.bag")
    last = sorted(t.last_ns for t in info.topics if t.topic in (TOP, SIDE))
    (tmp_path / "split").mkdir()
    write_drive_bag(drive, tmp_path / "split" / "drive.bag")
    # three files, the third from between the two LIDARs' last scans: it holds only the later one
    parts = split_ros1_bag(tmp_path / "split" / "drive.bag", ((last[0] + last[1]) / 2 - info.start_ns) / 2e9)
    assert len(parts) == 3 and len(bag_info(parts[-1]).topics) == 1
    split = calibrate_targetless(parts[::-1], mapping_topic=TOP, calibration_topics=[SIDE], config=_cfg())
    np.testing.assert_array_equal(split.rt_lidar0_sensor[1], whole.rt_lidar0_sensor[1])


def test_cli_targetless_prints_the_table_and_writes_outputs(drive, tmp_path, capsys):
    """Through the CLI, from a ROS2 mcap bag with organised Ouster-style clouds (padding, t in ns)."""
    from clcgraph.cli import main

    write_drive_bag(drive, tmp_path / "drive", format="ros2-mcap", layout="ouster")
    (tmp_path / "cfg.yaml").write_text(_cfg().to_yaml())
    rc = main(["-q", "targetless", "--bag", str(tmp_path / "drive"), "--mapping-topic", TOP,
               "--calibration-topics", SIDE, "--base-frame", "base_link", "--config", str(tmp_path / "cfg.yaml"),
               "--out", str(tmp_path / "out")])
    out = capsys.readouterr().out
    assert rc == 0, out
    lines = out.splitlines()
    assert lines[0].split()[:3] == ["sensor", "kind", "x,"] and any(ln.startswith(SIDE) for ln in lines)
    assert any(ln.startswith(f"base_link <- {TOP}") for ln in lines) and "report.html" in lines[-1]
    side = next(ln for ln in lines if ln.startswith(SIDE)).split()
    T_true = drive.T_lidar0_lidar(SIDE, TOP)
    assert np.allclose([float(v) for v in side[2:5]], T_true[:3, 3], atol=0.003)  # printed x y z, to 3 mm
    cal = yaml.safe_load((tmp_path / "out" / "calibration.yaml").read_text())
    assert cal["method"] == "targetless" and (tmp_path / "out" / "config.resolved.yaml").exists()
    # the result feeds the same tools as a target-based one; format-for-ros takes base_link <- top
    # from the ground plane (the bag's /tf_static is only the guess)
    rc = main(["-q", "format-for-ros", str(tmp_path / "drive"), "--calibration", str(tmp_path / "out"),
               "--out", str(tmp_path / "ros")])
    assert rc == 0
    ros = yaml.safe_load((tmp_path / "ros" / "ros-transforms.yaml").read_text())
    side_ros = ros["transforms"]["side_lidar"]
    T_base_side = np.array(cal["base_link"][1]["T_base_link_sensor"])
    assert np.allclose([side_ros["translation"][k] for k in "xyz"], T_base_side[:3, 3], atol=1e-9)
    assert main(["-q", "show-aligned", str(tmp_path / "drive"), "--calibration", str(tmp_path / "out"),
                 "--png", str(tmp_path / "aligned.png")]) == 0
    capsys.readouterr()
    assert main(["-q", "show-uncertainty", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "targetless" in err[0]


@pytest.mark.slow
def test_two_calibration_lidars_share_the_map():
    from clcgraph.sim.drive import LidarSpec, _rt

    base = DrivePlan.small()
    rear = LidarSpec("/rear/points", "rear_lidar", 16, 512, -15.0, 15.0, _rt([-20.0, 5.0, 185.0], [-0.9, -0.2, 1.4]), 0.061)
    dr = simulate_drive(DrivePlan.small(duration_s=15.0, lidars=base.lidars + (rear,)), seed=6)
    res = calibrate_targetless_scans(dr.scans, mapping_topic=TOP, calibration_topics=[SIDE, "/rear/points"],
                                     T_base_sensor_guess=dr.T_base_lidar_guess, config=_cfg())
    for t in (SIDE, "/rear/points"):
        T_true = dr.T_lidar0_lidar(t, TOP)
        e_deg, e_m = _err(T_true, _T(res, t))
        assert e_deg <= 0.03 and e_m <= 0.004, (t, e_deg, e_m)
        T = _T(res, t)  # the rear LIDAR is turned 185 deg: compose, never subtract rt
        err = np.r_[geo.r_from_R(T_true[:3, :3].T @ T[:3, :3]), T[:3, 3] - T_true[:3, 3]]
        sd = np.r_[geo.pose_stdevs(geo.rt_from_T(T), res.covariance_block(t))]
        assert np.all(np.abs(err) <= 3 * sd), (t, err, sd)
        assert res.targetless.graph[t]["keyframe_edges"] >= 1


@pytest.mark.slow
def test_a_better_scoring_initial_guess_is_kept_with_honest_sigmas(drive, monkeypatch):
    import clcgraph.targetless.pipeline as pl

    guess = np.linalg.inv(drive.T_base_lidar_guess[TOP]) @ drive.T_base_lidar_guess[SIDE]
    # every frame's points on the map at the guess, off it elsewhere
    monkeypatch.setattr(pl, "squared_distances", lambda frames, T: [np.zeros(1) if np.allclose(T, guess)
                                                                    else np.ones(1) for _ in frames])
    res = calibrate_targetless_scans(drive.scans, mapping_topic=TOP, calibration_topics=[SIDE],
                                     T_base_sensor_guess=drive.T_base_lidar_guess, config=_cfg())
    assert np.allclose(_T(res, SIDE), guess) and "initial guess kept" in res.targetless.notes[0]
    # the guess is 2 deg / 20 cm off and its sigmas say so (>= 1/3 of the distance to the registration)
    sd = res.stdev_rt(SIDE)
    assert np.degrees(np.linalg.norm(sd[:3])) > 0.6 and np.linalg.norm(sd[3:]) > 0.06


def test_open_flat_field_is_degenerate():
    dr = simulate_drive(DrivePlan.small(duration_s=4.0, scene="flat"), seed=1)
    with pytest.raises(DegenerateError, match="degenerate"):
        calibrate_targetless_scans(dr.scans, mapping_topic=TOP, calibration_topics=[SIDE],
                                   T_base_sensor_guess=dr.T_base_lidar_guess, config=_cfg())


def test_stopped_vehicle_is_degenerate():
    dr = simulate_drive(DrivePlan.small(duration_s=3.0, stopped=True), seed=2)
    with pytest.raises(DegenerateError, match="did not move"):
        calibrate_targetless_scans(dr.scans, mapping_topic=TOP, calibration_topics=[SIDE],
                                   T_base_sensor_guess=dr.T_base_lidar_guess, config=_cfg())


@pytest.mark.slow
def test_short_drive_with_default_settings_adapts_the_frame_spacing(tmp_path):
    """A 10 s drive (~5 m at 2 km/h, 6 keyframes): the seed's settings (skip 5 keyframes, 5 m between
    frames) left 1 calibration frame and failed; the spacing now follows the drive (and is reported).
    Bag written with drivers' log times, run through the CLI with default settings (--set only a
    picture setting, to show it is honoured)."""
    from clcgraph.cli import main

    dr = simulate_drive(DrivePlan.small(duration_s=10.0), seed=0)
    write_drive_bag(dr, tmp_path / "drive.bag")
    out = tmp_path / "out"
    assert main(["-q", "targetless", "--bag", str(tmp_path / "drive.bag"), "--mapping-topic", TOP,
                 "--calibration-topics", SIDE, "--out", str(out), "--set", "targetless.mapping_viz_leaf_size=0.3"]) == 0
    cal = yaml.safe_load((out / "calibration.yaml").read_text())
    plan = cal["calibration_frames"]
    assert plan["skip_keyframes"] == 0 and plan["spacing_m"] == Config().targetless.new_keyframe_min_distance
    assert 4.0 < plan["drive_length_m"] < 6.0 and cal["graph"][SIDE]["frames"] >= 4
    assert yaml.safe_load((out / "config.resolved.yaml").read_text())["targetless"]["mapping_viz_leaf_size"] == 0.3
    T = np.array(next(s for s in cal["sensors"] if s["topic"] == SIDE)["T_lidar0_sensor"])
    e_deg, e_m = _err(dr.T_lidar0_lidar(SIDE, TOP), T)
    assert e_deg <= 0.02 and e_m <= 0.003, (e_deg, e_m)


def test_frame_plan_follows_the_drive():
    from types import SimpleNamespace

    from clcgraph.targetless.selection import adapt_to_drive

    def drive(n_keyframes, step_m):
        T = [np.eye(4) for _ in range(n_keyframes)]
        for k, t in enumerate(T):
            t[0, 3] = k * step_m
        return SimpleNamespace(keyframe_ids=list(range(n_keyframes)), frames=[SimpleNamespace(T_map_lidar=t) for t in T])

    o = Config().targetless  # seed: skip 5, 5 m apart, at most 10 frames; keyframes 1 m apart
    short, long_, mid = adapt_to_drive(drive(6, 1.0), o), adapt_to_drive(drive(80, 1.0), o), adapt_to_drive(drive(30, 1.0), o)
    assert (short.skip_keyframes, short.spacing_m, short.drive_length_m) == (0, 1.0, 5.0)  # never below keyframes
    assert (long_.skip_keyframes, long_.spacing_m) == (5, 5.0)  # a long drive: the configured values
    assert mid.skip_keyframes == 5 and mid.spacing_m == pytest.approx(24.0 / 10)
    assert adapt_to_drive(drive(12, 1.0), o).skip_keyframes == 2  # skipping never costs a frame of the budget


@pytest.mark.slow
def test_one_process_and_thread_gives_the_bytes_of_two(drive, monkeypatch):
    """The same calibration to the bit as two threads and a forked child: small_gicp's per-point
    steps keep the thread count, its order-dependent reductions run on one thread (gicp.py); a
    forked child runs the same function on the same data (background.py)."""
    from clcgraph.targetless import background

    def run(threads):
        return calibrate_targetless_scans(drive.scans, mapping_topic=TOP, calibration_topics=[SIDE],
                                          T_base_sensor_guess=drive.T_base_lidar_guess, base_frame="base_link",
                                          config=_cfg().replace(targetless=dict(mapper_num_threads=threads)))

    assert background._can_fork()  # the default run below forks its children (Linux)
    two = run(2)
    monkeypatch.setattr(background, "_can_fork", lambda: False)
    one = run(1)
    assert np.array_equal(one.rt_lidar0_sensor, two.rt_lidar0_sensor)
    assert np.array_equal(one.covariance_block(SIDE), two.covariance_block(SIDE))
    assert np.array_equal(one.T_base_sensor[TOP], two.T_base_sensor[TOP])
