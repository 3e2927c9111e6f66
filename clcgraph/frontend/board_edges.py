"""Where a LIDAR saw the board's outline: edge intervals for the in-plane factor
(factors/lidar_edge.py).

A plane tells a LIDAR nothing about where the board sits within it; its outline does. Where a
ring leaves the board, the board's edge lies between the ring's last return on the board and
its next ray (the ray after that if the next one returned nothing: a miss may be a dropout on
the board); above the highest ring on the board (below the lowest), between that ring and the
next ring's ray at the same azimuth. Such an interval is an edge only if that next ray went
*behind* the board's plane (by more than ``plane_tol_m``) or returned nothing: a ray that hit
something in front (the holder's arm, a hand) may hide the board, and one on the plane beside
it (the holder's body touching it) says nothing either. Each interval is kept as its two rays
(unit directions in the LIDAR frame); which side of the board it bounds is decided by the solver
from the board pose (factors/lidar_edge.py).

SYNOPSIS
    rays = edge_rays(scan_rays(scan, 2*pi/2048), board_rows (K,), n, d, outline, plane_tol_m=0.05)
    rays   # (E,2,3): per interval the ray of the return on the board, then the ray past the edge
"""

from __future__ import annotations

import numpy as np

from ..geometry import circular_mean, wrap_angle
from .board_outline import Outline, ScanRays, ray_plane
from .lidar_preprocess import ring_neighbours, slice_medians

# How far a fitted rectangle's side may lie from the board's (board_outline's finest grid cell:
# its centre to a cell, its angle to a cell at the corners)
_OUTLINE_TOL_M = 0.03


def exit_sides(q_in: np.ndarray, q_out: np.ndarray, lo: np.ndarray, hi: np.ndarray, *, tol_m: float = 0.0):
    """For segments q_in -> q_out (E,2) and the box lo <= q <= hi (2,), known to ``tol_m``: the side
    each segment leaves through, the one it heads to whose line is nearest its midpoint. (ok (E,):
    that line within ``tol_m`` plus the segment's length of the midpoint, and the other axis's
    line farther by more than that (not a corner, where either could be it); axis (E,) of that
    side (0, 1); sign (E,): +1 the hi side, -1 the lo side)."""
    E = len(q_in)
    dq = q_out - q_in
    mid = (q_in + q_out) / 2
    line = np.where(dq > 0, hi, lo)
    dist = np.where(dq != 0, np.abs(line - mid), np.inf)  # (E,2) to the side ahead along each axis
    axis = np.argmin(dist, axis=1)
    near, other = dist[np.arange(E), axis], dist[np.arange(E), 1 - axis]
    slack = tol_m + np.linalg.norm(dq, axis=1)
    ok = (near <= slack) & (other > near + slack)
    return ok, axis, np.where(dq[np.arange(E), axis] > 0, 1.0, -1.0)


def _behind_or_missed(R, pos: np.ndarray, n: np.ndarray, d: float, tol: float) -> np.ndarray:
    """(len(pos),) whether the returns at positions ``pos`` of ``R`` lie behind the plane
    n . x = d (n toward the sensor, d < 0: behind means n . x < d) by more than ``tol`` along
    their rays; -1 positions (misses) count as behind."""
    out = np.ones(len(pos), bool)
    hit = pos >= 0
    p = R.points[pos[hit]]
    r = R.range[pos[hit]]
    u = p / r[:, None]
    un = u @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = d / un  # range at which the ray meets the plane
    out[hit] = np.isfinite(t) & (t > 0) & (r - t > tol)
    return out


def edge_rays(rays: ScanRays, rows: np.ndarray, n: np.ndarray, d: float, outline: Outline, *,
              plane_tol_m: float) -> np.ndarray:
    """(E,3,3) the board's edge intervals in the scan of ``rays`` (``scan_rays``; LIDAR frame: unit
    ray on the board, unit ray past its edge, outward normal of that side of ``outline``). ``rows``:
    the scan rows of the board's returns (one unbroken piece per ring); n . x = d its plane;
    ``outline``: the board's rectangle fitted to them; ``plane_tol_m``: how far behind the plane a
    return must be to show the ray passed the board."""
    rows = np.asarray(rows, np.int64)
    n = np.asarray(n, float)
    if d > 0:
        n, d = -n, -d
    R, step_rad = rays.rings, rays.step_rad
    if not len(R.index) or not len(rows):
        return np.zeros((0, 3, 3))
    pos_of_row = np.full(rays.n_rows, -1, np.int64)
    pos_of_row[R.index] = np.arange(len(R.index))
    pos = pos_of_row[rows]
    pos = np.sort(pos[pos >= 0])
    prv, nxt = ring_neighbours(R)
    dirs, before, after = rays.missed
    first_miss_after = np.full(len(R.index), -1, np.int64)  # per return: the missed ray right after it
    first_miss_after[before[before >= 0]] = np.flatnonzero(before >= 0)
    last_miss_before = np.full(len(R.index), -1, np.int64)
    last_miss_before[after[after >= 0]] = np.flatnonzero(after >= 0)
    u = R.points / R.range[:, None]

    def missed_dir(k):  # the direction of missed ray k (rows where k is not a missed ray are not used)
        return dirs[np.clip(k, 0, len(dirs) - 1)] if len(dirs) else np.zeros((len(k), 3))

    on = np.zeros(len(R.index), bool)
    on[pos] = True

    # along the rings: the ends of each ring's piece, in azimuth about the board
    ring = R.ring[pos]
    rel = wrap_angle(R.azimuth[pos] - circular_mean(R.azimuth[pos]))
    order = np.lexsort((rel, ring))
    p_sorted, r_sorted = pos[order], ring[order]
    starts = np.r_[0, np.flatnonzero(np.diff(r_sorted)) + 1]
    ends = np.r_[starts[1:], len(p_sorted)] - 1
    out = []
    for end, step_to, miss_of, way in ((p_sorted[ends], nxt, first_miss_after, 1),
                                       (p_sorted[starts], prv, last_miss_before, -1)):
        # rel increases with azimuth, and a ring's positions run in azimuth order: the ray after
        # the highest-azimuth end is next along the ring (the first missed ray, or the next return)
        miss = miss_of[end]
        neighbour = np.where(miss >= 0, -1, step_to[end])
        ok = ~on[np.maximum(neighbour, 0)] | (neighbour < 0)
        ok &= _behind_or_missed(R, neighbour, n, d, plane_tol_m)
        # A missed ray beside the board may be a dropout on it (dark squares drop often): the edge
        # then lies before the ray after it, which bounds the interval instead (two steps long).
        # After a lone miss that is the next return: it must have passed the board, else the board
        # went on past a dropout and does not end here.
        m = np.maximum(miss, 0)
        side = after if way > 0 else before  # empty where the scan missed no ray (then miss < 0 everywhere)
        past_miss = side[np.minimum(m, len(side) - 1)] if len(side) else np.full(len(m), -1)
        lone = (miss >= 0) & (past_miss >= 0)
        beyond = np.where(lone, past_miss, -1)
        ok &= ~lone | (~on[np.maximum(beyond, 0)] & _behind_or_missed(R, beyond, n, d, plane_tol_m))
        # A return behind the plane: the next ray along the ring tells what it was. On the plane:
        # the board went on past a stray return (a heavy tail). Farther behind, or a miss: it lay
        # between the board and what is behind it, a mixed pixel whose beam may have been partly on
        # the board, so the edge lies before that next ray (two steps). At its depth: the edge.
        hit = (miss < 0) & (neighbour >= 0)
        n1 = np.maximum(neighbour, 0)
        miss2 = miss_of[n1]
        n2 = np.where(miss2 >= 0, -1, step_to[n1])
        ok &= ~hit | _behind_or_missed(R, n2, n, d, plane_tol_m)
        mixed = hit & ((n2 < 0) | (R.range[np.maximum(n2, 0)] > R.range[n1] + plane_tol_m))
        past = np.where((n2 < 0)[:, None], missed_dir(miss2), u[np.maximum(n2, 0)])
        ray_out = np.where((miss >= 0)[:, None], np.where(lone[:, None], u[np.maximum(beyond, 0)], missed_dir(m + way)),
                           np.where(mixed[:, None], past, u[n1]))
        out.append(np.stack([u[end], ray_out], axis=1)[ok])

    # across the rings: above the highest ring on the board, below the lowest, at the middle of
    # that ring's piece
    elev = slice_medians(np.arcsin(np.clip(u[:, 2], -1, 1)), R.starts)
    by_elev = np.argsort(elev)  # slices of R by elevation
    rank_of_slice = np.empty(len(elev), np.int64)
    rank_of_slice[by_elev] = np.arange(len(elev))
    slice_of_ring = {int(r): s for s, r in enumerate(R.ring_ids)}
    board_ranks = np.array(sorted({int(rank_of_slice[slice_of_ring[int(r)]]) for r in np.unique(ring)}))
    for rank, beyond in ((board_ranks.max(), 1), (board_ranks.min(), -1)):
        nb = rank + beyond
        if not 0 <= nb < len(elev):  # the board reaches the edge of the LIDAR's field of view
            continue
        s = by_elev[rank]
        mine = p_sorted[r_sorted == R.ring_ids[s]]
        mid = mine[len(mine) // 2]
        az = R.azimuth[mid]
        s2 = by_elev[nb]
        a, b = R.starts[s2], R.starts[s2 + 1]
        gap = np.abs(wrap_angle(R.azimuth[a:b] - az))
        k = int(np.argmin(gap)) if b > a else -1
        if k >= 0 and gap[k] <= 0.5 * step_rad:
            other = a + k
            if on[other] or not _behind_or_missed(R, np.array([other]), n, d, plane_tol_m)[0]:
                continue
            ray_out = u[other]
        else:  # that ring returned nothing there
            e = elev[s2]
            ray_out = np.array([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.sin(e)])
        out.append(np.stack([u[mid], ray_out])[None])
    if not out:
        return np.zeros((0, 3, 3))
    rays = np.concatenate(out)
    # the side of the LIDAR's own rectangle each interval leaves through
    xy_in, _, ahead_in = ray_plane(rays[:, 0], outline.n, outline.d, outline.origin, outline.basis)
    xy_out, _, ahead_out = ray_plane(rays[:, 1], outline.n, outline.d, outline.origin, outline.basis)
    to_rect = lambda xy: (xy - outline.centre) @ outline.axes.T  # noqa: E731  along the rectangle's sides
    half = outline.size / 2
    # the rectangle's sides are fitted to a grid cell and an angle step (1-3 cm at its corners)
    ok, axis, sign = exit_sides(to_rect(xy_in), to_rect(xy_out), -half, half, tol_m=_OUTLINE_TOL_M)
    ok &= ahead_in & ahead_out
    normal = (sign[:, None] * outline.axes[axis]) @ outline.basis  # (E,3) in the LIDAR frame
    return np.concatenate([rays, normal[:, None]], axis=1)[ok]
