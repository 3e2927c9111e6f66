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

from ..geometry import T_from_rt, azimuth, elevation, transform
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


def margins(fig, *, left: float = 0.8, right: float = 0.2, bottom: float = 0.6, top: float = 0.45,
            wspace: float = 0.7, hspace: float = 0.7) -> None:
    """Lay the axes out with fixed margins and gaps, in inches (labels have a fixed size in points, so a
    margin in inches fits every figure size). One draw per figure: a tight bounding box
    (``bbox_inches="tight"``) or the constrained layout engine measures every text first, which
    costs as much as drawing the figure again."""
    w, h = fig.get_size_inches()
    ss = next((a.get_subplotspec() for a in fig.axes if a.get_subplotspec() is not None), None)
    nrows, ncols = ss.get_topmost_subplotspec().get_gridspec().get_geometry() if ss is not None else (1, 1)
    aw = (w - left - right - wspace * (ncols - 1)) / ncols  # one axes' width and height
    ah = (h - bottom - top - hspace * (nrows - 1)) / nrows
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h,
                        wspace=wspace / max(aw, 1e-3), hspace=hspace / max(ah, 1e-3))


def _save(fig, path, *, dpi: int = _DPI):
    """Save as PNG to a path (returned as a Path) or to a binary file object (returned as is), in one
    draw (the figure is laid out already: ``margins`` or ``layout="constrained"``)."""
    if not hasattr(path, "write"):
        path = Path(path)
    # zlib level 1: a plot's flat colours compress nearly as well, and level 6 (PIL's default) costs 3x
    fig.savefig(path, dpi=dpi, format="png", pil_kwargs={"compress_level": 1})
    return path


def _title(ax, text, **kwargs):
    """``ax.set_title`` at the height matplotlib would choose for axes whose ticks are below them
    (polar axes pass their own ``y``): told nothing, it measures every tick label of the axes once
    more to place the title, a fifth of the figure's drawing."""
    return ax.set_title(text, **{"y": 1.0, **kwargs})


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
        # one stepfilled patch per histogram, not a patch per bar (drawing 60 bars costs more than the data)
        ax.hist(np.clip(x, -lim, lim), bins=bins, density=True, color="C0", alpha=0.7, histtype="stepfilled",
                label=f"residuals (N={x.size})")
        if xo.size:
            # outliers on the same density scale as the inliers, clipped into the edge bins
            ax.hist(np.clip(xo, -lim, lim), bins=bins, weights=np.full(xo.size, 1.0 / (x.size * (bins[1] - bins[0]))),
                    color="r", alpha=0.6, histtype="stepfilled", label=f"outliers, rejected (N={xo.size})")
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
        _title(ax, f"{kind} residuals: RMS {np.sqrt(np.mean(x**2)):.3g} {unit}")
        ax.legend(fontsize=8)
    margins(fig, left=0.75, bottom=0.55, top=0.4, wspace=0.85)
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
        mine = [o for o in obs if o["kind"] == kind]
        plotted = sorted({o["sensor"] for o in mine})
        for i in plotted:  # one line artist per sensor (an artist per dot is slow to draw)
            k = np.array([o["snapshot"] for o in mine if o["sensor"] == i])
            v = np.array([o["rms"] for o in mine if o["sensor"] == i])
            ax.plot(k, v, "o", color=colors[i], ms=5, label=labels[i])
        bad = [(o["snapshot"], o["rms"]) for o in mine if o["n_outliers"]]
        if bad:
            ax.plot(*np.array(bad).T, "o", mfc="none", mec="r", ms=10, mew=1.5)
        per = result.noise.get("per_sensor") or {}
        for i in sorted(plotted):
            if i in per:  # each sensor's re-estimated noise, in its colour
                ax.axhline(per[i], color=colors[i], ls="--", lw=0.8, label=f"noise sigma {per[i]:.3g} {unit}")
        sigma = result.noise.get(nk)
        if not per and sigma and np.isfinite(sigma):
            ax.axhline(sigma, color="k", ls="--", lw=0.8, label=f"noise sigma {sigma:.3g} {unit}")
        # rejected observations of this kind's sensors, at the bottom of the axis
        rej = [r for r in result.rejected if r.snapshot is not None
               and (r.sensor is None or result.problem.sensors[r.sensor].kind == kind)]
        for c in {r.sensor for r in rej}:
            k = [r.snapshot for r in rej if r.sensor == c]
            ax.plot(k, np.zeros(len(k)), "x", color="k" if c is None else colors[c], ms=8, mew=2, clip_on=False, ls="none")
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
    _title(axes[0], "residual RMS per snapshot and sensor")
    named = result.problem.snapshot_bags and result.problem.n_snapshots <= 60
    margins(fig, left=0.95, right=2.9, bottom=1.25 if named else 0.55, top=0.35, hspace=0.2)
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
    _title(ax, "solved geometry in the lidar0 frame\n(LIDAR axes front-left-up; camera axes right-down-forward)")
    margins(fig, left=0.1, right=0.1, bottom=0.1, top=0.2)
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
        _title(ax, f"{title} ({unit})\nforward = up, left = left", fontsize=10, y=1.08)  # above the 0° label
        sm = ScalarMappable(norm=norm, cmap=cm)
        fig.colorbar(sm, ax=ax, shrink=0.7, pad=0.1, label=unit)
    margins(fig, left=0.6, right=0.3, bottom=0.75, top=0.75, wspace=1.2)
    return _save(fig, path)


def plot_coverage(result: Result, path) -> Path:
    """Per LIDAR: board centres in its frame (top view)."""
    problem = result.problem
    lidars = [i for i, s in enumerate(problem.sensors) if s.is_lidar]  # the cameras': plot_camera_residuals_and_coverage
    n = len(lidars)
    fig, axes = subplots(1, n, figsize=(4.2 * n, 4.2), squeeze=False)
    centre_b = np.mean(_board_outline(problem.board)[:4], axis=0)
    rtb = np.asarray(result.rt_lidar0_board, float).reshape(-1, 6)
    for ax, i in zip(axes[0], lidars):
        s = problem.sensors[i]
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
        _title(ax, f"{i}: {s.topic}\nboard centres, top view ({int(used.sum())} seen)", fontsize=9)
        ax.legend(fontsize=7)
    margins(fig, left=0.75, bottom=0.55, top=0.55, wspace=0.85)
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
    _title(ax, title or "point-transform uncertainty", fontsize=10)
    margins(fig, left=0.75, right=0.3, bottom=0.55, top=0.4)
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


def crop_box(clouds, *, percent: float = 1.0, margin_m: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(lo (3,), hi (3,)): the box holding all but ``percent`` % of the points at either end of each axis,
    grown by ``margin_m``: a few far returns (100 m) must not set the scale of 5 m of data."""
    p = np.concatenate([np.asarray(c, float).reshape(-1, 3) for c in clouds] + [np.zeros((0, 3))])
    p = p[np.all(np.isfinite(p), axis=1)]
    if not len(p):
        return -np.ones(3), np.ones(3)
    return np.percentile(p, percent, axis=0) - margin_m, np.percentile(p, 100 - percent, axis=0) + margin_m


def render_aligned_clouds(clouds: dict, rt_lidar0_sensor: dict, path_png, *, views=("top", "side"),
                          max_points: int = 60000, point_size: float = 1.0, seed: int = 0) -> Path:
    """LIDAR clouds (topic -> (N,3) in their own frame) moved into lidar0 and drawn, one colour per sensor
    (with transparency, the sparser cloud on top), cropped to where the data is (``crop_box``), each view
    with equal axes and its panel sized to its extent (a side view of 30 x 3 m is a strip, not a square).

    ``rt_lidar0_sensor``: topic -> (6,). Each cloud is subsampled to ``max_points``.
    """
    for v in views:
        if v not in _VIEWS:
            raise ValueError(f"unknown view {v!r}; one of {sorted(_VIEWS)}")
    moved = align_clouds(clouds, rt_lidar0_sensor, max_points=max_points, seed=seed)
    lo, hi = crop_box(moved.values())
    colors = dict(zip(moved, ("tab:blue", "tab:red", "tab:green", "tab:purple", "tab:orange", "tab:brown")))
    span = hi - lo
    heights = [max(span[_VIEWS[v][1]], 0.15 * span[_VIEWS[v][0]]) / span[_VIEWS[v][0]] for v in views]
    width = 12.0
    fig, axes = subplots(len(views), 1, figsize=(width, min(width * sum(heights) + 1.0 * len(views), 16)),
                         squeeze=False, gridspec_kw={"height_ratios": heights}, layout="constrained")
    order = sorted(moved, key=lambda t: -len(moved[t]))  # densest first, so the sparser stays visible
    for ax, v in zip(axes[:, 0], views):
        a, b, la, lb = _VIEWS[v]
        for topic in order:
            p = moved[topic]
            p = p[np.all((p >= lo) & (p <= hi), axis=1)]
            ax.scatter(p[:, a], p[:, b], s=point_size, color=colors[topic], alpha=0.4, label=f"{topic} ({len(p)} points)",
                       linewidths=0, rasterized=True)
        ax.set_xlim(lo[a], hi[a])
        ax.set_ylim(lo[b], hi[b])
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel(la)
        ax.set_ylabel(lb)
        ax.grid(alpha=0.3)
        _title(ax, f"{v} view, lidar0 frame, {span[a]:.1f} x {span[b]:.1f} m (1-99 % of the points)", fontsize=10)
        ax.legend(markerscale=8, fontsize=8, loc="upper right")
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
    _title(a, "top view")
    if len(pts):
        rng = np.linalg.norm(pts, axis=1)
        az = np.degrees(azimuth(pts))
        ring = (np.asarray(scan.ring)[np.asarray(scan.valid, bool)] if scan.ring is not None
                else np.degrees(elevation(pts)))
        s = b.scatter(az, ring, c=rng, s=0.5, cmap="turbo", vmax=np.percentile(rng, 98))
        fig.colorbar(s, ax=b, label="range [m]")
    b.set_xlabel("azimuth [deg]")
    b.set_ylabel("ring" if scan.ring is not None else "elevation [deg]")
    _title(b, "range image")
    fig.suptitle(title or f"{scan.topic}: {len(pts)} valid points")
    margins(fig, left=0.75, bottom=0.55, top=0.75, wspace=0.9)
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
    _title(ax, title or f"{image.topic}: {w}x{h} {image.encoding}")
    margins(fig, left=0.1, right=0.1, bottom=0.1, top=0.4)
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
    _title(a, "segments (blue), rejected planes (red), board (green)")
    if focus is not None and len(focus):
        c = pts[focus].mean(axis=0)
        near = ok & (np.linalg.norm(pts - c, axis=1) < 2.0)
        az = np.degrees(azimuth(pts))
        el = np.degrees(elevation(pts))
        b.scatter(az[near], el[near], s=4, c="0.6")
        b.scatter(az[focus], el[focus], s=6, c="tab:green" if getattr(result, "indices", None) is not None else "tab:red")
        b.invert_xaxis()
        b.set_xlabel("azimuth [deg]")
        b.set_ylabel("elevation [deg]")
        _title(b, "around the board, from the sensor")
    reason = getattr(result, "reason", None)
    fig.suptitle(reason if reason else f"board: {len(result.indices)} points, RMS {result.rms_m * 1e3:.1f} mm",
                 fontsize=9)
    margins(fig, left=0.75, bottom=0.55, top=0.7, wspace=0.9)
    return _save(fig, path)


# ---------------------------------------------------------------- report figures from plain arrays
# Each takes plain arrays (no Result), so the target-based and the targetless reports share them.


def plot_lidar_on_image(panels: list, imagersize, path, *, image=None, norm: tuple | None = None, dot_px: int = 2):
    """LIDAR points projected into one camera image, panels side by side (solved, nominal, ...), drawn
    straight into the image's pixels (no resampling: the picture is the camera's, full size; and fast).

    ``panels``: [{"q": (N,2) px, "range": (N,) m, "outline": (M,2) px or None}]; the outline (the board's
    edge fitted to the camera's own detected corners) is drawn dashed black and white. ``image``: (H,W)
    or (H,W,3) BGR (None: a grey canvas). Points are coloured by LIDAR range, turbo colour map from
    ``norm`` = (near, far) m (default: the 1-99 % range of all panels' points); a colour bar runs along
    the bottom. Titles belong in the caption. Writes a JPEG; returns ``path``.
    """
    w, h = imagersize
    if norm is None:
        v = np.concatenate([np.ravel(p["range"]) for p in panels] + [np.zeros(0)])
        norm = (float(np.percentile(v, 1)), float(np.percentile(v, 99))) if len(v) else (0.0, 1.0)
    lo, hi = norm[0], max(norm[1], norm[0] + 1e-3)
    lut = (matplotlib.colormaps["turbo"](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)
    if image is None:
        base = np.full((h, w, 3), 200, np.uint8)
    else:
        px = np.asarray(image)
        if px.dtype != np.uint8:  # mono16: scale to 8 bits for display
            px = (255.0 * px / max(float(np.percentile(px, 99.5)), 1.0)).clip(0, 255).astype(np.uint8)
        gray = px[..., ::-1].mean(axis=2) if px.ndim == 3 else px
        base = np.repeat((0.35 + 0.65 * gray[..., None] / 255.0) * 255, 3, axis=2).astype(np.uint8)  # dimmed
    tiles = []
    for p in panels:
        img = base.copy()
        q, r = np.asarray(p["q"], float).reshape(-1, 2), np.asarray(p["range"], float).ravel()
        order = np.argsort(-r)  # far first: near points stay on top
        c = lut[np.clip(((r[order] - lo) / (hi - lo) * 255).astype(int), 0, 255)]
        x0, y0 = np.round(q[order, 0]).astype(int), np.round(q[order, 1]).astype(int)
        for dx in range(dot_px):
            for dy in range(dot_px):
                x, y = x0 + dx, y0 + dy
                ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
                img[y[ok], x[ok]] = c[ok]
        if p.get("outline") is not None:
            o = np.asarray(p["outline"], float)
            seg = np.concatenate([o[k] + np.linspace(0, 1, 60, endpoint=False)[:, None] * (o[k + 1] - o[k])
                                  for k in range(len(o) - 1)])
            dash = (np.arange(len(seg)) // 12) % 2 == 0
            for d in (-1, 0, 1):
                x, y = np.round(seg[:, 0]).astype(int) + d, np.round(seg[:, 1]).astype(int)
                ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
                img[y[ok], x[ok]] = np.where(dash[ok, None], 0, 255)
        tiles.append(img)
        tiles.append(np.full((h, 8, 3), 255, np.uint8))
    pic = np.concatenate(tiles[:-1], axis=1)
    bar = np.repeat(lut[np.linspace(0, 255, pic.shape[1]).astype(int)][None], 14, axis=0)  # near ... far
    pic = np.concatenate([pic, np.full((4, pic.shape[1], 3), 255, np.uint8), bar], axis=0)
    from PIL import Image

    # JPEG: a camera image is a photograph (PNG of one costs 30x the time and twice the bytes)
    Image.fromarray(pic).save(path if hasattr(path, "write") else Path(path), format="jpeg", quality=90)
    return path


def plot_cloud_overlap(states: dict, path, *, box=None, board: dict | None = None, max_points: int = 8000):
    """Overlapping LIDAR clouds (lidar0 frame) under different extrinsics, cropped to ``box``.

    ``states``: {"before (nominal /tf_static)": {label: (N,3)}, "after (solved)": {...}} (one row each);
    ``box``: ((3,) lo, (3,) hi) or None (the data's 1-99 % extent); ``board``: {"centre": (3,),
    "normal", "along", "up": (3,) unit axes, "half_size": (2,) m} adds an edge-on view of the board: the
    distance from that plane (mm) of each point near it against its position along the board (m):
    calibrated clouds lie on one line. Sparser clouds are drawn last (on top).
    Columns: top view, side view (equal axes), board edge-on.
    """
    rows = list(states)
    labels = list(dict.fromkeys(lab for st in states.values() for lab in st))
    colors = {lab: c for lab, c in zip(labels, ("tab:blue", "tab:red", "tab:green", "tab:purple", "tab:orange"))}
    rng = np.random.default_rng(0)

    def crop(p):
        p = np.asarray(p, float).reshape(-1, 3)
        p = p[np.all(np.isfinite(p), axis=1)]
        if box is not None:
            p = p[np.all((p >= box[0]) & (p <= box[1]), axis=1)]
        return p[rng.choice(len(p), max_points, replace=False)] if len(p) > max_points else p

    data = {st: dict(sorted(((lab, crop(p)) for lab, p in states[st].items()), key=lambda x: -len(x[1])))
            for st in rows}
    every = np.concatenate([p for st in data.values() for p in st.values()] + [np.zeros((0, 3))])
    if box is None and len(every):
        box = (np.percentile(every, 1, axis=0) - 0.2, np.percentile(every, 99, axis=0) + 0.2)
    lo, hi = (np.asarray(box[0], float), np.asarray(box[1], float)) if box is not None else (-np.ones(3), np.ones(3))
    ncol = 3 if board is not None else 2
    if board is not None:  # the board edge-on: (position along it (m), distance from its plane (mm)) per cloud
        n, u, v = (np.asarray(board[k], float) for k in ("normal", "along", "up"))
        c0, half = np.asarray(board["centre"], float), np.asarray(board["half_size"], float) + 0.2
        edge_on = {}
        for st in rows:
            edge_on[st] = {}
            for lab, p in data[st].items():
                d = p - c0
                on = (np.abs(d @ n) < 0.15) & (np.abs(d @ u) < half[0]) & (np.abs(d @ v) < half[1])
                edge_on[st][lab] = (d[on] @ u, 1e3 * (d[on] @ n))
        off = np.concatenate([np.abs(y) for st in edge_on.values() for _, y in st.values()] + [np.zeros(1)])
        edge_lim = float(np.clip(1.3 * np.percentile(off, 99.5), 20, 150))
    span = hi - lo
    fig, axes = subplots(len(rows), ncol, figsize=(5.2 * ncol, 4.2 * len(rows)), squeeze=False,
                         gridspec_kw={"width_ratios": [1, 1, 1.2][:ncol]})
    for r, st in enumerate(rows):
        for c, (a, b, la, lb, view) in enumerate(((0, 1, "x (m)", "y (m)", "top view"), (0, 2, "x (m)", "z (m)", "side view"))):
            ax = axes[r, c]
            for lab, p in data[st].items():  # plot() markers: one cached marker stamped, far faster than scatter()
                ax.plot(p[:, a], p[:, b], ".", ms=1.5, mew=0, color=colors[lab], alpha=0.4, label=lab)
            ax.set_xlim(lo[a], hi[a])
            ax.set_ylim(lo[b], hi[b])
            ax.set_aspect("equal", adjustable="box")
            ax.set_xlabel(la, fontsize=8)
            ax.set_ylabel(lb, fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
            _title(ax, f"{st}: {view}, {span[a]:.1f} x {span[b]:.1f} m", fontsize=9)
        if board is not None:
            ax = axes[r, 2]
            for lab, (x_m, off_mm) in edge_on[st].items():
                ax.plot(x_m, off_mm, ".", ms=3, mew=0, color=colors[lab], alpha=0.6, label=lab)
            ax.axhline(0, color="k", lw=0.6)
            ax.set_ylim(-edge_lim, edge_lim)  # one scale for every row: before and after compare
            ax.set_xlabel("along the board (m)", fontsize=8)
            ax.set_ylabel("from the solved board plane (mm)", fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
            _title(ax, f"{st}: the board edge-on", fontsize=9)
        axes[r, 0].legend(markerscale=8, fontsize=7, loc="upper left")
    margins(fig, left=0.6, right=0.15, bottom=0.5, top=0.3, wspace=0.7, hspace=0.6)
    return _save(fig, path, dpi=80)


def plot_camera_residuals_and_coverage(cams: list, path):
    """Per camera, over the whole image: its reprojection errors as arrows (observed - predicted, scaled
    up), the convex hull of every corner it detected (shaded) and the image's thirds (dotted).

    ``cams``: [{"title", "imagersize": (w, h), "corners": (M,2) px, "residuals": (M,2) px or None,
    "outlier": (M,) bool, "coverage": evidence.image_coverage(...)}]. A camera whose coverage has a
    warning gets a red frame and title. The arrow scale is in the title.
    """
    from scipy.spatial import ConvexHull, QhullError

    n = max(1, len(cams))
    fig, axes = subplots(1, n, figsize=(5.4 * n, 4.6), squeeze=False)
    for ax, c in zip(axes[0], cams):
        w, h = c["imagersize"]
        q = np.asarray(c["corners"], float).reshape(-1, 2)
        fin = np.all(np.isfinite(q), axis=1)
        if fin.sum() >= 3:
            try:
                hv = ConvexHull(q[fin]).vertices
                ax.fill(q[fin][hv, 0], q[fin][hv, 1], color="C0", alpha=0.10, lw=1, ec="C0")
            except QhullError:
                pass
        for k in (1, 2):
            ax.axhline(k * h / 3, color="0.6", lw=0.6, ls=":")
            ax.axvline(k * w / 3, color="0.6", lw=0.6, ls=":")
        head = c["title"]
        if c.get("residuals") is not None:
            e = np.asarray(c["residuals"], float).reshape(-1, 2)
            bad = np.asarray(c.get("outlier", np.zeros(len(q), bool)), bool)
            mag = np.linalg.norm(e, axis=1)
            good = ~bad
            ref = float(np.percentile(mag[good], 90)) if good.any() else 1.0
            scale = 0.04 * max(w, h) / max(ref, 1e-6)  # the 90th-percentile arrow is 4 % of the image
            qv = ax.quiver(q[good, 0], q[good, 1], e[good, 0] * scale, e[good, 1] * scale, mag[good], cmap="viridis",
                           angles="xy", scale_units="xy", scale=1, width=0.003)
            if bad.any():
                ax.quiver(q[bad, 0], q[bad, 1], e[bad, 0] * scale, e[bad, 1] * scale, color="r", angles="xy",
                          scale_units="xy", scale=1, width=0.003, label="outliers (rejected)")
                ax.legend(fontsize=7, loc="lower right")
            fig.colorbar(qv, ax=ax, shrink=0.7, label="|error| (px)")
            rms = float(np.sqrt(np.mean(mag[good] ** 2))) if good.any() else float("nan")
            head += f"\n{good.sum()} corners, RMS {rms:.3f} px, arrows x{scale:.0f}"
        else:
            ax.plot(q[:, 0], q[:, 1], ".", ms=1.5)
        cov = c.get("coverage") or {}
        head += f"; hull {100 * cov.get('hull_fraction', 0):.0f} % of the image"
        if cov.get("warning"):
            for sp in ax.spines.values():
                sp.set_color("r")
                sp.set_linewidth(2.5)
            head += "\nTOO LITTLE OF THE IMAGE COVERED"
        _title(ax, head, fontsize=9, color="r" if cov.get("warning") else "k")
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
    if not cams:
        axes[0, 0].text(0.5, 0.5, "no cameras", ha="center", va="center")
        axes[0, 0].set_axis_off()
    margins(fig, left=0.45, right=0.1, bottom=0.35, top=0.75, wspace=0.5)
    return _save(fig, path, dpi=80)


def plot_lidar_residuals(lidars: list, path, *, max_points: int = 5000):
    """Per LIDAR, residuals against range and against ring (elevation angle), with binned mean and RMS.

    ``lidars``: [{"title", "residual": (N,) m, "range": (N,) m, "elevation_deg": (N,), "outlier": (N,)
    bool}]. A trend with range means a range-scale or timing error; one ring off the others, a
    miscalibrated ring elevation (the LIDAR's own intrinsics).
    """
    n = max(1, len(lidars))
    fig, axes = subplots(n, 2, figsize=(11, 3.0 * n), squeeze=False)
    rng = np.random.default_rng(0)
    for row, L in zip(axes, lidars):
        x = np.asarray(L["residual"], float) * 1e3
        good = ~np.asarray(L.get("outlier", np.zeros(len(x), bool)), bool) & np.isfinite(x)
        for ax, key, lab in ((row[0], "range", "range (m)"), (row[1], "elevation_deg", "ring: elevation angle (deg)")):
            v = np.asarray(L[key], float)
            k = np.flatnonzero(good)
            if len(k) > max_points:
                k = rng.choice(k, max_points, replace=False)
            ax.plot(v[k], x[k], ".", ms=1.5, mew=0, color="0.55", alpha=0.4)
            if key == "range":
                edges = np.linspace(np.nanmin(v[good]), np.nanmax(v[good]) + 1e-9, 13) if good.any() else np.zeros(2)
            else:  # one bin per ring: rings sit at distinct elevations
                e = np.unique(np.round(v[good], 1))
                edges = np.r_[e[0] - 0.05, 0.5 * (e[1:] + e[:-1]), e[-1] + 0.05] if len(e) else np.zeros(2)
                if len(e) > 128:
                    edges = np.linspace(e[0], e[-1] + 1e-9, 33)
            b = np.clip(np.searchsorted(edges, v[good]) - 1, 0, len(edges) - 2)
            cnt = np.bincount(b, minlength=len(edges) - 1)
            with np.errstate(invalid="ignore", divide="ignore"):
                mean = np.bincount(b, x[good], len(edges) - 1) / cnt
                rms = np.sqrt(np.bincount(b, x[good] ** 2, len(edges) - 1) / cnt)
            mid = 0.5 * (edges[1:] + edges[:-1])
            ok = cnt >= 5
            ax.plot(mid[ok], mean[ok], "o-", color="C3", ms=3, lw=1, label="mean per bin")
            ax.plot(mid[ok], rms[ok], "s--", color="C0", ms=3, lw=1, label="RMS per bin")
            ax.axhline(0, color="k", lw=0.6)
            lim = max(3 * np.std(x[good]), 1.0) if good.any() else 10.0
            ax.set_ylim(-lim, lim)
            ax.set_xlabel(lab, fontsize=8)
            ax.set_ylabel("residual (mm)", fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
            _title(ax, f"{L['title']}: residual against {lab.split(' (')[0]}", fontsize=9)
        row[0].legend(fontsize=7, loc="upper right")
    if not lidars:
        axes[0, 0].text(0.5, 0.5, "no LIDAR residuals", ha="center", va="center")
    margins(fig, left=0.6, right=0.15, bottom=0.45, top=0.3, wspace=0.6, hspace=0.7)
    return _save(fig, path, dpi=80)


def plot_map_trajectory(points: np.ndarray, trajectory: np.ndarray, path, *, keyframes: np.ndarray | None = None,
                        max_points: int = 60000):
    """Targetless: the map (N,3) from above coloured by height, with the trajectory (T,3) and keyframes (K,3)."""
    p = np.asarray(points, float).reshape(-1, 3)
    if len(p) > max_points:
        p = p[np.random.default_rng(0).choice(len(p), max_points, replace=False)]
    t = np.asarray(trajectory, float).reshape(-1, 3)
    lo, hi = crop_box([p, t], margin_m=1.0)  # a stray far point must not set the scale
    lo, hi = np.minimum(lo, t.min(0) - 1.0), np.maximum(hi, t.max(0) + 1.0)
    span = hi - lo
    # the figure shaped like the map (equal axes): a 80 x 20 m drive is a strip, not a square
    fig, ax = subplots(figsize=(10, float(np.clip(8.6 * span[1] / max(span[0], 1e-3) + 0.9, 3.0, 9.0))))
    if len(p):
        zlo, zhi = np.percentile(p[:, 2], [2, 98])
        s = ax.scatter(p[:, 0], p[:, 1], s=0.3, c=p[:, 2], cmap="viridis", vmin=zlo, vmax=zhi, linewidths=0, rasterized=True)
        fig.colorbar(s, ax=ax, shrink=0.8, label="z (m)", pad=0.02)
    ax.plot(t[:, 0], t[:, 1], "r-", lw=1.2, label="trajectory")
    if keyframes is not None and len(keyframes):
        k = np.asarray(keyframes, float).reshape(-1, 3)
        ax.plot(k[:, 0], k[:, 1], "k.", ms=4, label="keyframes")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    _title(ax, "map (top view, 1-99 % of the points) and trajectory")
    ax.legend(fontsize=8, loc="upper left")
    margins(fig, left=0.7, right=0.2, bottom=0.55, top=0.35)
    return _save(fig, path, dpi=80)


def plot_frame_scores(before: np.ndarray, after: np.ndarray, path, *, title: str = "",
                      ylabel: str = "truncated mean sq. distance (m^2)"):
    """Targetless: a score per calibration frame under the initial guess and the result (lower is better)."""
    b, a = np.asarray(before, float), np.asarray(after, float)
    fig, ax = subplots(figsize=(7, 3.2))
    x = np.arange(len(b))
    ax.bar(x - 0.2, b, 0.4, label="initial guess")
    ax.bar(x + 0.2, a, 0.4, label="final")
    ax.set_xlabel("calibration frame")
    ax.set_ylabel(ylabel, fontsize=8)
    _title(ax, title or "per-frame scores", fontsize=9)
    ax.legend(fontsize=8)
    margins(fig, left=0.7, right=0.15, bottom=0.5, top=0.3)
    return _save(fig, path, dpi=80)


def plot_distance_histograms(distances: dict, path, *, max_m: float, title: str = ""):
    """Targetless: histograms of each point's distance to the map ({label: (N,) m}), last bin = farther."""
    fig, ax = subplots(figsize=(7, 3.2))
    bins = np.linspace(0, max_m, 61)
    for (lab, d), col in zip(distances.items(), ("C0", "C3", "C2", "C4")):
        d = np.asarray(d, float)
        ax.hist(np.minimum(d, bins[-1]), bins, histtype="step", color=col, label=f"{lab}: median {1e3 * np.median(d):.1f} mm")
    ax.set_xlabel("distance of each point to the nearest map point (m) (last bin: farther)", fontsize=8)
    ax.set_ylabel("points")
    _title(ax, title, fontsize=9)
    ax.legend(fontsize=8)
    margins(fig, left=0.7, right=0.15, bottom=0.5, top=0.3)
    return _save(fig, path, dpi=80)
