"""Find the chessboard plane in a full LIDAR rotation, among ground, walls, poles, cars and people.

Three stages, as in the clc seed, vectorized per scan:

1. Segments: each ring is cut into runs of neighbouring returns (no azimuth gap longer than
   ``max_gap_points_stage1`` points, no range jump), runs into windows of ``points_per_segment``
   points; windows that are straight lines (RMS <= ``max_rms_segment_m``) are segments.
2. Clusters: segments of nearby rings that overlap in azimuth, run nearly parallel, lie a ring
   spacing apart, and whose common plane faces the sensor (<= ``max_tilt_deg`` off head-on) are
   linked; the ground (seen at grazing angles) falls out here. Connected components that are not
   one plane are split by RANSAC; a plane needs segments from >= ``min_rings`` rings.
3. Points: each candidate plane collects the contiguous coplanar returns of its rings and the
   rings next to it (gaps < ``max_gap_points_stage3``, no range jump). The board is then what
   fits the board's rectangle where the rest of the scan's rays show it can be (``board_outline``:
   pieces of ring beside it in its plane, a person, are dropped; no more than
   ``max_outside_fraction`` of its rings' returns may run on past it: a wall does), keeping one
   unbroken piece per ring, flat to within the range noise (``max_plane_rms_sigmas`` times the
   larger of the scan's and the plane's own along-ring noise), not too small, not a sliver, and
   crossed by a ring over most of its width once its rings span most of its height (a body or a
   post is tall and narrow).
   Exactly one such plane must remain (``require_unique``).

Static-scene suppression (``LidarOptions.suppress_static``) runs over a session before this:
walls and parked cars that never move are removed, the board (which moves) stays.

SYNOPSIS
    obs = segment_board(scan, SegmentationOptions(), LidarOptions(), BoardGeometry())
    obs -> LidarBoardObservation(points, plane, rms_m, indices, ring, edge_rays) or Rejected(reason)
    results = segment_many(scans, seg, lidar, board, sensor=1, snapshots=[0, 1, ...])
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from dataclasses import dataclass, field

import numpy as np

from ..errors import DataError
from ..geometry import azimuth, circular_mean, wrap_angle
from ..planes import fit_plane, ransac_plane
from ..two_processes import TwoProcesses
from ..types import BoardGeometry, LidarBoardObservation, LidarScan, Rejected
from .board_edges import edge_rays
from .board_outline import fit_outline, scan_rays
from .lidar_preprocess import (Rings, finite_rows, neighbour_steps, origin_height_m, prepare, ring_of, row_norms,
                               session_masks, slice_medians, typical_step)

STAGE = "segmentation"
log = logging.getLogger(__name__)


@dataclass
class _Segments:
    center: np.ndarray  # (S,3)
    direction: np.ndarray  # (S,3) unit
    rank: np.ndarray  # (S,) ring rank by elevation
    azimuth: np.ndarray  # (S,2) first and last point azimuth
    first: np.ndarray  # (S,) index into the Rings arrays of the first point
    run: np.ndarray  # (S,)
    window: np.ndarray  # (S,) window number within its run


@dataclass
class Debug:
    """What each stage found, for ``clcgraph segment --dump`` and pictures."""

    segments: np.ndarray | None = None  # (S,2,3) segment end points
    segment_rank: np.ndarray | None = None
    clusters: list = field(default_factory=list)  # per cluster: segment indices
    candidates: list = field(default_factory=list)  # (points indices into the scan, verdict)
    accepted: np.ndarray | None = None


def _max_jump(range_m, angle_rad, o):
    """Largest gap between neighbouring returns of one surface: 5 cm of range noise plus
    ``max_jump_spacings`` point spacings (a 60-deg tilted plane spaces returns 2 r dangle apart)."""
    return 0.05 + o.max_jump_spacings * range_m * angle_rad


def _across_rings(range_m, del_el, o):
    """Largest distance between the lines of two rings on a plane <= max_tilt off head-on."""
    return 0.05 + o.ring_spacing_tolerance * range_m * del_el / np.cos(np.radians(o.max_tilt_deg))


def _ring_ranks(R: Rings) -> tuple[np.ndarray, np.ndarray]:
    """Per point the ring's rank by elevation (ring numbers need not be ordered), and the
    elevation (rad) of each rank."""
    el = np.arcsin(np.clip(R.points[:, 2] / np.maximum(R.range, 1e-9), -1, 1))
    med = slice_medians(el, R.starts)
    order = np.argsort(med)
    rank_of_slice = np.empty(len(med), np.int64)
    rank_of_slice[order] = np.arange(len(med))
    per_point = np.repeat(rank_of_slice, np.diff(R.starts))
    return per_point, med[order]


def _azimuth_step(R: Rings, npoints_per_rotation: int | None) -> float:
    if npoints_per_rotation:
        return 2 * np.pi / npoints_per_rotation
    return typical_step(neighbour_steps(R)) or 2 * np.pi / 1800


def _stage1(R: Rings, rank: np.ndarray, step: float, o) -> tuple[_Segments, np.ndarray, float]:
    """Straight windows of ``points_per_segment`` neighbouring returns along each ring: the
    segments, their points, and the range noise they show."""
    k = o.points_per_segment
    p = R.points
    same_ring = R.ring[1:] == R.ring[:-1]
    daz = np.diff(R.azimuth)
    jump = row_norms(np.diff(p, axis=0))
    max_jump = _max_jump(R.range[:-1], np.maximum(daz, step), o)
    linked = same_ring & (daz <= (o.max_gap_points_stage1 + 1.5) * step) & (jump <= max_jump)
    run = np.r_[0, np.cumsum(~linked)]
    run_start = np.r_[0, np.flatnonzero(~linked) + 1]
    pos = np.arange(len(p)) - run_start[run]
    run_len = np.diff(np.r_[run_start, len(p)])
    window = pos // k
    full = (window + 1) * k <= run_len[run]
    first = np.flatnonzero(full & (pos % k == 0))
    W = p[first[:, None] + np.arange(k)]  # (S,k,3)
    c = W.mean(axis=1)
    X = W - c[:, None]
    cov = np.einsum("ski,skj->sij", X, X) / k
    lam, vec = np.linalg.eigh(cov)
    rms = np.sqrt(np.maximum(lam[:, 0] + lam[:, 1], 0))
    ok = rms <= o.max_rms_segment_m
    # this LIDAR's range noise, from its straight segments (2 of k dof go to the line fit)
    noise = float(np.median(rms[ok]) * np.sqrt(k / (k - 2))) if ok.any() else o.max_plane_rms_m
    first = first[ok]
    seg = _Segments(
        center=c[ok], direction=vec[ok, :, 2], rank=rank[first],
        azimuth=np.c_[R.azimuth[first], R.azimuth[first + k - 1]],
        first=first, run=run[first], window=window[first],
    )
    return seg, W[ok], noise


def _links(seg: _Segments, rank_elevation: np.ndarray, o) -> np.ndarray:
    """(L,2) pairs of segments that plausibly lie on one plane facing the sensor."""
    pairs = []
    # same ring: consecutive windows of one run, nearly collinear
    a = np.flatnonzero((seg.run[1:] == seg.run[:-1]) & (seg.window[1:] == seg.window[:-1] + 1))
    cos_same = np.abs(np.einsum("ij,ij->i", seg.direction[a], seg.direction[a + 1]))
    pairs.append(np.c_[a, a + 1][cos_same >= np.cos(np.radians(o.max_angle_same_ring_deg))])
    # across rings: overlapping azimuth intervals in a ring 1-2 ranks away
    by_rank = {r: np.flatnonzero(seg.rank == r) for r in np.unique(seg.rank)}
    lo_az = seg.azimuth.min(axis=1)
    hi_az = seg.azimuth.max(axis=1)
    for r, A in by_rank.items():
        for dr in range(1, o.max_ring_step + 1):
            B = by_rank.get(r + dr)
            if B is None:
                continue
            B = B[np.argsort(lo_az[B])]
            # B's intervals are disjoint and sorted, so their ends are sorted too
            lo = np.searchsorted(hi_az[B], lo_az[A])
            hi = np.searchsorted(lo_az[B], hi_az[A], side="right")
            n = np.maximum(hi - lo, 0)
            if not n.sum():
                continue
            ia = np.repeat(A, n)
            ib = B[np.concatenate([np.arange(l, h) for l, h in zip(lo[n > 0], hi[n > 0])])]
            pairs.append(np.c_[ia, ib])
    P = np.concatenate(pairs) if pairs else np.zeros((0, 2), np.int64)
    if not len(P):
        return P
    ca, cb = seg.center[P[:, 0]], seg.center[P[:, 1]]
    va, vb = seg.direction[P[:, 0]], seg.direction[P[:, 1]]
    cross = seg.rank[P[:, 0]] != seg.rank[P[:, 1]]
    d = cb - ca
    d_perp = d - np.einsum("ij,ij->i", d, va)[:, None] * va
    dist_perp = row_norms(d_perp)
    r = row_norms(ca)
    del_el = np.abs(rank_elevation[seg.rank[P[:, 0]]] - rank_elevation[seg.rank[P[:, 1]]])
    max_perp = _across_rings(r, del_el, o)
    parallel = np.abs(np.einsum("ij,ij->i", va, vb)) >= np.cos(np.radians(o.max_angle_cross_ring_deg))
    n = np.cross(va, d_perp)
    n /= np.maximum(row_norms(n), 1e-12)[:, None]
    facing = np.abs(np.einsum("ij,ij->i", n, ca / r[:, None])) >= np.cos(np.radians(o.max_tilt_deg))
    keep = ~cross | (parallel & (dist_perp <= max_perp) & (dist_perp > 1e-3) & facing)
    return P[keep]


def _components(n: int, links: np.ndarray) -> np.ndarray:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    g = coo_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])), shape=(n, n))
    return connected_components(g, directed=False)[1]


def _ransac_planes(points: np.ndarray, owner: np.ndarray, tol: float, min_points: int, inlier_share: float,
                   max_planes: int = 4):
    """Split a cluster's segment points into planes; yields the segment ids of each plane."""
    remaining = np.arange(len(points))
    for _ in range(max_planes):
        if len(remaining) < min_points:
            return
        inl = remaining[ransac_plane(points[remaining], tol)]
        ids, counts = np.unique(owner[inl], return_counts=True)
        total = np.bincount(owner[remaining], minlength=owner.max() + 1)[ids]
        segs = ids[counts >= inlier_share * total]
        if not len(segs):
            return
        yield segs
        remaining = remaining[~np.isin(owner[remaining], segs)]


def _stage3(R: Rings, rank: np.ndarray, rank_el: np.ndarray, members: np.ndarray, n: np.ndarray, d: float,
            step: float, o) -> np.ndarray:
    """Rows of R on the plane, contiguous along their ring (no range jump, gaps shorter than
    ``max_gap_points_stage3``) with the cluster's points; in the rings next to the cluster, runs
    one ring spacing from it (partly covered rings at the board's edges)."""
    from scipy.spatial import cKDTree

    tol = o.point_plane_tolerance_m
    mrank = rank[members]
    lo_r, hi_r = mrank.min() - o.max_ring_step, mrank.max() + o.max_ring_step
    az0 = circular_mean(R.azimuth[members])
    rel = lambda az: wrap_angle(az - az0)  # noqa: E731  azimuth around the cluster
    out, pending = [], []
    is_member = np.zeros(len(R.index), bool)  # a run holds one of its ring's members (no np.isin per run)
    is_member[members] = True
    for a, b in zip(R.starts[:-1], R.starts[1:]):
        rk = rank[a]
        if not lo_r <= rk <= hi_r:
            continue
        az = rel(R.azimuth[a:b])
        order = np.argsort(az)
        rows = (a + order)[np.abs(R.points[a + order] @ n - d) <= tol]
        if not len(rows):
            continue
        pos = np.searchsorted(az[order], rel(R.azimuth[rows]))  # position along the ring
        jump = row_norms(np.diff(R.points[rows], axis=0))
        max_jump = _max_jump(R.range[rows[:-1]], step * np.clip(np.diff(pos), 1, 2), o)
        brk = np.flatnonzero((np.diff(pos) > o.max_gap_points_stage3) | (jump > max_jump))
        has_members = bool((mrank == rk).any())
        for run in np.split(rows, brk + 1):
            if has_members:
                if is_member[run].any():  # a run lies in one ring: only that ring's members can be in it
                    out.append(run)
            elif len(run) >= 2:
                pending.append((rk, run))
    rows = np.concatenate(out)
    if pending:
        tree = cKDTree(R.points[rows])
        m_az = rel(R.azimuth[members])
        lo_az, hi_az = m_az.min() - 2 * step, m_az.max() + 2 * step
        for rk, run in pending:
            run = run[(rel(R.azimuth[run]) >= lo_az) & (rel(R.azimuth[run]) <= hi_az)]
            if len(run) < 2:
                continue
            gap = abs(rank_el[rk] - rank_el[np.clip(rk, mrank.min(), mrank.max())])
            reach = _across_rings(R.range[run].mean(), gap, o)
            if tree.query(R.points[run], distance_upper_bound=reach)[0].min() <= reach:
                out.append(run)
    return np.concatenate(out)


def _in_plane(points: np.ndarray, n: np.ndarray) -> np.ndarray:
    u = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    return np.c_[points @ u, points @ np.cross(n, u)]


def _spans(points: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(36,) the in-plane extents along directions 5 deg apart (the 19th is at right angles to the first)."""
    q = _in_plane(points, n)
    ang = np.linspace(0, np.pi, 36, endpoint=False)
    proj = q @ np.stack([np.cos(ang), np.sin(ang)])
    return proj.max(axis=0) - proj.min(axis=0)


def _extents(points: np.ndarray, n: np.ndarray) -> tuple[float, float]:
    """(diameter, width): the largest in-plane extent over 36 directions, and the smallest."""
    span = _spans(points, n)
    return float(span.max()), float(span.min())


def _bounding_rectangle(span: np.ndarray) -> tuple[float, float]:
    """(shorter, longer) side of the smallest-area rectangle around points of ``_spans`` ``span``."""
    i = int(np.argmin(span * np.roll(span, 18)))
    return tuple(sorted((float(span[i]), float(span[(i + 18) % 36]))))


def _chord_and_height(pts: np.ndarray, ring: np.ndarray, n: np.ndarray) -> tuple[float, float]:
    """The longest extent of one ring's points across the plane (rings cut planes nearly level),
    and the in-plane extent across the rings."""
    h = np.cross(n, [0.0, 0.0, 1.0])
    h = h / np.linalg.norm(h) if np.linalg.norm(h) > 1e-6 else np.array([1.0, 0.0, 0.0])
    x = pts @ h
    y = pts @ np.cross(n, h)
    order = np.lexsort((x, ring))
    x, ring = x[order], ring[order]
    starts = np.r_[0, np.flatnonzero(np.diff(ring)) + 1]
    ends = np.r_[starts[1:], len(x)] - 1
    return float((x[ends] - x[starts]).max()), float(np.ptp(y))


def _ring_pieces(pts: np.ndarray, ring: np.ndarray, step: float, o) -> np.ndarray:
    """(N,) piece number per point: the points of one ring in azimuth order, cut wherever a 3D
    jump exceeds ``max_jump_spacings`` point spacings (a body or post beside the board, crossing
    its plane, is a piece of its own)."""
    az = azimuth(pts)
    az = wrap_angle(az - circular_mean(az))
    order = np.lexsort((az, ring))
    p, r = pts[order], ring[order]
    jump = row_norms(np.diff(p, axis=0))
    limit = _max_jump(row_norms(p[:-1]), step, o)
    piece = np.empty(len(pts), np.int64)
    piece[order] = np.r_[0, np.cumsum((jump > limit) | (r[1:] != r[:-1]))]
    return piece


def _main_piece_per_ring(pts: np.ndarray, ring: np.ndarray, step: float, o) -> np.ndarray:
    """(N,) mask keeping, in each ring, its longest piece (``_ring_pieces``)."""
    piece = _ring_pieces(pts, ring, step, o)
    size = np.bincount(piece)
    ring_of_piece = np.zeros(len(size), ring.dtype)
    ring_of_piece[piece] = ring
    best = {}
    for k in np.argsort(size):  # ascending: the largest piece of each ring is written last
        best[ring_of_piece[k]] = k
    return np.isin(piece, list(best.values()))


# Fewer returns than this on a ring are not a piece of the board's outline (_verdict).
_MIN_RING_PIECE = 3
# A ring's piece this far off the plane of the board's other rings is something else (a head
# above the board's edge, a shoulder behind its corner): real per-laser range offsets reach 2-3 cm.
_OFF_PLANE_RING_M = 0.05


def _off_plane_ring(pts: np.ndarray, ring: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """(N,) mask of the kept points of the ring whose pieces lie furthest off the plane of the other
    kept rings (median distance), if that is beyond ``_OFF_PLANE_RING_M`` and 4 robust spreads of
    every ring's such distance; all False if none is, or fewer than 4 rings are kept (3 must remain)."""
    rings, r = np.unique(ring[keep], return_inverse=True)
    none = np.zeros(len(pts), bool)
    if len(rings) < 4:
        return none
    # each plane of all rings but one from the per-ring sums (one pass, no refit per ring)
    p = pts[keep] - pts[keep].mean(axis=0)
    count = np.bincount(r, minlength=len(rings)).astype(float)
    s1 = np.stack([np.bincount(r, p[:, a], len(rings)) for a in range(3)], axis=1)  # (R,3)
    s2 = np.zeros((len(rings), 3, 3))
    np.add.at(s2, r, p[:, :, None] * p[:, None, :])
    n_o, s1_o, s2_o = count.sum() - count, s1.sum(axis=0) - s1, s2.sum(axis=0) - s2
    c_o = s1_o / n_o[:, None]
    normal = np.linalg.eigh(s2_o / n_o[:, None, None] - c_o[:, :, None] * c_o[:, None, :])[1][:, :, 0]
    normal *= np.sign(normal @ normal[0])[:, None]  # one side of the board for every plane
    off = np.array([np.median((p[r == k] - c_o[k]) @ normal[k]) for k in range(len(rings))])
    dev = np.abs(off - np.median(off))
    worst = int(np.argmax(dev))
    spread = 1.4826 * np.median(np.delete(dev, worst))
    if dev[worst] <= max(_OFF_PLANE_RING_M, 4.0 * spread):
        return none
    return keep & (ring == rings[worst])


def _local_noise(pts: np.ndarray, ring: np.ndarray, k: int) -> float:
    """The range noise of the plane's own returns: the median RMS of straight-line fits to
    windows of ``k`` neighbouring returns along each ring, as _stage1 measures the scan's
    (0 when no ring has ``k`` returns)."""
    az = azimuth(pts)
    order = np.lexsort((wrap_angle(az - circular_mean(az)), ring))
    p, r = pts[order], ring[order]
    starts = np.r_[0, np.flatnonzero(np.diff(r)) + 1]
    ends = np.r_[starts[1:], len(r)]
    first = [np.arange(a, b - k + 1, k) for a, b in zip(starts, ends) if b - a >= k]
    if not first:
        return 0.0
    W = p[np.concatenate(first)[:, None] + np.arange(k)]
    X = W - W.mean(axis=1)[:, None]
    lam = np.linalg.eigvalsh(np.einsum("ski,skj->sij", X, X) / k)
    return float(np.median(np.sqrt(np.maximum(lam[:, 0] + lam[:, 1], 0))) * np.sqrt(k / (k - 2)))


def _rms_about_ring_offsets(pts: np.ndarray, ring: np.ndarray, n: np.ndarray, d: float) -> float:
    """RMS of the distances to the plane n . x = d about each ring's mean distance (the dof of
    the per-ring means taken out)."""
    res = pts @ n - d
    _, r = np.unique(ring, return_inverse=True)
    counts = np.bincount(r)
    within = res - (np.bincount(r, weights=res) / counts)[r]
    dof = max(len(res) - len(counts) - 2, 1)  # ring means + the plane's tilt
    return float(np.sqrt(np.sum(within**2) / dof))


def _verdict(pts: np.ndarray, ring: np.ndarray, board: BoardGeometry, step: float, noise_m: float, o,
             intensity: np.ndarray | None = None, others: np.ndarray | None = None):
    """Whether ``pts`` (with their ring ranks and ``intensity``) are the board: (None or why not,
    the refit plane (n, d, rms), the mask of the points kept, the fitted board_outline.Outline). ``others``: the scan's other
    returns, whose rays tell where the board is not (``fit_outline``). The plane and its flatness
    are judged with the dark squares' range walk removed (``dark_square_correction``)."""
    keep = np.ones(len(pts), bool)
    n, d, rms = fit_plane(pts)
    c = pts.mean(axis=0)
    at = f"plane at {np.linalg.norm(c):.1f} m"
    sx, sy = board.size_m  # the physical board (width, height), border included
    # edges bloom by about one point spacing and the range noise
    spacing_m = float(row_norms(pts).mean() * step)
    slack = 0.05 + 2.0 * spacing_m
    max_size = o.max_plane_size_m if o.max_plane_size_m is not None else float(np.hypot(sx + slack, sy + slack))
    others = np.zeros((0, 3)) if others is None else others
    outline = fit_outline(pts, others, n, d, size_m=(sx, sy), step_rad=step, plane_tol_m=o.point_plane_tolerance_m)
    keep = outline.inside
    if keep.sum() >= 3 and not keep.all():  # again on the plane of what fits: the rest may have tilted it
        n, d, _ = fit_plane(pts[keep])
        outline = fit_outline(pts, others, n, d, size_m=(sx, sy), step_rad=step, plane_tol_m=o.point_plane_tolerance_m,
                              near=outline)
        keep = outline.inside
    # Pieces of ring outside the board's rectangle are dropped (a person beside it, in its plane);
    # a plane whose rings run on past the rectangle is not a board (a wall, a car).
    piece = _ring_pieces(pts, ring, step, o)
    touching = np.isin(piece, piece[keep])
    beyond = (touching & ~keep).sum() / max(touching.sum(), 1)
    if keep.sum() < o.points_per_segment * o.min_rings:
        return (f"{at}: only {keep.sum()} of its {len(pts)} returns fit a {sx:.2f} x {sy:.2f} m rectangle where "
                f"the scan shows no board missing"), (n, d, rms), keep, outline
    if beyond > o.max_outside_fraction:
        span = _spans(pts, n)
        w, h = _bounding_rectangle(span)  # what the plane measures, to set against board.size_m
        return (f"{at}, {w:.2f} x {h:.2f} m ({span.max():.2f} m across), {beyond:.0%} of it outside any "
                f"{sx:.2f} x {sy:.2f} m rectangle: a wall, car, person or the board touching something"), (n, d, rms), keep, \
            outline
    # coplanar things crossing the board plane (a body, a hand) drift off it away from the crossing
    for _ in range(2):
        n, d, _ = fit_plane(pts[keep])
        res = np.abs(pts @ n - d)
        sigma = 1.4826 * np.median(res[keep])
        keep &= res <= max(3.0 * sigma, 0.01)
    keep[keep] = _main_piece_per_ring(pts[keep], ring[keep], step, o)
    # a ring's piece of one or two returns cannot tell the board from something coplanar beside it
    # (a hand, a head just above its edge), and would place the outline's edge there
    rings, counts = np.unique(ring[keep], return_counts=True)
    short = keep & np.isin(ring, rings[counts < _MIN_RING_PIECE])
    off = _off_plane_ring(pts, ring, keep & ~short)
    if (short | off).any() and (keep & ~short & ~off).sum() >= 3:
        keep &= ~(short | off)
        n, d, _ = fit_plane(pts[keep])
        # the board is not where an off-plane ring's rays crossed its plane: the outline again without it
        outline = fit_outline(pts[keep], np.r_[others, pts[off]], n, d, size_m=(sx, sy), step_rad=step,
                              plane_tol_m=o.point_plane_tolerance_m)
        keep[keep] = outline.inside
        if keep.sum() < o.points_per_segment * o.min_rings:
            return (f"{at}: only {keep.sum()} of its {len(pts)} returns fit a {sx:.2f} x {sy:.2f} m rectangle "
                    f"without its rings off the plane or of one or two returns"), (n, d, rms), keep, outline
    pts, ring = pts[keep], ring[keep]
    if intensity is not None:
        pts, _ = dark_square_correction(pts, intensity[keep])
    n, d, rms = fit_plane(pts)
    if d > 0:
        n, d = -n, -d  # normal toward the sensor at the origin
    plane = (n, d, rms)
    tilt = np.degrees(np.arccos(min(1.0, abs(n @ c) / np.linalg.norm(c))))
    n_rings = len(np.unique(ring))
    diameter, width = _extents(pts, n)
    diag = float(np.hypot(sx, sy))
    chord, height = _chord_and_height(pts, ring, n)
    need_chord = max(o.min_chord_fraction * min(sx, sy), 0.6 * min(height, sx, sy))
    # Flat means as flat across the board as along a few of its returns: real returns off a
    # chessboard are noisier than the scan's walls (dark squares, range walk with intensity),
    # so the plane's own along-ring noise counts too; a body or a curved surface is straight
    # along 8 returns but far off one plane.
    local_m = _local_noise(pts, ring, o.points_per_segment)
    # Real LIDARs range each laser with its own offset (1-3 cm, the same in every scan): a flat
    # board's rings then sit at different depths. So the noise bound applies to the points about
    # their own ring's offset (a body or a corner is curved along its rings), and the whole
    # plane's RMS, ring offsets included, only has to stay under max_plane_rms_m.
    rms_ring = _rms_about_ring_offsets(pts, ring, n, d)
    if n_rings < o.min_rings:
        why = f"{at} crosses {n_rings} rings < min_rings {o.min_rings}"
    elif rms > o.max_plane_rms_m or rms_ring > o.max_plane_rms_sigmas * max(noise_m, local_m):
        why = (f"{at} not flat: RMS {rms * 1e3:.0f} mm (about each ring's offset {rms_ring * 1e3:.0f} mm) > "
               f"max_plane_rms_m {o.max_plane_rms_m * 1e3:.0f} mm or, about the ring offsets, "
               f"{o.max_plane_rms_sigmas:g} x the range noise (scan {noise_m * 1e3:.0f} mm, along this plane's "
               f"rings {local_m * 1e3:.0f} mm)")
    elif tilt > o.max_tilt_deg:
        why = f"{at} tilted {tilt:.0f} deg from head-on > max_tilt_deg"
    elif diameter > max_size:
        why = f"{at} is {diameter:.2f} m across > max_plane_size_m {max_size:.2f} m"
    elif diameter < o.min_plane_size_fraction * diag:
        why = f"{at} is {diameter:.2f} m across, smaller than {o.min_plane_size_fraction:g} of the board diagonal"
    elif width < o.min_width_fraction * min(sx, sy):
        why = f"{at} is a {width:.2f} m wide sliver"
    elif chord < need_chord - slack:
        # a ring crosses a square board's middle once its rings span most of its height; and near
        # a corner (any roll) the crossing is at least as long as the height seen
        why = (f"{at}: its longest ring crossing is {chord:.2f} m, less than {need_chord:.2f} m for a board "
               f"seen {height:.2f} m high (a person, a post?)")
    else:
        why = None
    return why, plane, keep, outline


def segment_board(scan: LidarScan, options, lidar_options, board: BoardGeometry, *, sensor: int = 0,
                  snapshot: int = 0, exclude: np.ndarray | None = None, npoints_per_rotation: int | None = None,
                  debug: Debug | None = None) -> LidarBoardObservation | Rejected:
    """The board in one scan, or Rejected(reason). ``exclude``: (N,) rows to ignore (static scene)."""
    o = options

    def rejected(why):
        return Rejected(f"{scan.topic} at {scan.stamp_ns} ns: {why}", STAGE, sensor, snapshot)

    every = prepare(scan)  # the board's outline and edges look at every ray, the segmentation within range
    R = every.within(min_range_m=lidar_options.min_range_m, max_range_m=lidar_options.max_range_m, exclude=exclude)
    if len(R.index) < o.points_per_segment * o.min_rings:
        return rejected(f"only {len(R.index)} points within {lidar_options.min_range_m}-"
                        f"{lidar_options.max_range_m} m")
    rank, rank_el = _ring_ranks(R)
    step = _azimuth_step(R, npoints_per_rotation or lidar_options.npoints_per_rotation)
    seg, seg_pts, noise = _stage1(R, rank, step, o)
    if debug is not None:
        k = o.points_per_segment
        debug.segments = np.stack([R.points[seg.first], R.points[seg.first + k - 1]], axis=1)
        debug.segment_rank = seg.rank
    if len(seg.first) < o.min_segments_per_cluster:
        return rejected(f"only {len(seg.first)} straight segments along the rings")
    links = _links(seg, rank_el, o)
    comp = _components(len(seg.first), links)
    k = o.points_per_segment
    pieces, reasons = [], []
    for cid in np.flatnonzero(np.bincount(comp) >= o.min_segments_per_cluster):
        ids = np.flatnonzero(comp == cid)
        if len(np.unique(seg.rank[ids])) < o.min_rings:
            continue
        if debug is not None:
            debug.clusters.append(ids)
        pts = seg_pts[ids].reshape(-1, 3)
        owner = np.repeat(ids, k)
        _, _, rms = fit_plane(pts)
        planes = [ids] if rms <= o.point_plane_tolerance_m / 2 and len(ids) <= o.max_segments_per_cluster \
            else _ransac_planes(pts, owner, o.point_plane_tolerance_m, k * o.min_segments_per_cluster,
                                o.segment_inlier_share)
        for segs in planes:
            if len(segs) < o.min_segments_per_cluster or len(np.unique(seg.rank[segs])) < o.min_rings:
                continue
            if len(segs) > o.max_segments_per_cluster:
                reasons.append((len(segs) * k, f"plane of {len(segs)} segments > max_segments_per_cluster"))
                continue
            n, d, _ = fit_plane(seg_pts[segs].reshape(-1, 3))
            members = (seg.first[segs, None] + np.arange(k)).ravel()
            rows = _stage3(R, rank, rank_el, members, n, d, step, o)
            if len(rows) >= len(members) // 2:
                pieces.append((rows, n, d))
    found = []
    # every ray of the scan, those that returned nothing included: where one passed behind a
    # candidate plane, no board was in its way
    rays = scan_rays(scan, step, rings=every)
    intensity = None if scan.intensity is None else np.asarray(scan.intensity, float)[R.index]
    diag = float(np.hypot(*board.size_m))
    for rows in _merge(pieces, R.points, o.point_plane_tolerance_m, diag):
        # the rays that can count in the board's outline fit: near the candidate (its diagonal,
        # and a margin for the plane's refit in the verdict), not next to it along a ring
        n, d, _ = fit_plane(R.points[rows])
        near = rays.around(R.points[rows], n, d, 1.2 * diag)
        near = near[rays.away_from(R.index[rows])[near]]
        why, plane, keep, outline = _verdict(R.points[rows], rank[rows], board, step, noise, o,
                                             None if intensity is None else intensity[rows], rays.points[near])
        rows = rows[keep]
        if o.debug_region is not None:
            c = R.points[rows].mean(axis=0) if len(rows) else np.full(3, np.nan)
            x0, x1, y0, y1 = o.debug_region
            if x0 <= c[0] <= x1 and y0 <= c[1] <= y1:
                # warning level: asked for explicitly, so shown even when progress notes are not
                log.warning("debug %s @%d: plane at (%.2f, %.2f, %.2f) m, %d points on %d rings: %s", scan.topic,
                            scan.stamp_ns, *c, len(rows), len(np.unique(rank[rows])), why or "accepted")
        if debug is not None:
            debug.candidates.append((R.index[rows], why or "accepted"))
        if why is None:
            found.append((rows, plane, outline))
        else:
            reasons.append((len(rows), why))
    if not found:
        if not reasons:
            return rejected(f"no flat cluster of >= {o.min_segments_per_cluster} segments over "
                            f">= {o.min_rings} rings facing the sensor")
        # the verdicts on the largest candidates first: the board is usually among them
        seen, top = set(), []
        for _, why in sorted(reasons, key=lambda x: -x[0]):
            if why not in seen:
                seen.add(why)
                top.append(why)
        return rejected("no board-like plane; " + "; ".join(top[:3]))
    if len(found) > 1 and o.require_unique:
        where = ", ".join(f"{np.linalg.norm(R.points[r].mean(axis=0)):.1f} m" for r, _, _ in found)
        return rejected(f"{len(found)} board-like planes (at {where}); require_unique")
    rows, (n, d, rms), outline = max(found, key=lambda f: len(f[0]))
    idx = np.sort(R.index[rows])
    if debug is not None:
        debug.accepted = idx
    pts = np.asarray(scan.points, float)[idx]
    if scan.intensity is not None:  # the plane is already the corrected points' (_verdict)
        pts, offset = dark_square_correction(pts, np.asarray(scan.intensity, float)[idx])
        if offset:
            log.debug("%s: the board's weak returns range %.1f mm long; corrected", scan.topic, offset * 1e3)
    ring = ring_of(scan)[idx]
    # a ray passed the board if its return lies behind the plane by more than the range noise explains
    # (a board return 2 sigma long would otherwise end the board early on a noisy LIDAR)
    edges = edge_rays(rays, idx, n, d, outline, plane_tol_m=max(o.point_plane_tolerance_m, 4.0 * noise))
    return LidarBoardObservation(sensor=sensor, snapshot=snapshot, points=pts, plane=np.r_[n, d], rms_m=rms,
                                 indices=idx, ring=ring, edge_rays=edges)


# Fewest returns of either intensity group for dark_square_correction: the offset between their
# medians is tested against its standard error, which needs a few returns to mean anything.
_MIN_INTENSITY_GROUP = 10


def dark_square_correction(pts: np.ndarray, intensity: np.ndarray) -> tuple[np.ndarray, float]:
    """(points, range offset in m or 0.0): a chessboard's dark squares return weak and, in real
    LIDARs, long (range walk: 1-2 cm). When the board's returns fall into two intensity groups
    (the pattern) whose ranges to the bright group's plane differ significantly (> 4 standard
    errors), the weak returns are moved back along their rays by that offset: the bright squares
    and the white border return like the targets a LIDAR's ranges are calibrated on.

    Groups: the two means of the intensities (1-D 2-means), each of >= 10 returns and apart by
    more than 4x their pooled spread; otherwise nothing is changed. No share of the returns is
    asked of the weak group: where most of the dark squares return nothing (a black print that
    absorbs the laser, a laminated one that mirrors it away) the few that do are still long."""
    if len(pts) < 20 or not np.all(np.isfinite(intensity)):
        return pts, 0.0
    lo, hi = np.percentile(intensity, [5, 95])
    if not hi > lo:
        return pts, 0.0
    thr = (lo + hi) / 2
    for _ in range(10):  # 2-means in one dimension
        weak = intensity < thr
        if weak.all() or not weak.any():
            return pts, 0.0
        new = (intensity[weak].mean() + intensity[~weak].mean()) / 2
        if new == thr:
            break
        thr = new
    spread = np.sqrt((intensity[weak].var() * weak.sum() + intensity[~weak].var() * (~weak).sum()) / len(pts))
    if min(weak.sum(), (~weak).sum()) < _MIN_INTENSITY_GROUP or \
            intensity[~weak].mean() - intensity[weak].mean() <= 4 * spread:
        return pts, 0.0
    n, d, _ = fit_plane(pts[~weak])
    r = row_norms(pts)
    u = pts / r[:, None]
    along = d / (u @ n)  # where each ray meets the bright returns' plane
    delta = r - along
    a, b = delta[weak], delta[~weak]
    offset = float(np.median(a) - np.median(b))
    se = 1.2533 * np.sqrt(np.var(a) / len(a) + np.var(b) / len(b))  # of a median
    if abs(offset) <= 4 * se:
        return pts, 0.0
    out = pts.copy()
    out[weak] = u[weak] * (r[weak] - offset)[:, None]
    return out, offset


def _merge(pieces: list, points: np.ndarray, tol: float, reach: float) -> list:
    """Rows per physical plane: coplanar pieces within ``reach`` of each other (a board split by
    the azimuth wrap, a dropout or RANSAC) join up, and so do pieces that grew over the same
    returns (most of the smaller one's: a return lies on one surface; with noisy returns the
    pieces' own plane fits can differ by more than the coplanarity test allows)."""
    groups: list = []  # [rows, n, d]
    for rows, n, d in pieces:
        c = points[rows].mean(axis=0)
        for g in groups:
            c2 = points[g[0]].mean(axis=0)
            shared = np.intersect1d(rows, g[0], assume_unique=True).size
            same = (abs(n @ g[1]) > np.cos(np.radians(10)) and abs(c @ g[1] - g[2]) < tol
                    and abs(c2 @ n - d) < tol and np.linalg.norm(c - c2) < reach) \
                or 2 * shared > min(len(rows), len(g[0]))
            if same:
                g[0] = np.union1d(g[0], rows)
                break
        else:
            groups.append([rows, n, d])
    return [g[0] for g in groups]


# A LIDAR's rings meet within a few cm of its origin (beam offsets: HDL-64 up to ~0.25 m); a cloud
# moved into base_link has them 1-2 m off
_MAX_ORIGIN_HEIGHT_M = 0.5


def _check_sensor_frame(scans) -> None:
    """DataError if the scans are not in their LIDAR's own frame (``origin_height_m``, judged on the
    first of the first 3 scans that tells): the rays from the origin the segmentation and the board's
    outline rest on would not be the LIDAR's."""
    for scan in scans[:3]:
        h = origin_height_m(scan)
        if h is None:
            continue
        if abs(h) > _MAX_ORIGIN_HEIGHT_M:
            raise DataError(f"{scan.topic}: its points are not in the LIDAR's own frame: its rings meet about {abs(h):.1f} m "
                            f"{'above' if h > 0 else 'below'} the cloud's origin (a cloud already moved into base_link "
                            "or another frame?); record the driver's cloud in the sensor's frame")
        return


def segment_many(scans, options, lidar_options, board: BoardGeometry, *, sensor: int = 0,
                 snapshots=None, jobs: int | None = None, progress=None, debug: list | None = None,
                 ring_offsets: dict | None = None) -> list:
    """segment_board over a session of one LIDAR (static scene removed when suppress_static),
    by this process and a forked one (``jobs`` 1: this one alone). ``progress``: optional wrapper
    of an iteration over the scans (a progress bar);
    ``debug``: one Debug per scan to fill; ``ring_offsets``: filled with {ring: range offset (m)}
    taken out of the scans (``ring_range_offsets``), if any was."""
    scans = list(scans)
    snapshots = list(range(len(scans))) if snapshots is None else list(snapshots)
    if not scans:
        return []
    _check_sensor_frame(scans)
    npoints, static = session_masks(scans, lidar_options)

    def one(k):  # (result, its Debug or None): a Debug filled in a forked process is sent back with it
        d = None if debug is None else Debug()
        return segment_board(scans[k], options, lidar_options, board, sensor=sensor, snapshot=snapshots[k],
                             exclude=static[k], npoints_per_rotation=npoints, debug=d), d

    def all_scans(progress):
        ticks = iter(progress(range(len(scans)), len(scans))) if progress else iter(())
        shown = 0

        def advance(taken):
            nonlocal shown
            for _ in range(taken - shown):
                next(ticks, None)
            shown = max(shown, taken)

        # two processes, not threads: a scan's segmentation is many small numpy steps, between
        # which a thread holds the GIL (two threads kept 1.1 of 2 cores busy)
        with TwoProcesses([functools.partial(one, k) for k in range(len(scans))],
                          what=f"{scans[0].topic}: segmentation", fork=jobs != 1 and len(scans) >= 4) as both:
            found = both.results(advance)
        for _ in ticks:  # the bar ends
            pass
        if debug is not None:
            debug[:] = [d for _, d in found]
        return [r for r, _ in found]

    found = all_scans(progress)
    offsets = ring_range_offsets(found, scans)
    if offsets is None:
        return found
    # A ring whose offset is comparable to point_plane_tolerance_m lost part of its returns to
    # the plane's tolerance (those on the far side of its offset): its measured offset is short
    # and the board keeps a biased subset. The scans are corrected and segmented again, and what
    # is left of the offsets is measured on the complete boards.
    scans = [with_ring_offsets(sc, *offsets) for sc in scans]
    if debug is not None:
        debug[:] = [Debug() for _ in debug]
    found = all_scans(None)
    if ring_offsets is not None:
        _add_offsets(ring_offsets, *offsets)
    return correct_ring_offsets(found, scans, measured=ring_offsets)


def correct_ring_offsets(found: list, scans: list, *, measured: dict | None = None) -> list:
    """``found`` (segment_board results per scan of one LIDAR) with each ring's own range offset,
    measured on all the boards (``ring_range_offsets``), taken out of the board points and
    planes; ``found`` unchanged when the offsets do not stand out of their standard errors.
    ``measured``: {ring: offset (m)} to add the offsets taken out to."""
    offsets = ring_range_offsets(found, scans)
    if offsets is None:
        return found
    rings, offset = offsets
    if measured is not None:
        _add_offsets(measured, rings, offset)
    out = list(found)
    for k, o in enumerate(found):
        if not isinstance(o, LidarBoardObservation) or o.indices is None or scans[k].ring is None:
            continue
        q = _offset_points(np.asarray(o.points, float), np.asarray(scans[k].ring)[o.indices], rings, offset)
        n, d, rms = fit_plane(q)
        if d > 0:
            n, d = -n, -d
        out[k] = dataclasses.replace(o, points=q, plane=np.r_[n, d], rms_m=rms)
    return out


def _add_offsets(measured: dict, rings: np.ndarray, offset: np.ndarray) -> None:
    for r, x in zip(rings, offset):
        measured[int(r)] = measured.get(int(r), 0.0) + float(x)


def offsets_table(measured: dict) -> np.ndarray:
    """(R,2) ring number and range offset of ``measured`` ({ring: offset}), by ring: a
    Problem.lidar_ring_offsets entry."""
    return np.array(sorted(measured.items()), float).reshape(-1, 2)


def with_ring_offsets(scan: LidarScan, rings: np.ndarray, offset: np.ndarray) -> LidarScan:
    """``scan`` with each return of ring ``rings[j]`` moved ``offset[j]`` closer along its ray."""
    if scan.ring is None:
        return scan
    pts = np.asarray(scan.points, float)
    ok = finite_rows(pts)
    pts = pts.copy()
    pts[ok] = _offset_points(pts[ok], np.asarray(scan.ring)[ok], rings, offset)
    return dataclasses.replace(scan, points=pts)


def _offset_points(pts: np.ndarray, ring: np.ndarray, rings: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Points of rings ``ring`` with ``offset`` (per ring of ``rings``; 0 for the others) taken
    out of their ranges."""
    j = np.clip(np.searchsorted(rings, ring), 0, len(rings) - 1)
    off = np.where(rings[j] == ring, offset[j], 0.0)
    r = row_norms(pts)
    return pts * np.where(r > 0, (r - off) / np.where(r > 0, r, 1.0), 1.0)[:, None]


def ring_range_offsets(found: list, scans: list) -> tuple[np.ndarray, np.ndarray] | None:
    """(ring numbers, each ring's range offset in m), measured on all the boards of ``found``
    (segment_board results per scan of one LIDAR), or None when they do not stand out.

    Real lasers range with fixed offsets of their own (1-3 cm; the same in every scan): on one
    board they tilt and shift the plane by degrees and millimetres, differently for each board
    (which rings crossed it), errors the solver would take for independent noise. Each ring's
    offset is its returns' mean range beyond their board's plane, over all boards, alternating
    with the plane fits; what no board can tell apart from the planes (a common offset, one linear
    in the rings' elevation) is left. Only where the offsets stand out of their own standard
    errors (chi-square over the rings beyond 4 sigma of its dof).
    """
    obs = [(k, o) for k, o in enumerate(found) if isinstance(o, LidarBoardObservation) and o.indices is not None
           and scans[k].ring is not None]
    if len(obs) < 3:
        return None
    pts = [np.asarray(o.points, float) for _, o in obs]
    rings = [np.asarray(scans[k].ring)[o.indices].astype(np.int64) for k, o in obs]
    all_rings = np.unique(np.concatenate(rings))
    rid = [np.searchsorted(all_rings, r) for r in rings]
    R = len(all_rings)
    if R < 4:
        return None
    rng_m = [row_norms(p) for p in pts]
    u = [p / r[:, None] for p, r in zip(pts, rng_m)]
    elev = np.zeros(R)
    np.add.at(elev, np.concatenate(rid), np.concatenate([x[:, 2] for x in u]))
    counts = np.bincount(np.concatenate(rid), minlength=R).astype(float)
    elev = elev / np.maximum(counts, 1)
    A = np.c_[np.ones(R), elev] * np.sqrt(counts)[:, None]  # the unidentifiable part, point-weighted
    offset = np.zeros(R)
    for _ in range(6):
        num, sq = np.zeros(R), np.zeros(R)
        for p_u, r, ri in zip(u, rng_m, rid):
            q = p_u * (r - offset[ri])[:, None]
            n, d, _ = fit_plane(q)
            e = r - d / (p_u @ n)  # measured range beyond the corrected plane
            np.add.at(num, ri, e)
            np.add.at(sq, ri, e**2)
        mean = num / np.maximum(counts, 1)
        w = np.sqrt(counts)
        coef, *_ = np.linalg.lstsq(A, mean * w, rcond=None)
        new = mean - np.c_[np.ones(R), elev] @ coef
        done = np.max(np.abs(new - offset)) < 1e-4
        offset = new
        if done:
            break
    var = np.maximum(sq / np.maximum(counts, 1) - mean**2, 0)
    se2 = var / np.maximum(counts, 1)
    dof = R - 2
    ok = counts >= 2
    chi2 = float(np.sum(offset[ok] ** 2 / np.maximum(se2[ok], 1e-12)))
    if dof < 2 or chi2 <= dof + 4 * np.sqrt(2 * dof):
        return None
    log.info("ring range offsets of %s from %d boards: %s mm", scans[obs[0][0]].topic, len(obs),
             np.array2string(offset * 1e3, precision=0))
    return all_rings, offset
