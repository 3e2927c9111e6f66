"""Snapshots: synchronized sets of sensor messages, each of one stationary board pose.

SYNOPSIS

    snaps, rejected = assemble_snapshots(bags, ["/lidar0"], ["/cam0"], SnapshotOptions())

Two capture schemes (the clc seed's):
- one bag per board pose (``decimation_period_s`` None): the first message of every
  topic in each bag, a LIDAR's first scan averaged with the next ones of the still scene (up to
  ``max_scans_averaged``: less range noise, one observation). A bag in which the scene moves
  and stops more than once is a continuous one, cut at the motion (``still_intervals``): one
  snapshot per still interval, from the messages nearest its centre (as many LIDAR scans,
  averaged); so a single continuous bag needs no setting;
- one continuous bag: periods of ``decimation_period_s`` from the first kept message
  (messages in header-stamp order, never log order: see ``frontend.bag``); per period and
  topic the message nearest the period's centre. Whether a period is usable rests on
  whether the scene moved around that time: the period is dropped (``Rejected``) if LIDAR
  range images a ``motion_window_s`` before and after the chosen scan differ by more than
  ``max_board_motion_m`` over a region (runs of >= 2 neighbouring cells on a ring,
  >= ``min_moving_cells`` such cells), or if a chosen message lies outside the interval
  that check covered (nothing says the board was still then).

``max_time_spread_s`` (None by default, as clc) additionally drops a snapshot whose
chosen messages span more than that, in both schemes.

Time values (``after``, ``before``, ``exclude_time_periods``): int seconds or
nanoseconds since the epoch (told apart by magnitude: >= 1e13 is ns), float seconds,
or a date string (ISO 8601 via ``datetime.fromisoformat``, else ``dateutil`` if
installed); a date without a timezone is taken as UTC. Messages are streamed: a
continuous bag holds at most 3 decoded messages per topic in memory (and the reader's
re-ordering window of undecoded ones).
"""

from __future__ import annotations

import datetime as _dt
import logging
import os
import re
from concurrent.futures import ThreadPoolExecutor
from decimal import Decimal, InvalidOperation
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator, Sequence

import numpy as np

from clcgraph.errors import InputError
from clcgraph.geometry import azimuth
from clcgraph.frontend.lidar_preprocess import finite_rows, ring_of, row_norms, small_unique
from clcgraph.types import Image, LidarScan, Rejected, Snapshot, names_bag

log = logging.getLogger(__name__)

_NS_THRESHOLD = 10**13  # ints at or above: ns since the epoch (1e13 s is year 318857)
AZIMUTH_BINS = 1800  # range-image resolution for motion detection (0.2 deg)


# ---------------------------------------------------------------- time parsing


def parse_time_ns(value) -> int:
    """ns since the epoch from an int (s or ns), a float (s) or a date string."""
    if isinstance(value, bool):
        raise InputError(f"bad time value {value!r}")
    if isinstance(value, (int, np.integer)):
        v = int(value)
        return v if abs(v) >= _NS_THRESHOLD else v * 10**9
    if isinstance(value, (float, np.floating)):
        # through the shortest decimal repr: 1700000000.25 -> exactly ...250000000 ns
        return int(Decimal(repr(float(value))) * 10**9)
    if isinstance(value, _dt.datetime):
        return _datetime_ns(value)
    if isinstance(value, str):
        s = value.strip()
        if re.fullmatch(r"[+-]?\d+", s):
            return parse_time_ns(int(s))
        try:
            float(s)
            return int(Decimal(s) * 10**9)
        except (ValueError, InvalidOperation):
            pass
        try:
            return _datetime_ns(_dt.datetime.fromisoformat(s))
        except ValueError:
            pass
        try:
            import dateutil.parser
        except ImportError:
            raise InputError(f"cannot parse time {value!r} (ISO 8601, or install python-dateutil)")
        try:
            return _datetime_ns(dateutil.parser.parse(s))
        except (ValueError, OverflowError):
            raise InputError(f"cannot parse time {value!r}")
    raise InputError(f"bad time value {value!r}: use s/ns since epoch or a date string")


def _datetime_ns(d: _dt.datetime) -> int:
    if d.tzinfo is None:
        d = d.replace(tzinfo=_dt.timezone.utc)
    delta = d - _dt.datetime(1970, 1, 1, tzinfo=_dt.timezone.utc)
    return (delta.days * 86400 + delta.seconds) * 10**9 + delta.microseconds * 1000


@dataclass(frozen=True)
class TimeFilter:
    """Which stamps to keep: ``after <= t < before`` and outside every excluded period."""

    after_ns: int | None = None
    before_ns: int | None = None
    exclude_ns: tuple[tuple[int, int], ...] = ()

    @classmethod
    def from_options(cls, options) -> "TimeFilter":
        ex = []
        for p in options.exclude_time_periods or []:
            if isinstance(p, str):
                p = p.split(",")
            if len(p) != 2:
                raise InputError(f"exclude_time_periods entry {p!r}: need [start, end]")
            a, b = parse_time_ns(p[0]), parse_time_ns(p[1])
            if b < a:
                raise InputError(f"exclude_time_periods entry {p!r}: end before start")
            ex.append((a, b))
        after = None if options.after is None else parse_time_ns(options.after)
        before = None if options.before is None else parse_time_ns(options.before)
        if after is not None and before is not None and before <= after:
            raise InputError(f"snapshots.after ({options.after}) is not before snapshots.before ({options.before}): "
                             "no message can be kept")
        return cls(after, before, tuple(ex))

    def why_not(self, stamp_ns: int) -> str | None:
        """None if the stamp is kept, else the reason."""
        if self.after_ns is not None and stamp_ns < self.after_ns:
            return "before the 'after' time"
        if self.before_ns is not None and stamp_ns >= self.before_ns:
            return "after the 'before' time"
        for a, b in self.exclude_ns:
            if a <= stamp_ns <= b:
                return "in an excluded time period"
        return None

    def keeps(self, stamps_ns: np.ndarray) -> np.ndarray:
        """(N,) bool mask of kept stamps."""
        t = np.asarray(stamps_ns, dtype=np.int64)
        k = np.ones(t.shape, bool)
        if self.after_ns is not None:
            k &= t >= self.after_ns
        if self.before_ns is not None:
            k &= t < self.before_ns
        for a, b in self.exclude_ns:
            k &= ~((t >= a) & (t <= b))
        return k


def time_spread_s(stamps_ns: Iterable[int]) -> float:
    s = list(stamps_ns)
    return (max(s) - min(s)) * 1e-9 if s else 0.0


# ---------------------------------------------------------------- motion detection


def range_image(scan: LidarScan, *, azimuth_bins: int = AZIMUTH_BINS) -> tuple[np.ndarray, np.ndarray]:
    """Per-(ring, azimuth bin) nearest range of a scan.

    Returns (ring_ids (R,), ranges (R, azimuth_bins)) with NaN where no valid point
    fell. Rings as the segmentation numbers them (lidar_preprocess.ring_of).
    """
    p = np.asarray(scan.points, float)
    ok = np.asarray(scan.valid, bool) & finite_rows(p)
    ring = ring_of(scan)[ok]
    p = p[ok]
    r = row_norms(p)
    az = azimuth(p)
    a = np.floor((az + np.pi) / (2 * np.pi) * azimuth_bins).astype(np.int64) % azimuth_bins
    rings, ri = small_unique(ring)
    img = np.full(len(rings) * azimuth_bins, np.inf)
    cell = ri * azimuth_bins + a
    # the nearest return per cell (np.minimum.at, a tenth of its cost): write every return, then
    # again those nearer than what their cell holds until none is (exact whichever write won)
    img[cell] = r
    k = np.flatnonzero(r < img[cell])
    while len(k):
        img[cell[k]] = r[k]
        k = k[r[k] < img[cell[k]]]
    img[np.isinf(img)] = np.nan
    return rings, img.reshape(len(rings), azimuth_bins)


def scene_motion(a: LidarScan, b: LidarScan, *, threshold_m: float, min_cells: int,
                 azimuth_bins: int = AZIMUTH_BINS) -> tuple[bool, float, int]:
    """Did something move between two scans of the same LIDAR?

    Cells (ring, azimuth) whose range changed (to the closest of the cell and its azimuth
    neighbours in the other scan) by more than max(threshold_m, 4 x the
    robust noise of the differences) count as changed if a ring neighbour changed too
    (isolated noise hits do not); motion if at least ``min_cells`` such cells.
    Returns (moved, median |change| of those cells in m, their count).
    """
    return motion_between(range_image(a, azimuth_bins=azimuth_bins), range_image(b, azimuth_bins=azimuth_bins),
                          threshold_m=threshold_m, min_cells=min_cells)


def motion_between(image_a, image_b, *, threshold_m: float, min_cells: int) -> tuple[bool, float, int]:
    """``scene_motion`` of two scans' ``range_image``s (each computed once when one scan is
    compared with many)."""
    (ra, ia), (rb, ib) = image_a, image_b
    common, ka, kb = np.intersect1d(ra, rb, return_indices=True)
    A, B = ia[ka], ib[kb]  # (R, A)
    # the change to the closest of the cell and its azimuth neighbours in the other scan:
    # returns near a bin edge land in either bin from one rotation to the next (encoder
    # jitter), which at a depth edge would otherwise look like motion
    with np.errstate(invalid="ignore"):
        d = None
        for s in (-1, 0, 1):  # the first of the closest, as an argmin over the three (which costs 2x)
            c = A - np.roll(B, s, axis=1)
            c[~np.isfinite(c)] = np.inf
            d = c if d is None else np.where(np.abs(c) < np.abs(d), c, d)
    d[~np.isfinite(d) | ~np.isfinite(A) | ~np.isfinite(B)] = np.nan
    fin = np.isfinite(d)
    if not np.any(fin):
        return False, 0.0, 0
    same = A - B  # the noise from the cells themselves (the closest-of-3 would underestimate it)
    noise = 1.4826 * np.median(np.abs(same[np.isfinite(same)]))
    thr = max(threshold_m, 4.0 * noise)
    ch = np.zeros(d.shape, bool)
    ch[fin] = np.abs(d[fin]) > thr
    run = ch & (np.roll(ch, 1, axis=1) | np.roll(ch, -1, axis=1))
    n = int(run.sum())
    mag = float(np.median(np.abs(d[run]))) if n else 0.0
    return n >= min_cells, mag, n


# ---------------------------------------------------------------- assembly


def parse_exclude_bag(spec: str | None, bags: Sequence[Path]) -> tuple[set[Path], set[Path], set[int]]:
    """``snapshots.exclude_bag`` -> (bags not to read, bags whose snapshots to drop, snapshot indices to drop).

    Comma-separated items, each a bag (its path, file name or stem) or a snapshot index: those
    snapshots are read and then dropped, keeping every index as calibration.yaml's
    ``snapshots.list`` numbers them without the exclusion (like ``replay --exclude``). If some
    item is neither, the whole text is a regex searched in each bag's path, and the matching
    bags are not read at all (clc's --exclude-bag).
    """
    if not spec:
        return set(), set(), set()
    bags = [Path(b) for b in bags]
    items = [x.strip() for x in spec.split(",") if x.strip()]

    def named(item: str) -> list[Path]:
        return [b for b in bags if names_bag(item, b)]

    if items and all(named(x) or x.isdigit() for x in items):
        return set(), {b for x in items for b in named(x)}, {int(x) for x in items if not named(x)}
    return {b for b in bags if re.search(spec, str(b)) is not None}, set(), set()


def drop_excluded(snaps: list[Snapshot], spec: str | None, bags: Sequence[Path]) -> tuple[list[Snapshot], list[Rejected]]:
    """The snapshots with those that ``spec`` names by bag or index emptied (no scans, no images:
    indices and stamps stay), and a Rejected per dropped snapshot. InputError for an index
    beyond the snapshots."""
    _, drop_bags, drop_idx = parse_exclude_bag(spec, bags)
    bad = sorted(k for k in drop_idx if k >= len(snaps))
    if bad:
        raise InputError(f"--exclude-bag {spec!r}: no snapshot {bad[0]} (the bags give {len(snaps)}, 0..{len(snaps) - 1})")
    out, rejected = [], []
    for s in snaps:
        if s.index in drop_idx or Path(s.bag) in drop_bags:
            rejected.append(Rejected(f"excluded by the user (exclude_bag {spec!r})", "snapshot", snapshot=s.index))
            s = Snapshot(index=s.index, stamp_ns=s.stamp_ns, source=s.source, bag=s.bag)
        out.append(s)
    return out, rejected


@dataclass
class _Period:
    """The few messages one period keeps per topic (streaming state)."""

    k: int
    ref_ns: int
    start_ns: int
    stop_ns: int
    # topic -> [best before ref - w, nearest to ref, best after ref + w] as (|dt|, msg)
    picks: dict = field(default_factory=dict)


def _consider(period: _Period, msg, window_ns: int) -> None:
    slots = period.picks.setdefault(msg.topic, [None, None, None])
    for i, target in enumerate((period.ref_ns - window_ns, period.ref_ns, period.ref_ns + window_ns)):
        dt = abs(msg.stamp_ns - target)
        if slots[i] is None or dt < slots[i][0]:
            slots[i] = (dt, msg)


def _finish_period(period: _Period, lidar_topics, camera_topics, options, source: str,
                   index: int, tfilter: TimeFilter = TimeFilter()) -> Snapshot | Rejected:
    chosen = {t: s[1][1] for t, s in period.picks.items()}
    where = f"{source} period {period.k} @{period.ref_ns * 1e-9:.3f}s"
    for a, b in tfilter.exclude_ns:
        if a < period.stop_ns and b >= period.start_ns:
            return Rejected(f"{where}: overlaps an excluded time period", "snapshot")
    if not chosen:
        return Rejected(f"{where}: no messages", "snapshot")
    spread = _spread_rejection(chosen.values(), options)
    if spread:
        return Rejected(f"{where}: {spread}", "snapshot")
    still_from, still_to = -np.inf, np.inf  # when every LIDAR saw the scene still
    for t in lidar_topics:
        if t not in period.picks:
            continue
        before, mid, after = (s[1] for s in period.picks[t])
        still_from, still_to = max(still_from, before.stamp_ns), min(still_to, after.stamp_ns)
        for other in (before, after):
            if other is mid:
                continue
            moved, mag, n = scene_motion(other.data, mid.data, threshold_m=options.max_board_motion_m,
                                         min_cells=options.min_moving_cells)
            if moved:
                return Rejected(f"{where}: board/scene moving on {t}: {n} range cells changed by "
                                f"~{mag:.3f} m within {abs(other.stamp_ns - mid.stamp_ns) * 1e-9:.2f}s "
                                f"(max_board_motion_m {options.max_board_motion_m})", "snapshot")
    outside = [(t, m.stamp_ns) for t, m in chosen.items() if not still_from <= m.stamp_ns <= still_to]
    if outside:
        t, st = outside[0]
        return Rejected(f"{where}: {t} has no message while the LIDARs saw the scene still "
                        f"({still_from * 1e-9:.3f}-{still_to * 1e-9:.3f}s; nearest {st * 1e-9:.3f}s)", "snapshot")
    return _snapshot(index, chosen, where, lidar_topics, camera_topics, bag=source)


def _spread_rejection(chosen, options) -> str | None:
    """Why the chosen messages are too far apart in time (``max_time_spread_s``; None: no limit)."""
    if options.max_time_spread_s is None:
        return None
    spread = time_spread_s(m.stamp_ns for m in chosen)
    if spread > options.max_time_spread_s:
        return f"time spread {spread:.3f}s > max_time_spread_s {options.max_time_spread_s}"
    return None


def _snapshot(index: int, chosen: dict, source: str, lidar_topics, camera_topics, *, bag: str | None = None) -> Snapshot:
    stamps = [m.stamp_ns for m in chosen.values()]
    return Snapshot(index=index, stamp_ns=int(np.mean(stamps)), source=source, bag=source if bag is None else bag,
                    scans={t: chosen[t].data for t in lidar_topics if t in chosen},
                    images={t: chosen[t].data for t in camera_topics if t in chosen})


def group_periods(messages: Iterator, topics: Sequence[str], *, period_s: float,
                  window_s: float, tfilter: TimeFilter) -> Iterator[_Period]:
    """Stream messages (in header-stamp order) into periods; yield each finished period.

    Periods start at the first kept message's stamp; messages at excluded times are
    skipped (``_finish_period`` drops a period overlapping an excluded time whole).
    """
    period_ns = int(round(period_s * 1e9))
    window_ns = int(round(window_s * 1e9))
    t0 = None
    cur: _Period | None = None
    for m in messages:
        if tfilter.why_not(m.stamp_ns) is not None:
            continue
        if t0 is None:
            t0 = m.stamp_ns
        k = (m.stamp_ns - t0) // period_ns
        if cur is not None and k != cur.k:
            yield cur
            cur = None
        if cur is None:
            start = t0 + k * period_ns
            cur = _Period(k, start + period_ns // 2, start, start + period_ns)
        _consider(cur, m, window_ns)
    if cur is not None:
        yield cur


def assemble_snapshots(bags: Sequence[Path], lidar_topics: Sequence[str],
                       camera_topics: Sequence[str], options, *,
                       progress=None) -> tuple[list[Snapshot], list[Rejected]]:
    """Snapshots from bags, and the candidate snapshots dropped (with reasons). Snapshots that
    ``exclude_bag`` names by bag or index come back empty (no scans or images), each with a
    Rejected carrying its index (see parse_exclude_bag).

    options: ``config.SnapshotOptions``. Without ``decimation_period_s``, one snapshot
    per bag from the first message of each topic (LIDAR scans averaged: ``still_average``); with
    it, one per period of the (continuous) bags, streamed. Snapshot indices count the kept snapshots from 0.
    ``progress``: optional wrapper of the iteration over bags (the API's progress bar).
    """
    from clcgraph.frontend.bag import read_messages

    tfilter = TimeFilter.from_options(options)
    lidar_topics, camera_topics = list(lidar_topics), list(camera_topics)
    topics = lidar_topics + camera_topics
    rejected: list[Rejected] = []
    kept_bags = []
    skip_bags = parse_exclude_bag(options.exclude_bag, [Path(b) for b in bags])[0]
    for b in map(Path, bags):
        if b in skip_bags:
            rejected.append(Rejected(f"{b}: excluded by exclude_bag {options.exclude_bag!r}", "snapshot"))
        else:
            kept_bags.append(b)
    snaps: list[Snapshot] = []
    if options.decimation_period_s is None:
        # each bag's LIDAR scans are averaged (still_average) in worker threads while the next bags
        # are read: numpy releases the GIL there, and reading is mostly Python
        with ThreadPoolExecutor(max_workers=min(2, os.cpu_count() or 1), thread_name_prefix="clcgraph-average") as pool:
            for group in (progress(recordings(kept_bags)) if progress else recordings(kept_bags)):
                found = _continuous(group, lidar_topics, camera_topics, options, tfilter, len(snaps))
                if found is not None:
                    snaps += found[0]
                    rejected += found[1]
                    continue
                for b in group:
                    r_new = _first_messages_snapshot(b, snaps, pool, lidar_topics, camera_topics, options, tfilter)
                    rejected += r_new
            snaps = [s.result(lidar_topics, camera_topics) if isinstance(s, _PendingSnapshot) else s for s in snaps]
    else:
        if options.decimation_period_s <= 0:
            raise InputError(f"decimation_period_s must be > 0, got {options.decimation_period_s}")
        for b in (progress(kept_bags) if progress else kept_bags):  # each continuous bag on its own time line
            msgs = read_messages([b], topics, start_ns=tfilter.after_ns, stop_ns=tfilter.before_ns, missing_ok=True)
            for per in group_periods(msgs, topics, period_s=options.decimation_period_s,
                                     window_s=options.motion_window_s, tfilter=tfilter):
                r = _finish_period(per, lidar_topics, camera_topics, options, str(b), len(snaps),
                                   tfilter)
                (rejected if isinstance(r, Rejected) else snaps).append(r)
    snaps, dropped = drop_excluded(snaps, options.exclude_bag, bags)
    rejected += dropped
    log.info("%d snapshots kept, %d rejected", len(snaps) - len(dropped), len(rejected))
    return snaps, rejected


# Files of one recording split by `rosbag record --split` follow each other without a gap; separate
# recordings (a bag per pose) are seconds apart (the board is moved and the recording restarted)
_SPLIT_GAP_NS = 1_000_000_000


def recordings(bags: Sequence[Path]) -> list[list[Path]]:
    """The bags grouped into recordings: a bag alone, or the files of one recording split into
    consecutive files (each starting within 1 s of the previous one's end, by the bags' indexes),
    in time order; the groups in the order of their first bag in ``bags``."""
    from clcgraph.frontend.bag import log_span

    if len(bags) < 2:
        return [list(bags)]
    spans = [log_span(b) for b in bags]
    by_time = sorted(range(len(bags)), key=lambda i: (spans[i][0], i))
    groups: list[list[int]] = []
    for i in by_time:
        prev = groups[-1][-1] if groups else None
        if prev is not None and 0 <= spans[i][0] - spans[prev][1] <= _SPLIT_GAP_NS:
            groups[-1].append(i)
        else:
            groups.append([i])
    return [[bags[i] for i in g] for g in sorted(groups, key=min)]


def _first_messages_snapshot(b: Path, snaps: list, pool, lidar_topics, camera_topics, options,
                             tfilter: TimeFilter) -> list[Rejected]:
    """A bag per pose: its snapshot from the first messages of each topic appended to ``snaps``
    (pending: its LIDAR scans averaged in ``pool``), or why not."""
    from clcgraph.frontend.bag import leading_messages

    topics = list(lidar_topics) + list(camera_topics)
    lead = leading_messages(b, topics, {t: options.max_scans_averaged for t in lidar_topics}, missing_ok=True)
    if not lead:
        return [Rejected(f"{b}: none of the topics present", "snapshot")]
    why = next((w for w in (tfilter.why_not(ms[0].stamp_ns) for ms in lead.values()) if w), None)
    if why:
        return [Rejected(f"{b}: {why}", "snapshot")]
    spread = _spread_rejection([ms[0] for ms in lead.values()], options)
    if spread:
        return [Rejected(f"{b}: {spread}", "snapshot")]
    snaps.append(_PendingSnapshot(len(snaps), str(b), {t: ms[0].stamp_ns for t, ms in lead.items()},
                                  {t: pool.submit(still_average, ms, options) for t, ms in lead.items()}))
    return []


def continuous_snapshots(bag: Path | Sequence[Path], lidar_topics: Sequence[str], options) -> list[Snapshot]:
    """The snapshots ``assemble_snapshots`` takes from ``bag`` (or the files of one recording,
    ``recordings``) if it is a continuous recording (the scene still more than once, judged by
    ``lidar_topics``), one per still interval; else [] (a bag per pose: its first messages)."""
    found = _continuous(bag, lidar_topics, [], options, TimeFilter.from_options(options), 0)
    return [] if found is None else found[0]


def _continuous(bag: Path | Sequence[Path], lidar_topics, camera_topics, options, tfilter: TimeFilter,
                first_index: int) -> tuple[list[Snapshot], list[Rejected]] | None:
    """``_still_snapshots`` of ``bag`` (or a recording's files) if the board stopped more than once
    in it: a continuous recording, a snapshot per still interval; else None (a bag per pose, in
    which something may have moved, e.g. a passer-by: its first messages make its snapshot)."""
    if not _may_hold_two_still_intervals(bag, lidar_topics):
        return None
    still, moving_s = still_intervals(bag, lidar_topics, options, tfilter)
    if not (moving_s > 0 and len(still) >= 2):
        return None
    return _still_snapshots(bag, still, moving_s, lidar_topics, camera_topics, options, tfilter, first_index)


def _may_hold_two_still_intervals(bag: Path | Sequence[Path], lidar_topics: Sequence[str]) -> bool:
    """Whether ``still_intervals`` can find two still intervals in ``bag``: each needs >= 2 scans of
    every LIDAR seen, so a bag with fewer than 4 scans of each LIDAR (a bag per pose) cannot, and its
    scans need not be decoded and compared (from the bag's index: nothing is read)."""
    from clcgraph.frontend.bag import message_count

    return any(message_count(bag, t) >= 4 for t in lidar_topics)


def still_intervals(bag: Path | Sequence[Path], lidar_topics: Sequence[str], options,
                    tfilter: TimeFilter = TimeFilter()) -> tuple[list[tuple[int, int, dict]], float]:
    """Where the scene in ``bag`` (or the files of one recording, ``recordings``) was still, judged
    by motion, and how long it moved (s).

    Every LIDAR's scans are compared (``scene_motion``, ``options.max_board_motion_m``,
    ``min_moving_cells``) with the first scan of the current still run, so slow motion adds
    up; any LIDAR seeing motion ends the run. A run is a still interval only if each LIDAR
    scanned it at least twice (stillness was measured, not assumed) and it lasts at least
    ``motion_window_s`` (the span over which the motion threshold is judged, as for periods:
    a board drifting slowly changes little from one scan to the next): (start_ns, end_ns,
    {topic: scans}) from its first scan's stamp to the end of its last (``time_s``). A bag
    with one scan per LIDAR, or no motion, has moving time 0 (a bag per pose).
    """
    from clcgraph.frontend.bag import message_count, read_messages

    bags = [bag] if isinstance(bag, (str, Path)) else list(bag)
    if all(message_count(bags, t) <= 1 for t in lidar_topics):
        return [], 0.0
    runs: list[dict] = []  # {"anchor": {topic: scan}, "n": {topic: count}, "start", "end"}
    cur = None
    moving_ns = 0
    for m in read_messages(bags, lidar_topics, start_ns=tfilter.after_ns, stop_ns=tfilter.before_ns, missing_ok=True):
        if tfilter.why_not(m.stamp_ns) is not None:
            continue
        t = m.data.time_s
        end = m.stamp_ns + (int(float(np.max(t)) * 1e9) if t is not None and len(t) else 0)
        scan = range_image(m.data)  # all the comparison needs of the scan
        if cur is not None and m.topic in cur["anchor"]:
            moved, _, _ = motion_between(cur["anchor"][m.topic], scan, threshold_m=options.max_board_motion_m,
                                         min_cells=options.min_moving_cells)
            if moved:
                moving_ns += max(0, m.stamp_ns - cur["end"])
                cur = None
        if cur is None:
            cur = {"anchor": {}, "n": {}, "start": m.stamp_ns, "end": end}
            runs.append(cur)
        cur["anchor"].setdefault(m.topic, scan)
        cur["n"][m.topic] = cur["n"].get(m.topic, 0) + 1
        cur["end"] = max(cur["end"], end)
    if len(runs) <= 1:
        return [], 0.0
    present = {t for r in runs for t in r["n"]}
    window_ns = int(options.motion_window_s * 1e9)

    def is_still(r):
        return set(r["n"]) == present and min(r["n"].values()) >= 2 and r["end"] - r["start"] >= window_ns

    still = [(r["start"], r["end"], dict(r["n"])) for r in runs if is_still(r)]
    moving_ns += sum(r["end"] - r["start"] for r in runs if not is_still(r))
    return still, moving_ns * 1e-9


def _still_snapshots(bag: Path | Sequence[Path], still, moving_s: float, lidar_topics, camera_topics, options,
                     tfilter: TimeFilter, first_index: int) -> tuple[list[Snapshot], list[Rejected]]:
    """One snapshot per still interval of a continuous ``bag`` or split recording (``still_intervals``):
    per topic the message nearest the interval's centre among those inside it (streamed: one
    message per topic held); named by the file of the interval's first message."""
    from clcgraph.frontend.bag import read_messages

    bags = [Path(bag)] if isinstance(bag, (str, Path)) else list(bag)

    snaps: list[Snapshot] = []
    name = bags[0] if len(bags) == 1 else f"{bags[0]} (+ {len(bags) - 1} more file(s) of the recording)"
    rejected = [Rejected(f"{name}: the scene moved for {moving_s:.1f} s in all (not used); "
                         f"{len(still)} still interval(s) judged by motion", "snapshot")]
    if not still:
        return snaps, rejected
    starts = np.array([a for a, _, _ in still], np.int64)
    picks: dict[str, list[tuple[int, _Msg]]] = {}  # per topic the messages nearest the centre, nearest first
    k_open, file_open = -1, bags[0]

    def close(k):
        a, b, _ = still[k]
        where = f"{file_open} still {a * 1e-9:.3f}-{b * 1e-9:.3f}s"
        chosen = {t: _Msg(t, ms[0][1].stamp_ns, still_average([m.data for _, m in ms])) for t, ms in picks.items()}
        spread = _spread_rejection(chosen.values(), options)
        if spread:
            rejected.append(Rejected(f"{where}: {spread}", "snapshot"))
        elif chosen:
            snaps.append(_snapshot(first_index + len(snaps), chosen, where, lidar_topics, camera_topics))

    for m in read_messages(bags, list(lidar_topics) + list(camera_topics), missing_ok=True, start_ns=int(starts[0]),
                           stop_ns=int(still[-1][1]) + 1):
        k = int(np.searchsorted(starts, m.stamp_ns, side="right")) - 1
        if k < 0 or m.stamp_ns > still[k][1] or tfilter.why_not(m.stamp_ns) is not None:
            continue
        if k != k_open:
            if k_open >= 0:
                close(k_open)
            picks, k_open, file_open = {}, k, m.bag
        dt = abs(m.stamp_ns - (still[k][0] + still[k][1]) // 2)
        keep = options.max_scans_averaged if m.topic in lidar_topics else 1
        ms = picks.setdefault(m.topic, [])
        if len(ms) < keep or dt < ms[-1][0]:
            ms.append((dt, _Msg(m.topic, m.stamp_ns, m.data)))
            ms.sort(key=lambda x: x[0])
            del ms[keep:]
    if k_open >= 0:
        close(k_open)
    return snaps, rejected


def still_average(messages: list, options=None) -> LidarScan | Image:
    """The first of one topic's messages of a still scene; for a LIDAR, its rays at their mean range
    over it and those of the others in which nothing moved since (``average_scans``). ``options``:
    each later scan judged against the first as for periods (``max_board_motion_m``,
    ``min_moving_cells``); None: they are known still (a still interval's, judged by motion)."""
    first = messages[0]
    if len(messages) == 1 or not isinstance(first, LidarScan):
        return first
    from clcgraph.frontend.lidar_preprocess import average_scans

    still = messages
    if options is not None:
        image = range_image(first)
        still = [first] + [m for m in messages[1:]
                           if not motion_between(image, range_image(m), threshold_m=options.max_board_motion_m,
                                                 min_cells=options.min_moving_cells)[0]]
    return average_scans(still)[0]


@dataclass(frozen=True)
class _PendingSnapshot:
    """A bag's snapshot whose messages (``still_average``) are still being computed: per topic the
    first message's stamp and the Future of the message."""

    index: int
    source: str
    stamps: dict
    futures: dict

    def result(self, lidar_topics, camera_topics) -> Snapshot:
        chosen = {t: _Msg(t, self.stamps[t], f.result()) for t, f in self.futures.items()}
        return _snapshot(self.index, chosen, self.source, lidar_topics, camera_topics)


@dataclass(frozen=True)
class _Msg:
    topic: str
    stamp_ns: int
    data: LidarScan | Image
