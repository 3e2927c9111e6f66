"""report.html of a targetless calibration: poses, the final graphs, convergence, timings and
the pictures (map and trajectory, per-frame scores, before / after alignment, distances to the map).

``report.write_report`` calls this for a Result with ``method == "targetless"``; the data of
the pictures were computed by the calibration (``Result.targetless.pictures``): this only draws.

SYNOPSIS
    path = write_targetless_report(result, "out/")   # also writes the PNGs
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from .. import __version__
from ..geometry import pose_stdevs
from ..types import Result
from .plots import subplots  # Figure objects: the user's matplotlib backend is left alone
from .report import convergence_html

_DPI = 90


def _name(topic: str) -> str:
    return topic.strip("/").replace("/", "_")


def _finish(fig, ax, title: str, path, **legend) -> Path:
    ax.set_title(title)
    ax.legend(**legend)
    fig.savefig(path, dpi=_DPI, bbox_inches="tight")
    return Path(path)


def plot_map(pictures: dict, path) -> Path:
    """Top view of the map, the trajectory and the keyframes."""
    pts, traj, kf = pictures["map_points"], pictures["trajectory"], pictures["keyframes"]
    fig, ax = subplots(figsize=(8, 6))
    ax.scatter(pts[:, 0], pts[:, 1], s=0.2, c=pts[:, 2], cmap="viridis")
    ax.plot(traj[:, 0], traj[:, 1], "r-", lw=1, label="trajectory")
    ax.plot(traj[kf, 0], traj[kf, 1], "k.", label="keyframes")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    return _finish(fig, ax, "map (top view) and trajectory", path, loc="upper left", bbox_to_anchor=(1, 1))


def plot_scores(topic: str, rows: list, path) -> Path:
    """Per calibration frame: the score of the initial guess and of the result."""
    fig, ax = subplots(figsize=(7, 3.5))
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r["score_guess"] for r in rows], 0.4, label="initial guess")
    ax.bar(x + 0.2, [r["score_final"] for r in rows], 0.4, label="final")
    ax.set_xlabel("calibration frame")
    ax.set_ylabel("truncated mean sq. distance [m^2]")
    return _finish(fig, ax, f"{topic}: per-frame scores", path)


def plot_alignment(topic: str, pic: dict, path) -> Path:
    """One frame near the sensor, before (tf_static) and after, top and side views."""
    tg, box = pic["target"], pic["box_m"]
    fig, axs = subplots(2, 2, figsize=(13, 8), height_ratios=[2, 1], layout="constrained")
    for col, (s, title) in enumerate(((pic["source_guess"], "before (tf_static)"), (pic["source_final"], "after"))):
        for row, (i, j, lab) in enumerate(((0, 1, "y"), (0, 2, "z"))):
            a = axs[row, col]
            a.scatter(tg[:, i], tg[:, j], s=0.2, c="0.6", label="mapping (dense)")
            a.scatter(s[:, i], s[:, j], s=0.5, c="r", label=topic)
            a.set_aspect("equal")
            a.set_xlabel("x [m]")
            a.set_ylabel(f"{lab} [m]")
            a.set_title(f"{title}: {'top' if row == 0 else 'side'} view, {box:.0f} m around the sensor")
    axs[0, 1].legend(loc="upper left", bbox_to_anchor=(1, 1))
    fig.savefig(path, dpi=_DPI, bbox_inches="tight")
    return Path(path)


def plot_distances(topic: str, pic: dict, path) -> Path:
    """Histogram of every frame's point-to-map distances, before and after."""
    fig, ax = subplots(figsize=(7, 3.5))
    bins = np.linspace(0, pic["max_corr_m"] * 3, 61)
    for key, lab, col in (("distances_guess", "before", "C0"), ("distances_final", "after", "C3")):
        dist = pic[key]
        ax.hist(np.minimum(dist, bins[-1]), bins, histtype="step", color=col,
                label=f"{lab}: median {1e3 * np.median(dist):.1f} mm")
    ax.set_xlabel("distance of each point to the nearest dense-map point [m] (last bin: farther)")
    ax.set_ylabel("points")
    return _finish(fig, ax, f"{topic}: all {pic['frames']} calibration frames", path)


def plot_all_targetless(result: Result, out_dir) -> list[str]:
    """Every picture of the report into ``out_dir``; their file names, in report order."""
    out_dir, run = Path(out_dir), result.targetless
    out = [plot_map(run.pictures["map"], out_dir / "map_top.png").name]
    for topic, rows in run.per_frame.items():
        out.append(plot_scores(topic, rows, out_dir / f"scores_{_name(topic)}.png").name)
        pic = run.pictures["alignment"].get(topic)
        if pic:
            out.append(plot_alignment(topic, pic, out_dir / f"aligned_{_name(topic)}.png").name)
            out.append(plot_distances(topic, pic, out_dir / f"distances_{_name(topic)}.png").name)
    return out


def targetless_report_html(result: Result, pngs: list[str], *, title: str = "clcgraph targetless calibration") -> str:
    run, p = result.targetless, result.problem
    rows = []
    for i, s in enumerate(p.sensors):
        rt = np.asarray(result.rt_lidar0_sensor[i], float)
        sd_rot, sd_pos = pose_stdevs(rt, result.covariance_block(i))
        rows.append(f"<tr><td>{html.escape(s.topic)}</td><td>{np.round(rt, 6).tolist()}</td>"
                    f"<td>{np.round(1e3 * sd_pos, 3).tolist()}</td><td>{np.round(np.degrees(sd_rot), 4).tolist()}</td></tr>")
    graph = "".join(f"<tr><td>{html.escape(t)}</td><td>{g['frames']}</td><td>{g['keyframes']}</td><td>{g['keyframe_edges']}</td>"
                    f"<td>{g['noise_scale']['frames']:.3g}</td><td>{g['noise_scale']['keyframes']:.3g}</td>"
                    f"<td>{g['common_mode']:g}</td></tr>" for t, g in run.graph.items())
    timings = "".join(f"<tr><td>{html.escape(k)}</td><td>{v:.2f}</td></tr>"
                      for k, v in (result.stats.get("stage_time_s") or {}).items())
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title></head><body>"
            f"<h1>{html.escape(title)}</h1><p>clcgraph {__version__}. Reference: {html.escape(p.sensors[p.reference].topic)}</p>"
            "<table border=1><tr><th>topic</th><th>rt_lidar0_sensor</th>"
            "<th>stdev position along lidar0 x y z [mm]</th><th>stdev orientation about the sensor's x y z [deg]</th></tr>"
            + "".join(rows) + "</table>"
            "<h2>final graph</h2><p>extrinsic + keyframe poses; one factor per frame, registration edges "
            "between keyframe submaps; noise scales estimated from the residuals (x GICP Hessian^-1); the "
            "sigmas include a bias shared by all frames (prior: 'common mode' x one frame's covariance).</p>"
            "<table border=1><tr><th>topic</th><th>frames</th><th>keyframes</th><th>edges</th>"
            f"<th>scale frames</th><th>scale edges</th><th>common mode</th></tr>{graph}</table>"
            + "".join(f"<h2>convergence: {html.escape(t)}</h2>" + convergence_html(c) for t, c in run.convergence.items())
            + f"<h2>timings [s]</h2><table border=1>{timings}</table>"
            + "".join(f"<h2>{html.escape(n)}</h2><img src='{html.escape(n)}'>" for n in pngs)
            + "".join(f"<p>{html.escape(n)}</p>" for n in run.notes) + "</body></html>")


def write_targetless_report(result: Result, out_dir, *, title: str = "clcgraph targetless calibration") -> Path:
    """Draw every picture into ``out_dir`` and write ``out_dir/report.html`` referencing them."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "report.html"
    path.write_text(targetless_report_html(result, plot_all_targetless(result, out_dir), title=title))
    return path
