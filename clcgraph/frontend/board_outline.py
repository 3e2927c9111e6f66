"""The board's known rectangle fitted in its plane to one LIDAR scan: which of the plane's
returns are the board, and which only touch its plane beside it (a person, a hand, a post).

Every return of the scan is put where its ray crosses the board's plane (so a long-ranging
mixed pixel at an edge stays at the edge). The plane's returns pull the rectangle over them;
returns *behind* the plane push it away: their ray passed through the plane there, so no board
was in the way. Returns in front of the plane (an arm, the person holding the board) say
nothing: the board may be hidden behind them. The rectangle (the board's width x height, any
in-plane rotation) is placed where it holds the most plane returns less the behind-returns
inside it; a ring's first ray past the plane's returns does not count (it lies within a point
spacing of the edge, and mixed pixels sit there: ``ScanRays.away_from``). A plane return is the
board when it lies within the rectangle, or within half its point spacing along its ring plus
the search grid's cell of it (the edge lies between a ring's last return on the board and its
next ray).

SYNOPSIS
    rays = scan_rays(scan, step_rad=2*pi/1800)           # every ray of the scan, misses included
    others = rays.points[rays.away_from(rows)]           # rows: the plane's returns (scan rows)
    o = fit_outline(scan.points[rows] (N,3), others (M,3), n, d, size_m=(1.3, 1.3), step_rad=2*pi/1800,
                    plane_tol_m=0.05)
    o.inside            # (N,) which points lie on the board
    o.corners_3d()      # (4,3) the fitted rectangle's corners in the LIDAR frame
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import azimuth, circular_mean, wrap_angle
from ..types import LidarScan
from .lidar_preprocess import Rings, missed_rays, prepare, ring_neighbours, row_norms

# The fine search grid: cells of half the point spacing, within these bounds (m).
_CELL_M = (0.01, 0.03)
# A refit about a previous outline (``fit_outline``'s ``near``): the coarse search within this many
# angle steps and this fraction of the board's short side of it.
_NEAR_STEPS = 4
_NEAR_REACH = 0.5


@dataclass(frozen=True)
class Outline:
    """The fitted rectangle: plane n . x = d with in-plane basis (e1, e2) about ``origin``;
    the rectangle's centre (2,) and side directions ``axes`` (2,2 rows: along size[0], along
    size[1]) in that basis; ``inside`` (N,) and ``tolerance_m`` (N,) per plane return."""

    n: np.ndarray
    d: float
    origin: np.ndarray
    basis: np.ndarray  # (2,3): e1, e2
    centre: np.ndarray
    axes: np.ndarray
    size: np.ndarray
    inside: np.ndarray
    tolerance_m: np.ndarray
    score: float

    def corners_3d(self) -> np.ndarray:
        """(4,3) corners in the LIDAR frame."""
        h = self.size / 2
        c2 = self.centre + np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * h @ self.axes
        return self.origin + c2 @ self.basis


@dataclass(frozen=True)
class ScanRays:
    """Every ray of a scan: its returns, and far points along the rays that returned nothing;
    per ray the scan rows of its neighbours along the ring (-1: none, or a ray that returned
    nothing). ``rings``: the scan's valid returns (``prepare`` without range limits) and
    ``missed``: ``missed_rays`` of them at ``step_rad``, for the board's edges (``board_edges``)."""

    points: np.ndarray  # (M,3)
    prev: np.ndarray  # (M,)
    next: np.ndarray  # (M,)
    n_rows: int
    by_azimuth: np.ndarray | None = None  # (M,) the rays in azimuth order (-pi..pi)
    azimuth: np.ndarray | None = None  # (M,) sorted: the azimuth of by_azimuth's rays
    elevation: np.ndarray | None = None  # (M,) per ray (not sorted)
    rings: Rings | None = None
    missed: tuple | None = None  # (directions (K,3), position before, position after)
    step_rad: float = 0.0

    def away_from(self, rows: np.ndarray) -> np.ndarray:
        """(M,) the rays that are not ring neighbours of the scan rows ``rows``: where a ring
        leaves the board, its first return past the edge (or first miss) may be a mixed pixel,
        and lies within a point spacing of the edge anyway."""
        mine = np.zeros(self.n_rows + 1, bool)  # the last entry stands for -1
        mine[rows] = True
        return ~(mine[self.prev] | mine[self.next])

    def around(self, points: np.ndarray, n: np.ndarray, d: float, reach_m: float) -> np.ndarray:
        """(K,) indices of the rays that may cross the plane n . x = d within ``reach_m`` of where
        the rays of ``points`` (N,3) cross it: those within the angle ``reach_m`` subtends at the
        nearest of those crossings, of the points' azimuth and elevation span (all rays when that
        angle is wide, or a point's ray does not meet the plane ahead). A board's rectangle over
        the points lies within its diagonal of them, so only these rays can count in its fit."""
        every = np.arange(len(self.points))
        if self.azimuth is None or not len(points):
            return every
        r = row_norms(points)
        u = points / np.where(r > 0, r, 1.0)[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = d / (u @ n)
        if not (np.isfinite(t).all() and (t > 0).all()) or reach_m >= t.min():
            return every
        m = float(np.arcsin(reach_m / t.min()))  # the widest angle between such a ray and a point's
        el = np.arcsin(np.clip(u[:, 2], -1, 1))
        el_lo, el_hi = el.min() - m, el.max() + m
        c = min(np.cos(el_lo), np.cos(el_hi)) if el_lo > -np.pi / 2 and el_hi < np.pi / 2 else 0.0
        if c <= np.sin(m / 2):
            return every
        # |u - v| = 2 sin(angle / 2) >= 2 cos(elevation) sin(d_azimuth / 2) for unit u, v
        m_az = 2 * float(np.arcsin(np.sin(m / 2) / c))
        az = azimuth(u)
        az0 = circular_mean(az)
        rel = wrap_angle(az - az0)
        lo, hi = az0 + rel.min() - m_az, az0 + rel.max() + m_az
        if hi - lo >= 2 * np.pi:
            return every
        lo, hi = wrap_angle(lo), wrap_angle(hi)  # the window may wrap past +-pi
        a, b = np.searchsorted(self.azimuth, [lo, hi])
        k = self.by_azimuth[a:b] if lo <= hi else np.r_[self.by_azimuth[a:], self.by_azimuth[:b]]
        return k[(self.elevation[k] >= el_lo) & (self.elevation[k] <= el_hi)]


def scan_rays(scan: LidarScan, step_rad: float, far_m: float = 1e4, *, rings: Rings | None = None) -> ScanRays:
    """ScanRays of ``scan`` (every valid return, static scene and any range included; ``far_m``
    along each missed ray); ``step_rad``: the azimuth step; ``rings``: ``prepare(scan)`` if
    already made."""
    R = prepare(scan) if rings is None else rings
    ok = R.range > 0
    prv, nxt = ring_neighbours(R)
    dirs, before, after = missed_rays(R, step_rad)
    rows = np.r_[R.index, -1]  # position -1 -> row -1
    pts = np.r_[R.points[ok], far_m * dirs]
    u = pts / row_norms(pts)[:, None]
    az = azimuth(u)
    order = np.argsort(az, kind="stable")
    return ScanRays(pts, np.r_[rows[prv[ok]], rows[before]], np.r_[rows[nxt[ok]], rows[after]], len(scan.points),
                    by_azimuth=order, azimuth=az[order], elevation=np.arcsin(np.clip(u[:, 2], -1, 1)), rings=R,
                    missed=(dirs, before, after), step_rad=step_rad)


def plane_basis(n: np.ndarray, d: float) -> tuple[np.ndarray, np.ndarray]:
    """(origin (3,), basis (2,3)): the plane's point nearest the sensor and two in-plane unit
    vectors, the first level (along the rings of a level LIDAR)."""
    e1 = np.cross(n, [0.0, 0.0, 1.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(n, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return n * d, np.stack([e1, np.cross(n, e1)])


def ray_plane(points: np.ndarray, n: np.ndarray, d: float, origin: np.ndarray, basis: np.ndarray):
    """(xy (N,2) where each return's ray crosses the plane, in the plane's basis; depth (N,) m:
    the return's range beyond that crossing, negative in front; ahead (N,): the ray meets the
    plane ahead of the sensor)."""
    r = row_norms(points)
    u = points / np.where(r > 0, r, 1.0)[:, None]
    un = u @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = d / un
    ahead = np.isfinite(t) & (t > 0)
    t = np.where(ahead, t, 0.0)
    xy = (u * t[:, None] - origin) @ basis.T
    return xy, r - t, ahead


def along_ring_step(points: np.ndarray, n: np.ndarray, d: float, step_rad: float) -> np.ndarray:
    """(N,3) m: where on the plane the next ray of each return's ring lands, relative to its own
    crossing (the derivative of the ray-plane crossing with azimuth, times the step)."""
    r = row_norms(points)
    u = points / np.where(r > 0, r, 1.0)[:, None]
    du = np.c_[-u[:, 1], u[:, 0], np.zeros(len(u))]  # d u / d azimuth (|du| = cos elevation)
    un = u @ n
    un = np.where(np.abs(un) > 1e-6, un, 1e-6)
    t = d / un
    return t[:, None] * (du - ((du @ n) / un)[:, None] * u) * step_rad


def _box_counts(tables, blocks: np.ndarray, cells: np.ndarray, k: np.ndarray, tile: np.ndarray,
                how: str | None = None) -> np.ndarray:
    """(B, tile[0], tile[1]) per anchor a of the sorted ``blocks`` (B,): the sum over ``tables``
    [(members, ox, sign)] of sign x the returns of ``members`` (block, cell in its block, of
    ``cells`` (2,) cells padded by one before each axis) in the anchor's box [a + ox, a + k - ox)
    per axis.

    The counts are exact either way, and taken the cheaper of two ways: a summed-area table of
    the blocks' cells (an entry per return), or a difference grid of the anchors, a box of them
    per return with +-1 at its corners (four entries per return, but a grid as large as the
    anchors: those of the fine search are 40x fewer than its cells). ``how``: "table" or "grid"
    to choose."""
    B = len(blocks)
    P0, P1 = cells[0] + 1, cells[1] + 1
    picked = []
    for m, ox, sign in tables:
        if m is None or k.min() <= 2 * ox:  # no returns, or boxes of no cell
            continue
        if blocks[-1] - blocks[0] + 1 == B:  # consecutive blocks (one per angle): no search
            b = m[0] - blocks[0]
            hit = (b >= 0) & (b < B)
        else:
            b = np.minimum(np.searchsorted(blocks, m[0]), B - 1)
            hit = blocks[b] == m[0]
        picked.append((b[hit], m[1][hit], ox, sign))
    out = np.zeros((B, tile[0], tile[1]), np.int64)
    n = sum(len(p[0]) for p in picked)
    if how is None:  # numpy passes over the entries and over the table / grid, roughly
        cheaper = 10 * n + 6 * B * P0 * P1 * len(picked) < 36 * n + 4 * B * (tile[0] + 1) * (tile[1] + 1)
        how = "table" if cheaper else "grid"
    if how == "table":
        for b, loc, ox, sign in picked:
            S = np.bincount(b * (P0 * P1) + loc, minlength=B * P0 * P1).reshape(B, P0, P1)
            np.cumsum(S, axis=1, out=S)  # in place: no temporaries of the table's size
            np.cumsum(S, axis=2, out=S)
            i0, i1, j0, j1 = ox, k[0] - ox, ox, k[1] - ox
            for i, j, s in ((i1, j1, sign), (i0, j1, -sign), (i1, j0, -sign), (i0, j0, sign)):
                (np.add if s > 0 else np.subtract)(out, S[:, i:i + tile[0], j:j + tile[1]], out=out)
        return out
    T0, T1 = tile[0] + 1, tile[1] + 1
    D = np.zeros(B * T0 * T1, np.int64)
    for b, loc, ox, sign in picked:
        # int32 (D is far smaller than 2**31 cells) and temporaries dropped early: memory
        ci, cj = np.divmod(loc.astype(np.int32), np.int32(P1))
        b = b.astype(np.int32) * np.int32(T0 * T1)
        i0 = np.minimum(np.maximum(ci - (k[0] - ox), 0), tile[0]) * T1 + b  # ci - 1: the cell, unpadded
        i1 = np.minimum(np.maximum(ci - ox, 0), tile[0]) * T1 + b
        del b, ci
        j0 = np.minimum(np.maximum(cj - (k[1] - ox), 0), tile[1])
        j1 = np.minimum(np.maximum(cj - ox, 0), tile[1])
        del cj
        for at, s in ((i0 + j0, sign), (i1 + j1, sign), (i1 + j0, -sign), (i0 + j1, -sign)):
            (np.add if s > 0 else np.subtract)(D, np.bincount(at, minlength=D.size), out=D)
    D = D.reshape(B, T0, T1)
    np.cumsum(D, axis=1, out=D)
    np.cumsum(D, axis=2, out=D)
    out += D[:, :tile[0], :tile[1]]
    return out


def _search(xy_on, xy_behind, angles, size, cell, margin, c0, hint=None, reach=0.0):
    """Best (score, angle, centre (2,)) over ``angles`` and the anchors of a grid of ``cell``
    m: rectangles over the plane returns ``xy_on`` (or, with ``hint``, centred within ``reach``
    of it). ``margin``: cells along the rectangle's edges where behind-returns do not count (the
    grid's rounding); ties go to the rectangle centred nearest ``c0``.

    Without a hint the grid spans the returns' extent plus a board each side, which for a wall or
    the ground (or returns grazing the plane, crossing it far off) can be hundreds of metres. So
    along an axis longer than a few boards the anchors are cut into tiles of one rectangle's
    cells, and only the blocks of tiles where a rectangle can hold a plane return are scored (a
    rectangle anchored in a tile covers it and the next one: a return counts for the 2 x 2 tiles
    before it). Memory and time then grow with the returns, not with the plane's extent."""
    k = (np.floor(size / cell) + 1).astype(np.int64)  # cells per side, the rectangle rounded up
    best = (-np.inf, 0.0, c0)
    # rotations in chunks of 16 angles (each chunk one grid size), their grids scored for a few
    # angles at a time: memory bounded by (1 << 17) rotated returns
    sub = int(np.clip((1 << 17) // max(len(xy_on) + len(xy_behind), 1), 1, 16))
    for a in range(0, len(angles), 16):
        th = angles[a:a + 16]
        A = len(th)
        c, s = np.cos(th), np.sin(th)
        # (np.stack, not np.c_ / np.r_: those cost more than the arithmetic at these sizes)
        rot = np.stack([np.stack([c, s], axis=1), np.stack([-s, c], axis=1)], axis=1)  # (A,2,2): rows along the sides
        to_sides = np.stack([np.concatenate([c, -s]), np.concatenate([s, c])])  # (2,2A)

        def rotated(xy):  # (A,N) coordinates along each angle's two sides
            q = xy @ to_sides
            return q[:, :A].T, q[:, A:].T

        qx, qy = rotated(xy_on)
        if hint is None:  # any rectangle touching the plane returns
            lo = np.stack([qx.min(axis=1), qy.min(axis=1)], axis=1) - size - cell
            hi = np.stack([qx.max(axis=1), qy.max(axis=1)], axis=1) + size + cell
        else:
            h = rot @ hint
            lo, hi = h - size / 2 - reach - cell, h + size / 2 + reach + cell
        G = np.maximum(np.ceil((hi - lo).max(axis=0) / cell).astype(np.int64) + 1, k)
        n_anchor = G + 1 - k  # anchors of the whole grid, per axis
        tile = np.where((n_anchor > 8 * k) & (hint is None), k, n_anchor)  # anchors per tile, per axis
        n_tile = -(-n_anchor // tile)
        cells = tile + k - 1  # a block's cells: its tile's anchors' rectangles
        bx, by = rotated(xy_behind) if len(xy_behind) else (None, None)
        r0 = rot @ c0
        # the tie-break's scale: the farthest anchor of the whole grid (a corner) from c0
        corner_i = lo[:, 0, None] + (np.array([0, n_anchor[0] - 1]) + k[0] / 2) * cell - r0[:, 0, None]
        corner_j = lo[:, 1, None] + (np.array([0, n_anchor[1] - 1]) + k[1] / 2) * cell - r0[:, 1, None]
        far = np.sqrt(np.max(np.max(corner_i**2, axis=1) + np.max(corner_j**2, axis=1)))
        for a0 in range(0, A, sub):
            a1 = min(a0 + sub, A)

            def members(q):  # (block, cell in the block, padded) of each of the returns q's blocks
                i = np.floor((q[0][a0:a1] - lo[a0:a1, :1]) / cell).astype(np.int64)
                j = np.floor((q[1][a0:a1] - lo[a0:a1, 1:]) / cell).astype(np.int64)
                # cells off the grid hold no rectangle (read unsigned, a negative cell is off it too)
                ok = (i.view(np.uint64) < np.uint64(G[0])) & (j.view(np.uint64) < np.uint64(G[1]))
                ia, i, j = np.nonzero(ok)[0] + a0, i[ok], j[ok]

                def along(i, ax):  # [(tile, cell in its block, mask)]: the tile of i's anchors, the one before
                    if n_tile[ax] == 1:
                        return [(0, i, None)]
                    t = np.minimum(i // tile[ax], n_tile[ax] - 1)
                    li = i - t * tile[ax]
                    return [(t, li, None), (t - 1, li + tile[ax], (t >= 1) & (li < k[ax] - 1))]

                block, local = [], []
                for ti, li, mi in along(i, 0):
                    for tj, lj, mj in along(j, 1):
                        blk = ia if n_tile[0] * n_tile[1] == 1 else (ia * n_tile[0] + ti) * n_tile[1] + tj
                        loc = (li + 1) * (cells[1] + 1) + lj + 1
                        m = mi if mj is None else mj if mi is None else mi & mj
                        block.append(blk if m is None else blk[m])
                        local.append(loc if m is None else loc[m])
                if len(block) == 1:
                    return block[0], local[0]
                return np.concatenate(block), np.concatenate(local)

            m_on = members((qx, qy))
            m_b = members((bx, by)) if bx is not None else None
            # the blocks: where the plane returns are (with a hint, every angle's one block)
            blocks, n_on = np.unique(m_on[0], return_counts=True) if hint is None else (np.arange(a0, a1), None)
            per_batch = max(1, (1 << 19) // int(cells[0] * cells[1]))  # blocks at a time: ~0.5M cells
            if n_on is not None:  # the blocks holding the most returns first
                order = np.argsort(-n_on, kind="stable")
                blocks, n_on = blocks[order], n_on[order]
            for b0 in range(0, len(blocks), per_batch):
                if n_on is not None and n_on[b0] < best[0]:
                    break  # no rectangle in the blocks left holds more returns than the best one scores
                bl = np.sort(blocks[b0:b0 + per_batch])
                # per anchor: the plane returns in its rectangle less the behind-returns in it (away
                # from its edges by the margin)
                count = _box_counts([(m_on, 0, 1), (m_b, margin, -1)], bl, cells, k, tile).astype(np.float64)
                ba = bl // (n_tile[0] * n_tile[1])
                if (tile < n_anchor).any():  # the last tiles' anchors past the grid's
                    ai = (bl // n_tile[1] % n_tile[0] * tile[0])[:, None] + np.arange(tile[0])  # (B, tile) anchors
                    aj = (bl % n_tile[1] * tile[1])[:, None] + np.arange(tile[1])
                    count[(ai >= n_anchor[0])[:, :, None] | (aj >= n_anchor[1])[:, None, :]] = -np.inf
                # ties (a board seen in part may slide over where nothing was seen): the rectangle
                # centred nearest c0, by a penalty below one return (below 1/2: so only the anchors
                # of the most returns can win, and only theirs are computed)
                top = count.max()
                ib, i, j = np.unravel_index(np.flatnonzero(count.reshape(-1) == top), count.shape)
                ci = lo[ba[ib], 0] + (bl[ib] // n_tile[1] % n_tile[0] * tile[0] + i + k[0] / 2) * cell
                cj = lo[ba[ib], 1] + (bl[ib] % n_tile[1] * tile[1] + j + k[1] / 2) * cell
                score = top - 0.5 * np.hypot(ci - r0[ba[ib], 0], cj - r0[ba[ib], 1]) / (far + 1e-9)
                w = int(np.argmax(score))
                if score[w] > best[0]:
                    best = (float(score[w]), float(th[ba[ib[w]]]), rot[ba[ib[w]]].T @ np.array([ci[w], cj[w]]))
    return best


def _segment_in_box(p: np.ndarray, v: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(N,) whether the segments p - v .. p + v (N,2 each) meet the box |x| <= half (2,)."""
    lo, hi = np.full(len(p), -1.0), np.full(len(p), 1.0)
    for k in range(2):
        flat = np.abs(v[:, k]) < 1e-12
        with np.errstate(divide="ignore", invalid="ignore"):
            a, b = (-half[k] - p[:, k]) / v[:, k], (half[k] - p[:, k]) / v[:, k]
        a, b = np.where(flat, -np.inf, np.minimum(a, b)), np.where(flat, np.inf, np.maximum(a, b))
        out = flat & (np.abs(p[:, k]) > half[k])
        lo, hi = np.maximum(lo, a), np.where(out, -np.inf, np.minimum(hi, b))
    return lo <= hi


def fit_outline(points: np.ndarray, others: np.ndarray, n: np.ndarray, d: float, *, size_m, step_rad: float,
                plane_tol_m: float, near: Outline | None = None) -> Outline:
    """The board-sized rectangle (``size_m`` = width, height) in the plane n . x = d that holds the
    most of ``points`` (N,3; the plane's returns) less ``others`` (M,3; every other return of the
    scan) that lie behind the plane by more than ``plane_tol_m`` inside it. ``step_rad``: the
    LIDAR's azimuth step. ``near``: the outline fitted to the same returns in a plane close to
    this one (the plane refitted to what that outline kept): the search is about it, not over
    every rotation and the whole plane."""
    n = np.asarray(n, float)
    origin, basis = plane_basis(n, d)
    xy, _, _ = ray_plane(points, n, d, origin, basis)
    ring_step = along_ring_step(points, n, d, step_rad) @ basis.T  # (N,2) in the plane's basis
    spacing = np.linalg.norm(ring_step, axis=1)
    size = np.asarray(size_m, float)
    diag = float(np.hypot(*size))
    c0 = np.median(xy, axis=0)
    xy_b = np.zeros((0, 2))
    if len(others):
        xb, depth, ahead = ray_plane(others, n, d, origin, basis)
        xy_b = xb[ahead & (depth > plane_tol_m)]
        # a rectangle holding a plane return lies within its diagonal of it: behind-returns
        # farther from the plane returns count only in rectangles without one, which never win
        xy_b = xy_b[((xy_b >= xy.min(axis=0) - diag) & (xy_b <= xy.max(axis=0) + diag)).all(axis=1)]
    s_edge = float(np.median(spacing))
    # coarse to fine: a grid of 1/24 of the board's short side over every rotation, then about
    # the best one a grid of half the point spacing (1-3 cm); angle steps of one cell at a corner
    # (a rectangle is symmetric under a half turn, a square under a quarter turn). The coarse
    # grid's boundary cells reach past the board: behind-returns there do not count.
    period = np.pi / 2 if abs(size[0] - size[1]) < 1e-9 else np.pi
    cell_c = min(size) / 24
    dth_c = cell_c / (diag / 2)
    if near is None:
        _, th, centre = _search(xy, xy_b, np.arange(0.0, period, dth_c), size, cell_c, 1, c0)
    else:  # about the previous rectangle (its centre along its ray, its side in this plane's basis)
        hint = ray_plane((near.origin + near.centre @ near.basis)[None], n, d, origin, basis)[0][0]
        side = basis @ (near.axes[0] @ near.basis)
        th0 = float(np.arctan2(side[1], side[0]))
        _, th, centre = _search(xy, xy_b, th0 + np.arange(-_NEAR_STEPS, _NEAR_STEPS + 1) * dth_c, size, cell_c, 1, c0,
                                hint=hint, reach=_NEAR_REACH * min(size))
    cell = float(np.clip(s_edge / 2, *_CELL_M))
    dth = cell / (diag / 2)
    # the fine grid (at any angle) lies within half a board, the reach and 3 cells of the coarse
    # centre along its axes: returns farther off would only be dropped from it
    close = lambda q: q[np.hypot(*(q - centre).T) <= np.hypot(*(size / 2 + 2 * cell_c + 4 * cell))]  # noqa: E731
    score, th, centre = _search(close(xy), close(xy_b), th + np.arange(-cell_c / cell, cell_c / cell + 1) * dth, size,
                                cell, 0, c0, hint=centre, reach=2 * cell_c)
    axes = np.array([[np.cos(th), np.sin(th)], [-np.sin(th), np.cos(th)]])
    # A plane return is inside the scored cells, or within tol of them along its ring: the edge
    # lies between a ring's last return on the board and its next ray, so within half a spacing of
    # a fitted edge between them (plus the grid's cell). Across the rings no tolerance: the fit
    # already put the edge between the last ring on the board and the first one off it.
    half = (np.floor(size / cell) + 1) * cell / 2
    tol = spacing / 2 + cell
    inside = _segment_in_box((xy - centre) @ axes.T, (ring_step / np.maximum(spacing, 1e-12)[:, None] * tol[:, None])
                             @ axes.T, half)
    return Outline(n, float(d), origin, basis, centre, axes, size, inside, tol, score)
