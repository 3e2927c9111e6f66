"""Chessboard corner detection in camera images (mrgingham CLI or OpenCV).

SYNOPSIS

    from clcgraph.frontend.camera_board import detect_corners
    out = detect_corners(images, DetectionOptions(), BoardGeometry())   # detector "auto"
    for o in out:
        if isinstance(o, Rejected): print(o.reason)
        else: o.shape == (corners_y*corners_x, 2)

Detector: ``auto`` (the default) picks mrgingham for a square grid of inner corners and
OpenCV otherwise (mrgingham finds only NxN grids), and OpenCV when mrgingham is not
installed; a named detector is used as named.

Pixel convention: mrcal's (the centre of pixel (u, v) is at integer (u, v)).

Corner order and its limitation: the returned corners are in board-corner order
(row-major, x fastest, like ``BoardGeometry.corners()``). A printed chessboard has a
front side, so mirror orderings are never produced (the grid's handedness in the image
is that of a board seen from its front). The remaining in-plane rotation (4 for a
square grid, 2 otherwise) cannot be told from the image of a plain chessboard; we pick
the one whose rows run most nearly left-to-right in the image (and columns
top-to-bottom). Consequence: two cameras of the same snapshot get the same ordering
iff their views of the board differ in roll by less than 45 deg (square grid) / 90 deg;
cameras mounted upside-down or 90 deg rolled relative to each other get orderings
rotated by a multiple of 90 deg and the solver must resolve that (e.g. by trying the
4 rotations at seeding).
"""

from __future__ import annotations

import functools
import logging
import os
import shutil
import subprocess
import tempfile
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np

from clcgraph.errors import DependencyError, InputError
from clcgraph.types import BoardGeometry, Image, Rejected

log = logging.getLogger(__name__)

MRGINGHAM = "mrgingham"
# images no larger than this (long side, px) always get the OpenCV fallback (see detect_corners)
SMALL_IMAGE_PX = 640


def to_gray8(pixels: np.ndarray) -> np.ndarray:
    """(H,W) uint8 from mono8, (H,W,3) BGR uint8 or 16-bit mono.

    16-bit images are scaled by their 0.5 / 99.5 percentiles so a few hot pixels or a
    dark 12-bit range do not crush the board's contrast.
    """
    import cv2

    p = np.asarray(pixels)
    if p.ndim == 3:
        if p.shape[2] == 1:
            p = p[..., 0]
        else:
            if p.dtype != np.uint8:
                p = _scale8(p[..., :3])
            p = cv2.cvtColor(np.ascontiguousarray(p[..., :3]), cv2.COLOR_BGR2GRAY)
    if p.dtype == np.uint8:
        return np.ascontiguousarray(p)
    return _scale8(p)


def _scale8(p: np.ndarray) -> np.ndarray:
    p = p.astype(np.float32)
    lo, hi = np.percentile(p, [0.5, 99.5])
    if hi <= lo:
        hi = lo + 1.0
    return np.clip((p - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)


# ---------------------------------------------------------------- ordering and checks


def canonicalize(grid: np.ndarray, nx: int, ny: int) -> np.ndarray | None:
    """Reorder (ny*nx, 2) corners to the canonical board order; None if mirrored.

    The grid is first made right-handed in the image (x right, y down), then rotated
    (4 ways if nx == ny, else 2) so rows run most nearly left-to-right and columns
    top-to-bottom. See the module docstring for the limitation.
    """
    g = grid.reshape(ny, nx, 2)
    # Handedness: cross(row direction, column direction) > 0 for a front view (y down).
    drow = (g[:, -1] - g[:, 0]).mean(axis=0)
    dcol = (g[-1, :] - g[0, :]).mean(axis=0)
    if drow[0] * dcol[1] - drow[1] * dcol[0] < 0:
        # a mirrored order from a detector: flip the columns (board seen from the front)
        g = g[:, ::-1]
    candidates = [g, g[::-1, ::-1]]
    if nx == ny:
        gt = np.swapaxes(g, 0, 1)
        candidates += [gt[:, ::-1], gt[::-1, :]]  # the two 90 deg rotations
    best, score_best = None, -np.inf
    for c in candidates:
        dr = (c[:, -1] - c[:, 0]).mean(axis=0)
        dc = (c[-1, :] - c[0, :]).mean(axis=0)
        score = dr[0] / (np.linalg.norm(dr) + 1e-12) + dc[1] / (np.linalg.norm(dc) + 1e-12)
        if score > score_best:
            best, score_best = c, score
    return best.reshape(-1, 2)


def check_grid(corners: np.ndarray, nx: int, ny: int, imagersize: tuple[int, int],
               *, max_irregularity: float) -> str | None:
    """Why a (ny*nx, 2) grid is implausible, or None if it looks like a chessboard.

    Checks: finite and inside the image; every cell has the same orientation (no fold);
    neighbour steps change smoothly (second difference / step < max_irregularity).
    """
    w, h = imagersize
    c = corners.reshape(ny, nx, 2)
    if not np.all(np.isfinite(c)):
        return "non-finite corners"
    if np.any(c[..., 0] < -0.5) or np.any(c[..., 1] < -0.5) or np.any(c[..., 0] > w - 0.5) \
            or np.any(c[..., 1] > h - 0.5):
        return "corners outside the image"
    a = c[:-1, 1:] - c[:-1, :-1]
    b = c[1:, :-1] - c[:-1, :-1]
    cross = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    if not (np.all(cross > 0) or np.all(cross < 0)):
        return "non-monotonic grid (cells of both orientations)"
    for axis in (0, 1):
        d = np.diff(c, axis=axis)
        step = np.linalg.norm(d, axis=-1)
        if np.any(step < 2.0):
            return "grid cells smaller than 2 px"
        dd = np.linalg.norm(np.diff(d, axis=axis), axis=-1)
        s = np.minimum(np.take(step, range(step.shape[axis] - 1), axis=axis),
                       np.take(step, range(1, step.shape[axis]), axis=axis))
        worst = float(np.max(dd / s))
        if worst > max_irregularity:
            return f"irregular grid (step change {worst:.2f} > {max_irregularity})"
    return None


def _saddles(gray: np.ndarray, corners: np.ndarray, nx: int, ny: int, out: int) -> tuple[np.ndarray, np.ndarray]:
    """Per corner of a canonical (ny*nx, 2) grid extended ``out`` steps on every side (linearly:
    (ny+2*out, nx+2*out)), the saddle contrast from the intensities at the centres of its four
    squares, |(a + c) - (b + d)| / 2 - (|a - c| + |b - d|) / 2: the squares' contrast at a true
    corner, ~0 where two of its squares are the board's border; NaN where a centre is outside the
    image. Also the squares' centres' inside-the-image mask, (ny+2*out+1, nx+2*out+1)."""
    from scipy.ndimage import map_coordinates

    g = corners.reshape(ny, nx, 2)
    for _ in range(out + 1):  # the corners and, one step beyond them, the squares' far sides
        g = np.pad(g, ((1, 1), (1, 1), (0, 0)))
        g[0, 1:-1], g[-1, 1:-1] = 2 * g[1, 1:-1] - g[2, 1:-1], 2 * g[-2, 1:-1] - g[-3, 1:-1]
        g[:, 0], g[:, -1] = 2 * g[:, 1] - g[:, 2], 2 * g[:, -2] - g[:, -3]
    centres = 0.25 * (g[:-1, :-1] + g[1:, :-1] + g[:-1, 1:] + g[1:, 1:])
    h, w = gray.shape
    inside = np.all((centres >= 0) & (centres <= [w - 1, h - 1]), axis=-1)
    v = map_coordinates(gray.astype(np.float32), [centres[..., 1].ravel(), centres[..., 0].ravel()],
                        order=1, mode="nearest").reshape(centres.shape[:2])
    v[~inside] = np.nan
    a, b, cc, d = v[:-1, :-1], v[:-1, 1:], v[1:, 1:], v[1:, :-1]  # each corner's four squares
    return np.abs(a + cc - b - d) / 2 - (np.abs(a - cc) + np.abs(b - d)) / 2, inside


def _side_contrasts(gray: np.ndarray, corners: np.ndarray, nx: int, ny: int, out: int):
    """(the interior corners' typical saddle contrast or None, {side name: the finite contrasts of
    the corners ``out`` steps past that side of the grid, 0: its own outer row or column}, the
    squares' inside-the-image mask) of a canonical (ny*nx, 2) grid (``_saddles``)."""
    score, inside = _saddles(gray, corners, nx, ny, out)
    k = out + 1
    typical = _typical(score[k:-k, k:-k])
    rows, cols = score.shape
    sides = {"top row": score[0, out:cols - out], "bottom row": score[-1, out:cols - out],
             "left column": score[out:rows - out, 0], "right column": score[out:rows - out, -1]}
    return typical, {name: side[np.isfinite(side)] for name, side in sides.items()}, inside


def off_board_side(gray: np.ndarray, corners: np.ndarray, nx: int, ny: int) -> str | None:
    """The side ("left column", ...) of a canonical (ny*nx, 2) grid that is one square off the
    chessboard, or None.

    A detector can read a board cut off by the image's edge as whole: OpenCV's sector-based one
    took the pattern's outer edge, where the squares meet the white border, for a row of corners,
    and the grid came out one square off (34 px; the last row lay beyond the image). A true
    corner has light squares on one diagonal and dark on the other (``_saddles``). A side whose
    median is under half the interior corners' is not on the pattern, but that alone is also what
    something in front of the board's edge does: the grid is off only where the pattern can go
    on past the image's edge, on the opposite side (one of its outer squares is not in the image)."""
    if nx < 3 or ny < 3:
        return None
    typical, sides, inside = _side_contrasts(gray, corners, nx, ny, 0)
    if typical is None:
        return None
    opposite = {"top row": inside[-1], "bottom row": inside[0], "left column": inside[:, -1],
                "right column": inside[:, 0]}
    for name, judged in sides.items():
        if len(judged) and np.median(judged) < 0.5 * typical and not np.all(opposite[name]):
            return name
    return None


def side_without_corners(gray: np.ndarray, corners: np.ndarray, nx: int, ny: int) -> str | None:
    """The side ("left column", ...) of a canonical (ny*nx, 2) grid none of whose corners is one (90 %
    of them under half the interior corners' saddle contrast), or None: a grid of more inner
    corners than the board has, which OpenCV's sector-based detector completes with a row along
    the pattern's edge, where the outer squares meet the white border (a whole board in view,
    board.corners one too many: 2 of 16 images of a 9x6 board read as 10x6). A side hidden in part
    (an arm across it) keeps the corners it shows."""
    if nx < 3 or ny < 3:
        return None
    typical, sides, _ = _side_contrasts(gray, corners, nx, ny, 0)
    if typical is None:
        return None
    for name, judged in sides.items():
        if len(judged) >= 3 and np.quantile(judged, 0.9) < 0.5 * typical:
            return name
    return None


# how a detection of a part of a larger pattern is rejected (api names board.corners from it)
PATTERN_GOES_ON = "the chessboard goes on past the grid's"
# ... and one of more corners than the pattern has
PATTERN_ENDS = "no chessboard corner along the grid's"


def pattern_goes_on(gray: np.ndarray, corners: np.ndarray, nx: int, ny: int) -> str | None:
    """The side ("left column", ...) past which the chessboard goes on, or None: a grid of fewer
    inner corners than the board has read off part of it (``board.corners`` set short, e.g. the
    squares counted less one too many), each corner then a square or more from the one it is taken
    for. One step past a true grid's outer corners lies the pattern's edge, two of each corner's
    squares the border (saddle contrast ~0); past a part of the pattern, more true corners (the
    contrast of the interior's). Judged on a side's corners whose four squares are in the image."""
    if nx < 3 or ny < 3:
        return None
    typical, ring, _ = _side_contrasts(gray, corners, nx, ny, 1)  # the corners one step past the grid's sides
    if typical is None:
        return None
    for name, judged in ring.items():
        if len(judged) >= 2 and np.median(judged) > 0.5 * typical:
            return name
    return None


def _typical(interior: np.ndarray) -> float | None:
    """The interior corners' median saddle contrast, or None if there is none to compare with."""
    if not np.any(np.isfinite(interior)):
        return None
    typical = float(np.nanmedian(interior))
    return typical if typical > 0 else None


def blur_sigma_px(gray: np.ndarray, corners: np.ndarray, nx: int, ny: int) -> float:
    """Median Gaussian-blur sigma (px) of the board's edges, from intensity profiles.

    Profiles cross the square edges midway between neighbour corners, perpendicular
    to the edge; a step of contrast C blurred by sigma has a peak slope
    C / (sqrt(2 pi) sigma). An ideal area-sampled step reads ~0.4 px.
    """
    from scipy.ndimage import map_coordinates

    c = corners.reshape(ny, nx, 2)
    mids, perps, lens = [], [], []
    for axis in (0, 1):  # edges between neighbours along rows (axis=1) / columns (axis=0)
        d = np.diff(c, axis=1 - axis)
        m = 0.5 * (np.take(c, range(c.shape[1 - axis] - 1), axis=1 - axis)
                   + np.take(c, range(1, c.shape[1 - axis]), axis=1 - axis))
        L = np.linalg.norm(d, axis=-1)
        u = d / L[..., None]
        p = np.stack([-u[..., 1], u[..., 0]], axis=-1)
        mids.append(m.reshape(-1, 2))
        perps.append(p.reshape(-1, 2))
        lens.append(L.reshape(-1))
    mids = np.concatenate(mids)
    perps = np.concatenate(perps)
    half = 0.35 * np.concatenate(lens)  # stay inside the two squares
    t = np.linspace(-1.0, 1.0, 41)
    xy = mids[:, None, :] + (half[:, None] * t)[..., None] * perps[:, None, :]  # (E,41,2)
    prof = map_coordinates(gray.astype(np.float32), [xy[..., 1].ravel(), xy[..., 0].ravel()],
                           order=1, mode="nearest").reshape(xy.shape[:2])
    dt = half * (t[1] - t[0])  # px per sample
    contrast = np.abs(prof[:, -5:].mean(axis=1) - prof[:, :5].mean(axis=1))
    slope = np.max(np.abs(np.gradient(prof, axis=1)), axis=1) / dt
    ok = contrast > 10.0
    if not np.any(ok):
        return float("inf")
    sigma = contrast[ok] / (np.sqrt(2 * np.pi) * slope[ok])
    return float(np.median(sigma))


def _validate(corners: np.ndarray | None, gray: np.ndarray, nx: int, ny: int, options,
              why_missing: str) -> np.ndarray | Rejected:
    if corners is None:
        return Rejected(why_missing, "detection")
    if corners.shape != (nx * ny, 2):
        return Rejected(f"wrong corner count {len(corners)} (expected {nx * ny})", "detection")
    c = canonicalize(corners, nx, ny)
    h, w = gray.shape
    why = check_grid(c, nx, ny, (w, h), max_irregularity=options.max_grid_irregularity)
    if why is not None:
        return Rejected(why, "detection")
    side = off_board_side(gray, c, nx, ny)
    if side is not None:
        return Rejected(f"a board cut off by the image's edge, read as whole: the grid's {side} of corners is "
                        "not on the chessboard (one square off)", "detection")
    side = pattern_goes_on(gray, c, nx, ny)
    if side is not None:
        return Rejected(f"{PATTERN_GOES_ON} {side}: more inner corners than the {nx}x{ny} of "
                        "board.corners (a part of the pattern read as the board)", "detection")
    side = side_without_corners(gray, c, nx, ny)
    if side is not None:
        return Rejected(f"{PATTERN_ENDS} {side}: the pattern's edge read as corners (fewer inner corners than the "
                        f"{nx}x{ny} of board.corners?)", "detection")
    sigma = blur_sigma_px(gray, c, nx, ny)
    if sigma > options.max_blur_sigma_px:
        return Rejected(f"blurred board (edge sigma {sigma:.2f} px > {options.max_blur_sigma_px})",
                        "detection")
    return refine_corners(gray, c, nx, ny) if options.refine_subpix else c


def refine_corners(gray: np.ndarray, corners: np.ndarray, nx: int, ny: int) -> np.ndarray:
    """Corners refined to the saddle point of the image gradient (OpenCV cornerSubPix), in a
    window of a third of the local square size. Both detectors leave structured errors of
    ~0.1-0.2 px (small boards come out shrunk by ~0.3 %), which bias the camera poses; after
    this step they are ~0.05 px on simulated images. A corner that moves more than a quarter
    square keeps its detected position. Squares under 6 px (a window of 2 px would reach
    into the next corner's) are refined in the image upsampled to 6 px squares."""
    import cv2

    grid = corners.reshape(ny, nx, 2)
    steps = np.r_[np.linalg.norm(np.diff(grid, axis=0), axis=-1).ravel(),
                  np.linalg.norm(np.diff(grid, axis=1), axis=-1).ravel()]
    step = float(np.median(steps))
    if step < 6.0:
        f = int(np.ceil(6.0 / step))
        up = cv2.resize(gray, None, fx=f, fy=f, interpolation=cv2.INTER_CUBIC)
        return (refine_corners(up, (corners + 0.5) * f - 0.5, nx, ny) + 0.5) / f - 0.5
    half = int(np.clip(step / 3, 2, 15))
    # cornerSubPix puts pixel centres at integer coordinates, like mrcal
    refined = cv2.cornerSubPix(gray, corners.astype(np.float32).reshape(-1, 1, 2).copy(), (half, half), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)).reshape(-1, 2)
    moved = np.linalg.norm(refined - corners, axis=1) > step / 4
    return np.where(moved[:, None], corners, refined.astype(float))


# ---------------------------------------------------------------- mrgingham


@functools.lru_cache(maxsize=None)
def _warn_once(message: str) -> None:
    log.warning(message)


def choose_detector(options, board: BoardGeometry) -> str:
    """The detector to run: the one named in ``options.detector``, or for ``auto`` the one that
    handles the board (mrgingham: square grids only, when installed; else OpenCV)."""
    if options.detector not in ("auto", "mrgingham", "opencv"):
        raise InputError(f"unknown detector {options.detector!r}: use auto, mrgingham or opencv")
    square = board.is_square_grid
    if options.detector == "auto":
        if square and shutil.which(MRGINGHAM) is None:
            _warn_once("mrgingham not installed (apt install mrgingham): detecting chessboards with OpenCV")
            return "opencv"
        return MRGINGHAM if square else "opencv"
    if options.detector == MRGINGHAM and not square:
        raise InputError(f"detection.detector: mrgingham finds only square grids, the board has "
                         f"{board.corners_x}x{board.corners_y} inner corners: use detector auto or opencv")
    return options.detector


def _scratch_dir() -> str | None:
    """Where the images for the mrgingham command go: the user's TMPDIR when set (their place for
    temporary files; None: tempfile's choice, which skips a TMPDIR it cannot write to), else
    memory-backed /dev/shm when there is one, else the system's default."""
    if os.environ.get("TMPDIR"):
        return None
    return "/dev/shm" if os.access("/dev/shm", os.W_OK) else None


# Added to the detectors' output to get mrcal's convention (measured against rendered
# truth in tests/test_camera_board.py).
_OFFSET_PX = {"mrgingham": np.zeros(2), "opencv": np.zeros(2)}


def _run_mrgingham(grays: list[np.ndarray], n: int, jobs: int) -> list[np.ndarray | None]:
    """Corners (N,2, mrcal's pixel convention) or None per image of an n x n grid, from ONE mrgingham
    run over all the images.

    The images are written uncompressed (PGM: a memory copy; PNG compression cost 6x the detector)."""
    import cv2

    exe = shutil.which(MRGINGHAM)
    if exe is None:
        raise DependencyError("mrgingham command-line tool not found (apt install mrgingham, "
                              "or set detection.detector: opencv)")
    if not grays:
        return []
    with tempfile.TemporaryDirectory(prefix="clcgraph-mrg-", dir=_scratch_dir()) as tmp:
        names = []
        for i, g in enumerate(grays):
            name = os.path.join(tmp, f"{i:06d}.pgm")
            if not cv2.imwrite(name, np.ascontiguousarray(g)):
                raise DependencyError(f"cannot write the image for mrgingham in {tmp}")
            names.append(name)
        cmd = [exe, "--jobs", str(max(1, jobs)), "--gridn", str(n), os.path.join(tmp, "*.pgm")]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            raise DependencyError(f"mrgingham failed (exit {r.returncode}): "
                                  f"{r.stderr.strip().splitlines()[-1:] or ''}")
    pts: dict[str, list[tuple[float, float]]] = {n: [] for n in names}
    for line in r.stdout.splitlines():
        if not line or line.startswith("#"):
            continue
        f = line.split()
        if f[1] == "-":
            continue
        pts[f[0]].append((float(f[1]), float(f[2])))
    return [np.array(pts[n], dtype=float) + _OFFSET_PX["mrgingham"] if pts[n] else None for n in names]


# ---------------------------------------------------------------- opencv


def _opencv_one(args) -> np.ndarray | None:
    import cv2

    gray, nx, ny, exhaustive, accuracy = args
    cv2.setNumThreads(1)
    flags = (cv2.CALIB_CB_NORMALIZE_IMAGE | (cv2.CALIB_CB_ACCURACY if accuracy else 0)
             | (cv2.CALIB_CB_EXHAUSTIVE if exhaustive else 0))
    ok, c = cv2.findChessboardCornersSB(gray, (nx, ny), flags=flags)
    if not ok or c is None:
        return None
    return c.reshape(-1, 2).astype(float) + _OFFSET_PX["opencv"]


def _run_opencv(grays: list[np.ndarray], nx: int, ny: int, jobs: int, *, quick_first: bool,
                exhaustive=True) -> list[np.ndarray | None]:
    """Corners (N,2, mrcal's pixel convention) or None per image, from OpenCV's sector-based
    detector. ``exhaustive``: per image (or one for all), whether it searches exhaustively
    (CALIB_CB_EXHAUSTIVE: more board hypotheses, for a board anywhere among clutter; on a miss it
    costs 2x). ``quick_first``: search without
    OpenCV's own refinement (CALIB_CB_ACCURACY, on an upsampled image) first, with it only where
    that missed; for whole images whose corners will be refined (refine_corners). There it takes
    4-5x the time (1.4-1.8 s against 0.33 s per real ACFR 1920x1208 image) and the refined corners
    are the same with or without it (0.0002-0.0005 px; 0.05 px on one of 9 boards), though it finds
    2 boards of those 11 that the quick search misses. Not for the fallback's small crops of boards
    mrgingham missed: there it costs 0.1-0.2 s and finds what the quick search misses."""
    exhaustive = [exhaustive] * len(grays) if isinstance(exhaustive, bool) else list(exhaustive)
    out = _opencv_all([(g, nx, ny, e, not quick_first) for g, e in zip(grays, exhaustive)], jobs)
    if quick_first:
        missed = [k for k, c in enumerate(out) if c is None]
        for k, c in zip(missed, _opencv_all([(grays[k], nx, ny, exhaustive[k], True) for k in missed], jobs)):
            out[k] = c
    return out


def _opencv_all(args: list, jobs: int) -> list[np.ndarray | None]:
    """_opencv_one of each of ``args``, in ``jobs`` threads."""
    if jobs <= 1 or len(args) < 2:
        return [_opencv_one(a) for a in args]
    # threads: OpenCV releases the GIL while detecting (and worker processes would fork a
    # threaded process or re-import the caller's script)
    with ThreadPoolExecutor(max_workers=jobs) as ex:
        return list(ex.map(_opencv_one, args, chunksize=max(1, len(args) // (4 * jobs))))


def not_found_text(board: BoardGeometry) -> str:
    """The detector's own reason when it finds no grid (api.explain_not_found says more after a solve)."""
    return f"no full {board.corners_x}x{board.corners_y} chessboard found"


def detect_corners(images: list[Image], options, board: BoardGeometry, *,
                   regions: list | None = None) -> list[np.ndarray | Rejected]:
    """Chessboard corners per image: (corners_y*corners_x, 2) pixels, or Rejected(reason).

    options: ``config.DetectionOptions``; ``board``: its inner-corner grid is searched for.
    Corners are in canonical board order (module docstring) in mrcal's pixel convention. The
    mrgingham detector runs one batched command-line call (``--jobs``) for all the images, then
    one for the retries of its misses; OpenCV runs in ``jobs`` threads. ``regions``: per image,
    where a missed board can be (see ``BoardDetection.retry``); None: anywhere.
    """
    return BoardDetection(images, options, board).retry(regions)


class BoardDetection:
    """Chessboard detection in two steps, so a caller can say where the missed boards can be.

    SYNOPSIS
        d = BoardDetection(images, options, board)   # first pass: every image at once
        d.results                                     # (N,2) corners or Rejected, per image
        d.missed                                      # indices of the images with no grid found
        d.retry(regions)                              # the misses again, only where a board can be

    The first pass finds boards with squares of >= ~8 px. A miss is retried in the image
    upsampled 2x (mrgingham finds squares of 5-8 px there), then with OpenCV's sector-based
    detector where it still finds nothing. Upsampling a whole image costs 4x a first pass:
    ``regions`` limits the retries to a box per image (a LIDAR's view of the board predicts
    it), and an empty box skips them.
    """

    def __init__(self, images: list[Image], options, board: BoardGeometry):
        self.images, self.options, self.board = list(images), options, board
        self.detector = choose_detector(options, board)
        self.grays = [to_gray8(im.pixels) for im in self.images]
        nx, ny, jobs = board.corners_x, board.corners_y, options.jobs
        if self.detector == MRGINGHAM:
            raw = _run_mrgingham(self.grays, nx, jobs)
        else:
            raw = _run_opencv(self.grays, nx, ny, jobs, quick_first=options.refine_subpix)
        self.results = [self._validated(k, c) for k, c in enumerate(raw)]
        # only mrgingham's misses are retried (OpenCV has searched the whole image already)
        self.missed = [k for k, c in enumerate(raw) if c is None] if self.detector == MRGINGHAM else []

    def _validated(self, k: int, corners: np.ndarray | None) -> np.ndarray | Rejected:
        nx, ny = self.board.corners_x, self.board.corners_y
        r = _validate(corners, self.grays[k], nx, ny, self.options, not_found_text(self.board))
        if isinstance(r, Rejected):
            log.debug("%s @%d: %s", self.images[k].topic, self.images[k].stamp_ns, r.reason)
        return r

    def grid_shown_instead(self, *, sample: int = 24, reach: int = 2) -> tuple[int, list[str], int] | None:
        """After a mrgingham first pass that found no board in any image: the square grid of m x m
        inner corners (m within ``reach`` of board.corners, m != it) shown whole (the pattern ends
        at its sides: ``pattern_goes_on``) in >= 2 of up to ``sample`` images spread over the
        list: (m, the topics of the images showing it, images checked), else None (the boards too
        small for a first pass, say: the retries look for them). A board has one such m: a grid
        one short of the board's is a part of its pattern, not whole."""
        n = self.board.corners_x
        if self.detector != MRGINGHAM or not self.images or any(isinstance(r, np.ndarray) for r in self.results):
            return None
        picked = np.unique(np.linspace(0, len(self.images) - 1, min(sample, len(self.images))).round().astype(int))
        for m in sorted({n + d for d in range(-reach, reach + 1)} - {n}, key=lambda m: (abs(m - n), m)):
            if m < 3:
                continue
            found = _run_mrgingham([self.grays[k] for k in picked], m, self.options.jobs)
            shown = [self.images[k].topic for k, c in zip(picked, found) if c is not None and isinstance(
                _validate(c, self.grays[k], m, m, self.options, ""), np.ndarray)]
            if len(shown) >= 2:
                return m, shown, len(picked)
        return None

    def retry(self, regions: list | None = None) -> list[np.ndarray | Rejected]:
        """Retry the missed images (mrgingham, then the OpenCV fallback); returns ``results``.

        ``regions``: per image (all of them, in order) None (the board can be anywhere: the whole
        image, upsampled 2x), or a ``Region`` where it can be: that box is searched, upsampled 2x
        if the predicted squares are small (``_UPSAMPLE_BELOW_PX``) or the box is at most a
        quarter of the image (then at no more cost than the first pass); an empty box
        (``NOWHERE``) means it cannot be in view and a ``hidden`` one that something in front of
        the board covers its pattern (that is the image's reason): neither is searched again."""
        import cv2

        nx, ny, jobs = self.board.corners_x, self.board.corners_y, self.options.jobs
        crops = {}  # image index -> (x0, y0, x1, y1, upsampling factor for mrgingham, OpenCV's in turn)
        for k in self.missed:
            h, w = self.grays[k].shape
            r = None if regions is None else regions[k]
            if r is not None and r.hidden:
                self.results[k] = Rejected(r.hidden, "detection")
                continue
            box = (0, 0, w, h) if r is None else r[:4]
            x0, y0 = max(0, int(np.floor(box[0]))), max(0, int(np.floor(box[1])))
            x1, y1 = min(w, int(np.ceil(box[2]))), min(h, int(np.ceil(box[3])))
            # 2x where the squares are small, and wherever that costs no more than the first pass did
            # (a box of at most a quarter of the image): the first pass missed this board at this
            # scale, a board hidden in part at its edge among them. OpenCV tries such a box as it is
            # first: it finds most boards of >= 8 px squares there, at a third of the cost
            small = r is None or r.square_px is None or r.square_px < _UPSAMPLE_BELOW_PX
            f = 2 if small or 4 * (x1 - x0) * (y1 - y0) <= w * h else 1
            if x1 - x0 >= 2 * (nx + 1) and y1 - y0 >= 2 * (ny + 1):  # room for squares of >= 2 px
                crops[k] = (x0, y0, x1, y1, f, (2,) if small else (1, 2)[:f])
        log.debug("retrying %d of the %d missed images (%d of them whole: no prediction)", len(crops), len(self.missed),
                  sum(regions is None or regions[k] is None for k in crops))
        self.missed = []

        @functools.lru_cache(maxsize=None)
        def crop(k, f):  # the box of image k, upsampled f times
            x0, y0, x1, y1 = crops[k][:4]
            g = self.grays[k][y0:y1, x0:x1]
            return cv2.resize(g, None, fx=f, fy=f, interpolation=cv2.INTER_CUBIC) if f > 1 else g

        def back(k, c, f):  # (upsampled) crop -> image pixels (pixel centres at integers in both)
            x0, y0 = crops[k][:2]
            return (c + 0.5) / f - 0.5 + (x0, y0)

        # mrgingham misses small boards (squares of 5-8 px): it finds them in the image upsampled 2x,
        # and some boards in a crop it misses in the whole image
        keys = list(crops)
        still = []
        for k, c in zip(keys, _run_mrgingham([crop(k, crops[k][4]) for k in keys], nx, jobs)):
            if c is None:
                still.append(k)
            else:
                self.results[k] = self._validated(k, back(k, c, crops[k][4]))
        # ... and where it still finds nothing, OpenCV's sector-based detector may, in the
        # upsampled image too (its grid passes the same checks). The full detector is slow, so
        # it runs only where OpenCV's quick check sees a board, except in low-resolution images
        # (<= SMALL_IMAGE_PX on the long side, cheap to search): there a board at LIDAR ranges
        # has squares of 3-5 px, which the quick check misses. Its exhaustive search (twice the
        # cost of a miss, the usual outcome here: a board hidden in part) only where the board can
        # be anywhere in the image; a box the LIDARs predicted holds little but the board
        for turn in range(2 if still and self.options.fallback_opencv else 0):
            tries = [(k, crops[k][5][turn]) for k in still if turn < len(crops[k][5])]
            tries = [(k, f) for k, f in tries if max(self.grays[k].shape) <= SMALL_IMAGE_PX
                     or cv2.checkChessboard(crop(k, f), (nx, ny))]
            if not tries:
                continue
            anywhere = [regions is None or regions[k] is None for k, _ in tries]
            for (k, f), c in zip(tries, _run_opencv([crop(k, f) for k, f in tries], nx, ny, jobs,
                                                    exhaustive=anywhere, quick_first=False)):
                if c is not None:
                    self.results[k] = self._validated(k, back(k, c, f))
                    still.remove(k)
        return self.results


# The seed's camera pose is good to ~1 deg: predicted pixels get this angle's worth of slack.
_REGION_MARGIN_RAD = np.radians(2.0)
# mrgingham misses squares of 5-8 px; a predicted square (from the board's diagonal) is up to
# 1/cos(45 deg) = 1.4x a tilted board's short side: under 8 x 1.4 px, a retry upsamples 2x
_UPSAMPLE_BELOW_PX = 12.0


# Something counts as in front of the board this far (m) before it along the camera's ray: beyond
# a LIDAR's range noise and the seed's error, short of a hand on the board's edge
_IN_FRONT_M = 0.15
# ... and as hiding the board when this many of its LIDAR returns cover the board's pattern, each
# with two others within this distance (m): a surface's returns, not stray ones (a heavy-tailed
# range error puts a board's own return decimetres short, alone)
_HIDING_RETURNS = 3
_NEIGHBOUR_M = 0.15


class Region(NamedTuple):
    """Where a board can be in an image (pixels), and its predicted square size (px; None: unknown).
    ``hidden``: why no detector can find it there (something in front of the board), else None."""
    x0: float
    y0: float
    x1: float
    y1: float
    square_px: float | None = None
    hidden: str | None = None


NOWHERE = Region(0.0, 0.0, 0.0, 0.0)


def board_regions(camera, views, board: BoardGeometry, scenes=None) -> list:
    """Where the board can be in each of a camera's images, from LIDAR views of the same boards.

    ``camera``: the camera's Sensor; ``views``: per image, a list of (rt_camera_lidar (6,),
    LidarBoardObservation) of its snapshot (empty: no LIDAR saw that board); ``scenes``: optional,
    per image, the same LIDARs' whole scans (LidarScan, or None), in the order of its views.
    Returns per image None (no prediction: the board may be anywhere), a ``Region`` (a box in
    pixels and the predicted square size), or ``NOWHERE`` when the whole board cannot be in view.

    The LIDAR's board points are on the board: when one of them projects outside the image
    (by more than the seed's error, ``_REGION_MARGIN_RAD``) or lies behind the camera, the
    board is not whole in the image and no detector can find it. Otherwise the board lies
    within its half diagonal of the points' centroid: the box holds that disc, projected. A
    scan's returns in front of the board that cover its pattern in the image (``hidden_by``) make
    the region ``hidden``: the camera sees them, not the whole pattern.
    """
    from clcgraph import cameras
    from clcgraph.geometry import transform

    xmin, xmax, ymin, ymax = board.extent()
    radius = 0.5 * float(np.hypot(xmax - xmin, ymax - ymin))
    a = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    w, h = camera.imagersize
    slack = float(np.mean(np.asarray(camera.intrinsics[:2], float))) * np.tan(_REGION_MARGIN_RAD)

    def in_image(q):
        return np.all((q >= -slack) & (q <= np.array([w - 1, h - 1]) + slack), axis=1)

    def project(p, *, give_up_outside=False):
        """Pixels, and whether each is a true projection (in front, not folded back by the lens);
        ``give_up_outside``: None when a point is behind the camera or outside the image (checking
        the fold-back, an iterative unprojection, is most of the cost)."""
        q = cameras.project(p, camera.lensmodel, camera.intrinsics)
        ok = (p[:, 2] > 0) & np.all(np.isfinite(q), axis=1)
        if give_up_outside and not np.all(ok & in_image(q)):
            return None
        back = cameras.unproject(q, camera.lensmodel, camera.intrinsics)
        ray = p / np.linalg.norm(p, axis=1)[:, None]
        ok &= np.einsum("ij,ij->i", back, ray) > np.cos(np.radians(1.0))
        return q, ok

    out = []
    for image_views in views:
        if not image_views:
            out.append(None)
            continue
        on_board, discs = [], []
        for rt_camera_lidar, obs in image_views:
            p = np.asarray(obs.points, float)
            n = np.asarray(obs.plane[:3], float)
            u = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
            u /= np.linalg.norm(u)
            v = np.cross(n, u)
            on_board.append(transform(np.asarray(rt_camera_lidar, float), p))
            discs.append(transform(np.asarray(rt_camera_lidar, float),
                                   p.mean(axis=0) + radius * (np.cos(a)[:, None] * u + np.sin(a)[:, None] * v)))
        projected = project(np.concatenate(on_board), give_up_outside=True)
        if projected is None or not np.all(projected[1]):
            out.append(NOWHERE)
            continue
        q = projected[0]
        qd, okd = project(np.concatenate(discs))
        # the disc's projected diameter is the board's diagonal: squares are that over diagonal / square
        square = float(np.max(np.ptp(qd[okd], axis=0))) * board.square_m / (2 * radius) if okd.sum() > 2 else None
        hidden = None
        ends = np.cumsum([len(p) for p in on_board])
        for (rt_camera_lidar, obs), scan, p_view, q_view in zip(image_views, scenes[len(out)] if scenes else (),
                                                                 on_board, np.split(q, ends[:-1])):
            hidden = hidden or hidden_by(camera, rt_camera_lidar, obs, scan, p_view, q_view, board)
        q = np.r_[q, qd[okd]]
        lo, hi = q.min(axis=0) - slack, q.max(axis=0) + slack
        out.append(Region(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]), square, hidden))
    return out


def hidden_by(camera, rt_camera_lidar, obs, scan, p_board: np.ndarray, q_board: np.ndarray,
              board: BoardGeometry) -> str | None:
    """Why the camera cannot see the whole pattern of a board a LIDAR saw, or None: that LIDAR's
    returns in ``scan`` (its LidarScan of the snapshot, or None) lying in front of the board's
    plane (``_IN_FRONT_M`` before it along the camera's ray) and projecting onto the board's
    pattern (``_HIDING_RETURNS`` of them, each with two others within ``_NEIGHBOUR_M``): the
    board's returns (``obs.points`` in the camera's frame, ``p_board`` (N,3), and as projected,
    ``q_board`` (N,2) px) shrunk about their centre to the pattern's share of the board.
    Whatever a LIDAR sees in front of the board is there for the camera too: a pole, an arm
    across it, the person holding it."""
    import cv2
    from scipy.spatial import cKDTree

    from clcgraph import cameras
    from clcgraph.geometry import R_from_r, transform

    if scan is None or not scan.valid.any() or len(q_board) < 3:
        return None
    rt = np.asarray(rt_camera_lidar, float)
    p = transform(rt, np.asarray(scan.points, float)[scan.valid])
    n = R_from_r(rt[:3]) @ np.asarray(obs.plane[:3], float)
    d = float(obs.plane[3]) + n @ rt[3:]  # the board's plane n . x = d in the camera's frame
    r = np.linalg.norm(p, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = d * r / (p @ n)  # where each return's camera ray meets the plane
    front = (p[:, 2] > 0) & (s > 0) & (r < s - _IN_FRONT_M)
    # ... near the board (no farther from its returns' centre than the board's half diagonal): only
    # those can cover it, and a lens model is not asked about rays far outside its view
    centre = p_board.mean(axis=0)
    front[front] = np.linalg.norm(p[front] * (s[front] / r[front])[:, None] - centre, axis=1) \
        <= 0.5 * np.hypot(*board.size_m)
    if front.sum() < _HIDING_RETURNS:
        return None
    q = cameras.project(p[front], camera.lensmodel, camera.intrinsics)
    share = min(*np.divide(board.pattern_size_m, board.size_m), 1.0)
    c = q_board.mean(axis=0)
    pattern = (c + share * (q_board - c)).astype(np.float32)
    hull = cv2.convexHull(pattern)
    near = np.all((q >= pattern.min(axis=0)) & (q <= pattern.max(axis=0)), axis=1)  # (NaN: False)
    inside = near.copy()
    inside[near] = [cv2.pointPolygonTest(hull, (float(u), float(v)), False) >= 0 for u, v in q[near]]
    if inside.sum() < _HIDING_RETURNS:
        return None
    cover = p[front][inside]
    solid = cKDTree(cover).query_ball_point(cover, _NEIGHBOUR_M, return_length=True) >= 3
    if solid.sum() < _HIDING_RETURNS:
        return None
    ahead = float(np.median((s - r)[front][inside][solid]))
    return (f"board hidden in part: {int(solid.sum())} LIDAR returns {ahead:.1f} m in front of it cover its "
            "pattern in this image (a pole, an arm, the person?)")


# Squares smaller than this (px) are often missed even in the 2x upsampled image (see detect_corners)
SMALL_SQUARE_PX = 5.0


def not_found_reason(q_px: np.ndarray, imagersize: tuple[int, int], board: BoardGeometry, *, what: str) -> str:
    """What a camera saw where it found no chessboard, from where the solved poses put the board:
    ``q_px`` (N,2) are the board's points (``what``: e.g. "its LIDAR points") projected into the
    image, NaN where behind the camera. "no board in view", "board partly outside the image (..)",
    "board 60 px wide: too small (..)", or in full view and still not found."""
    w, h = imagersize
    q = np.asarray(q_px, float).reshape(-1, 2)
    ok = np.all(np.isfinite(q), axis=1)
    inside = ok & (q[:, 0] >= -0.5) & (q[:, 1] >= -0.5) & (q[:, 0] <= w - 0.5) & (q[:, 1] <= h - 0.5)
    n = len(q)
    if not inside.any():
        return f"no board in view ({what} project outside the image, by the solved poses)"
    if not inside.all():
        share = f"{100 * inside.mean():.0f} %" if inside.mean() >= 0.005 else "< 1 %"
        return f"board partly outside the image ({share} of {what} inside, by the solved poses)"
    width = float(np.max(np.ptp(q, axis=0)))
    square = width * board.square_m / max(board.width_m, board.height_m)
    if square < SMALL_SQUARE_PX:
        return f"board {width:.0f} px wide: too small (squares ~{square:.1f} px, by the solved poses)"
    return (f"board in view, {width:.0f} px wide (squares ~{square:.0f} px, by the solved poses), but no full "
            f"{board.corners_x}x{board.corners_y} chessboard found: blurred, badly lit or partly hidden?")


def detect_in_bags(bags, topic: str, options, board: BoardGeometry, *, every: bool = False, batch: int = 32,
                   with_bag: bool = False):
    """Yield (Image, corners (N,2) | Rejected) for the images of ``topic`` in ``bags``
    (``with_bag``: (Image, result, the bag's path)).

    Default: the first image of each bag (one snapshot per bag); ``every``: all images,
    streamed and detected in batches of ``batch``.
    """
    from clcgraph.frontend.bag import first_messages, read_messages

    def images():
        if every:
            for m in read_messages(list(bags), [topic]):
                yield m.bag, m.data
        else:
            for b in bags:
                first = first_messages(b, [topic])
                if topic in first:
                    yield b, first[topic]

    def done(buf):
        found = detect_corners([im for _, im in buf], options, board)
        return [(im, r, b) if with_bag else (im, r) for (b, im), r in zip(buf, found)]

    buf: list = []
    for b, im in images():
        if not isinstance(im, Image):
            raise InputError(f"{b}: topic {topic} holds {type(im).__name__}, not images (sensor_msgs/Image or "
                             "CompressedImage)")
        buf.append((b, im))
        if len(buf) == batch:
            yield from done(buf)
            buf = []
    if buf:
        yield from done(buf)


def draw_detection(image: Image, result) -> np.ndarray:
    """(H,W,3) BGR picture of an image with its detected grid or the rejection reason."""
    import cv2

    g = to_gray8(image.pixels)
    out = cv2.cvtColor(g, cv2.COLOR_GRAY2BGR)
    if isinstance(result, Rejected):
        cv2.putText(out, result.reason[:90], (10, 25), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 255), 2)
        return out
    pts = np.round(result).astype(np.int32)
    cv2.polylines(out, [pts.reshape(-1, 1, 2)], False, (0, 200, 0), 1)
    for k, (u, v) in enumerate(pts):
        cv2.circle(out, (int(u), int(v)), 3, (0, 0, 255) if k == 0 else (0, 255, 255), -1)
    return out
