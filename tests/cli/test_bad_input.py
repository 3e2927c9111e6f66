"""The bad-input contract of `clcgraph solve` and friends: one line on stderr naming the
file/topic/sensor, exit code 2, no traceback, and no output directory left behind."""

from pathlib import Path

import numpy as np
import pytest

from clcgraph.cli import main
from clcgraph.geometry import T_from_rt
from clcgraph.sim.bag_writer import BagWriter
from clcgraph.types import Image, LidarScan

T0 = 1_700_000_000_000_000_000


def _scan(rng, stamp_ns, topic, *, all_invalid=False):
    elev = np.linspace(-0.25, 0.25, 16)[:, None]
    az = np.linspace(-np.pi, np.pi, 360, endpoint=False)[None, :]
    r = rng.uniform(3, 15, (16, 360))
    pts = np.stack([r * np.cos(elev) * np.cos(az), r * np.cos(elev) * np.sin(az),
                    r * np.sin(elev) * np.ones_like(az)], -1).reshape(-1, 3)
    valid = np.zeros(len(pts), bool) if all_invalid else np.ones(len(pts), bool)
    return LidarScan(topic, stamp_ns, pts, valid, ring=np.repeat(np.arange(16), 360),
                     time_s=np.tile(np.linspace(0, 0.099, 360), 16), shape=(16, 360))


def _bag(path, *, lidars=("/lidar0", "/lidar1"), camera="/cam0", all_invalid=False, encoding="mono8"):
    rng = np.random.default_rng(0)
    with BagWriter(path, format="ros1") as w:
        w.write_tf_static([("base_link", "lidar0", np.eye(4)),
                           ("base_link", "lidar1", T_from_rt(np.array([0, 0, 0.1, 0.5, 0, 0])))], stamp_ns=T0)
        for k, t in enumerate(lidars):
            w.write_pointcloud(t, _scan(rng, T0 + k, t, all_invalid=all_invalid and k == 1),
                               frame_id=t.strip("/"), layout="velodyne")
        if camera:
            px = rng.integers(0, 255, (48, 64), dtype=np.uint8)
            if encoding == "mono8":
                w.write_image(camera, Image(camera, T0 + 5, px, "mono8"), frame_id="cam0")
            else:  # an encoding clcgraph cannot decode, written the way a driver would
                T = w.typestore.types
                msg = T["sensor_msgs/msg/Image"](header=w._header(camera, T0 + 5, "cam0"), height=48, width=64,
                                                 encoding=encoding, is_bigendian=0, step=64,
                                                 data=px.reshape(-1))
                w._write(camera, "sensor_msgs/msg/Image", msg, T0 + 5)
    return path


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    return _bag(tmp_path_factory.mktemp("bags") / "good.bag")


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    import mrcal

    p = tmp_path_factory.mktemp("models") / "cam0.cameramodel"
    mrcal.cameramodel(intrinsics=("LENSMODEL_PINHOLE", np.array([50.0, 50.0, 31.5, 23.5])),
                      imagersize=np.array([64, 48])).write(str(p))
    return p


def _run(capsys, argv, *names, code=2):
    rc = main(argv)
    err = capsys.readouterr().err
    lines = [l for l in err.splitlines() if l.strip()]
    assert rc == code, err
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for n in names:
        assert str(n) in lines[0], (n, lines[0])
    return lines[0]


def _solve(bag, out, *extra, topics="/lidar0,/lidar1,/cam0", models=()):
    return ["solve", "--bag", str(bag), "--topics", topics, "--out", str(out), *map(str, models), *map(str, extra)]


def test_missing_bag(capsys, tmp_path, model):
    out = tmp_path / "out"
    _run(capsys, _solve(tmp_path / "nope*.bag", out, models=[model]), "nope*.bag")
    assert not out.exists()


def test_unreadable_bag(capsys, tmp_path, model):
    bad = tmp_path / "garbage.bag"
    bad.write_bytes(b"this is not a bag" * 10)
    out = tmp_path / "out"
    _run(capsys, _solve(bad, out, models=[model]), "garbage.bag")
    assert not out.exists()


def test_truncated_bag(capsys, tmp_path, good, model):
    cut = tmp_path / "cut.bag"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    out = tmp_path / "out"
    _run(capsys, _solve(cut, out, models=[model]), "cut.bag")
    assert not out.exists()


def test_empty_bag(capsys, tmp_path, model):
    empty = tmp_path / "empty.bag"
    with BagWriter(empty, format="ros1"):
        pass
    out = tmp_path / "out"
    _run(capsys, _solve(empty, out, models=[model]), "empty.bag")
    assert not out.exists()


def test_topic_absent(capsys, tmp_path, good, model):
    out = tmp_path / "out"
    _run(capsys, _solve(good, out, topics="/lidar0,/lidar9,/cam0", models=[model]), "/lidar9")
    assert not out.exists()


def test_wrong_message_type(capsys, tmp_path, good, model):
    out = tmp_path / "out"
    _run(capsys, _solve(good, out, topics="/lidar0,/tf_static,/cam0", models=[model]), "/tf_static", "TFMessage")
    assert not out.exists()


def test_all_points_invalid(capsys, tmp_path, model):
    b = _bag(tmp_path / "nan.bag", all_invalid=True)
    out = tmp_path / "out"
    _run(capsys, _solve(b, out, models=[model]), "/lidar1", "invalid")
    assert not out.exists()


def test_unknown_image_encoding(capsys, tmp_path, model):
    b = _bag(tmp_path / "yuv.bag", encoding="yuv422_weird")
    out = tmp_path / "out"
    _run(capsys, _solve(b, out, models=[model]), "yuv.bag", "/cam0", "yuv422_weird")
    assert not out.exists()


def test_model_count(capsys, tmp_path, good, model):
    out = tmp_path / "out"
    _run(capsys, _solve(good, out, models=[model, model]), "2 camera model", "/cam0")
    _run(capsys, _solve(good, out, models=[]), "0 camera model", "/cam0")
    assert not out.exists()


def test_unreadable_cameramodel(capsys, tmp_path, good):
    bad = tmp_path / "bad.cameramodel"
    bad.write_text("{ this is not a model")
    out = tmp_path / "out"
    _run(capsys, _solve(good, out, models=[bad]), "bad.cameramodel")
    _run(capsys, _solve(good, out, models=[tmp_path / "missing.cameramodel"]), "missing.cameramodel", "/cam0")
    assert not out.exists()


def test_unknown_config_key(capsys, tmp_path, good, model):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("solve:\n  outlier_sigmaa: 3\n")
    out = tmp_path / "out"
    _run(capsys, _solve(good, out, "--config", cfg, models=[model]), "c.yaml", "solve.outlier_sigmaa")
    _run(capsys, _solve(good, out, "--set", "segmentation.nope=1", models=[model]), "segmentation.nope")
    _run(capsys, ["config", "check", "--config", str(cfg)], "solve.outlier_sigmaa")
    assert not out.exists()


def test_unwritable_output(capsys, tmp_path, good, model):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    _run(capsys, _solve(good, blocker / "out", models=[model]), str(blocker / "out"))
    _run(capsys, _solve(good, blocker, models=[model]), str(blocker))
    assert blocker.read_text() == "x"


def test_internal_error_exit_1_and_verbose_traceback(capsys, caplog, monkeypatch, tmp_path, good, model):
    import clcgraph.api

    def boom(*a, **k):
        raise RuntimeError("kaboom")

    monkeypatch.setattr(clcgraph.api, "read_problem", boom)
    line = _run(capsys, _solve(good, tmp_path / "out", models=[model]), "kaboom", code=1)
    assert "--verbose" in line
    rc = main(["--verbose", *_solve(good, tmp_path / "out", models=[model])])
    assert rc == 1 and "kaboom" in capsys.readouterr().err
    assert "Traceback" in caplog.text  # logged with the stack only under --verbose
