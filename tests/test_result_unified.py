"""One Result, one output path: a target-based and a targetless result go out through the same
writer and come back through load_result as the same type (issue 14, point 1)."""

from __future__ import annotations

import dataclasses
from html import escape as html_escape

import numpy as np
import pytest
import yaml

import clcgraph
from clcgraph import geometry as geo
from clcgraph.outputs.results import Calibration, load_result
from clcgraph.outputs.tables import summary_table
from clcgraph.types import Problem, Result, Sensor, TargetlessRun

from test_outputs import make_result

TOP, SIDE = "/top/points", "/side/points"
RT_SIDE = np.array([0.02, -0.01, 1.4, 0.6, 0.85, 0.1])
T_BASE_TOP = geo.T_from_xyz_rpy([0.1, 0.0, 1.8], [0.5, -0.3, 0.0])


def targetless_result(seed: int = 0) -> Result:
    """A hand-built targetless Result (two LIDARs, base_link from the ground) with the pictures'
    data the report draws."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(6, 6)) * 1e-3
    cov = A @ A.T + 1e-8 * np.eye(6)
    T_side = geo.T_from_rt(RT_SIDE)
    pts = rng.uniform(-5, 5, (300, 3))
    run = TargetlessRun(
        T_lidar0_sensor_guess={TOP: np.eye(4), SIDE: T_side @ geo.T_from_xyz_rpy([0.1, 0, 0], [1.0, 0, 0])},
        graph={SIDE: {"frames": 6, "keyframes": 5, "keyframe_edges": 4, "noise_scale": {"frames": 1.1, "keyframes": 0.9},
                      "redundancy": {"frames": 0.8}, "common_mode": 0.5}},
        convergence={SIDE: {"converged": True, "warnings": [], "stages": [{"stage": "final", "iterations": 3,
                                                                          "converged": True, "reason": "tolerance"}]}},
        per_frame={SIDE: [{"keyframe": k, "score_guess": 0.02, "score_final": 0.01} for k in range(6)]},
        frame_plan={"skip_keyframes": 0, "spacing_m": 1.0, "drive_length_m": 12.0},
        pictures={"map": {"map_points": pts, "trajectory": np.c_[np.arange(20.0), np.zeros((20, 2))],
                          "keyframes": np.arange(0, 20, 4)},
                  "alignment": {SIDE: {"target": pts, "source_guess": pts + 0.1, "source_final": pts + 0.01,
                                       "box_m": 10.0, "frames": 6, "distances_guess": rng.uniform(0, 0.3, 500),
                                       "distances_final": rng.uniform(0, 0.03, 500), "max_corr_m": 0.5}}},
    )
    problem = Problem(sensors=(Sensor(TOP, "lidar"), Sensor(SIDE, "lidar")), board=None, lidar_observations=(),
                      camera_observations=(), snapshot_stamps_ns=np.zeros(0, np.int64))
    return Result(problem=problem, rt_lidar0_sensor=np.array([np.zeros(6), RT_SIDE]), covariance_rt=cov,
                  rt_lidar0_board=np.zeros((0, 6)), noise={}, rms={}, rejected=(), method="targetless",
                  frames={TOP: "top_lidar", SIDE: "side_lidar"}, base_frame="base_link",
                  T_base_sensor={TOP: T_BASE_TOP, SIDE: T_BASE_TOP @ T_side},
                  stats={"stage_time_s": {"mapping": 1.5}, "peak_rss_mb": {"mapping": 100.0}}, targetless=run)


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("unified")
    target, targetless = make_result(), targetless_result()
    clcgraph.write_outputs(target, d / "target")
    clcgraph.write_outputs(targetless, d / "targetless")
    return d, target, targetless


def test_load_result_gives_the_same_type_for_both_methods(outputs):
    d, target, targetless = outputs
    a, b = load_result(d / "target"), load_result(d / "targetless")
    assert type(a) is type(b) is Calibration
    assert (a.method, b.method) == ("target", "targetless")
    assert a.reference == "/lidar/front/points" and b.reference == TOP and b.topics == [TOP, SIDE]
    np.testing.assert_allclose(b.T_lidar0_sensor(SIDE), geo.T_from_rt(RT_SIDE), atol=1e-12)
    np.testing.assert_allclose(b.covariance_rt, targetless.covariance_rt, rtol=1e-12)
    np.testing.assert_allclose(a.covariance_rt, target.covariance_rt, rtol=1e-12)
    np.testing.assert_allclose(b.base_link[SIDE], T_BASE_TOP @ geo.T_from_rt(RT_SIDE), atol=1e-12)
    assert a.base_link == {}
    # the common part of the schema is the same; each method adds its own sections
    ya, yb = (yaml.safe_load((d / m / "calibration.yaml").read_text()) for m in ("target", "targetless"))
    common = ["clcgraph_version", "method", "reference", "sensors", "covariance_rt_lidar0_sensor", "coordinates"]
    assert list(ya)[:6] == list(yb)[:6] == common
    assert {"rms", "noise", "snapshots", "sectors", "board"} <= set(ya) and not {"rms", "board"} & set(yb)
    assert {"graph", "calibration_frames", "convergence", "base_link", "frames"} <= set(yb)
    assert [list(s) for s in ya["sensors"]][1][:7] == [list(s) for s in yb["sensors"]][1][:7]
    # both wrote the same kinds of files: timings out of calibration.yaml, cameramodels, report
    for m in ("target", "targetless"):
        assert "timings_s" in yaml.safe_load((d / m / "timings.yaml").read_text())
        assert (d / m / "report.html").stat().st_size > 500 and (d / m / "sensor1-mounted.cameramodel").exists()
    assert (d / "target" / "problem.npz").exists() and not (d / "targetless" / "problem.npz").exists()
    html = (d / "targetless" / "report.html").read_text()
    for png in ("map_top.png", "scores_side_points.png", "aligned_side_points.png", "distances_side_points.png"):
        assert f"alt='{png}'" in html and not (d / "targetless" / png).exists()  # embedded, not beside it
    assert html.count("data:image/png;base64,") == 4


def test_an_older_file_without_method_loads_as_target_based(outputs, tmp_path):
    d, _, _ = outputs
    y = yaml.safe_load((d / "target" / "calibration.yaml").read_text())
    del y["method"]
    (tmp_path / "calibration.yaml").write_text(yaml.safe_dump(y))
    assert load_result(tmp_path).method == "target"
    y["method"] = "chessboard"
    (tmp_path / "calibration.yaml").write_text(yaml.safe_dump(y))
    with pytest.raises(clcgraph.errors.DataError, match="method 'chessboard'"):
        load_result(tmp_path)


def test_targetless_ros_files_are_under_the_ground_planes_base_link(outputs):
    d, _, _ = outputs
    ros = yaml.safe_load((d / "targetless" / "ros" / "ros-transforms.yaml").read_text())["transforms"]
    assert set(ros) == {"top_lidar", "side_lidar"} and {e["parent_frame"] for e in ros.values()} == {"base_link"}
    T = T_BASE_TOP @ geo.T_from_rt(RT_SIDE)
    np.testing.assert_allclose([ros["side_lidar"]["translation"][k] for k in "xyz"], T[:3, 3], atol=1e-12)
    assert not (d / "target" / "ros").exists()  # a target-based result has no frames: format-for-ros does it


def test_one_summary_table(outputs):
    _, target, targetless = outputs
    a, b = summary_table(target).splitlines(), summary_table(targetless).splitlines()
    assert a[0].split()[:3] == b[0].split()[:3] == ["sensor", "kind", "x,"]
    assert geo.RPY_LABEL in a[0] and geo.RPY_LABEL in b[0]  # one rotation format for both methods
    assert "1-sigma about own x, y, z [deg]" in a[0] and "1-sigma about own x, y, z [deg]" in b[0]
    side = next(ln for ln in b if ln.startswith(SIDE)).split()
    np.testing.assert_allclose([float(v) for v in side[2:5]], RT_SIDE[3:], atol=1e-4)
    assert side[-1] == "6"  # calibration frames
    base = next(ln for ln in b if ln.startswith(f"base_link <- {SIDE}")).split()
    np.testing.assert_allclose([float(v) for v in base[4:7]], (T_BASE_TOP @ geo.T_from_rt(RT_SIDE))[:3, 3], atol=1e-4)
    assert any(ln.startswith("RMS: normalized 1.010") for ln in a)


def test_rpy_helpers_are_one_convention():
    rng = np.random.default_rng(3)
    for _ in range(5):
        rpy = rng.uniform(-1.2, 1.2, 3)
        R = geo.R_from_rpy(rpy)
        c, s = np.cos(rpy), np.sin(rpy)
        Rx = np.array([[1, 0, 0], [0, c[0], -s[0]], [0, s[0], c[0]]])
        Ry = np.array([[c[1], 0, s[1]], [0, 1, 0], [-s[1], 0, c[1]]])
        Rz = np.array([[c[2], -s[2], 0], [s[2], c[2], 0], [0, 0, 1]])
        np.testing.assert_allclose(R, Rz @ Ry @ Rx, atol=1e-12)  # fixed axes x, then y, then z
        np.testing.assert_allclose(geo.rpy_from_R(R), rpy, atol=1e-12)
        T = geo.T_from_xyz_rpy([1, 2, 3], np.degrees(rpy))
        np.testing.assert_allclose(geo.invert_T(T) @ T, np.eye(4), atol=1e-12)
        xi = rng.normal(size=6) * 0.3
        np.testing.assert_allclose(geo.xi_log(geo.T_exp(xi)), xi, atol=1e-12)


def test_compare_reads_a_result_of_either_method_like_its_files(outputs):
    """comparison.poses_of takes the Result itself, its Calibration or its output directory and
    gets the same poses and covariances from each; a calibration compared with its own files has
    not moved (chi-square ~ 0)."""
    from clcgraph.comparison import compare, poses_of

    d, target, targetless = outputs
    for res, out in ((target, d / "target"), (targetless, d / "targetless")):
        a, b, c = poses_of(res), poses_of(load_result(out)), poses_of(out)
        assert a.reference == b.reference == c.reference == res.problem.sensors[res.problem.reference].topic
        assert list(a.poses) == list(b.poses) == list(c.poses) == [s.topic for s in res.problem.sensors]
        assert a.has_covariance and b.has_covariance
        for topic, (T, C) in a.poses.items():
            for other in (b, c):
                np.testing.assert_allclose(other.poses[topic][0], T, atol=1e-9)
                if C is None:
                    assert topic == a.reference and other.poses[topic][1] is None
                else:
                    np.testing.assert_allclose(other.poses[topic][1], C, rtol=1e-9, atol=1e-18)
        same = compare(res, out)
        assert not same.changed and same.reference == a.reference
        assert all(s.chi2 < 1e-6 for s in same.sensors if s.status != "reference"), same.sensors


def _report_of(result, out) -> str:
    clcgraph.write_outputs(result, out)
    return (out / "report.html").read_text()


def test_targetless_report_has_the_verdicts_and_the_record(outputs, tmp_path):
    """The targetless report: the target-based report's banner (its checks from what the Result carries),
    pose table (roll, pitch, yaw) and record of the run (the call, the settings, the version), written
    by write_outputs without report_inputs; and the verdicts turn red on a calibration worse than its guess."""
    from clcgraph.geometry import RPY_LABEL, rpy_deg_from_rt

    d, _, good = outputs
    text = (d / "targetless" / "report.html").read_text()
    top = text.index("<h2>Poses</h2>")
    for verdict in (f"Registration scores of {SIDE}: <b>better than the guess</b>: 6 of 6 calibration frames",
                    f"Distances to the map of {SIDE}: <b>closer</b>",
                    f"base_link &lt;- {TOP} from the ground plane: <b>roll +0.50 deg, pitch -0.30 deg, z +1.800 m</b>"):
        assert text.index(verdict) < top, verdict
    assert "class='verdict warn'" not in text and "class='verdict ok'" in text
    assert f"<th>{html_escape(RPY_LABEL)}</th>" in text
    assert " ".join(f"{v:+.3f}" for v in rpy_deg_from_rt(RT_SIDE)) in text
    record = text[text.index("<h2>Inputs and settings</h2>"):]
    assert f"clcgraph {clcgraph.__version__}" in record and "clcgraph.write_outputs(result, " in record
    assert "targetless:" in record and "registration_common_mode" in record  # the effective settings
    # a result that fits the map worse than the /tf_static guess, farther from it
    run = good.targetless
    pf = {SIDE: [{**r, "score_guess": r["score_final"], "score_final": r["score_guess"]} for r in run.per_frame[SIDE]]}
    al = dict(run.pictures["alignment"][SIDE])
    al["distances_guess"], al["distances_final"] = al["distances_final"], al["distances_guess"]
    bad = dataclasses.replace(good, targetless=dataclasses.replace(
        run, per_frame=pf, pictures={**run.pictures, "alignment": {SIDE: al}},
        convergence={SIDE: {"converged": False, "warnings": ["final: 100 iterations"], "stages": []}}))
    text = _report_of(bad, tmp_path / "bad")
    top = text.index("<h2>Poses</h2>")
    for verdict in (f"Registration scores of {SIDE}: <b>NOT BETTER than the guess</b>: 0 of 6",
                    f"Distances to the map of {SIDE}: <b>FARTHER</b>", f"Graph of {SIDE}: <b>NOT CONVERGED</b>"):
        assert text.index(verdict) < top, verdict
        assert text.rindex("class='verdict warn'", 0, text.index(verdict)) > text.rfind("</div>", 0, text.index(verdict))
