"""The board as described against what the sensors see: board.size_m and board.pattern_offset_m
against the LIDARs' outlines and the cameras' corners, board.square_m against the LIDARs' planes.

**Size and pattern offset.** The edge factors hold each side of the board where board.size_m and
board.pattern_offset_m put it against the pattern, which the cameras see. A board measured wrong
(its border left out, the wrong sheet's size) moves opposite sides opposite ways on every board;
a pattern offset described wrong moves the outline against the pattern within the board's plane.
Both are estimated beside the sensors' poses: one Gauss-Newton step from the final solution with
their corrections as four more unknowns (the measurements' change per metre of each: the
corner factors' own Jacobian columns for a translation of the pattern in its plane, the edge
intervals' sides moved out by half the growth, their Huber weights held as in the step itself).
A camera's shift takes up most of a wrong offset where its boards all face it alike (3 cm along
the width moved the bench capture's cameras 27 mm at a 1-sigma of 5 mm, written as a result);
the boards' turns and the LIDARs' own view of the outline separate the two. Physics adds an
outward bias to the size only: a beam partly on the board still returns from it, so the board
looks larger by part of the footprint (on the real ACFR Ouster 3-6 mm a side at 3.8 m;
divergences are 2-3 mrad). Refused where a correction stands out of 4 standard errors (>= 5
boards) and beyond 10 mm a side for the size (a board measured to the centimetre; outward 2 mrad
more per metre of the outlines' median range) or 5 mm for the offset (a pattern placed by hand).
The squares are checked first (the scale check below): with no scale unknown here, squares
0.2 % large on the bench capture read as an offset of 8 mm along the height (+-1.7), refused
with the offset's message (which names the squares as the other cause); the cameras were
11-13 mm off at 3-4 mm sigma there, so the refusal stands.
On the bench capture (1.3 m board, 24 boards at 2-9 m): the right description gives a size +1.5
/ +3.0 mm (+-0.9 / 1.7) and an offset (-0.1, -0.6) mm (+-0.8 / 1.2); described 1.36, 1.34,
1.25, 1.2, 1.45 or 1.6 m, the size shown is 1.28-1.32 m; the offset 3 cm / 1 cm along the
width off, -30.0 +- 3.4 / -9.5 +- 1.1 mm. The real ACFR runs: size +7.4 / +11.6 and
+7.1 / +11.5 mm, offset (2.5, -2.0) and (3.3, -2.3) mm (+-2.6-3.7), not refused. 34 ms of the
24-pose bench solve. A board
described 20 cm smaller than it is (its border left out) fails earlier: the segmentation takes
its planes for larger than a board.

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
stated uncertainty added) and exceeds 0.2 %. The standard error is the larger of the fit's and
the leave-one-board-out jackknife's: stress seed 42's dim, blurred colour camera has its
farthest board 61 px across, its corners' scale 2e-3 off, and that board alone pulled the
slope to 0.9976 +- 0.0004 (right squares refused); at the true poses the jackknife gives
0.9972 +- 0.0040. A camera model's focal length off by that much does the same, and the
message says so (and how to state a focal length known only to a few %).
Boards all at one distance cannot tell it: the real ACFR boards at 2.9-3.5 m give a = 0.980 +- 0.012 and
0.982 +- 0.022 (runs 1, 2), not refused; the bench capture's right squares 0.9998-1.0004 (+-
0.0002-0.0003), 0.098 and 0.102 0.978-0.980 and 1.020-1.021.

SYNOPSIS
    check_board(problem, board_seen(problem, g, lin))   # InputError naming board.size_m / .pattern_offset_m
    check_scale(problem, scale_seen(problem, active, rt_sensor), options)  # InputError naming the camera
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..factors.lidar_edge import edge_sides
from ..geometry import T_from_rt
from . import graph as G
from .seed import board_pose_from_corners

TOLERANCE_M = 0.010  # a side's offset allowed either way: a board measured to the centimetre
GROWTH_RAD = 0.002  # outward, per metre of range: the part of a beam's footprint still returning
MIN_BOARDS = 5
MIN_SIGMAS = 4.0
OFFSET_TOLERANCE_M = 0.005  # a pattern placed on its board by hand, to half a centimetre
SCALE_TOLERANCE = 0.002  # a pattern's scale error below which no check refuses (0.2 mm on a 0.1 m square)


@dataclass(frozen=True)
class ScaleFit:
    slope: float  # a of d_camera = a d_lidar + b
    se: float  # its standard error
    boards: int
    near_m: float  # the nearest and farthest board (LIDAR distance)
    far_m: float


def scale_seen(problem, active, rt_sensor: np.ndarray, rt_camera_board: dict | None = None) -> dict:
    """{camera index: ScaleFit} over its active observations of boards an active LIDAR observation
    shows too: a point per board (its distance by the corners against the mean of the LIDARs'),
    its standard error the larger of the fit's and the leave-one-board-out jackknife's (one board's
    corners off, as a dim camera's farthest board can be, moves the slope by more than the scatter
    of the others shows). ``rt_camera_board``: {(camera, snapshot): the board pose by PnP of its
    corners} where made already (the seed's); the others' are made here."""
    T = [T_from_rt(np.asarray(rt, float)) for rt in rt_sensor]
    centre = problem.board.corners().mean(axis=0)
    planes: dict = {}
    for o, m in zip(problem.lidar_observations, active.lidar):
        if m is not None and m.any():
            planes.setdefault(o.snapshot, []).append(o)
    boards: dict = {}
    for o, m in zip(problem.camera_observations, active.camera):
        if m is None or o.snapshot not in planes:
            continue
        rt = (rt_camera_board or {}).get((o.sensor, o.snapshot))
        if rt is None:
            rt = board_pose_from_corners(o.corners_px, problem.sensors[o.sensor], problem.board, np.inf)
        if isinstance(rt, str):
            continue
        c = T_from_rt(rt)[:3] @ np.r_[centre, 1.0]  # the pattern's centre, camera frame
        u = c / np.linalg.norm(c)
        along = []
        for L in planes[o.snapshot]:
            T_cl = np.linalg.solve(T[o.sensor], T[L.sensor])
            n = T_cl[:3, :3] @ np.asarray(L.plane[:3], float)
            d = float(L.plane[3]) + n @ T_cl[:3, 3]
            if abs(n @ u) > 0.1:
                along.append(d / (n @ u))
        if along:
            boards.setdefault(o.sensor, []).append((float(np.mean(along)), float(np.linalg.norm(c))))
    fits = {}
    for i, v in boards.items():
        lidar, camera = np.array(v).T
        if len(v) < MIN_BOARDS or np.ptp(lidar) <= 0:
            continue
        slope, se = _line_slope(lidar, camera)
        left_out = np.array([_line_slope(np.delete(lidar, k), np.delete(camera, k))[0] for k in range(len(v))])
        jackknife = np.sqrt((len(v) - 1) / len(v) * np.sum((left_out - left_out.mean()) ** 2))
        fits[i] = ScaleFit(slope, max(se, float(jackknife)), len(v), float(lidar.min()), float(lidar.max()))
    return fits


def _line_slope(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """The slope a of y = a x + b by least squares, and its standard error from the residuals."""
    A = np.c_[x, np.ones(len(x))]
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    r = y - A @ coef
    cov = (r @ r / max(len(x) - 2, 1)) * np.linalg.inv(A.T @ A)
    return float(coef[0]), float(np.sqrt(cov[0, 0]))


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
class BoardFit:
    """The board's pattern offset and size as the sensors see them, less the description's."""

    offset_m: np.ndarray  # (2,) the pattern's centre less where board.pattern_offset_m puts it (width, height)
    offset_se_m: np.ndarray  # (2,) its standard errors
    size_m: np.ndarray  # (2,) the board's width and height less board.size_m's
    size_se_m: np.ndarray  # (2,)
    boards_both: int  # snapshots seen by a camera and by a LIDAR's outline (the offset's)
    boards_outline: int  # snapshots whose outline a LIDAR saw (the size's)
    range_m: float  # the median range to those outlines


def _pattern_columns(problem, g, lin) -> dict:
    """{factor index: (rows, 2) its whitened error's change per metre of the pattern shifted along
    the board's width, height (Jacobian columns)} for the camera factors of ``g`` (``lin``: its
    noise.Linearization). The corners are seen at the board's pose, or at T_b C D C^-1 where the observation has its own
    D (C a translation): a right perturbation of that pose by a translation within the board's
    plane moves every corner as the shifted pattern would, so the columns are the factor's own
    Jacobian's (whitened: lin.rows) for D's or the board's translation."""
    import gtsam

    out = {}
    for f, (i, k, _, terms) in enumerate(lin.factors):
        if i is None or k is None or not problem.sensors[i].is_camera:
            continue
        A = lin.rows[terms.start][1]
        kinds = [chr(gtsam.Symbol(key).chr()) for key in g.at(f).keys()]
        at = 6 * kinds.index("e" if "e" in kinds else "b")
        out[f] = A[:, at + 3:at + 5]
    return out


def _size_columns(problem, g, lin) -> dict:
    """{factor index: (rows, 2) its whitened error's change per metre of the board grown along its
    width, height (Jacobian columns)} for the edge factors of ``g`` (robust, lidar_edge_factor):
    each interval's side moves out by half of it (err = its midpoint less the side's bound; the
    sides as edge_sides assigns them at lin's values), whitened by the factor's sigmas and its Huber weight held (as the
    Gauss-Newton step that ``lin`` is does)."""
    import gtsam

    board = problem.board
    x0, x1, y0, y1 = board.extent()
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    obs = {(o.sensor, o.snapshot): o for o in problem.lidar_observations}
    out = {}
    for f, (i, k, _, _) in enumerate(lin.factors):
        factor = g.at(f)
        model = factor.noiseModel()
        if i is None or k is None or not isinstance(model, gtsam.noiseModel.Robust):
            continue
        T_s = None if i == problem.reference else lin.values.atPose3(G.sensor_key(i))
        T_b = lin.values.atPose3(G.board_key(k))
        keep, axis, bounds, _, _ = edge_sides(T_s, T_b, obs[(i, k)].edge_rays, board,
                                              face_m=G.lidar_face(board, T_s, T_b))
        if np.count_nonzero(keep) != factor.dim():  # sides assigned otherwise since the factor was made
            continue
        axis, side = axis[keep], np.sign(bounds[keep] - centre[axis[keep]])
        w = model.robust().weight(float(np.linalg.norm(model.noise().whiten(factor.unwhitenedError(lin.values)))))
        cols = np.zeros((len(axis), 2))
        cols[np.arange(len(axis)), axis] = -side / 2  # d err / d growth, as a Jacobian column
        out[f] = np.sqrt(w) * cols / model.noise().sigmas()[:, None]
    return out


def board_seen(problem, g, lin) -> BoardFit | None:
    """The board's pattern offset and size as the cameras' corners and the LIDARs' outlines see
    them: one Gauss-Newton step from the final solution (``g``, ``lin``: its graph and
    noise.Linearization) with their corrections as four more unknowns beside the sensors; None
    without an outline seen."""
    outlined = [o for o in problem.lidar_observations if o.edge_rays is not None and len(o.edge_rays)]
    if not outlined or lin.rows is None:
        return None
    cols = {f: np.c_[c, np.zeros((len(c), 2))] for f, c in _pattern_columns(problem, g, lin).items()}
    cols.update({f: np.c_[np.zeros((len(c), 2)), c] for f, c in _size_columns(problem, g, lin).items()})
    if not cols:
        return None
    try:
        S, r, _ = lin.with_known(cols, 4).reduced()  # each correction with a unit prior (1 m): free
        C = np.linalg.inv(S)
    except np.linalg.LinAlgError:  # a sensor's direction undetermined: the covariance names it, next
        return None
    x, se = (C @ r)[-4:], np.sqrt(np.diag(C)[-4:])
    if not np.all(np.isfinite(x) & np.isfinite(se)):
        return None
    seen = {o.snapshot for o in outlined}
    return BoardFit(x[:2], se[:2], x[2:], se[2:],
                    len(seen & {o.snapshot for o in problem.camera_observations}), len(seen),
                    float(np.median([np.median(np.linalg.norm(o.points, axis=1)) for o in outlined])))


def check_board(problem, fit: BoardFit | None) -> None:
    """InputError where the outlines show the board's size off board.size_m beyond a board measured
    to the centimetre (a beam's footprint allowed outward), or its pattern off
    board.pattern_offset_m beyond one placed by hand; each beyond 4 standard errors too."""
    if fit is None:
        return
    board = problem.board
    size = np.array([board.width_m, board.height_m])
    allowed = np.where(fit.size_m > 0, 2 * (TOLERANCE_M + GROWTH_RAD * fit.range_m), 2 * TOLERANCE_M)
    off = np.abs(fit.size_m) > np.maximum(allowed, MIN_SIGMAS * fit.size_se_m)
    if fit.boards_outline >= MIN_BOARDS and off.any():
        seen = size + fit.size_m
        raise InputError(
            f"board.size_m: the LIDARs' outlines of {fit.boards_outline} boards show the board {seen[0]:.2f} x "
            f"{seen[1]:.2f} m (+-{fit.size_se_m[0] * 1e3:.0f}, {fit.size_se_m[1] * 1e3:.0f} mm), not the "
            f"[{size[0]:g}, {size[1]:g}] it says: measure the physical board, its white border included, and set "
            "board.size_m (width x height)")
    off = np.abs(fit.offset_m) > np.maximum(OFFSET_TOLERANCE_M, MIN_SIGMAS * fit.offset_se_m)
    if fit.boards_both >= MIN_BOARDS and off.any():
        stated = np.asarray(board.pattern_offset_m, float)
        seen = stated + fit.offset_m
        where = " and ".join(f"{abs(fit.offset_m[a]) * 1e3:.0f} mm {('along the width', 'along the height')[a]} "
                             f"(+-{fit.offset_se_m[a] * 1e3:.1f})" for a in (0, 1) if off[a])
        raise InputError(
            f"board.pattern_offset_m: the cameras' corners and the LIDARs' outlines of the same {fit.boards_both} "
            f"boards put the pattern's centre {where} off where [{stated[0]:g}, {stated[1]:g}] puts it: measure "
            "the pattern's centre from the board's centre (along the width, the height) and set "
            f"board.pattern_offset_m (these captures show [{seen[0]:.3f}, {seen[1]:.3f}]); squares a few tenths "
            "of a percent off board.square_m look alike")
