"""Fuzz the message decoders with randomly mutated real messages (issue 13, item 6).

Messages of a small simulated ROS1 bag (a Velodyne-layout and an Ouster-layout PointCloud2,
mono8 and bgr8 Images, JPEG and PNG CompressedImages, a /tf_static TFMessage) are serialized,
mutated at random (bytes flipped or set, 32-bit words overwritten with extreme values — mostly
in the first 256 bytes, where the sizes live, or in a compressed image's header —,
truncated, extended, chunks duplicated), deserialized by rosbags as the bag reader does, and
decoded by clcgraph's decoders. Every case must end in a decoded message or a DataError: any
other exception (or a RuntimeWarning), a case over 1 s, or an allocation beyond
``MEMORY_FACTOR`` x the larger of the message and its genuine decoded size counts as a failure.
A message rosbags cannot deserialize is counted apart: the bag reader turns that into a
DataError naming bag, topic and message index.

    python -m bench fuzz          # 10^5 cases: prints cases run / DataErrors / anything else (must be 0)
"""

from __future__ import annotations

import tempfile
import time
import tracemalloc
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

N_CASES = 100_000
MAX_CASE_S = 1.0
MEMORY_FACTOR = 4
MEMORY_SLACK = 256 << 10  # interpreter noise: small temporaries of any decode
_EXTREME_WORDS = (0, 1, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF, 0xFFFF, 0x10000, 300_000_000)


@dataclass
class Sample:
    kind: str  # a short name for the table
    topic: str
    msgtype: str
    raw: bytes
    header_span: tuple[int, int]  # where the sizes live: mutated more often
    decoded_bytes: int  # memory of the genuine decoded message


@dataclass
class Tally:
    cases: int = 0
    decoded: int = 0
    data_errors: int = 0
    undeserializable: int = 0
    other: int = 0
    slow: int = 0
    over_memory: int = 0
    worst_ratio: float = 0.0
    worst_s: float = 0.0
    failures: list = field(default_factory=list)  # (kind, mutation, what), the first few


def _decoder(msgtype: str):
    from clcgraph.frontend.bag import decode_tf_message
    from clcgraph.frontend.images import decode_image
    from clcgraph.frontend.pointcloud import decode_pointcloud2

    if msgtype.endswith("PointCloud2"):
        return lambda msg, topic: decode_pointcloud2(msg, topic=topic)
    if msgtype.endswith("TFMessage"):
        return lambda msg, topic: decode_tf_message(msg, where=topic)
    return lambda msg, topic: decode_image(msg, topic=topic)


def _decoded_bytes(obj) -> int:
    if isinstance(obj, list):  # tf
        return sum(T.nbytes for _, _, T in obj)
    return sum(v.nbytes for v in vars(obj).values() if isinstance(v, np.ndarray))


def sample_messages(workdir: Path):
    """(samples, typestore): the serialized messages of a small bag written by clcgraph's
    simulator writer, and the bag's typestore (it knows every message type in the bag)."""
    import cv2
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from clcgraph.geometry import T_from_rt
    from clcgraph.sim.bag_writer import BagWriter
    from clcgraph.types import Image, LidarScan

    rng = np.random.default_rng(0)
    t0 = 1_700_000_000_000_000_000

    def scan(topic, rings, cols):
        elev = np.linspace(-0.25, 0.25, rings)[:, None]
        az = np.linspace(-np.pi, np.pi, cols, endpoint=False)[None, :]
        r = rng.uniform(2, 20, (rings, cols))
        p = np.stack([r * np.cos(elev) * np.cos(az), r * np.cos(elev) * np.sin(az),
                      r * np.sin(elev) * np.ones_like(az)], -1).reshape(-1, 3)
        return LidarScan(topic, t0, p, rng.uniform(size=len(p)) > 0.05, intensity=rng.uniform(0, 255, len(p)).astype(np.float32),
                         ring=np.repeat(np.arange(rings), cols), time_s=np.tile(np.linspace(0, 0.099, cols), rings),
                         shape=(rings, cols))

    board = (np.indices((48, 64)).sum(0) // 8 % 2 * 180 + 40).astype(np.uint8)
    noisy = np.clip(board + rng.normal(0, 6, board.shape), 0, 255).astype(np.uint8)
    colour = cv2.cvtColor(noisy, cv2.COLOR_GRAY2BGR)
    path = workdir / "fuzz.bag"
    with BagWriter(path, format="ros1") as w:
        w.write_tf_static([("base_link", "lidar0", np.eye(4)),
                           ("lidar0", "cam0", T_from_rt(np.array([0.1, -0.2, 0.3, 1.0, 2.0, 3.0])))], stamp_ns=t0)
        w.write_pointcloud("/velodyne", scan("/velodyne", 16, 360), frame_id="v", layout="velodyne")
        w.write_pointcloud("/ouster", scan("/ouster", 8, 128), frame_id="o", layout="ouster")
        w.write_image("/mono", Image("/mono", t0, noisy, "mono8"), frame_id="c")
        w.write_image("/bgr", Image("/bgr", t0, colour, "bgr8"), frame_id="c")
        w.write_image("/jpeg", Image("/jpeg", t0, colour, "bgr8"), frame_id="c", compressed="jpeg")
        w.write_image("/png", Image("/png", t0, noisy, "mono8"), frame_id="c", compressed="png")
    out = []
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS1_NOETIC)) as r:
        store = r.typestore
        for conn, _, raw in r.messages():
            raw = bytes(raw)
            msg = store.deserialize_ros1(raw, conn.msgtype)
            span = (0, 256)
            if conn.msgtype.endswith("CompressedImage"):  # the image header sits after the ROS header
                start = len(raw) - len(msg.data)
                span = (0, start + 700)
            decoded = _decoder(conn.msgtype)(msg, conn.topic)
            out.append(Sample(conn.topic.strip("/"), conn.topic, conn.msgtype, raw, span, _decoded_bytes(decoded)))
    return out, store


def mutate(raw: bytes, span: tuple[int, int], rng: np.random.Generator) -> tuple[bytes, str]:
    """One random mutation of ``raw`` -> (bytes, what was done)."""
    b = bytearray(raw)
    n = len(b)
    pick = rng.integers(8)
    lo, hi = (span[0], min(span[1], n)) if rng.random() < 0.7 else (0, n)

    def pos(width=1):
        return int(rng.integers(lo, max(lo + 1, hi - width + 1)))

    if pick <= 1:  # flip a few bits
        k = int(rng.integers(1, 9))
        for _ in range(k):
            b[pos()] ^= 1 << int(rng.integers(8))
        return bytes(b), f"flip {k} bits"
    if pick == 2:  # set a few bytes
        k = int(rng.integers(1, 5))
        for _ in range(k):
            b[pos()] = int(rng.choice([0, 0xFF, int(rng.integers(256))]))
        return bytes(b), f"set {k} bytes"
    if pick <= 4:  # an extreme 32-bit word (sizes, counts, steps, offsets, lengths)
        p = pos(4)
        word = int(rng.choice(_EXTREME_WORDS)) if rng.random() < 0.6 else int(rng.integers(2**32))
        b[p:p + 4] = word.to_bytes(4, "little" if rng.random() < 0.7 else "big")
        return bytes(b[:n]), f"word {word:#x} at {p}"
    if pick == 5:  # truncate
        cut = int(rng.integers(0, n))
        return bytes(b[:cut]), f"truncate to {cut}"
    if pick == 6:  # extend with garbage
        k = int(rng.integers(1, 4096))
        return bytes(b) + rng.integers(0, 256, k, dtype=np.uint8).tobytes(), f"extend by {k}"
    p, k = pos(), int(rng.integers(1, 64))  # duplicate a chunk in place
    return bytes(b[:p] + b[p:p + k] + b[p:]), f"duplicate {k} bytes at {p}"


def run(n_cases: int, *, seed: int = 0, samples=None) -> dict[str, Tally]:
    """Run ``n_cases`` mutations spread over the sample messages (``sample_messages``' result, made
    in a temporary directory when None) -> per message kind, a Tally."""
    from clcgraph.errors import DataError

    if samples is None:
        with tempfile.TemporaryDirectory() as d:
            samples = sample_messages(Path(d))
    samples, store = samples
    rng = np.random.default_rng(seed)
    tallies = {s.kind: Tally() for s in samples}
    decoders = {s.kind: _decoder(s.msgtype) for s in samples}
    was_tracing = tracemalloc.is_tracing()
    if not was_tracing:
        tracemalloc.start()
    try:
        for k in range(n_cases):
            s = samples[k % len(samples)]
            t = tallies[s.kind]
            data, what = mutate(s.raw, s.header_span, rng)
            t.cases += 1
            base = tracemalloc.get_traced_memory()[0]
            tracemalloc.reset_peak()
            t_start = time.perf_counter()
            outcome = None
            with warnings.catch_warnings():
                warnings.simplefilter("error")  # a RuntimeWarning on garbage is a failure too
                try:
                    msg = store.deserialize_ros1(data, s.msgtype)
                except Exception:
                    t.undeserializable += 1
                    msg = None
                if msg is not None:
                    try:
                        decoders[s.kind](msg, s.topic)
                        t.decoded += 1
                    except DataError as e:
                        t.data_errors += 1
                        if "\n" in str(e):
                            outcome = f"multi-line DataError: {str(e)[:200]!r}"
                    except Exception as e:  # noqa: BLE001 - exactly what the fuzz looks for
                        outcome = f"{type(e).__name__}: {str(e).splitlines()[0][:200] if str(e) else ''}"
            dt = time.perf_counter() - t_start
            peak = tracemalloc.get_traced_memory()[1] - base
            allowed = MEMORY_FACTOR * max(len(s.raw), s.decoded_bytes) + MEMORY_SLACK
            t.worst_ratio = max(t.worst_ratio, peak / max(len(s.raw), s.decoded_bytes))
            t.worst_s = max(t.worst_s, dt)
            if outcome:
                t.other += 1
            if dt > MAX_CASE_S:
                t.slow += 1
                outcome = outcome or f"took {dt:.2f} s"
            if peak > allowed:
                t.over_memory += 1
                outcome = outcome or f"allocated {peak} bytes (allowed {allowed})"
            if outcome and len(t.failures) < 5:
                t.failures.append((s.kind, what, outcome))
    finally:
        if not was_tracing:
            tracemalloc.stop()
    return tallies


def table(tallies: dict[str, Tally]) -> str:
    rows = [f"{'message':10s} {'cases':>7s} {'decoded':>8s} {'DataError':>10s} {'undeser.':>9s} {'other':>6s} "
            f"{'>1 s':>5s} {'>mem':>5s} {'worst s':>8s} {'peak/size':>9s}"]
    tot = Tally()
    for kind, t in tallies.items():
        rows.append(f"{kind:10s} {t.cases:7d} {t.decoded:8d} {t.data_errors:10d} {t.undeserializable:9d} {t.other:6d} "
                    f"{t.slow:5d} {t.over_memory:5d} {t.worst_s:8.3f} {t.worst_ratio:9.2f}")
        for f in ("cases", "decoded", "data_errors", "undeserializable", "other", "slow", "over_memory"):
            setattr(tot, f, getattr(tot, f) + getattr(t, f))
    rows.append(f"cases run {tot.cases}, decoded {tot.decoded}, DataErrors {tot.data_errors} "
                f"(+{tot.undeserializable} the bag reader reports as DataError), anything else {tot.other}, "
                f"over {MAX_CASE_S:g} s {tot.slow}, over memory {tot.over_memory}")
    for t in tallies.values():
        rows += [f"  FAILED {k}: {what}: {why}" for k, what, why in t.failures]
    return "\n".join(rows)


def main() -> str:
    return table(run(N_CASES))


if __name__ == "__main__":
    print(main())
