"""show-aligned --mcap: the MCAP file read back with rosbags: /tf_static, clouds and images
present, every data frame in the tf tree, and the tree's transforms equal to the calibration."""

from __future__ import annotations

import numpy as np
import pytest

from clcgraph.cli import main
from clcgraph.errors import InputError
from clcgraph.export_mcap import write_aligned_mcap
from clcgraph.geometry import T_from_rt
from clcgraph.outputs.results import write_results
from clcgraph.outputs.ros import T_from_ros_entry
from clcgraph.sim.bag_writer import BagWriter
from clcgraph.types import Image, LidarScan
from test_outputs import make_result

FRAMES = {"/lidar/front/points": "lidar_front", "/lidar/rear/points": "lidar_rear", "/cam/image": "cam"}
T_BASE_LIDAR0 = T_from_rt(np.r_[0.01, -0.02, 0.3, 1.2, 0.1, 1.9])


def _scan(topic, stamp, rng, n=500):
    pts = rng.uniform(-10, 10, (n, 3))
    valid = np.ones(n, bool)
    valid[:7] = False  # invalid returns are left out of the MCAP
    return LidarScan(topic, stamp, pts, valid, intensity=rng.uniform(0, 100, n).astype(np.float32),
                     ring=rng.integers(0, 16, n))


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """Three bags named as make_result's snapshots 0, 1, 2 (ROS1, /tf_static base_link -> lidar_front
    only, as a robot's description may have it), and the calibration written from make_result."""
    tmp = tmp_path_factory.mktemp("mcap")
    result = make_result()
    write_results(result, tmp / "calib")
    rng = np.random.default_rng(4)
    scans = {}
    for k in range(3):
        stamp = 1_700_000_000_000_000_000 + k * 10**10
        with BagWriter(tmp / f"pose{k:03d}.bag") as w:
            w.write_tf_static([("base_link", "lidar_front", T_BASE_LIDAR0)], stamp_ns=stamp)
            for topic in ("/lidar/front/points", "/lidar/rear/points"):
                scans[k, topic] = _scan(topic, stamp + 1000, rng)
                w.write_pointcloud(topic, scans[k, topic], frame_id=FRAMES[topic])
            px = rng.integers(0, 255, (800, 1280), dtype=np.uint8)
            w.write_image("/cam/image", Image("/cam/image", stamp + 2000, px, "mono8"), frame_id="cam")
    return tmp, result, scans


def _read(path):
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    out: dict[str, list] = {}
    with Reader(path) as r:
        qos = {c.topic: c.ext.offered_qos_profiles for c in r.connections}
        for conn, t, raw in r.messages():
            out.setdefault(conn.topic, []).append((t, store.deserialize_cdr(raw, conn.msgtype)))
    return out, qos


def _T(tr):
    from scipy.spatial.transform import Rotation

    q, p = tr.rotation, tr.translation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    T[:3, 3] = p.x, p.y, p.z
    return T


def _lookup(edges: dict, root: str, frame: str) -> np.ndarray:
    """T_root_frame by walking parents up (each child has one parent in a tf tree)."""
    parent_of = {c: (p, T) for (p, c), T in edges.items()}
    T = np.eye(4)
    while frame != root:
        p, T_pc = parent_of[frame]
        T, frame = T_pc @ T, p
    return T


def test_mcap_reads_back_with_consistent_frames(capture):
    tmp, result, scans = capture
    info = write_aligned_mcap([tmp / "*.bag"], tmp / "calib", tmp / "a.mcap", snapshots=["1", "pose002.bag"])
    assert [s["bag"] for s in info["snapshots"]] == ["pose001.bag", "pose002.bag"]
    msgs, qos = _read(tmp / "a.mcap")
    assert set(msgs) == {"/tf_static", "/lidar/front/points", "/lidar/rear/points", "/cam/image"}
    assert len(msgs["/lidar/rear/points"]) == len(msgs["/cam/image"]) == 2
    # /tf_static: one message, first, latched as tf2 publishes it
    (t_tf, tf_msg), = msgs["/tf_static"]
    assert t_tf <= min(t for topic in msgs for t, _ in msgs[topic])
    assert qos["/tf_static"][0].durability.name == "TRANSIENT_LOCAL"
    edges = {(tr.header.frame_id, tr.child_frame_id): _T(tr.transform) for tr in tf_msg.transforms}
    children = [c for _, c in edges]
    assert len(children) == len(set(children))  # a tree: one parent per frame
    # the data frames are in the tree, the camera's images in its optical frame
    frames = {topic: m.header.frame_id for topic in msgs if topic != "/tf_static" for _, m in msgs[topic][:1]}
    assert frames == {"/lidar/front/points": "lidar_front", "/lidar/rear/points": "lidar_rear",
                      "/cam/image": "cam_optical"}
    assert set(frames.values()) <= set(children)
    # lidar0 hangs off base_link as the bag's /tf_static says; every sensor where the calibration puts it
    np.testing.assert_allclose(_lookup(edges, "base_link", "lidar_front"), T_BASE_LIDAR0, atol=1e-12)
    for i, s in enumerate(result.problem.sensors):
        T_l0_s = np.linalg.inv(_lookup(edges, "base_link", "lidar_front")) @ _lookup(edges, "base_link", frames[s.topic])
        np.testing.assert_allclose(T_l0_s, T_from_rt(result.rt_lidar0_sensor[i]), atol=1e-9)
    # the clouds are the bags' valid points (float32), each in its sensor's frame
    _, cloud = msgs["/lidar/rear/points"][0]
    xyz = np.frombuffer(bytes(cloud.data), dtype=np.float32).reshape(-1, cloud.point_step // 4)[:, :3]
    want = scans[1, "/lidar/rear/points"]
    np.testing.assert_allclose(xyz, want.points[want.valid].astype(np.float32), atol=0)
    _, image = msgs["/cam/image"][0]
    assert (image.width, image.height, image.encoding) == (1280, 800, "mono8")


def test_mcap_without_base_link_is_rooted_at_lidar0_and_says_so(capture, tmp_path):
    tmp, result, _ = capture
    with BagWriter(tmp_path / "pose000.bag") as w:  # no /tf_static at all
        w.write_pointcloud("/lidar/front/points", _scan("/lidar/front/points", 10**18, np.random.default_rng(0)),
                           frame_id="lidar_front")
    info = write_aligned_mcap([tmp_path / "pose000.bag"], tmp / "calib", tmp_path / "b.mcap",
                              topics=["/lidar/front/points"])
    assert "rooted at lidar_front" in info["base_source"]
    msgs, _ = _read(tmp_path / "b.mcap")
    (_, tf_msg), = msgs["/tf_static"]
    edges = {(tr.header.frame_id, tr.child_frame_id): _T(tr.transform) for tr in tf_msg.transforms}
    # sensors with no messages in this bag are in the tree under names made from their topics
    assert {p for p, _ in edges} == {"lidar_front", "cam_image"}
    np.testing.assert_allclose(edges["lidar_front", "lidar_rear_points"], T_from_rt(result.rt_lidar0_sensor[1]),
                               atol=1e-12)


def test_mcap_bad_input_is_one_line(capture, capsys, tmp_path):
    tmp, *_ = capture
    bags = str(tmp / "*.bag")
    with pytest.raises(InputError, match="no snapshot 42"):
        write_aligned_mcap([bags], tmp / "calib", tmp_path / "x.mcap", snapshots=["42"])
    with pytest.raises(InputError, match="its bag pose005.bag is not among the bags given"):
        write_aligned_mcap([bags], tmp / "calib", tmp_path / "x.mcap", snapshots=["5"])
    with pytest.raises(InputError, match="'nope.bag': neither a snapshot index nor one of the bags given"):
        write_aligned_mcap([bags], tmp / "calib", tmp_path / "x.mcap", snapshots=["nope.bag"])
    (tmp_path / "taken.mcap").write_text("mine")
    for args, why in ((["--mcap", str(tmp_path / "taken.mcap")], "exists"),
                      (["--mcap", str(tmp_path / "x.bag")], "name the file"),
                      (["--snapshots", "1"], "give --mcap")):
        assert main(["-q", "show-aligned", bags, "--calibration", str(tmp / "calib"), *args]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and why in err[0], err
    assert (tmp_path / "taken.mcap").read_text() == "mine"  # nothing of the user's touched
    # the PNG shows one bag: refused before the MCAP is written, so neither is left
    two = [str(tmp / "pose000.bag"), str(tmp / "pose001.bag")]
    assert main(["-q", "show-aligned", *two, "--calibration", str(tmp / "calib"), "--mcap", str(tmp_path / "y.mcap"),
                 "--png", str(tmp_path / "y.png")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the PNG shows one bag, 2 given" in err[0], err
    assert not (tmp_path / "y.mcap").exists() and not (tmp_path / "y.png").exists()
    assert not list(tmp_path.glob(".*clcgraph-tmp*"))
    # the CLI writes it and says from where /tf_static's base came
    assert main(["-q", "show-aligned", bags, "--calibration", str(tmp / "calib"), "--mcap", str(tmp_path / "c.mcap"),
                 "--snapshots", "0"]) == 0
    out = capsys.readouterr().out
    assert "/tf_static: /tf_static of" in out and "1 snapshot(s) (pose000.bag)" in out and (tmp_path / "c.mcap").is_file()


def test_format_for_ros_cli_states_its_base(capture, capsys, tmp_path):
    """The bag's /tf_static knows only base_link -> lidar_front: with /tf_static as the base the other
    sensors' frames cannot be told (one line naming the topic); with --rt-vehicle-lidar0 the messages'
    own frame_ids serve, and the source is printed and written."""
    import yaml

    tmp, result, _ = capture
    bag, calib = str(tmp / "pose000.bag"), str(tmp / "calib")
    assert main(["-q", "format-for-ros", bag, "--calibration", calib]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "/lidar/rear/points" in err[0], err
    rt = "0.01,0.02,-0.3,1.0,-0.1,1.8"
    assert main(["-q", "format-for-ros", bag, "--calibration", calib, "--rt-vehicle-lidar0", rt,
                 "--out", str(tmp_path / "ros")]) == 0
    out = capsys.readouterr().out
    assert out.startswith("base_link <- lidar_front from --rt-vehicle-lidar0"), out
    d = yaml.safe_load((tmp_path / "ros" / "ros-transforms.yaml").read_text())
    assert d["base"]["source"].startswith("--rt-vehicle-lidar0") and set(d["transforms"]) == \
        {"lidar_front", "lidar_rear", "cam", "cam_optical"}
    T = T_from_ros_entry(d["transforms"]["lidar_rear"])
    want = T_from_rt(np.array(rt.split(","), float)) @ T_from_rt(result.rt_lidar0_sensor[1])
    np.testing.assert_allclose(T, want, atol=1e-9)
