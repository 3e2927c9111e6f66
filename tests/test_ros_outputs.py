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


def _truth(result, i):
    return T_BASE_CHASSIS @ T_CHASSIS_LIDAR0 @ T_from_rt(result.rt_lidar0_sensor[i])


def test_transforms_reproduce_truth(setup):
    result, cal, tf, out = setup
    assert out["stamp"] == {"nsec": 123}
    # a camera is a body frame under base_link and its optical frame under the body
    assert set(out["transforms"]) == {"lidar_front", "lidar_rear", "cam", "cam_optical"}
    assert "/tf_static" in out["base"]["source"] and out["base"]["child_frame"] == "lidar_front"
    for i, s in enumerate(result.problem.sensors):
        data_frame = FRAMES[s.topic] + ("_optical" if s.is_camera else "")
        np.testing.assert_allclose(ros.T_base_frame(out, data_frame), _truth(result, i), atol=1e-12)
        np.testing.assert_allclose(out["transforms"][data_frame]["T_base_frame"], _truth(result, i), atol=1e-12)
        q = [out["transforms"][data_frame]["rotation"][k] for k in "xyzw"]
        assert np.linalg.norm(q) == pytest.approx(1, abs=1e-12)
    assert out["transforms"]["cam"]["parent_frame"] == "base_link"
    assert out["transforms"]["cam_optical"]["parent_frame"] == "cam"
    # REP 103: the body frame's x is the optical z (forward), its y the optical -x (left), z the optical -y (up)
    R_body, R_opt = ros.T_base_frame(out, "cam")[:3, :3], ros.T_base_frame(out, "cam_optical")[:3, :3]
    np.testing.assert_allclose(R_body[:, 0], R_opt[:, 2], atol=1e-12)
    np.testing.assert_allclose(R_body[:, 1], -R_opt[:, 0], atol=1e-12)
    np.testing.assert_allclose(R_body[:, 2], -R_opt[:, 1], atol=1e-12)
    # the reference LIDAR sits exactly where /tf_static says
    np.testing.assert_allclose(ros.T_from_ros_entry(out["transforms"]["lidar_front"]),
                               T_BASE_CHASSIS @ T_CHASSIS_LIDAR0, atol=1e-12)
    # the images' frame "cam" is the body frame now: said so
    assert any("cam_optical" in n and "/cam/image" in n for n in out["notes"])


def test_camera_frames_names():
    assert ros.camera_frames("cam") == ("cam", "cam_optical")
    assert ros.camera_frames("front_optical_frame") == ("front", "front_optical_frame")
    assert ros.camera_frames("front_optical") == ("front", "front_optical")


def test_base_link_source_is_stated_and_chosen(setup):
    result, cal, tf, _ = setup
    rt_given = np.r_[0.01, 0.02, -0.3, 1.0, -0.1, 1.8]
    out = ros.format_for_ros(cal, tf, frames=FRAMES, rt_vehicle_lidar0=rt_given)
    assert out["base"]["source"].startswith("--rt-vehicle-lidar0")
    np.testing.assert_allclose(ros.T_base_frame(out, "lidar_rear"),
                               T_from_rt(rt_given) @ T_from_rt(result.rt_lidar0_sensor[1]), atol=1e-12)
    # the solve's own (non-zero) sectors.rt_vehicle_lidar0 comes before /tf_static; all zeros means unset
    out = ros.format_for_ros(cal, tf, frames=FRAMES, solve_rt_vehicle_lidar0=list(rt_given))
    assert "sectors.rt_vehicle_lidar0" in out["base"]["source"]
    np.testing.assert_allclose(out["base"]["T"], T_from_rt(rt_given), atol=1e-12)
    out = ros.format_for_ros(cal, tf, frames=FRAMES, solve_rt_vehicle_lidar0=[0.0] * 6)
    assert "/tf_static" in out["base"]["source"]
    # a named source wins over auto's order, and must exist
    out = ros.format_for_ros(cal, tf, frames=FRAMES, solve_rt_vehicle_lidar0=list(rt_given), base_source="tf-static")
    np.testing.assert_allclose(out["base"]["T"], T_BASE_CHASSIS @ T_CHASSIS_LIDAR0, atol=1e-12)
    with pytest.raises(InputError, match="--base-source calibration"):
        ros.format_for_ros(cal, tf, frames=FRAMES, base_source="calibration")
    with pytest.raises(InputError, match="give --rt-vehicle-lidar0"):
        ros.format_for_ros(cal, None, frames=FRAMES)
    # the YAML and the URDF say it too
    given = ros.format_for_ros(cal, tf, frames=FRAMES, rt_vehicle_lidar0=rt_given)
    assert "from --rt-vehicle-lidar0" in ros.ros_yaml(given) and "from rt-vehicle-lidar0" in ros.urdf_joints(given)


def test_covariance_matches_monte_carlo(setup):
    """The 6x6 PoseWithCovariance-ordered covariance (x, y, z, then rotation about base_link's
    fixed axes) against samples of rt_lidar0_sensor drawn from the calibration's covariance."""
    from clcgraph.geometry import R_from_r, r_from_R

    result, cal, tf, out = setup
    rng = np.random.default_rng(5)
    T_base_lidar0 = T_BASE_CHASSIS @ T_CHASSIS_LIDAR0
    for i, frame in ((1, "lidar_rear"), (2, "cam_optical")):
        C = result.covariance_block(i)
        got = np.array(out["transforms"][frame]["covariance"])
        samples = rng.multivariate_normal(result.rt_lidar0_sensor[i], C, size=40000)
        R = T_base_lidar0[:3, :3] @ R_from_r(samples[:, :3])
        R0 = ros.T_base_frame(out, frame)[:3, :3]
        w = r_from_R(R @ R0.T)  # rotation about base_link's fixed axes (left perturbation)
        p = samples[:, 3:] @ T_base_lidar0[:3, :3].T
        mc = np.cov(np.c_[p, w].T)
        sd = np.sqrt(np.diag(mc))
        np.testing.assert_allclose(np.sqrt(np.diag(got)), sd, rtol=0.03)
        np.testing.assert_allclose(got / np.outer(sd, sd), mc / np.outer(sd, sd), atol=0.03)  # correlations
    assert np.all(np.array(out["transforms"]["lidar_front"]["covariance"]) == 0)  # the reference
    assert out["transforms"]["cam"]["covariance"] == out["transforms"]["cam_optical"]["covariance"]


def test_clc_yaml_shape(setup):
    *_, out = setup
    text = ros.ros_yaml(out)
    d = yaml.safe_load(text)
    assert set(d) == {"stamp", "base", "transforms"}
    e = d["transforms"]["lidar_rear"]
    assert set(e) == {"parent_frame", "translation", "rotation", "covariance"}
    assert set(e["translation"]) == set("xyz") and set(e["rotation"]) == set("xyzw")
    assert np.array(e["covariance"]).shape == (6, 6)
    assert "# covariance: 6x6 row-major as geometry_msgs/PoseWithCovariance" in text


def _urdf_T(origin):
    xyz = np.array(origin.get("xyz").split(), float)
    roll, pitch, yaw = np.array(origin.get("rpy").split(), float)
    # URDF semantics: R = Rz(yaw) Ry(pitch) Rx(roll)
    T = np.eye(4)
    T[:3, :3] = (Rotation.from_euler("z", yaw).as_matrix() @ Rotation.from_euler("y", pitch).as_matrix()
                 @ Rotation.from_euler("x", roll).as_matrix())
    T[:3, 3] = xyz
    return T


def test_urdf_joints_only_and_full_robot(setup):
    result, cal, tf, out = setup
    root = ET.fromstring(f"<robot name='r'>{ros.urdf_joints(out)}</robot>")
    joints = root.findall("joint")
    assert len(joints) == 4
    # only the optical link this adds is declared: the robot's description has the sensor links
    assert [lk.get("name") for lk in root.findall("link")] == ["cam_optical"]
    parents = {j.find("child").get("link"): j.find("parent").get("link") for j in joints}
    T = {j.find("child").get("link"): _urdf_T(j.find("origin")) for j in joints}
    for i, s in enumerate(result.problem.sensors):
        frame = FRAMES[s.topic]
        assert parents[frame] == "base_link"
        T_base = T[frame]
        if s.is_camera:
            assert parents["cam_optical"] == "cam"
            np.testing.assert_allclose(T["cam_optical"][:3, :3], ros.R_BODY_OPTICAL, atol=1e-8)  # 9 digits printed
            T_base = T["cam"] @ T["cam_optical"]
        np.testing.assert_allclose(T_base, _truth(result, i), atol=1e-8)
    cam_rpy = next(j for j in joints if j.find("child").get("link") == "cam_optical").find("origin").get("rpy")
    np.testing.assert_allclose(np.array(cam_rpy.split(), float), [-np.pi / 2, 0, -np.pi / 2], atol=1e-9)
    assert "/tf_static" in ros.urdf_joints(out).splitlines()[0]
    # the whole robot: every link once, joints as above
    full = ET.fromstring(ros.urdf_robot(out))
    assert sorted(lk.get("name") for lk in full.findall("link")) == ["base_link", "cam", "cam_optical", "lidar_front",
                                                                     "lidar_rear"]
    assert len(full.findall("joint")) == 4


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
    nodes = ET.fromstring(ros.launch_ros1_xml(out)).findall("node")
    assert len(nodes) == 4
    for node in nodes:
        a = node.get("args").split()
        assert a[7] == out["transforms"][a[8]]["parent_frame"]
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
    assert len(lines1) == 4
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
    # with base_link <- lidar0 from elsewhere, the messages' own frame_ids need not be in /tf_static
    assert ros.infer_frames(["/front/image"], set(), frame_ids={"/front/image": "cam"}, need_tf=False) == \
        {"/front/image": "cam"}


def test_ros_files(setup):
    *_, out = setup
    files = ros.ros_files(out)
    assert set(files) == {"ros-transforms.yaml", "sensors.urdf.xml", "static_tf.launch", "static_tf.launch.py",
                          "static_tf_ros1.sh", "static_tf_ros2.sh"}
    assert yaml.safe_load(files["ros-transforms.yaml"])["transforms"]["cam"]["parent_frame"] == "base_link"
    assert set(ros.ros_files(out, full_urdf=True)) - set(files) == {"sensors.urdf"}


def test_ground_plane_base_link_of_a_targetless_calibration_wins_over_tf(setup):
    result, cal, tf, _ = setup
    T_ground = T_from_rt(np.r_[0.01, -0.02, 0.0, 1.2, 0.0, 1.93])  # base_link <- reference from the ground plane
    tl = dict(cal, base_link=[{"topic": cal["reference"], "frame": "base_link", "T_base_link_sensor": T_ground}])
    out = ros.format_for_ros(tl, tf, frames=FRAMES)
    assert "ground-plane" in out["base"]["source"]
    for i, s in enumerate(result.problem.sensors):
        frame = FRAMES[s.topic] + ("_optical" if s.is_camera else "")
        np.testing.assert_allclose(ros.T_base_frame(out, frame), T_ground @ T_from_rt(result.rt_lidar0_sensor[i]),
                                   atol=1e-12)
