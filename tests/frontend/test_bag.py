"""Bag round trips (writer -> reader) for ROS1 / ROS2-sqlite3 / ROS2-mcap, tf_static, bad bags."""

import dataclasses

import numpy as np
import pytest

from clcgraph.errors import DataError, InputError
from clcgraph.frontend import bag
from clcgraph.geometry import T_from_rt
from clcgraph.sim.bag_writer import BagWriter
from clcgraph.types import Image, LidarScan

FORMATS = {"ros1": "x.bag", "ros2-sqlite3": "x_sqlite", "ros2-mcap": "x_mcap"}
RINGS, COLS = 8, 64
T0 = 1_700_000_000_123_456_789


def _scan(rng, stamp_ns, topic):
    """An (8 x 64) scan on a sphere of 2-20 m radius with a few invalid returns."""
    elev = np.linspace(-0.3, 0.3, RINGS)[:, None]
    az = np.linspace(-np.pi, np.pi, COLS, endpoint=False)[None, :]
    r = rng.uniform(2, 20, (RINGS, COLS))
    pts = np.stack([r * np.cos(elev) * np.cos(az), r * np.cos(elev) * np.sin(az),
                    r * np.sin(elev) * np.ones_like(az)], axis=-1).reshape(-1, 3)
    pts = pts.astype(np.float32).astype(np.float64)  # exactly representable in float32
    valid = rng.uniform(size=len(pts)) > 0.1
    # invalid points keep finite coordinates: the writer must mark them as the drivers do
    return LidarScan(
        topic=topic, stamp_ns=stamp_ns, points=pts, valid=valid,
        intensity=rng.integers(0, 255, len(pts)).astype(np.float32),
        ring=np.repeat(np.arange(RINGS), COLS),
        time_s=np.tile(np.linspace(0, 0.099, COLS), RINGS),
        shape=(RINGS, COLS),
    )


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """Every format x endianness: two snapshots of two LIDARs (both layouts) and four cameras."""
    rng = np.random.default_rng(42)
    root = tmp_path_factory.mktemp("bags")
    stamps = [T0, T0 + 1_500_000_000]
    scans = {s: {"/velo": _scan(rng, s + 1000, "/velo"), "/os": _scan(rng, s + 2000, "/os")} for s in stamps}
    y, x = np.mgrid[0:48, 0:64]
    colour = np.stack([x * 4, y * 5, 255 - x * 3], axis=-1).astype(np.uint8)
    images = {s: {"/cam/raw": Image("/cam/raw", s + 3000, rng.integers(0, 255, (48, 64, 3), dtype=np.uint8), "bgr8"),
                  "/cam/mono16": Image("/cam/mono16", s + 4000, rng.integers(0, 65535, (48, 64), dtype=np.uint16), "mono16"),
                  "/cam/png": Image("/cam/png", s + 5000, rng.integers(0, 255, (48, 64), dtype=np.uint8), "mono8"),
                  "/cam/jpeg": Image("/cam/jpeg", s + 6000, colour, "bgr8")} for s in stamps}
    tf = [("base_link", "lidar0", T_from_rt(np.array([0.1, -0.2, 0.3, 1.0, 2.0, 3.0]))),
          ("lidar0", "cam0", T_from_rt(np.array([-1.2, 0.1, 0.05, 0.1, -0.3, 0.2]))),
          ("base_link", "lidar1", T_from_rt(np.array([0.0, 0.0, 3.0, -1.0, 0.5, 0.0])))]
    paths = {}
    for fmt, name in FORMATS.items():
        for big in (False, True):
            p = root / (("be_" if big else "le_") + name)
            with BagWriter(p, format=fmt, compress=True) as w:
                w.write_tf_static(tf, stamp_ns=T0 - 10)
                for s in stamps:
                    w.write_pointcloud("/velo", scans[s]["/velo"], frame_id="lidar0", layout="velodyne", big_endian=big)
                    w.write_pointcloud("/os", scans[s]["/os"], frame_id="lidar1", layout="ouster", big_endian=big)
                    w.write_image("/cam/raw", images[s]["/cam/raw"], frame_id="cam0")
                    w.write_image("/cam/mono16", images[s]["/cam/mono16"], frame_id="cam0")
                    w.write_image("/cam/png", images[s]["/cam/png"], frame_id="cam1", compressed="png")
                    w.write_image("/cam/jpeg", images[s]["/cam/jpeg"], frame_id="cam2", compressed="jpeg")
            paths[(fmt, big)] = p
    return paths, stamps, scans, images, tf


TOPICS = ["/velo", "/os", "/cam/raw", "/cam/mono16", "/cam/png", "/cam/jpeg"]


def _check_scan(got, want, layout):
    assert got.stamp_ns == want.stamp_ns and got.topic == want.topic
    np.testing.assert_array_equal(got.valid, want.valid)
    np.testing.assert_array_equal(got.points[got.valid], want.points[want.valid])
    np.testing.assert_array_equal(got.ring, want.ring)
    if layout == "ouster":
        assert got.shape == (RINGS, COLS)
        assert (got.points[~got.valid] == 0).all()  # the driver's invalid marker
        np.testing.assert_allclose(got.time_s, want.time_s, rtol=0, atol=0.5e-9)  # uint32 ns
    else:
        assert got.shape is None
        assert np.isnan(got.points[~got.valid]).all()
        np.testing.assert_allclose(got.time_s, want.time_s, rtol=0, atol=1e-8)  # float32 s
    np.testing.assert_array_equal(got.intensity, want.intensity)


@pytest.mark.parametrize("big", [False, True], ids=["le", "be"])
@pytest.mark.parametrize("fmt", list(FORMATS))
def test_round_trip_exact(written, fmt, big):
    paths, stamps, scans, images, _ = written
    p = paths[(fmt, big)]
    msgs = list(bag.read_messages([p], TOPICS))
    assert len(msgs) == 2 * len(TOPICS)
    assert [m.stamp_ns for m in msgs] == sorted(m.stamp_ns for m in msgs)
    for m in msgs:
        s = [s for s in stamps if 0 <= m.stamp_ns - s < 10_000][0]
        assert m.bag == p and m.index == stamps.index(s)
        if m.topic == "/velo":
            _check_scan(m.data, scans[s]["/velo"], "velodyne")
        elif m.topic == "/os":
            _check_scan(m.data, scans[s]["/os"], "ouster")
        else:
            want = images[s][m.topic]
            assert m.data.stamp_ns == want.stamp_ns == m.stamp_ns
            assert m.data.pixels.shape == want.pixels.shape and m.data.pixels.dtype == want.pixels.dtype
            err = np.abs(m.data.pixels.astype(int) - want.pixels.astype(int))
            if m.topic == "/cam/jpeg":
                assert err.mean() < 2 and err.max() < 25, (err.mean(), err.max())
            else:
                assert err.max() == 0, m.topic


@pytest.mark.parametrize("fmt", ["ros2-sqlite3", "ros2-mcap"])
def test_a_ros2_bag_compressed_whole_reads_from_its_folder_or_its_storage_file(written, fmt):
    """`ros2 bag record --compression-mode file --compression-format zstd` leaves the storage file as
    *.db3.zstd / *.mcap.zstd (the fixture writes so): given the folder or that file, the same messages."""
    paths, *_ = written
    folder = paths[(fmt, False)]
    (storage,) = [f for f in folder.iterdir() if f.name.endswith(".zstd")]
    by_folder = [(m.topic, m.stamp_ns) for m in bag.read_messages([folder], TOPICS)]
    assert len(by_folder) == 2 * len(TOPICS)
    assert [(m.topic, m.stamp_ns) for m in bag.read_messages([storage], TOPICS)] == by_folder


@pytest.mark.parametrize("layout, fields", [("pcl_xyzi", ["x", "y", "z", "intensity"]), ("pcl_xyz", ["x", "y", "z"])])
def test_a_pcl_filters_cloud_reads_without_rings_and_they_come_from_elevation(tmp_path, layout, fields):
    """pcl::PointXYZI (pcl::PointXYZ) as a filter node republishes a driver's cloud: dense (invalid
    points dropped), no ring or time field (nor intensity). The reader takes it as it is; the rings
    come from the elevations."""
    from clcgraph.frontend.lidar_preprocess import ring_of

    scan = _scan(np.random.default_rng(3), T0, "/xyzi")
    with BagWriter(tmp_path / "x.bag", format="ros1") as w:
        w.write_pointcloud("/xyzi", scan, frame_id="lidar0", layout=layout)
    raw = bag.first_raw_message(tmp_path / "x.bag", "/xyzi")
    assert [f.name for f in raw.fields] == fields and raw.height == 1 and raw.is_dense
    got = bag.first_messages(tmp_path / "x.bag", ["/xyzi"])["/xyzi"]
    assert got.ring is None and got.time_s is None and got.shape is None and got.valid.all()
    np.testing.assert_array_equal(got.points, scan.points[scan.valid])
    if "intensity" in fields:
        np.testing.assert_array_equal(got.intensity, scan.intensity[scan.valid])
    else:
        assert got.intensity is None
    np.testing.assert_array_equal(ring_of(got), scan.ring[scan.valid])


def test_a_hesai_cloud_reads_with_its_absolute_float64_times_and_rings_as_numbered(tmp_path):
    """Hesai's PointXYZIT: each point's absolute time in float64 seconds (the reader makes it
    relative to the header stamp, to the microsecond) and rings as the driver numbers them."""
    scan = _scan(np.random.default_rng(4), T0 + 123_456_789, "/hesai")
    with BagWriter(tmp_path / "h.bag", format="ros1") as w:
        w.write_pointcloud("/hesai", scan, frame_id="lidar0", layout="hesai")
    raw = bag.first_raw_message(tmp_path / "h.bag", "/hesai")
    assert [(f.name, f.datatype) for f in raw.fields][3:] == [("intensity", 7), ("timestamp", 8), ("ring", 4)]
    got = bag.first_messages(tmp_path / "h.bag", ["/hesai"])["/hesai"]
    np.testing.assert_array_equal(got.points[got.valid], scan.points[scan.valid])
    np.testing.assert_array_equal(got.ring[got.valid], scan.ring[scan.valid])
    np.testing.assert_allclose(got.time_s[got.valid], scan.time_s[scan.valid], atol=1e-6)


def test_info_first_frame_window_and_merge(written):
    paths, stamps, scans, _, _ = written
    p = paths[("ros1", False)]
    info = bag.bag_info(p)
    assert {t.topic for t in info.topics} == set(TOPICS) | {"/tf_static"}
    velo = info.topic("/velo")
    assert velo.msgtype == "sensor_msgs/msg/PointCloud2" and velo.count == 2
    assert (velo.first_ns, velo.last_ns) == (stamps[0] + 1000, stamps[1] + 1000)
    assert info.start_ns == T0 - 10 and info.end_ns == stamps[1] + 6000
    first = bag.first_messages(p, ["/os", "/cam/png"])
    _check_scan(first["/os"], scans[stamps[0]]["/os"], "ouster")
    assert first["/cam/png"].stamp_ns == stamps[0] + 5000
    assert bag.frame_id(p, "/os") == "lidar1" and bag.frame_id(paths[("ros2-mcap", True)], "/cam/jpeg") == "cam2"
    # time window keeps the second snapshot only; indices still count from the bag start
    late = list(bag.read_messages(p, ["/velo"], start_ns=stamps[0] + 2000))
    assert [(m.index, m.stamp_ns) for m in late] == [(1, stamps[1] + 1000)]
    # two bags merged in stamp order
    both = list(bag.read_messages([paths[("ros1", False)], paths[("ros2-mcap", False)]], ["/velo"]))
    assert [m.stamp_ns for m in both] == sorted([stamps[0] + 1000] * 2 + [stamps[1] + 1000] * 2)
    assert {m.bag for m in both} == {paths[("ros1", False)], paths[("ros2-mcap", False)]}


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_tf_static_chain(written, fmt):
    paths, _, _, _, tf = written
    T = {(a, b): M for a, b, M in tf}
    tree = bag.read_tf_static([paths[(fmt, False)]])
    want = np.linalg.inv(T[("base_link", "lidar1")]) @ T[("base_link", "lidar0")] @ T[("lidar0", "cam0")]
    np.testing.assert_allclose(tree.lookup("lidar1", "cam0"), want, atol=1e-12)
    np.testing.assert_allclose(tree.lookup("cam0", "lidar1"), np.linalg.inv(want), atol=1e-12)
    np.testing.assert_allclose(tree.lookup("base_link", "lidar0"), T[("base_link", "lidar0")], atol=1e-12)
    with pytest.raises(DataError, match="'nowhere' unknown"):
        tree.lookup("nowhere", "cam0")


def _assert_one_line(e, *names):
    s = str(e.value)
    assert "\n" not in s, s
    for n in names:
        assert str(n) in s, (n, s)


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_truncated_bag(written, tmp_path, fmt):
    src = written[0][(fmt, False)]
    if src.is_file():
        dst = tmp_path / src.name
        dst.write_bytes(src.read_bytes()[: src.stat().st_size // 2])
    else:  # a ROS2 directory: cut its storage file in half, keep metadata.yaml
        dst = tmp_path / src.name
        dst.mkdir()
        for f in src.iterdir():
            b = f.read_bytes()
            (dst / f.name).write_bytes(b if f.name == "metadata.yaml" else b[: len(b) // 2])
    with pytest.raises(DataError) as e:
        list(bag.read_messages([dst], TOPICS))
    _assert_one_line(e, dst)


def test_empty_bag(tmp_path):
    p = tmp_path / "empty.bag"
    with BagWriter(p, format="ros1"):
        pass
    with pytest.raises(DataError) as e:
        bag.bag_info(p)
    _assert_one_line(e, p, "empty")
    p2 = tmp_path / "empty_mcap"
    with BagWriter(p2, format="ros2-mcap"):
        pass
    with pytest.raises(DataError) as e:
        list(bag.read_messages(p2, ["/x"]))
    _assert_one_line(e, p2, "empty")


def test_missing_file_topic_and_wrong_type(written, tmp_path):
    p = written[0][("ros2-sqlite3", False)]
    with pytest.raises(InputError) as e:
        bag.first_messages(tmp_path / "nope.bag", ["/velo"])
    _assert_one_line(e, tmp_path / "nope.bag")
    with pytest.raises(InputError) as e:
        list(bag.read_messages([p], ["/velo", "/lidar/missing"]))
    _assert_one_line(e, p, "/lidar/missing", "/velo", "/cam/raw")  # lists what is available
    with pytest.raises(DataError) as e:
        list(bag.read_messages([p], ["/tf_static"]))
    _assert_one_line(e, p, "/tf_static", "tf2_msgs/msg/TFMessage")


def test_undecodable_message_names_bag_topic_index(tmp_path):
    rng = np.random.default_rng(0)
    p = tmp_path / "bad.bag"
    with BagWriter(p, format="ros1") as w:
        w.write_image("/cam", Image("/cam", T0, np.zeros((4, 4), np.uint8), "mono8"), frame_id="c")
        # second message in an encoding nobody decodes
        bad = Image("/cam", T0 + 1, np.zeros((4, 4), np.uint8), "mono8")
        w.write_image("/cam", bad, frame_id="c")
        w.write_pointcloud("/l", _scan(rng, T0, "/l"), frame_id="l")
    # rewrite the encoding by patching bytes: "mono8" of the 2nd message -> "xxxx8"
    raw = p.read_bytes()
    i = raw.find(b"mono8", raw.find(b"mono8") + 5)
    p.write_bytes(raw[:i] + b"yuv48" + raw[i + 5:])
    it = bag.read_messages([p], ["/cam"])
    assert next(it).index == 0
    with pytest.raises(DataError) as e:
        next(it)
    _assert_one_line(e, p, "/cam", "message 1", "yuv48")


def test_show_bag_cli(written, capsys, tmp_path):
    from clcgraph.cli import main

    p = written[0][("ros2-mcap", True)]
    assert main(["show-bag", str(p)]) == 0
    out = capsys.readouterr().out
    assert "/velo" in out and "sensor_msgs/msg/PointCloud2" in out and "tf2_msgs/msg/TFMessage" in out
    assert "/os: PointCloud2 8 x 64, point_step 48" in out and "big endian" in out
    assert "/velo: PointCloud2 1 x 512, point_step 32" in out
    assert "range          offset  32  uint32" in out
    assert main(["show-bag", str(tmp_path / "missing.bag")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "missing.bag" in err


def test_not_a_bag(tmp_path):
    p = tmp_path / "notes.bag"
    p.write_text("hello, not a bag\n")
    d = tmp_path / "not_a_ros2_bag"
    d.mkdir()
    for path in (p, d):
        with pytest.raises(DataError) as e:
            bag.bag_info(path)
        _assert_one_line(e, path, "cannot read bag")


def _tf_msg(parent, child, t=(1.0, 2.0, 3.0), q=(0.0, 0.0, 0.0, 1.0)):
    from types import SimpleNamespace as NS

    tr = NS(translation=NS(x=t[0], y=t[1], z=t[2]), rotation=NS(x=q[0], y=q[1], z=q[2], w=q[3]))
    return NS(transforms=[NS(header=NS(frame_id=parent), child_frame_id=child, transform=tr)])


@pytest.mark.parametrize("parent, child, t, q, pattern", [
    ("base", "lidar", (1, 2, 3), (0, 0, 0, 0), "not normalized"),
    ("base", "lidar", (1, 2, 3), (0, 0, 0.6, 0.6), "not normalized"),
    ("base", "lidar", (np.nan, 2, 3), (0, 0, 0, 1), "non-finite"),
    ("base", "lidar", (1, 2, 3), (0, 0, np.inf, 1), "non-finite"),
    ("", "lidar", (1, 2, 3), (0, 0, 0, 1), "non-empty frame names"),
    ("base", "base", (1, 2, 3), (0, 0, 0, 1), "two different"),
])
def test_tf_messages_tf2_would_refuse_are_dataerrors(parent, child, t, q, pattern):
    with pytest.raises(DataError, match=f"x.bag: /tf_static message 0: '{parent}' -> '{child}': .*{pattern}"):
        bag.decode_tf_message(_tf_msg(parent, child, t, q), where="x.bag: /tf_static message 0")
    # a slightly unnormalized quaternion (as tf2 tolerates) is fine, and normalized
    ((p, c, T),) = bag.decode_tf_message(_tf_msg("base", "lidar", q=(0, 0, 0.7072, 0.7072)), where="x")
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [1, 2, 3])


# ---------------------------------------------------------------- stamp order, not log order


def test_stamp_ordered_sorts_a_drivers_log_and_names_what_it_cannot_place(caplog):
    rng = np.random.default_rng(4)
    stamps = np.sort(rng.integers(0, 10**10, 400))
    delays = rng.uniform(0.0, 0.4e9, 400).astype(np.int64)  # logged up to 0.4 s after the stamp
    delays[100] = 3 * 10**9  # one message logged 3 s late: beyond the 1 s the helper waits
    log_t = stamps + delays
    order = np.argsort(log_t, kind="stable")
    items = [(int(log_t[k]), int(stamps[k]), "/cam" if k == 100 else "/lidar", k) for k in order]
    assert [it[1] for it in items] != sorted(it[1] for it in items)  # log order is not stamp order
    with caplog.at_level("WARNING"):
        out = list(bag.stamp_ordered(items))
    got = [s for s, _, _ in out]
    assert got == sorted(got) and len(out) == 399 and 100 not in {p for _, _, p in out}
    assert sorted(p for _, _, p in out) == sorted(set(range(400)) - {100})
    assert any("/cam: 1 messages" in r.getMessage() and "skipped" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("fmt", ["ros1", "ros2-mcap"])
def test_drivers_log_times_are_read_in_stamp_order(tmp_path, fmt):
    """BagWriter(log_delays=...) logs a scan one rotation after its stamp and a frame 20-35 ms
    after: across topics the log order differs from the stamp order; read_messages undoes it."""
    from clcgraph.sim.bag_writer import LogDelays

    rng = np.random.default_rng(0)
    path = tmp_path / ("d.bag" if fmt == "ros1" else "d")
    T0 = 1_700_000_000 * 10**9
    with BagWriter(path, format=fmt, log_delays=LogDelays(seed=1)) as w:
        for k in range(20):
            w.write_pointcloud("/lidar", _scan(rng, T0 + k * 10**8, "/lidar"), frame_id="l")
        for k in range(10):
            w.write_image("/cam", Image("/cam", T0 + 30_000_000 + k * 2 * 10**8, np.zeros((4, 4), np.uint8), "mono8"),
                          frame_id="c")
    with bag._Bag(path) as b:
        logged = [(c.topic, bag._stamp(m, t)) for c, _, t, m in b.raw(b.connections(["/lidar", "/cam"]))]
    assert [s for _, s in logged] != sorted(s for _, s in logged)
    read = [(m.topic, m.stamp_ns) for m in bag.read_messages(path, ["/lidar", "/cam"])]
    assert [s for _, s in read] == sorted(s for _, s in logged) and sorted(read) == sorted(logged)


@pytest.mark.parametrize("clock", ["boot", "3 s behind", "2.5 s ahead"])
def test_a_sensor_stamping_on_its_own_clock_is_timed_by_log_time(tmp_path, caplog, clock):
    """An Ouster left at TIME_FROM_INTERNAL_OSC stamps its scans in seconds since it booted, an
    unsynchronised sensor's clock is seconds off: its messages are read in their place among
    the others', timed by their log times (one note naming the topic: info, not a warning, so a
    refused run still prints one line), in read_messages and in leading_messages alike; the
    other topics keep their stamps. (Seconds off, unnoticed, its messages were dropped as
    logged too late, or paired with the others' of seconds before.)"""
    import logging

    from clcgraph.sim.bag_writer import LogDelays

    rng = np.random.default_rng(0)
    T0 = 1_700_000_000 * 10**9
    offset = {"boot": 42 * 10**9 - T0, "3 s behind": -3 * 10**9, "2.5 s ahead": 25 * 10**8}[clock]
    path = tmp_path / "boot.bag"
    with BagWriter(path, log_delays=LogDelays(seed=1), clock_offsets_ns={"/os": offset}) as w:
        for k in range(10):
            w.write_pointcloud("/os", _scan(rng, T0 + k * 10**8, "/os"), frame_id="os")
            w.write_pointcloud("/vlp", _scan(rng, T0 + k * 10**8 + 5 * 10**7, "/vlp"), frame_id="v")
    with bag._Bag(path) as b:
        logged = {(c.topic, i): (t, bag._stamp(m, t)) for c, i, t, m in b.raw(b.connections(["/os", "/vlp"]))}
    assert all(abs(t - s) > 2 * 10**9 for (topic, _), (t, s) in logged.items() if topic == "/os")
    bag._WARNED_CLOCK.discard("/os")
    with caplog.at_level(logging.INFO, logger="clcgraph.frontend.bag"):
        read = list(bag.read_messages(path, ["/os", "/vlp"]))
    # in their place among the others' (each about a rotation late), not all before them
    assert len(read) == 20 and [m.stamp_ns for m in read] == sorted(m.stamp_ns for m in read)
    assert [m.topic for m in read][1:-1] == ["/os", "/vlp"] * 9
    for m in read:
        log_ns, stamp = logged[m.topic, m.index]
        assert m.stamp_ns == m.data.stamp_ns == (log_ns if m.topic == "/os" else stamp)
    noted = [r for r in caplog.records if "own clock" in r.getMessage()]
    assert len(noted) == 1 and noted[0].getMessage().startswith("/os: header stamps") and noted[0].levelname == "INFO"
    lead = bag.leading_messages(path, ["/os", "/vlp"], {})
    assert lead["/os"][0].stamp_ns == logged["/os", 0][0] and lead["/vlp"][0].stamp_ns == logged["/vlp", 0][1]


def test_bags_with_the_same_message_definitions_share_one_typestore(written, tmp_path, monkeypatch):
    """Parsing a bag's message definitions and compiling their deserializers costs more than reading
    a small bag: bags that carry the same ones (every bag of a capture) share one typestore, parsed
    once; a bag with other definitions gets its own, built (and its digests checked) the stock way."""
    import rosbags.highlevel.anyreader as anyreader

    parsed = []
    real = anyreader.get_types_from_msg
    monkeypatch.setattr(anyreader, "get_types_from_msg", lambda text, name: parsed.append(name) or real(text, name))
    monkeypatch.setattr(bag, "_TYPESTORES", {})
    a, b = tmp_path / "a.bag", tmp_path / "b.bag"
    rng = np.random.default_rng(3)
    for p in (a, b):
        with BagWriter(p) as w:
            w.write_pointcloud("/velo", _scan(rng, T0, "/velo"), frame_id="lidar0", layout="velodyne")
    with bag._Bag(a) as ba, bag._Bag(b) as bb:
        assert ba.reader.typestore is bb.reader.typestore
        assert parsed == ["sensor_msgs/msg/PointCloud2"]  # once, for both bags
        with bag._Bag(written[0][("ros1", False)]) as other:  # more topics: other definitions
            assert other.reader.typestore is not ba.reader.typestore
            assert len(parsed) > 1
    # what the shared typestore decodes is what rosbags' own reader decodes
    from rosbags.highlevel import AnyReader

    with AnyReader([b]) as stock:
        conn, _, raw = next(stock.messages())
        want = stock.deserialize(raw, conn.msgtype)
    got = bag.first_raw_message(b, "/velo")
    assert bytes(got.data) == bytes(want.data) and got.header.stamp == want.header.stamp
    assert [f.name for f in got.fields] == [f.name for f in want.fields]


@pytest.mark.parametrize("fmt", ["ros1", "ros2-sqlite3", "ros2-mcap"])
def test_a_cameras_camera_info_is_read_beside_its_images(tmp_path, fmt):
    """CameraInfo (K, D as ROS 1's K, D and ROS 2's k, d) on the topic image_transport puts beside
    the images (/ns/image_raw[/compressed] -> /ns/camera_info); its absence names both topics."""
    path = tmp_path / ("c.bag" if fmt == "ros1" else "c")
    K = [[500.0, 0, 320], [0, 501, 240], [0, 0, 1]]
    with BagWriter(path, format=fmt) as w:
        w.write_camera_info("/cam/camera_info", stamp_ns=10**18, frame_id="c", size=(640, 480), K=K,
                            distortion_model="plumb_bob", D=[-0.1, 0.02, 0.001, -0.002, 0.003])
    for topic in ("/cam/image_raw", "/cam/image_raw/compressed"):
        info = bag.camera_info([path], topic)
        np.testing.assert_array_equal(info.K, K)
        np.testing.assert_array_equal(info.D, [-0.1, 0.02, 0.001, -0.002, 0.003])
        assert info.distortion_model == "plumb_bob" and info.size == (640, 480) and "/cam/camera_info" in info.where
    with pytest.raises(InputError, match=r"no camera model file given for /other/image and no /other/camera_info in the "
                                         r"bags \(CameraInfo topics: /cam/camera_info\)"):
        bag.camera_info([path], "/other/image")
    from clcgraph.cameras import camera_from_info

    assert camera_from_info("/cam/image_raw", info).lensmodel == "LENSMODEL_OPENCV5"
    uncalibrated = dataclasses.replace(info, K=np.zeros((3, 3)), D=np.zeros(0))  # what an uncalibrated driver sends
    with pytest.raises(DataError, match=r"/cam/camera_info: not a calibrated camera .* give a camera model for /cam/x"):
        camera_from_info("/cam/x", uncalibrated)
