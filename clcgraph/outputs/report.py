"""report.html: one self-contained page (figures embedded as PNG data URIs, nothing else needed)
that lets a person see whether the calibration is right, not only self-consistent.

At the top, the verdicts: self-consistency, convergence, the LIDAR board points against each
camera's own board, image coverage, how far each sensor moved from its nominal pose. Then the
run's record (bags with sizes, camera models, the call, the settings, the version), the tables,
and the figures, each after a paragraph saying how to read it: LIDAR points on every camera's
image (solved beside nominal /tf_static), overlapping clouds before / after, per-sensor residuals,
image coverage, and the solve's diagnostics.

SYNOPSIS
    path = write_report(result, "out/", title="rig 17", inputs=report_inputs)   # out/report.html
"""

from __future__ import annotations

import base64
import contextlib
import html
import io
import logging
from collections import Counter
from pathlib import Path

import numpy as np

from .. import __version__, cameras
from ..geometry import RPY_LABEL, R_from_r, compose_rt, invert_rt, pose_stdevs, rpy_deg_from_R, rpy_deg_from_rt, transform
from ..types import Result
from . import evidence as ev

log = logging.getLogger(__name__)

HOWTO = {
    "lidar-on-camera": "Every LIDAR's points (the whole scan, coloured by range) moved into the camera with the "
    "extrinsics and projected through its lens model, on the camera's own image. The dashed outline is the board's "
    "edge fitted to the corners the camera detected (no extrinsics involved). Right extrinsics put the board's "
    "points inside it, reaching its edges, and the walls' and the ground's points on the walls and the ground; "
    "a shift or rotation shows as a row of points spilling past one edge of the board. The caption gives the "
    "spill (how far past the outline the third-farthest point lies: one or two edge returns hit the board's rim), "
    "in px and in sigmas of the calibration's own uncertainty (about 3 or less is right).",
    "clouds-before-after.png": "The LIDARs' clouds of one snapshot in the lidar0 frame, cropped to the board and "
    "what is around it, with the nominal /tf_static extrinsics (top row, when the bag has them) and the solved "
    "ones. Each LIDAR has its colour; where they overlap, the colours must coincide: one wall, one board. The "
    "right column shows the board edge-on (distance from the solved board plane, in mm): calibrated clouds form "
    "one line a few mm thick (the range noise).",
    "camera-residuals-and-coverage.png": "Each camera's reprojection errors (observed minus predicted corner) as "
    "arrows over the image, scaled up (the factor is in the title), over the convex hull of every corner it detected "
    "(shaded) and the image's thirds (dotted). The arrows should point every which way with no pattern; arrows "
    "growing toward the edges or swirling mean the lens model does not fit (re-calibrate the intrinsics); all "
    "arrows of one board pointing one way mean that board moved or was seen at another time. Coverage rule: a "
    "camera whose corners' hull covers less than 30 % of the image, or leaves a third of it (rows or columns) "
    "empty, is flagged red and warned about at the top: only one band of its image constrains its pose.",
    "lidar-residuals.png": "Each LIDAR's range residuals against the point's range and against its ring (elevation "
    "angle). Mean and RMS per bin should be flat: the mean at zero, the RMS at the LIDAR's noise. A trend with "
    "range is a range scale error; a ring whose mean is off the others has a wrong elevation angle in the LIDAR's "
    "own calibration.",
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
    "coverage.png": "Where each LIDAR saw the board (board centres from above, in its own frame; the cameras' "
    "coverage is drawn with their residuals above). Boards spread over the field of view constrain the pose; "
    "clustered boards leave it weak.",
}


def _board_line(board) -> str:
    ox, oy = board.pattern_offset_m
    thick = (f"{board.thickness_m * 1e3:g} mm thick" if board.thickness_m is not None else
             f"thickness not stated ({board.back_m * 1e3:g} mm assumed where a LIDAR sees its back)")
    return (f"Board: {board.corners_x} x {board.corners_y} inner corners, {board.square_m * 1e3:g} mm squares, "
            f"{board.width_m * 1e3:g} x {board.height_m * 1e3:g} mm (width x height), pattern centre offset "
            f"({ox * 1e3:g}, {oy * 1e3:g}) mm from the board's centre, {thick}.")


def _fmt(v, f="{:.3g}"):
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "–"
    return f.format(v)


def pose_table(result: Result, *, extra: dict | None = None) -> str:
    """The poses of both reports, in the people's format (geometry.RPY_LABEL, as the CLI's table and the
    README): position and roll, pitch, yaw of every sensor in lidar0, the per-axis 1-sigmas (position
    along lidar0's axes, orientation about the sensor's own), then the base-frame poses when known.
    ``extra``: {column heading: [one cell per sensor]} (the noise sigmas, the frames registered)."""
    extra = extra or {}
    p = result.problem
    rows = []
    for i, s in enumerate(p.sensors):
        rt = np.asarray(result.rt_lidar0_sensor[i], float)
        ref = i == p.reference
        sd_rot, sd_pos = pose_stdevs(rt, result.covariance_block(i))
        cells = [i, html.escape(s.topic) + (" (reference)" if ref else ""), s.kind,
                 " ".join(f"{x:+.4f}" for x in rt[3:]), " ".join(f"{x:+.3f}" for x in rpy_deg_from_rt(rt)),
                 "–" if ref else " ".join(f"{x:.2f}" for x in sd_pos * 1e3),
                 "–" if ref else " ".join(f"{x:.3f}" for x in np.degrees(sd_rot)),
                 *(html.escape(str(col[i])) for col in extra.values())]
        rows.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    for t, T in result.T_base_sensor.items():
        T = np.asarray(T, float)
        cells = ["", f"{html.escape(str(result.base_frame))} &lt;- {html.escape(t)}", "base", " ".join(f"{x:+.4f}" for x in T[:3, 3]),
                 " ".join(f"{x:+.3f}" for x in rpy_deg_from_R(T[:3, :3])), "ground plane", "", *([""] * len(extra))]
        rows.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    head = ["#", "sensor", "kind", "x, y, z [m] in lidar0", html.escape(RPY_LABEL),
            "1-sigma position along lidar0 x, y, z [mm]", "1-sigma orientation about the sensor's own x, y, z [deg]",
            *map(html.escape, extra)]
    return ("<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>" + "".join(rows) + "</table>"
            "<p class='howto'>Each sensor's pose in the lidar0 frame (<code>T_lidar0_sensor</code>: x_lidar0 = R x_sensor "
            "+ t). The rotation R = Rz(yaw) Ry(pitch) Rx(roll): roll about x, then pitch about y, then yaw about z, "
            "all three about lidar0's fixed axes (the URDF's rpy); calibration.yaml holds the same rotation as a "
            "Rodrigues vector in radians. The 1-sigmas are per axis: the position's along lidar0's x, y, z; the "
            "orientation's about the sensor's own x, y, z (a small rotation of the sensor). A sigma of several mm or "
            "a tenth of a degree or more means the data did not constrain that sensor well.</p>")


def _noise_cells(result: Result) -> list[str]:
    per = result.noise.get("per_sensor") or {}
    return ["–" if i not in per else (f"{per[i] * 1e3:.1f} mm" if s.kind == "lidar" else f"{per[i]:.3f} px")
            for i, s in enumerate(result.problem.sensors)]


def banner(items) -> str:
    """The verdicts at the top of both reports, failures first, then the checks passed, then what is for
    information: ``items`` of (state, what, word, detail), state False (failed: red), True (passed: green)
    or None, e.g. (True, "Self-consistency", "passed", "12 checks ..."). ``detail`` is HTML."""
    cls = {True: "verdict ok", False: "verdict warn", None: "verdict"}
    order = sorted(items, key=lambda x: {False: 0, True: 1, None: 2}[x[0]])
    return "\n".join(f"<div class='{cls[st]}'>{html.escape(what, quote=False)}: <b>{html.escape(word, quote=False)}</b>"
                     f"{': ' + detail if detail else ''}</div>" for st, what, word, detail in order)


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


def _uncertainty_check(result: Result) -> str:
    """The jackknife block: model vs leave-one-snapshot-out sigma per principal axis."""
    jk = result.jackknife
    if not jk:
        return "<p>Too few snapshots for a leave-one-snapshot-out check.</p>"
    rows = []
    for i, s in jk["sensors"].items():
        big = s["largest_influence"]
        for what, unit, f in (("position", "mm", "{:.2f}"), ("orientation", "deg", "{:.3f}")):
            m, j, r = s[f"{what}_model_{unit}"], s[f"{what}_jackknife_{unit}"], s[f"{what}_ratio"]
            lo, hi = np.asarray(s[f"{what}_ratio_expected_95"]).T  # the ratio's range if the model is right
            flag = " style='background:#fdd'" if np.any((np.asarray(r) > hi) | (np.asarray(r) < lo)) else ""
            up = np.asarray(s.get(f"{what}_raised", np.ones(3)))
            rows.append(f"<tr{flag}><td>{html.escape(result.problem.sensors[i].topic)}</td><td>{what} ({unit})</td>"
                        f"<td>{' / '.join(f.format(x) for x in m)}</td><td>{' / '.join(f.format(x) for x in j)}</td>"
                        f"<td>{' / '.join(f'{x:.2f}' for x in r)}</td>"
                        f"<td>{' / '.join(f'{a:.2f}-{b:.2f}' for a, b in zip(lo, hi))}</td>"
                        f"<td>{' / '.join('-' if x == 1 else f'x{x:.2f}' for x in up)}</td>"
                        + (f"<td rowspan=2>snapshot {big['snapshot']}: {big['position_mm']:.1f} mm, "
                           f"{big['orientation_deg']:.3f} deg</td>" if what == "position" else "") + "</tr>")
    w = jk["largest_influence"]
    need = jk["indispensable_snapshots"]
    return ("<table><tr><th>sensor</th><th></th><th>model sigma (3 principal axes)</th><th>jackknife sigma</th>"
            "<th>ratio</th><th>ratio expected if the model is right (95 %)</th><th>sigma raised</th>"
            "<th>largest single-snapshot move</th></tr>" + "".join(rows) + "</table>"
            f"<p>Snapshot {w['snapshot']} moves <code>{html.escape(result.problem.sensors[w['sensor']].topic)}</code> most: "
            f"{w['position_mm']:.1f} mm, {w['orientation_deg']:.3f} deg."
            + (f" Without snapshot(s) {', '.join(map(str, need))} some sensor is not determined." if need else "")
            + "</p>" + _uncertainty_terms(result))


def _uncertainty_terms(result: Result) -> str:
    """What the sigmas include (backend/consider.py): each term's share of the final variance."""
    terms = result.stats.get("uncertainty_terms") or {}
    cams = [s.topic for s in result.problem.sensors if s.is_camera
            and not {f"intrinsics {s.topic}", f"focal length {s.topic}"} & set(terms.get("included", ()))]
    note = (f"<p>Camera intrinsics uncertainty is not included for {', '.join(html.escape(c) for c in cams)} "
            "(its camera model carries no optimization_inputs; state its focal length's error with "
            "<code>solve.camera_focal_scale_sigma</code>: where every board stands at one distance, 1 % of it "
            "is ~1 % of that distance along the camera's line of sight).</p>") if cams else ""
    if not terms:
        return note
    names = terms["included"]
    rows = "".join(f"<tr><td>{html.escape(topic)}</td><td>{what}</td>"
                   + "".join(f"<td>{100 * sh[what][n]:.0f} %</td>" for n in names) + "</tr>"
                   for topic, sh in terms["variance_share"].items() for what in ("position", "orientation"))
    return ("<p>Share of each sensor's final variance (trace) per term; the jackknife above judges the first "
            "(errors fixed for the whole capture bias every snapshot alike, so it cannot see the others).</p>"
            "<table><tr><th>sensor</th><th></th>" + "".join(f"<th>{html.escape(n)}</th>" for n in names)
            + "</tr>" + rows + "</table>" + note)


_CSS = """body{font-family:sans-serif;max-width:1200px;margin:2em auto;color:#222}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #bbb;padding:3px 8px;font-size:90%;text-align:left}
th{background:#eee}img{max-width:100%;border:1px solid #ddd}.howto{background:#f4f8ff;padding:.5em 1em;border-left:4px solid #58f}
code{background:#f3f3f3}.warn{background:#fff3f0;padding:.5em 1em;border-left:4px solid #e43}
.ok{background:#f0fff3;padding:.5em 1em;border-left:4px solid #2a4}
.verdict{font-size:130%;padding:.6em 1em;margin:.5em 0}
pre{background:#f6f6f6;padding:.5em;white-space:pre-wrap;word-break:break-all;font-size:85%}"""

# section headings of the figures (file-like names stay the figures' alt texts)
_HEADINGS = {
    "lidar-on-camera": "LIDAR points on the camera images",
    "clouds-before-after.png": "Overlapping LIDAR clouds, before and after",
    "camera-residuals-and-coverage.png": "Camera reprojection errors and image coverage",
    "lidar-residuals.png": "LIDAR residuals against range and ring",
    "residuals-histogram.png": "Residual histograms",
    "residuals-per-snapshot.png": "Residuals per snapshot",
    "geometry.png": "Sensor and board geometry",
    "sectors.png": "Uncertainty and observations per sector",
    "coverage.png": "Board coverage per LIDAR",
}


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
    for x in v.get("left_out", []):  # the verdict above is of the rest (backend/solve.calibrate)
        parts.append(f"<p><b>Left out</b> (the verdict is of the other snapshots): {html.escape(x['why'])}</p>")
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
    if v.get("components_not_assumed"):  # backend/solve.py: in the sigmas, not in these checks
        level = v.get("components_assumed_from", {})
        names = ", ".join(f"{html.escape(k)} ({_fmt(x)})" for k, x in v["components_not_assumed"].items())
        parts.append("<p>Per-observation noise components in the sigmas but not assumed by these checks (their "
                     f"likelihood-ratio statistic under {_fmt(level.get('lr_statistic'))}, p = {_fmt(level.get('p'))}; "
                     f"the checks' sigmas and the table above are without them): {names}.</p>")
    parts.append("<p class='howto'>Each check splits the data in two independent parts (one snapshot against the "
                 "others; the boards two sensors saw together against the rest) and asks whether both give the same "
                 "poses within their uncertainty. A disagreement of many sigma means a wrong board association, a "
                 "sensor that moved, or a model error; the result is then written with this verdict (or refused, with <code>solve.refuse_inconsistent: true</code>). 'Unverified' names "
                 "directions that a single snapshot determines, so no check could see an error there.</p>")
    return "\n".join(parts)


# ---------------------------------------------------------------- figures

def _png(fig_fn, *args, **kwargs) -> bytes:
    buf = io.BytesIO()
    fig_fn(*args, buf, **kwargs)
    return buf.getvalue()


def embed_image(name: str, data: bytes) -> str:
    """An <img> holding the PNG or JPEG itself (a data URI): the page needs no other file."""
    mime = "image/jpeg" if data[:3] == b"\xff\xd8\xff" else "image/png"
    return (f"<img src='data:{mime};base64,{base64.b64encode(data).decode('ascii')}' alt='{html.escape(name)}' "
            f"title='{html.escape(name)}'>")


def _snapshot_name(k, inputs) -> str:
    """'snapshot 7 (pose007.bag)' (the bag's name, and its period for a continuous bag) when known."""
    src = inputs.sources.get(k) if inputs is not None else None
    if not src:
        return f"snapshot {k}"
    bag, _, period = src.partition(" period ")
    return f"snapshot {k} ({Path(bag).name}{' period ' + period if period else ''})"


def _max_ray_angle(cam) -> float:
    """The widest angle from the optical axis the image shows (its border, unprojected)."""
    w, h = cam.imagersize
    t = np.linspace(0, 1, 9)
    border = np.r_[np.c_[t * (w - 1), 0 * t], np.c_[t * (w - 1), 0 * t + h - 1], np.c_[0 * t, t * (h - 1)],
                   np.c_[0 * t + w - 1, t * (h - 1)]]
    v = cameras.unproject(border, cam.lensmodel, cam.intrinsics)
    return float(np.max(np.arccos(np.clip(v[:, 2] / np.linalg.norm(v, axis=1), -1, 1))))


def _into_camera(result, i_cam, rts, clouds: dict) -> tuple[np.ndarray, np.ndarray]:
    """LIDAR clouds {sensor: (N,3) own frame} -> (q (M,2) px inside the image, LIDAR range (M,))."""
    cam = result.problem.sensors[i_cam]
    w, h = cam.imagersize
    limit = _max_ray_angle(cam) * 1.02  # beyond it, a lens polynomial can fold points back into the image
    qs, rs = [np.zeros((0, 2))], [np.zeros(0)]
    for i, pts in clouds.items():
        if i not in rts:
            continue
        P = transform(compose_rt(invert_rt(np.asarray(rts[i_cam], float)), np.asarray(rts[i], float)), pts)
        ang = np.arccos(np.clip(P[:, 2] / np.maximum(np.linalg.norm(P, axis=1), 1e-9), -1, 1))
        keep = (P[:, 2] > 0.2) & (ang < limit)
        q = cameras.project(P[keep], cam.lensmodel, cam.intrinsics)
        inside = np.all((q >= -0.5) & (q <= [w - 0.5, h - 0.5]), axis=1)
        qs.append(q[inside])
        rs.append(np.linalg.norm(pts[keep][inside], axis=1))
    return np.concatenate(qs), np.concatenate(rs)


def _all_rts(result, inputs) -> dict:
    """{"solved": {sensor: rt}, "nominal": {...}} (nominal only with /tf_static poses; lidar0 is its own)."""
    solved = {i: np.asarray(rt, float) for i, rt in enumerate(result.rt_lidar0_sensor)}
    out = {"solved": solved}
    if inputs is not None and inputs.rt_nominal:
        out["nominal /tf_static"] = {result.problem.reference: np.zeros(6),
                                     **{i: np.asarray(rt, float) for i, rt in inputs.rt_nominal.items()}}
    return out


def _scan_clouds(result, inputs, k, *, max_points: int = 15000) -> dict:
    """{LIDAR sensor: (N,3) own frame} at snapshot k: the whole scans when the report has them, else the
    board points the LIDARs found."""
    p = result.problem
    snap = inputs.snapshots.get(k) if inputs is not None else None
    out = {}
    for i, s in enumerate(p.sensors):
        if not s.is_lidar:
            continue
        if snap is not None and s.topic in snap.scans:
            sc = snap.scans[s.topic]
            pts = np.asarray(sc.points, float)[np.asarray(sc.valid, bool)]
            pts = pts[np.all(np.isfinite(pts), axis=1)]
            out[i] = pts[:: max(1, len(pts) // max_points)]
        else:
            obs = [o for o in p.lidar_observations if o.sensor == i and o.snapshot == k]
            if obs:
                out[i] = np.asarray(obs[0].points, float)
    return out


def _lidar_on_camera_pictures(result, inputs) -> list[tuple[str, dict, bytes]]:
    """Per camera: (name, view, jpeg) of the LIDAR points on its image, solved beside nominal; ``view``
    holds what its caption says but what the checks found (``_lidar_on_camera_caption``)."""
    from . import plots  # matplotlib only when drawing

    p = result.problem
    rts = _all_rts(result, inputs)
    out = []
    for i_cam, cam in enumerate(p.sensors):
        if not cam.is_camera or cam.imagersize is None:
            continue
        obs = {o.snapshot: o for o in p.camera_observations if o.sensor == i_cam}
        if not obs:
            continue
        with_image = [k for k in obs if inputs is not None and k in inputs.snapshots
                      and cam.topic in inputs.snapshots[k].images]
        lidars_at = Counter(o.snapshot for o in p.lidar_observations)
        k = max(with_image or list(obs), key=lambda k: (lidars_at.get(k, 0), k in with_image))
        image = inputs.snapshots[k].images[cam.topic].pixels if k in with_image else None
        outline = ev.board_outline_px(ev.board_homography(obs[k].corners_px, p.board, cam), p.board, cam)
        clouds = _scan_clouds(result, inputs, k)
        panels = []
        for label, rt in rts.items():
            q, r = _into_camera(result, i_cam, rt, clouds)
            panels.append({"q": q, "range": r, "outline": outline})
        v = np.concatenate([x["range"] for x in panels])
        norm = (float(np.percentile(v, 1)), float(np.percentile(v, 99))) if len(v) else (0.0, 1.0)
        view = {"camera": i_cam, "snapshot": k, "labels": list(rts), "whole_scans": image is not None, "norm": norm}
        out.append((f"lidar-on-camera-{i_cam}.jpg", view,
                    _png(plots.plot_lidar_on_image, panels, cam.imagersize, image=image, norm=norm)))
    return out


def _lidar_on_camera_caption(result, inputs, view: dict, checks: dict) -> str:
    """The caption of a ``_lidar_on_camera_pictures`` picture: the camera, the snapshot, and how far the
    LIDAR board points spill past the board's outline with each set of extrinsics (``checks``)."""
    i_cam, k, labels, norm = view["camera"], view["snapshot"], view["labels"], view["norm"]
    says = []
    for side, label in zip(("left", "right"), labels):
        rows = [x for x in checks.get(label, ()) if x["camera"] == i_cam and x["snapshot"] == k]
        spill = "" if not rows else (f": board points spill {max(x['spill_px'] for x in rows):.1f} px past the outline"
                                     + (f" ({max(x['spill_sigma'] for x in rows):.1f} sigma)" if label == "solved" else ""))
        says.append(f"{side if len(labels) > 1 else 'the'} picture: {label} extrinsics{spill}")
    what = "whole scans" if view["whole_scans"] else "board points only (the report has no image of it)"
    return (f"{i_cam}: {result.problem.sensors[i_cam].topic}, {_snapshot_name(k, inputs)}, {what}. " + "; ".join(says)
            + f". Colour: LIDAR range, {norm[0]:.1f} m (blue) to {norm[1]:.1f} m (red), the bar at the bottom.")


def _clouds_figure(result, inputs) -> tuple[str, bytes] | None:
    """The overlapping LIDAR clouds of the snapshot most LIDARs saw the board in, before and after."""
    from . import plots

    p = result.problem
    lidars = [i for i, s in enumerate(p.sensors) if s.is_lidar]
    if len(lidars) < 2:
        return None
    rtb = np.asarray(result.rt_lidar0_board, float).reshape(-1, 6)
    n_at = Counter(o.snapshot for o in p.lidar_observations)
    cands = [k for k in n_at if n_at[k] >= 2 and np.all(np.isfinite(rtb[k]))]
    if not cands:
        return None
    k = max(cands, key=lambda k: (inputs is not None and k in inputs.snapshots, n_at[k]))
    clouds = _scan_clouds(result, inputs, k)
    R = R_from_r(rtb[k][:3])
    centre = transform(rtb[k], p.board.centre()[None])[0]
    states = {}
    for label, rt in _all_rts(result, inputs).items():
        states[f"{'before' if label != 'solved' else 'after'} ({label})"] = {
            f"{i}: {p.sensors[i].topic}": transform(rt[i], pts) for i, pts in clouds.items() if i in rt}
    states = dict(sorted(states.items(), key=lambda x: not x[0].startswith("before")))  # before first
    half = max(p.board.width_m, p.board.height_m) + 1.5
    box = (centre - [half, half, half * 0.6], centre + [half, half, half * 0.6])
    caption = f"{_snapshot_name(k, inputs)}, {2 * half:.1f} m around the board"
    return caption, _png(plots.plot_cloud_overlap, states, box=box,
                         board={"centre": centre, "normal": R[:, 2], "along": R[:, 0], "up": R[:, 1],
                                "half_size": (p.board.width_m / 2, p.board.height_m / 2)})


# Rough CPU cost of each picture relative to the others (the 24-pose bench capture): the drawing
# processes take the costly ones first, so they finish together. Only the schedule depends on it.
_COST = {"sectors.png": 9, "clouds-before-after.png": 6, "camera-residuals-and-coverage.png": 5,
         "lidar-residuals.png": 4, "lidar-on-camera": 4, "residuals-per-snapshot.png": 3}


def _figure_jobs(result: Result, inputs) -> list[tuple[str, object]]:
    """[(name, job)] of every figure, in report order; a job returns [(name, caption, png)] (none when
    there is nothing to draw), the LIDAR points on the camera images' a view for the caption (their
    checks are made beside the drawing: ``_lidar_on_camera_caption``)."""
    from . import plots

    p = result.problem

    def clouds():
        c = _clouds_figure(result, inputs)
        return [("clouds-before-after.png", c[0], c[1])] if c else []

    def camera_residuals():
        vec = ev.camera_residual_vectors(result)
        cams = [{**c, **vec.get(c["sensor"], {"corners": np.concatenate([np.reshape(x, (-1, 2)) for x in c["corners"]]),
                                              "residuals": None})} for c in _coverage(result)]
        return [("camera-residuals-and-coverage.png", "", _png(plots.plot_camera_residuals_and_coverage, cams))] if cams else []

    def lidar_residuals():
        geo = ev.lidar_residual_geometry(result)
        return [("lidar-residuals.png", "", _png(plots.plot_lidar_residuals, [
            {"title": f"{i}: {p.sensors[i].topic}", **v} for i, v in sorted(geo.items())]))] if geo else []

    jobs = [("lidar-on-camera", lambda: _lidar_on_camera_pictures(result, inputs)),
            ("clouds-before-after.png", clouds), ("camera-residuals-and-coverage.png", camera_residuals),
            ("lidar-residuals.png", lidar_residuals)]
    jobs += [(name, lambda name=name, fn=fn: [(name, "", _png(fn, result))]) for name, fn in plots.PLOTS.items()]
    return jobs


# The figures drawn from the estimate alone (poses, board poses, noise sigmas, residuals, rejections):
# `clcgraph solve` starts them while the solve still computes the covariance (start_estimate_figures).
# The sectors need the covariance (and the captions of the LIDAR points on the images the checks made with it).
ESTIMATE_FIGURES = ("lidar-on-camera", "clouds-before-after.png", "camera-residuals-and-coverage.png",
                    "lidar-residuals.png", "residuals-histogram.png", "residuals-per-snapshot.png", "geometry.png",
                    "coverage.png")


def start_figures(result: Result, inputs, *, names=None):
    """An ``outputs.drawing.Drawing`` of the report's figures (``names``: only these), its second
    process drawing from now on."""
    from .drawing import Drawing

    jobs = [(n, job) for n, job in _figure_jobs(result, inputs) if names is None or n in names]
    order = sorted(range(len(jobs)), key=lambda k: -_COST.get(jobs[k][0], 1))
    return Drawing([job for _, job in jobs], names=[name for name, _ in jobs], order=order)


def start_estimate_figures(estimate: Result, inputs):
    """``start_figures`` of the ESTIMATE_FIGURES, from the solve's estimate (``backend.solve.calibrate``'s
    ``on_estimate``): they are the same pictures as the final result's. Give it to ``report_writer``
    (``early``); close it if the solve fails."""
    return start_figures(estimate, inputs, names=ESTIMATE_FIGURES)


def _figures(result: Result, inputs, checks: dict, first=None, drawing=None, early=None) -> list[tuple[str, str, bytes]]:
    """[(name, caption, png)] of every figure, in report order; a failing one is logged and left out.
    The figures are drawn by two processes (``drawing``: ``start_figures``, started earlier; else here),
    ``early`` (``start_estimate_figures``) the ones it drew from the estimate. ``first``: work of this
    process that the pictures do not need, done while the other process already draws; ``checks``
    (what the LIDAR points on the camera images show) may be filled by it: their captions are
    written after it."""
    order = [name for name, _ in _figure_jobs(result, inputs)]
    with contextlib.ExitStack() as stack:
        if early is not None:
            stack.enter_context(early)
        d = stack.enter_context(drawing if drawing is not None else start_figures(
            result, inputs, names=None if early is None else [n for n in order if n not in early.names]))
        if first is not None:
            first()
        drawn = {}
        for x in (early, d):  # the estimate's first: this process takes what is left of them
            if x is not None:
                drawn.update(zip(x.names, x.results()))
    out = []
    for name, caption, png in (f for n in order for f in drawn.get(n, [])):
        if isinstance(caption, dict):  # a LIDAR-on-camera picture's view
            try:
                caption = _lidar_on_camera_caption(result, inputs, caption, checks)
            except Exception:  # a diagnostic figure must never lose the calibration
                log.exception("could not write the caption of %s", name)
                caption = ""
        out.append((name, caption, png))
    return out


def _coverage(result) -> list[dict]:
    p = result.problem
    cams = []
    for i, s in enumerate(p.sensors):
        if s.is_camera and s.imagersize is not None:
            corners = [o.corners_px for o in p.camera_observations if o.sensor == i]
            cams.append({"title": f"{i}: {s.topic}", "imagersize": s.imagersize, "corners": corners,
                         "coverage": ev.image_coverage(corners, s.imagersize), "sensor": i})
    return cams


# ---------------------------------------------------------------- verdicts and record


def consistency_verdict(result: Result) -> tuple:
    """The self-consistency verdict (backend/consistency.py) as one banner item (see ``banner``)."""
    v = result.stats.get("consistency") or {}
    if not v:
        return (False, "Self-consistency", "not checked", "")
    if v.get("passed"):
        left = v.get("left_out", [])
        return (True, "Self-consistency", "passed", f"{v.get('n_checks', 0)} checks: every snapshot and every sensor "
                "pair agrees with the rest within its uncertainty"
                + (f" (after leaving out {', '.join(_snapshot(result, x['snapshot']) for x in left)}, which disagreed)"
                   if left else ""))
    return (False, "Self-consistency", "FAILED", html.escape((v.get("failures") or v.get("unverifiable") or ["?"])[0]))


def convergence_verdict(conv: dict, what: str = "Solve") -> tuple | None:
    """A banner item when a solve did not converge (None when it did, or when nothing was recorded)."""
    if not conv or conv.get("converged"):
        return None
    return (False, what, "NOT CONVERGED", html.escape("; ".join(conv.get("warnings", ()))))


def _jackknife_verdict(result: Result):
    """The banner line of the leave-one-snapshot-out check (None without one): the axes along which
    it rejected the model and the sigma was raised to its spread."""
    jk = result.jackknife
    if not jk:
        return None
    raised = [(result.problem.sensors[i].topic, what, float(f)) for i, s in jk["sensors"].items()
              for what in ("position", "orientation") for f in np.asarray(s.get(f"{what}_raised", ())) if f > 1]
    if not raised:
        return (True, "Sigmas against the leave-one-snapshot-out spread", "confirmed",
                f"along every principal axis the jackknife over {jk['n_snapshots']} snapshots is within or below the "
                "range the noise model expects of it")
    top = max(raised, key=lambda x: x[2])
    return (None, "Sigmas against the leave-one-snapshot-out spread", f"raised on {len(raised)} axes",
            f"the noise model was short along {len(raised)} principal axes; the sigmas there are the jackknife's "
            f"(up to x{top[2]:.2f}: {html.escape(top[0])} {top[1]}), see the Uncertainty check")


def _verdicts(result: Result, inputs, checks: dict, coverage: list) -> str:
    """The banner at the top: what says the calibration is right (or not), worst first."""
    items = [consistency_verdict(result), convergence_verdict(result.stats.get("convergence") or {})]
    rows = checks.get("solved", [])
    if rows:
        worst = max(rows, key=lambda x: x["spill_sigma"])
        p = result.problem
        nominal = checks.get("nominal /tf_static", [])
        nom = (f" With the nominal /tf_static extrinsics the spill is up to {max(x['spill_px'] for x in nominal):.1f} px."
               if nominal else "")
        ok = worst["spill_sigma"] <= 4.0
        items.append((ok, "LIDAR board points on the cameras' boards", "on the board" if ok else "OFF THE BOARD",
                      f"over {len(rows)} (camera, LIDAR, snapshot) views, the largest spill past the board's outline (a "
                      f"view's third-farthest point: one or two rim returns do not count) is {worst['spill_px']:.2f} px = "
                      f"{worst['spill_sigma']:.1f} sigma ({html.escape(p.sensors[worst['lidar']].topic)} in "
                      f"{html.escape(p.sensors[worst['camera']].topic)}, {html.escape(_snapshot_name(worst['snapshot'], inputs))}; "
                      f"more than 4 sigma is flagged).{nom}"))
    items.append(_jackknife_verdict(result))
    for c in coverage:
        if c["coverage"].get("warning"):
            items.append((False, f"Image coverage of {c['title']}", "too little", html.escape(c["coverage"]["warning"])))
    if inputs is not None and inputs.rt_nominal:
        moved = ev.moved_from_nominal(result, inputs.rt_nominal)
        if moved:
            far = max(moved, key=lambda m: m["rotation_deg"])
            items.append((None, f"Moved from the nominal pose ({inputs.nominal_source})",
                          f"up to {far['rotation_deg']:.2f} deg", f"{html.escape(far['topic'])}; and up to "
                          f"{max(m['translation_mm'] for m in moved):.0f} mm; see the table below"))
    return banner([x for x in items if x is not None])


def _moved_table(result, inputs) -> str:
    if inputs is None or not inputs.rt_nominal:
        return "<p>No nominal poses (the bags have no /tf_static linking the sensors' frames to lidar0's).</p>"
    rows = "".join(f"<tr><td>{m['sensor']}</td><td>{html.escape(m['topic'])}</td><td>{m['rotation_deg']:.3f}</td>"
                   f"<td>{m['sigma_deg']:.3f}</td><td>{m['translation_mm']:.1f}</td><td>{m['sigma_mm']:.1f}</td></tr>"
                   for m in ev.moved_from_nominal(result, inputs.rt_nominal))
    return (f"<p>Nominal poses from {html.escape(inputs.nominal_source)}. Rotation: the angle of R_nominal^T R_solved; "
            "translation: the distance between the two origins; 1-sigma: the root-sum-square of the solved pose's "
            "per-axis sigmas. A difference of many sigma is the CAD / tf_static being off (or the sensor moved), "
            "not the calibration.</p><table><tr><th>#</th><th>sensor</th><th>rotation (deg)</th><th>1-sigma (deg)</th>"
            f"<th>translation (mm)</th><th>1-sigma (mm)</th></tr>{rows}</table>")


def inputs_html(result, inputs) -> str:
    """The run's record of both reports: the version, the sensors (cameras with their models), the call,
    the bags with their sizes, the effective settings."""
    p = result.problem
    cams = "".join(f"<tr><td>{i}</td><td>{html.escape(s.topic)}</td><td>{html.escape(str(s.lensmodel))}</td>"
                   f"<td>{s.imagersize[0]}x{s.imagersize[1]}</td><td>{html.escape(dict(inputs.models).get(s.topic, '–') if inputs else '–')}</td></tr>"
                   for i, s in enumerate(p.sensors) if s.is_camera and s.imagersize is not None)
    parts = [f"<p>clcgraph {__version__}. Sensors: "
             + ", ".join(f"{i}: <code>{html.escape(s.topic)}</code> ({s.kind})" for i, s in enumerate(p.sensors)) + ".</p>"]
    if cams:
        parts.append("<table><tr><th>#</th><th>camera</th><th>lens model</th><th>image</th><th>.cameramodel</th></tr>"
                     f"{cams}</table>")
    if inputs is None:
        parts.append("<p>No record of the bags and the call (this report was written from a Result alone).</p>")
        return "\n".join(parts)
    if inputs.command:
        parts.append(f"<p>Call:</p><pre>{html.escape(inputs.command)}</pre>")
    total = sum(n for _, n in inputs.bags)
    bags = "".join(f"<tr><td>{html.escape(b)}</td><td>{n / 1e6:.1f}</td></tr>" for b, n in inputs.bags)
    parts.append(f"<details><summary>{len(inputs.bags)} bag(s), {total / 1e6:.1f} MB</summary><table>"
                 f"<tr><th>bag</th><th>MB</th></tr>{bags}</table></details>")
    if inputs.config_yaml:
        parts.append(f"<details><summary>effective settings (config.resolved.yaml)</summary>"
                     f"<pre>{html.escape(inputs.config_yaml)}</pre></details>")
    return "\n".join(parts)


def jk_n(result: Result) -> int:
    return int(result.jackknife.get("n_snapshots", 0))


def report_html(result: Result, *, title: str = "clcgraph calibration", inputs: "ev.ReportInputs | None" = None,
                drawing=None, early=None) -> str:
    """The whole self-contained HTML text (figures embedded); ``drawing``: ``start_figures(result, inputs)``
    started earlier (the pictures drawn while the caller did other work), without the ``early`` ones
    (``start_estimate_figures``, started during the solve) when given."""
    rms, noise = result.rms, result.noise
    used = int(np.sum(np.all(np.isfinite(np.asarray(result.rt_lidar0_board, float).reshape(-1, 6)), axis=1)))
    checks: dict = {}

    def board_checks():  # while the other process draws
        checks["solved"] = ev.lidar_board_in_images(result)
        rts = _all_rts(result, inputs)
        if "nominal /tf_static" in rts:
            nom = np.array([rts["nominal /tf_static"].get(i, rt) for i, rt in enumerate(result.rt_lidar0_sensor)])
            checks["nominal /tf_static"] = ev.lidar_board_in_images(result, rt_lidar0_sensor=nom)

    figures = _figures(result, inputs, checks, first=board_checks, drawing=drawing, early=early)
    coverage = _coverage(result)
    for c in coverage:
        if c["coverage"].get("warning"):
            log.warning("camera %s: %s", c["title"], c["coverage"]["warning"])
    parts = [
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        _verdicts(result, inputs, checks, coverage),
        f"<p>Reference frame: lidar0 = <code>{html.escape(result.problem.sensors[result.problem.reference].topic)}</code>. "
        f"Snapshots used: {used} of {result.problem.n_snapshots}.</p>",
        f"<p>{html.escape(_board_line(result.problem.board))}</p>",
        "<h2>Poses</h2>", pose_table(result, extra={"noise sigma": _noise_cells(result)}),
        "<h2>Moved from the nominal pose</h2>", _moved_table(result, inputs),
        "<h2>Inputs and settings</h2>", inputs_html(result, inputs),
        "<h2>Fit</h2><table><tr><th>RMS normalized</th><th>RMS LIDAR (m)</th><th>RMS camera (px)</th>"
        "<th>noise sigma LIDAR (m)</th><th>noise sigma camera (px)</th></tr>"
        f"<tr><td>{_fmt(rms.get('normalized'))}</td><td>{_fmt(rms.get('lidar_m'))}</td><td>{_fmt(rms.get('camera_px'))}</td>"
        f"<td>{_fmt(noise.get('lidar_m'))}</td><td>{_fmt(noise.get('camera_px'))}</td></tr></table>",
        "<p class='howto'>The normalized RMS should be near 1 once the noise is re-estimated. A LIDAR RMS well above "
        "the LIDAR's range noise (typically 1–3 cm) or a camera RMS above ~1 px points at bad data.</p>",
    ]
    shown = set()
    for name, caption, png in figures:
        key = "lidar-on-camera" if name.startswith("lidar-on-camera") else name
        if key not in shown:
            parts.append(f"<h2>{html.escape(_HEADINGS.get(key, key))}</h2>")
            parts.append(f"<p class='howto'>{html.escape(HOWTO.get(key, ''))}</p>")
            shown.add(key)
        if caption:
            parts.append(f"<p>{html.escape(caption)}</p>")
        parts.append(embed_image(name, png))
    parts += ["<h2>Convergence</h2>", convergence_html(result.stats.get("convergence") or {}),
              "<h2>Consistency</h2>", _consistency(result),
              "<h2>Uncertainty check</h2>", _uncertainty_check(result),
              "<p class='howto'>Each snapshot is left out in turn and the poses re-solved; the spread of those answers "
              "(jackknife) estimates the uncertainty without trusting the noise model. A ratio jackknife/model inside the "
              f"range the model expects of it (from the same linearization; with {jk_n(result)} snapshots, and wider along "
              "an axis few boards carry) says the sigmas can be trusted; above it, the data have errors the model does not "
              "know of, and the reported sigma along that axis is raised to the jackknife's (by ratio / expected: "
              "'sigma raised'). A snapshot that moves a sensor by much more than its sigma is the first to re-take or exclude.</p>",
              "<h2>Rejections</h2>", _rejections(result), "</body></html>"]
    return "\n".join(parts)


def write_report(result: Result, out_dir, *, title: str = "clcgraph calibration",
                 inputs: "ev.ReportInputs | None" = None) -> Path:
    """Write ``out_dir/report.html``: one file, figures embedded, nothing else needed to open it;
    the one report entry point of both methods (a targetless result: report_targetless.py)."""
    with report_writer(result, title=title, inputs=inputs) as write:
        return write(out_dir)


@contextlib.contextmanager
def report_writer(result: Result, *, title: str = "clcgraph calibration", inputs: "ev.ReportInputs | None" = None,
                  early=None):
    """``write_report`` in two steps: on entry the figures start drawing in a second process
    (target-based); the call it yields, ``write(out_dir) -> path``, writes the report. Work the
    caller does in between (the other result files) overlaps the drawing; leaving the block
    without writing stops it. ``early``: the figures of the estimate, started during the solve
    (``start_estimate_figures``): only the others start here.

    SYNOPSIS
        with report_writer(result, inputs=inputs) as write:
            ...                       # e.g. calibration.yaml, problem.npz
            write("out/")             # out/report.html
    """
    if result.method == "targetless":
        from .report_targetless import start_figures as start_targetless_figures, write_targetless_report

        with start_targetless_figures(result) as drawing:
            yield lambda out_dir: write_targetless_report(result, out_dir, inputs=inputs, drawing=drawing,
                                                          title=title.replace("calibration", "targetless calibration"))
        return

    def write(out_dir) -> Path:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        path = out_dir / "report.html"
        path.write_text(report_html(result, title=title, inputs=inputs, drawing=drawing, early=early))
        return path

    from ..determinism import single_threaded_blas

    names = None if early is None else [n for n, _ in _figure_jobs(result, inputs) if n not in early.names]
    # BLAS on one thread (the drawing process too): the checks' small products gain nothing from a second
    # one, whose waiting costs up to 3x their CPU time on a loaded machine (and the same bytes, always)
    with single_threaded_blas(), early if early is not None else contextlib.nullcontext(), \
            start_figures(result, inputs, names=names) as drawing:
        yield write
