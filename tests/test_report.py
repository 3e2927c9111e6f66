"""report.html and its plots."""

from __future__ import annotations

import html
import re

import matplotlib.image as mpimg
import numpy as np
import pytest

from clcgraph.outputs import plots
from clcgraph.outputs.report import HOWTO, write_report
from clcgraph.outputs.results import write_results
from test_outputs import CAMERA_RT, LIDAR1_RT, make_result


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    result = make_result()
    out = tmp_path_factory.mktemp("rep")
    return result, out, write_report(result, out, title="test rig")


def test_report_references_existing_pngs(report):
    result, out, path = report
    text = path.read_text()
    srcs = re.findall(r"<img src='([^']+)'", text)
    assert sorted(srcs) == sorted(HOWTO)  # every plot, each once
    for s in srcs:
        img = mpimg.imread(out / s)
        assert img.shape[0] > 200 and img.shape[1] > 300
        assert np.std(img[..., :3]) > 0.05  # not blank
    # every plot has its how-to-read paragraph right before it
    for name in HOWTO:
        assert text.index(html.escape(HOWTO[name][:40])) < text.index(f"<img src='{name}'")


def test_report_tables(report):
    result, out, path = report
    text = path.read_text()
    assert "test rig" in text
    for s in result.problem.sensors:
        assert s.topic in text
    # lidar1's position and its stdev in mm appear in the pose table
    assert " ".join(f"{x:+.4f}" for x in LIDAR1_RT[3:]) in text
    assert " ".join(f"{x:.2f}" for x in result.stdev_rt(1)[3:] * 1e3) in text
    assert " ".join(f"{x:+.4f}" for x in CAMERA_RT[3:]) in text
    assert "board not found" in text and "residual 8.1 sigma" in text
    assert "<td>0.012</td>" in text and "<td>0.4</td>" in text
    assert "Snapshots used: 7 of 8" in text


def test_report_inside_atomic_write(tmp_path):
    result = make_result()
    out = tmp_path / "out"
    write_results(result, out, extra_files={"report.html": lambda p: write_report(result, p.parent)})
    assert (out / "report.html").is_file() and (out / "sectors.png").is_file()
    assert (out / "calibration.yaml").is_file()


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
