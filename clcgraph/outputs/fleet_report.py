"""The fleet summary as a table (fleet.csv) and one self-contained page (fleet.html, plot inlined).

Both read only the plain summary dict that `clcgraph fleet` writes as fleet.yaml
(clcgraph.fleet: per vehicle ``status``, ``error``, ``time_s``, ``sensors`` and the
comparisons ``previous`` / ``nominal`` of clcgraph.comparison's ``to_dict``).

SYNOPSIS
    text = fleet_csv(summary); html = fleet_html(summary)
"""

from __future__ import annotations

import base64
import csv
import html
import io

import numpy as np

CSV_COLUMNS = ("vehicle", "status", "error", "time_s", "sensor", "x_m", "y_m", "z_m", "sigma_orientation_deg",
               "sigma_position_mm", "previous_status", "previous_rotation_deg", "previous_translation_mm",
               "previous_p_value", "nominal_status", "nominal_rotation_deg", "nominal_translation_mm")


def _change(c: dict | None, topic: str) -> dict:
    for s in (c or {}).get("sensors", ()):
        if s["topic"] == topic:
            return s
    return {}


def _norm(v) -> float | None:
    return None if v is None else float(np.linalg.norm(v))


def _rows(summary: dict):
    """(vehicle row, sensor dict or None, change vs previous, change vs nominal) per vehicle x sensor."""
    for v in summary["vehicles"]:
        if v["status"] != "ok" or not v["sensors"]:
            yield v, None, {}, {}
            continue
        for s in v["sensors"]:
            yield v, s, _change(v.get("previous"), s["topic"]), _change(v.get("nominal"), s["topic"])


def fleet_csv(summary: dict) -> str:
    """One row per vehicle and sensor (one row with the error for a failed vehicle); sigmas the largest
    per-axis 1-sigma; changes as rotation angle and translation norm."""
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(CSV_COLUMNS)

    def num(x, fmt):
        return "" if x is None else format(x, fmt)

    for v, s, prev, nom in _rows(summary):
        if s is None:
            w.writerow([v["id"], v["status"], v.get("error") or "", num(v.get("time_s"), ".3f")] + [""] * 13)
            continue
        rt = s["rt_lidar0_sensor"]
        sd_r, sd_p = s.get("stdev_orientation_deg"), s.get("stdev_position_mm")
        w.writerow([v["id"], v["status"], "", num(v.get("time_s"), ".3f"), s["topic"], *(f"{x:.6f}" for x in rt[3:]),
                    num(None if sd_r is None else max(sd_r), ".5f"), num(None if sd_p is None else max(sd_p), ".4f"),
                    prev.get("status", ""), num(prev.get("rotation_deg"), ".5f"),
                    num(_norm(prev.get("translation_mm")), ".4f"), num(prev.get("p_value"), ".3g"),
                    nom.get("status", ""), num(nom.get("rotation_deg"), ".5f"), num(_norm(nom.get("translation_mm")), ".4f")])
    return out.getvalue()


def drift_png(summary: dict) -> bytes | None:
    """Bars per vehicle and sensor: rotation [deg] and translation [mm] since the previous calibration
    (vs /tf_static where a vehicle has no previous), moved ones in red. None if nothing to draw."""
    from .plots import subplots

    bars = []  # (label, rotation, translation, moved, against)
    for v, s, prev, nom in _rows(summary):
        if s is None:
            continue
        c, against = (prev, "previous") if prev else (nom, "tf_static")
        if c.get("rotation_deg") is None:
            continue
        bars.append((f"{v['id']}\n{s['topic']}", c["rotation_deg"], _norm(c["translation_mm"]),
                     c["status"] == "moved", against))
    if not bars:
        return None
    fig, axs = subplots(2, 1, figsize=(max(6.0, 0.6 * len(bars) + 2), 6), sharex=True, layout="constrained")
    x = np.arange(len(bars))
    colors = ["C3" if b[3] else ("C0" if b[4] == "previous" else "0.6") for b in bars]
    axs[0].bar(x, [b[1] for b in bars], color=colors)
    axs[0].set_ylabel("rotation [deg]")
    axs[0].set_title("drift per vehicle and sensor\nred: moved; blue: since previous; grey: vs /tf_static", fontsize=9)
    axs[1].bar(x, [b[2] for b in bars], color=colors)
    axs[1].set_ylabel("translation [mm]")
    axs[1].set_xticks(x, [b[0] for b in bars], rotation=60, ha="right", fontsize=7)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return buf.getvalue()


def fleet_html(summary: dict) -> str:
    """The whole summary on one page, the drift plot inlined (no other file needed)."""
    e = html.escape
    c = summary["counts"]
    head = (f"<p>{c['ok']} of {c['vehicles']} vehicles calibrated, {c['failed']} failed. Moved since their previous "
            f"calibration (chi-square test against both covariances): "
            f"<b>{e(', '.join(summary['changed_since_previous']) or 'none')}</b>. "
            f"Off their /tf_static by more than the thresholds: {e(', '.join(summary['off_nominal']) or 'none')}.</p>")
    trs = []
    for v, s, prev, nom in _rows(summary):
        t = v.get("time_s")
        cells = [v["id"], v["status"] + (" (kept)" if v.get("resumed") else ""), "-" if t is None else f"{t:.1f}"]
        if s is None:
            cells += [v.get("error") or "", "", "", "", ""]
        else:
            sd_r, sd_p = s.get("stdev_orientation_deg"), s.get("stdev_position_mm")
            cells += [s["topic"], " ".join(f"{x:+.4f}" for x in s["rt_lidar0_sensor"][3:]),
                      "-" if sd_r is None else f"{max(sd_p):.2f} mm, {max(sd_r):.4f} deg",
                      prev.get("verdict", "-" if not v.get("previous") else v["previous"].get("error", "-")),
                      nom.get("verdict", "-" if not v.get("nominal") else v["nominal"].get("error", "-"))]
        style = ' style="background:#fdd"' if v["status"] != "ok" or prev.get("status") == "moved" else ""
        trs.append(f"<tr{style}>" + "".join(f"<td>{e(str(x))}</td>" for x in cells) + "</tr>")
    png = drift_png(summary)
    img = "" if png is None else f'<h2>drift</h2><img alt="drift" src="data:image/png;base64,{base64.b64encode(png).decode()}">'
    return ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>clcgraph fleet</title></head><body>"
            f"<h1>clcgraph fleet</h1><p>manifest: {e(summary['manifest'])}</p>{head}"
            "<table border=1 cellspacing=0 cellpadding=3><tr><th>vehicle</th><th>status</th><th>time [s]</th>"
            "<th>sensor / error</th><th>position in lidar0 [m]</th><th>largest 1-sigma</th><th>since previous</th>"
            "<th>vs /tf_static</th></tr>" + "".join(trs) + f"</table>{img}</body></html>\n")
