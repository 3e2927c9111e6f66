"""The board's size as the LIDARs' edges show it, against board.size_m.

The edge factors hold each side of the board where board.size_m puts it. A board measured wrong
(its border left out, the wrong sheet's size) moves every side the same way: each edge interval
then lies inside the declared side (the board is smaller) or outside it (larger), on every board,
whatever its pose, where a board misplaced within its plane moves opposite sides opposite ways.
So the median of the boards' outward offsets per LIDAR and side direction measures the error:
declared width + 2 x offset is the width the LIDAR sees.

Physics adds an outward bias only: a beam partly on the board still returns from it, so the
board looks larger by part of the footprint (on the real ACFR Ouster ~2 mm a side at 3.9 m;
divergences are 2-3 mrad). The check allows 10 mm a side either way (a board measured to the
centimetre) and outward 2 mrad more per metre of range, and asks the offset to stand out of its
standard error across the boards (4 sigma, with >= 5 boards): a 3 cm error a side on the bench
capture gave -26 mm (se 1.2) where the right size gives +0.7 to +2.8 mm.

A board described larger than it is by more than ~a board's edge tolerance the frontend's
outline fit accepts (tens of cm) leaves few intervals to measure: the solve's own checks refuse
those captures (the edges then disagree with everything else).

SYNOPSIS
    seen = size_seen(problem, active, rt_sensor, rt_board)   # {(sensor, axis): SideOffset}
    check(problem, seen)                                    # InputError naming the LIDAR and the size
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..factors.lidar_edge import edge_sides, lidar_edge_residuals
from ..geometry import pose3_from_rt
from .graph import _pose, lidar_face

TOLERANCE_M = 0.010  # a side's offset allowed either way: a board measured to the centimetre
GROWTH_RAD = 0.002  # outward, per metre of range: the part of a beam's footprint still returning
MIN_BOARDS = 5
MIN_SIGMAS = 4.0


@dataclass(frozen=True)
class SideOffset:
    offset_m: float  # median over the boards of each board's median outward offset of that direction's sides
    se_m: float  # its standard error (MAD across the boards)
    boards: int
    range_m: float  # the median range to those edges


def size_seen(problem, active, rt_sensor: np.ndarray, rt_board: np.ndarray) -> dict:
    """{(LIDAR index, axis 0 width / 1 height): SideOffset} of the active observations' edge rays at
    the given poses."""
    board = problem.board
    x0, x1, y0, y1 = board.extent()
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    per: dict = {}
    for o, m in zip(problem.lidar_observations, active.lidar):
        if m is None or not m.any() or o.edge_rays is None or not len(o.edge_rays):
            continue
        T_s, T_b = _pose(problem, rt_sensor, o.sensor), pose3_from_rt(rt_board[o.snapshot])
        face = lidar_face(board, T_s, T_b)
        keep, axis, bounds, _, rng = edge_sides(T_s, T_b, o.edge_rays, board, face_m=face)
        if not keep.any():
            continue
        axis, bounds, rng = axis[keep], bounds[keep], rng[keep]
        err = lidar_edge_residuals(T_s, T_b, o.edge_rays[keep], axis, bounds, face_m=face)
        out = err * np.sign(bounds - centre[axis])
        for a in (0, 1):
            on = axis == a
            if on.any():
                per.setdefault((o.sensor, a), []).append((float(np.median(out[on])), float(np.median(rng[on]))))
    seen = {}
    for key, v in per.items():
        off, rng = np.array(v).T
        med = float(np.median(off))
        seen[key] = SideOffset(med, 1.4826 * float(np.median(np.abs(off - med))) / np.sqrt(len(off)), len(off),
                               float(np.median(rng)))
    return seen


def check(problem, seen: dict) -> None:
    """InputError where a LIDAR's edges put the board's sides off board.size_m beyond what a
    measurement or a beam explains (module docstring)."""
    board = problem.board
    size = (board.width_m, board.height_m)
    for (i, a), s in sorted(seen.items()):
        allowed = TOLERANCE_M + (GROWTH_RAD * s.range_m if s.offset_m > 0 else 0.0)
        if s.boards < MIN_BOARDS or abs(s.offset_m) <= max(allowed, MIN_SIGMAS * s.se_m):
            continue
        other = seen.get((i, 1 - a))
        seen_size = [size[0] + 2 * (s.offset_m if a == 0 else other.offset_m if other else 0.0),
                     size[1] + 2 * (s.offset_m if a == 1 else other.offset_m if other else 0.0)]
        raise InputError(
            f"{problem.sensors[i].topic}: its scans show the board {seen_size[0]:.2f} x {seen_size[1]:.2f} m, "
            f"board.size_m says [{size[0]:g}, {size[1]:g}]: the board's {('left and right', 'top and bottom')[a]} "
            f"edges lie {abs(s.offset_m) * 1e3:.0f} mm {'outside' if s.offset_m > 0 else 'inside'} where it puts them "
            f"(median of {s.boards} boards, +-{s.se_m * 1e3:.1f} mm); measure the physical board, its white border "
            "included, and set board.size_m (width x height)")
