"""Diagnostic PNG plots (matplotlib Figure objects drawn by the Agg canvas: no display needed, and
no pyplot state, so importing this module leaves a notebook's or an application's backend alone).

Residuals are read from ``Result.residuals`` (keys any solver may fill; missing ones
give a plot that says so):
    "lidar_m" (N,) LIDAR residuals in m, with "lidar_sensor", "lidar_snapshot" (N,) int;
    "camera_px" (M,) camera residuals in px (both coordinates), with "camera_sensor",
    "camera_snapshot" (M,) int; optional "lidar_outlier" (N,) / "camera_outlier" (M,) bool
    masks of residuals the solver rejected (drawn apart, left out of the RMS).

SYNOPSIS
    paths = plot_all(result, "out/")        # {name: png path}
    plot_uncertainty_grid(grid, xs, ys, "u.png", title="lidar0 -> lidar1")
"""

from __future__ import annotations

import logging
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure

from ..geometry import T_from_rt, transform
from ..types import Result

log = logging.getLogger(__name__)

_DPI = 100


def _figure(**kwargs) -> Figure:
    """A Figure with its own Agg canvas (pyplot's figure manager never sees it)."""
    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig


def subplots(*grid, figsize, layout=None, **kwargs):
    """pyplot.subplots without pyplot's global state: (figure, axes); save with ``fig.savefig``.
    ``kwargs`` go to ``Figure.subplots`` (sharex, squeeze, gridspec_kw, height_ratios, ...)."""
    fig = _figure(figsize=figsize, layout=layout)
    return fig, fig.subplots(*grid, **kwargs)


def _save(fig, path) -> Path:
    path = Path(path)
    fig.savefig(path, dpi=_DPI, bbox_inches="tight")
    return path


def _labels(result: Result) -> list[str]:
    return [f"{i}: {s.topic}" for i, s in enumerate(result.problem.sensors)]


def _colors(n):
    cmap = matplotlib.colormaps["tab10"]
    return [cmap(i % 10) for i in range(n)]


def plot_residual_histograms(result: Result, path) -> Path:
    """Histograms of LIDAR (m) and camera (px) residuals with the Gaussian of the re-estimated sigma."""
    fig, axes = subplots(1, 2, figsize=(11, 4))
    for ax, key, unit, noise_key in ((axes[0], "lidar_m", "m", "lidar_m"), (axes[1], "camera_px", "px", "camera_px")):
        x = np.asarray(result.residuals.get(key, []), dtype=float).ravel()
        out_mask = np.asarray(result.residuals.get(key.split("_")[0] + "_outlier", np.zeros(x.shape, bool)), bool).ravel()
        if out_mask.shape != x.shape:
            out_mask = np.zeros(x.shape, bool)
        xo = x[out_mask & np.isfinite(x)]
        x = x[~out_mask & np.isfinite(x)]
        kind = "LIDAR" if key == "lidar_m" else "camera"
        if x.size == 0:
            ax.text(0.5, 0.5, f"no {kind} residuals", ha="center", va="center", transform=ax.transAxes)
            ax.set_axis_off()
            continue
        sigma = result.noise.get(noise_key)
        sigma = float(sigma) if sigma and np.isfinite(sigma) and sigma > 0 else float(np.std(x))
        lim = max(4 * sigma, np.percentile(np.abs(x), 99.5))
        bins = np.linspace(-lim, lim, 61)
        ax.hist(np.clip(x, -lim, lim), bins=bins, density=True, color="C0", alpha=0.7, label=f"residuals (N={x.size})")
        if xo.size:
            # outliers on the same density scale as the inliers, clipped into the edge bins
            ax.hist(np.clip(xo, -lim, lim), bins=bins, weights=np.full(xo.size, 1.0 / (x.size * (bins[1] - bins[0]))),
                    color="r", alpha=0.6, label=f"outliers, rejected (N={xo.size})")
        g = np.linspace(-lim, lim, 400)
        # each sensor has its own sigma: the expected density is their mixture, by residual count
        sens = np.asarray(result.residuals.get(key.split("_")[0] + "_sensor", []), int).ravel()
        per = result.noise.get("per_sensor") or {}
        if sens.shape == out_mask.shape and per:
            sens = sens[~out_mask & np.isfinite(np.asarray(result.residuals.get(key), float).ravel())]
            ids, counts = np.unique(sens, return_counts=True)
            sig = np.array([per.get(int(i), sigma) for i in ids])
            w = counts / counts.sum()
        else:
            sig, w = np.array([sigma]), np.array([1.0])
        dens = sum(wi * np.exp(-0.5 * (g / si) ** 2) / (si * np.sqrt(2 * np.pi)) for wi, si in zip(w, sig))
        what = (f"Gaussian, sigma={sigma:.3g} {unit}" if len(sig) == 1 else
                "Gaussians of the sensors' sigmas (" + ", ".join(f"{x:.3g}" for x in sig) + f" {unit})")
        ax.plot(g, dens, "r-", label=what)
        ax.set_xlabel(f"{kind} residual ({unit})")
        ax.set_ylabel("density")
        ax.set_title(f"{kind} residuals: RMS {np.sqrt(np.mean(x**2)):.3g} {unit}")
        ax.legend(fontsize=8)
    return _save(fig, path)


def per_observation_rms(result: Result) -> list[dict]:
    """[{kind, sensor, snapshot, rms, n_outliers}] from the residual arrays (unit: m or px; RMS over inliers)."""
    out = []
    for kind, key in (("lidar", "lidar_m"), ("camera", "camera_px")):
        x = np.asarray(result.residuals.get(key, []), dtype=float).ravel()
        isens = np.asarray(result.residuals.get(f"{kind}_sensor", []), dtype=int).ravel()
        isnap = np.asarray(result.residuals.get(f"{kind}_snapshot", []), dtype=int).ravel()
        if x.size == 0 or isens.shape != x.shape or isnap.shape != x.shape:
            continue
        bad = np.asarray(result.residuals.get(f"{kind}_outlier", np.zeros(x.shape, bool)), bool).ravel()
        if bad.shape != x.shape:
            bad = np.zeros(x.shape, bool)
        pair = isens.astype(np.int64) * (1 << 32) + isnap
        u, inv = np.unique(pair, return_inverse=True)
        good = ~bad & np.isfinite(x)
        ss = np.bincount(inv, weights=np.where(good, x * x, 0.0), minlength=len(u))
        n = np.bincount(inv, weights=good.astype(float), minlength=len(u))
        nbad = np.bincount(inv, weights=bad.astype(float), minlength=len(u))
        with np.errstate(invalid="ignore", divide="ignore"):
            rms = np.sqrt(ss / n)
        for k, p in enumerate(u):
            out.append({"kind": kind, "sensor": int(p >> 32), "snapshot": int(p & 0xFFFFFFFF),
                        "rms": float(rms[k]), "n_outliers": int(nbad[k])})
    return out


def plot_residuals_per_snapshot(result: Result, path) -> Path:
    """RMS residual per (snapshot, sensor); rejected observations marked with x on the axis."""
    obs = per_observation_rms(result)
    n = len(result.problem.sensors)
    colors = _colors(n)
    labels = _labels(result)
    fig, axes = subplots(2, 1, figsize=(11, 6), sharex=True)
    for ax, kind, unit, nk in ((axes[0], "lidar", "m", "lidar_m"), (axes[1], "camera", "px", "camera_px")):
        plotted = set()
        for o in obs:
            if o["kind"] != kind:
                continue
            i = o["sensor"]
            ax.plot(o["snapshot"], o["rms"], "o", color=colors[i], ms=5, label=None if i in plotted else labels[i])
            if o["n_outliers"]:
                ax.plot(o["snapshot"], o["rms"], "o", mfc="none", mec="r", ms=10, mew=1.5)
            plotted.add(i)
        per = result.noise.get("per_sensor") or {}
        for i in sorted(plotted):
            if i in per:  # each sensor's re-estimated noise, in its colour
                ax.axhline(per[i], color=colors[i], ls="--", lw=0.8, label=f"noise sigma {per[i]:.3g} {unit}")
        sigma = result.noise.get(nk)
        if not per and sigma and np.isfinite(sigma):
            ax.axhline(sigma, color="k", ls="--", lw=0.8, label=f"noise sigma {sigma:.3g} {unit}")
        # rejected observations of this kind's sensors, at the bottom of the axis
        for r in result.rejected:
            if r.snapshot is None:
                continue
            if r.sensor is not None and result.problem.sensors[r.sensor].kind != kind:
                continue
            c = "k" if r.sensor is None else colors[r.sensor]
            ax.plot(r.snapshot, 0, "x", color=c, ms=8, mew=2, clip_on=False)
        ax.plot([], [], "kx", ms=8, mew=2, label="rejected (see report table)")
        ax.plot([], [], "o", mfc="none", mec="r", ms=10, mew=1.5, label="has outlier residuals")
        ax.set_ylabel(f"{kind} RMS ({unit})")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        if not plotted:
            ax.text(0.5, 0.5, f"no {kind} residuals", ha="center", va="center", transform=ax.transAxes)
    ks = range(result.problem.n_snapshots)
    if result.problem.snapshot_bags and result.problem.n_snapshots <= 60:  # the bags by name, while they fit
        axes[1].set_xticks(list(ks), [f"{k} {result.problem.snapshot_bag(k)}" for k in ks], rotation=90, fontsize=6)
    axes[1].set_xlabel("snapshot (index, bag)")
    axes[0].set_title("residual RMS per snapshot and sensor")
    return _save(fig, path)


def _board_outline(board) -> np.ndarray:
    xmin, xmax, ymin, ymax = board.extent()
    return np.array([[xmin, ymin, 0], [xmax, ymin, 0], [xmax, ymax, 0], [xmin, ymax, 0], [xmin, ymin, 0]], float)


def _set_equal_3d(ax, pts):
    pts = np.asarray(pts).reshape(-1, 3)
    c = 0.5 * (pts.min(0) + pts.max(0))
    r = 0.5 * np.max(pts.max(0) - pts.min(0)) + 0.2
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)


def plot_geometry(result: Result, path, *, with_boards: bool = True, axis_len_m: float = 0.3) -> Path:
    """3D view in lidar0: sensor axes triads (x red, y green, z blue) with labels, boards as outlines."""
    fig = _figure(figsize=(9, 8))
    ax = fig.add_subplot(111, projection="3d")
    pts = []
    colors = _colors(len(result.problem.sensors))
    for i, s in enumerate(result.problem.sensors):
        T = T_from_rt(result.rt_lidar0_sensor[i])
        o = T[:3, 3]
        for k, c in enumerate("rgb"):
            e = o + axis_len_m * T[:3, k]
            ax.plot(*np.c_[o, e], color=c, lw=2)
        ax.text(*o, f" {i}: {s.topic}", color=colors[i], fontsize=8)
        pts.append(o)
    if with_boards:
        outline = _board_outline(result.problem.board)
        rtb = np.asarray(result.rt_lidar0_board, float).reshape(-1, 6)
        first = True
        for k, rt in enumerate(rtb):
            if not np.all(np.isfinite(rt)):
                continue
            p = transform(rt, outline)
            ax.plot(p[:, 0], p[:, 1], p[:, 2], color="0.4", lw=1, label="boards" if first else None)
            first = False
            pts.append(p)
    _set_equal_3d(ax, np.vstack([np.reshape(p, (-1, 3)) for p in pts]))
    ax.set_xlabel("x (m, lidar0)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.plot([], [], "r-", label="x axis")
    ax.plot([], [], "g-", label="y axis")
    ax.plot([], [], "b-", label="z axis")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title("solved geometry in the lidar0 frame\n(LIDAR axes front-left-up; camera axes right-down-forward)")
    return _save(fig, path)


def plot_sectors(result: Result, path) -> Path:
    """Polar map around the vehicle: worst-pair stdev and observations per sector; last snapshot's sector marked."""
    s = result.sectors
    fig = _figure(figsize=(12, 5.5))
    if s is None:
        ax = fig.add_subplot(111)
        ax.text(0.5, 0.5, "no sector feedback in this result", ha="center", va="center")
        ax.set_axis_off()
        return _save(fig, path)
    n = int(s.n_sectors)
    width = 2 * np.pi / n
    theta = (np.arange(n) + 0.5) * width
    std_mm = np.asarray(s.stdev_worst_per_sector, float) * 1e3
    nobs = np.asarray(s.observations_per_sector, float)
    for k, (vals, title, cmap, unit) in enumerate(
        ((std_mm, "worst-pair position stdev per sector", "viridis", "mm"),
         (nobs, "board observations per sector", "Blues", "count"))
    ):
        ax = fig.add_subplot(1, 2, k + 1, projection="polar")
        finite = np.isfinite(vals)
        vmax = np.nanmax(vals[finite]) if finite.any() else 1.0
        vmax = vmax if vmax > 0 else 1.0
        norm = Normalize(0, vmax)
        cm = matplotlib.colormaps[cmap]
        colors = [cm(norm(v)) if np.isfinite(v) else (0.8, 0.2, 0.2, 1) for v in vals]
        heights = np.where(finite, vals, vmax)
        ax.bar(theta, heights, width=width, color=colors, edgecolor="k", lw=0.3)
        last = int(s.isector_of_last_snapshot)
        if 0 <= last < n:
            ax.bar(theta[last], vmax * 1.05, width=width, fill=False, edgecolor="r", lw=2.5, label="last snapshot's sector")
            ax.legend(fontsize=8, loc="lower left", bbox_to_anchor=(-0.15, -0.15))
        ax.set_theta_zero_location("N")  # vehicle forward (+x) up, counter-clockwise = toward +y (left)
        ax.set_rlabel_position(112.5)
        ax.set_title(f"{title} ({unit})\nforward = up, left = left", fontsize=10)
        sm = ScalarMappable(norm=norm, cmap=cm)
        fig.colorbar(sm, ax=ax, shrink=0.7, pad=0.1, label=unit)
    return _save(fig, path)


def plot_coverage(result: Result, path) -> Path:
    """Per sensor: board centres in the sensor frame (top view); cameras: detected corners in the image."""
    problem = result.problem
    n = len(problem.sensors)
    fig, axes = subplots(1, n, figsize=(4.2 * n, 4.2), squeeze=False)
    centre_b = np.mean(_board_outline(problem.board)[:4], axis=0)
    rtb = np.asarray(result.rt_lidar0_board, float).reshape(-1, 6)
    for i, (ax, s) in enumerate(zip(axes[0], problem.sensors)):
        if s.is_camera and s.imagersize is not None:
            obs = [o for o in problem.camera_observations if o.sensor == i]
            for o in obs:
                q = np.asarray(o.corners_px, float)
                ax.plot(q[:, 0], q[:, 1], ".", ms=1.5)
            w, h = s.imagersize
            ax.set_xlim(0, w)
            ax.set_ylim(h, 0)
            ax.set_aspect("equal")
            ax.set_xlabel("x (px)")
            ax.set_ylabel("y (px)")
            ax.set_title(f"{i}: {s.topic}\ncorners in the image ({len(obs)} boards)", fontsize=9)
            continue
        # board centres in this sensor's frame: lidar0 -> sensor
        T_s_l0 = np.linalg.inv(T_from_rt(result.rt_lidar0_sensor[i]))
        seen = {o.snapshot for o in problem.lidar_observations if o.sensor == i}
        cs, used = [], []
        for k, rt in enumerate(rtb):
            if np.all(np.isfinite(rt)):
                c = T_s_l0[:3, :3] @ transform(rt, centre_b[None])[0] + T_s_l0[:3, 3]
                cs.append(c)
                used.append(k in seen)
        cs = np.array(cs).reshape(-1, 3)
        used = np.array(used, bool)
        ax.plot(cs[used, 0], cs[used, 1], "o", color="C0", ms=5, label="seen by this sensor")
        ax.plot(cs[~used, 0], cs[~used, 1], "o", mfc="none", color="0.6", ms=5, label="not seen")
        ax.plot(0, 0, "r^", ms=9, label="sensor")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
        ax.set_xlabel("x forward (m)")
        ax.set_ylabel("y left (m)")
        ax.set_title(f"{i}: {s.topic}\nboard centres, top view ({int(used.sum())} seen)", fontsize=9)
        ax.legend(fontsize=7)
    return _save(fig, path)


def plot_uncertainty_grid(stdev_m: np.ndarray, xs: np.ndarray, ys: np.ndarray, path, *,
                          title: str = "", sensor_xy: dict | None = None, cbmax_m: float | None = None) -> Path:
    """Heat map of a point-transform stdev (gridn_y, gridn_x) in m over the ground grid xs (gridn_x,), ys (gridn_y,).

    ``sensor_xy``: label -> (x, y) sensor positions to mark.
    """
    stdev_mm = np.asarray(stdev_m, float) * 1e3
    fig, ax = subplots(figsize=(7, 6))
    vmax = None if cbmax_m is None else cbmax_m * 1e3
    im = ax.pcolormesh(xs, ys, stdev_mm, shading="nearest", cmap="viridis", vmin=0, vmax=vmax)
    cs = ax.contour(xs, ys, stdev_mm, colors="w", linewidths=0.6, levels=6)
    ax.clabel(cs, fontsize=7, fmt="%.0f")
    for label, (x, y) in (sensor_xy or {}).items():
        ax.plot(x, y, "r^", ms=8)
        ax.annotate(label, (x, y), color="r", fontsize=8, xytext=(4, 4), textcoords="offset points")
    fig.colorbar(im, ax=ax, label="worst-direction stdev (mm)")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or "point-transform uncertainty", fontsize=10)
    return _save(fig, path)


_VIEWS = {"top": (0, 1, "x (m)", "y (m)"), "side": (0, 2, "x (m)", "z (m)"), "front": (1, 2, "y (m)", "z (m)")}


def align_clouds(clouds: dict, rt_lidar0_sensor: dict, *, max_points: int | None = None, seed: int = 0) -> dict:
    """topic -> (N,3) own-frame cloud  ==>  topic -> (M,3) in lidar0 (non-finite rows dropped, subsampled)."""
    rng = np.random.default_rng(seed)
    moved = {}
    for topic, p in clouds.items():
        if topic not in rt_lidar0_sensor:
            raise KeyError(f"no rt_lidar0_sensor for {topic}")
        p = np.asarray(p, float).reshape(-1, 3)
        p = p[np.all(np.isfinite(p), axis=1)]
        if max_points is not None and len(p) > max_points:
            p = p[rng.choice(len(p), max_points, replace=False)]
        moved[topic] = transform(np.asarray(rt_lidar0_sensor[topic], float), p)
    return moved


def render_aligned_clouds(clouds: dict, rt_lidar0_sensor: dict, path_png, *, views=("top", "side"),
                          max_points: int = 60000, point_size: float = 0.5, seed: int = 0) -> Path:
    """LIDAR clouds (topic -> (N,3) in their own frame) moved into lidar0 and drawn, one colour per sensor.

    ``rt_lidar0_sensor``: topic -> (6,). Each cloud is subsampled to ``max_points``.
    """
    for v in views:
        if v not in _VIEWS:
            raise ValueError(f"unknown view {v!r}; one of {sorted(_VIEWS)}")
    moved = align_clouds(clouds, rt_lidar0_sensor, max_points=max_points, seed=seed)
    fig, axes = subplots(1, len(views), figsize=(7 * len(views), 6.5), squeeze=False)
    colors = _colors(len(clouds))
    for ax, v in zip(axes[0], views):
        a, b, la, lb = _VIEWS[v]
        for (topic, p), c in zip(moved.items(), colors):
            ax.scatter(p[:, a], p[:, b], s=point_size, color=c, label=topic, linewidths=0, rasterized=True)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(la)
        ax.set_ylabel(lb)
        ax.grid(alpha=0.3)
        ax.set_title(f"{v} view, lidar0 frame")
        ax.legend(markerscale=12, fontsize=8, loc="upper right")
    return _save(fig, path_png)


PLOTS = {
    "residuals-histogram.png": plot_residual_histograms,
    "residuals-per-snapshot.png": plot_residuals_per_snapshot,
    "geometry.png": plot_geometry,
    "sectors.png": plot_sectors,
    "coverage.png": plot_coverage,
}


def plot_all(result: Result, out_dir) -> dict[str, Path]:
    """Every report plot into out_dir; returns {file name: path}. A failing plot is logged, not raised."""
    out = {}
    for name, fn in PLOTS.items():
        try:
            out[name] = fn(result, Path(out_dir) / name)
        except Exception:  # a diagnostic plot must never lose the calibration
            log.exception("could not draw %s", name)
    return out


def plot_scan_preview(scan, path, *, title: str = "") -> Path:
    """One LIDAR scan: top view coloured by height, and a ring x azimuth range image."""
    pts = np.asarray(scan.points, float)[np.asarray(scan.valid, bool)]
    fig, (a, b) = subplots(1, 2, figsize=(13, 5), gridspec_kw={"width_ratios": [1, 1.6]})
    if len(pts):
        s = a.scatter(pts[:, 0], pts[:, 1], c=pts[:, 2], s=0.3, cmap="viridis")
        fig.colorbar(s, ax=a, label="z [m]")
    a.set_aspect("equal")
    a.set_xlabel("x [m]")
    a.set_ylabel("y [m]")
    a.set_title("top view")
    if len(pts):
        rng = np.linalg.norm(pts, axis=1)
        az = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
        ring = (np.asarray(scan.ring)[np.asarray(scan.valid, bool)] if scan.ring is not None
                else np.degrees(np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1]))))
        s = b.scatter(az, ring, c=rng, s=0.5, cmap="turbo", vmax=np.percentile(rng, 98))
        fig.colorbar(s, ax=b, label="range [m]")
    b.set_xlabel("azimuth [deg]")
    b.set_ylabel("ring" if scan.ring is not None else "elevation [deg]")
    b.set_title("range image")
    fig.suptitle(title or f"{scan.topic}: {len(pts)} valid points")
    return _save(fig, path)


def plot_image_preview(image, path, *, title: str = "") -> Path:
    """One camera image as it was decoded (mono shown in gray, colour as RGB)."""
    px = np.asarray(image.pixels)
    h, w = px.shape[:2]
    fig, ax = subplots(figsize=(8, 8 * h / max(w, 1) + 0.5))
    if px.ndim == 3:
        ax.imshow(px[..., ::-1])  # BGR -> RGB
    else:
        ax.imshow(px, cmap="gray")
    ax.set_axis_off()
    ax.set_title(title or f"{image.topic}: {w}x{h} {image.encoding}")
    return _save(fig, path)


def plot_segmentation(scan, debug, result, path) -> Path:
    """A scan's board segmentation: top view with the straight segments, candidate planes and
    the accepted board, and a zoom on the board (or the best candidate) from the sensor."""
    pts = np.asarray(scan.points, float)
    ok = np.asarray(scan.valid, bool)
    fig, (a, b) = subplots(1, 2, figsize=(14, 6))
    a.scatter(pts[ok, 0], pts[ok, 1], s=0.2, c="0.75")
    if debug.segments is not None and len(debug.segments):
        s = debug.segments
        a.plot(s[:, :, 0].T, s[:, :, 1].T, "-", color="tab:blue", lw=0.6)
    focus = None
    for idx, verdict in debug.candidates:
        accepted = verdict == "accepted"
        a.scatter(pts[idx, 0], pts[idx, 1], s=2, c="tab:green" if accepted else "tab:red")
        if focus is None or accepted:
            focus = idx
    if getattr(result, "indices", None) is not None:
        focus = result.indices
        a.scatter(pts[focus, 0], pts[focus, 1], s=3, c="tab:green", label="board")
    a.set_aspect("equal")
    a.set_xlabel("x [m]")
    a.set_ylabel("y [m]")
    a.set_title("segments (blue), rejected planes (red), board (green)")
    if focus is not None and len(focus):
        c = pts[focus].mean(axis=0)
        near = ok & (np.linalg.norm(pts - c, axis=1) < 2.0)
        az = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
        el = np.degrees(np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1])))
        b.scatter(az[near], el[near], s=4, c="0.6")
        b.scatter(az[focus], el[focus], s=6, c="tab:green" if getattr(result, "indices", None) is not None else "tab:red")
        b.invert_xaxis()
        b.set_xlabel("azimuth [deg]")
        b.set_ylabel("elevation [deg]")
        b.set_title("around the board, from the sensor")
    reason = getattr(result, "reason", None)
    fig.suptitle(reason if reason else f"board: {len(result.indices)} points, RMS {result.rms_m * 1e3:.1f} mm",
                 fontsize=9)
    return _save(fig, path)
