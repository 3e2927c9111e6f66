"""Targetless calibration: map with one LIDAR, register the others, fit the ground for base_link.

SYNOPSIS
    res = calibrate_targetless(["drive.bag"], mapping_topic="/top/points",
                               calibration_topics=["/side/points"], base_frame="base_link")
    res.T_lidar0_sensor["/side/points"]      # (4,4); res.covariance_rt["/side/points"] (6,6)
    write_targetless_outputs(res, "out/")    # calibration.yaml, ros_static_tf.txt, report.html + PNGs

    res = calibrate_targetless_scans(scans_by_topic, mapping_topic=..., calibration_topics=[...],
                                     T_base_sensor_guess={...})   # in-memory variant (tests, sim)

Stages (timed in ``res.timings_s``): mapping (deskew + scan-to-map GICP), calibration
frames, selection, registration (ensemble + per-frame refinement), graph (GTSAM fusion
and Marginals), ground (base_link roll/pitch/z).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import geometry as geo
from ..config import Config
from ..errors import DegenerateError, InputError
from ..outputs.atomic import atomic_dir
from ..outputs.report import convergence_html
from ..outputs.results import COORDINATES, stdev_fields
from .calibration_frames import make_calibration_frames, nearest_to_keyframes
from .graph import fuse
from .mapping import build_map
from .registration import deskew_sources, ensemble, keyframe_edges, prepare_frames, refine_per_frame, score
from .selection import adapt_to_drive, select_frames

log = logging.getLogger(__name__)


@dataclass
class TargetlessResult:
    mapping_topic: str
    T_lidar0_sensor: dict  # topic -> (4,4) (the mapping topic maps to identity)
    covariance_rt: dict  # topic -> (6,6) Var(rt_lidar0_sensor)
    T_lidar0_sensor_guess: dict
    frames: dict = field(default_factory=dict)  # topic -> frame_id
    T_base_sensor: dict = field(default_factory=dict)  # topic -> (4,4) base_link results
    base_frame: str | None = None
    map_result: object = None
    per_frame: dict = field(default_factory=dict)  # topic -> list of dicts (score, frame, errors)
    candidates: dict = field(default_factory=dict)  # topic -> ensemble candidates
    graph: dict = field(default_factory=dict)  # topic -> size of the final graph and its noise scales
    convergence: dict = field(default_factory=dict)  # topic -> how its graph solves stopped (graph.Estimate)
    frame_data: dict = field(default_factory=dict, repr=False)  # topic -> registration FrameData (report pictures)
    frame_plan: dict = field(default_factory=dict)  # skipped keyframes, frame spacing, drive length (selection)
    timings_s: dict = field(default_factory=dict)
    peak_rss_mb: dict = field(default_factory=dict)  # stage -> process peak RSS after it
    notes: list = field(default_factory=list)

    def rt_lidar0_sensor(self, topic: str) -> np.ndarray:
        return geo.rt_from_T(self.T_lidar0_sensor[topic])

    def stdev_rt(self, topic: str) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance_rt[topic]))


def _stage(timings, name, memory=None):
    """Adds the stage's wall time to ``timings``; ``memory``: the process's peak RSS (MB) after it."""
    class _T:
        def __enter__(self):
            self.t = time.perf_counter()

        def __exit__(self, *exc):
            timings[name] = timings.get(name, 0.0) + time.perf_counter() - self.t
            if memory is not None:
                import resource

                memory[name] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return _T()


def calibrate_targetless_scans(scans: dict, *, mapping_topic: str, calibration_topics, T_base_sensor_guess: dict,
                               base_frame: str | None = None, config: Config | None = None, frames: dict | None = None,
                               progress=None, counts: dict | None = None) -> TargetlessResult:
    """Calibrate from scans: ``scans[topic]`` a time-ordered list or iterable of LidarScan, read once
    (the mapping topic streams through the mapping; of a calibration topic only the scans nearest
    to keyframes are kept). ``counts``: topic -> number of scans, for the progress bar.

    T_base_sensor_guess: topic -> (4,4) initial guess (tf_static) in a common parent frame.
    """
    cfg = config or Config()
    o = cfg.targetless
    timings: dict = {}
    memory: dict = {}
    if mapping_topic not in scans:
        raise InputError(f"{mapping_topic}: no scans of the mapping topic")
    if progress is None:
        from .. import progress as _pg

        def progress(items, desc=f"mapping {mapping_topic}"):
            total = len(items) if hasattr(items, "__len__") else (counts or {}).get(mapping_topic)
            return _pg.progress(items, desc=desc, total=total, unit="scan")
    with _stage(timings, "mapping", memory):
        mp = build_map(scans[mapping_topic], o, progress=progress)
    G0 = np.asarray(T_base_sensor_guess[mapping_topic])
    res = TargetlessResult(mapping_topic, {mapping_topic: np.eye(4)}, {mapping_topic: np.zeros((6, 6))},
                           {mapping_topic: np.eye(4)}, frames=dict(frames or {}), base_frame=base_frame, map_result=mp)
    edge_cache: dict = {}  # keyframe submap registrations, shared by the calibration LIDARs
    plan = adapt_to_drive(mp, o)
    res.frame_plan = plan.as_dict()
    for topic in calibration_topics:
        with _stage(timings, "calibration frames", memory):
            kept = nearest_to_keyframes(mp, scans.get(topic, ()))
            if not kept:
                raise InputError(f"{topic}: no scans of this calibration topic")
            cfs = make_calibration_frames(mp, kept, o, skip_keyframes=plan.skip_keyframes)
        Tg = np.linalg.inv(G0) @ np.asarray(T_base_sensor_guess[topic])
        res.T_lidar0_sensor_guess[topic] = Tg
        with _stage(timings, "selection", memory):
            chosen = select_frames(cfs, mp, o, spacing_m=plan.spacing_m)
        if len(chosen) < o.lidar_calibration_min_frames:
            reasons = sorted({cf.reason for cf in cfs if cf.reason})
            raise DegenerateError(f"{topic}: {len(chosen)} usable calibration frames of {len(cfs)} "
                                  f"(< lidar_calibration_min_frames={o.lidar_calibration_min_frames}) on a "
                                  f"{plan.drive_length_m:.1f} m drive, {plan.spacing_m:.2f} m apart; "
                                  f"rejections: {'; '.join(reasons[:3]) or 'none'}")
        with _stage(timings, "registration", memory):
            fr = prepare_frames(list(progress(chosen, desc=f"dense targets {topic}")), mp, Tg, o, deskew_on=o.deskew)
            T_best, cands = ensemble(fr, Tg, o)
            deskew_sources(fr, T_best)
            meas = refine_per_frame(fr, T_best, o)
        with _stage(timings, "graph", memory):
            used = sorted({m.anchor for m in meas} | {p for m in meas for p in m.influence})
            keyframes = {p: mp.frames[mp.keyframe_ids[p]].T_map_lidar for p in used}
            edges = keyframe_edges(mp, used, o, cache=edge_cache)
            est = fuse(meas, keyframes, edges, common_mode=o.registration_common_mode,
                       min_frames=o.lidar_calibration_min_frames)
        res.graph[topic] = {"frames": len(meas), "keyframes": len(keyframes), "keyframe_edges": len(edges),
                            "noise_scale": {k: float(v) for k, v in est.scales.items()},
                            "redundancy": {k: float(v) for k, v in est.redundancy.items() if k in est.scales},
                            "common_mode": float(o.registration_common_mode)}
        res.convergence[topic] = est.convergence
        if est.convergence["warnings"]:
            log.warning("%s: the targetless graph did not converge everywhere: %s", topic,
                        "; ".join(est.convergence["warnings"]))
            res.notes.append(f"{topic}: NOT CONVERGED: " + "; ".join(est.convergence["warnings"]))
        log.info("%s: graph of %d frames, %d keyframes, %d keyframe edges; noise scales %s", topic, len(meas),
                 len(keyframes), len(edges), {k: f"{v:.3g}" for k, v in est.scales.items()})
        s_guess, s_final = score(fr, Tg, o), score(fr, est.T, o)
        T_final, cov = est.T, est.cov_rt
        if s_guess <= s_final:  # the initial guess stays a candidate
            log.warning("%s: the initial guess scores better than the registration; keeping it", topic)
            res.notes.append(f"{topic}: initial guess kept (score {s_guess:.3g} <= {s_final:.3g}); its sigmas "
                             "include the difference to the registration estimate")
            T_final = Tg
            # nothing measured the guess: it is as uncertain as it is far from the estimate (that
            # distance composed in the tangent at the guess, then in rt coordinates there)
            import gtsam

            d = np.asarray(gtsam.Pose3(Tg).localCoordinates(gtsam.Pose3(est.T)))
            J = geo.drt_dxi(geo.rt_from_T(Tg))
            cov = J @ (est.cov_xi + np.outer(d, d)) @ J.T
        res.T_lidar0_sensor[topic] = T_final
        res.covariance_rt[topic] = cov
        res.candidates[topic] = cands
        res.per_frame[topic] = [
            {"keyframe": fd.cf.keyframe_id, "stamp_ns": int(fd.cf.scan.stamp_ns), "pca": fd.cf.score,
             "score_guess": score([fd], Tg, o), "score_final": score([fd], T_final, o),
             "rt_frame": geo.rt_from_T(m.T).tolist(), **fd.cf.stats} for fd, m in zip(fr, meas)]
        res.frame_data[topic] = fr
    if base_frame is not None:
        from .ground import calibrate_base

        with _stage(timings, "ground", memory):
            T_b0, info = calibrate_base(mp, G0, o)
        for topic, T in res.T_lidar0_sensor.items():
            res.T_base_sensor[topic] = T_b0 @ T
    res.timings_s, res.peak_rss_mb = timings, memory
    return res


def calibrate_targetless(bags, *, mapping_topic: str, calibration_topics, base_frame: str | None = None,
                         config: Config | None = None, progress=None) -> TargetlessResult:
    """Read the bags (scans + /tf_static guess) and run :func:`calibrate_targetless_scans`."""
    from ..frontend.bag import frame_id, message_count, read_messages, read_tf_static

    bags = [bags] if isinstance(bags, (str, Path)) else list(bags)
    calibration_topics = list(calibration_topics)
    topics = [mapping_topic] + calibration_topics
    # each topic streams from the bags when its stage needs it: a drive is never all in memory
    scans = {t: (m.data for m in read_messages(bags, [t])) for t in topics}  # in stamp order
    counts = {t: message_count(bags, t) for t in topics}
    frames = {t: frame_id(bags[0], t) for t in topics}
    tf = read_tf_static(bags)
    parent = base_frame or frames[mapping_topic]
    guess = {}
    for t in topics:
        try:
            guess[t] = tf.lookup(parent, frames[t])
        except Exception as e:  # noqa: BLE001 - the tf tree raises its own error types
            raise InputError(f"{t}: no /tf_static transform from {parent} to {frames[t]} ({e})") from None
    return calibrate_targetless_scans(scans, mapping_topic=mapping_topic, calibration_topics=calibration_topics,
                                      T_base_sensor_guess=guess, base_frame=base_frame, config=config,
                                      frames=frames, progress=progress, counts=counts)


# ------------------------------------------------------------------ outputs

def calibration_dict(res: TargetlessResult) -> dict:
    """calibration.yaml content: the ``sensors`` shape of the target-based result plus ``base_link``.

    The covariance is over the non-reference sensors, as `clcgraph solve` writes it; each LIDAR
    is calibrated in its own graph, so the blocks between LIDARs are zero (their shared map
    errors are not modelled across LIDARs).
    """
    topics = [res.mapping_topic] + [t for t in res.T_lidar0_sensor if t != res.mapping_topic]
    n = len(topics)
    cov = np.zeros((6 * (n - 1), 6 * (n - 1)))
    sensors = []
    for i, t in enumerate(topics):
        rt = res.rt_lidar0_sensor(t)
        if i > 0:
            cov[6 * (i - 1):6 * i, 6 * (i - 1):6 * i] = 0.5 * (res.covariance_rt[t] + res.covariance_rt[t].T)
        sensors.append({"topic": t, "kind": "lidar", "rt_lidar0_sensor": rt.tolist(),
                        "T_lidar0_sensor": geo.T_from_rt(rt).tolist(), "stdev_rt": res.stdev_rt(t).tolist(),
                        **stdev_fields(*geo.pose_stdevs(rt, res.covariance_rt[t]))})
    d = {"reference": res.mapping_topic, "method": "targetless", "sensors": sensors,
         "covariance_rt_lidar0_sensor": cov.tolist(), "coordinates": COORDINATES}
    if res.base_frame is not None:
        d["base_link"] = [{"topic": t, "frame": res.base_frame, "T_base_link_sensor": np.asarray(T).tolist(),
                           "rt_base_link_sensor": geo.rt_from_T(T).tolist()} for t, T in res.T_base_sensor.items()]
    d["graph"] = res.graph
    d["calibration_frames"] = res.frame_plan  # how frames were taken from this drive
    d["convergence"] = res.convergence
    return d  # wall-clock timings go to timings.yaml: the same inputs give the same calibration.yaml


def summary_table(res: TargetlessResult) -> str:
    """The table `clcgraph targetless` prints: pose and per-axis 1-sigmas per LIDAR, then base_link
    poses. Rotations as geometry.RPY_LABEL says."""
    def rpy(T):
        return np.degrees(geo.rpy_from_R(np.asarray(T)[:3, :3]))

    rows = [("sensor", "x [m]", "y [m]", "z [m]", geo.RPY_LABEL, "1-sigma x, y, z [mm]",
             "1-sigma about own x, y, z [deg]", "frames")]
    for t, T in res.T_lidar0_sensor.items():
        sd_rot, sd_pos = geo.pose_stdevs(res.rt_lidar0_sensor(t), res.covariance_rt[t])
        ref = t == res.mapping_topic
        rows.append((t, *(f"{v:+.4f}" for v in np.asarray(T)[:3, 3]), " ".join(f"{v:+.3f}" for v in rpy(T)),
                     "reference" if ref else " ".join(f"{v:.2f}" for v in 1e3 * sd_pos),
                     "" if ref else " ".join(f"{v:.4f}" for v in np.degrees(sd_rot)),
                     str(res.graph.get(t, {}).get("frames", "-"))))
    for t, T in res.T_base_sensor.items():
        rows.append((f"{res.base_frame} <- {t}", *(f"{v:+.4f}" for v in np.asarray(T)[:3, 3]),
                     " ".join(f"{v:+.3f}" for v in rpy(T)), "ground plane", "", "-"))
    widths = [max(len(r[k]) for r in rows) for k in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    lines.append("(x, y, z and their sigmas along the mapping LIDAR's axes; rotation sigmas about the sensor's own axes)")
    return "\n".join(lines + list(res.notes))


def _static_tf_lines(res: TargetlessResult) -> str:
    lines = []
    parent_T = res.T_base_sensor if res.base_frame else res.T_lidar0_sensor
    parent = res.base_frame or res.frames.get(res.mapping_topic, res.mapping_topic.strip("/").replace("/", "_"))
    for t, T in parent_T.items():
        child = res.frames.get(t, t.strip("/").replace("/", "_"))
        if child == parent:
            continue
        x, y, z = np.asarray(T)[:3, 3]
        from scipy.spatial.transform import Rotation

        yaw, pitch, roll = Rotation.from_matrix(np.asarray(T)[:3, :3]).as_euler("ZYX")
        lines.append(f"ros2 run tf2_ros static_transform_publisher --x {x:.6f} --y {y:.6f} --z {z:.6f} "
                     f"--roll {roll:.8f} --pitch {pitch:.8f} --yaw {yaw:.8f} --frame-id {parent} --child-frame-id {child}")
    return "\n".join(lines) + "\n"


def _urdf(res: TargetlessResult) -> str:
    from scipy.spatial.transform import Rotation

    parent_T = res.T_base_sensor if res.base_frame else res.T_lidar0_sensor
    parent = res.base_frame or res.frames.get(res.mapping_topic, "lidar0")
    out = []
    for t, T in parent_T.items():
        child = res.frames.get(t, t.strip("/").replace("/", "_"))
        if child == parent:
            continue
        r, p, y = Rotation.from_matrix(np.asarray(T)[:3, :3]).as_euler("xyz")
        x = np.asarray(T)[:3, 3]
        out.append(f'<joint name="{child}_joint" type="fixed">\n  <parent link="{parent}"/>\n  <child link="{child}"/>\n'
                   f'  <origin xyz="{x[0]:.6f} {x[1]:.6f} {x[2]:.6f}" rpy="{r:.8f} {p:.8f} {y:.8f}"/>\n</joint>')
    return "\n".join(out) + "\n"


def _plots(res: TargetlessResult, d: Path, o) -> list:
    from ..outputs.plots import subplots  # Figure objects: the user's matplotlib backend is left alone

    out = []
    mp = res.map_result
    P = mp.poses()
    kf = np.array(mp.keyframe_ids)
    fig, ax = subplots(figsize=(8, 6))
    from .mapping import voxel_down

    near = [mp.frames[k].points[np.linalg.norm(mp.frames[k].points, axis=1) <= o.viz_max_range] for k in kf]
    pts = voxel_down(np.concatenate([p @ mp.frames[k].T_map_lidar[:3, :3].T + mp.frames[k].T_map_lidar[:3, 3]
                                     for p, k in zip(near, kf)]), o.mapping_viz_leaf_size)
    ax.scatter(pts[:, 0], pts[:, 1], s=0.2, c=pts[:, 2], cmap="viridis")
    ax.plot(P[:, 0, 3], P[:, 1, 3], "r-", lw=1, label="trajectory")
    ax.plot(P[kf, 0, 3], P[kf, 1, 3], "k.", label="keyframes")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("map (top view) and trajectory")
    ax.legend(loc="upper left", bbox_to_anchor=(1, 1))
    fig.savefig(d / "map_top.png", dpi=90, bbox_inches="tight")
    out.append("map_top.png")
    for topic, rows in res.per_frame.items():
        name = topic.strip("/").replace("/", "_")
        fig, ax = subplots(figsize=(7, 3.5))
        x = np.arange(len(rows))
        ax.bar(x - 0.2, [r["score_guess"] for r in rows], 0.4, label="initial guess")
        ax.bar(x + 0.2, [r["score_final"] for r in rows], 0.4, label="final")
        ax.set_xlabel("calibration frame")
        ax.set_ylabel("truncated mean sq. distance [m^2]")
        ax.set_title(f"{topic}: per-frame scores")
        ax.legend()
        fig.savefig(d / f"scores_{name}.png", dpi=90, bbox_inches="tight")
        out.append(f"scores_{name}.png")
        fds = res.frame_data.get(topic)
        if fds:
            out += _alignment_plots(res, topic, fds, d, o)
    return out


def _alignment_plots(res: TargetlessResult, topic: str, fds, d: Path, o) -> list:
    """Before/after views of one frame near the sensor (top and side), and the distances of all
    frames' points to the dense map before and after."""
    from ..outputs.plots import subplots
    from .mapping import voxel_down

    name = topic.strip("/").replace("/", "_")
    before, after = res.T_lidar0_sensor_guess[topic], res.T_lidar0_sensor[topic]
    fd = fds[len(fds) // 2]
    c = after[:3, 3]
    box = 10.0  # m around the sensor: far enough for structure, near enough to see centimetres
    tg = voxel_down(fd.target_pts, o.calibration_viz_leaf_size / 3)
    tg = tg[np.all(np.abs(tg[:, :2] - c[:2]) < box, axis=1)]
    fig, axs = subplots(2, 2, figsize=(13, 8), height_ratios=[2, 1], layout="constrained")
    for col, (T, title) in enumerate(((before, "before (tf_static)"), (after, "after"))):
        s = fd.source_pts @ T[:3, :3].T + T[:3, 3]
        s = s[np.all(np.abs(s[:, :2] - c[:2]) < box, axis=1)]
        for row, (i, j, lab) in enumerate(((0, 1, "y"), (0, 2, "z"))):
            a = axs[row, col]
            a.scatter(tg[:, i], tg[:, j], s=0.2, c="0.6", label="mapping (dense)")
            a.scatter(s[:, i], s[:, j], s=0.5, c="r", label=topic)
            a.set_aspect("equal")
            a.set_xlabel("x [m]")
            a.set_ylabel(f"{lab} [m]")
            a.set_title(f"{title}: {'top' if row == 0 else 'side'} view, {box:.0f} m around the sensor")
    axs[0, 1].legend(loc="upper left", bbox_to_anchor=(1, 1))
    fig.savefig(d / f"aligned_{name}.png", dpi=90, bbox_inches="tight")
    fig, ax = subplots(figsize=(7, 3.5))
    bins = np.linspace(0, o.calibration_eval_max_corr_distance * 3, 61)
    for T, lab, col in ((before, "before", "C0"), (after, "after", "C3")):
        dist = np.concatenate([f.kdtree.query(f.source_pts[::4] @ T[:3, :3].T + T[:3, 3])[0] for f in fds])
        ax.hist(np.minimum(dist, bins[-1]), bins, histtype="step", color=col,
                label=f"{lab}: median {1e3 * np.median(dist):.1f} mm")
    ax.set_xlabel("distance of each point to the nearest dense-map point [m] (last bin: farther)")
    ax.set_ylabel("points")
    ax.set_title(f"{topic}: all {len(fds)} calibration frames")
    ax.legend()
    fig.savefig(d / f"distances_{name}.png", dpi=90, bbox_inches="tight")
    return [f"aligned_{name}.png", f"distances_{name}.png"]


def write_targetless_outputs(res: TargetlessResult, out_dir, *, config: Config | None = None,
                             force: bool = False) -> dict:
    """Write calibration.yaml, static_tf.txt, urdf_snippet.xml, report.html (+ PNGs) atomically into out_dir
    (a previous clcgraph output there is replaced; anything else only with ``force``)."""
    import yaml

    out_dir = Path(out_dir)
    with atomic_dir(out_dir, force=force) as tmp:
        cal = calibration_dict(res)
        (tmp / "calibration.yaml").write_text(yaml.safe_dump(cal, sort_keys=False))
        (tmp / "timings.yaml").write_text(yaml.safe_dump({"timings_s": {k: float(v) for k, v in res.timings_s.items()},
                                                          "peak_rss_mb": {k: float(v) for k, v in res.peak_rss_mb.items()}},
                                                         sort_keys=False))
        (tmp / "static_tf.txt").write_text(_static_tf_lines(res))
        (tmp / "urdf_snippet.xml").write_text(_urdf(res))
        if config is not None:
            (tmp / "config.resolved.yaml").write_text(config.to_yaml())
        pngs = _plots(res, tmp, (config or Config()).targetless)
        rows = "".join(f"<tr><td>{s['topic']}</td><td>{np.round(s['rt_lidar0_sensor'], 6).tolist()}</td>"
                       f"<td>{np.round(s['stdev_position_mm'], 3).tolist()}</td>"
                       f"<td>{np.round(s['stdev_orientation_deg'], 4).tolist()}</td></tr>" for s in cal["sensors"])
        tim = "".join(f"<tr><td>{k}</td><td>{v:.2f}</td></tr>" for k, v in res.timings_s.items())
        gr = "".join(f"<tr><td>{t}</td><td>{g['frames']}</td><td>{g['keyframes']}</td><td>{g['keyframe_edges']}</td>"
                     f"<td>{g['noise_scale']['frames']:.3g}</td><td>{g['noise_scale']['keyframes']:.3g}</td>"
                     f"<td>{g['common_mode']:g}</td></tr>"
                     for t, g in res.graph.items())
        html = (f"<html><head><title>clcgraph targetless</title></head><body><h1>clcgraph targetless calibration</h1>"
                f"<p>reference: {res.mapping_topic}</p><table border=1><tr><th>topic</th><th>rt_lidar0_sensor</th>"
                f"<th>stdev position along lidar0 x y z [mm]</th><th>stdev orientation about the sensor's x y z [deg]</th></tr>{rows}</table>"
                f"<h2>final graph</h2><p>extrinsic + keyframe poses; one factor per frame, registration edges "
                f"between keyframe submaps; noise scales estimated from the residuals (x GICP Hessian^-1); the "
                f"sigmas include a bias shared by all frames (prior: 'common mode' x one frame's covariance).</p>"
                f"<table border=1><tr><th>topic</th><th>frames</th><th>keyframes</th><th>edges</th>"
                f"<th>scale frames</th><th>scale edges</th><th>common mode</th></tr>{gr}</table>"
                + "".join(f"<h2>convergence: {t}</h2>" + convergence_html(c) for t, c in res.convergence.items())
                + f"<h2>timings [s]</h2><table border=1>{tim}</table>"
                + "".join(f'<h2>{p}</h2><img src="{p}">' for p in pngs)
                + "".join(f"<p>{n}</p>" for n in res.notes) + "</body></html>")
        (tmp / "report.html").write_text(html)
    return {"calibration": out_dir / "calibration.yaml", "report": out_dir / "report.html"}
