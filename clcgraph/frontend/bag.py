"""Read ROS1 and ROS2 (sqlite3, mcap) bags without ROS: messages, tf_static, summaries.

SYNOPSIS
    from clcgraph.frontend import bag
    info = bag.bag_info("session.bag")                   # topics, types, counts, spans
    for m in bag.read_messages(["a.bag", "b.bag"], ["/lidar/points", "/cam/image"]):
        m.bag, m.topic, m.index, m.stamp_ns, m.data      # data: LidarScan | Image
    first = bag.first_messages("a.bag", ["/lidar/points"])   # {topic: LidarScan | Image}
    lead = bag.leading_messages("a.bag", ["/lidar/points"], {"/lidar/points": 5})  # {topic: [first 5]}
    tf = bag.read_tf_static(["a.bag"])
    T_base_lidar = tf.lookup("base_link", "lidar0")      # (4,4) T_target_source
    bag.frame_id("a.bag", "/lidar/points")               # header.frame_id

A bag path is a ROS1 ``.bag`` file, or a ROS2 bag directory (its ``.db3`` / ``.mcap``
file is accepted too and means its directory). Bags are read with rosbags' AnyReader
and a default typestore (Noetic for ROS1, Humble for ROS2) for bags that do not
carry their message definitions. Time is header.stamp; log time only for messages
without a header. Drivers log a message after its stamp (a LIDAR scan about one rotation
after its scan-start stamp, a camera frame tens of ms after mid-exposure), so log order
is not stamp order across topics: every reader here yields messages in header-stamp
order (``stamp_ordered``), never in log order. Supported message types: sensor_msgs/PointCloud2 -> LidarScan,
sensor_msgs/Image and CompressedImage -> Image, tf2_msgs/TFMessage on /tf_static.

Every problem becomes an InputError (missing file, absent topic) or DataError
(unreadable/truncated/empty bag, wrong message type, undecodable message) with one
line naming the bag, the topic and the message index. No rosbags traceback escapes.
"""

from __future__ import annotations

import dataclasses
import functools
import glob
import heapq
import logging
import threading
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Iterable, Iterator, Mapping, NamedTuple, Sequence

import numpy as np

from ..errors import DataError, InputError
from ..geometry import invert_T
from ..types import Image, LidarScan
from .images import decode_image
from .pointcloud import decode_pointcloud2, stamp_ns_of

logger = logging.getLogger(__name__)

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TFMESSAGE = "tf2_msgs/msg/TFMessage"
DECODABLE = (POINTCLOUD2, IMAGE, COMPRESSED_IMAGE)

# header stamps may lag the log time; the reader's time window is widened by this much
_LOG_TIME_SLACK_NS = 5_000_000_000
# stamp_ordered: a message is logged at most this long after its stamp (drivers: 0.02-0.2 s)
MAX_LOG_DELAY_NS = 1_000_000_000


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a bag. Stamps are log times in ns (None when the topic is empty)."""

    topic: str
    msgtype: str  # e.g. "sensor_msgs/msg/PointCloud2"
    count: int
    first_ns: int | None
    last_ns: int | None


@dataclass(frozen=True)
class BagInfo:
    """Summary of one bag: its topics, and the log-time span of all its messages."""

    path: Path
    topics: tuple[TopicInfo, ...]
    start_ns: int | None
    end_ns: int | None

    @property
    def duration_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) * 1e-9

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self.topics)

    def topic(self, name: str) -> TopicInfo:
        for t in self.topics:
            if t.topic == name:
                return t
        raise InputError(
            f"{self.path}: topic {name} not in bag (available: {', '.join(t.topic for t in self.topics) or 'none'})"
        )


@dataclass(frozen=True)
class Message:
    """One decoded message. ``index`` counts the messages of ``topic`` in ``bag`` from 0."""

    bag: Path
    topic: str
    index: int
    stamp_ns: int  # header.stamp (log time for header-less messages)
    data: LidarScan | Image


class TfTree:
    """Static transforms from /tf_static; ``lookup`` chains through parents either way.

    ``edges`` maps (parent, child) -> T_parent_child (4,4).
    """

    def __init__(self, edges: dict[tuple[str, str], np.ndarray] | None = None):
        self.edges: dict[tuple[str, str], np.ndarray] = dict(edges or {})

    @property
    def frames(self) -> set[str]:
        return {f for e in self.edges for f in e}

    def add(self, parent: str, child: str, T_parent_child: np.ndarray) -> None:
        self.edges[(parent, child)] = np.asarray(T_parent_child, dtype=np.float64)

    def lookup(self, target_frame: str, source_frame: str) -> np.ndarray:
        """(4,4) T_target_source mapping points in source_frame into target_frame."""
        if target_frame == source_frame:
            return np.eye(4)
        nbrs: dict[str, list[tuple[str, np.ndarray]]] = {}
        for (p, c), T in self.edges.items():
            nbrs.setdefault(p, []).append((c, T))
            nbrs.setdefault(c, []).append((p, invert_T(T)))
        for f in (target_frame, source_frame):
            if f not in nbrs:
                raise DataError(
                    f"tf_static: frame {f!r} unknown (frames: {', '.join(sorted(nbrs)) or 'none'})"
                )
        # breadth-first from the target, accumulating T_target_frame
        found = {target_frame: np.eye(4)}
        todo = deque([target_frame])
        while todo:
            a = todo.popleft()
            for b, T_a_b in nbrs[a]:
                if b not in found:
                    found[b] = found[a] @ T_a_b
                    if b == source_frame:
                        return found[b]
                    todo.append(b)
        raise DataError(f"tf_static: no chain of transforms from {source_frame!r} to {target_frame!r}")


# tf_static holds a vehicle's frames; a kilometre apart is already absurd, 10^6 m is garbage
_MAX_TF_TRANSLATION_M = 1e6


def _T_from_transform(tr, where: str = "tf_static") -> np.ndarray:
    """(4,4) from a geometry_msgs/Transform; DataError (naming ``where``) for non-finite values or
    a quaternion tf2 itself would refuse (|q|^2 more than 0.01 from 1)."""
    from scipy.spatial.transform import Rotation

    q = np.array([tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w], float)
    t = np.array([tr.translation.x, tr.translation.y, tr.translation.z], float)
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))):
        raise DataError(f"{where}: non-finite transform (translation {t.tolist()}, rotation {q.tolist()})")
    if np.any(np.abs(t) > _MAX_TF_TRANSLATION_M):
        raise DataError(f"{where}: translation {t.tolist()} m is beyond any vehicle "
                        f"(more than {_MAX_TF_TRANSLATION_M:g} m)")
    if np.any(np.abs(q) > 2) or abs(q @ q - 1.0) > 0.01:
        raise DataError(f"{where}: rotation quaternion {q.tolist()} is not normalized (|q| = {np.linalg.norm(q):.4g})")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q).as_matrix()
    T[:3, 3] = t
    return T


# --------------------------------------------------------------------------- opening

def _one_line(e: BaseException) -> str:
    s = str(e).strip().splitlines()
    return f"{type(e).__name__}: {s[0]}" if s else type(e).__name__


# A ROS2 bag's storage files, inside its directory (compressed whole: ros2 bag record --compression-mode file)
ROS2_STORAGE_SUFFIXES = (".db3", ".mcap", ".db3.zstd", ".mcap.zstd")


def _bag_root(path) -> Path:
    p = Path(path)
    if not p.exists():
        if glob.has_magic(str(p)):  # a pattern where one bag is wanted (several go through api.expand_bags)
            n = len(glob.glob(str(p)))
            raise InputError(f"{p}: a pattern ({n} match{'es' if n != 1 else ''}), not one bag; give one bag file")
        raise InputError(f"{p}: no such bag file or directory")
    if p.is_file() and p.name.endswith(ROS2_STORAGE_SUFFIXES):
        return p.parent
    return p


# (ROS2?, the bag's message definitions) -> the rosbags typestore built from them
_TYPESTORES: dict[tuple, object] = {}
_TYPESTORES_LOCK = threading.Lock()
_DEFAULT_TYPESTORES: dict[bool, object] = {}


@functools.cache
def _reader_class():
    """rosbags' AnyReader, sharing one typestore among bags with the same message definitions.

    Opening a bag parses the message definitions it carries and compiles a deserializer per type
    (~40 ms of CPU per bag, more than reading a small bag's messages); the bags of one capture
    carry the same definitions, so they are parsed and compiled once per process. A bag with new
    definitions (or digests) is opened the stock way first, which also checks its digests.
    """
    from rosbags.highlevel import AnyReader

    class SharedTypesReader(AnyReader):
        def _open(self) -> None:
            for reader in self.readers:
                self.stack.enter_context(reader)
            connections = [c for r in self.readers for c in r.connections]
            key = (self.is2, tuple(sorted({(c.msgtype, c.msgdef, c.digest) for c in connections},
                                          key=repr)))
            with _TYPESTORES_LOCK:
                typestore = _TYPESTORES.get(key)
            if typestore is None:
                with AnyReader(self.paths, default_typestore=self.default_typestore) as stock:
                    typestore = stock.typestore
                with _TYPESTORES_LOCK:
                    if len(_TYPESTORES) >= 64:  # a fleet of differently recorded bags: stay bounded
                        _TYPESTORES.clear()
                    _TYPESTORES[key] = typestore
            self.connections = connections
            self.typestore = typestore

    return SharedTypesReader


class _Bag:
    """An open AnyReader over one bag, with errors turned into one-line DataErrors."""

    def __init__(self, path):
        self.path = _bag_root(path)
        self._other_clock: dict[str, bool] = {}  # topic -> its stamps on another clock (``stamp``)
        from rosbags.typesys import Stores, get_typestore

        ros1 = self.path.is_file()
        if not ros1 and not (self.path / "metadata.yaml").is_file() and any(self.path.glob("*.bag")):
            raise InputError(f"{self.path}: a directory of ROS1 bags, not one bag; give one of its .bag files")
        if ros1 not in _DEFAULT_TYPESTORES:  # for bags without message definitions
            _DEFAULT_TYPESTORES[ros1] = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        try:
            self.reader = _reader_class()([self.path], default_typestore=_DEFAULT_TYPESTORES[ros1])
            self.reader.open()
        except Exception as e:  # rosbags raises many kinds on broken files
            raise DataError(f"{self.path}: cannot read bag ({_one_line(e)}); is it truncated or not a bag?") from None
        if not self.reader.connections or sum(c.msgcount for c in self.reader.connections) == 0:
            self.reader.close()
            raise DataError(f"{self.path}: bag is empty (no messages)")

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        try:
            self.reader.close()
        except Exception:  # closing a broken bag must not mask the real error
            pass

    def topics(self) -> dict[str, str]:
        return {c.topic: c.msgtype for c in self.reader.connections}

    def connections(self, topics: Iterable[str], *, msgtypes: Sequence[str] = DECODABLE, missing_ok: bool = False):
        """The connections of ``topics``; a topic the bag lacks is an InputError unless ``missing_ok``
        (a capture's bags: one without a sensor's messages holds none of them, as a recording split
        into files may leave a short last file)."""
        have = self.topics()
        conns = []
        for t in topics:
            if t not in have:
                if missing_ok:
                    continue
                raise InputError(
                    f"{self.path}: topic {t} not in bag (available: {', '.join(sorted(have))})"
                )
            if have[t] not in msgtypes:
                what = ("not a LIDAR (PointCloud2) or camera (Image, CompressedImage) topic"
                        if tuple(msgtypes) == DECODABLE else f"expected one of {', '.join(msgtypes)}")
                raise DataError(f"{self.path}: topic {t} has type {have[t]}: {what}")
            conns += [c for c in self.reader.connections if c.topic == t]
        return conns

    def raw(self, conns, start_ns=None, stop_ns=None):
        """Yield (connection, index in topic, logtime, deserialized message)."""
        counters: dict[str, int] = {}
        it = self.reader.messages(connections=conns, start=start_ns, stop=stop_ns)
        while True:
            try:
                conn, logtime, rawdata = next(it)
            except StopIteration:
                return
            except Exception as e:
                raise DataError(f"{self.path}: cannot read messages ({_one_line(e)}); is the bag truncated?") from None
            i = counters.get(conn.topic, 0)
            counters[conn.topic] = i + 1
            try:
                msg = self.reader.deserialize(rawdata, conn.msgtype)
            except Exception as e:
                raise DataError(
                    f"{self.path}: topic {conn.topic} message {i}: cannot deserialize ({_one_line(e)})"
                ) from None
            yield conn, i, logtime, msg

    def stamp(self, topic: str, msg, logtime: int) -> int:
        """The message's time: its header stamp, or its log time where the topic's stamps are on
        another clock (judged on its first message in this bag: ``_OTHER_CLOCK_NS``)."""
        s = _stamp(msg, logtime)
        other = self._other_clock.get(topic)
        if other is None:
            other = self._other_clock[topic] = abs(int(logtime) - s) > _OTHER_CLOCK_NS
            if other:
                _warn_other_clock(topic, (int(logtime) - s) * 1e-9)
        return int(logtime) if other else s

    def decode(self, conn, i, msg, stamp: int):
        """The decoded message, timed ``stamp`` (``stamp``'s: the log time where the topic's stamps
        are on another clock)."""
        data = self._decode(conn, i, msg)
        return data if data.stamp_ns == stamp else dataclasses.replace(data, stamp_ns=stamp)

    def _decode(self, conn, i, msg):
        try:
            if conn.msgtype == POINTCLOUD2:
                return decode_pointcloud2(msg, topic=conn.topic)
            return decode_image(msg, topic=conn.topic)
        except DataError as e:
            raise DataError(f"{self.path}: topic {conn.topic} message {i}: {e}") from None
        except Exception as e:
            raise DataError(
                f"{self.path}: topic {conn.topic} message {i}: cannot decode ({_one_line(e)})"
            ) from None


# ---------------------------------------------------------------------------- API

def bag_info(path) -> BagInfo:
    """Summary of one bag: topics with msgtype, message count and first/last log time."""
    with _Bag(path) as b:
        r = b.reader
        topics = []
        for topic in sorted({c.topic for c in r.connections}):
            conns = [c for c in r.connections if c.topic == topic]
            topics.append(TopicInfo(topic, conns[0].msgtype, sum(c.msgcount for c in conns), None, None))
        # per-topic spans need a pass over the index (no deserialization)
        first: dict[str, int] = {}
        last: dict[str, int] = {}
        try:
            for conn, t, _ in r.messages():
                first.setdefault(conn.topic, t)
                last[conn.topic] = t
        except Exception as e:
            raise DataError(f"{b.path}: cannot read messages ({_one_line(e)}); is the bag truncated?") from None
        topics = tuple(
            TopicInfo(ti.topic, ti.msgtype, ti.count, first.get(ti.topic), last.get(ti.topic))
            for ti in topics
        )
        return BagInfo(b.path, topics, min(first.values(), default=None), max(last.values(), default=None))


@dataclass(frozen=True)
class CameraInfo:
    """A camera's calibration as its driver publishes it (sensor_msgs/CameraInfo)."""

    K: np.ndarray  # (3,3)
    D: np.ndarray
    distortion_model: str
    size: tuple[int, int]  # (width, height)
    where: str  # "BAG: topic T"


def camera_info_topic(image_topic: str) -> str:
    """The CameraInfo topic beside an image topic, as image_transport names them:
    /ns/image_raw and /ns/image_raw/compressed -> /ns/camera_info."""
    base = image_topic[: -len("/compressed")] if image_topic.endswith("/compressed") else image_topic
    return base.rsplit("/", 1)[0] + "/camera_info"


def camera_info(paths, image_topic: str) -> CameraInfo:
    """The first CameraInfo on ``camera_info_topic(image_topic)`` in the bags ``paths``; InputError
    naming the topic (and the CameraInfo topics there are) if none has it."""
    topic = camera_info_topic(image_topic)
    others = set()
    for path in paths:
        with _Bag(path) as b:
            have = b.topics()
            others |= {t for t, m in have.items() if m == CAMERA_INFO}
            if have.get(topic) != CAMERA_INFO:
                continue
            msg = next((m for _, _, _, m in b.raw(b.connections([topic], msgtypes=(CAMERA_INFO,)))), None)
            if msg is None:
                continue
            # ROS 1 names them K, D; ROS 2 k, d
            K, D = (np.asarray(getattr(msg, n, getattr(msg, n.lower(), ())), float).reshape(-1) for n in ("K", "D"))
            return CameraInfo(K.reshape(3, 3) if K.size == 9 else np.full((3, 3), np.nan), D, str(msg.distortion_model),
                              (int(msg.width), int(msg.height)), f"{b.path}: topic {topic}")
    raise InputError(f"no camera model file given for {image_topic} and no {topic} in the bags"
                     + (f" (CameraInfo topics: {', '.join(sorted(others))})" if others else "")
                     + ": give its camera model (.cameramodel or ROS calibration .yaml) in its place among the models")


def log_span(path) -> tuple[int, int]:
    """(first, last) log time (ns) of the bag at ``path``, from its index (nothing is read)."""
    index = bag_index(path)
    return index.start_ns, index.end_ns


class BagIndex(NamedTuple):
    """What a bag's index says without reading a message: its log-time span and messages per topic."""

    start_ns: int
    end_ns: int
    counts: Mapping[str, int]


def bag_index(path) -> BagIndex:
    """The index of the bag at ``path``, read once per version of its files: opening a bag parses
    its whole index, and a capture's reading asks each bag's span and counts several times
    (grouping split recordings, telling a bag per pose from a continuous one)."""
    root = _bag_root(path)
    files = [root] if root.is_file() else sorted(f for f in root.iterdir() if f.is_file())
    stats = [(f.name, f.stat()) for f in files]
    return _bag_index(root.resolve(), tuple((name, st.st_ino, st.st_mtime_ns, st.st_size) for name, st in stats))


@functools.lru_cache(maxsize=1024)
def _bag_index(root: Path, version: tuple) -> BagIndex:
    with _Bag(root) as b:
        counts: dict[str, int] = {}
        for c in b.reader.connections:
            counts[c.topic] = counts.get(c.topic, 0) + int(c.msgcount)
        return BagIndex(int(b.reader.start_time), int(b.reader.end_time), MappingProxyType(counts))


# A sensor whose header stamps differ from the recorder's log times by more than this is on
# another clock (an Ouster's default TIME_FROM_INTERNAL_OSC counts from its boot, a camera its own
# time, an unsynchronised computer's clock seconds off): drivers log within a second of their
# stamps, which is what stamp order assumes (MAX_LOG_DELAY_NS): a topic stamped seconds earlier
# would be dropped as logged too late, one stamped seconds later paired with the others' older
# messages. Its messages are then timed by their log times (a driver's delay, tens of ms, late).
_OTHER_CLOCK_NS = MAX_LOG_DELAY_NS
_WARNED_CLOCK: set = set()
_WARNED_CLOCK_LOCK = threading.Lock()


def _warn_other_clock(topic: str, offset_s: float) -> None:
    with _WARNED_CLOCK_LOCK:
        if topic in _WARNED_CLOCK:
            return
        _WARNED_CLOCK.add(topic)
    # a note, not a warning: handled, nothing for the user to do (and a refused run prints one line)
    logger.info("%s: header stamps %.4g s from the bag's log times (the sensor's own clock, not ROS time: an "
                "Ouster's TIME_FROM_INTERNAL_OSC, an unsynchronised clock): its messages are timed by their log times",
                topic, -offset_s)


def _stamp(msg, logtime: int) -> int:
    header = getattr(msg, "header", None)
    return stamp_ns_of(header) if header is not None else int(logtime)


def stamp_ordered(items: Iterable[tuple], *, max_delay_ns: int = MAX_LOG_DELAY_NS,
                  where: str = "") -> Iterator[tuple]:
    """Re-order a log-time-ordered stream into header-stamp order.

    items: (log_time_ns, stamp_ns, topic, payload) in log-time order; yields
    (stamp_ns, topic, payload) in stamp order (ties in log order). A message is held until
    the log time has passed its stamp by ``max_delay_ns``: every later message was logged
    later, so (if logged at most that long after its stamp) it has a later stamp. A message
    stamped before one already yielded (logged longer than that after its stamp, or stamped
    on another clock) cannot be placed: it is skipped, and a warning per topic says so.
    """
    heap: list = []
    last = None
    late: dict[str, list[int]] = {}
    for n, (log_ns, stamp_ns, topic, payload) in enumerate(items):
        if last is not None and stamp_ns < last:
            late.setdefault(topic, []).append(int(log_ns) - int(stamp_ns))
            continue
        heapq.heappush(heap, (stamp_ns, n, topic, payload))
        while heap and heap[0][0] < log_ns - max_delay_ns:
            last, _, t, p = heapq.heappop(heap)
            yield last, t, p
    while heap:
        last, _, t, p = heapq.heappop(heap)
        yield last, t, p
    for topic, delays in late.items():
        logger.warning("%s%s: %d messages logged more than %.1f s after their header stamp (up to %.1f s; "
                       "stamps on another clock?) could not be put in stamp order and were skipped",
                       f"{where}: " if where else "", topic, len(delays), max_delay_ns * 1e-9, max(delays) * 1e-9)


def _iter_bag(path, topics, start_ns, stop_ns, missing_ok: bool = False) -> Iterator[Message]:
    with _Bag(path) as b:
        conns = b.connections(topics, missing_ok=missing_ok)
        lo = None if start_ns is None else max(0, start_ns - _LOG_TIME_SLACK_NS)
        hi = None if stop_ns is None else stop_ns + _LOG_TIME_SLACK_NS

        def stamped():
            for conn, i, logtime, msg in b.raw(conns, lo, hi):
                stamp = b.stamp(conn.topic, msg, logtime)
                if (start_ns is None or stamp >= start_ns) and (stop_ns is None or stamp < stop_ns):
                    yield logtime, stamp, conn.topic, (conn, i, msg)

        # decoded only once in order: the window holds deserialized messages, not point arrays
        for stamp, topic, (conn, i, msg) in stamp_ordered(stamped(), where=str(b.path)):
            yield Message(b.path, topic, i, stamp, b.decode(conn, i, msg, stamp))


def read_messages(paths, topics: Sequence[str], *, start_ns: int | None = None,
                  stop_ns: int | None = None, missing_ok: bool = False) -> Iterator[Message]:
    """Decoded messages of ``topics`` from all ``paths``, merged in header-stamp order.

    paths: one path or a sequence. Only messages with start_ns <= stamp < stop_ns are
    yielded (either bound None = open). Each bag is re-ordered from log order into stamp
    order (``stamp_ordered``), and the bags are merged.
    ``index`` is counted over all of the topic's messages in that bag, so it names the
    message in errors even with a time window. Every bag is opened (and checked for
    the topics, unless ``missing_ok``: ``_Bag.connections``) before the first message is yielded.
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    topics = list(topics)
    for p in paths:  # fail early, before any message is produced
        with _Bag(p) as b:
            b.connections(topics, missing_ok=missing_ok)
    streams = [_iter_bag(p, topics, start_ns, stop_ns, missing_ok) for p in paths]
    yield from heapq.merge(*streams, key=lambda m: m.stamp_ns)


def message_count(paths, topic: str) -> int:
    """Messages of ``topic`` in all ``paths``, from the bags' indexes (nothing is read)."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    return sum(bag_index(p).counts.get(topic, 0) for p in paths)


def first_messages(path, topics: Sequence[str]) -> dict[str, LidarScan | Image]:
    """{topic: decoded first message of that topic in this bag} (one snapshot per bag)."""
    return {t: ms[0] for t, ms in leading_messages(path, topics, {}).items()}


def leading_messages(path, topics: Sequence[str], counts: dict[str, int], *,
                     missing_ok: bool = False) -> dict[str, list[LidarScan | Image]]:
    """{topic: the first ``counts.get(topic, 1)`` decoded messages of that topic in this bag}, in
    stamp order (topics without messages left out; ``missing_ok``: ``_Bag.connections``)."""
    out: dict[str, list] = {}
    with _Bag(path) as b:
        conns = b.connections(topics, missing_ok=missing_ok)
        for conn in conns:
            if conn.topic in out:
                continue
            n = max(1, int(counts.get(conn.topic, 1)))
            got = []
            for c, i, logtime, msg in b.raw([c for c in conns if c.topic == conn.topic]):
                got.append(b.decode(c, i, msg, b.stamp(c.topic, msg, logtime)))
                if len(got) >= n:
                    break
            if got:
                out[conn.topic] = sorted(got, key=lambda m: m.stamp_ns)
    return {t: out[t] for t in topics if t in out}


def first_raw_message(path, topic: str):
    """The first rosbags-deserialized message of ``topic`` (e.g. to show a cloud's fields)."""
    with _Bag(path) as b:
        conns = b.connections([topic], msgtypes=tuple(b.topics().values()))
        for _, _, _, msg in b.raw(conns):
            return msg
    raise DataError(f"{path}: topic {topic} has no messages")


def frame_id(path, topic: str) -> str:
    """header.frame_id of the first message of ``topic`` in the bag at ``path``."""
    msg = first_raw_message(path, topic)
    header = getattr(msg, "header", None)
    if header is None:
        raise DataError(f"{path}: topic {topic} messages have no header")
    return str(header.frame_id)


def decode_tf_message(msg, *, where: str) -> list[tuple[str, str, np.ndarray]]:
    """[(parent, child, T_parent_child (4,4))] of a tf2_msgs/TFMessage; DataError naming ``where``
    and the frames for a transform tf2 would refuse (empty or equal names, NaN, unnormalized)."""
    out = []
    for ts in msg.transforms:
        parent, child = str(ts.header.frame_id), str(ts.child_frame_id)
        here = f"{where}: {parent!r} -> {child!r}"
        if not parent or not child or parent == child:
            raise DataError(f"{here}: a transform needs two different, non-empty frame names")
        out.append((parent, child, _T_from_transform(ts.transform, here)))
    return out


def read_tf_static(paths) -> TfTree:
    """All /tf_static transforms of ``paths`` (later bags override earlier ones)."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    tree = TfTree()
    for p in paths:
        with _Bag(p) as b:
            conns = [c for c in b.reader.connections if c.topic == "/tf_static"]
            if not conns:
                logger.debug("%s: no /tf_static", b.path)
                continue
            for conn, i, _, msg in b.raw(conns):
                if conn.msgtype != TFMESSAGE:
                    raise DataError(f"{b.path}: /tf_static has type {conn.msgtype}, expected {TFMESSAGE}")
                for parent, child, T in decode_tf_message(msg, where=f"{b.path}: /tf_static message {i}"):
                    tree.add(parent, child, T)
    return tree
