"""The board as described against what the sensors see: board.size_m against the LIDARs' edges,
board.square_m against the LIDARs' planes, board.pattern_offset_m against both.

**Size.** The edge factors hold each side of the board where board.size_m puts it. A board
measured wrong (its border left out, the wrong sheet's size) moves every side the same way: each
edge interval then lies inside the declared side (the board is smaller) or outside it (larger),
on every board, whatever its pose, where a board misplaced within its plane moves opposite sides
opposite ways. So the median of the boards' outward offsets per LIDAR and side direction measures
the error: declared width + 2 x offset is the width the LIDAR sees. Physics adds an outward bias
only: a beam partly on the board still returns from it, so the board looks larger by part of the
footprint (on the real ACFR Ouster 3-6 mm a side at 3.8 m; divergences are 2-3 mrad). The check
allows 10 mm a side either way (a board measured to the centimetre) and outward 2 mrad more per
metre of range, and asks the offset to stand out of its standard error across the boards (4
sigma, >= 5 boards): a 3 cm error a side on the bench capture gave -26 mm (se 1.2) where the
right size gives +0.7 to +2.8 mm. A board described larger than it is by more than the outline
fit accepts (tens of cm) leaves few intervals to measure; the solve's own checks refuse those.

**Scale.** A camera's view of the pattern fixes the board's distance only through the square
size: squares declared 2 % small put every board 2 % nearer (a pattern printed at 98 %, "fit to
page"). The camera's translation then moves along its view to meet the LIDARs' planes halfway,
and per-board errors that grow with distance are left, which the observation effects absorb: on
the bench capture square_m 0.098 for 0.1 gave every camera 108-117 mm off at 16-21 mm sigma
(7 sigma), written as a result. Each board's distance from the camera by its corners alone
(PnP, the declared squares) against the distance along the same ray to a LIDAR's plane of it
(the solved poses) is a line through the origin when the scale is right: fitted d_camera = a
d_lidar + b over the camera's boards, a - 1 is the scale error (b takes the camera's shift).
Refused where it stands out of its standard error (4 sigma, >= 5 boards; the focal length's
stated uncertainty added) and exceeds 0.2 %. A camera model's focal length off by that much does
the same, and the message says so (and how to state a focal length known only to a few %).
Boards all at one distance cannot tell it: the real ACFR boards at 2.9-3.5 m give a = 0.980 +- 0.012 and
0.982 +- 0.022 (runs 1, 2), not refused; the bench capture's right squares 0.9998-1.0004 (+-
0.0002-0.0003), 0.098 and 0.102 0.978-0.980 and 1.020-1.021.

**Pattern offset.** board.pattern_offset_m places the pattern, which the cameras see, against
the outline, which the LIDARs' edges see. Described wrong, the two disagree within the board's
plane on every board a camera and a LIDAR both saw; a camera's shift takes up most of it where
its boards all face it alike (3 cm off along the width moved the bench capture's cameras 27 mm at
a 1-sigma of 5 mm, written as a result). So the offset's correction is estimated beside the
sensors' poses, one Gauss-Newton step from the final solution with two more unknowns (the
corners' change per metre of it from a rebuilt graph, as consider.py's terms): the boards'
turns and the LIDARs' own view of the outline separate it from the cameras' shifts. Refused
beyond 5 mm (a pattern placed by hand) and 4 standard errors (>= 5 boards). On the bench
capture a right description gives (0.0 +- 0.8, 1.2 +- 1.1) mm, 3 cm along the width 29.9 +- 3.4
mm, 1 cm 9.3 +- 1.1 mm; the real ACFR runs (3.0 +- 2.6, -1.5 +- 2.5) and (3.5 +- 3.7, -1.2 +-
3.6) mm, not refused.

SYNOPSIS
    check_offset(problem, offset_seen(problem, lin, rebuild))   # InputError naming board.pattern_offset_m
    check_size(problem, size_seen(problem, active, rt_sensor, rt_board))   # InputError naming the LIDAR
    check_scale(problem, scale_seen(problem, active, rt_sensor), options)  # InputError naming the camera
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .. import cameras
from ..errors import InputError
from ..factors.lidar_edge import edge_sides, lidar_edge_residuals
from ..geometry import T_from_rt, compose_rt, invert_rt, pose3_from_rt, rt_from_pose3, transform
from . import graph as G
from .consider import moved_graph
from .graph import lidar_face
from .seed import board_pose_from_corners

TOLERANCE_M = 0.010  # a side's offset allowed either way: a board measured to the centimetre
GROWTH_RAD = 0.002  # outward, per metre of range: the part of a beam's footprint still returning
MIN_BOARDS = 5
MIN_SIGMAS = 4.0
OFFSET_TOLERANCE_M = 0.005  # a pattern placed on its board by hand, to half a centimetre
SCALE_TOLERANCE = 0.002  # a pattern's scale error below which no check refuses (0.2 mm on a 0.1 m square)


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
        T_s = None if o.sensor == problem.reference else pose3_from_rt(rt_sensor[o.sensor])
        T_b = pose3_from_rt(rt_board[o.snapshot])
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


def check_size(problem, seen: dict) -> None:
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


@dataclass(frozen=True)
class ScaleFit:
    slope: float  # a of d_camera = a d_lidar + b
    se: float  # its standard error
    boards: int
    near_m: float  # the nearest and farthest board (LIDAR distance)
    far_m: float


def scale_seen(problem, active, rt_sensor: np.ndarray) -> dict:
    """{camera index: ScaleFit} over its active observations of boards an active LIDAR observation
    shows too (each pair of a camera's and a LIDAR's view of one board a point)."""
    T = [T_from_rt(np.asarray(rt, float)) for rt in rt_sensor]
    centre = problem.board.corners().mean(axis=0)
    planes: dict = {}
    for o, m in zip(problem.lidar_observations, active.lidar):
        if m is not None and m.any():
            planes.setdefault(o.snapshot, []).append(o)
    pairs: dict = {}
    for o, m in zip(problem.camera_observations, active.camera):
        if m is None or o.snapshot not in planes:
            continue
        rt = board_pose_from_corners(o.corners_px, problem.sensors[o.sensor], problem.board, np.inf)
        if isinstance(rt, str):
            continue
        c = T_from_rt(rt)[:3] @ np.r_[centre, 1.0]  # the pattern's centre, camera frame
        u = c / np.linalg.norm(c)
        for L in planes[o.snapshot]:
            T_cl = np.linalg.solve(T[o.sensor], T[L.sensor])
            n = T_cl[:3, :3] @ np.asarray(L.plane[:3], float)
            d = float(L.plane[3]) + n @ T_cl[:3, 3]
            if abs(n @ u) > 0.1:
                pairs.setdefault(o.sensor, []).append((d / (n @ u), float(np.linalg.norm(c))))
    fits = {}
    for i, v in pairs.items():
        lidar, camera = np.array(v).T
        if len(v) < MIN_BOARDS or np.ptp(lidar) <= 0:
            continue
        A = np.c_[lidar, np.ones(len(v))]
        coef, *_ = np.linalg.lstsq(A, camera, rcond=None)
        r = camera - A @ coef
        cov = (r @ r / (len(v) - 2)) * np.linalg.inv(A.T @ A)
        fits[i] = ScaleFit(float(coef[0]), float(np.sqrt(cov[0, 0])), len(v), float(lidar.min()), float(lidar.max()))
    return fits


def _focal_sigma(sensor, options) -> float:
    """The relative 1 sigma of a camera's focal length the solve's uncertainty includes (its model's
    intrinsics covariance, else solve.camera_focal_scale_sigma: consider.py)."""
    cov = sensor.intrinsics_covariance
    if cov is not None and np.any(cov):
        return float(np.sqrt(np.asarray(cov, float)[0, 0]) / float(sensor.intrinsics[0]))
    return float(options.camera_focal_scale_sigma)


def check_scale(problem, fits: dict, options) -> None:
    """InputError where a camera's boards' distances grow with the LIDARs' at a slope other than 1
    (module docstring) beyond its focal length's stated uncertainty too (a focal length known to
    1 % allows the slope 1 % more: the sigmas include that error)."""
    sq = problem.board.square_m
    for i, f in sorted(fits.items()):
        off = f.slope - 1.0
        focal = _focal_sigma(problem.sensors[i], options)
        if abs(off) <= max(SCALE_TOLERANCE, MIN_SIGMAS * np.hypot(f.se, focal)):
            continue
        way = "farther" if off > 0 else "nearer"
        raise InputError(
            f"{problem.sensors[i].topic}: its boards lie {abs(off) * 100:.1f} % {way} by their corners than by the "
            f"LIDARs' planes ({f.boards} views of boards {f.near_m:.1f}-{f.far_m:.1f} m away, slope {f.slope:.4f} +- "
            f"{f.se:.4f}): the squares are {sq / f.slope * 1e3:.1f} mm, not the "
            f"{sq * 1e3:g} mm of board.square_m (a pattern printed scaled?), or this camera model's focal length is "
            f"{abs(off) * 100:.1f} % {'long' if off > 0 else 'short'}; measure the squares across the whole pattern "
            f"(a focal length known only to a few %: --set solve.camera_focal_scale_sigma={max(abs(off), 0.001):.3f})")


@dataclass(frozen=True)
class OffsetFit:
    shift_m: np.ndarray  # (2,) the pattern's centre less where board.pattern_offset_m puts it (along the width, height)
    se_m: np.ndarray  # (2,) its standard errors
    boards: int  # snapshots seen by a camera and by a LIDAR's outline


_STEP_M = 1e-3  # the pattern's trial shift (the corners are linear in it far below the noise)


def _pattern_moved(problem, values, axis: int, h: float):
    """``problem`` with every camera's corners where they would be with the pattern ``h`` (m)
    farther along the board's ``axis`` than the board's description puts it (the outline, which
    the LIDARs see, in place), at the poses ``values``."""
    corners = problem.board.corners()
    moved = corners.copy()
    moved[:, axis] += h
    T = {i: rt_from_pose3(values.atPose3(G.sensor_key(i))) for i in range(len(problem.sensors)) if i != problem.reference}
    out = []
    for o in problem.camera_observations:
        key = G.board_key(o.snapshot)
        if not values.exists(key):
            out.append(o)
            continue
        s = problem.sensors[o.sensor]
        rt_c_b = compose_rt(invert_rt(T[o.sensor]), rt_from_pose3(values.atPose3(key)))
        dq = cameras.project(transform(rt_c_b, moved), s.lensmodel, s.intrinsics) - \
            cameras.project(transform(rt_c_b, corners), s.lensmodel, s.intrinsics)
        out.append(dataclasses.replace(o, corners_px=o.corners_px + dq))
    return dataclasses.replace(problem, camera_observations=tuple(out))


def offset_seen(problem, lin, build) -> OffsetFit | None:
    """The pattern's offset on the board as the cameras' corners and the LIDARs' outlines of the
    same boards see it: one Gauss-Newton step from the final solution (``lin``: its
    noise.Linearization; ``build``: the final graph's rebuild of a problem, as consider's) with
    the offset's correction as two more unknowns beside the sensors; None without a board that a
    camera and a LIDAR's outline both saw."""
    cams = {o.snapshot for o in problem.camera_observations}
    boards = len(cams & {o.snapshot for o in problem.lidar_observations
                         if o.edge_rays is not None and len(o.edge_rays)})
    if not boards or lin.rows is None:
        return None
    cols: dict = {}
    for a in (0, 1):
        for f, factor in moved_graph(problem, _pattern_moved(problem, lin.values, a, _STEP_M), lin, build).items():
            db = (factor.linearize(lin.values).jacobian()[1] - lin.rows[lin.factors[f][3].start][2]) / _STEP_M
            cols.setdefault(f, np.zeros((len(db), 2)))[:, a] = db
    if not cols:
        return None
    S, r, _ = lin.with_known(cols, 2).reduced()
    C = np.linalg.inv(S)
    return OffsetFit((C @ r)[-2:], np.sqrt(np.diag(C)[-2:]), boards)


def check_offset(problem, fit: OffsetFit | None) -> None:
    """InputError where the boards' patterns sit off board.pattern_offset_m beyond a pattern placed by
    hand (OFFSET_TOLERANCE_M) and their standard error (module docstring)."""
    if fit is None or fit.boards < MIN_BOARDS:
        return
    off = np.abs(fit.shift_m) > np.maximum(OFFSET_TOLERANCE_M, MIN_SIGMAS * fit.se_m)
    if not off.any():
        return
    stated = np.asarray(problem.board.pattern_offset_m, float)
    seen = stated + fit.shift_m
    where = " and ".join(f"{abs(fit.shift_m[a]) * 1e3:.0f} mm {('along the width', 'along the height')[a]} "
                         f"(+-{fit.se_m[a] * 1e3:.1f})" for a in (0, 1) if off[a])
    raise InputError(
        f"board.pattern_offset_m: the cameras' corners and the LIDARs' outlines of the same {fit.boards} boards put "
        f"the pattern's centre {where} off where [{stated[0]:g}, {stated[1]:g}] puts it: measure the pattern's "
        f"centre from the board's centre (along the width, the height) and set board.pattern_offset_m "
        f"(these captures show [{seen[0]:.3f}, {seen[1]:.3f}])")
