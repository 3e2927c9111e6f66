"""Lens-exact camera images of the scene: any mrcal lens model, an anti-aliased chessboard with
its white border.

Every pixel's ray comes from mrcal's unprojection of that pixel through the camera's own
lens model, so a detector run on the picture sees exactly the geometry the solver assumes.
The scene is ray cast once per pixel; pixels on or next to the board are then supersampled
(``supersample``^2 rays each, intersected with the board plane analytically), so corners are
anti-aliased to well under 0.1 px. Other surfaces get a flat shade per object with a little
texture; the sky is light gray. Gaussian pixel noise and an optional blur follow.

SYNOPSIS
    image, corners_px = render(camera, T_world_camera, scene, board, T_world_board, rng, topic="/cam")
"""

from __future__ import annotations

import numpy as np

from .. import cameras
from ..types import BoardGeometry, Image, Sensor

BLACK, WHITE = 25.0, 225.0

# A raw Bayer mosaic as machine-vision drivers publish it (ROS names; row 0 = its first two letters)
BAYER_ENCODINGS = ("bayer_rggb8", "bayer_bggr8", "bayer_gbrg8", "bayer_grbg8")
# The sensor's raw response to the scene's (white-balanced) colour, per B, G, R: a silicon sensor
# under daylight records red and blue at about half of green before white balance
_RAW_GAINS_BGR = np.array([0.6, 1.0, 0.5])


def board_shade(board: BoardGeometry, xy: np.ndarray) -> np.ndarray:
    """Gray level of board-frame points (…,2): the pattern's (corners + 1) x (corners + 1) squares,
    edges through the inner corners, reaching one square beyond the outer corners; white border
    around them (to the board's edge, ``board.extent()``)."""
    s = board.square_m
    x, y = xy[..., 0], xy[..., 1]
    i, j = np.floor(x / s), np.floor(y / s)
    inside = (i >= -1) & (i <= board.corners_x - 1) & (j >= -1) & (j <= board.corners_y - 1)
    return np.where(inside & ((i + j) % 2 == 0), BLACK, WHITE)


def board_corners_px(camera: Sensor, T_world_camera: np.ndarray, board: BoardGeometry,
                     T_world_board: np.ndarray) -> np.ndarray | None:
    """(N,2) pixels of the board's corners in ``camera``, or None if one is behind it (corners
    behind the camera project to plausible-looking pixels: they are not seen)."""
    T_cb = np.linalg.inv(T_world_camera) @ T_world_board
    pc = board.corners() @ T_cb[:3, :3].T + T_cb[:3, 3]
    return cameras.project(pc, camera.lensmodel, camera.intrinsics) if np.all(pc[:, 2] > 0.05) else None


def render(camera: Sensor, T_world_camera: np.ndarray, scene, board: BoardGeometry, T_world_board: np.ndarray | None,
           rng, *, topic: str = "/camera", stamp_ns: int = 0, colour: bool = False, supersample: int = 4,
           noise_sigma: float = 2.0, blur_sigma_px: float = 0.0, gain: float = 1.0) -> tuple[Image, np.ndarray | None]:
    """(Image, truth corners (N,2) in px or None) of ``camera`` at ``T_world_camera``; ``gain``: the
    exposure's scale of every grey level (0.25: a dim image), before the blur and the noise."""
    w, h = camera.imagersize
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    q = np.stack([u, v], -1).reshape(-1, 2)
    grid = _pixel_directions(camera)
    d_cam = grid.reshape(-1, 3)
    R, t = T_world_camera[:3, :3], T_world_camera[:3, 3]
    d_world = d_cam @ R.T
    rays = np.concatenate([np.broadcast_to(t, d_world.shape), d_world], 1)
    t_hit, gid = scene.cast(rays)
    # background: a flat shade per object id, a faint texture from the hit position, sky light gray
    p = t + d_world * np.where(np.isfinite(t_hit), t_hit, 0.0)[:, None]
    shade = 90.0 + 25.0 * ((gid * 37) % 5) + 12.0 * np.sin(3.0 * p[:, 0]) * np.cos(3.0 * p[:, 1])
    img = np.where(np.isfinite(t_hit), shade, 200.0)
    corners = None
    if T_world_board is not None:
        on = gid == scene.board_id
        near = _dilate(on.reshape(h, w), 2).ravel()
        if near.any():
            img[near] = _supersampled_board(q[near], grid, T_world_camera, board, T_world_board, supersample,
                                            background=img[near], t_first=t_hit[near])
        corners = board_corners_px(camera, T_world_camera, board, T_world_board)
    img = img.reshape(h, w) * gain
    if blur_sigma_px > 0:
        import cv2

        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
    img = np.clip(img + rng.normal(0.0, noise_sigma, img.shape), 0, 255).astype(np.uint8)
    if colour:
        tint = np.array([0.95, 1.0, 1.05])  # a slightly bluish gray world, BGR
        img = np.clip(img[..., None] * tint, 0, 255).astype(np.uint8)
        return Image(topic, stamp_ns, img, "bgr8"), corners
    return Image(topic, stamp_ns, img, "mono8"), corners


def _dilate(mask: np.ndarray, n: int) -> np.ndarray:
    out = mask.copy()
    for _ in range(n):
        out[1:] |= out[:-1]
        out[:-1] |= out[1:]
        out[:, 1:] |= out[:, :-1]
        out[:, :-1] |= out[:, 1:]
    return out


_GRID_CACHE: dict = {}


def _pixel_directions(camera: Sensor) -> np.ndarray:
    """(h, w, 3) unit rays of the pixel centres, through mrcal (cached: it is the slow part)."""
    key = (camera.lensmodel, np.asarray(camera.intrinsics, float).tobytes(), tuple(camera.imagersize))
    if key not in _GRID_CACHE:
        w, h = camera.imagersize
        u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
        d = cameras.unproject(np.stack([u, v], -1).reshape(-1, 2), camera.lensmodel, camera.intrinsics)
        _GRID_CACHE.clear()  # one camera at a time is what the capture loop needs
        _GRID_CACHE[key] = d.reshape(h, w, 3)
    return _GRID_CACHE[key]


def _interpolate(grid: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Rays at subpixel positions q (M,2) by bilinear interpolation of the pixel-centre rays
    (the lens is smooth on a pixel's scale: the error is far below 0.01 px)."""
    h, w, _ = grid.shape
    x0 = np.clip(np.floor(q[:, 0]).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(q[:, 1]).astype(int), 0, h - 2)
    fx, fy = (q[:, 0] - x0)[:, None], (q[:, 1] - y0)[:, None]
    d = ((1 - fx) * (1 - fy) * grid[y0, x0] + fx * (1 - fy) * grid[y0, x0 + 1]
         + (1 - fx) * fy * grid[y0 + 1, x0] + fx * fy * grid[y0 + 1, x0 + 1])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _supersampled_board(q, grid, T_world_camera, board, T_world_board, n, *, background, t_first):
    """Mean gray over n x n subpixel rays of pixels q (M,2): board shade where a subray meets the
    board (and nothing is in front of it), else the pixel's background shade."""
    offs = (np.arange(n) + 0.5) / n - 0.5
    ou, ov = np.meshgrid(offs, offs)
    sub = (q[:, None, :] + np.stack([ou.ravel(), ov.ravel()], -1)[None]).reshape(-1, 2)
    d = _interpolate(grid, sub)
    T_bc = np.linalg.inv(T_world_board) @ T_world_camera  # camera -> board frame
    o_b = T_bc[:3, 3]
    d_b = d @ T_bc[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -o_b[2] / d_b[:, 2]
    xy = o_b[:2] + d_b[:, :2] * s[:, None]
    xmin, xmax, ymin, ymax = board.extent()
    hit = np.isfinite(s) & (s > 0) & (xy[:, 0] >= xmin) & (xy[:, 0] <= xmax) & (xy[:, 1] >= ymin) & (xy[:, 1] <= ymax)
    # occluded if the pixel's first hit is clearly nearer than the board (e.g. a pole in front)
    dist = s * np.linalg.norm(d, axis=1)
    occluded = np.repeat(t_first, n * n) < dist - 0.05
    val = np.where(hit & ~occluded, board_shade(board, xy), np.repeat(background, n * n))
    return val.reshape(-1, n * n).mean(axis=1)


def bayer_mosaic(image: Image, encoding: str) -> Image:
    """``image`` (BGR) as the raw mosaic of ``encoding`` (one of BAYER_ENCODINGS): each pixel the one
    channel its filter passes, at the sensor's raw (not white-balanced) response."""
    pattern = encoding.removeprefix("bayer_").removesuffix("8")
    bgr = np.asarray(image.pixels, float) * _RAW_GAINS_BGR
    raw = np.zeros(bgr.shape[:2])
    for k, (dy, dx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        raw[dy::2, dx::2] = bgr[dy::2, dx::2, "bgr".index(pattern[k])]
    return Image(image.topic, image.stamp_ns, np.clip(np.rint(raw), 0, 255).astype(np.uint8), encoding)
