"""PointCloud2 decoding: unusual layouts, endianness, padding, invalid points, malformed messages."""

from types import SimpleNamespace

import numpy as np
import pytest

from clcgraph.errors import DataError
from clcgraph.frontend.pointcloud import decode_pointcloud2

F32, F64, U8, U16, U32, I32 = 7, 8, 2, 4, 6, 5
_NP = {2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
STAMP_NS = 1_700_000_123_456_789_000


def _msg(values: dict, fields, *, point_step, height, width, row_step=None, big=False, stamp_ns=STAMP_NS):
    """A PointCloud2-like object: fields = [(name, offset, datatype)], values name -> (h*w,) array."""
    row_step = row_step or point_step * width
    bo = ">" if big else "<"
    dt = np.dtype({"names": [f[0] for f in fields], "formats": [bo + _NP[f[2]] for f in fields],
                   "offsets": [f[1] for f in fields], "itemsize": point_step})
    arr = np.zeros(height * width, dtype=dt)
    for k, v in values.items():
        arr[k] = v
    rows = np.frombuffer(arr.tobytes(), np.uint8).reshape(height, width * point_step)
    buf = np.full((height, row_step), 0xAB, np.uint8)  # garbage in the row padding
    buf[:, : width * point_step] = rows
    return SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=STAMP_NS // 10**9, nanosec=STAMP_NS % 10**9), frame_id="l"),
        height=height, width=width, is_bigendian=big, point_step=point_step, row_step=row_step,
        fields=[SimpleNamespace(name=n, offset=o, datatype=d, count=1) for n, o, d in fields],
        data=buf.reshape(-1), is_dense=False,
    )


@pytest.mark.parametrize("big", [False, True])
def test_unusual_layout_float64_padding_rowstep(big):
    rng = np.random.default_rng(1)
    h, w = 3, 7
    n = h * w
    xyz = rng.normal(scale=10, size=(n, 3))
    inten = rng.integers(0, 65535, n)
    chan = rng.integers(0, 255, n)
    trel = rng.uniform(0, 0.1, n)
    tabs = STAMP_NS * 1e-9 + trel
    # extra fields first, float64 xyz in the middle, a 'timestamp' absolute float64 time
    fields = [("foo", 0, U8), ("x", 8, F64), ("y", 16, F64), ("z", 24, F64), ("bar", 32, I32),
              ("reflectivity", 36, U16), ("channel", 38, U8), ("timestamp", 40, F64)]
    m = _msg({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "foo": 7, "bar": -3,
              "reflectivity": inten, "channel": chan, "timestamp": tabs},
             fields, point_step=56, height=h, width=w, row_step=56 * w + 13, big=big)
    s = decode_pointcloud2(m, topic="/odd")
    assert s.topic == "/odd" and s.stamp_ns == STAMP_NS and s.shape == (h, w)
    np.testing.assert_array_equal(s.points, xyz)
    assert s.valid.all()
    np.testing.assert_array_equal(s.intensity, inten.astype(np.float32))
    np.testing.assert_array_equal(s.ring, chan)
    # absolute float64 seconds near 1.7e9 carry ~2.4e-7 s resolution
    np.testing.assert_allclose(s.time_s, trel, atol=5e-7)


def test_velodyne_like_unorganised_with_invalid_points():
    n = 10
    xyz = np.tile([1.0, 2.0, 3.0], (n, 1)).astype(np.float32)
    xyz[1] = [np.nan, 0, 0]
    xyz[2] = [np.inf, 1, 1]
    xyz[3] = [0, 0, 0]
    xyz[4] = [1, -np.inf, 0]
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("intensity", 16, F32),
              ("ring", 20, U16), ("time", 24, F32)]
    t = np.linspace(0, 0.1, n, dtype=np.float32)
    m = _msg({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "ring": np.arange(n) % 16, "time": t},
             fields, point_step=32, height=1, width=n)
    s = decode_pointcloud2(m, topic="/v")
    np.testing.assert_array_equal(s.valid, [True, False, False, False, False] + [True] * 5)
    assert s.shape is None
    np.testing.assert_array_equal(s.ring, np.arange(n) % 16)
    np.testing.assert_array_equal(s.time_s, t.astype(np.float64))


def test_ouster_like_big_endian_t_ns_and_ring_from_rows():
    h, w = 4, 5
    n = h * w
    rng = np.random.default_rng(2)
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    xyz[7] = 0
    t_ns = rng.integers(0, 100_000_000, n)
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("t", 20, U32), ("range", 32, U32)]
    m = _msg({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "t": t_ns}, fields,
             point_step=48, height=h, width=w, big=True)
    s = decode_pointcloud2(m, topic="/os")
    np.testing.assert_array_equal(s.points, xyz.astype(np.float64))
    assert not s.valid[7] and s.valid.sum() == n - 1
    np.testing.assert_array_equal(s.ring, np.repeat(np.arange(h), w))  # no ring field: row index
    np.testing.assert_allclose(s.time_s, t_ns * 1e-9, rtol=0, atol=1e-15)
    assert s.intensity is None


def test_livox_offset_time():
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("line", 12, U8), ("offset_time", 16, U32)]
    m = _msg({"x": 1, "y": 2, "z": 3, "line": [0, 1, 2], "offset_time": [0, 1000, 2000]}, fields,
             point_step=20, height=1, width=3)
    s = decode_pointcloud2(m, topic="/livox")
    np.testing.assert_array_equal(s.ring, [0, 1, 2])
    np.testing.assert_allclose(s.time_s, [0, 1e-6, 2e-6])


_BASIC = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32)]


@pytest.mark.parametrize(
    "case, pattern",
    [
        ("point_step", "point_step 8 too small"),
        ("truncated", "fewer than"),
        ("no_z", "no 'z' field"),
        ("datatype", "unsupported datatype 42"),
        ("row_step", "row_step"),
    ],
)
def test_malformed_is_one_line_dataerror(case, pattern):
    m = _msg({"x": 1, "y": 2, "z": 3}, _BASIC, point_step=16, height=2, width=4)
    if case == "point_step":
        m.point_step = 8
        m.row_step = 32
    elif case == "truncated":
        m.data = m.data[: len(m.data) // 2]
    elif case == "no_z":
        m.fields = m.fields[:2]
    elif case == "datatype":
        m.fields[2].datatype = 42
    elif case == "row_step":
        m.row_step = 16
    with pytest.raises(DataError) as e:
        decode_pointcloud2(m, topic="/bad/topic")
    msg = str(e.value)
    assert "\n" not in msg and "/bad/topic" in msg and pattern in msg, msg


def test_lying_sizes_allocate_nothing():
    """height 3e8 x width 0 without a ring field is an empty scan (np.repeat of 3e8 rows was 2.3 GB);
    10^9 points claimed in a 64-byte buffer is a DataError before any allocation."""
    import tracemalloc

    m = _msg({"x": 1, "y": 2, "z": 3}, _BASIC, point_step=16, height=2, width=2)
    tracemalloc.start()
    m.height, m.width, m.row_step = 300_000_000, 0, 0
    s = decode_pointcloud2(m, topic="/l")
    assert len(s.points) == 0 and s.ring is None and s.shape is None
    m.height, m.width, m.row_step = 1_000_000_000, 1, 16
    with pytest.raises(DataError, match="/l.*64 bytes, fewer than height 1000000000"):
        decode_pointcloud2(m, topic="/l")
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 100_000, peak


def test_garbage_values_are_invalid_points_without_warnings():
    m = _msg({"x": 1, "y": 2, "z": 3}, _BASIC, point_step=16, height=1, width=4)
    m.data = m.data.copy()
    m.data[:12] = 0xFF  # signalling-NaN float32 bytes
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        s = decode_pointcloud2(m, topic="/l")
    np.testing.assert_array_equal(s.valid, [False, True, True, True])
