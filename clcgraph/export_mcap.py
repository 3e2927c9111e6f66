"""A calibration as an MCAP file for Foxglove and `ros2 bag play` + RViz: /tf_static from the
calibration, and the LIDAR clouds and camera images of chosen snapshots in their own frames,
so the viewer aligns them with the calibrated transforms.

The tf tree is format-for-ros's (outputs/ros.py): base_link <- lidar0 from the stated source
when one is known, else rooted at lidar0's frame; each camera as a body frame and an optical
frame ``<sensor>_optical`` (REP 103), its images stamped in the optical one. Messages are ROS 2
(sensor_msgs/PointCloud2, sensor_msgs/Image, tf2_msgs/TFMessage; /tf_static offered as
transient-local, as tf2 latches it), written with rosbags' rosbag2 writer, MCAP storage.

SYNOPSIS
    info = write_aligned_mcap(["capture/*.bag"], "calib/", "aligned.mcap", snapshots=["3", "pose007.bag"])
    info["frames"], info["snapshots"]      # what went in
    # Foxglove: open aligned.mcap; ROS 2 (Iron and later): ros2 bag play aligned.mcap, RViz fixed frame base_link
"""

from __future__ import annotations

import logging
import os
import tempfile
from pathlib import Path

import numpy as np

from .errors import InputError

log = logging.getLogger(__name__)


def _choose(bags: list[Path], cal: dict, wanted) -> list[tuple[int | None, Path, int | None]]:
    """(snapshot index or None, bag, stamp_ns or None) of each chosen snapshot: ``wanted`` items
    are snapshot indices (calibration.yaml's snapshots.list) or bag names; None: every bag."""
    from .types import names_bag

    listed = (cal.get("snapshots") or {}).get("list") or []
    named = lambda name: [b for b in bags if names_bag(name, b)]  # noqa: E731
    if not wanted:
        return [(None, b, None) for b in bags]
    out = []
    for item in wanted:
        item = str(item).strip()
        if item.isdigit():
            entry = next((e for e in listed if int(e.get("index", -1)) == int(item)), None)
            if entry is None:
                raise InputError(f"--snapshots {item}: the calibration lists no snapshot {item} "
                                 f"({len(listed)} listed)" + ("" if listed else "; name bags instead"))
            hits = named(str(entry.get("bag")))
            if not hits:
                raise InputError(f"--snapshots {item}: its bag {entry.get('bag')} is not among the bags given")
            # a bag of one snapshot is read from its start (as solve did); one of several (a continuous
            # bag, --decimation-period) around the snapshot's stamp
            several = sum(e.get("bag") == entry.get("bag") for e in listed) > 1
            out.append((int(item), hits[0], entry.get("stamp_ns") if several else None))
        elif named(item):
            out.append((None, named(item)[0], None))
        else:
            raise InputError(f"--snapshots {item!r}: neither a snapshot index nor one of the bags given "
                             f"({', '.join(sorted(b.name for b in bags)[:5])}{', ...' if len(bags) > 5 else ''})")
    return out


def snapshot_messages(bag: Path, topics: list[str], stamp_ns: int | None) -> dict:
    """{topic: decoded message}: the one nearest ``stamp_ns`` (a continuous bag's snapshot), or
    the first of each topic (one snapshot per bag)."""
    from .frontend.bag import first_messages, read_messages

    if stamp_ns is None:
        return first_messages(bag, topics)
    best: dict = {}
    for m in read_messages([bag], topics, start_ns=int(stamp_ns) - 10**9, stop_ns=int(stamp_ns) + 10**9):
        if m.topic not in best or abs(m.stamp_ns - stamp_ns) < abs(best[m.topic].stamp_ns - stamp_ns):
            best[m.topic] = m
    return {t: best[t].data for t in topics if t in best}


def tf_tree(cal: dict, bag: Path, *, base_frame: str = "base_link", rt_vehicle_lidar0=None) -> dict:
    """format-for-ros's transforms for ``cal`` with the frame names of ``bag``; rooted at lidar0's
    frame (``ros["base"]["source"]`` says so) when nothing gives base_frame <- lidar0."""
    from .frontend.bag import frame_id, read_tf_static
    from .outputs.ros import format_for_ros, infer_frames

    from .frontend.bag import bag_info

    tf = read_tf_static(bag)
    in_bag = {t.topic for t in bag_info(bag).topics if t.count}
    frames = {}
    for s in cal["sensors"]:
        t = s["topic"]
        try:
            frames.update(infer_frames([t], tf.frames, frame_ids={t: frame_id(bag, t)} if t in in_bag else {},
                                       need_tf=False))
        except InputError:  # a sensor with no messages here: in the tree under a name made from its topic
            frames[t] = t.strip("/").replace("/", "_")
    try:
        return format_for_ros(cal, tf, base_frame=base_frame, frames=frames, rt_vehicle_lidar0=rt_vehicle_lidar0,
                              tf_name=str(bag))
    except InputError:  # no base_link <- lidar0 anywhere: lidar0's frame is the root
        ref = frames[cal["reference"]]
        ros = format_for_ros(cal, None, base_frame=ref, frames=frames, rt_vehicle_lidar0=np.zeros(6))
        del ros["transforms"][ref]
        ros["base"]["source"] = f"nothing ({bag} has no /tf_static path {base_frame} <- {ref}): the tree is rooted at {ref}"
        return ros


def write_aligned_mcap(bags, calibration, out, *, snapshots=None, topics=None, base_frame: str = "base_link",
                       rt_vehicle_lidar0=None, force: bool = False) -> dict:
    """Write ``out`` (one .mcap file: a ROS 2 bag without its metadata.yaml) with /tf_static from
    ``calibration`` (its --out directory) and the clouds and images of the chosen snapshots.

    ``bags``: files, globs or directories (api.expand_bags); ``snapshots``: snapshot indices
    (as calibration.yaml's snapshots.list numbers them) or bag names, default every bag;
    ``topics``: the sensors to include, default all of the calibration's. ``out`` must not
    exist unless ``force`` (which replaces a file). Returns
    ``{"path", "frames": {topic: frame_id}, "tf": [(parent, child, T)], "snapshots": [...],
    "base_source"}``.
    """
    from .api import expand_bags
    from .outputs.results import load_result
    from .sim.bag_writer import BagWriter
    from .types import Image, LidarScan

    cal = load_result(calibration)
    paths = expand_bags(bags)
    chosen = _choose(paths, cal, snapshots)
    sensors = {s["topic"]: s for s in cal["sensors"]}
    topics = list(topics or sensors)
    unknown = [t for t in topics if t not in sensors]
    if unknown:
        raise InputError(f"{unknown[0]} is not a sensor of the calibration in {calibration}")
    ros = tf_tree(cal, chosen[0][1], base_frame=base_frame, rt_vehicle_lidar0=rt_vehicle_lidar0)
    data_frame = {e["topic"]: f for f, e in ros["transforms"].items()
                  if e.get("optical") or sensors[e["topic"]]["kind"] == "lidar"}
    data_frame.setdefault(cal["reference"], ros["base"]["child_frame"])  # the root when nothing is above lidar0
    edges = [(e["parent_frame"], f, np.asarray(e["T_parent_child"], float)) for f, e in ros["transforms"].items()]
    if ros["base"]["parent_frame"] != ros["base"]["child_frame"] and ros["base"]["child_frame"] not in ros["transforms"]:
        edges.insert(0, (ros["base"]["parent_frame"], ros["base"]["child_frame"], np.asarray(ros["base"]["T"], float)))

    out = Path(out)
    if out.suffix != ".mcap":
        raise InputError(f"--mcap {out}: name the file *.mcap")
    if out.is_dir() or (out.exists() and not force):
        raise InputError(f"{out}: exists; choose a new --mcap file (or --force to replace a file)")
    if not out.parent.is_dir():
        raise InputError(f"{out}: its directory {out.parent} does not exist")
    written, stamps, pending = [], [], []
    for index, bag, stamp in chosen:
        msgs = snapshot_messages(bag, topics, stamp)
        if not msgs:
            raise InputError(f"{bag}: no message on {', '.join(topics)}")
        pending.append((index, bag, msgs))
        stamps += [m.stamp_ns for m in msgs.values()]
    # rosbag2 writes a directory (the .mcap + metadata.yaml) next to out; the .mcap alone moves into
    # place at the end, so a failure leaves no half-written file
    with tempfile.TemporaryDirectory(prefix=f".{out.name}.clcgraph-tmp-", dir=out.parent) as tmp:
        bag_dir = Path(tmp) / out.stem
        with BagWriter(bag_dir, format="ros2-mcap") as w:
            w.write_tf_static(edges, stamp_ns=min(stamps))  # first, so a player has it before any data
            for index, bag, msgs in pending:
                for t, m in msgs.items():
                    if isinstance(m, LidarScan):
                        keep = m.valid
                        scan = LidarScan(t, m.stamp_ns, m.points[keep], np.ones(int(keep.sum()), bool),
                                         None if m.intensity is None else m.intensity[keep],
                                         None if m.ring is None else m.ring[keep])
                        w.write_pointcloud(t, scan, frame_id=data_frame[t], layout="velodyne")
                    elif isinstance(m, Image):
                        enc = "bgr8" if m.pixels.ndim == 3 else ("mono16" if m.pixels.dtype == np.uint16 else "mono8")
                        topic = t[: -len("/compressed")] if t.endswith("/compressed") else t  # written raw
                        w.write_image(topic, Image(topic, m.stamp_ns, m.pixels, enc), frame_id=data_frame[t])
                written.append({"index": index, "bag": bag.name, "topics": sorted(msgs)})
        os.replace(next(bag_dir.glob("*.mcap")), out)
    log.info("wrote %s: %d snapshots, /tf_static with %d transforms", out, len(written), len(edges))
    return {"path": out, "frames": {t: data_frame[t] for t in topics}, "tf": edges,
            "snapshots": written, "base_source": ros["base"]["source"]}
