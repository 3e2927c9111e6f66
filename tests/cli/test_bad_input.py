"""The bad-input contract of `clcgraph solve` and friends: one line on stderr naming the
file/topic/sensor, exit code 2, no traceback, and no output directory left behind."""

from clcgraph.cli import main
from clcgraph.sim.bag_writer import BagWriter


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


def test_all_points_invalid(capsys, tmp_path, model, bag_factory):
    b = bag_factory(tmp_path / "nan.bag", all_invalid=True)
    out = tmp_path / "out"
    _run(capsys, _solve(b, out, models=[model]), "/lidar1", "invalid")
    assert not out.exists()


def test_unknown_image_encoding(capsys, tmp_path, model, bag_factory):
    b = bag_factory(tmp_path / "yuv.bag", encoding="yuv422_weird")
    out = tmp_path / "out"
    _run(capsys, _solve(b, out, models=[model]), "yuv.bag", "/cam0", "yuv422_weird")
    assert not out.exists()


def test_model_count(capsys, tmp_path, good, model):
    out = tmp_path / "out"
    _run(capsys, _solve(good, out, models=[model, model]), "2 camera model", "/cam0")
    # none given: the camera's CameraInfo in the bags, which these bags lack
    _run(capsys, _solve(good, out, models=[]), "no camera model file given for /cam0", "/camera_info")
    assert not out.exists()


def test_images_of_another_size_than_their_camera_info(capsys, tmp_path, model, bag_factory):
    """camera_info given for the camera: its CameraInfo is the model, and images of another size
    are refused naming the CameraInfo topic (with the other cameras' models given as files)."""
    b = bag_factory(tmp_path / "info.bag", camera_info_size=(640, 480))
    out = tmp_path / "out"
    _run(capsys, _solve(b, out, models=["camera_info"]), "/cam0", "64x48", "CameraInfo", "topic /camera_info", "640x480")
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


def test_set_on_targetless_and_detect(capsys, tmp_path, good):
    """--set is parsed the same way by every command with a config, before any bag is read."""
    tl = ["targetless", "--bag", str(good), "--mapping-topic", "/lidar0", "--calibration-topics", "/lidar1",
          "--out", str(tmp_path / "tl")]
    _run(capsys, tl + ["--set", "targetless.nope=1"], "targetless.nope")
    _run(capsys, tl + ["--set", "targetless.calibration_min_distance_between_frames=far"],
         "targetless.calibration_min_distance_between_frames", "number")
    _run(capsys, tl + ["--set", "targetless"], "--set", "SECTION.KEY=VALUE")
    assert not (tmp_path / "tl").exists()
    det = ["detect", str(good), "--topic", "/cam0"]
    _run(capsys, det + ["--set", "detection.corners_z=3"], "detection.corners_z")
    _run(capsys, det + ["--set", "detection.detector=bogus"], "'detection.detector' must be one of auto, mrgingham, opencv")
    assert main(det + ["--set", "detection.detector=opencv"]) == 0
    assert "0/1 images with a chessboard" in capsys.readouterr().out


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



def test_unquoted_bag_glob(capsys, tmp_path, good, model):
    """`--bag capture/*.bag cam.cameramodel`, the glob expanded by the shell: the bags are bags and
    the models models (here one model too many, so it stops at the count, before any solve); a bag
    where the models go is a one-line hint, not "unrecognized arguments"."""
    from clcgraph.api import bags_and_models
    from clcgraph.cli import build_parser

    out = tmp_path / "out"
    args = build_parser().parse_args(["solve", "--bag", "a.bag", "b.bag", "m.cameramodel", "--topics", "/l,/c",
                                      "--out", str(out), "n.cameramodel"])
    assert bags_and_models(args.bag, args.models) == (["a.bag", "b.bag"], ["m.cameramodel", "n.cameramodel"])
    _run(capsys, ["solve", "--bag", str(good), str(good), str(model), str(model), "--topics", "/lidar0,/lidar1,/cam0",
                  "--out", str(out)], "2 camera model", "/cam0")
    line = _run(capsys, ["solve", "--bag", str(good), "--topics", "/lidar0,/lidar1,/cam0", "--out", str(out),
                         str(model), str(good)], str(good))
    assert "put every bag after --bag" in line and "quote the glob" in line
    assert not out.exists()
