"""Targetless calibration: map with one LIDAR, register the others, fit the ground for base_link.

SYNOPSIS
    res = calibrate_targetless(["drive.bag"], mapping_topic="/top/points",
                               calibration_topics=["/side/points"], base_frame="base_link")
    res.method                               # "targetless": a types.Result, as `clcgraph solve` makes
    res.rt_lidar0_sensor[res.sensor_index("/side/points")]; res.covariance_block("/side/points")  # (6,), (6,6)
    res.T_base_sensor["/side/points"]        # (4,4) base_link <- side, from the ground plane
    clcgraph.write_outputs(res, "out/", cfg)  # the one output path (outputs/): calibration.yaml, report, ROS

    res = calibrate_targetless_scans(scans_by_topic, mapping_topic=..., calibration_topics=[...],
                                     T_base_sensor_guess={...})   # in-memory variant (tests, sim)

Stages (timed in ``res.stats["stage_time_s"]``, peak memory in ``res.stats["peak_rss_mb"]``):
mapping (deskew + scan-to-map VGICP; the scans read and prepared in a forked child process),
calibration frames, selection, registration (dense targets, every other one made in a forked
child; ensemble + per-frame refinement), graph (GTSAM fusion and Marginals; the keyframe submap
registrations computed in a forked child process beside the calibration frames and
registration), ground (base_link roll/pitch/z: in another forked child; the stage is the wait
for it at the end). The children's memory is not in the peak (they share the parent's pages;
their own buffers are tens of MB, the dense targets' child's a few hundred: bench_targetless
measures them together).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from .. import geometry as geo
from ..config import Config
from ..determinism import single_threaded_blas
from ..errors import DegenerateError, InputError
from ..timing import StageClock
from ..types import Problem, Result, Sensor, TargetlessRun
from .calibration_frames import make_calibration_frames, nearest_to_keyframes
from .keyframe_graph import fuse
from .mapping import build_map
from .registration import (all_keyframe_edges, deskew_sources, ensemble, keyframe_edges, prepare_frames,
                           refine_per_frame, squared_distances, truncated_score)
from .selection import adapt_to_drive, select_frames

log = logging.getLogger(__name__)


@single_threaded_blas()
def calibrate_targetless_scans(scans: dict, *, mapping_topic: str, calibration_topics, T_base_sensor_guess: dict,
                               base_frame: str | None = None, config: Config | None = None, frames: dict | None = None,
                               progress=None, counts: dict | None = None) -> Result:
    """Calibrate from scans: ``scans[topic]`` a time-ordered list or iterable of LidarScan, read once
    (the mapping topic streams through the mapping; of a calibration topic only the scans nearest
    to keyframes are kept). ``counts``: topic -> number of scans, for the progress bar.

    T_base_sensor_guess: topic -> (4,4) initial guess (tf_static) in a common parent frame.
    Returns a ``types.Result`` with ``method == "targetless"`` (sensors: the mapping LIDAR, the
    reference, then ``calibration_topics``).
    """
    cfg = config or Config()
    o = cfg.targetless
    timings: dict = {}
    memory: dict = {}
    clock = StageClock(timings, memory)
    if mapping_topic not in scans:
        raise InputError(f"{mapping_topic}: no scans of the mapping topic")
    if progress is None:
        from .. import progress as _pg

        def progress(items, desc=f"mapping {mapping_topic}"):
            total = len(items) if hasattr(items, "__len__") else (counts or {}).get(mapping_topic)
            return _pg.progress(items, desc=desc, total=total, unit="scan")
    with clock("mapping"):
        mp = build_map(scans[mapping_topic], o, progress=progress)
    G0 = np.asarray(T_base_sensor_guess[mapping_topic])
    # what needs the map only goes on the other core while the LIDARs are registered: the
    # submap registrations of the keyframe graph (all keyframes; the graph takes those it uses)
    # and the ground plane
    from .background import Background

    jobs = {"edges": Background(all_keyframe_edges, mp, o)}
    if base_frame is not None:
        from .ground import calibrate_base

        jobs["ground"] = Background(calibrate_base, mp, G0, o)
    try:
        return _calibrate(scans, mp, G0, jobs, mapping_topic=mapping_topic, calibration_topics=calibration_topics,
                          T_base_sensor_guess=T_base_sensor_guess, base_frame=base_frame, o=o, frames=frames,
                          progress=progress, clock=clock, timings=timings, memory=memory)
    finally:
        for job in jobs.values():
            job.cancel()  # only where an error left it running


def _calibrate(scans, mp, G0, jobs, *, mapping_topic, calibration_topics, T_base_sensor_guess, base_frame, o,
               frames, progress, clock, timings, memory) -> Result:
    """The rest of :func:`calibrate_targetless_scans` once the map is there (``jobs``: the
    Background jobs "edges" (all_keyframe_edges) and, with a base frame, "ground")."""
    T_final_of, cov_of = {mapping_topic: np.eye(4)}, {mapping_topic: np.zeros((6, 6))}
    guess_of: dict = {mapping_topic: np.eye(4)}
    graph, convergence, per_frame, candidates, notes = {}, {}, {}, {}, []
    pictures: dict = {"map": _map_pictures(mp, o), "alignment": {}}
    edge_cache: dict = {}  # keyframe submap registrations, shared by the calibration LIDARs
    plan = adapt_to_drive(mp, o)
    for topic in calibration_topics:
        with clock("calibration frames"):
            kept = nearest_to_keyframes(mp, scans.get(topic, ()))
            if not kept:
                raise InputError(f"{topic}: no scans of this calibration topic")
            cfs = make_calibration_frames(mp, kept, o, skip_keyframes=plan.skip_keyframes)
        Tg = np.linalg.inv(G0) @ np.asarray(T_base_sensor_guess[topic])
        guess_of[topic] = Tg
        with clock("selection"):
            chosen = select_frames(cfs, mp, o, spacing_m=plan.spacing_m)
        if len(chosen) < o.lidar_calibration_min_frames:
            reasons = sorted({cf.reason for cf in cfs if cf.reason})
            raise DegenerateError(f"{topic}: {len(chosen)} usable calibration frames of {len(cfs)} "
                                  f"(< lidar_calibration_min_frames={o.lidar_calibration_min_frames}) on a "
                                  f"{plan.drive_length_m:.1f} m drive, {plan.spacing_m:.2f} m apart; "
                                  f"rejections: {'; '.join(reasons[:3]) or 'none'}")
        with clock("registration"):
            fr = prepare_frames(list(progress(chosen, desc=f"dense targets {topic}")), mp, Tg, o, deskew_on=o.deskew)
            T_best, cands = ensemble(fr, Tg, o)
            deskew_sources(fr, T_best)
            meas = refine_per_frame(fr, T_best, o)
        with clock("graph"):
            used = sorted({m.anchor for m in meas} | {p for m in meas for p in m.influence})
            keyframes = {p: mp.frames[mp.keyframe_ids[p]].T_map_lidar for p in used}
            if "edges" in jobs:
                edge_cache.update(jobs.pop("edges").result())
            edges = keyframe_edges(mp, used, o, cache=edge_cache)
            est = fuse(meas, keyframes, edges, common_mode=o.registration_common_mode,
                       min_frames=o.lidar_calibration_min_frames)
        graph[topic] = {"frames": len(meas), "keyframes": len(keyframes), "keyframe_edges": len(edges),
                        "noise_scale": {k: float(v) for k, v in est.scales.items()},
                        "redundancy": {k: float(v) for k, v in est.redundancy.items() if k in est.scales},
                        "common_mode": float(o.registration_common_mode)}
        convergence[topic] = est.convergence
        if est.convergence["warnings"]:
            log.warning("%s: the targetless graph did not converge everywhere: %s", topic,
                        "; ".join(est.convergence["warnings"]))
            notes.append(f"{topic}: NOT CONVERGED: " + "; ".join(est.convergence["warnings"]))
        log.info("%s: graph of %d frames, %d keyframes, %d keyframe edges; noise scales %s", topic, len(meas),
                 len(keyframes), len(edges), {k: f"{v:.3g}" for k, v in est.scales.items()})
        # each frame's distances at the guess and the estimate, once: the scores, per frame and
        # over all, and the report's distance histograms
        d2_guess, d2_final = squared_distances(fr, Tg), squared_distances(fr, est.T)
        s_guess, s_final = truncated_score(d2_guess, o), truncated_score(d2_final, o)
        T_final, cov = est.T, est.cov_rt
        if s_guess <= s_final:  # the initial guess stays a candidate
            log.warning("%s: the initial guess scores better than the registration; keeping it", topic)
            notes.append(f"{topic}: initial guess kept (score {s_guess:.3g} <= {s_final:.3g}); its sigmas "
                         "include the difference to the registration estimate")
            T_final, d2_final = Tg, d2_guess
            # nothing measured the guess: it is as uncertain as it is far from the estimate (that
            # distance composed in the tangent at the guess, then in rt coordinates there)
            import gtsam

            d = np.asarray(gtsam.Pose3(Tg).localCoordinates(gtsam.Pose3(est.T)))
            J = geo.drt_dxi(geo.rt_from_T(Tg))
            cov = J @ (est.cov_xi + np.outer(d, d)) @ J.T
        T_final_of[topic], cov_of[topic], candidates[topic] = T_final, cov, cands
        per_frame[topic] = [
            {"keyframe": fd.cf.keyframe_id, "stamp_ns": int(fd.cf.scan.stamp_ns), "pca": fd.cf.score,
             "score_guess": truncated_score([g], o), "score_final": truncated_score([f], o),
             "rt_frame": geo.rt_from_T(m.T).tolist(), **fd.cf.stats}
            for fd, m, g, f in zip(fr, meas, d2_guess, d2_final)]
        pictures["alignment"][topic] = _alignment_pictures(fr, Tg, T_final, o, d2_guess, d2_final)
    T_base_sensor: dict = {}
    if "ground" in jobs:
        with clock("ground"):  # what is left of it: it ran beside the registration
            T_b0, info = jobs["ground"].result()
        T_base_sensor = {topic: T_b0 @ T for topic, T in T_final_of.items()}
    return _result(T_final_of, cov_of, frames=dict(frames or {}), base_frame=base_frame, T_base_sensor=T_base_sensor,
                   stats={"stage_time_s": timings, "peak_rss_mb": memory},
                   run=TargetlessRun(T_lidar0_sensor_guess=guess_of, graph=graph, convergence=convergence,
                                     per_frame=per_frame, frame_plan=plan.as_dict(), candidates=candidates,
                                     pictures=pictures, map_result=mp, notes=tuple(notes)))


def _result(T_lidar0_sensor: dict, covariance: dict, *, run: TargetlessRun, **fields) -> Result:
    """The Result of both methods: sensors in order (the reference first), poses as rt, the
    covariance over the non-reference sensors. Each LIDAR is calibrated in its own graph, so the
    blocks between LIDARs are zero (their shared map errors are not modelled across LIDARs)."""
    topics = list(T_lidar0_sensor)
    n = len(topics) - 1
    cov = np.zeros((6 * n, 6 * n))
    for k, t in enumerate(topics[1:]):
        cov[6 * k:6 * k + 6, 6 * k:6 * k + 6] = 0.5 * (covariance[t] + covariance[t].T)
    problem = Problem(sensors=tuple(Sensor(topic=t, kind="lidar") for t in topics), board=None,
                      lidar_observations=(), camera_observations=(), snapshot_stamps_ns=np.zeros(0, np.int64))
    return Result(problem=problem, rt_lidar0_sensor=np.array([geo.rt_from_T(T_lidar0_sensor[t]) for t in topics]),
                  covariance_rt=cov, rt_lidar0_board=np.zeros((0, 6)), noise={}, rms={}, rejected=(),
                  method="targetless", targetless=run, **fields)


def _map_pictures(mp, o) -> dict:
    """The report's top view of the map: keyframe points near the vehicle (voxel-thinned), the
    trajectory and the keyframes."""
    from .mapping import voxel_down

    P = mp.poses()
    kf = np.array(mp.keyframe_ids)
    near = [mp.frames[k].points[np.linalg.norm(mp.frames[k].points, axis=1) <= o.viz_max_range] for k in kf]
    pts = voxel_down(np.concatenate([p @ mp.frames[k].T_map_lidar[:3, :3].T + mp.frames[k].T_map_lidar[:3, 3]
                                     for p, k in zip(near, kf)]), o.mapping_viz_leaf_size)
    return {"map_points": pts, "trajectory": P[:, :3, 3], "keyframes": kf}


# the report's before/after view: far enough for structure, near enough to see centimetres
_VIEW_BOX_M = 10.0


def _alignment_pictures(fds, before: np.ndarray, after: np.ndarray, o, d2_before: list, d2_after: list) -> dict:
    """One frame (the middle one) near the sensor before (guess) and after (final), and the
    distances of every frame's points (1 in 4: ``squared_distances``' ``d2_before`` / ``d2_after``)
    to the dense map before and after."""
    from .mapping import voxel_down

    fd = fds[len(fds) // 2]
    c = after[:3, 3]

    def near(x):
        return x[np.all(np.abs(x[:, :2] - c[:2]) < _VIEW_BOX_M, axis=1)]

    def moved(T, pts):
        return pts @ T[:3, :3].T + T[:3, 3]

    return {"target": near(voxel_down(fd.target_pts, o.calibration_viz_leaf_size / 3)),
            "source_guess": near(moved(before, fd.source_pts)), "source_final": near(moved(after, fd.source_pts)),
            "box_m": _VIEW_BOX_M, "frames": len(fds),
            "distances_guess": np.sqrt(np.concatenate(d2_before)), "distances_final": np.sqrt(np.concatenate(d2_after)),
            "max_corr_m": float(o.calibration_eval_max_corr_distance)}


def calibrate_targetless(bags, *, mapping_topic: str, calibration_topics, base_frame: str | None = None,
                         config: Config | None = None, progress=None) -> Result:
    """Read the bags (scans + /tf_static guess) and run :func:`calibrate_targetless_scans`."""
    from ..frontend.bag import frame_id, message_count, read_messages, read_tf_static

    bags = [bags] if isinstance(bags, (str, Path)) else list(bags)
    calibration_topics = list(calibration_topics)
    topics = [mapping_topic] + calibration_topics
    counts = {t: message_count(bags, t) for t in topics}
    for t in topics:
        if not counts[t]:
            raise InputError(f"topic {t} has no message in the {len(bags)} bag(s) ({bags[0]}, ...); "
                             "check the topics against `clcgraph show-bag`")
    # each topic streams from the bags when its stage needs it: a drive is never all in memory. A
    # drive recorded in split files may leave a topic out of a short last file: it holds none of it
    scans = {t: (m.data for m in read_messages(bags, [t], missing_ok=True)) for t in topics}  # in stamp order
    frames = {t: frame_id(next(b for b in bags if message_count(b, t)), t) for t in topics}
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
