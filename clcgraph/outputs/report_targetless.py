"""report.html of a targetless calibration: poses, the final graphs, convergence, timings and
the pictures (map and trajectory, per-frame scores, before / after alignment, distances to the map).

``report.write_report`` calls this for a Result with ``method == "targetless"``; the data of
the pictures were computed by the calibration (``Result.targetless.pictures``): this only draws.

SYNOPSIS
    path = write_targetless_report(result, "out/")   # one self-contained file
"""

from __future__ import annotations

import html
import io
from pathlib import Path

import numpy as np

from .. import __version__
from ..geometry import pose_stdevs
from ..types import Result
from . import plots
from .report import convergence_html, embed_image

def _name(topic: str) -> str:
    return topic.strip("/").replace("/", "_")


def _png(draw) -> bytes:
    buf = io.BytesIO()
    draw(buf)
    return buf.getvalue()


def figures(result: Result) -> dict[str, bytes]:
    """Every picture of the report as PNG bytes, in report order (name -> PNG), drawn by
    outputs/plots.py from the arrays the calibration kept."""
    run = result.targetless
    m = run.pictures["map"]
    kf = np.asarray(m["keyframes"])
    out = {"map_top.png": _png(lambda f: plots.plot_map_trajectory(m["map_points"], m["trajectory"], f,
                                                                  keyframes=m["trajectory"][kf]))}
    for topic, rows in run.per_frame.items():
        out[f"scores_{_name(topic)}.png"] = _png(lambda f: plots.plot_frame_scores(
            [r["score_guess"] for r in rows], [r["score_final"] for r in rows], f, title=f"{topic}: per-frame scores"))
        pic = run.pictures["alignment"].get(topic)
        if pic:
            states = {"before (tf_static)": {"mapping (dense)": pic["target"], topic: pic["source_guess"]},
                      "after (solved)": {"mapping (dense)": pic["target"], topic: pic["source_final"]}}
            box = plots.crop_box([pic["target"], pic["source_final"]], margin_m=0.2)
            out[f"aligned_{_name(topic)}.png"] = _png(lambda f: plots.plot_cloud_overlap(states, f, box=box))
            dist = {"before": pic["distances_guess"], "after": pic["distances_final"]}
            out[f"distances_{_name(topic)}.png"] = _png(lambda f: plots.plot_distance_histograms(
                dist, f, max_m=pic["max_corr_m"] * 3, title=f"{topic}: all {pic['frames']} calibration frames"))
    return out


def targetless_report_html(result: Result, pngs: dict[str, bytes], *, title: str = "clcgraph targetless calibration") -> str:
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
            + "".join(f"<h2>{html.escape(n)}</h2>" + embed_image(n, png) for n, png in pngs.items())
            + "".join(f"<p>{html.escape(n)}</p>" for n in run.notes) + "</body></html>")


def write_targetless_report(result: Result, out_dir, *, title: str = "clcgraph targetless calibration") -> Path:
    """Write ``out_dir/report.html``: one file, the pictures embedded."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "report.html"
    path.write_text(targetless_report_html(result, figures(result), title=title))
    return path
