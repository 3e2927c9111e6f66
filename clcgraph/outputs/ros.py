"""ROS outputs: base_link-relative transforms (clc's format-for-ros YAML), URDF, static tf launch.

The solve lives in the lidar0 frame; ROS wants poses relative to ``base_link``. The anchor,
base_link <- lidar0, comes from one stated source (``choose_base``): ``--rt-vehicle-lidar0``,
the calibration's own (the solve's ``sectors.rt_vehicle_lidar0`` or a targetless ground-plane
fit), or the bag's /tf_static (nominal: its error goes into every transform). Every output
says which.

Cameras (REP 103 / 105): the solve's camera frame is mrcal's right-down-forward, which is ROS's
*optical* frame. Each camera gets a body frame ``<sensor>`` (x forward, y left, z up) under
base_link and an optical frame ``<sensor>_optical`` under it with the fixed rotation
R_BODY_OPTICAL; images belong in the optical frame.

SYNOPSIS
    cal = load_result("out/")
    tf = read_tf_static(["session.bag"])        # anything with lookup(target, source) -> (4,4)
    ros = format_for_ros(cal, tf, frames={"/lidar/front/points": "lidar_front", ...})
    print(ros["base"]["source"]); print(ros_yaml(ros)); print(urdf_joints(ros))
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError
from ..geometry import R_from_r, T_from_rt, rpy_from_R, so3_right_jacobian

# columns: the optical frame's x (right), y (down), z (forward) in the camera body frame (x
# forward, y left, z up): rpy (-pi/2, 0, -pi/2), the rotation every ROS camera driver publishes
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
_OPTICAL_SUFFIXES = ("_optical_frame", "_optical")


def camera_frames(frame: str) -> tuple[str, str]:
    """(body, optical) frame names of a camera whose data frame is ``frame``: "cam" -> ("cam",
    "cam_optical"); a name that already says it is optical keeps it ("cam_optical_frame" ->
    ("cam", "cam_optical_frame"))."""
    for suffix in _OPTICAL_SUFFIXES:
        if frame.endswith(suffix) and len(frame) > len(suffix):
            return frame[: -len(suffix)], frame
    return frame, frame + "_optical"


def _frame_of(topic: str, frames: dict) -> str:
    try:
        return frames[topic]
    except KeyError:
        raise InputError(f"topic {topic}: no frame_id known for it; pass its frame") from None


def infer_frames(topics, tf_frames, *, frame_ids: dict | None = None, need_tf: bool = True) -> dict[str, str]:
    """topic -> ROS frame name: the message's header.frame_id when it is in /tf_static (or, with
    ``need_tf=False``, whenever the message has one), else (clc's rule) the topic component that
    names a /tf_static frame ("/lidar/velodyne_0/points" -> "velodyne_0"). Raises InputError
    naming a topic that matches no frame.
    """
    tf_frames = set(tf_frames)
    out = {}
    for topic in topics:
        fid = ((frame_ids or {}).get(topic) or "").lstrip("/")
        if fid and (fid in tf_frames or not need_tf):
            out[topic] = fid
            continue
        hits = [c for c in topic.split("/") if c and c in tf_frames]
        if len(hits) != 1:
            raise InputError(
                f"topic {topic}: cannot tell its /tf_static frame ({'none' if not hits else 'several'} of "
                f"{', '.join(sorted(tf_frames)) or 'no frames'} in the topic name); give the frames explicitly"
            )
        out[topic] = hits[0]
    return out


BASE_SOURCES = ("auto", "rt-vehicle-lidar0", "calibration", "tf-static")


def choose_base(calibration: dict, tf, *, base_frame: str, ref_frame: str, rt_vehicle_lidar0=None,
                solve_rt_vehicle_lidar0=None, source: str = "auto", tf_name: str = "the bag") -> tuple[np.ndarray, str]:
    """(T_base_lidar0 (4,4), a sentence naming where it came from).

    ``source`` "auto" takes, in this order: ``rt_vehicle_lidar0`` (the user's, mrcal rt); the
    calibration's own (a targetless ground-plane fit of base_frame <- reference, or the solve's
    non-zero ``sectors.rt_vehicle_lidar0``, passed as ``solve_rt_vehicle_lidar0``); ``tf``'s
    base_frame <- ref_frame (/tf_static: nominal). A named source must be available, or InputError.
    """
    if source not in BASE_SOURCES:
        raise InputError(f"--base-source {source!r}: use one of {', '.join(BASE_SOURCES)}")
    if base_frame == ref_frame:  # the transforms are relative to the reference itself
        return np.eye(4), f"{ref_frame} itself (poses relative to the reference)"
    ref = calibration["reference"]
    ground = {b["topic"]: b for b in calibration.get("base_link") or [] if b.get("frame", base_frame) == base_frame}
    given = None if rt_vehicle_lidar0 is None else np.asarray(rt_vehicle_lidar0, float).reshape(6)
    solve_rt = None if solve_rt_vehicle_lidar0 is None or not np.any(solve_rt_vehicle_lidar0) \
        else np.asarray(solve_rt_vehicle_lidar0, float).reshape(6)
    if source in ("auto", "rt-vehicle-lidar0") and given is not None:
        return T_from_rt(given), "--rt-vehicle-lidar0 (given on the command line)"
    if source == "rt-vehicle-lidar0":
        raise InputError("--base-source rt-vehicle-lidar0: give --rt-vehicle-lidar0 r0,r1,r2,t0,t1,t2")
    if source in ("auto", "calibration"):
        if ref in ground:
            return (np.asarray(ground[ref]["T_base_link_sensor"], float),
                    f"the calibration's ground-plane fit of {base_frame} <- {ref} (targetless: roll, pitch, z; "
                    "x, y, yaw from its initial guess)")
        if solve_rt is not None:
            return T_from_rt(solve_rt), "the calibration's sectors.rt_vehicle_lidar0 (config.resolved.yaml)"
    if source == "calibration":
        raise InputError(f"--base-source calibration: the calibration has no {base_frame} <- {ref} (no ground-plane "
                         "fit, no sectors.rt_vehicle_lidar0); use --rt-vehicle-lidar0 or --base-source tf-static")
    if tf is None:
        raise InputError(f"no {base_frame} <- {ref_frame} known: give --rt-vehicle-lidar0 or a bag with /tf_static")
    try:
        T = np.asarray(tf.lookup(base_frame, ref_frame), dtype=float)
    except Exception as e:  # the tf tree's own error, made one line with both frames named
        raise InputError(
            f"/tf_static has no transform {base_frame} <- {ref_frame} (reference {ref}): "
            f"{str(e).splitlines()[0] if str(e) else type(e).__name__}; give --rt-vehicle-lidar0"
        ) from None
    return T, (f"/tf_static of {tf_name} (nominal: its error goes into every sensor's transform; give "
               "--rt-vehicle-lidar0 for a measured one)")


def ros_covariance(rt_lidar0_sensor, covariance_rt, R_base_lidar0) -> np.ndarray:
    """(6,6) covariance of a sensor's pose as geometry_msgs/PoseWithCovariance orders it: x, y, z
    of its origin, then rotation about the parent's fixed x, y, z (a left perturbation,
    R = Exp(w) R_solved), both in base_link axes; from the (6,6) rt covariance relative to
    lidar0. The uncertainty of base_link <- lidar0 itself is not in it."""
    rt = np.asarray(rt_lidar0_sensor, float).reshape(6)
    R = R_from_r(rt[:3])
    J = np.zeros((6, 6))
    J[:3, 3:] = np.eye(3)  # position = the rt translation
    J[3:, :3] = R @ so3_right_jacobian(rt[:3])  # left-perturbation angle from dr: R Jr (the left Jacobian)
    B = np.kron(np.eye(2), np.asarray(R_base_lidar0, float))
    M = B @ J
    C = M @ np.asarray(covariance_rt, float).reshape(6, 6) @ M.T
    return 0.5 * (C + C.T)


def _entry(parent: str, T: np.ndarray, **extra) -> dict:
    q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x, y, z, w
    return {"parent_frame": parent, **extra,
            "translation": {k: float(v) for k, v in zip("xyz", T[:3, 3])},
            "rotation": {k: float(v) for k, v in zip("xyzw", q)},
            "T_parent_child": T.tolist()}


def format_for_ros(calibration: dict, tf=None, *, base_frame: str = "base_link", frames: dict[str, str],
                   stamp_ns: int | None = None, rt_vehicle_lidar0=None, solve_rt_vehicle_lidar0=None,
                   base_source: str = "auto", tf_name: str = "the bag") -> dict:
    """Transforms of every sensor frame, in clc's format-geometry-for-ros shape, with the base stated.

    ``calibration``: load_result()'s dict; ``tf``: has ``lookup(target, source) -> T_target_source``
    (4,4) (needed only when base_link <- lidar0 comes from /tf_static, see choose_base);
    ``frames``: topic -> ROS frame_id of its data. Returns ``{"stamp": {"nsec"}, "base":
    {"parent_frame", "child_frame", "source", "T"}, "transforms": {frame: {"parent_frame",
    "topic", "translation": {x,y,z}, "rotation": {x,y,z,w}, "T_parent_child", "T_base_frame",
    "covariance" (6x6, see ros_covariance) | absent, "optical": bool}}, "notes": [str]}``.
    LIDARs hang off base_frame; a camera's body frame off base_frame and its optical frame off the body.
    """
    ref_topic = calibration["reference"]
    ref_frame = _frame_of(ref_topic, frames)
    T_base_lidar0, source = choose_base(calibration, tf, base_frame=base_frame, ref_frame=ref_frame,
                                        rt_vehicle_lidar0=rt_vehicle_lidar0, source=base_source,
                                        solve_rt_vehicle_lidar0=solve_rt_vehicle_lidar0, tf_name=tf_name)
    sensors = calibration["sensors"]
    C = np.asarray(calibration["covariance_rt_lidar0_sensor"], float)
    variable = [k for k, s in enumerate(sensors) if s["topic"] != ref_topic]
    T_body_optical = np.eye(4)
    T_body_optical[:3, :3] = R_BODY_OPTICAL
    transforms, notes = {}, []
    for k, s in enumerate(sensors):
        frame = _frame_of(s["topic"], frames)
        T = T_base_lidar0 @ np.asarray(s["T_lidar0_sensor"], dtype=float)  # the data frame (optical for cameras)
        if s["topic"] == ref_topic:
            cov = np.zeros((6, 6))
        else:
            b = 6 * variable.index(k)
            cov = ros_covariance(s["rt_lidar0_sensor"], C[b:b + 6, b:b + 6], T_base_lidar0[:3, :3])
        cov = np.round(cov, 15).tolist()  # exact zeros stay zeros, no -0.0 noise
        if s["kind"] != "camera":
            transforms[frame] = _entry(base_frame, T, topic=s["topic"], T_base_frame=T.tolist(), covariance=cov,
                                       optical=False)
            continue
        body, optical = camera_frames(frame)
        T_base_body = T @ np.linalg.inv(T_body_optical)
        transforms[body] = _entry(base_frame, T_base_body, topic=s["topic"], T_base_frame=T_base_body.tolist(),
                                  covariance=cov, optical=False)
        transforms[optical] = _entry(body, T_body_optical, topic=s["topic"], T_base_frame=T.tolist(),
                                     covariance=cov, optical=True)
        if frame != optical:
            notes.append(f"camera {s['topic']}: its images are in frame {frame}, which here is the camera's body "
                         f"frame (x forward); the images belong in {optical}: set the driver's frame_id to {optical}")
    return {"stamp": {"nsec": int(stamp_ns or 0)},
            "base": {"parent_frame": base_frame, "child_frame": ref_frame, "source": source, "T": T_base_lidar0.tolist()},
            "transforms": transforms, "notes": notes}


def T_from_ros_entry(entry: dict) -> np.ndarray:
    """(4,4) from one ``transforms`` entry's translation + quaternion."""
    T = np.eye(4)
    r = entry["rotation"]
    T[:3, :3] = Rotation.from_quat([r["x"], r["y"], r["z"], r["w"]]).as_matrix()
    T[:3, 3] = [entry["translation"][k] for k in "xyz"]
    return T


def _xyz_rpy(entry: dict) -> tuple[np.ndarray, np.ndarray]:
    T = T_from_ros_entry(entry)
    return T[:3, 3], rpy_from_R(T[:3, :3])  # URDF rpy: fixed axes, R = Rz(yaw) Ry(pitch) Rx(roll)


def _f(v) -> str:
    return " ".join(f"{x + 0.0:.9g}" for x in v)  # + 0.0: no "-0"


def _joints(ros: dict) -> list[str]:
    out = []
    for frame, e in ros["transforms"].items():
        xyz, rpy = _xyz_rpy(e)
        out += [
            f'<joint name="{frame}_joint" type="fixed">',
            f'  <parent link="{e["parent_frame"]}"/>',
            f'  <child link="{frame}"/>',
            f'  <origin xyz="{_f(xyz)}" rpy="{_f(rpy)}"/>',
            "</joint>",
        ]
    return out


def _header(ros: dict) -> str:
    b = ros["base"]
    text = (f"clcgraph extrinsics. {b['parent_frame']} <- {b['child_frame']} from {b['source']}. "
            "rpy: roll, pitch, yaw [rad] about fixed x-y-z (URDF)")
    lines = [text, *(f"note: {n}" for n in ros.get("notes", ()))]
    return "\n".join(f"<!-- {line.replace('--', '')} -->" for line in lines)  # "--" may not appear in an XML comment


def urdf_joints(ros: dict) -> str:
    """The fixed ``<joint>`` of every sensor frame, to paste into an existing robot description
    (which declares the sensor links already); only the optical links this adds are declared."""
    optical = [f for f, e in ros["transforms"].items() if e.get("optical")]
    out = [_header(ros), "<!-- paste inside your <robot>; its sensor links stay as they are -->"]
    if optical:
        out.append("<!-- the cameras' optical frames (REP 103): drop these links if your description has them -->")
        out += [f'<link name="{f}"/>' for f in optical]
    return "\n".join(out + _joints(ros)) + "\n"


def urdf_robot(ros: dict, *, name: str = "clcgraph_sensors") -> str:
    """A whole ``<robot>``: every link (base and sensor frames) and joint; loads on its own."""
    links = [ros["base"]["parent_frame"], *ros["transforms"]]
    out = [f'<?xml version="1.0"?>', _header(ros), f'<robot name="{name}">']
    out += [f'  <link name="{f}"/>' for f in links]
    out += ["  " + line for line in _joints(ros)]
    return "\n".join(out + ["</robot>"]) + "\n"


def static_tf_cli_lines(ros: dict, *, ros_version: int = 2) -> str:
    """One ``static_transform_publisher`` command line per sensor (x y z qx qy qz qw parent child)."""
    lines = []
    for frame, e in ros["transforms"].items():
        t, r = e["translation"], e["rotation"]
        args = f"{t['x']:.9g} {t['y']:.9g} {t['z']:.9g} {r['x']:.9g} {r['y']:.9g} {r['z']:.9g} {r['w']:.9g}"
        if ros_version == 1:
            lines.append(f"rosrun tf2_ros static_transform_publisher {args} {e['parent_frame']} {frame}")
        else:
            lines.append(
                "ros2 run tf2_ros static_transform_publisher "
                f"--x {t['x']:.9g} --y {t['y']:.9g} --z {t['z']:.9g} "
                f"--qx {r['x']:.9g} --qy {r['y']:.9g} --qz {r['z']:.9g} --qw {r['w']:.9g} "
                f"--frame-id {e['parent_frame']} --child-frame-id {frame}"
            )
    return "\n".join(lines) + "\n"


def launch_ros1_xml(ros: dict) -> str:
    """A ROS1 ``<launch>`` file with one tf2_ros static_transform_publisher node per sensor."""
    out = ["<launch>"]
    for frame, e in ros["transforms"].items():
        t, r = e["translation"], e["rotation"]
        args = (f"{t['x']:.9g} {t['y']:.9g} {t['z']:.9g} {r['x']:.9g} {r['y']:.9g} {r['z']:.9g} {r['w']:.9g} "
                f"{e['parent_frame']} {frame}")
        out.append(f'  <node pkg="tf2_ros" type="static_transform_publisher" name="clcgraph_{frame}" args="{args}"/>')
    out.append("</launch>")
    return "\n".join(out) + "\n"


def launch_ros2_python(ros: dict) -> str:
    """A ROS2 Python launch file with one static_transform_publisher Node per sensor."""
    out = [
        "from launch import LaunchDescription",
        "from launch_ros.actions import Node",
        "",
        "",
        "def generate_launch_description():",
        "    return LaunchDescription([",
    ]
    for frame, e in ros["transforms"].items():
        t, r = e["translation"], e["rotation"]
        args = [f"{t['x']:.9g}", f"{t['y']:.9g}", f"{t['z']:.9g}", f"{r['x']:.9g}", f"{r['y']:.9g}",
                f"{r['z']:.9g}", f"{r['w']:.9g}"]
        argv = ", ".join(
            [f'"--{k}", "{v}"' for k, v in zip(["x", "y", "z", "qx", "qy", "qz", "qw"], args)]
            + [f'"--frame-id", "{e["parent_frame"]}"', f'"--child-frame-id", "{frame}"']
        )
        out.append('        Node(package="tf2_ros", executable="static_transform_publisher",')
        out.append(f'             name="clcgraph_{frame}", arguments=[{argv}]),')
    out.append("    ])")
    return "\n".join(out) + "\n"


def T_base_frame(ros: dict, frame: str) -> np.ndarray:
    """(4,4) base_frame <- ``frame``, composed along the parents of the ``transforms``."""
    T = np.eye(4)
    while frame in ros["transforms"]:
        e = ros["transforms"][frame]
        T = T_from_ros_entry(e) @ T
        frame = e["parent_frame"]
    return T


_YAML_HEADER = """# clcgraph format-for-ros: {base}
#   <- {child} from {source}.
# translation [m], rotation as a quaternion x, y, z, w, of each frame in its parent_frame.
# covariance: 6x6 row-major as geometry_msgs/PoseWithCovariance (x, y, z [m^2], then rotation about
# the fixed x, y, z [rad^2]) in {base}'s axes: the calibration's uncertainty relative to {child};
# that of {base} <- {child} itself is not in it.
"""


def ros_yaml(ros: dict) -> str:
    """The clc-shaped YAML (stamp + transforms with parent, translation, rotation), plus the base's
    source and each frame's covariance, with a header saying what they are."""
    import yaml

    keep = ("parent_frame", "translation", "rotation", "covariance")
    slim = {"stamp": ros["stamp"],
            "base": {k: ros["base"][k] for k in ("parent_frame", "child_frame", "source")},
            "transforms": {f: {k: e[k] for k in keep if k in e} for f, e in ros["transforms"].items()}}
    b = ros["base"]
    notes = "".join(f"# note: {n}\n" for n in ros.get("notes", ()))
    return (_YAML_HEADER.format(base=b["parent_frame"], child=b["child_frame"], source=b["source"]) + notes
            + yaml.safe_dump(slim, sort_keys=False, width=200, default_flow_style=None))


def ros_files(ros: dict, *, full_urdf: bool = False) -> dict[str, str]:
    """{file name: text} of every ROS output, for format-for-ros to write next to each other."""
    files = {
        "ros-transforms.yaml": ros_yaml(ros),
        "sensors.urdf.xml": urdf_joints(ros),
        "static_tf.launch": launch_ros1_xml(ros),
        "static_tf.launch.py": launch_ros2_python(ros),
        "static_tf_ros1.sh": static_tf_cli_lines(ros, ros_version=1),
        "static_tf_ros2.sh": static_tf_cli_lines(ros, ros_version=2),
    }
    if full_urdf:
        files["sensors.urdf"] = urdf_robot(ros)
    return files
