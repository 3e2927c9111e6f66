"""report.html and its plots."""

from __future__ import annotations

import base64
import html
import io
import re
import shutil
import time

import matplotlib.image as mpimg
import numpy as np
import pytest

import clcgraph
from clcgraph.outputs import evidence as ev
from clcgraph.outputs import plots
from clcgraph.outputs.report import HOWTO, write_report
from clcgraph.outputs.results import write_results
from test_outputs import CAMERA_RT, LIDAR1_RT, make_result


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    result = make_result()
    out = tmp_path_factory.mktemp("rep")
    return result, out, write_report(result, out, title="test rig")


def _embedded_pngs(text: str) -> dict:
    """{alt name: decoded image} of every <img> in the report (all must be PNG or JPEG data URIs)."""
    imgs = re.findall(r"<img src='([^']+)' alt='([^']+)'", text)
    out = {}
    for src, alt in imgs:
        fmt = re.match(r"data:image/(png|jpeg);base64,", src)
        assert fmt, src[:60]
        img = mpimg.imread(io.BytesIO(base64.b64decode(src.split(",", 1)[1])), format=fmt.group(1))
        out[alt] = img / 255.0 if img.dtype == np.uint8 else img
    return out


def test_report_is_one_self_contained_file(report, tmp_path):
    result, out, path = report
    assert sorted(p.name for p in out.iterdir()) == ["report.html"]  # no PNG beside it
    alone = tmp_path / "mailed" / "report.html"
    alone.parent.mkdir()
    shutil.copy(path, alone)
    text = alone.read_text()
    # nothing the page would fetch: every src / href / url() / @import is a data URI or an anchor
    refs = re.findall(r"""(?:src|href)\s*=\s*['"]?([^'" >]+)""", text) + re.findall(r"url\(([^)]*)\)", text)
    assert refs and all(r.startswith(("data:", "#")) for r in refs), [r[:40] for r in refs if not r.startswith("data:")]
    assert "@import" not in text and "<link" not in text and "<script" not in text
    imgs = _embedded_pngs(text)
    assert len(imgs) == len(re.findall("<img ", text))
    for name, img in imgs.items():
        assert img.shape[0] > 200 and img.shape[1] > 300, name
        assert np.std(img[..., :3]) > 0.05, name  # not blank


def test_report_figures_each_after_their_howto(report):
    result, out, path = report
    text = path.read_text()
    imgs = _embedded_pngs(text)
    # the Result-only report: every figure but the clouds needing scans of two LIDARs' overlap is drawn
    want = {"lidar-on-camera-2.jpg", "clouds-before-after.png", "camera-residuals-and-coverage.png", *plots.PLOTS}
    assert want <= set(imgs), sorted(want - set(imgs))
    for name in imgs:
        key = "lidar-on-camera" if name.startswith("lidar-on-camera") else name
        assert text.index(html.escape(HOWTO[key][:40])) < text.index(f"alt='{name}'")
    assert "board points only (the report has no image of it)" in text


def test_report_verdicts_at_the_top(report):
    result, out, path = report
    text = path.read_text()
    top = text.index("<h2>Poses</h2>")
    assert text.index("Self-consistency: <b>not checked</b>") < top
    assert text.index("LIDAR board points on the cameras' boards: <b>on the board</b>") < top
    # make_result's camera sees corners in one band only: warned about, with the rule
    assert text.index("Image coverage of 2: /cam/image: <b>too little</b>") < top
    assert "no corner in the top third" in text


def test_report_records_inputs_and_nominal(tmp_path, caplog):
    from clcgraph.geometry import compose_rt

    result = make_result()
    nominal = compose_rt(LIDAR1_RT, np.r_[0, 0, np.radians(1.0), 0.02, 0, 0])  # 1 deg, 20 mm off
    inputs = ev.ReportInputs(bags=(("/data/a.bag", 12_300_000), ("/data/b.bag", 4_500_000)),
                             models=(("/cam/image", "/models/cam.cameramodel"),),
                             command="clcgraph solve --bag '/data/*.bag' --topics x,y,z", config_yaml="solve:\n  x: 1\n",
                             rt_nominal={1: nominal}, nominal_source="/tf_static of a.bag ...")
    with caplog.at_level("WARNING"):
        text = write_report(result, tmp_path, inputs=inputs).read_text()
    assert "/data/a.bag" in text and "<td>12.3</td>" in text and "2 bag(s), 16.8 MB" in text
    assert "/models/cam.cameramodel" in text and "LENSMODEL_OPENCV4" in text and "1280x800" in text
    assert "clcgraph solve --bag &#x27;/data/*.bag&#x27;" in text and "solve:\n  x: 1" in text
    assert f"clcgraph {clcgraph.__version__}" in text
    row = re.search(r"<td>1</td><td>/lidar/rear/points</td><td>([0-9.]+)</td><td>[0-9.]+</td><td>([0-9.]+)</td>", text)
    assert float(row.group(1)) == pytest.approx(1.0, abs=1e-3) and float(row.group(2)) == pytest.approx(20.0, abs=0.05)
    assert text.index("Moved from the nominal pose (/tf_static of a.bag ...): <b>up to 1.00 deg</b>") < text.index("<h2>Poses</h2>")
    assert any("corners only in rows" in r.message for r in caplog.records)  # the coverage warning is logged too


def test_per_observation_rms_matches_numpy():
    result = make_result()
    obs = plots.per_observation_rms(result)
    r = result.residuals
    m = (r["lidar_sensor"] == 1) & (r["lidar_snapshot"] == 4)
    want = np.sqrt(np.mean(r["lidar_m"][m] ** 2))
    got = [o["rms"] for o in obs if o["kind"] == "lidar" and o["sensor"] == 1 and o["snapshot"] == 4]
    assert got == [pytest.approx(want, rel=1e-12)]
    assert len([o for o in obs if o["kind"] == "camera"]) == 7


def test_outliers_left_out_of_rms(tmp_path):
    import dataclasses

    r0 = make_result()
    res = dict(r0.residuals)
    x = res["lidar_m"].copy()
    m = (res["lidar_sensor"] == 0) & (res["lidar_snapshot"] == 2)
    k = np.flatnonzero(m)[:3]
    x[k] = 5.0  # three gross outliers
    res["lidar_m"] = x
    res["lidar_outlier"] = np.zeros(x.shape, bool)
    res["lidar_outlier"][k] = True
    r = dataclasses.replace(r0, residuals=res)
    o = [o for o in plots.per_observation_rms(r) if o["kind"] == "lidar" and o["sensor"] == 0 and o["snapshot"] == 2][0]
    assert o["n_outliers"] == 3
    inl = m.copy()
    inl[k] = False
    assert o["rms"] == pytest.approx(np.sqrt(np.mean(x[inl] ** 2)), rel=1e-12) and o["rms"] < 0.02
    assert set(plots.plot_all(r, tmp_path)) == set(plots.PLOTS)


def test_plots_without_optional_data(tmp_path):
    # no residuals, no sectors: plots still render (saying what is missing)
    import dataclasses

    result = dataclasses.replace(make_result(), residuals={}, sectors=None)
    written = plots.plot_all(result, tmp_path)
    assert sorted(written) == sorted(plots.PLOTS)


def test_uncertainty_grid_plot(tmp_path):
    xs = np.linspace(-20, 20, 25)
    ys = np.linspace(-20, 20, 25)
    X, Y = np.meshgrid(xs, ys)
    stdev = 0.002 + 0.0005 * np.hypot(X, Y)
    p = plots.plot_uncertainty_grid(stdev, xs, ys, tmp_path / "u.png", title="lidar0 -> lidar1",
                                    sensor_xy={"lidar0": (0, 0), "lidar1": (-0.5, 0.8)})
    img = mpimg.imread(p)
    assert img.shape[0] > 300


def test_render_aligned_clouds(tmp_path):
    rng = np.random.default_rng(1)
    # a wall x = 5 in lidar0, seen by lidar1 in its own frame
    wall = np.c_[np.full(3000, 5.0), rng.uniform(-3, 3, 3000), rng.uniform(-1, 2, 3000)]
    from clcgraph.geometry import invert_rt, transform

    clouds = {"/lidar/front/points": wall, "/lidar/rear/points": transform(invert_rt(LIDAR1_RT), wall)}
    rts = {"/lidar/front/points": np.zeros(6), "/lidar/rear/points": LIDAR1_RT}
    moved = plots.align_clouds(clouds, rts)
    np.testing.assert_allclose(moved["/lidar/rear/points"], wall, atol=1e-12)
    sub = plots.align_clouds({"/lidar/rear/points": np.vstack([clouds["/lidar/rear/points"], [[np.nan, 0, 0]]])},
                             rts, max_points=500)
    assert sub["/lidar/rear/points"].shape == (500, 3)
    np.testing.assert_allclose(sub["/lidar/rear/points"][:, 0], 5.0, atol=1e-12)  # all on the wall, NaN dropped
    p = plots.render_aligned_clouds(clouds, {"/lidar/front/points": np.zeros(6), "/lidar/rear/points": LIDAR1_RT},
                                    tmp_path / "aligned.png")
    assert mpimg.imread(p).shape[1] > 600
    with pytest.raises(ValueError, match="unknown view"):
        plots.render_aligned_clouds(clouds, {}, tmp_path / "x.png", views=("diagonal",))


def test_poses_table_in_roll_pitch_yaw(report):
    """The report's poses as the CLI's table and the README write them: roll, pitch, yaw [deg] about
    lidar0's fixed x-y-z axes (never the Rodrigues vector in degrees), per-axis sigmas labelled."""
    from clcgraph.geometry import RPY_LABEL, pose_stdevs, rpy_deg_from_rt

    result, out, path = report
    text = path.read_text()
    table = text[text.index("<h2>Poses</h2>"):text.index("</table>", text.index("<h2>Poses</h2>"))]
    head = re.findall(r"<th>([^<]*)</th>", table)
    assert head[3:7] == ["x, y, z [m] in lidar0", html.escape(RPY_LABEL), "1-sigma position along lidar0 x, y, z [mm]",
                         "1-sigma orientation about the sensor's own x, y, z [deg]"]
    for i, s in enumerate(result.problem.sensors):
        cells = re.search(rf"<tr><td>{i}</td><td>{re.escape(s.topic)}[^<]*</td><td>{s.kind}</td>" + r"<td>([^<]*)</td>" * 4,
                          table).groups()
        rt = np.asarray(result.rt_lidar0_sensor[i], float)
        np.testing.assert_allclose(np.array(cells[0].split(), float), rt[3:], atol=1e-4)
        np.testing.assert_allclose(np.array(cells[1].split(), float), rpy_deg_from_rt(rt), atol=1e-3)
        if i != result.problem.reference:
            assert np.max(np.abs(rpy_deg_from_rt(rt) - np.degrees(rt[:3]))) > 0.01  # the two formats differ here
            sd_rot, sd_pos = pose_stdevs(rt, result.covariance_block(i))
            np.testing.assert_allclose(np.array(cells[2].split(), float), 1e3 * sd_pos, atol=0.006)
            np.testing.assert_allclose(np.array(cells[3].split(), float), np.degrees(sd_rot), atol=6e-4)


def test_the_pictures_of_the_estimate_are_the_results(tmp_path):
    # `clcgraph solve` draws most pictures from the solve's estimate while it computes the covariance
    # (report.start_estimate_figures): the report is the one the final result alone gives, byte for byte
    from clcgraph.api import calibrate, write_outputs
    from clcgraph.outputs.report import ESTIMATE_FIGURES, start_estimate_figures
    from clcgraph.sim.observations import make_rig, simulate_problem

    problem, _ = simulate_problem(rig=make_rig(n_lidars=2, n_cameras=1), n_snapshots=10, seed=1, planned_tilts=True)
    inputs, early = ev.ReportInputs(command="test"), []
    result = calibrate(problem, on_estimate=lambda e: early.append(start_estimate_figures(e, inputs)))
    assert len(early) == 1 and early[0].names == list(ESTIMATE_FIGURES)
    write_outputs(result, tmp_path / "a", report_inputs=inputs, figures=early[0])
    write_outputs(result, tmp_path / "b", report_inputs=inputs)
    a, b = ((tmp_path / d / "report.html").read_text() for d in "ab")
    assert a == b
    assert len(re.findall("<img ", a)) >= len(ESTIMATE_FIGURES) + 1  # theirs and the sectors'


def test_a_solve_failing_after_its_estimate_stops_the_drawing(tmp_path, monkeypatch):
    # calibrate_bags starts the pictures at the estimate; a solve refused after it leaves no drawing process
    import multiprocessing

    from clcgraph import api
    from clcgraph.backend import solve
    from clcgraph.errors import SolveError
    from clcgraph.outputs import report
    from clcgraph.sim.observations import make_rig, simulate_problem

    problem, _ = simulate_problem(rig=make_rig(n_lidars=2, n_cameras=1), n_snapshots=10, seed=1, planned_tilts=True)
    monkeypatch.setattr(api, "read_problem", lambda *a, **k: problem)
    drawings = []
    real = report.start_estimate_figures
    monkeypatch.setattr(report, "start_estimate_figures", lambda *a: drawings.append(real(*a)) or drawings[-1])

    def refused(*a, **k):
        time.sleep(0.3)  # the drawing process is busy
        raise SolveError("refused after the estimate")

    monkeypatch.setattr(solve, "_covariance", refused)
    (tmp_path / "a.bag").write_bytes(b"")
    with pytest.raises(SolveError, match="refused after the estimate"):
        api.calibrate_bags([str(tmp_path / "a.bag")], [s.topic for s in problem.sensors], out=tmp_path / "out")
    assert len(drawings) == 1 and drawings[0].child is None
    assert not multiprocessing.active_children() and not (tmp_path / "out").exists()


def test_the_drawing_process_is_forked_after_the_background_import_ended(tmp_path, monkeypatch):
    # a child forked while the import thread holds an import lock inherits it held: its imports hang
    import importlib
    import threading

    from clcgraph import api
    from clcgraph.outputs import report
    from clcgraph.sim.observations import make_rig, simulate_problem

    problem, _ = simulate_problem(rig=make_rig(n_lidars=2, n_cameras=1), n_snapshots=10, seed=1, planned_tilts=True)
    monkeypatch.setattr(api, "read_problem", lambda *a, **k: problem)
    real_import = importlib.import_module

    def slow_in_the_thread(name, *a):  # the import still running when the solve has its estimate
        if threading.current_thread().name == "clcgraph-import":
            time.sleep(3.0)
        return real_import(name, *a)

    monkeypatch.setattr(importlib, "import_module", slow_in_the_thread)
    importing_at_fork = []
    real = report.start_estimate_figures

    def start(*a):
        importing_at_fork.append(any(t.name == "clcgraph-import" and t.is_alive() for t in threading.enumerate()))
        return real(*a)

    monkeypatch.setattr(report, "start_estimate_figures", start)
    (tmp_path / "a.bag").write_bytes(b"")
    api.calibrate_bags([str(tmp_path / "a.bag")], [s.topic for s in problem.sensors], out=tmp_path / "out")
    assert importing_at_fork == [False] and (tmp_path / "out" / "report.html").exists()
