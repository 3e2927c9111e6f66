"""format-for-ros: base_link-relative transforms, URDF and launch snippets against a known tf tree."""

from __future__ import annotations

import ast
import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from clcgraph.errors import InputError
from clcgraph.frontend.bag import TfTree
from clcgraph.geometry import T_from_rt
from clcgraph.outputs import ros
from clcgraph.outputs.results import load_result, write_results
from test_outputs import make_result

FRAMES = {"/lidar/front/points": "lidar_front", "/lidar/rear/points": "lidar_rear", "/cam/image": "cam"}
# base_link -> chassis -> lidar_front: a two-edge chain, so lookup has to compose
T_BASE_CHASSIS = T_from_rt(np.r_[0, 0, 0.05, 1.2, 0.0, 0.4])
T_CHASSIS_LIDAR0 = T_from_rt(np.r_[0.02, -0.01, 0.1, 0.3, 0.1, 1.5])


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    result = make_result()
    out = tmp_path_factory.mktemp("ros") / "out"
    write_results(result, out)
    cal = load_result(out)
    tf = TfTree()
    tf.add("base_link", "chassis", T_BASE_CHASSIS)
    tf.add("chassis", "lidar_front", T_CHASSIS_LIDAR0)
    return result, cal, tf, ros.format_for_ros(cal, tf, frames=FRAMES, stamp_ns=123)


def test_transforms_reproduce_truth(setup):
    result, cal, tf, out = setup
    assert out["stamp"] == {"nsec": 123}
    assert set(out["transforms"]) == set(FRAMES.values())
    for i, s in enumerate(result.problem.sensors):
        e = out["transforms"][FRAMES[s.topic]]
        assert e["parent_frame"] == "base_link"
        truth = T_BASE_CHASSIS @ T_CHASSIS_LIDAR0 @ T_from_rt(result.rt_lidar0_sensor[i])
        np.testing.assert_allclose(ros.T_from_ros_entry(e), truth, atol=1e-12)
        q = [e["rotation"][k] for k in "xyzw"]
        assert np.linalg.norm(q) == pytest.approx(1, abs=1e-12)
    # the reference LIDAR sits exactly where /tf_static says
    np.testing.assert_allclose(ros.T_from_ros_entry(out["transforms"]["lidar_front"]),
                               T_BASE_CHASSIS @ T_CHASSIS_LIDAR0, atol=1e-12)


def test_clc_yaml_shape(setup):
    *_, out = setup
    d = yaml.safe_load(ros.ros_yaml(out))
    assert set(d) == {"stamp", "transforms"}
    e = d["transforms"]["lidar_rear"]
    assert set(e) == {"parent_frame", "translation", "rotation"}
    assert set(e["translation"]) == set("xyz") and set(e["rotation"]) == set("xyzw")


def test_urdf_snippet(setup):
    result, cal, tf, out = setup
    root = ET.fromstring(f"<robot name='r'>{ros.urdf_snippet(out)}</robot>")
    joints = root.findall("joint")
    assert len(joints) == 3 and len(root.findall("link")) == 3
    for j in joints:
        child = j.find("child").get("link")
        o = j.find("origin")
        xyz = np.array(o.get("xyz").split(), float)
        roll, pitch, yaw = np.array(o.get("rpy").split(), float)
        # URDF semantics: R = Rz(yaw) Ry(pitch) Rx(roll)
        Rz = Rotation.from_euler("z", yaw).as_matrix()
        Ry = Rotation.from_euler("y", pitch).as_matrix()
        Rx = Rotation.from_euler("x", roll).as_matrix()
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Rz @ Ry @ Rx, xyz
        np.testing.assert_allclose(T, ros.T_from_ros_entry(out["transforms"][child]), atol=1e-8)
        assert j.find("parent").get("link") == "base_link"


def _T_from_args(nums):
    x, y, z, qx, qy, qz, qw = map(float, nums)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
    T[:3, 3] = x, y, z
    return T


def test_launch_snippets(setup):
    *_, out = setup
    truth = {f: ros.T_from_ros_entry(e) for f, e in out["transforms"].items()}
    # ROS1 XML launch: args = x y z qx qy qz qw parent child
    for node in ET.fromstring(ros.launch_ros1_xml(out)).findall("node"):
        a = node.get("args").split()
        assert a[7] == "base_link"
        np.testing.assert_allclose(_T_from_args(a[:7]), truth[a[8]], atol=1e-8)
    # ROS2 python launch: valid python, named arguments
    src = ros.launch_ros2_python(out)
    ast.parse(src)
    for args in re.findall(r"arguments=\[(.*?)\]", src):
        a = ast.literal_eval(f"[{args}]")
        kv = dict(zip(a[::2], a[1::2]))
        nums = [kv[f"--{k}"] for k in ("x", "y", "z", "qx", "qy", "qz", "qw")]
        np.testing.assert_allclose(_T_from_args(nums), truth[kv["--child-frame-id"]], atol=1e-8)
    lines1 = ros.static_tf_cli_lines(out, ros_version=1).splitlines()
    assert len(lines1) == 3
    a = lines1[0].split()[3:]
    np.testing.assert_allclose(_T_from_args(a[:7]), truth[a[8]], atol=1e-8)
    assert all("--child-frame-id" in line for line in ros.static_tf_cli_lines(out).splitlines())


def test_missing_frames_are_input_errors(setup):
    result, cal, tf, out = setup
    with pytest.raises(InputError, match="/cam/image"):
        ros.format_for_ros(cal, tf, frames={k: v for k, v in FRAMES.items() if k != "/cam/image"})
    with pytest.raises(InputError, match="odom"):
        ros.format_for_ros(cal, tf, base_frame="odom", frames=FRAMES)


def test_infer_frames():
    tf_frames = {"base_link", "velodyne_0", "velodyne_1", "left_cam"}
    topics = ["/lidar/velodyne_0/points", "/lidar/velodyne_1/points", "/front/image"]
    got = ros.infer_frames(topics, tf_frames, frame_ids={"/front/image": "/left_cam", "/lidar/velodyne_1/points": "vlp"})
    assert got == {"/lidar/velodyne_0/points": "velodyne_0", "/lidar/velodyne_1/points": "velodyne_1",
                   "/front/image": "left_cam"}
    with pytest.raises(InputError, match="/front/image"):
        ros.infer_frames(["/front/image"], tf_frames)


def test_ros_files(setup):
    *_, out = setup
    files = ros.ros_files(out)
    assert set(files) == {"ros-transforms.yaml", "sensors.urdf.xml", "static_tf.launch", "static_tf.launch.py",
                          "static_tf_ros1.sh", "static_tf_ros2.sh"}
    assert yaml.safe_load(files["ros-transforms.yaml"])["transforms"]["cam"]["parent_frame"] == "base_link"


def test_ground_plane_base_link_of_a_targetless_calibration_wins_over_tf(setup):
    result, cal, tf, _ = setup
    T_ground = T_from_rt(np.r_[0.01, -0.02, 0.0, 1.2, 0.0, 1.93])  # base_link <- reference from the ground plane
    tl = dict(cal, base_link=[{"topic": cal["reference"], "frame": "base_link", "T_base_link_sensor": T_ground}])
    out = ros.format_for_ros(tl, tf, frames=FRAMES)
    for i, s in enumerate(result.problem.sensors):
        np.testing.assert_allclose(ros.T_from_ros_entry(out["transforms"][FRAMES[s.topic]]),
                                   T_ground @ T_from_rt(result.rt_lidar0_sensor[i]), atol=1e-12)
