"""The `clcgraph` subcommands on real (written) bags: what they print and draw."""

from clcgraph.cli import main


def test_show_bag_previews(capsys, tmp_path, good):
    assert main(["show-bag", str(good), "--png", str(tmp_path / "png")]) == 0
    out = capsys.readouterr().out
    assert "/lidar0" in out and "PointCloud2 1 x 5760" in out
    names = sorted(p.name for p in (tmp_path / "png").iterdir())
    assert names == ["good_cam0.png", "good_lidar0.png", "good_lidar1.png"]
    import matplotlib.image

    assert matplotlib.image.imread(tmp_path / "png" / "good_lidar0.png").shape[1] > 600


def test_segment_and_spacing_on_a_non_cloud_topic_are_one_line_errors(capsys, good):
    for cmd in ("segment", "infer-lidar-spacing"):
        assert main([cmd, str(good), "--topic", "/cam0"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "good.bag" in err[0] and "/cam0" in err[0] and "PointCloud2" in err[0], err
    assert main(["detect", str(good), "--topic", "/lidar0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "good.bag" in err[0] and "/lidar0" in err[0] and "not images" in err[0], err


def test_segment_dump_and_spacing(capsys, tmp_path, good):
    import numpy as np

    assert main(["infer-lidar-spacing", str(good), "--topic", "/lidar0"]) == 0
    assert "/lidar0:" in capsys.readouterr().out
    assert main(["segment", str(good), "--topic", "/lidar0", "--dump", str(tmp_path / "d.npz"),
                 "--png", str(tmp_path / "png")]) == 0
    assert "scans with a board" in capsys.readouterr().out
    assert "scan0_segments" in np.load(tmp_path / "d.npz").files
    assert len(list((tmp_path / "png").iterdir())) == 1


def test_a_directory_of_bags(capsys, tmp_path, bag_factory):
    """A directory means the ROS1 .bag files (and ROS2 bag directories) in it, for every command
    that takes bags; a directory without bags is a one-line error naming it."""
    d = tmp_path / "capture"
    d.mkdir()
    for name in ("b.bag", "a.bag"):
        bag_factory(d / name)
    (d / "notes.txt").write_text("not a bag")
    assert main(["segment", str(d), "--topic", "/lidar0"]) == 0
    assert "/2 scans with a board" in capsys.readouterr().out
    assert main(["show-bag", str(d)]) == 0
    out = capsys.readouterr().out
    assert out.index("a.bag:") < out.index("b.bag:") and "notes.txt" not in out
    assert main(["detect", str(d), "--topic", "/cam0", "--set", "board.corners=[7,5]",
                 "--set", "board.square_m=0.095", "--set", "board.size_m=[0.85,0.61]"]) == 0
    assert "0/2 images with a chessboard" in capsys.readouterr().out
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["segment", str(empty), "--topic", "/lidar0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(empty) in err[0] and "no ROS1 .bag file" in err[0], err


def test_old_board_keys_are_one_line_errors(capsys, good):
    assert main(["segment", str(good), "--topic", "/lidar0", "--set", "detection.margin_m=0.1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'detection.margin_m' moved to the 'board' section" in err[0], err


def test_segment_every_scan_of_each_bag(capsys, tmp_path, bag_factory):
    """--every segments each scan of each bag alone and names the bag it came from."""
    d = tmp_path / "capture"
    d.mkdir()
    for name in ("b.bag", "a.bag"):
        bag_factory(d / name)
    assert main(["segment", str(d), "--topic", "/lidar0", "--every"]) == 0
    out = capsys.readouterr().out
    assert "/2 scans with a board" in out and "a.bag" in out and "b.bag" in out, out


def test_detect_every_image_and_outputs_that_are_not_folders_or_yaml(capsys, tmp_path, bag_factory):
    """detect --every reads every image of each bag; --png naming a user's file, --dump into a
    missing directory and a --set value that is not YAML are one-line errors, the file intact."""
    d = tmp_path / "capture"
    d.mkdir()
    for name in ("b.bag", "a.bag"):
        bag_factory(d / name)
    assert main(["detect", str(d), "--topic", "/cam0", "--every"]) == 0
    assert "a.bag" in capsys.readouterr().out
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    for args, words in ((["show-bag", str(d), "--png", str(notes)], "a file; name a directory"),
                        (["segment", str(d), "--topic", "/lidar0", "--png", str(notes)], "a file; name a directory"),
                        (["segment", str(d), "--topic", "/lidar0", "--dump", str(tmp_path / "no" / "d.npz")],
                         "does not exist"),
                        (["segment", str(d), "--topic", "/lidar0", "--set", "board.corners=[7,5"], "not YAML"),
                        (["segment", str(d / "a.bag"), "--topic", "/tf_static"],
                         "/tf_static has type tf2_msgs/msg/TFMessage: not a LIDAR (PointCloud2) or camera")):
        assert main(args) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], (args, err)
    assert notes.read_text() == "mine"


def test_a_directory_or_a_glob_of_bags_where_one_bag_is_wanted(tmp_path, bag_factory):
    import pytest

    from clcgraph.errors import InputError
    from clcgraph.frontend.bag import first_messages

    d = tmp_path / "capture"
    d.mkdir()
    bag_factory(d / "a.bag")
    with pytest.raises(InputError, match="a directory of ROS1 bags, not one bag; give one of its .bag files"):
        first_messages(d, ["/lidar0"])
    bag_factory(d / "b.bag")
    with pytest.raises(InputError, match=r"\*.bag: a pattern \(2 matches\), not one bag; give one bag file"):
        first_messages(d / "*.bag", ["/lidar0"])


def test_why_boards_were_missed_quotes_the_commonest_reason_with_its_numbers():
    from types import SimpleNamespace

    from clcgraph.api import _why_missed
    from clcgraph.types import Rejected

    sensors = [SimpleNamespace(topic="/l"), SimpleNamespace(topic="/c")]
    rejected = [Rejected(f"scan: plane {1.7 + k / 100:.2f} m across, larger than the board", "segmentation", 0, k)
                for k in range(3)] + [Rejected("scan: no plane", "segmentation", 0, 9)]
    assert _why_missed(sensors, [], [], rejected) == '/l: 0 found, 3 like "plane 1.70 m across, larger than the board"; '
    # a long reason is quoted to a clause's end
    long = [Rejected("scan: no board-like plane; plane at 8.7 m, 1.36 x 1.41 m (1.70 m across), 11% of it outside "
                     "any 1.10 x 1.10 m rectangle: a wall, car, person or the board touching something", "segmentation",
                     0, 1)]
    assert _why_missed(sensors, [], [], long) == ('/l: 0 found, 1 like "no board-like plane; plane at 8.7 m, 1.36 x '
                                                  '1.41 m (1.70 m across)..."; ')


def test_a_sensor_that_found_no_board_anywhere_names_the_board_setting_to_check():
    """A camera that found no board in any image (a pattern other than board.corners says) is
    named with its commonest reason and the setting, before the solve could only say it cannot
    be connected; a LIDAR likewise with board.size_m. One that found fewer boards than the seed
    needs likewise; one that found enough passes."""
    from types import SimpleNamespace

    import pytest

    from clcgraph.api import _check_every_sensor_found_a_board
    from clcgraph.errors import DegenerateError
    from clcgraph.types import BoardGeometry, CameraBoardObservation, Rejected

    board = BoardGeometry.from_spec(corners=[9, 7], square_m=0.1, size_m=[1.2, 1.0])
    sensors = [SimpleNamespace(topic="/l", is_camera=False), SimpleNamespace(topic="/c", is_camera=True)]
    rejected = [Rejected("no full 9x7 chessboard found", "detection", 1, k) for k in range(5)]
    with pytest.raises(DegenerateError, match=r'^/c: no board found in any of its 5 images \(5 like "no full 9x7 '
                                              r'chessboard found"\); is board.corners \[9, 7\] \(inner corners'):
        _check_every_sensor_found_a_board(sensors, [], [], rejected, board)
    seen = [CameraBoardObservation(sensor=1, snapshot=7, corners_px=None)]
    _check_every_sensor_found_a_board(sensors, [], seen, rejected, board)
    lidar = [Rejected("scan: plane 1.79 m across, larger than the board", "segmentation", 0, k) for k in range(3)]
    with pytest.raises(DegenerateError, match=r"^/l: no board found in any of its 3 scans .*board.size_m \[1.2, 1\]"):
        _check_every_sensor_found_a_board(sensors, [], seen, lidar + rejected, board)
    # fewer than the seed needs to connect it (a board described smaller than it is: most planes too large)
    one = [SimpleNamespace(sensor=0, snapshot=5)]
    _check_every_sensor_found_a_board(sensors, one, seen, lidar + rejected, board)
    with pytest.raises(DegenerateError, match=r'^/l: only 1 board found in its 4 scans \(3 like "plane 1.79 m across, '
                                              r'larger than the board"\); is board.size_m \[1.2, 1\]'):
        _check_every_sensor_found_a_board(sensors, one, [*seen] * 3, lidar + rejected, board, 3)
    # a camera with too few boards and one grid read past the pattern's edge: the few boards said, not the count
    past_one = [Rejected("no chessboard corner along the grid's top row: the pattern's edge read as corners (fewer "
                         "inner corners than the 9x7 of board.corners?)", "detection", 1, 6)]
    with pytest.raises(DegenerateError, match=r'^/c: only 1 board found in its 7 images \(5 like "no full 9x7'):
        _check_every_sensor_found_a_board(sensors, [*one] * 3, seen, rejected + past_one, board, 3)
    # a part of a larger pattern found in one image: the count itself is short, said as such
    from clcgraph.errors import InputError

    part = [Rejected("the chessboard goes on past the grid's left column: more inner corners than the 9x7 of "
                     "board.corners (a part of the pattern read as the board)", "detection", 1, 5)]
    with pytest.raises(InputError, match=r"^/c: the chessboard in 1 of its 6 images has more inner corners than "
                                         r"board.corners \[9, 7\]"):
        _check_every_sensor_found_a_board(sensors, [], [], rejected + part, board)
    # a grid with a row along the pattern's edge: the count is too large
    past = [Rejected("no chessboard corner along the grid's top row: the pattern's edge read as corners (fewer inner "
                     "corners than the 9x7 of board.corners?)", "detection", 1, 5)]
    with pytest.raises(InputError, match=r"^/c: the chessboard in 1 of its 6 images has fewer inner corners than "
                                         r"board.corners \[9, 7\] \(the pattern ends inside the grid found\)"):
        _check_every_sensor_found_a_board(sensors, [], [], rejected + past, board)


def test_a_topic_of_raw_lidar_packets_says_to_play_it_through_the_driver(monkeypatch):
    import pytest

    from clcgraph import api
    from clcgraph.errors import DataError
    from clcgraph.frontend import bag

    types = {"/velodyne_packets": "velodyne_msgs/msg/VelodyneScan",
             "/ouster/lidar_packets": "ouster_sensor_msgs/msg/PacketMsg",
             "/tf": "tf2_msgs/msg/TFMessage"}
    info = bag.BagInfo("a.bag", tuple(bag.TopicInfo(t, m, 1, 0, 0) for t, m in types.items()), 0, 0)
    monkeypatch.setattr(bag, "bag_info", lambda path: info)
    for t in ("/velodyne_packets", "/ouster/lidar_packets"):
        with pytest.raises(DataError, match=f"topic {t} has type .*raw packets: play the bag through its driver"):
            api.classify_topics(["a.bag"], [t])
    with pytest.raises(DataError) as e:
        api.classify_topics(["a.bag"], ["/tf"])
    assert "packets" not in str(e.value)


def test_settings_that_can_keep_nothing_are_one_line_errors(capsys, tmp_path, good):
    """--after not before --before, no topic in --topics, the mapping topic among the
    calibration topics: each refused before any work, naming what to change."""
    out = str(tmp_path / "o")
    for args, words in ((["solve", "--bag", str(good), "--topics", "/lidar0,/lidar1", "--after", "1700000090",
                          "--before", "1700000010", "--out", out], "is not before snapshots.before"),
                        (["solve", "--bag", str(good), "--topics", ",", "--out", out], "no topics given"),
                        (["targetless", "--bag", str(good), "--mapping-topic", "/lidar0",
                          "--calibration-topics", "/lidar0,/lidar1", "--out", out], "is the mapping topic")):
        assert main(args) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], (args, err)
