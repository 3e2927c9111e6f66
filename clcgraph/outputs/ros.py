"""ROS outputs: base_link-relative transforms (clc's format-for-ros YAML), URDF, static tf launch.

The solve lives in the lidar0 frame; ROS wants poses relative to ``base_link``. The
anchor is the reference LIDAR's transform base_link <- lidar0 from /tf_static.

SYNOPSIS
    cal = load_result("out/")
    tf = read_tf_static(["session.bag"])        # anything with lookup(target, source) -> (4,4)
    ros = format_for_ros(cal, tf, frames={"/lidar/front/points": "lidar_front", ...})
    print(yaml.safe_dump(ros)); print(urdf_snippet(ros)); print(launch_ros2_python(ros))
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError
from ..geometry import rpy_from_R


def _frame_of(topic: str, frames: dict) -> str:
    try:
        return frames[topic]
    except KeyError:
        raise InputError(f"topic {topic}: no frame_id known for it; pass its frame") from None


def infer_frames(topics, tf_frames, *, frame_ids: dict | None = None) -> dict[str, str]:
    """topic -> ROS frame name: the message's header.frame_id when it is in /tf_static, else
    (clc's rule) the topic component that names a /tf_static frame ("/lidar/velodyne_0/points"
    -> "velodyne_0"). Raises InputError naming a topic that matches no frame.
    """
    tf_frames = set(tf_frames)
    out = {}
    for topic in topics:
        fid = (frame_ids or {}).get(topic)
        if fid is not None and fid.lstrip("/") in tf_frames:
            out[topic] = fid.lstrip("/")
            continue
        hits = [c for c in topic.split("/") if c and c in tf_frames]
        if len(hits) != 1:
            raise InputError(
                f"topic {topic}: cannot tell its /tf_static frame ({'none' if not hits else 'several'} of "
                f"{', '.join(sorted(tf_frames)) or 'no frames'} in the topic name); give the frames explicitly"
            )
        out[topic] = hits[0]
    return out


def format_for_ros(calibration: dict, tf, *, base_frame: str = "base_link", frames: dict[str, str],
                   stamp_ns: int | None = None) -> dict:
    """Transforms base_frame -> every sensor frame, in clc's format-geometry-for-ros shape.

    ``calibration``: load_result()'s dict; ``tf``: has ``lookup(target, source) -> T_target_source``
    (4,4); ``frames``: topic -> ROS frame_id. Returns
    ``{"stamp": {"nsec": int}, "transforms": {frame: {"parent_frame", "translation": {x,y,z},
    "rotation": {x,y,z,w}}}}`` plus ``T_base_sensor`` (4x4 lists) per frame for scripts.
    """
    ref_topic = calibration["reference"]
    ref_frame = _frame_of(ref_topic, frames)
    # a targetless calibration may carry base_link <- reference from the ground plane: it wins
    # over /tf_static (whose roll, pitch and height it corrected)
    ground = {b["topic"]: b for b in calibration.get("base_link") or [] if b.get("frame", base_frame) == base_frame}
    try:
        T_base_lidar0 = (np.asarray(ground[ref_topic]["T_base_link_sensor"], dtype=float) if ref_topic in ground
                         else np.asarray(tf.lookup(base_frame, ref_frame), dtype=float))
    except Exception as e:  # the tf tree's own error, made one line with both frames named
        raise InputError(
            f"/tf_static has no transform {base_frame} <- {ref_frame} (reference {ref_topic}): {str(e).splitlines()[0] if str(e) else type(e).__name__}"
        ) from None
    transforms = {}
    for s in calibration["sensors"]:
        frame = _frame_of(s["topic"], frames)
        T = T_base_lidar0 @ np.asarray(s["T_lidar0_sensor"], dtype=float)
        q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x, y, z, w
        transforms[frame] = {
            "parent_frame": base_frame,
            "topic": s["topic"],
            "translation": {k: float(v) for k, v in zip("xyz", T[:3, 3])},
            "rotation": {k: float(v) for k, v in zip("xyzw", q)},
            "T_base_sensor": T.tolist(),
        }
    return {"stamp": {"nsec": int(stamp_ns or 0)}, "transforms": transforms}


def T_from_ros_entry(entry: dict) -> np.ndarray:
    """(4,4) from one ``transforms`` entry's translation + quaternion."""
    T = np.eye(4)
    r = entry["rotation"]
    T[:3, :3] = Rotation.from_quat([r["x"], r["y"], r["z"], r["w"]]).as_matrix()
    T[:3, 3] = [entry["translation"][k] for k in "xyz"]
    return T


def _xyz_rpy(entry: dict) -> tuple[np.ndarray, np.ndarray]:
    T = T_from_ros_entry(entry)
    # URDF rpy: fixed axes, R = Rz(yaw) Ry(pitch) Rx(roll) == scipy's extrinsic "xyz"
    return T[:3, 3], rpy_from_R(T[:3, :3])


def _f(v) -> str:
    return " ".join(f"{x:.9g}" for x in v)


def urdf_snippet(ros: dict) -> str:
    """URDF ``<link>``/``<joint>`` elements, one fixed joint per sensor frame."""
    out = ["<!-- clcgraph extrinsics: paste inside your <robot> -->"]
    for frame, e in ros["transforms"].items():
        xyz, rpy = _xyz_rpy(e)
        out += [
            f'<link name="{frame}"/>',
            f'<joint name="{frame}_joint" type="fixed">',
            f'  <parent link="{e["parent_frame"]}"/>',
            f'  <child link="{frame}"/>',
            f'  <origin xyz="{_f(xyz)}" rpy="{_f(rpy)}"/>',
            "</joint>",
        ]
    return "\n".join(out) + "\n"


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


def ros_yaml(ros: dict) -> str:
    """The clc-shaped YAML (stamp + transforms with translation/rotation only)."""
    import yaml

    slim = {"stamp": ros["stamp"], "transforms": {
        f: {k: e[k] for k in ("parent_frame", "translation", "rotation")} for f, e in ros["transforms"].items()}}
    return yaml.safe_dump(slim, sort_keys=False)


def ros_files(ros: dict) -> dict[str, str]:
    """{file name: text} of every ROS output, for format-for-ros to write next to each other."""
    return {
        "ros-transforms.yaml": ros_yaml(ros),
        "sensors.urdf.xml": urdf_snippet(ros),
        "static_tf.launch": launch_ros1_xml(ros),
        "static_tf.launch.py": launch_ros2_python(ros),
        "static_tf_ros1.sh": static_tf_cli_lines(ros, ros_version=1),
        "static_tf_ros2.sh": static_tf_cli_lines(ros, ros_version=2),
    }
