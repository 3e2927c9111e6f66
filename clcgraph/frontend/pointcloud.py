"""Decode sensor_msgs/PointCloud2 of any field layout into a LidarScan.

SYNOPSIS
    scan = decode_pointcloud2(msg, topic="/lidar/points")
    scan.points[scan.valid]          # (K,3) float64, sensor frame

The layout is read from the message: ``fields`` (offset, datatype), ``point_step``,
``row_step`` (row padding), ``height`` x ``width`` and ``is_bigendian``. The bytes are
viewed through a numpy structured dtype (no loop over points). Recognised fields:

- x, y, z (any numeric datatype; float32 or float64 in practice), required;
- intensity, else reflectivity;
- ring, else channel, else line; an organised cloud without one gets ring = row index;
- per-point time, converted to float64 seconds relative to header.stamp:
  ``time`` (float s relative, Velodyne), ``t`` (uint32 ns relative, Ouster),
  ``offset_time`` (uint32 ns relative, Livox), ``timestamp`` (float64 s absolute,
  Hesai; the header stamp is subtracted).

NaN, inf and (0,0,0) points are flagged ``valid=False`` and kept, so organised clouds
keep their (height, width) order (``scan.shape``).
"""

from __future__ import annotations

import numpy as np

from ..errors import DataError
from ..types import LidarScan
from .lidar_preprocess import finite_rows

# sensor_msgs/PointField datatype -> numpy kind and size
_DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}

_RING_NAMES = ("ring", "channel", "line")
_INTENSITY_NAMES = ("intensity", "reflectivity")
_TIME_NAMES = ("time", "t", "offset_time", "timestamp")


def stamp_ns_of(header) -> int:
    """Integer ns of a std_msgs/Header's stamp (ROS1 and ROS2 messages alike)."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def describe_fields(msg) -> list[tuple[str, int, int, int]]:
    """[(name, offset, datatype, count)] of a PointCloud2's fields, for show-bag."""
    return [(f.name, int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields]


def _structured_view(msg, topic: str, wanted: set[str]) -> tuple[np.ndarray, dict]:
    """(height, width) structured array view over msg.data holding the ``wanted`` fields."""
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    bo = ">" if msg.is_bigendian else "<"
    fields = {}
    for f in msg.fields:
        if f.name in fields:
            continue  # duplicate names: the first wins
        fields[f.name] = f
    for f in fields.values():
        if int(f.datatype) not in _DATATYPES:
            if f.name in wanted:
                raise DataError(
                    f"PointCloud2 on {topic}: field {f.name!r} has unsupported datatype {f.datatype}"
                )
            continue
        size = int(np.dtype(_DATATYPES[int(f.datatype)]).itemsize) * max(int(f.count), 1)
        if int(f.offset) + size > point_step:
            raise DataError(
                f"PointCloud2 on {topic}: point_step {point_step} too small for field "
                f"{f.name!r} at offset {f.offset} ({size} bytes)"
            )
    for name in "xyz":
        if name not in fields:
            raise DataError(
                f"PointCloud2 on {topic}: no {name!r} field (fields: "
                f"{', '.join(fields) or 'none'})"
            )
    if point_step <= 0 or width * point_step > row_step:
        raise DataError(
            f"PointCloud2 on {topic}: row_step {row_step} smaller than width {width} x point_step {point_step}"
        )
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if data.size < height * row_step:
        raise DataError(
            f"PointCloud2 on {topic}: data has {data.size} bytes, fewer than height {height} x row_step {row_step}"
        )
    use = [n for n in fields if n in wanted and int(fields[n].datatype) in _DATATYPES]
    if height * width == 0:  # nothing to view (and point_step may be anything): an empty cloud
        return np.zeros((0, 0), dtype=[(n, bo + _DATATYPES[int(fields[n].datatype)]) for n in use]), fields
    dtype = np.dtype({
        "names": use,
        "formats": [bo + _DATATYPES[int(fields[n].datatype)] for n in use],
        "offsets": [int(fields[n].offset) for n in use],
        "itemsize": point_step,
    })
    view = np.ndarray(shape=(height, width), dtype=dtype, buffer=data,
                      strides=(row_step, point_step))
    return view, fields


def decode_pointcloud2(msg, *, topic: str) -> LidarScan:
    """A LidarScan from a (rosbags-deserialized) sensor_msgs/PointCloud2.

    Returns points (N,3) float64 with N = height*width in row-major order, valid (N,),
    intensity (N,) float32 or None, ring (N,) int or None, time_s (N,) float64 seconds
    relative to header.stamp or None, and shape (height, width) when height > 1.
    Raises DataError (one line naming the topic) on a malformed message.
    """
    wanted = {"x", "y", "z", *_RING_NAMES, *_INTENSITY_NAMES, *_TIME_NAMES}
    view, fields = _structured_view(msg, topic, wanted)
    stamp_ns = stamp_ns_of(msg.header)
    height, width = view.shape
    flat = view.reshape(-1)
    names = set(view.dtype.names)
    # garbage bytes (signalling NaNs, a false is_bigendian) must not warn: bad points are flagged invalid
    with np.errstate(invalid="ignore", over="ignore"):
        points = np.stack([flat["x"], flat["y"], flat["z"]], axis=-1).astype(np.float64)
        intensity = next((flat[n].astype(np.float32) for n in _INTENSITY_NAMES if n in names), None)
        time_s = None
        if "time" in names:
            time_s = flat["time"].astype(np.float64)
        elif "t" in names:
            time_s = flat["t"].astype(np.float64) * 1e-9
        elif "offset_time" in names:
            time_s = flat["offset_time"].astype(np.float64) * 1e-9
        elif "timestamp" in names:
            sec, nsec = divmod(stamp_ns, 1_000_000_000)
            time_s = (flat["timestamp"].astype(np.float64) - sec) - nsec * 1e-9
        ring = next((flat[n].astype(np.int64) for n in _RING_NAMES if n in names), None)
    nonzero = points != 0.0  # (by columns: numpy's reductions over a short axis cost 5x)
    valid = finite_rows(points) & (nonzero[:, 0] | nonzero[:, 1] | nonzero[:, 2])
    organised = height > 1 and width > 0  # an empty cloud of "3e8 rows" is just empty
    if ring is None and organised:
        ring = np.repeat(np.arange(height, dtype=np.int64), width)

    return LidarScan(
        topic=topic,
        stamp_ns=stamp_ns,
        points=points,
        valid=valid,
        intensity=intensity,
        ring=ring,
        time_s=time_s,
        shape=(height, width) if organised else None,
    )
