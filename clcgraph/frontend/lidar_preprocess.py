"""LIDAR scans made regular: valid points in range, rings (derived when the cloud has none),
azimuths, per-ring azimuth order; the ring count and Npoints_per_rotation inferred from data;
and static-scene suppression over a session.

SYNOPSIS
    r = prepare(scan, min_range_m=0.5, max_range_m=9.0)   # Rings: per-ring sorted indices
    every = prepare(scan); r = every.within(min_range_m=0.5, max_range_m=9.0)  # the same
    n_rings, npoints = infer_lidar_spacing(scans)
    static = static_masks(scans, npoints_per_rotation=1800)  # per scan: points at the session's mode range
    scan, n = average_scans([scan0, scan1, scan2])   # scan0's rays at their mean range over still scans
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..geometry import azimuth, elevation, wrap_angle
from ..types import LidarScan

# Npoints_per_rotation values real LIDARs use; an estimate within 3% snaps to one of these.
COMMON_NPOINTS = (360, 440, 512, 900, 1024, 1800, 2000, 2048, 3600, 4096)


def finite_rows(p: np.ndarray) -> np.ndarray:
    """(N,) whether each row of ``p`` (N,3) is finite: ``np.all(np.isfinite(p), axis=1)`` without
    numpy's slow reduction over a short axis."""
    f = np.isfinite(p)
    return f[:, 0] & f[:, 1] & f[:, 2]


def row_norms(p: np.ndarray) -> np.ndarray:
    """(N,) ``np.linalg.norm(p, axis=1)`` of ``p`` (N,3), bit for bit (numpy sums the squares in
    this order too), without the reduction over a short axis."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    return np.sqrt(x * x + y * y + z * z)


def small_unique(values: np.ndarray, *, counts: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(values, return_inverse=True)`` (``counts``: ``return_counts=True``) of (N,)
    integers such as ring numbers or dense cell keys: by counting (no sort) when they span less
    than 2**16 or 8 x N, else by np.unique."""
    if not len(values) or int(values.max()) - int(values.min()) >= max(1 << 16, 8 * len(values)):
        return np.unique(values, return_counts=True) if counts else np.unique(values, return_inverse=True)
    lo = values.min()
    c = np.bincount(values - lo)
    seen = c > 0
    unique = (np.flatnonzero(seen) + lo).astype(values.dtype, copy=False)
    return (unique, c[seen]) if counts else (unique, (np.cumsum(seen) - 1)[values - lo])


def slice_medians(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """(S,) ``np.median`` of each slice ``values[starts[j]:starts[j + 1]]`` (non-empty; e.g. per ring of
    a ``Rings``), the same values by a partition each (np.median's own overhead was most of it)."""
    out = np.empty(len(starts) - 1)
    for j, (a, b) in enumerate(zip(starts[:-1].tolist(), starts[1:].tolist())):
        k = (b - a) // 2
        if (b - a) % 2:
            out[j] = np.partition(values[a:b], k)[k]
        else:
            mid = np.partition(values[a:b], (k - 1, k))
            out[j] = (mid[k - 1] + mid[k]) / 2
    return out


def ring_of(scan: LidarScan) -> np.ndarray:
    """(N,) ring index per point: the ring field, or clusters of the elevation angle."""
    if scan.ring is not None:
        return np.asarray(scan.ring).astype(np.int64)
    p = np.asarray(scan.points, float)
    el = np.degrees(elevation(p))
    ok = np.asarray(scan.valid, bool) & np.isfinite(el)
    ring = np.full(len(p), -1, np.int64)
    if not ok.any():
        return ring
    e = np.sort(el[ok])
    gaps = np.diff(e)
    if not len(gaps):
        return np.where(ok, 0, -1)
    # a new ring where the sorted elevations jump well beyond their within-ring spread
    big = gaps > max(0.08, 5.0 * np.median(gaps))
    edges = e[1:][big]
    ring[ok] = np.searchsorted(edges, el[ok], side="right")
    return ring


@dataclass(frozen=True)
class Rings:
    """A scan's usable points: ``index`` into the scan rows, sorted by (ring, azimuth)."""

    index: np.ndarray  # (M,) rows of the scan
    ring: np.ndarray  # (M,)
    azimuth: np.ndarray  # (M,) rad in [-pi, pi)
    range: np.ndarray  # (M,)
    points: np.ndarray  # (M,3)
    starts: np.ndarray  # (Nrings+1,) slice bounds of each ring in the sorted arrays
    ring_ids: np.ndarray  # (Nrings,) the ring number of each slice

    def within(self, *, min_range_m: float, max_range_m: float, exclude: np.ndarray | None = None) -> "Rings":
        """The points within [min, max] range, minus the scan rows ``exclude`` (N,) (a mask), in the
        same (ring, azimuth) order."""
        ok = (self.range >= min_range_m) & (self.range <= max_range_m)
        if exclude is not None:
            ok &= ~exclude[self.index]
        idx = np.flatnonzero(ok)
        r = self.ring[idx]
        starts = np.flatnonzero(np.r_[True, r[1:] != r[:-1]]) if len(r) else np.zeros(0, np.int64)
        return Rings(self.index[idx], r, self.azimuth[idx], self.range[idx], self.points[idx],
                     np.r_[starts, len(idx)], r[starts])


def prepare(scan: LidarScan, *, min_range_m: float = 0.0, max_range_m: float = np.inf,
            exclude: np.ndarray | None = None) -> Rings:
    """Valid, finite points within [min, max] range (minus ``exclude``), sorted by ring then azimuth.
    The default range keeps every valid return (``Rings.within`` then cuts it without sorting again)."""
    p = np.asarray(scan.points, float)
    ring = ring_of(scan)
    idx = np.flatnonzero(np.asarray(scan.valid, bool) & finite_rows(p) & (ring >= 0))
    pts = p[idx]
    with np.errstate(invalid="ignore", over="ignore"):  # huge garbage points fail the range test
        rng = row_norms(pts)
    az = azimuth(pts)
    # np.lexsort((az, ring)): by ring as 16-bit keys where they fit (a radix sort), then each ring by
    # azimuth, stably (a ring's returns come in azimuth order, which the stable sort exploits; the
    # returns of all rings at once, interleaved, cost 3x)
    r = ring[idx]
    order = np.argsort(r.astype(np.uint16) if r.max(initial=0) < 1 << 16 else r, kind="stable")
    r = r[order]
    starts = np.flatnonzero(np.r_[True, r[1:] != r[:-1]]) if len(r) else np.zeros(0, np.int64)
    bounds = np.r_[starts, len(r)]
    az_by_ring = az[order]
    for a, b in zip(bounds[:-1].tolist(), bounds[1:].tolist()):
        order[a:b] = order[a:b][np.argsort(az_by_ring[a:b], kind="stable")]
    order = _first_returns(order, r, az)
    if len(order) < len(r):
        r = ring[idx[order]]
        starts = np.flatnonzero(np.r_[True, r[1:] != r[:-1]]) if len(r) else np.zeros(0, np.int64)
        bounds = np.r_[starts, len(r)]
    every = Rings(idx[order], r, az[order], rng[order], pts[order], bounds, r[starts])
    if min_range_m <= 0 and max_range_m == np.inf and exclude is None:
        return every
    return every.within(min_range_m=min_range_m, max_range_m=max_range_m, exclude=exclude)


def origin_height_m(scan: LidarScan) -> float | None:
    """How far above (> 0) or below the scan's origin its rings' apex lies (m, roughly: a height H
    reads as H cos^2 of the rings' elevations), or None where the rings
    are not known (no ring field, unorganised) or too few returns lie near and far. A LIDAR's own
    cloud has each ring on a cone about the origin: a return's elevation is its ring's at any
    range, but for a few cm of beam offsets (VLP-16 ~1 cm, HDL-64 up to ~0.25 m). A cloud already
    moved into another frame (base_link, 1-2 m below the LIDAR) has its near returns' elevation off
    by about that height over their range: per ring, the median of range x (elevation - its far
    returns' elevation) over the returns at 2-8 m; the median over the rings."""
    if scan.ring is None and scan.shape is None:
        return None
    p = np.asarray(scan.points, float)
    ring = ring_of(scan)
    ok = np.asarray(scan.valid, bool) & finite_rows(p) & (ring >= 0)
    p, ring = p[ok], ring[ok]
    r = row_norms(p)
    with np.errstate(invalid="ignore", divide="ignore"):
        el = np.arcsin(np.clip(p[:, 2] / r, -1, 1))
    near, far = (r >= 2.0) & (r <= 8.0), r >= 15.0
    h = []
    for k in np.unique(ring[near]):
        n, f = near & (ring == k), far & (ring == k)
        if n.sum() >= 20 and f.sum() >= 20:
            h.append(np.median(r[n] * (el[n] - np.median(el[f]))))
    return float(np.median(h)) if len(h) >= 3 else None


# Two returns of one ray (a LIDAR in dual-return mode: strongest and last in one cloud) share its
# ring and azimuth to float precision (~1e-7 rad); neighbouring rays are >= 1e-3 rad apart.
_SAME_RAY_RAD = 1e-5


def has_second_returns(scan: LidarScan, ring: np.ndarray, az: np.ndarray) -> bool:
    """Whether ``scan`` holds rays that returned twice (``_first_returns``), from its fullest ring
    alone (a dual-return LIDAR reports two for most rays of every ring): cheaper than ``prepare``.
    ``ring``, ``az``: per row (``ring_of``, ``azimuth``)."""
    ok = np.asarray(scan.valid, bool) & (ring >= 0) & np.isfinite(az)
    if not ok.any():
        return False
    fullest = np.argmax(np.bincount(ring[ok] - ring[ok].min())) + ring[ok].min()
    a = np.sort(az[ok & (ring == fullest)])
    return bool(len(a) > 1 and np.any(np.diff(a) <= _SAME_RAY_RAD))


def _first_returns(order: np.ndarray, ring_sorted: np.ndarray, az: np.ndarray) -> np.ndarray:
    """``order`` (positions of the points, sorted by ring, then azimuth) with one return per ray:
    where a ray returned twice, the first in the cloud's own order. A second return counted as a
    second measurement would shrink the sigmas (the same echo twice: by sqrt 2); keeping the nearer
    one would bias a surface's noisy ranges toward the LIDAR (two returns of one surface both noisy)."""
    if len(order) < 2:
        return order
    same = (np.diff(ring_sorted) == 0) & (np.abs(np.diff(az[order])) <= _SAME_RAY_RAD)
    if not same.any():
        return order
    group = np.cumsum(np.r_[True, ~same])  # one id per ray, in the sorted order
    by = np.lexsort((order, group))  # per ray, its returns in the cloud's order
    first = np.r_[True, group[by][1:] != group[by][:-1]]
    return order[np.sort(by[first])]


def ring_neighbours(R: Rings) -> tuple[np.ndarray, np.ndarray]:
    """(previous, next): per point of ``R``, the position in ``R`` of its neighbour along its
    ring in azimuth order (wrapping around; a ring of one point is its own neighbour)."""
    n = len(R.index)
    nxt, prv = np.arange(1, n + 1), np.arange(-1, n - 1)
    if n:
        nxt[R.starts[1:] - 1] = R.starts[:-1]
        prv[R.starts[:-1]] = R.starts[1:] - 1
    return prv, nxt


def missed_rays(R: Rings, step: float, *, limit: int = 1_000_000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rays that returned nothing: the azimuth steps missing between consecutive returns of
    a ring (wrapping around), each at its neighbours' mean elevation. ``R``: every valid return
    of a scan (``prepare`` without range limits); ``step``: the azimuth step (rad). Returns
    ((K,3) unit directions, (K,) the position in ``R`` of the return just before each (-1 unless
    it is the first missed ray of its gap), and of the return just after (-1 unless the last));
    at most ``limit`` rays (a scan mostly of sky)."""
    none = (np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64))
    if not len(R.index):
        return none
    _, nxt = ring_neighbours(R)
    daz = (R.azimuth[nxt] - R.azimuth) % (2 * np.pi)
    last = R.starts[1:] - 1
    daz[last] = np.where(np.diff(R.starts) > 1, daz[last], 2 * np.pi)
    n_miss = np.maximum(np.rint(daz / step).astype(np.int64) - 1, 0)
    n_miss = np.minimum(n_miss, np.maximum(limit - np.r_[0, np.cumsum(n_miss)[:-1]], 0))
    if not n_miss.sum():
        return none
    g = np.repeat(np.arange(len(n_miss)), n_miss)
    m = np.arange(len(g)) - np.repeat(np.cumsum(n_miss) - n_miss, n_miss) + 1  # 1..n_miss within a gap
    az = R.azimuth[g] + daz[g] * m / (n_miss[g] + 1)
    u = R.points / R.range[:, None]
    el = (np.arcsin(np.clip(u[g, 2], -1, 1)) + np.arcsin(np.clip(u[nxt[g], 2], -1, 1))) / 2
    dirs = np.c_[np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]
    return dirs, np.where(m == 1, g, -1), np.where(m == n_miss[g], nxt[g], -1)


def neighbour_steps(R: Rings) -> np.ndarray:
    """Azimuth steps (rad) between consecutive returns of the same ring."""
    d = np.diff(R.azimuth)
    return d[(d > 1e-6) & (np.diff(R.ring) == 0)]


def typical_step(d: np.ndarray) -> float | None:
    """The azimuth step of neighbouring returns, not of gaps over missing ones (None if no steps)."""
    return float(np.median(d[d < 3 * np.percentile(d, 25)])) if len(d) else None


def average_scans(scans: list[LidarScan]) -> tuple[LidarScan, np.ndarray]:
    """One scan of a still scene from several of the same LIDAR: ``scans[0]``'s rays, each at the
    mean range of that ray in every scan that returned from the same surface there.

    The other scans' ranges are interpolated along their ring to each ray's azimuth (a rotation's
    azimuths jitter from one to the next; interpolation keeps a tilted surface's points on it) from
    two neighbouring returns of one surface (an organised cloud of fixed columns: the same row's),
    and count only where they agree with the ray's range within 4 robust sigmas of the
    scan-to-scan differences (not across a depth edge, a mixed pixel, a stray return). Returns
    (the scan, (N,) how many scans each row's range averages; 0 where the first scan has no
    valid return)."""
    ref = scans[0]
    R = prepare(ref)
    n = np.zeros(len(ref.points), np.int64)
    n[R.index] = 1
    if len(scans) == 1 or not len(R.index):
        return ref, n
    total = np.zeros(len(ref.points))
    total[R.index] = R.range
    key_r = R.ring * 8.0 + R.azimuth  # ring, then azimuth in [-pi, pi): one sortable key
    step_r = typical_step(neighbour_steps(R)) if ref.shape is not None else None  # for _same_rays' organised clouds
    for scan in scans[1:]:
        found = _same_rays(ref, scan, R, step_r) or _along_rings(scan, R, key_r)
        if found is None:
            continue
        r_q, near, dq, step = found
        d = r_q - R.range
        sigma = 1.4826 * np.median(np.abs(d[near]))
        gate = max(4.0 * sigma, 1e-3)
        ok = near & (np.abs(d) <= gate) & (dq <= gate + 2 * step * R.range)
        total[R.index[ok]] += r_q[ok]
        n[R.index[ok]] += 1
    p = np.asarray(ref.points, float).copy()
    rows = R.index
    p[rows] *= (total[rows] / n[rows] / R.range)[:, None]
    return dataclasses.replace(ref, points=p.astype(np.asarray(ref.points).dtype, copy=False)), n


def _same_rays(ref: LidarScan, scan: LidarScan, R: Rings, step: float | None):
    """An organised cloud of fixed columns (an Ouster's: every rotation fires at the same azimuths):
    ``scan``'s range on each of R's rows (``ref``'s, azimuth step ``step``), directly ((M,) ranges,
    (M,) usable, (M,) 0, the step); None if the clouds' layouts or azimuths differ."""
    if not step or ref.shape is None or scan.shape != ref.shape or len(scan.points) != len(ref.points):
        return None
    p = np.asarray(scan.points, float)[R.index]
    with np.errstate(invalid="ignore", over="ignore"):
        r = row_norms(p)
    near = np.asarray(scan.valid, bool)[R.index] & np.isfinite(r) & (r > 0)
    if scan.ring is not None:
        near &= np.asarray(scan.ring)[R.index] == R.ring
    if near.sum() < 2:
        return None
    daz = wrap_angle(azimuth(p[near]) - R.azimuth[near])
    if np.median(np.abs(daz)) > 0.02 * step:
        return None
    return np.where(near, r, 0.0), near, np.zeros(len(r)), step


def _along_rings(scan: LidarScan, R: Rings, key_r: np.ndarray):
    """``scan``'s range on each of R's rays, interpolated along its ring between the two returns
    either side of the ray's azimuth ((M,) ranges, (M,) usable: one ring, neighbouring returns,
    (M,) their range difference, the azimuth step); None if it has too few returns."""
    Q = prepare(scan)
    step = typical_step(neighbour_steps(Q))
    if len(Q.index) < 2 or not step:
        return None
    key_q = Q.ring * 8.0 + Q.azimuth
    j = np.clip(np.searchsorted(key_q, key_r, side="right"), 1, len(key_q) - 1)
    a, b = j - 1, j
    span = key_q[b] - key_q[a]
    w = np.clip((key_r - key_q[a]) / np.where(span > 0, span, 1.0), 0.0, 1.0)
    same_ring = (Q.ring[a] == R.ring) & (Q.ring[b] == R.ring)
    near = same_ring & (span <= 1.5 * step) & (key_r >= key_q[a] - 0.5 * step) & (key_r <= key_q[b] + 0.5 * step)
    if not near.any():
        return None
    return (1 - w) * Q.range[a] + w * Q.range[b], near, np.abs(Q.range[b] - Q.range[a]), step


def infer_lidar_spacing(scans) -> tuple[int, int]:
    """(number of rings, Npoints_per_rotation) from the angular spacing of neighbouring returns."""
    n_rings, steps = 0, []
    for scan in scans:
        R = prepare(scan, min_range_m=0.0, max_range_m=np.inf)
        n_rings = max(n_rings, len(R.ring_ids))
        steps.append(neighbour_steps(R))
    step = typical_step(np.concatenate(steps)) if steps else None
    if not step:
        return n_rings, 0
    n = 2 * np.pi / step
    best = min(COMMON_NPOINTS, key=lambda c: abs(c - n))
    return n_rings, int(best if abs(best - n) < 0.03 * n else round(n))


def session_masks(scans, lidar_options) -> tuple[int | None, list]:
    """(Npoints_per_rotation: configured or inferred, per scan the static-scene mask or None)
    for a session of one LIDAR's scans."""
    npoints = lidar_options.npoints_per_rotation or infer_lidar_spacing(scans[:5])[1] or None
    if lidar_options.suppress_static and npoints:
        return npoints, static_masks(scans, npoints_per_rotation=npoints, quantum_m=lidar_options.static_range_quantum_m,
                                     max_range_m=lidar_options.max_range_m)
    return npoints, [None] * len(scans)


# A cell never seen static (the board's usual place) takes its background from the static cells
# either side along the ring, across at most this much azimuth (a 1.3 m board at 2 m spans 36 deg).
MAX_BACKGROUND_GAP_DEG = 45.0


def _fill_background(r_static: np.ndarray, max_gap: int) -> np.ndarray:
    """(rings, columns) static range per cell, NaN where none: NaN runs of at most ``max_gap``
    cells between two static cells of the same ring (wrapping around) are filled with the
    range at which each cell's ray meets the straight line through those two cells' points
    (a wall is straight across the shadow of a board held in front of it)."""
    R, C = r_static.shape
    G = np.concatenate([r_static] * 3, axis=1)  # wrap-around without special cases
    col = np.arange(3 * C)
    known = np.isfinite(G)
    prev = np.maximum.accumulate(np.where(known, col, -1), axis=1)
    nxt = np.minimum.accumulate(np.where(known, col, 3 * C)[:, ::-1], axis=1)[:, ::-1]
    prev, nxt = prev[:, C : 2 * C], nxt[:, C : 2 * C]  # indices into G, the middle copy's neighbours
    fill = ~np.isfinite(r_static) & (prev >= 0) & (nxt < 3 * C) & (nxt - prev - 1 <= max_gap)
    rows, cols = np.nonzero(fill)
    p, n = prev[rows, cols], nxt[rows, cols]
    a1, a2, a = (2 * np.pi / C) * p, (2 * np.pi / C) * n, (2 * np.pi / C) * (cols + C)
    r1, r2 = G[rows, p], G[rows, n]
    P1 = np.c_[r1 * np.cos(a1), r1 * np.sin(a1)]
    P2 = np.c_[r2 * np.cos(a2), r2 * np.sin(a2)]
    Dv = P2 - P1
    u = np.c_[np.cos(a), np.sin(a)]
    den = u[:, 0] * Dv[:, 1] - u[:, 1] * Dv[:, 0]
    s = (P1[:, 0] * P2[:, 1] - P1[:, 1] * P2[:, 0]) / np.where(np.abs(den) > 1e-12, den, np.nan)
    out = r_static.copy()
    out[rows, cols] = np.where(s > 0, s, np.nan)
    return out


def static_masks(scans, *, npoints_per_rotation: int, quantum_m: float = 0.2, min_share: float = 0.5,
                 max_range_m: float = 1e4) -> list[np.ndarray]:
    """Per scan, the points at their (ring, azimuth) cell's static range over the session.

    The board (and whoever holds it) moves between snapshots, walls and the ground do not:
    removing the static points leaves the board standing out. A cell is static at its most
    common range if that range holds in >= ``min_share`` of the scans. A cell the board
    covers in most scans (held at one spot, turned from pose to pose) never is, so the wall
    behind it would reappear, board-sized, whenever the board moves off: such cells take the
    background of the static cells either side along the ring (``_fill_background``). A point
    within 1.5 quanta of its cell's static range is static. Works for bags per pose and for
    the snapshots of one continuous bag alike. Fewer than 4 scans: nothing is static.
    """
    if len(scans) < 4:
        return [np.zeros(len(s.points), bool) for s in scans]
    keys, ranges = [], []
    for s in scans:
        p = np.asarray(s.points, float)
        ring = ring_of(s)
        with np.errstate(invalid="ignore", over="ignore"):  # garbage points are masked out below
            r = row_norms(p)
            az = azimuth(p)
        # only returns in segmentation range take part: one scan of garbage (a false is_bigendian)
        # must not overflow the keys and spoil every other scan's modes
        ok = np.asarray(s.valid, bool) & np.isfinite(r) & (r <= max_range_m) & (ring >= 0)
        if has_second_returns(s, ring, az):  # each ray counts once in its cell's modes
            first = np.zeros(len(ok), bool)
            first[prepare(s).index] = True
            ok &= first
        col = np.floor((np.where(ok, az, 0.0) + np.pi) / (2 * np.pi) * npoints_per_rotation).astype(np.int64)
        keys.append(np.where(ok, ring * npoints_per_rotation + col % npoints_per_rotation, -1))
        ranges.append(np.where(ok, r, np.nan))
    K = np.concatenate(keys)
    Q = np.floor(np.concatenate(ranges) / quantum_m)
    good = K >= 0
    if not good.any():  # no return in range anywhere (all-NaN clouds): nothing is static
        return [np.zeros(len(k), bool) for k in keys]
    Qg = Q[good].astype(np.int64)
    span = int(Qg.max()) + 1
    # one int64 per (cell, range bin): a 1-D unique is much faster than a row-wise one. The cells (<
    # the r_static array's size below) times the range bins (max_range_m / quantum_m <= 1e7 by the
    # config's bounds) are far from int64 overflow: no dense numbering of the cells first (2x the cost)
    kq, counts = small_unique(K[good] * span + Qg, counts=True)
    kc, qb = kq // span, kq % span
    # the most common range bin of each cell
    order = np.lexsort((-counts, kc))
    kc, qb, counts = kc[order], qb[order], counts[order]
    first = np.r_[True, kc[1:] != kc[:-1]]
    cells, mq, mc = kc[first], qb[first], counts[first]
    static_cell = mc >= min_share * len(scans)
    n_rings = int(cells.max() // npoints_per_rotation) + 1 if len(cells) else 1
    r_static = np.full(n_rings * npoints_per_rotation, np.nan)
    r_static[cells[static_cell]] = (mq[static_cell] + 0.5) * quantum_m
    max_gap = int(np.radians(MAX_BACKGROUND_GAP_DEG) / (2 * np.pi) * npoints_per_rotation)
    r_static = _fill_background(r_static.reshape(n_rings, npoints_per_rotation), max_gap).reshape(-1)
    out = []
    for k, r in zip(keys, ranges):
        bg = np.where(k >= 0, r_static[np.maximum(k, 0)], np.nan)
        with np.errstate(invalid="ignore"):
            out.append(np.abs(r - bg) <= 1.5 * quantum_m)
    return out
