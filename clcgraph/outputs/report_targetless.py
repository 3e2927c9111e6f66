"""report.html of a targetless calibration: the verdicts at the top (convergence, registration scores,
agreement of the per-frame registrations, distances to the map, the ground plane), the poses in the
people's format, the run's record (bags, the call, the settings, the version), the final graphs,
convergence, timings and the pictures (map and trajectory, per-frame scores, before / after
alignment, distances to the map), each after a paragraph saying how to read it.

``report.write_report`` calls this for a Result with ``method == "targetless"``; the data of the
pictures were computed by the calibration (``Result.targetless.pictures``): this only draws. The
banner, the pose table and the inputs record are the target-based report's (report.py), not copies.

SYNOPSIS
    path = write_targetless_report(result, "out/", inputs=report_inputs)   # one self-contained file
"""

from __future__ import annotations

import html
import io
from pathlib import Path

import numpy as np

from ..geometry import pose_difference, rpy_deg_from_R
from ..types import Result
from . import plots
from .report import _CSS, banner, convergence_html, convergence_verdict, embed_image, inputs_html, pose_table

HOWTO = {
    "map": "The map the mapping LIDAR built while driving, from above and coloured by height, with the "
    "trajectory (red) and the keyframes (black). Straight walls and one trajectory without jumps mean the "
    "odometry held; a doubled wall or a jump is a mapping failure, and every calibration below is then suspect.",
    "scores": "One pair of bars per calibration frame: the frame's score (truncated mean squared distance of its "
    "points to the map) with the initial /tf_static guess and with the result; lower is better. The final bar "
    "should be lower in nearly every frame; a frame whose final bar is higher disagrees with the rest.",
    "aligned": "One calibration frame's points (red) on the dense map around them (blue), before (the guess) and "
    "after (the result), cropped to where they overlap: after, walls and poles of both colours must coincide.",
    "distances": "Every calibration frame's points' distances to the nearest map point, before and after: after, "
    "the histogram should pile up near zero (the LIDARs' noise and the map's thickness); the last bin counts the "
    "points farther than its edge (parts of the scene the map does not have).",
}


def _name(topic: str) -> str:
    return topic.strip("/").replace("/", "_")


def _png(draw) -> bytes:
    buf = io.BytesIO()
    draw(buf)
    return buf.getvalue()


def figure_jobs(result: Result) -> list[tuple[str, object]]:
    """[(name, job)] of every picture of the report, in report order: a job draws its picture from
    the arrays the calibration kept (outputs/plots.py) and returns [PNG bytes]."""
    run = result.targetless
    m = run.pictures["map"]
    kf = np.asarray(m["keyframes"])
    jobs = [("map_top.png", lambda f: plots.plot_map_trajectory(m["map_points"], m["trajectory"], f,
                                                                keyframes=m["trajectory"][kf]))]
    for topic, rows in run.per_frame.items():
        jobs.append((f"scores_{_name(topic)}.png", lambda f, topic=topic, rows=rows: plots.plot_frame_scores(
            [r["score_guess"] for r in rows], [r["score_final"] for r in rows], f, title=f"{topic}: per-frame scores")))
        pic = run.pictures["alignment"].get(topic)
        if pic:
            states = {"before (tf_static)": {"mapping (dense)": pic["target"], topic: pic["source_guess"]},
                      "after (solved)": {"mapping (dense)": pic["target"], topic: pic["source_final"]}}
            box = plots.crop_box([pic["target"], pic["source_final"]], margin_m=0.2)
            jobs.append((f"aligned_{_name(topic)}.png",
                         lambda f, states=states, box=box: plots.plot_cloud_overlap(states, f, box=box)))
            dist = {"before": pic["distances_guess"], "after": pic["distances_final"]}
            jobs.append((f"distances_{_name(topic)}.png", lambda f, topic=topic, pic=pic, dist=dist:
                         plots.plot_distance_histograms(dist, f, max_m=pic["max_corr_m"] * 3,
                                                        title=f"{topic}: all {pic['frames']} calibration frames")))
    return [(name, lambda draw=draw: [_png(draw)]) for name, draw in jobs]


def start_figures(result: Result):
    """An ``outputs.drawing.Drawing`` of the report's pictures, its second process drawing from now on
    (the clouds first: the map's and the overlaps' take longest, so the two processes finish together)."""
    from .drawing import Drawing

    jobs = figure_jobs(result)
    order = sorted(range(len(jobs)), key=lambda k: not jobs[k][0].startswith(("map_", "aligned_")))
    return Drawing([job for _, job in jobs], names=[name for name, _ in jobs], order=order)


def figures(result: Result, drawing=None) -> dict[str, bytes]:
    """Every picture of the report as PNG bytes, in report order (name -> PNG); ``drawing``:
    ``start_figures(result)``, started earlier (else here). A picture that failed is left out (logged)."""
    if drawing is None:
        with start_figures(result) as drawing:
            return figures(result, drawing)
    return {name: png[0] for name, png in zip(drawing.names, drawing.results()) if png}


def verdicts(result: Result) -> list[tuple]:
    """The banner items (see report.banner) of a targetless calibration, from what its Result carries."""
    from ..geometry import T_from_rt

    run, p = result.targetless, result.problem
    items = []
    for topic, conv in run.convergence.items():
        items.append(convergence_verdict(conv, f"Graph of {topic}"))
    kept = {n.split(":", 1)[0] for n in run.notes if "initial guess kept" in n}
    for topic, rows in run.per_frame.items():
        g = np.array([r["score_guess"] for r in rows], float)
        f = np.array([r["score_final"] for r in rows], float)
        better = int(np.sum(f < g))
        ok = topic not in kept and f.sum() < g.sum()
        items.append((ok, f"Registration scores of {topic}", "better than the guess" if ok else "NOT BETTER than the guess",
                      f"{better} of {len(rows)} calibration frames fit the map better with the result; RMS distance "
                      f"to the map (truncated) {1e3 * np.sqrt(g.mean()):.1f} mm with the /tf_static guess, "
                      f"{1e3 * np.sqrt(f.mean()):.1f} mm with the result"
                      + ("; the guess was kept (it scored better than every registration)" if topic in kept else "")))
        i = next(k for k, s in enumerate(p.sensors) if s.topic == topic)
        T = T_from_rt(np.asarray(result.rt_lidar0_sensor[i], float))
        diffs = np.array([pose_difference(T, T_from_rt(np.asarray(r["rt_frame"], float))) for r in rows if "rt_frame" in r])
        if len(diffs):
            sd_rot = np.degrees(np.linalg.norm(result.stdev_rt(i)[:3]))
            items.append((None, f"Per-frame registrations of {topic}",
                          f"median {np.degrees(np.median(diffs[:, 0])):.2f} deg, {1e3 * np.median(diffs[:, 1]):.0f} mm from the result",
                          f"each of the {len(diffs)} frames registered alone, against the fused result: largest "
                          f"{np.degrees(diffs[:, 0].max()):.2f} deg, {1e3 * diffs[:, 1].max():.0f} mm (the fused result's "
                          f"rotation 1-sigma is {sd_rot:.3f} deg; one frame alone is far less certain)"))
        cands = run.candidates.get(topic) or []
        if len(cands) > 1:
            best = min(cands, key=lambda c: c[2])
            items.append((None, f"Registration ensemble of {topic}", f"{len(cands)} candidates",
                          f"best: {html.escape(str(best[0]))} (score {best[2]:.3g}; the initial guess's "
                          f"{cands[0][2]:.3g})"))
        pic = (run.pictures.get("alignment") or {}).get(topic)
        if pic:
            before, after = np.median(pic["distances_guess"]), np.median(pic["distances_final"])
            items.append((after <= before, f"Distances to the map of {topic}",
                          "closer" if after <= before else "FARTHER",
                          f"median {1e3 * before:.1f} mm before, {1e3 * after:.1f} mm after, over every point (1 in 4) "
                          f"of all {pic['frames']} calibration frames"))
    if result.T_base_sensor:
        ref = p.sensors[p.reference].topic
        T = np.asarray(result.T_base_sensor.get(ref, next(iter(result.T_base_sensor.values()))), float)
        r, pch, _ = rpy_deg_from_R(T[:3, :3])
        items.append((None, f"{result.base_frame} <- {ref} from the ground plane",
                      f"roll {r:+.2f} deg, pitch {pch:+.2f} deg, z {T[2, 3]:+.3f} m",
                      "the ground fixes roll, pitch and height only; x, y and yaw stay the /tf_static guess's"))
    else:
        items.append((None, "Ground plane", "not fitted", "no base frame asked for (--base-frame)"))
    return [x for x in items if x is not None]


def targetless_report_html(result: Result, pngs: dict[str, bytes], *, title: str = "clcgraph targetless calibration",
                           inputs=None) -> str:
    run, p = result.targetless, result.problem
    frames = ["reference" if i == p.reference else (run.graph.get(s.topic) or {}).get("frames", "–")
              for i, s in enumerate(p.sensors)]
    graph = "".join(f"<tr><td>{html.escape(t)}</td><td>{g['frames']}</td><td>{g['keyframes']}</td><td>{g['keyframe_edges']}</td>"
                    f"<td>{g['noise_scale']['frames']:.3g}</td><td>{g['noise_scale']['keyframes']:.3g}</td>"
                    f"<td>{g['common_mode']:g}</td></tr>" for t, g in run.graph.items())
    timings = "".join(f"<tr><td>{html.escape(k)}</td><td>{v:.2f}</td></tr>"
                      for k, v in (result.stats.get("stage_time_s") or {}).items())
    shown, pictures = set(), []
    for n, png in pngs.items():
        key = n.split("_", 1)[0].removesuffix(".png")
        if key not in shown:
            shown.add(key)
            pictures.append(f"<p class='howto'>{html.escape(HOWTO.get(key, ''))}</p>")
        pictures.append(f"<h3>{html.escape(n)}</h3>" + embed_image(n, png))
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title><style>{_CSS}</style>"
            f"</head><body><h1>{html.escape(title)}</h1>" + banner(verdicts(result))
            + f"<p>Reference frame: lidar0 = the mapping LIDAR <code>{html.escape(p.sensors[p.reference].topic)}</code>.</p>"
            "<h2>Poses</h2>" + pose_table(result, extra={"calibration frames": frames})
            + "<h2>Inputs and settings</h2>" + inputs_html(result, inputs)
            + "<h2>Final graph</h2><p class='howto'>Extrinsic + keyframe poses; one factor per frame, registration edges "
            "between keyframe submaps; noise scales estimated from the residuals (x GICP Hessian^-1); the "
            "sigmas include a bias shared by all frames (prior: 'common mode' x one frame's covariance).</p>"
            "<table><tr><th>topic</th><th>frames</th><th>keyframes</th><th>edges</th>"
            f"<th>scale frames</th><th>scale edges</th><th>common mode</th></tr>{graph}</table>"
            + "".join(f"<h2>Convergence: {html.escape(t)}</h2>" + convergence_html(c) for t, c in run.convergence.items())
            + f"<h2>Timings [s]</h2><table>{timings}</table><h2>Pictures</h2>" + "".join(pictures)
            + ("<h2>Notes</h2>" + "".join(f"<p>{html.escape(n)}</p>" for n in run.notes) if run.notes else "")
            + "</body></html>")


def write_targetless_report(result: Result, out_dir, *, title: str = "clcgraph targetless calibration",
                            inputs=None, drawing=None) -> Path:
    """Write ``out_dir/report.html``: one file, the pictures embedded. ``inputs``: an
    ``evidence.ReportInputs`` (the run's record: bags, the call, the settings); ``drawing``: its
    pictures' ``start_figures``, started earlier."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "report.html"
    path.write_text(targetless_report_html(result, figures(result, drawing), title=title, inputs=inputs))
    return path
