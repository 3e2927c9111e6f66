"""The text tables the CLI prints, for both methods (formatting lives here, not in cli/).

SYNOPSIS
    print(summary_table(result))            # pose, 1-sigma and observations per sensor
    print(replay_lines(result))             # `clcgraph replay`: one line a sensor, the noise
    print(bag_table(info, clouds))          # `clcgraph show-bag`; segmentation_line, detection_line, ...
    print(truth_table(errors, "truth.yaml"))  # `clcgraph demo`: errors against the simulator's truth
    print(comparison_table(c))              # `clcgraph compare`; fleet_table(summary): `clcgraph fleet`
"""

from __future__ import annotations

import numpy as np

from ..geometry import RPY_LABEL, pose_stdevs, rpy_deg_from_R, rpy_deg_from_rt
from ..types import Rejected, Result


def _columns(rows) -> list[str]:
    widths = [max(len(r[k]) for r in rows) for k in range(len(rows[0]))]
    return ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]


def _observations(result: Result) -> list[str]:
    """Per sensor: its board observations (target) or calibration frames (targetless)."""
    p = result.problem
    if result.method == "targetless":
        graph = result.targetless.graph
        return [str(graph.get(s.topic, {}).get("frames", "-")) for s in p.sensors]
    nobs = np.zeros(len(p.sensors), int)
    for o in [*p.lidar_observations, *p.camera_observations]:
        nobs[o.sensor] += 1
    return [str(n) for n in nobs]


def summary_table(result: Result) -> str:
    """The final table `clcgraph solve` and `clcgraph targetless` print: pose, per-axis 1-sigmas
    and observations per sensor, then base_link poses (if any), then the fit's verdicts and the
    unused snapshots by bag. Rotations as geometry.RPY_LABEL says."""
    targetless = result.method == "targetless"
    rows = [("sensor", "kind", "x, y, z [m]", RPY_LABEL, "1-sigma x, y, z [mm]", "1-sigma about own x, y, z [deg]",
             "frames" if targetless else "obs")]
    p = result.problem
    for i, (s, n) in enumerate(zip(p.sensors, _observations(result))):
        rt = np.asarray(result.rt_lidar0_sensor[i], float)
        sd_rot, sd_pos = pose_stdevs(rt, result.covariance_block(i))
        ref = i == p.reference
        rows.append((s.topic, s.kind, " ".join(f"{v:+.4f}" for v in rt[3:]),
                     " ".join(f"{v:+.3f}" for v in rpy_deg_from_rt(rt)),
                     "reference" if ref else " ".join(f"{v:.2f}" for v in 1e3 * sd_pos),
                     "" if ref else " ".join(f"{v:.3f}" for v in np.degrees(sd_rot)), n))
    for t, T in result.T_base_sensor.items():
        T = np.asarray(T, float)
        rows.append((f"{result.base_frame} <- {t}", "lidar", " ".join(f"{v:+.4f}" for v in T[:3, 3]),
                     " ".join(f"{v:+.3f}" for v in rpy_deg_from_R(T[:3, :3])), "ground plane", "", "-"))
    lines = _columns(rows)
    lines.append(f"(x, y, z and their sigmas along {'the mapping LIDAR' if targetless else 'lidar0'}'s axes; "
                 "rotation sigmas about the sensor's own axes)")
    if targetless:
        return "\n".join(lines + list(result.targetless.notes))
    rms, noise = result.rms, result.noise
    lines.append(f"RMS: normalized {rms.get('normalized', float('nan')):.3f}, LIDAR {1e3 * rms.get('lidar_m', float('nan')):.1f} mm, "
                 f"camera {rms.get('camera_px', float('nan')):.3f} px; re-estimated noise: LIDAR "
                 f"{1e3 * noise.get('lidar_m', float('nan')):.1f} mm, camera {noise.get('camera_px', float('nan')):.3f} px")
    used = np.all(np.isfinite(np.asarray(result.rt_lidar0_board, float).reshape(-1, 6)), axis=1)
    lines.append(f"{int(used.sum())} of {p.n_snapshots} snapshots used; {len(result.rejected)} rejections (see calibration.yaml)")
    lines += _unused_line(result, used)
    conv = result.stats.get("convergence") or {}
    if conv and not conv.get("converged"):
        lines.append("NOT CONVERGED: " + "; ".join(conv.get("warnings", ())))
    verdict = result.stats.get("consistency") or {}
    if verdict.get("passed") is False:  # written anyway (solve.refuse_inconsistent is off)
        why = (verdict.get("failures") or verdict.get("unverifiable") or ["?"])[0]
        lines.append(f"NOT SELF-CONSISTENT (see calibration.yaml consistency:): {why}")
    return "\n".join(lines)


def _unused_line(result: Result, used: np.ndarray) -> list[str]:
    """'unused: snapshot 3 (pose003.bag @3.000 s): why; ...' for the first 10 unused snapshots."""
    p = result.problem
    why: dict[int, str] = {}
    for r in sorted(result.rejected, key=lambda r: r.sensor is not None):  # snapshot-level reasons first
        if r.snapshot is not None:
            why.setdefault(int(r.snapshot), r.reason if r.sensor is None else f"{p.sensors[r.sensor].topic}: {r.reason}")
    unused = [k for k in range(p.n_snapshots) if not used[k]]
    if not unused:
        return []
    more = f"; ... {len(unused) - 10} more in calibration.yaml" if len(unused) > 10 else ""
    return ["unused: " + "; ".join(f"{p.snapshot_label(k)}: {why.get(k, 'no board pose')}" for k in unused[:10]) + more]


def replay_lines(result: Result) -> str:
    """`clcgraph replay`: rt_lidar0_sensor and its stdev, one line a sensor; the noise; rejections."""
    out = []
    for i, s in enumerate(result.problem.sensors):
        sd = result.stdev_rt(i) if np.all(np.isfinite(result.covariance_rt)) else np.full(6, np.nan)
        out.append(f"{s.topic}: rt_lidar0_sensor {np.array2string(result.rt_lidar0_sensor[i], precision=6, max_line_width=10**4)}"
                   f"  stdev {np.array2string(sd, precision=6, max_line_width=10**4)}")
    def value(v):  # a sigma, or {component: sigma} (observation_effects)
        return ", ".join(f"{c} {x:.4g}" for c, x in v.items()) if isinstance(v, dict) else f"{v:.4g}"

    for k, v in result.noise.items():
        if isinstance(v, dict):  # per sensor: {sensor index: sigma or {component: sigma}}
            if v:
                out.append(f"noise {k}: " + "; ".join(f"{result.problem.sensor_name(int(i))} {value(s)}"
                                                     for i, s in v.items()))
        else:
            out.append(f"noise {k}: {v:.4g}")
    out.append(f"{len(result.rejected)} rejected")
    return "\n".join(out)


def truth_table(errors: list[dict], truth_path) -> str:
    """`clcgraph demo`: rotation and translation errors against the simulator's truth, with 1-sigmas."""
    # errors as one angle and one distance; their sigmas root-sum-square over the three axes
    out = [f"\nagainst the simulator's truth ({truth_path}):",
           f"{'sensor':34s} {'rotation error [deg]':>21s} {'1-sigma rss':>12s} {'translation error [mm]':>23s} "
           f"{'1-sigma rss':>12s}"]
    for e in errors:
        out.append(f"{e['topic']:34s} {e['rotation_deg']:21.3f} {e['sigma_deg']:12.3f} {e['translation_mm']:23.1f} "
                   f"{e['sigma_mm']:12.1f}")
    return "\n".join(out)


# ---------------------------------------------------------------- looking at bags

_DATATYPES = {1: "int8", 2: "uint8", 3: "int16", 4: "uint16", 5: "int32", 6: "uint32", 7: "float32", 8: "float64"}


def bag_table(info, clouds: dict) -> str:
    """`clcgraph show-bag`: a bag's topics (type, count, time span), then each PointCloud2
    topic's layout from its first message (``clouds``: topic -> raw message); a blank line last."""
    out = [f"{info.path}: {info.message_count} messages, {info.duration_s:.3f} s"]
    rows = [("topic", "type", "count", "first [s]", "last [s]", "span [s]")]
    for t in info.topics:
        seen = t.first_ns is not None
        rows.append((t.topic, t.msgtype, str(t.count), f"{t.first_ns * 1e-9:.3f}" if seen else "-",
                     f"{t.last_ns * 1e-9:.3f}" if seen else "-", f"{(t.last_ns - t.first_ns) * 1e-9:.3f}" if seen else "-"))
    out += ["  " + line for line in _columns(rows)]
    for topic, m in clouds.items():
        out.append(f"  {topic}: PointCloud2 {m.height} x {m.width}, point_step {m.point_step}, "
                   f"row_step {m.row_step}, {'big' if m.is_bigendian else 'little'} endian, frame {m.header.frame_id}")
        for fld in m.fields:
            dt = _DATATYPES.get(int(fld.datatype), f"datatype {fld.datatype}")
            out.append(f"      {fld.name:<14} offset {fld.offset:>3}  {dt}" + (f" x{fld.count}" if fld.count != 1 else ""))
    return "\n".join(out) + "\n"


def segmentation_line(scan, r, bag: str = "") -> str:
    """`clcgraph segment`: one scan's board (points, distance, normal, RMS) or why not, after its
    bag's name and stamp."""
    t = f"{bag} {scan.stamp_ns * 1e-9:.6f}".lstrip()
    if isinstance(r, Rejected):
        return f"{t} rejected: {r.reason}"
    return (f"{t} board: {len(r.indices)} points at {np.linalg.norm(r.points.mean(axis=0)):.2f} m, normal "
            f"{np.round(r.plane[:3], 3).tolist()}, RMS {r.rms_m * 1e3:.1f} mm")


def detection_line(image, r, bag: str = "") -> str:
    """`clcgraph detect`: one image's corners found, or why not, after its bag's name and stamp."""
    t = f"{bag} {image.stamp_ns * 1e-9:.6f}".lstrip()
    return f"{t} rejected: {r.reason}" if isinstance(r, Rejected) else f"{t} found {len(r)} corners"


def found_count(found: list, what: str) -> str:
    """'3/5 scans with a board': how many of (item, result, ...) tuples found something."""
    return f"{sum(not isinstance(f[1], Rejected) for f in found)}/{len(found)} {what}"


def mcap_lines(info: dict) -> str:
    """`clcgraph show-aligned --mcap`: where /tf_static's base came from, what went into the file."""
    snaps = info["snapshots"]
    return (f"/tf_static: {info['base_source']}\n"
            f"wrote {info['path']}: {len(snaps)} snapshot(s) ({', '.join(s['bag'] for s in snaps[:5])}"
            f"{', ...' if len(snaps) > 5 else ''}), /tf_static with {len(info['tf'])} transforms")



def comparison_table(c) -> str:
    """`clcgraph compare`: A, B, the reference, then per sensor rotation, axis, translation, Mahalanobis, p, verdict."""
    rows = [("sensor", "rotation [deg]", "axis (ref)", "translation [mm] (ref)", "Mahalanobis", "p", "verdict")]
    for s in c.sensors:
        rows.append((s.topic, "-" if s.rotation_deg is None else f"{s.rotation_deg:.3f}",
                     "-" if s.axis_ref is None else " ".join(f"{x:+.2f}" for x in s.axis_ref),
                     "-" if s.translation_mm is None else " ".join(f"{x:+.1f}" for x in s.translation_mm),
                     "-" if s.mahalanobis is None else f"{s.mahalanobis:.2f}",
                     "-" if s.p_value is None else f"{s.p_value:.2g}", s.verdict))
    widths = [max(len(r[k]) for r in rows) for k in range(len(rows[0]))]
    lines = [f"A: {c.a}", f"B: {c.b}", f"reference: {c.reference}"] + ([f"units' errors: {c.unit_errors}"] if c.unit_errors else [])
    lines += ["  ".join(cell.ljust(w) for cell, w in zip(r, widths)).rstrip() for r in rows]
    return "\n".join(lines)


def fleet_table(summary: dict) -> str:
    """`clcgraph fleet`: one line per vehicle (status, time, changes since previous and against /tf_static), then the counts."""
    rows = [("vehicle", "status", "time [s]", "since previous", "vs /tf_static")]

    def words(c):
        if not c:
            return "-"
        if "error" in c:
            return "not compared: " + c["error"][:60]
        moved = [s for s in c["sensors"] if s["status"] == "moved"]
        return "; ".join(f"{s['topic']} {s['verdict']}" for s in moved) if moved else "same"

    for r in summary["vehicles"]:
        t = r.get("time_s")
        rows.append((r["id"], r["status"] + (" (kept)" if r.get("resumed") else ""), "-" if t is None else f"{t:.1f}",
                     words(r.get("previous")) if r["status"] == "ok" else r["error"],
                     words(r.get("nominal")) if r["status"] == "ok" else ""))
    widths = [max(len(r[k]) for r in rows) for k in range(len(rows[0]) - 1)] + [0]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    c = summary["counts"]
    lines.append(f"{c['ok']} of {c['vehicles']} vehicles calibrated, {c['failed']} failed; "
                 f"moved since previous: {', '.join(summary['changed_since_previous']) or 'none'}")
    return "\n".join(lines)
