"""LIDAR scans made regular: valid points in range, rings (derived when the cloud has none),
azimuths, per-ring azimuth order; the ring count and Npoints_per_rotation inferred from data;
and static-scene suppression over a session.

SYNOPSIS
    r = prepare(scan, min_range_m=0.5, max_range_m=9.0)   # Rings: per-ring sorted indices
    n_rings, npoints = infer_lidar_spacing(scans)
    static = static_masks(scans, npoints_per_rotation=1800)  # per scan: points at the session's mode range
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..types import LidarScan

# Npoints_per_rotation values real LIDARs use; an estimate within 3% snaps to one of these.
COMMON_NPOINTS = (360, 440, 512, 900, 1024, 1800, 2000, 2048, 3600, 4096)


def ring_of(scan: LidarScan) -> np.ndarray:
    """(N,) ring index per point: the ring field, or clusters of the elevation angle."""
    if scan.ring is not None:
        return np.asarray(scan.ring).astype(np.int64)
    p = np.asarray(scan.points, float)
    el = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
    ok = np.asarray(scan.valid, bool) & np.isfinite(el)
    ring = np.full(len(p), -1, np.int64)
    if not ok.any():
        return ring
    e = np.sort(el[ok])
    gaps = np.diff(e)
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


def prepare(scan: LidarScan, *, min_range_m: float, max_range_m: float, exclude: np.ndarray | None = None) -> Rings:
    """Valid, finite points within [min, max] range (minus ``exclude``), sorted by ring then azimuth."""
    p = np.asarray(scan.points, float)
    rng = np.linalg.norm(p, axis=1)
    ok = np.asarray(scan.valid, bool) & np.all(np.isfinite(p), axis=1) & (rng >= min_range_m) & (rng <= max_range_m)
    if exclude is not None:
        ok &= ~exclude
    ring = ring_of(scan)
    ok &= ring >= 0
    idx = np.flatnonzero(ok)
    az = np.arctan2(p[idx, 1], p[idx, 0])
    order = np.lexsort((az, ring[idx]))
    idx = idx[order]
    r = ring[idx]
    ring_ids, starts = np.unique(r, return_index=True)
    return Rings(idx, r, az[order], rng[idx], p[idx], np.r_[starts, len(idx)], ring_ids)


def neighbour_steps(R: Rings) -> np.ndarray:
    """Azimuth steps (rad) between consecutive returns of the same ring."""
    d = np.diff(R.azimuth)
    return d[(d > 1e-6) & (np.diff(R.ring) == 0)]


def typical_step(d: np.ndarray) -> float | None:
    """The azimuth step of neighbouring returns, not of gaps over missing ones (None if no steps)."""
    return float(np.median(d[d < 3 * np.percentile(d, 25)])) if len(d) else None


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
        return npoints, static_masks(scans, npoints_per_rotation=npoints, quantum_m=lidar_options.static_range_quantum_m)
    return npoints, [None] * len(scans)


def static_masks(scans, *, npoints_per_rotation: int, quantum_m: float = 0.2, min_share: float = 0.5) -> list[np.ndarray]:
    """Per scan, the points at their (ring, azimuth) cell's most common range over the session.

    The board (and whoever holds it) moves between snapshots, walls and the ground do not:
    removing the static points leaves the board standing out. A cell counts as static only
    if its mode range holds in >= ``min_share`` of the scans. Works for bags per pose and for
    the snapshots of one continuous bag alike. Fewer than 4 scans: nothing is static.
    """
    if len(scans) < 4:
        return [np.zeros(len(s.points), bool) for s in scans]
    keys, qs = [], []
    for s in scans:
        p = np.asarray(s.points, float)
        ring = ring_of(s)
        r = np.linalg.norm(p, axis=1)
        ok = np.asarray(s.valid, bool) & np.isfinite(r) & (ring >= 0)
        p = np.where(ok[:, None], p, 1.0)  # invalid points (NaN in organised clouds) never reach the int casts
        az = np.arctan2(p[:, 1], p[:, 0])
        cell = ring * npoints_per_rotation + np.floor((az + np.pi) / (2 * np.pi) * npoints_per_rotation).astype(np.int64) % npoints_per_rotation
        keys.append(np.where(ok, cell, -1))
        qs.append(np.where(ok, np.floor(np.where(ok, r, 0.0) / quantum_m), -1).astype(np.int64))
    K = np.concatenate(keys)
    Q = np.concatenate(qs)
    good = K >= 0
    span = int(Q[good].max()) + 1 if good.any() else 1
    # one int64 per (cell, range bin): a 1-D unique is much faster than a row-wise one
    kq, counts = np.unique(K[good] * span + Q[good], return_counts=True)
    kc, qb = kq // span, kq % span
    # the most common range bin of each cell
    order = np.lexsort((-counts, kc))
    kc, qb, counts = kc[order], qb[order], counts[order]
    first = np.r_[True, kc[1:] != kc[:-1]]
    cells, mq, mc = kc[first], qb[first], counts[first]
    n = len(scans)
    out = []
    for k, q in zip(keys, qs):
        m = np.zeros(len(k), bool)
        j = np.searchsorted(cells, k)
        j = np.clip(j, 0, len(cells) - 1)
        hit = (k >= 0) & (cells[j] == k)
        m[hit] = (np.abs(q[hit] - mq[j[hit]]) <= 1) & (mc[j[hit]] >= min_share * n)
        out.append(m)
    return out
