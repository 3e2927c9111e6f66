"""report.html: a self-contained page with the pose table, RMS, noise, rejections and the plots.

SYNOPSIS
    path = write_report(result, "out/", title="rig 17")   # also writes the PNGs
"""

from __future__ import annotations

import html
from collections import Counter
from pathlib import Path

import numpy as np

from .. import __version__
from ..geometry import pose_stdevs
from ..types import Result

HOWTO = {
    "residuals-histogram.png": "The histogram should match the red Gaussian (the re-estimated noise sigma). "
    "Heavy tails or a shifted peak mean outliers or a systematic error (bad intrinsics, a warped board, "
    "time skew).",
    "residuals-per-snapshot.png": "Each dot is one sensor's RMS residual in one snapshot. They should scatter "
    "evenly around the dashed noise level with no trend; a snapshot far above the rest is suspect. "
    "Crosses at the bottom are rejected observations (reasons in the table above).",
    "geometry.png": "The solved sensor poses (x red, y green, z blue) and the board poses, in the lidar0 frame. "
    "Check it against the physical rig: a sensor in the wrong place or upside down is obvious here.",
    "sectors.png": "The ground around the vehicle in slices. Left: the worst sensor-pair position "
    "uncertainty of a ground point at the quantification range; sectors with large stdev need more "
    "board poses there. Right: how many board observations fell in each sector. The red outline is the "
    "sector of the last snapshot.",
    "coverage.png": "Where each sensor saw the board. Boards spread over the field of view (and, for "
    "cameras, corners reaching the image edges) constrain the pose; clustered boards leave it weak.",
}


def _board_line(board) -> str:
    ox, oy = board.pattern_offset_m
    return (f"Board: {board.corners_x} x {board.corners_y} inner corners, {board.square_m * 1e3:g} mm squares, "
            f"{board.width_m * 1e3:g} x {board.height_m * 1e3:g} mm (width x height), pattern centre offset "
            f"({ox * 1e3:g}, {oy * 1e3:g}) mm from the board's centre.")


def _fmt(v, f="{:.3g}"):
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "–"
    return f.format(v)


def _pose_table(result: Result) -> str:
    rows = []
    per = result.noise.get("per_sensor") or {}
    for i, s in enumerate(result.problem.sensors):
        rt = np.asarray(result.rt_lidar0_sensor[i], float)
        sd_rot, sd_pos = pose_stdevs(rt, result.covariance_block(i))
        ref = " (reference)" if i == result.problem.reference else ""
        noise = "–" if i not in per else (f"{per[i] * 1e3:.1f} mm" if s.kind == "lidar" else f"{per[i]:.3f} px")
        rows.append(
            "<tr>" + "".join(
                f"<td>{c}</td>" for c in (
                    i, html.escape(s.topic) + ref, s.kind,
                    " ".join(f"{x:+.4f}" for x in rt[3:]),
                    " ".join(f"{x:+.3f}" for x in np.degrees(rt[:3])),
                    " ".join(f"{x:.2f}" for x in sd_pos * 1e3),
                    " ".join(f"{x:.3f}" for x in np.degrees(sd_rot)),
                    noise,
                )
            ) + "</tr>"
        )
    head = ("<tr><th>#</th><th>topic</th><th>kind</th><th>t_lidar0_sensor (m)</th><th>r_lidar0_sensor (deg)</th>"
            "<th>stdev position along lidar0 x y z (mm)</th><th>stdev orientation about the sensor's x y z (deg)</th><th>noise sigma</th></tr>")
    return f"<table>{head}{''.join(rows)}</table>"


def convergence_html(conv: dict) -> str:
    """The convergence block of calibration.yaml as HTML: warnings first, then every solve stage."""
    if not conv:
        return "<p>No convergence record (a seed-only or replayed result).</p>"
    warn = "".join(f"<p class='warn'>{html.escape(w)}</p>" for w in conv.get("warnings", ()))
    ok = "<p>Every solve converged.</p>" if conv.get("converged") else ""
    rows = "".join(f"<tr><td>{html.escape(str(r.get('stage')))}</td><td>{r.get('iterations')}</td>"
                   f"<td>{'yes' if r.get('converged') else '<b>no</b>'}</td><td>{html.escape(str(r.get('reason')))}</td></tr>"
                   for r in conv.get("stages", ()))
    rounds = conv.get("rounds")
    extra = "" if not rounds else (f"<p>Rounds: {rounds.get('count')} of at most {rounds.get('max')}"
                                   f" ({html.escape(str(rounds.get('reason')))}).</p>")
    return (warn + ok + extra + "<table><tr><th>stage</th><th>iterations</th><th>converged</th><th>why it stopped</th></tr>"
            + rows + "</table>")


def _rejections(result: Result) -> str:
    if not result.rejected:
        return "<p>Nothing was rejected.</p>"
    counts = Counter((r.stage, r.reason) for r in result.rejected)
    summary = "".join(f"<tr><td>{html.escape(st)}</td><td>{html.escape(re)}</td><td>{n}</td></tr>"
                      for (st, re), n in counts.most_common())
    rows = []
    for r in result.rejected[:500]:
        sensor = "–" if r.sensor is None else html.escape(result.problem.sensors[r.sensor].topic)
        snap = "–" if r.snapshot is None else html.escape(result.problem.snapshot_label(r.snapshot))
        rows.append(f"<tr><td>{snap}</td><td>{sensor}</td><td>{html.escape(r.stage)}</td><td>{html.escape(r.reason)}</td></tr>")
    more = f"<p>… and {len(result.rejected) - 500} more (all in calibration.yaml).</p>" if len(result.rejected) > 500 else ""
    return (f"<table><tr><th>stage</th><th>reason</th><th>count</th></tr>{summary}</table>"
            f"<details><summary>every rejection ({len(result.rejected)})</summary><table>"
            f"<tr><th>snapshot</th><th>sensor</th><th>stage</th><th>reason</th></tr>{''.join(rows)}</table>{more}</details>")


_CSS = """body{font-family:sans-serif;max-width:1200px;margin:2em auto;color:#222}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #bbb;padding:3px 8px;font-size:90%;text-align:left}
th{background:#eee}img{max-width:100%;border:1px solid #ddd}.howto{background:#f4f8ff;padding:.5em 1em;border-left:4px solid #58f}
code{background:#f3f3f3}.warn{background:#fff3f0;padding:.5em 1em;border-left:4px solid #e43}"""


def _snapshot(result: Result, k) -> str:
    """'snapshot 7 (pose007.bag @... s)', or '-' when there is none."""
    return "snapshot -" if k is None else html.escape(result.problem.snapshot_label(int(k)))


def _consistency(result: Result) -> str:
    """The self-consistency verdict (backend/consistency.py) as a paragraph and tables."""
    v = result.stats.get("consistency")
    if not v:
        return "<p>No consistency checks were run.</p>"
    snaps = v.get("snapshots", {})
    parts = [f"<p>Verdict: <b>{'self-consistent' if v.get('passed') else 'NOT self-consistent'}</b> "
             f"({v.get('n_checks', 0)} checks, refused below p = {_fmt(v.get('p_limit'))}). "
             f"Worst leave-one-snapshot-out: {_snapshot(result, snaps.get('worst'))}, {_fmt(snaps.get('worst_sigma'))} sigma "
             f"({html.escape(str(snaps.get('worst_direction', '-')))}); largest single-snapshot share of the "
             f"information: {_fmt(snaps.get('max_leverage'))}.</p>"]
    for why in [*v.get("failures", []), *v.get("unverifiable", [])]:
        parts.append(f"<p><b>Failed:</b> {html.escape(why)}</p>")
    if v.get("pairs"):
        rows = "".join(f"<tr><td>{html.escape(k)}</td><td>{x['shared_snapshots']}</td><td>{_fmt(x['sigma'])}</td>"
                       f"<td>{x['dof']}</td><td>{html.escape(x['direction'])}</td></tr>" for k, x in v["pairs"].items())
        parts.append("<table><tr><th>sensor pair</th><th>shared boards</th><th>disagreement (sigma)</th><th>dof</th>"
                     f"<th>dominant direction</th></tr>{rows}</table>")
    if v.get("unchecked_pairs"):
        parts.append("<p>Pairs no other data checks (every path between them uses the same boards): "
                     + ", ".join(html.escape(x) for x in v["unchecked_pairs"]) + ".</p>")
    rows = "".join(f"<tr><td>{html.escape(t)}</td><td>{html.escape(w['weakest_translation'])}</td>"
                   f"<td>{_fmt(w['weakest_translation_stdev_mm'])}</td><td>{html.escape(w['weakest_rotation'])}</td>"
                   f"<td>{_fmt(w['weakest_rotation_stdev_deg'])}</td></tr>" for t, w in v.get("weakest", {}).items())
    parts.append("<table><tr><th>sensor</th><th>weakest translation</th><th>1-sigma (mm)</th><th>weakest rotation</th>"
                 f"<th>1-sigma (deg)</th></tr>{rows}</table>")
    for why in v.get("unverified", [])[:5]:
        parts.append(f"<p>Unverified: {html.escape(why)}</p>")
    parts.append("<p class='howto'>Each check splits the data in two independent parts (one snapshot against the "
                 "others; the boards two sensors saw together against the rest) and asks whether both give the same "
                 "poses within their uncertainty. A disagreement of many sigma means a wrong board association, a "
                 "sensor that moved, or a model error; clcgraph then refuses to write a result. 'Unverified' names "
                 "directions that a single snapshot determines, so no check could see an error there.</p>")
    return "\n".join(parts)


def report_html(result: Result, plots: dict[str, Path], *, title: str = "clcgraph calibration") -> str:
    """The HTML text; ``plots`` maps PNG file names (relative to the report) to paths."""
    rms, noise = result.rms, result.noise
    used = int(np.sum(np.all(np.isfinite(np.asarray(result.rt_lidar0_board, float).reshape(-1, 6)), axis=1)))
    parts = [
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f"<p>clcgraph {__version__}. Reference frame: lidar0 = <code>{html.escape(result.problem.sensors[result.problem.reference].topic)}</code>. "
        f"Snapshots used: {used} of {result.problem.n_snapshots}.</p>",
        f"<p>{html.escape(_board_line(result.problem.board))}</p>",
        "<h2>Poses</h2>", _pose_table(result),
        "<p class='howto'>Poses are <code>rt_lidar0_sensor</code>: the sensor's position and orientation (Rodrigues "
        "vector, in degrees) in the lidar0 frame. The stdevs are 1-sigma marginals computed with the re-estimated "
        "noise; a stdev of several mm or a tenth of a degree or more means the capture did not constrain that sensor "
        "well (see the sector and coverage plots).</p>",
        "<h2>Fit</h2><table><tr><th>RMS normalized</th><th>RMS LIDAR (m)</th><th>RMS camera (px)</th>"
        "<th>noise sigma LIDAR (m)</th><th>noise sigma camera (px)</th></tr>"
        f"<tr><td>{_fmt(rms.get('normalized'))}</td><td>{_fmt(rms.get('lidar_m'))}</td><td>{_fmt(rms.get('camera_px'))}</td>"
        f"<td>{_fmt(noise.get('lidar_m'))}</td><td>{_fmt(noise.get('camera_px'))}</td></tr></table>",
        "<p class='howto'>The normalized RMS should be near 1 once the noise is re-estimated. A LIDAR RMS well above "
        "the LIDAR's range noise (typically 1–3 cm) or a camera RMS above ~1 px points at bad data.</p>",
        "<h2>Convergence</h2>", convergence_html(result.stats.get("convergence") or {}),
        "<h2>Consistency</h2>", _consistency(result),
        "<h2>Rejections</h2>", _rejections(result),
    ]
    for name, how in HOWTO.items():
        if name not in plots:
            continue
        parts.append(f"<h2>{html.escape(name[:-4].replace('-', ' '))}</h2>")
        parts.append(f"<p class='howto'>{html.escape(how)}</p>")
        parts.append(f"<img src='{html.escape(name)}' alt='{html.escape(name)}'>")
    parts.append("</body></html>")
    return "\n".join(parts)


def write_report(result: Result, out_dir, *, title: str = "clcgraph calibration") -> Path:
    """Draw every plot into ``out_dir`` and write ``out_dir/report.html`` referencing them; the one
    report entry point of both methods (a targetless result: report_targetless.py)."""
    if result.method == "targetless":
        from .report_targetless import write_targetless_report

        return write_targetless_report(result, out_dir, title=title.replace("calibration", "targetless calibration"))
    from .plots import plot_all

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    plots = plot_all(result, out_dir)
    path = out_dir / "report.html"
    path.write_text(report_html(result, plots, title=title))
    return path
