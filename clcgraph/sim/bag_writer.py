"""Write ROS1 / ROS2 bags (PointCloud2, Image, CompressedImage, /tf_static) with rosbags.

SYNOPSIS
    from clcgraph.sim.bag_writer import BagWriter
    with BagWriter("out.bag", format="ros1", compress=True) as w:
        w.write_tf_static([("base_link", "lidar0", T_base_lidar0)], stamp_ns=0)
        w.write_pointcloud("/lidar0/points", scan, frame_id="lidar0", layout="ouster")
        w.write_image("/cam0/image", image, frame_id="cam0", compressed="png")

No ROS installation is needed: messages are built from rosbags' typestores
(ROS1 Noetic / ROS2 Humble) and serialized by rosbags. The log time of a message is its
header stamp, or with ``log_delays=LogDelays()`` when a driver would publish it: a LIDAR
scan after its last point (about one rotation after its scan-start stamp) plus a few ms,
a camera frame 20-35 ms after its stamp (mid-exposure), so log order differs from stamp
order across topics, as in real recordings. Field layouts mimic the real drivers:

- ``layout="velodyne"``: unorganised (height 1; ``organised=True``: height = rings,
  width = columns, from ``scan.shape``), velodyne_pointcloud's PointXYZIRT
  (invalid points as NaN):
  x y z @0,4,8 (float32), 4 bytes pad, intensity @16 (float32), ring @20 (uint16),
  time @24 (float32, s relative to the stamp), point_step 32.
- ``layout="ouster"``: organised (height = rings, width = columns), ouster_ros' point:
  x y z @0,4,8, pad, intensity @16 (float32), t @20 (uint32 ns), reflectivity @24
  (uint16), ring @26 (uint16), ambient @28 (uint16), range @32 (uint32 mm),
  point_step 48; invalid points are written as (0,0,0) with range 0.
- ``layout="pcl_xyzi"``: a PCL filter node's output (pcl::PointXYZI): unorganised and dense
  (invalid points dropped), x y z @0,4,8, pad, intensity @16 (float32), point_step 32: no ring,
  no time.
- ``layout="pcl_xyz"``: the same as pcl::PointXYZ (a voxel filter's, say): x y z @0,4,8, pad,
  point_step 16: no intensity either.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..types import Image, LidarScan

logger = logging.getLogger(__name__)

FORMATS = ("ros1", "ros2-sqlite3", "ros2-mcap")

# sensor_msgs/PointField datatypes
_INT8, _UINT8, _INT16, _UINT16, _INT32, _UINT32, _FLOAT32, _FLOAT64 = range(1, 9)

# (name, offset, datatype, numpy type) per layout, and the point_step
LAYOUTS = {
    "velodyne": (
        [("x", 0, _FLOAT32), ("y", 4, _FLOAT32), ("z", 8, _FLOAT32),
         ("intensity", 16, _FLOAT32), ("ring", 20, _UINT16), ("time", 24, _FLOAT32)],
        32,
    ),
    "ouster": (
        [("x", 0, _FLOAT32), ("y", 4, _FLOAT32), ("z", 8, _FLOAT32),
         ("intensity", 16, _FLOAT32), ("t", 20, _UINT32), ("reflectivity", 24, _UINT16),
         ("ring", 26, _UINT16), ("ambient", 28, _UINT16), ("range", 32, _UINT32)],
        48,
    ),
    # Hesai's drivers (PointXYZIT): each point's absolute time in float64 seconds, the ring
    # numbered from the top beam down (sim/lidar.py numbers it so)
    "hesai": (
        [("x", 0, _FLOAT32), ("y", 4, _FLOAT32), ("z", 8, _FLOAT32),
         ("intensity", 16, _FLOAT32), ("timestamp", 24, _FLOAT64), ("ring", 32, _UINT16)],
        48,
    ),
    # what a PCL filter node (crop box, voxel) republishes: pcl::PointXYZI, no ring or time
    "pcl_xyzi": (
        [("x", 0, _FLOAT32), ("y", 4, _FLOAT32), ("z", 8, _FLOAT32), ("intensity", 16, _FLOAT32)],
        32,
    ),
    # pcl::PointXYZ: no intensity either
    "pcl_xyz": ([("x", 0, _FLOAT32), ("y", 4, _FLOAT32), ("z", 8, _FLOAT32)], 16),
}
_NP = {_INT8: "i1", _UINT8: "u1", _INT16: "i2", _UINT16: "u2", _INT32: "i4",
       _UINT32: "u4", _FLOAT32: "f4", _FLOAT64: "f8"}

_IMAGE_CHANNELS = {"mono8": (1, "u1"), "8UC1": (1, "u1"), "mono16": (1, "u2"),
                   "16UC1": (1, "u2"), "bgr8": (3, "u1"), "rgb8": (3, "u1"),
                   "bgra8": (4, "u1"), "rgba8": (4, "u1"),
                   **{f"bayer_{p}8": (1, "u1") for p in ("rggb", "bggr", "gbrg", "grbg")}}


@dataclass(frozen=True)
class LogDelays:
    """How long after its stamp a driver logs a message (s), uniform in each [lo, hi].

    A LIDAR scan: after its last point (``time_s`` max, else ``lidar_rotation_s``) plus
    ``lidar_s``; a camera frame: ``camera_s`` after its stamp. Seeded: the same bytes each run.
    """

    lidar_s: tuple = (0.002, 0.012)
    lidar_rotation_s: float = 0.1
    camera_s: tuple = (0.020, 0.035)
    seed: int = 0


def _quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion (x, y, z, w) of a (3,3) rotation matrix."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat()


def _latched_qos():
    """ROS 2's /tf_static QoS: reliable, transient local, keep last 1."""
    from rosbags.rosbag2.metadata import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    forever = QosTime(sec=0, nsec=0)
    return Qos(history=QosHistory.KEEP_LAST, depth=1, reliability=QosReliability.RELIABLE,
               durability=QosDurability.TRANSIENT_LOCAL, deadline=forever, lifespan=forever,
               liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=forever,
               avoid_ros_namespace_conventions=False)


class BagWriter:
    """A context manager writing one bag: ``format`` is "ros1", "ros2-sqlite3" or "ros2-mcap".

    ``compress=True``: lz4 chunk compression for ROS1 bags; for ROS2, the storage file compressed
    with zstd as a whole (``ros2 bag record --compression-mode file --compression-format zstd``:
    ``*.db3.zstd`` / ``*.mcap.zstd``).
    The ROS1 path is a file (``x.bag``); a ROS2 path is a directory that must not exist.
    ``log_delays``: log times as a driver's (``LogDelays``); None: log time = stamp.
    ``clock_offsets_ns``: {topic: offset}: that topic's header stamps on another clock (e.g. an
    Ouster's default TIME_FROM_INTERNAL_OSC: seconds since the sensor booted), log times unchanged.
    """

    def __init__(self, path, *, format: str = "ros1", compress: bool = False,
                 log_delays: LogDelays | None = None, clock_offsets_ns: dict | None = None):
        from rosbags.typesys import Stores, get_typestore

        if format not in FORMATS:
            raise InputError(f"bag format {format!r} unknown; use one of {', '.join(FORMATS)}")
        self.path = Path(path)
        self.format = format
        self.compress = compress
        self._ros1 = format == "ros1"
        self.typestore = get_typestore(Stores.ROS1_NOETIC if self._ros1 else Stores.ROS2_HUMBLE)
        if "tf2_msgs/msg/TFMessage" not in self.typestore.types:  # Noetic's store lacks it
            from rosbags.typesys import get_types_from_msg

            self.typestore.register(get_types_from_msg(
                "geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
        self.log_delays = log_delays
        self.clock_offsets_ns = dict(clock_offsets_ns or {})
        self._delay_rng = np.random.default_rng(log_delays.seed) if log_delays else None
        self._writer = None
        self._connections: dict[str, object] = {}
        self._seq: dict[str, int] = {}

    # context manager -----------------------------------------------------------------
    def __enter__(self) -> "BagWriter":
        if self._ros1:
            from rosbags.rosbag1 import Writer

            self._writer = Writer(self.path)
            if self.compress:
                self._writer.set_compression(Writer.CompressionFormat.LZ4)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer
            from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

            plugin = StoragePlugin.MCAP if self.format == "ros2-mcap" else StoragePlugin.SQLITE3
            self._writer = Writer(self.path, version=9, storage_plugin=plugin)
            if self.compress:
                self._writer.set_compression(CompressionMode.FILE, CompressionFormat.ZSTD)
        self._writer.open()
        return self

    def __exit__(self, *exc) -> None:
        self._writer.close()

    # helpers ------------------------------------------------------------------------
    def _conn(self, topic: str, msgtype: str):
        if topic not in self._connections:
            extra = {}
            if topic == "/tf_static":  # latched, as tf2 publishes it, so a late subscriber (RViz) still gets it
                extra = {"latching": 1} if self._ros1 else {"offered_qos_profiles": [_latched_qos()]}
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=self.typestore, **extra
            )
        conn = self._connections[topic]
        if conn.msgtype != msgtype:
            raise InputError(f"topic {topic} already holds {conn.msgtype}, not {msgtype}")
        return conn

    def _header(self, topic: str, stamp_ns: int, frame_id: str):
        T = self.typestore.types
        stamp_ns = int(stamp_ns) + self.clock_offsets_ns.get(topic, 0)
        stamp = T["builtin_interfaces/msg/Time"](
            sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000)
        )
        if self._ros1:
            seq = self._seq.get(topic, 0)
            self._seq[topic] = seq + 1
            return T["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=frame_id)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def _delay_ns(self, lo_hi, after_s: float = 0.0) -> int:
        if self.log_delays is None:
            return 0
        return int(round((after_s + self._delay_rng.uniform(*lo_hi)) * 1e9))

    def _write(self, topic: str, msgtype: str, msg, stamp_ns: int) -> None:
        conn = self._conn(topic, msgtype)
        if self._ros1:
            raw = self.typestore.serialize_ros1(msg, msgtype)
        else:
            raw = self.typestore.serialize_cdr(msg, msgtype)
        self._writer.write(conn, int(stamp_ns), raw)

    # messages -----------------------------------------------------------------------
    def write_pointcloud(self, topic: str, scan: LidarScan, *, frame_id: str,
                         layout: str = "velodyne", big_endian: bool = False, organised: bool = False) -> None:
        """Write ``scan`` as a sensor_msgs/PointCloud2 stamped ``scan.stamp_ns``.

        layout "velodyne": unorganised unless ``organised`` (then, like "ouster", it needs
        ``scan.shape``); "ouster": organised, needs ``scan.shape`` =
        (rings, columns) with points row-major; "hesai": as velodyne, times absolute (float64 s);
        "pcl_xyzi" ("pcl_xyz"): x, y, z (, intensity) of the valid points. Invalid points
        (``~scan.valid``) keep NaN in the velodyne layout and (0,0,0) in the ouster layout, so the reader's valid
        mask equals ``scan.valid``. Coordinates and times are stored as float32 (ouster
        time as uint32 ns). Missing ring / time / intensity are written as zeros.
        """
        if layout not in LAYOUTS:
            raise InputError(f"pointcloud layout {layout!r} unknown; use {', '.join(LAYOUTS)}")
        fields, point_step = LAYOUTS[layout]
        if layout.startswith("pcl_"):  # dense: a filter drops the invalid points (and the cloud's layout)
            keep = np.asarray(scan.valid, bool)
            scan = dataclasses.replace(scan, points=np.asarray(scan.points)[keep], valid=keep[keep], shape=None,
                                       ring=None, intensity=None if scan.intensity is None else
                                       np.asarray(scan.intensity)[keep],
                                       time_s=None if scan.time_s is None else np.asarray(scan.time_s)[keep])
        n = len(scan.points)
        if layout == "ouster" or organised:
            if scan.shape is None or scan.shape[0] * scan.shape[1] != n:
                raise InputError(f"{topic}: an organised cloud needs scan.shape = (rings, columns)")
            height, width = scan.shape
        else:
            height, width = 1, n
        bo = ">" if big_endian else "<"
        dtype = np.dtype({
            "names": [f[0] for f in fields],
            "formats": [bo + _NP[f[2]] for f in fields],
            "offsets": [f[1] for f in fields],
            "itemsize": point_step,
        })
        arr = np.zeros(n, dtype=dtype)
        pts = np.asarray(scan.points, dtype=np.float64)
        valid = np.asarray(scan.valid, dtype=bool)
        zeros = np.zeros(n)
        ring = scan.ring if scan.ring is not None else zeros
        time_s = scan.time_s if scan.time_s is not None else zeros
        intensity = scan.intensity if scan.intensity is not None else zeros
        if layout == "ouster":
            pts = np.where(valid[:, None], pts, 0.0)
            arr["t"] = np.round(np.asarray(time_s) * 1e9).astype(np.uint32)
            rng_mm = np.round(np.linalg.norm(pts, axis=1) * 1000.0)
            arr["range"] = np.where(valid, rng_mm, 0).astype(np.uint32)
            arr["reflectivity"] = np.clip(np.asarray(intensity), 0, 65535).astype(np.uint16)
        else:
            pts = np.where(valid[:, None], pts, np.nan)  # the driver's invalid marker
        if "time" in arr.dtype.names:
            arr["time"] = time_s
        if "timestamp" in arr.dtype.names:
            arr["timestamp"] = scan.stamp_ns // 1_000_000_000 + (scan.stamp_ns % 1_000_000_000 * 1e-9 + np.asarray(time_s))
        arr["x"], arr["y"], arr["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
        if "intensity" in arr.dtype.names:
            arr["intensity"] = intensity
        if "ring" in arr.dtype.names:
            arr["ring"] = np.asarray(ring).astype(np.uint16)

        T = self.typestore.types
        msgtype = "sensor_msgs/msg/PointCloud2"
        pf = T["sensor_msgs/msg/PointField"]
        msg = T[msgtype](
            header=self._header(topic, scan.stamp_ns, frame_id),
            height=height,
            width=width,
            fields=[pf(name=name, offset=off, datatype=dt, count=1) for name, off, dt in fields],
            is_bigendian=bool(big_endian),
            point_step=point_step,
            row_step=point_step * width,
            data=np.frombuffer(arr.tobytes(), dtype=np.uint8),
            is_dense=bool(valid.all()),
        )
        last_point_s = float(np.max(time_s)) if scan.time_s is not None and n else \
            (self.log_delays.lidar_rotation_s if self.log_delays else 0.0)
        delay = self._delay_ns(self.log_delays.lidar_s, last_point_s) if self.log_delays else 0
        self._write(topic, msgtype, msg, scan.stamp_ns + delay)

    def write_image(self, topic: str, image: Image, *, frame_id: str,
                    compressed: str | None = None) -> None:
        """Write ``image`` as sensor_msgs/Image (``compressed=None``) or CompressedImage.

        Raw: ``image.encoding`` is used as is (pixels in that encoding's channel order;
        colour pixels of the clcgraph Image are BGR, so write colour as "bgr8").
        ``compressed`` "png" or "jpeg": encoded with OpenCV from BGR / mono pixels.
        """
        T = self.typestore.types
        header = self._header(topic, image.stamp_ns, frame_id)
        px = np.ascontiguousarray(image.pixels)
        if compressed is None:
            if image.encoding not in _IMAGE_CHANNELS:
                raise InputError(f"{topic}: cannot write image encoding {image.encoding!r}")
            nch, kind = _IMAGE_CHANNELS[image.encoding]
            h, w = px.shape[:2]
            px = px.astype(np.dtype("<" + kind), copy=False)
            step = w * nch * px.dtype.itemsize
            msgtype = "sensor_msgs/msg/Image"
            msg = T[msgtype](
                header=header, height=h, width=w, encoding=image.encoding,
                is_bigendian=0, step=step,
                data=np.frombuffer(px.tobytes(), dtype=np.uint8),
            )
        else:
            import cv2

            if compressed not in ("png", "jpeg"):
                raise InputError(f"{topic}: compression {compressed!r} unknown; use png or jpeg")
            ok, buf = cv2.imencode(".png" if compressed == "png" else ".jpg", px)
            if not ok:
                raise InputError(f"{topic}: OpenCV could not encode the image as {compressed}")
            msgtype = "sensor_msgs/msg/CompressedImage"
            msg = T[msgtype](header=header, format=compressed,
                             data=np.asarray(buf, dtype=np.uint8).reshape(-1))
        delay = self._delay_ns(self.log_delays.camera_s) if self.log_delays else 0
        self._write(topic, msgtype, msg, image.stamp_ns + delay)

    def write_camera_info(self, topic: str, *, stamp_ns: int, frame_id: str, size: tuple[int, int], K,
                          distortion_model: str, D) -> None:
        """Write one sensor_msgs/CameraInfo (K (3,3), D, ``size`` (width, height); R identity, P = [K 0])."""
        T = self.typestore.types
        K = np.asarray(K, float).reshape(3, 3)
        fields = {"D": np.asarray(D, float), "K": K.ravel(), "R": np.eye(3).ravel(), "P": np.c_[K, np.zeros(3)].ravel()}
        if not self._ros1:  # ROS 2 names them in lower case
            fields = {k.lower(): v for k, v in fields.items()}
        msgtype = "sensor_msgs/msg/CameraInfo"
        msg = T[msgtype](header=self._header(topic, stamp_ns, frame_id), height=int(size[1]), width=int(size[0]),
                         distortion_model=distortion_model, **fields, binning_x=0, binning_y=0,
                         roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                                   do_rectify=False))
        self._write(topic, msgtype, msg, stamp_ns)

    def write_tf_static(self, transforms, *, stamp_ns: int) -> None:
        """Write one tf2_msgs/TFMessage on /tf_static.

        transforms: list of (parent_frame, child_frame, T_parent_child (4,4)).
        """
        T = self.typestore.types
        tfs = []
        for parent, child, Tpc in transforms:
            Tpc = np.asarray(Tpc, dtype=np.float64)
            q = _quaternion_xyzw(Tpc[:3, :3])
            tfs.append(T["geometry_msgs/msg/TransformStamped"](
                header=self._header("/tf_static", stamp_ns, parent),
                child_frame_id=child,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](
                        x=float(Tpc[0, 3]), y=float(Tpc[1, 3]), z=float(Tpc[2, 3])),
                    rotation=T["geometry_msgs/msg/Quaternion"](
                        x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
                ),
            ))
        msgtype = "tf2_msgs/msg/TFMessage"
        self._write("/tf_static", msgtype, T[msgtype](transforms=tfs), stamp_ns)


def split_ros1_bag(path, every_s: float) -> list[Path]:
    """Cut a ROS1 bag into consecutive files of ``every_s`` seconds of log time each, as
    `rosbag record --split --duration` leaves a long recording (``NAME_0.bag``, ``NAME_1.bag``, ...,
    beside it, each new: rosbags' Writer overwrites nothing; the original is left as it is). A
    latched topic (/tf_static) is in the first file only, as its one message arrived when the
    recording started. Returns the files' paths."""
    from rosbags.rosbag1 import Reader, Writer

    path = Path(path)
    out: list[Path] = []
    with Reader(path) as r:
        t0 = r.start_time
        writers: dict[int, tuple] = {}  # part -> (Writer, {connection id: its connection there})
        try:
            for conn, t, raw in r.messages():
                part = int((t - t0) // int(every_s * 1e9))
                if part not in writers:
                    p = path.with_name(f"{path.stem}_{part}{path.suffix}")
                    w = Writer(p)
                    w.open()
                    writers[part] = (w, {})
                    out.append(p)
                w, conns = writers[part]
                if conn.id not in conns:
                    conns[conn.id] = w.add_connection(conn.topic, conn.msgtype, msgdef=conn.msgdef.data,
                                                      md5sum=conn.digest, callerid=conn.ext.callerid,
                                                      latching=conn.ext.latching)
                w.write(conns[conn.id], t, raw)
        finally:
            for w, _ in writers.values():
                w.close()
    return out
