"""Rotating LIDARs by ray casting: per-ring elevation, per-column azimuth, range noise, dropout.

SYNOPSIS
    model = LidarModel.preset("vlp16")
    scan, hit_board = simulate_scan(model, T_world_lidar, scene, rng, stamp_ns=t, topic="/lidar")

Layouts as the drivers write them: "velodyne" = unorganised, only returns, column by column
(all rings of one firing, then the next); "ouster" = organised (rings x columns, row-major),
no-returns as (0,0,0) invalid. Per-point time: the column's time in the 0.1 s rotation.
The scan is from a stationary sensor (target calibration): no motion smear.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..types import LidarScan

# Elevation tables (degrees, ring 0 lowest).
_VLP16 = np.linspace(-15.0, 15.0, 16)
_HDL32 = np.linspace(-30.67, 10.67, 32)
_OS1 = np.linspace(-22.5, 22.5, 64)
_OS1_128 = np.linspace(-22.5, 22.5, 128)
# Real units' beams are not evenly spaced: dense about the horizon, sparse at the ends (the
# manuals' tables). VLP-32C: 0.33 deg apart from -4.7 to +1.7 deg, 9.7 deg apart at the bottom.
_VLP32C = (-25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667, -3.333, -3.0, -2.667,
           -2.333, -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0, 0.333, 0.667, 1.0, 1.333, 1.667, 2.333,
           3.333, 4.667, 7.0, 10.333, 15.0)
# Hesai Pandar40P: 0.33 deg apart from -6 to +1.7 deg, 1 deg below to -14, then -19 and -25
_PANDAR40P = tuple(sorted((15.0, 11.0, 8.0, 5.0, 3.0, 2.0, *(np.arange(5, -19, -1) / 3).round(3).tolist(),
                           -7.0, -8.0, -9.0, -10.0, -11.0, -12.0, -13.0, -14.0, -19.0, -25.0)))


@dataclass(frozen=True)
class LidarModel:
    name: str
    elevations_deg: tuple
    npoints_per_rotation: int
    range_noise_m: float = 0.01
    dropout: float = 0.005
    max_range_m: float = 100.0
    min_range_m: float = 0.3
    layout: str = "velodyne"
    rotation_period_s: float = 0.1
    # Errors real LIDARs make the same way in every scan (sim/observations.CorrelatedErrors):
    # sd of each ring's range bias and of its elevation error, drawn once from errors_seed.
    ring_range_bias_m: float = 0.0
    ring_elevation_error_deg: float = 0.0
    errors_seed: int = 0
    # Errors that vary per return (the factors assume none of them; 0 = off):
    # this share of returns has range noise heavy_tail_scale times range_noise_m (a heavy tail),
    heavy_tail_fraction: float = 0.0
    heavy_tail_scale: float = 10.0
    # returns from the board's dark squares are this much long (low reflectivity: their
    # intensity is then low too, 20 against the board's 180),
    dark_range_bias_m: float = 0.0
    # this share of the returns from the board's dark squares never comes back (a black print
    # that absorbs the laser, or a laminated one that mirrors it away at an angle),
    dark_dropout: float = 0.0
    # a ring's board return next to a miss of the board is up to this much long (part of the
    # beam's footprint hit the background: a mixed pixel).
    mixed_pixel_m: float = 0.0
    # dual-return mode: a second return of every ray, with one surface on the ray the same echo
    # again (strongest = last); velodyne layout: after each firing's returns (as Hesai drivers
    # publish it); ouster layout: organised, each column followed by its second returns' column
    dual_returns: bool = False
    # the way the head spins, seen from above (+z): clockwise (Velodyne, Hesai) or not; either
    # way the columns come in firing order, so the azimuth falls or rises along each ring
    clockwise: bool = True

    def ring_errors(self) -> tuple[np.ndarray, np.ndarray]:
        """(range bias (rings,) m, elevation error (rings,) deg): this unit's fixed errors."""
        rng = np.random.default_rng(self.errors_seed)
        bias, elev = rng.normal(0, 1, self.n_rings), rng.normal(0, 1, self.n_rings)
        return self.ring_range_bias_m * bias, self.ring_elevation_error_deg * elev

    @staticmethod
    def preset(name: str, **overrides) -> "LidarModel":
        """"vlp16" (16 x 1800), "hdl32"/"32ring" (32 x 1800), "os1-64" (64 x 2048), "os1-128" (128 x 2048),
        "vlp32c" (32 x 1800) and "pandar40p" (40 x 1800, Hesai's layout): the last two with their
        real, unevenly spaced beams."""
        table = {
            "vlp16": LidarModel("vlp16", tuple(_VLP16), 1800, 0.01),
            "hdl32": LidarModel("hdl32", tuple(_HDL32), 1800, 0.015),
            "32ring": LidarModel("32ring", tuple(_HDL32), 1800, 0.015),
            "os1-64": LidarModel("os1-64", tuple(_OS1), 2048, 0.01, layout="ouster"),
            "os1-128": LidarModel("os1-128", tuple(_OS1_128), 2048, 0.01, layout="ouster"),
            "vlp32c": LidarModel("vlp32c", _VLP32C, 1800, 0.015),
            "pandar40p": LidarModel("pandar40p", _PANDAR40P, 1800, 0.01, layout="hesai"),
        }
        if name not in table:
            raise KeyError(f"unknown LIDAR model {name!r}; known: {', '.join(table)}")
        return replace(table[name], **overrides)

    @property
    def n_rings(self) -> int:
        return len(self.elevations_deg)

    def directions(self, true: bool = False) -> np.ndarray:
        """(rings, columns, 3) unit ray directions in the LIDAR frame (front-left-up): as the
        driver reports them, or (``true``) as the beams really leave (ring elevation errors)."""
        el = np.asarray(self.elevations_deg, float) + (self.ring_errors()[1] if true else 0.0)
        el = np.radians(el)[:, None]
        turned = 2 * np.pi * np.arange(self.npoints_per_rotation) / self.npoints_per_rotation
        az = np.pi - turned if self.clockwise else turned - np.pi
        az = az[None, :]
        return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az)], -1)


def simulate_scan(model: LidarModel, T_world_lidar: np.ndarray, scene, rng, *, stamp_ns: int = 0,
                  topic: str = "/lidar") -> tuple[LidarScan, np.ndarray]:
    """One rotation of ``model`` at ``T_world_lidar`` in ``scene`` -> (LidarScan, hit_board mask).

    ``T_world_lidar``: (4,4) for a still sensor, or (columns,4,4), the pose at each column's
    firing time, for a moving one (the scan is then motion-distorted like a real driver's).
    """
    d = model.directions()
    d_true = model.directions(true=True) if model.ring_elevation_error_deg else d
    T = np.asarray(T_world_lidar, float)
    if T.ndim == 2:
        dw = d_true.reshape(-1, 3) @ T[:3, :3].T
        ow = np.broadcast_to(T[:3, 3], dw.shape)
    else:
        dw = np.einsum("cij,rcj->rci", T[:, :3, :3], d_true).reshape(-1, 3)
        ow = np.broadcast_to(T[None, :, :3, 3], d.shape).reshape(-1, 3)
    rays = np.concatenate([ow, dw], axis=1)
    r, gid = scene.cast(rays)
    valid = np.isfinite(r) & (r > model.min_range_m) & (r < model.max_range_m)
    valid &= rng.uniform(size=r.shape) >= model.dropout
    rings, cols = model.n_rings, model.npoints_per_rotation
    ring = np.repeat(np.arange(rings), cols)
    bias = model.ring_errors()[0][ring] if model.ring_range_bias_m else 0.0
    on_board = gid == getattr(scene, "board_id", -2)
    extra, dark = _per_return_errors(model, scene, rays, r, on_board, rng)
    if model.dark_dropout:
        valid &= ~(dark & (rng.uniform(size=r.shape) < model.dark_dropout))
    r = np.where(valid, r + bias + extra + rng.normal(0.0, model.range_noise_m, r.shape), 0.0)
    pts = d.reshape(-1, 3) * r[:, None]
    time_s = np.tile(np.arange(cols) / cols * model.rotation_period_s, rings)
    # the board bright; with dark_range_bias_m its dark squares also return weak (what makes them long)
    intensity = np.where(on_board, np.where(dark, 20.0, 180.0), 60.0).astype(np.float32)
    hit_board = valid & on_board
    if model.layout == "ouster":
        if model.dual_returns:  # kept organised: each column followed by its second returns' column
            pts, valid, intensity, ring, time_s, hit_board = (
                np.repeat(x.reshape(rings, cols, *x.shape[1:]), 2, axis=1).reshape(rings * 2 * cols, *x.shape[1:])
                for x in (pts, valid, intensity, ring, time_s, hit_board))
            return LidarScan(topic, stamp_ns, pts, valid, intensity, ring, time_s, (rings, 2 * cols)), hit_board
        return LidarScan(topic, stamp_ns, pts, valid, intensity, ring, time_s, (rings, cols)), hit_board
    if model.layout == "hesai":  # Hesai numbers its channels from the top beam down
        ring = rings - 1 - ring
    order = np.arange(rings * cols).reshape(rings, cols).T.ravel()  # firing order: column by column
    if model.dual_returns:  # each column's second returns right after its first ones
        pts = np.concatenate([pts, pts])
        order = np.stack([order.reshape(cols, rings), order.reshape(cols, rings) + rings * cols], axis=1).ravel()
        valid, intensity, ring, time_s, hit_board = (np.r_[x, x] for x in (valid, intensity, ring, time_s, hit_board))
    order = order[valid[order]]
    scan = LidarScan(topic, stamp_ns, pts[order], np.ones(len(order), bool), intensity[order], ring[order],
                     time_s[order], None)
    return scan, hit_board[order]


def _per_return_errors(model: LidarModel, scene, rays: np.ndarray, r: np.ndarray, on_board: np.ndarray,
                       rng) -> tuple[np.ndarray | float, np.ndarray | bool]:
    """((rings*columns,) range errors of ``model``'s per-return options (0.0 when all are off):
    heavy-tailed noise, dark squares returning long, mixed pixels at the board's edge; the mask
    of returns from the board's dark squares (False unless dark_range_bias_m or dark_dropout))."""
    dark = np.zeros(r.shape, bool)
    if not (model.heavy_tail_fraction or model.dark_range_bias_m or model.dark_dropout or model.mixed_pixel_m):
        return 0.0, dark
    e = np.zeros(r.shape)
    if model.heavy_tail_fraction:
        wild = rng.uniform(size=r.shape) < model.heavy_tail_fraction
        e[wild] += rng.normal(0.0, model.heavy_tail_scale * model.range_noise_m, int(wild.sum()))
    if (model.dark_range_bias_m or model.dark_dropout) and on_board.any() and \
            getattr(scene, "T_world_board", None) is not None:
        from .camera import BLACK, board_shade

        p_world = rays[on_board, :3] + rays[on_board, 3:] * r[on_board, None]
        T = scene.T_world_board
        xy = ((p_world - T[:3, 3]) @ T[:3, :3])[:, :2]
        dark[on_board] = board_shade(scene.board, xy) == BLACK
        e[dark] += model.dark_range_bias_m
    if model.mixed_pixel_m:
        grid = on_board.reshape(model.n_rings, model.npoints_per_rotation)
        edge = (grid & ~(np.roll(grid, 1, axis=1) & np.roll(grid, -1, axis=1))).ravel()
        e[edge] += rng.uniform(0.0, model.mixed_pixel_m, int(edge.sum()))
    return e, dark
