"""The Python API: the one module that joins the stages (bags -> Problem -> Result -> files).

SYNOPSIS
    import clcgraph
    from clcgraph.config import Config

    cfg = Config.from_yaml("clcgraph.yaml")                      # or Config()
    problem = clcgraph.read_problem(["capture/*.bag"], ["/lidar0/points", "/lidar1/points",
                                    "/cam0/image"], models=["cam0.cameramodel"], config=cfg)
    result = clcgraph.calibrate(problem, cfg)                    # GTSAM solve + uncertainty + sectors
    clcgraph.write_outputs(result, "out/", cfg)                  # calibration.yaml, models, report
    cal = clcgraph.load_result("out/")                           # what downstream scripts read

    # or all at once, as `clcgraph solve` does:
    result = clcgraph.calibrate_bags(["capture/*.bag"], topics, models, out="out/", config=cfg)
    # targetless, from a drive (`clcgraph targetless`): the same Result type, the same outputs
    result = clcgraph.calibrate_targetless(["drive.bag"], mapping_topic="/top/points",
                                           calibration_topics=["/side/points"], out="out/", config=cfg)

Every failure is a ``clcgraph.errors.ClcgraphError`` with a one-line message naming the
bag, topic or sensor; nothing is written to ``out`` unless the whole calibration succeeded.
"""

from __future__ import annotations

import dataclasses
import glob
import logging
from pathlib import Path
from typing import Sequence

import numpy as np

from .config import Config, ConfigError, read_yaml
from .determinism import single_threaded_blas
from .errors import DataError, DegenerateError, InputError
from .progress import progress
from .timing import StageClock
from .types import (
    BoardGeometry,
    CameraBoardObservation,
    LidarBoardObservation,
    PosePrior,
    Problem,
    Rejected,
    Result,
    Sensor,
)

log = logging.getLogger(__name__)

# Visibility points kept per LIDAR for the sector report (a subsample of one scan).
_VISIBILITY_POINTS = 20000


# ---------------------------------------------------------------- inputs


def expand_bags(patterns: Sequence[str | Path]) -> list[Path]:
    """Bag paths from globs, paths or directories, sorted, duplicates dropped; InputError for no match.

    A directory that is not itself a ROS2 bag (no metadata.yaml) means the bags in it: its
    ROS1 ``*.bag`` files and its ROS2 bag subdirectories.
    """
    out: list[Path] = []
    for pat in patterns:
        matches = sorted(glob.glob(str(pat)))
        if not matches:
            if Path(pat).exists():
                matches = [str(pat)]
            else:
                raise InputError(f"{pat}: no such bag (nothing matches this path or glob)")
        for m in map(Path, matches):
            inside = [m]
            if m.is_dir() and not (m / "metadata.yaml").exists():
                inside = sorted(p for p in m.iterdir()
                                if (p.suffix == ".bag" and p.is_file()) or (p / "metadata.yaml").exists())
                if not inside:
                    raise InputError(f"{m}: a directory with no ROS1 .bag file and no ROS2 bag (a directory "
                                     "with metadata.yaml) in it")
            out.extend(p for p in inside if p not in out)
    return out


def bags_and_models(bags: Sequence[str], models: Sequence[str]) -> tuple[list[str], list[str]]:
    """`--bag a.bag b.bag cam.cameramodel` (an unquoted glob, expanded by the shell, before the
    models): --bag takes every word up to the next option, so the .cameramodel and .yaml files among
    them (not a ROS2 bag's metadata.yaml) are models (in order, before the later ones); a bag among
    the models is an InputError hint."""
    is_model = [str(b).endswith((".cameramodel", ".yaml", ".yml")) and Path(b).name != "metadata.yaml" for b in bags]
    models = [b for b, m in zip(bags, is_model) if m] + list(models)
    bags = [b for b, m in zip(bags, is_model) if not m]
    from .frontend.bag import ROS2_STORAGE_SUFFIXES

    stray = [m for m in models if str(m).endswith((".bag", *ROS2_STORAGE_SUFFIXES))]
    if stray:
        raise InputError(f"{stray[0]} is a bag, given where the camera models go: put every bag after --bag "
                         "(or quote the glob: --bag 'capture/*.bag')")
    return bags, models


def board_geometry(config=None) -> BoardGeometry:
    """The physical board of the config's ``board`` section."""
    return BoardGeometry.from_spec(**dataclasses.asdict(_config(config).board))


def _config(config) -> Config:
    if config is None:
        return Config()
    if isinstance(config, Config):
        return config
    try:
        return Config.from_yaml(config) if isinstance(config, (str, Path)) else Config.from_dict(config)
    except ConfigError as e:
        raise InputError(str(e)) from None


# Message types of LIDAR drivers' raw packets (velodyne_msgs/VelodyneScan, ouster_msgs/PacketMsg,
# hesai_ros_driver/UdpFrame, rslidar_msg/RslidarPacket, pandar_msgs/PandarScan): a bag recorded to save space
_PACKET_TYPE_WORDS = ("Packet", "VelodyneScan", "PandarScan", "UdpFrame")


def classify_topics(bags: Sequence[Path], topics: Sequence[str]) -> tuple[list[str], list[str]]:
    """(lidar topics, camera topics) in the given order, from the message types in the bags."""
    from .frontend.bag import COMPRESSED_IMAGE, IMAGE, POINTCLOUD2, bag_info

    if not topics:
        raise InputError("no topics given: --topics LIDAR0,OTHER,... (lidar0 first; see `clcgraph show-bag`)")
    types: dict[str, str] = {}
    for b in bags:
        for t in bag_info(b).topics:
            types.setdefault(t.topic, t.msgtype)
        if all(t in types for t in topics):
            break
    lidars, cams = [], []
    for t in topics:
        if t not in types:
            raise InputError(f"topic {t} is in none of the {len(bags)} bags ({bags[0]}, ...); "
                             f"check --topics against `clcgraph show-bag`")
        if types[t] == POINTCLOUD2:
            lidars.append(t)
        elif types[t] in (IMAGE, COMPRESSED_IMAGE):
            cams.append(t)
        else:
            raw = any(w in types[t] for w in _PACKET_TYPE_WORDS)
            raise DataError(f"topic {t} has type {types[t]}: expected sensor_msgs/PointCloud2, Image or CompressedImage"
                            + ("; these are the LIDAR's raw packets: play the bag through its driver (e.g. "
                               "velodyne_pointcloud, ouster_ros) and record the PointCloud2 it publishes" if raw else ""))
    if not lidars:
        raise InputError(f"none of the topics {', '.join(topics)} is a LIDAR (PointCloud2); lidar0 is the reference")
    return lidars, cams


def nominal_poses(bags, sensors: Sequence[Sensor], *, strict: bool = False) -> dict[int, np.ndarray]:
    """sensor index -> nominal rt_lidar0_sensor from the bags' /tf_static (every non-reference sensor
    whose frame it links to lidar0's). ``strict``: InputError for a missing /tf_static or path (the
    priors need them all); else those sensors are left out (the report shows what there is)."""
    from .frontend.bag import frame_id, read_tf_static
    from .geometry import rt_from_T

    bags = list(bags)
    tf = read_tf_static(bags)
    if not tf.frames:
        if strict:
            raise InputError(f"--prior-from-tf-static: no /tf_static in {bags[0]} ...")
        return {}
    frames = [frame_id(bags[0], s.topic) for s in sensors]
    ref = next(i for i, s in enumerate(sensors) if s.is_lidar)
    out = {}
    for i, s in enumerate(sensors):
        if i == ref:
            continue
        try:
            out[i] = rt_from_T(tf.lookup(frames[ref], frames[i]))
        except Exception as e:
            if strict:
                raise InputError(f"--prior-from-tf-static: /tf_static has no path {frames[ref]} <- {frames[i]} "
                                 f"(sensor {s.topic}): {str(e).splitlines()[0] if str(e) else ''}") from None
    return out


def _tf_priors(bags, sensors: Sequence[Sensor], sigma_rad: float, sigma_m: float) -> tuple[PosePrior, ...]:
    """Nominal poses of every non-reference sensor from /tf_static, as priors with per-axis
    sigmas ``sigma_rad`` (rotation) and ``sigma_m`` (translation)."""
    sigma = np.repeat([float(sigma_rad), float(sigma_m)], 3)
    return tuple(PosePrior(sensor=i, rt_lidar0_sensor=rt, sigma_rt=sigma)
                 for i, rt in nominal_poses(bags, sensors, strict=True).items())


@single_threaded_blas()  # OpenBLAS's idle threads spin: they doubled the frontend's CPU time
def read_problem(bags, topics: Sequence[str], models: Sequence[str | Path] = (), *, config=None,
                 timings: dict | None = None, report_material: dict | None = None) -> Problem:
    """Bags -> Problem: snapshots, LIDAR board segmentation, chessboard detection.

    ``topics``: LIDAR and camera topics in any order (the first LIDAR is lidar0);
    ``models``: one camera model per camera topic, in the cameras' order (an mrcal .cameramodel or
    a ROS camera calibration .yaml: ``cameras.load_camera``; or ``cameras.FROM_CAMERA_INFO``: the
    camera's CameraInfo in the bags, ``frontend.bag.camera_info``, ``cameras.camera_from_info``),
    or none: every camera's CameraInfo. A snapshot is
    kept only if >= 2 sensors saw the board; everything dropped is in ``Problem.rejected``.
    ``timings``: if given, filled with wall seconds per stage (read, segment, detect).
    ``report_material``: if given, filled with what the report draws: "snapshots" (index ->
    Snapshot: a few decoded ones, see ``_report_snapshots``) and "sources" (index -> bag).
    """
    clock = StageClock(timings)
    from . import cameras
    from .frontend.camera_board import choose_detector
    from .frontend.lidar_board import offsets_table
    from .frontend.snapshots import assemble_snapshots

    cfg = _config(config)
    paths = expand_bags(bags)
    topics = list(dict.fromkeys(t.strip() for t in topics if t.strip()))
    lidar_topics, camera_topics = classify_topics(paths, topics)
    if models and len(models) != len(camera_topics):
        raise InputError(f"{len(models)} camera model(s) given for {len(camera_topics)} camera topic(s) "
                         f"({', '.join(camera_topics) or 'none'}): give one camera model per camera topic, in order "
                         f"(.cameramodel, ROS calibration .yaml, or {cameras.FROM_CAMERA_INFO}: its CameraInfo in the "
                         "bags), or none: each camera's CameraInfo")
    sensors = [Sensor(topic=t, kind="lidar") for t in lidar_topics]
    sources = []  # per camera: where its model came from, for the messages
    for t, m in zip(camera_topics, models or [cameras.FROM_CAMERA_INFO] * len(camera_topics)):
        if str(m) == cameras.FROM_CAMERA_INFO:  # as the driver published it, beside the images
            from .frontend.bag import camera_info

            info = camera_info(paths, t)
            sensors.append(cameras.camera_from_info(t, info))
            sources.append(f"CameraInfo ({info.where})")
            log.info("%s: camera model from %s (%s)", t, info.where, sensors[-1].lensmodel)
        else:
            sensors.append(cameras.load_camera(t, m))
            sources.append(str(m))
    if len(sensors) < 2:
        raise InputError(f"only one sensor ({sensors[0].topic}): calibration needs >= 2 sensors")

    board = board_geometry(cfg)
    if camera_topics:  # a detector that cannot handle the board fails here, before the bags are read
        log.info("board %s; chessboard detector %s", board.spec(), choose_detector(cfg.detection, board))
    with clock("read"):
        snaps, rejected = assemble_snapshots(paths, lidar_topics, camera_topics, cfg.snapshots,
                                             progress=lambda it: progress(it, desc="reading bags", unit="bag"))
    rejected = list(rejected)
    excluded = {r.snapshot for r in rejected if r.snapshot is not None}  # emptied by exclude_bag
    if not snaps:
        raise DataError(f"no usable snapshot in {len(paths)} bag(s): "
                        + (rejected[0].reason if rejected else "no messages on the topics"))

    # every camera's images, checked against their models before any work
    cam_images: list[tuple[int, int, object]] = []  # (sensor index, snapshot, Image)
    for j, t in enumerate(camera_topics):
        i = len(lidar_topics) + j
        w, h = sensors[i].imagersize
        for s in snaps:
            im = s.images.get(t)
            if im is None:
                continue
            if im.pixels.shape[:2] != (h, w):
                raise DataError(f"topic {t}: images are {im.pixels.shape[1]}x{im.pixels.shape[0]} but its model "
                                f"{sources[j]} is {w}x{h}; give the model of this camera")
            cam_images.append((i, s.index, im))

    from concurrent.futures import ThreadPoolExecutor

    lidar_obs: list[LidarBoardObservation] = []
    visibility: dict[int, np.ndarray] = {}
    ring_offsets: dict[int, np.ndarray] = {}
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="clcgraph-detect") as pool:
        # the first detection pass (one mrgingham process for every image) runs while the LIDARs
        # are segmented; its misses are retried below, where the LIDARs say a board can be
        first = pool.submit(_first_detection_pass, [im for *_, im in cam_images], cfg.detection, board,
                            clock.into) if cam_images else None
        clock.start("segment")
        for t in lidar_topics:
            scans = [s.scans[t] for s in snaps if t in s.scans]
            if scans and not any(sc.valid.any() for sc in scans):
                raise DataError(f"topic {t}: every point of all {len(scans)} scans is invalid (NaN, inf or zero); "
                                "is this LIDAR's driver writing its points?")
        for i, t in enumerate(lidar_topics):
            scans = [(s.index, s.scans[t]) for s in snaps if t in s.scans]
            measured: dict = {}
            for k, r in zip([k for k, _ in scans], segment([sc for _, sc in scans], config=cfg, sensor=i,
                                                          snapshots=[k for k, _ in scans], board=board,
                                                          ring_offsets=measured)):
                (lidar_obs if isinstance(r, LidarBoardObservation) else rejected).append(r)
            if measured:
                ring_offsets[i] = offsets_table(measured)
            if scans:
                pts = scans[0][1].points[scans[0][1].valid]
                step = max(1, len(pts) // _VISIBILITY_POINTS)
                visibility[i] = np.asarray(pts[::step], float)
        clock.stop()
        detection = first.result() if first is not None else None

    camera_obs: list[CameraBoardObservation] = []
    if detection is not None:
        with clock("detect"):
            scans = _scans_by_lidar(snaps, lidar_topics)
            found = detection.retry(_board_regions(sensors, lidar_obs, cam_images, detection, cfg, board,
                                                   1 + max(s.index for s in snaps), scans))
        for (i, k, _), r in zip(cam_images, found):
            if isinstance(r, Rejected):
                rejected.append(dataclasses.replace(r, sensor=i, snapshot=k))
            else:
                camera_obs.append(CameraBoardObservation(sensor=i, snapshot=k, corners_px=np.asarray(r, float)))

    _check_every_sensor_found_a_board(sensors, lidar_obs, camera_obs, rejected, board, cfg.solve.min_shared_snapshots)
    # The seed's rule: a snapshot counts only if >= 2 sensors saw the board.
    seen: dict[int, int] = {}
    for o in [*lidar_obs, *camera_obs]:
        seen[o.snapshot] = seen.get(o.snapshot, 0) + 1
    lonely = {k for k, n in seen.items() if n < 2}
    for k in sorted(lonely):
        rejected.append(Rejected("board seen by only one sensor", "snapshot", snapshot=k))
    for k in sorted({s.index for s in snaps} - set(seen) - excluded):
        rejected.append(Rejected("board seen by no sensor", "snapshot", snapshot=k))
    lidar_obs = [o for o in lidar_obs if o.snapshot not in lonely]
    camera_obs = [o for o in camera_obs if o.snapshot not in lonely]
    if report_material is not None:
        keep = _report_snapshots(sensors, lidar_obs, camera_obs)
        report_material["snapshots"] = {s.index: s for s in snaps if s.index in keep}
        report_material["sources"] = {s.index: s.source for s in snaps}
    n_used = len(set(seen) - lonely)
    log.info("%d snapshots, %d with the board seen by >= 2 sensors; %d LIDAR and %d camera observations",
             len(snaps), n_used, len(lidar_obs), len(camera_obs))
    if n_used < 3:
        raise DegenerateError(f"only {n_used} snapshot(s) with the board seen by >= 2 sensors (of {len(snaps)}); "
                              + _why_missed(sensors, lidar_obs, camera_obs, rejected)
                              + "record more board poses (see `clcgraph segment` / `clcgraph detect` for why boards were missed)")

    priors: tuple[PosePrior, ...] = ()
    sig_rad, sig_m = cfg.solve.prior_from_tf_static_sigma_rad, cfg.solve.prior_from_tf_static_sigma_m
    if sig_rad is not None or sig_m is not None:
        if sig_rad is None or sig_m is None or not (np.isfinite(sig_rad) and np.isfinite(sig_m)
                                                    and sig_rad > 0 and sig_m > 0):
            raise InputError(f"solve.prior_from_tf_static_sigma_rad={sig_rad}, solve.prior_from_tf_static_sigma_m="
                             f"{sig_m}: set both, each a positive number (--prior-from-tf-static SIGMA_RAD,SIGMA_M)")
        priors = _tf_priors(paths, sensors, sig_rad, sig_m)
    return Problem(
        sensors=tuple(sensors),
        board=board,
        lidar_observations=tuple(lidar_obs),
        camera_observations=tuple(camera_obs),
        snapshot_stamps_ns=np.array([s.stamp_ns for s in snaps], dtype=np.int64),
        rejected=tuple(rejected),
        priors=priors,
        lidar_visibility_points=visibility,
        snapshot_bags=tuple(s.bag for s in snaps),
        lidar_ring_offsets=ring_offsets,
    )


def _report_snapshots(sensors, lidar_obs, camera_obs) -> set[int]:
    """The snapshots whose images and scans the report draws: per camera, the one where the most LIDARs
    saw the board with it (then the most corners' spread); and the one where the most LIDARs saw the board
    (then the most board points) for the clouds before / after."""
    lidars_at: dict[int, int] = {}
    points_at: dict[int, int] = {}
    for o in lidar_obs:
        lidars_at[o.snapshot] = lidars_at.get(o.snapshot, 0) + 1
        points_at[o.snapshot] = points_at.get(o.snapshot, 0) + len(o.points)
    keep = set()
    for i in {o.sensor for o in camera_obs}:
        obs = [o for o in camera_obs if o.sensor == i]
        spread = lambda o: float(np.nanmax(o.corners_px, 0).sum() - np.nanmin(o.corners_px, 0).sum())  # noqa: E731
        keep.add(max(obs, key=lambda o: (lidars_at.get(o.snapshot, 0), spread(o))).snapshot)
    if lidars_at:
        keep.add(max(lidars_at, key=lambda k: (lidars_at[k], points_at[k])))
    return keep


def _first_detection_pass(images, options, board, timings):
    """The chessboard detection's first pass over every camera image (frontend BoardDetection)."""
    from .frontend.camera_board import BoardDetection

    with StageClock(timings)("detect"):
        detection = BoardDetection(images, options, board)
        # a board.corners off by a few finds nothing anywhere: said at once, with the count the
        # images show, instead of after the retries (tens of seconds) as "no board found"
        shown = detection.grid_shown_instead()
        if shown is not None:
            m, topics, checked = shown
            topic = max(set(topics), key=topics.count)
            raise InputError(f"{topic}: its images show a whole {m}x{m} grid of inner corners ({len(topics)} of the "
                             f"{checked} images checked), none the {board.corners_x}x{board.corners_y} of board.corners: "
                             f"set board.corners: [{m}, {m}] (inner corners, where four squares meet: one fewer than "
                             "the squares along each side)")
        return detection


def _scans_by_lidar(snaps, lidar_topics) -> dict:
    """{(snapshot index, LIDAR index): its LidarScan} of the snapshots (``_board_regions``' ``scans``)."""
    return {(s.index, i): s.scans[t] for i, t in enumerate(lidar_topics) for s in snaps if t in s.scans}


def _board_regions(sensors, lidar_obs, cam_images, detection, cfg, board, n_snapshots, scans=None) -> list | None:
    """Per camera image, where its board can be (frontend.camera_board.board_regions): each camera
    with misses is placed with the LIDARs from the first pass's detections (backend.seed's
    sensor_poses), and the LIDARs' views of each missed board are projected into it, with their
    whole scans (``scans``: (snapshot, LIDAR index) -> LidarScan) for what stands in front of the
    board. None for a camera the seed cannot place (fewer than min_shared_snapshots boards seen
    with a LIDAR): its misses are searched whole."""
    from .backend.seed import sensor_poses
    from .errors import ClcgraphError
    from .frontend.camera_board import board_regions
    from .geometry import compose_rt, invert_rt

    missed = set(detection.missed)
    if not missed:
        return None
    lidars = [i for i, s in enumerate(sensors) if s.is_lidar]
    by_snapshot: dict[int, list] = {}
    for o in lidar_obs:
        by_snapshot.setdefault(o.snapshot, []).append(o)
    regions: list = [None] * len(cam_images)
    for cam in sorted({cam_images[k][0] for k in missed}):
        mine = [k for k, (i, _, _) in enumerate(cam_images) if i == cam]
        todo = [k for k in mine if k in missed]
        if not any(cam_images[k][1] in by_snapshot for k in todo):
            continue  # no LIDAR saw any of its missed boards: nothing to predict them from (searched whole)
        c = len(lidars)  # the camera's index in a problem of the LIDARs and this camera
        obs = tuple(CameraBoardObservation(sensor=c, snapshot=cam_images[k][1],
                                           corners_px=np.asarray(detection.results[k], float))
                    for k in mine if not isinstance(detection.results[k], Rejected))
        problem = Problem(sensors=tuple(sensors[i] for i in lidars) + (sensors[cam],), board=board,
                          lidar_observations=tuple(lidar_obs), camera_observations=obs,
                          snapshot_stamps_ns=np.zeros(n_snapshots, np.int64))
        try:
            rt_lidar0 = sensor_poses(problem, cfg.solve)
        except (ClcgraphError, np.linalg.LinAlgError, ValueError) as e:  # a prediction only: search whole
            log.debug("%s: no seed for predicting where its boards are (%s): missed images searched whole",
                      sensors[cam].topic, e)
            continue
        rt_camera_lidar = {i: compose_rt(invert_rt(rt_lidar0[c]), rt_lidar0[n]) for n, i in enumerate(lidars)}
        views = [[(rt_camera_lidar[o.sensor], o) for o in by_snapshot.get(cam_images[k][1], ())] for k in todo]
        scenes = [[(scans or {}).get((o.snapshot, o.sensor)) for _, o in v] for v in views]
        for k, box in zip(todo, board_regions(sensors[cam], views, board, scenes)):
            regions[k] = box
    return regions


def _misses(sensors, lidar_obs, camera_obs, rejected) -> dict[int, tuple[int, int, int, str]]:
    """{sensor: (boards found, scans or images that missed it, how many of those for its most
    common reason, that reason quoted)}, for the sensors that missed any: reasons that differ
    only in their numbers (a scan's: in its first plane's) counted together, the first one quoted."""
    import re
    from collections import Counter

    found = Counter(o.sensor for o in [*lidar_obs, *camera_obs])
    why: dict[int, Counter] = {}
    example: dict = {}
    for r in rejected:
        if r.sensor is not None and r.stage in ("segmentation", "detection"):
            text = r.reason.split(": ", 1)[-1] if r.stage == "segmentation" else r.reason
            # a scan's planes are listed after "no board-like plane": counted by its first
            text = "; ".join(text.split("; ")[:2])
            kind = re.sub(r"\d+(\.\d+)?", "#", text)
            why.setdefault(r.sensor, Counter())[kind] += 1
            example.setdefault((r.sensor, kind), text)
    out = {}
    for i in range(len(sensors)):
        if i in why:
            reason, n = why[i].most_common(1)[0]
            out[i] = (found.get(i, 0), sum(why[i].values()), n, example[(i, reason)])
    return out


def _quoted(text: str, n: int) -> str:
    """``text`` cut to at most ``n`` characters (then "...") at a clause's end in its second half,
    else at a word's."""
    if len(text) <= n:
        return text
    cut = max(text.rfind(sep, 0, n - 3) for sep in (": ", "; ", ", "))
    cut = cut if cut > n // 2 else text.rfind(" ", 0, n - 3)
    return text[:cut if cut > 0 else n - 3] + "..."


def _why_missed(sensors, lidar_obs, camera_obs, rejected) -> str:
    """Per sensor, how many boards it found and its most common reason for the rest, e.g. a board
    size that does not match the config: '/l: 2 found, 14 like "plane 1.79 m across, ..."'."""
    parts = [f'{sensors[i].topic}: {found} found, {n} like "{_quoted(text, 90)}"'
             for i, (found, _, n, text) in _misses(sensors, lidar_obs, camera_obs, rejected).items()]
    return ("; ".join(parts) + "; ") if parts else ""


def _check_every_sensor_found_a_board(sensors, lidar_obs, camera_obs, rejected, board, need: int = 1) -> None:
    """DegenerateError naming the first sensor that found fewer than ``need`` boards (the seed's
    min_shared_snapshots: it could not be calibrated, and the solve would only say it cannot be
    connected), with its commonest reason for the rest and the board setting to check: the pattern
    for a camera, the size for a LIDAR. An InputError where a camera's images showed a part of a
    larger pattern (board.corners short) or a grid past its edge (board.corners too large)."""
    from .frontend.camera_board import PATTERN_ENDS, PATTERN_GOES_ON

    for i, (found, missed, n, text) in _misses(sensors, lidar_obs, camera_obs, rejected).items():
        if found >= need:
            continue
        s = sensors[i]
        mine = [r.reason for r in rejected if r.sensor == i and r.stage == "detection"]
        more, fewer = (sum(r.startswith(words) for r in mine) for words in (PATTERN_GOES_ON, PATTERN_ENDS))
        # a grid off the pattern by its count where no image showed the board: the count itself is wrong
        # (beside boards found, one such image is a misread; the few boards are the cause)
        if s.is_camera and (more or fewer) and not found:
            raise InputError(f"{s.topic}: the chessboard in {more or fewer} of its {missed} images has "
                             f"{'more' if more else 'fewer'} inner corners than board.corners "
                             f"[{board.corners_x}, {board.corners_y}] (the pattern "
                             f"{'goes on past the grid found' if more else 'ends inside the grid found'}): count the "
                             "inner corners, where four squares meet, along the board's width and height")
        what = "images" if s.is_camera else "scans"
        setting = (f"board.corners [{board.corners_x}, {board.corners_y}] (inner corners along the board's width "
                   f"and height)" if s.is_camera else
                   f"board.size_m [{board.width_m:g}, {board.height_m:g}] (the physical board, its border included)")
        where = (f"only {found} board{'s' if found > 1 else ''} found in its {found + missed} {what}" if found else
                 f"no board found in any of its {missed} {what}")
        raise DegenerateError(f'{s.topic}: {where} ({n} like "{_quoted(text, 120)}"); '
                              f"is {setting} right, and was the board in its view? "
                              f"`clcgraph {'detect' if s.is_camera else 'segment'}` shows each")


@single_threaded_blas()  # as read_problem's (`clcgraph segment`, scripts)
def segment(scans, *, config=None, sensor: int = 0, snapshots: Sequence[int] | None = None,
            board: BoardGeometry | None = None, ring_offsets: dict | None = None) -> list:
    """LIDAR board segmentation of many scans: LidarBoardObservation or Rejected per scan.
    ``ring_offsets``: filled with {ring: range offset (m)} measured on the boards and taken out."""
    from .frontend.lidar_board import segment_many

    cfg = _config(config)
    board = board_geometry(cfg) if board is None else board
    snapshots = list(range(len(scans))) if snapshots is None else list(snapshots)
    bar = lambda it, n: progress(it, desc=f"segmenting LIDAR {sensor}", total=n, unit="scan")  # noqa: E731
    return segment_many(scans, cfg.segmentation, cfg.lidar, board, sensor=sensor, snapshots=snapshots, progress=bar,
                        ring_offsets=ring_offsets)


def detect(images, *, config=None, board: BoardGeometry | None = None) -> list:
    """Chessboard corners per image ((N,2) pixels in board order) or Rejected(reason);
    ``board`` defaults to the config's ``board`` section."""
    from .frontend.camera_board import detect_corners

    cfg = _config(config)
    return detect_corners(list(images), cfg.detection, board_geometry(cfg) if board is None else board)


# ---------------------------------------------------------------- solve


@single_threaded_blas()
def calibrate(problem: Problem, config=None, *, timings: dict | None = None, on_estimate=None) -> Result:
    """Solve a Problem: seed, staged LM, noise re-estimation, outliers, covariance, sectors.
    ``on_estimate(estimate)``: called as soon as the poses are final (backend.solve.calibrate)."""
    from .backend.sectors import sector_report
    from .backend.solve import calibrate as solve

    cfg = _config(config)
    clock = StageClock(timings)
    with clock("solve"):
        try:
            result = solve(problem, cfg.solve, on_estimate=on_estimate)
        except DegenerateError as e:  # a sensor left unconnected: what its scans or images missed says why
            missed = _why_missed(problem.sensors, problem.lidar_observations, problem.camera_observations,
                                 problem.rejected)
            if not str(e).startswith("cannot connect") or not missed:
                raise
            raise DegenerateError(f"{e}. Boards missed: {missed.rstrip('; ')}") from None
    with clock("uncertainty"):
        sectors = sector_report(result, cfg.sectors)
    return dataclasses.replace(result, sectors=sectors, rejected=explain_not_found(result))


def explain_not_found(result: Result) -> tuple[Rejected, ...]:
    """``result.rejected`` with each camera's bare "no full chessboard found" replaced by what it
    saw, where the solve placed the board (frontend.camera_board.not_found_reason): the board's
    points as the LIDARs saw them (the in-plane position of a LIDAR-only board pose is a guess),
    else the physical board's outline from the solved board pose."""
    from . import cameras
    from .frontend.camera_board import not_found_reason, not_found_text
    from .geometry import invert_rt, transform

    p = result.problem
    generic = not_found_text(p.board)
    lidar_points: dict[int, list] = {}
    for o in p.lidar_observations:
        lidar_points.setdefault(o.snapshot, []).append(transform(result.rt_lidar0_sensor[o.sensor], o.points))
    x0, x1, y0, y1 = p.board.extent()
    outline = np.array([[x, y, 0.0] for x in np.linspace(x0, x1, 5) for y in np.linspace(y0, y1, 5)])
    out = []
    for r in result.rejected:
        k, i = r.snapshot, r.sensor
        board = None if k is None else np.asarray(result.rt_lidar0_board[k], float)
        if r.stage != "detection" or r.reason != generic or i is None or not np.all(np.isfinite(board)):
            out.append(r)
            continue
        if k in lidar_points:
            pts, what = np.concatenate(lidar_points[k]), "its LIDAR points"
        else:
            pts, what = transform(board, outline), "its outline"
        s = p.sensors[i]
        p_cam = transform(invert_rt(result.rt_lidar0_sensor[i]), pts)
        q = cameras.project(p_cam, s.lensmodel, s.intrinsics)
        q[p_cam[:, 2] <= 0] = np.nan  # behind the camera
        out.append(dataclasses.replace(r, reason=not_found_reason(q, s.imagersize, p.board, what=what)))
    return tuple(out)


def write_outputs(result: Result, out_dir, config=None, *, force: bool = False, report_inputs=None,
                  figures=None) -> dict[str, Path]:
    """The one output path of both methods, atomically: calibration.yaml, .cameramodels,
    timings.yaml, config.resolved.yaml, report.html (one self-contained file), ros/ (when the
    frames are known), and (target-based) the replayable problem.npz.

    ``out_dir`` must be new, empty or a previous clcgraph output; ``force``: replace it anyway.
    ``report_inputs``: an ``outputs.evidence.ReportInputs`` (the run's record, images and clouds to
    draw, nominal poses); without it, ``gather_report_inputs(result, config)`` gathers them from the bags the
    result names (the same report as `clcgraph solve`'s). ``figures``: the report's pictures of the
    estimate, started before the solve ended (``outputs.report.start_estimate_figures``)."""
    from .outputs.dump import save_problem
    from .outputs.report import report_writer
    from .outputs.results import write_results

    cfg = _config(config)
    inputs = report_inputs if report_inputs is not None else gather_report_inputs(
        result, cfg, call=f"clcgraph.write_outputs(result, {str(out_dir)!r})")
    # the report's pictures are drawn (in a second process) while the other files are written
    with report_writer(result, inputs=inputs, early=figures) as write_report:
        return write_results(
            result, out_dir, config=cfg,
            problem_dump=(lambda problem, path: save_problem(path, problem, cfg)) if result.method == "target" else None,
            extra_files={"report.html": lambda path: write_report(path.parent)},
            force=force,
        )


def calibrate_bags(bags, topics: Sequence[str], models: Sequence[str | Path] = (), *, out=None,
                   config=None, force: bool = False) -> Result:
    """read_problem + calibrate (+ write_outputs when ``out`` is given): `clcgraph solve`.

    ``out`` must be new, empty or a previous clcgraph output (checked before any work);
    ``force``: replace whatever is there."""
    cfg = _config(config)
    if out is not None:
        check_out_dir(out, force=force)
    timings: dict[str, float] = {}
    material: dict = {}
    importing = _import_in_background("clcgraph.outputs.report", "clcgraph.outputs.plots") if out is not None else None
    problem = read_problem(bags, topics, models, config=cfg, timings=timings, report_material=material)
    call = (f"clcgraph.calibrate_bags({[str(b) for b in bags]!r}, {list(topics)!r}, "
            f"{[str(m) for m in models]!r}, out={str(out)!r})")
    report: dict = {}

    def start_report(estimate):  # the pictures of the estimate drawn while the solve computes its uncertainty
        from .outputs.report import start_estimate_figures

        if report.get("figures") is not None:  # an estimate of before a snapshot was left out (solve.calibrate)
            report["figures"].close(wait=False)
        importing.join()  # the drawing child is forked: not while another thread may hold an import lock
        with StageClock(timings)("report"):  # (inside the solve's clock, which counts it too)
            report["inputs"] = gather_report_inputs(estimate, cfg, bags=bags, models=models, call=call,
                                                    material=material)
            report["figures"] = start_estimate_figures(estimate, report["inputs"])

    try:
        result = calibrate(problem, cfg, timings=timings, on_estimate=start_report if out is not None else None)
        result = dataclasses.replace(result, stats={**result.stats, "stage_time_s": timings})
        if out is not None:
            importing.join()
            with StageClock(timings)("report"):
                inputs = report.get("inputs") or gather_report_inputs(result, cfg, bags=bags, models=models, call=call,
                                                                      material=material)
                write_outputs(result, out, cfg, force=force, report_inputs=inputs, figures=report.get("figures"))
    finally:  # the solve failed or the report is written: the drawing process is not needed any more
        if report.get("figures") is not None:
            report["figures"].close(wait=False)
    return result


def _import_in_background(*modules: str):
    """The started daemon thread importing ``modules``: the report's matplotlib import overlaps
    reading and detection instead of following the solve. A later import of the same module waits
    for this one (Python's per-module import lock); join it before forking (a child forked while
    the thread holds an import lock inherits the lock held, and its own imports hang)."""
    import importlib
    import threading

    def run():
        for m in modules:
            try:
                importlib.import_module(m)
            except Exception:  # noqa: BLE001 - the real import, later, reports it
                return

    thread = threading.Thread(target=run, name="clcgraph-import", daemon=True)
    thread.start()
    return thread


def gather_report_inputs(result: Result, config=None, *, bags=None, models=(), call: str | None = None,
                  material: dict | None = None):
    """The report's record of a run (bags with sizes, camera models, the call, the effective settings),
    the snapshots it draws and the nominal poses from /tf_static: what `clcgraph solve` and
    ``write_outputs`` give ``outputs.report.write_report`` (an ``outputs.evidence.ReportInputs``).

    ``bags``: the bags given (default: the ones ``result.problem`` names, where they still exist);
    ``material``: read_problem's ``report_material`` (the decoded snapshots, kept while reading); without
    it, the few snapshots the report draws are read again from the bags. The nominal poses are the
    priors' when the solve had /tf_static priors (read once), else the first bag's /tf_static.
    Nothing here fails the calibration: what cannot be read is logged and left out."""
    import shlex
    import sys

    from . import cameras
    from .outputs.evidence import ReportInputs

    cfg = _config(config)
    p = result.problem
    if bags is not None:
        paths = expand_bags(bags)
    else:
        paths = [Path(b) for b in dict.fromkeys(p.snapshot_bags) if b and Path(b).exists()]
    size = lambda q: q.stat().st_size if q.is_file() else sum(f.stat().st_size for f in q.rglob("*") if f.is_file())  # noqa: E731
    cams = [s.topic for s in p.sensors if s.is_camera]
    command = "\n".join(x for x in (call, f"process: {shlex.join(sys.argv)}") if x)
    material = dict(material or {})
    if "snapshots" not in material and result.method == "target" and paths:
        material.update(_read_report_snapshots(p))
    nominal, source = {}, ""
    if p.priors:
        nominal, source = {q.sensor: np.asarray(q.rt_lidar0_sensor, float) for q in p.priors}, "/tf_static (the priors')"
    elif result.method == "target" and paths:
        try:  # /tf_static is static: the first bag's (reading every bag's costs a second on 20 bags)
            nominal = nominal_poses(paths[:1], p.sensors)
            source = f"/tf_static of {paths[0].name}" if nominal else ""
        except Exception as e:  # the nominal poses only add to the report: never lose the calibration
            log.warning("report: no nominal poses from /tf_static (%s)", str(e).splitlines()[0] if str(e) else e)
    return ReportInputs(bags=tuple((str(q), size(q)) for q in paths if q.exists()),
                        models=tuple(zip(cams, map(str, models or [cameras.FROM_CAMERA_INFO] * len(cams)))),
                        command=command, config_yaml=cfg.to_yaml(), snapshots=material.get("snapshots", {}),
                        sources=material.get("sources", {}) or {k: b for k, b in enumerate(p.snapshot_bags)},
                        rt_nominal=nominal, nominal_source=source)


def _read_report_snapshots(problem: Problem) -> dict:
    """read_problem's report material, read again from the bags the problem names: the snapshots the
    report draws (``_report_snapshots``), each topic's message nearest the snapshot's stamp."""
    from .export_mcap import snapshot_messages
    from .types import Image, Snapshot

    out: dict = {}
    topics = [s.topic for s in problem.sensors]
    for k in sorted(_report_snapshots(problem.sensors, problem.lidar_observations, problem.camera_observations)):
        bag = problem.snapshot_bags[k] if k < len(problem.snapshot_bags) else ""
        if not bag or not Path(bag).exists():
            continue
        try:
            msgs = snapshot_messages(Path(bag), topics, int(problem.snapshot_stamps_ns[k]))
        except Exception as e:  # noqa: BLE001 - a picture less, never a lost calibration
            log.warning("report: snapshot %d not read again from %s (%s)", k, bag, e)
            continue
        out[k] = Snapshot(index=k, stamp_ns=int(problem.snapshot_stamps_ns[k]), source=bag, bag=bag,
                          scans={t: m for t, m in msgs.items() if not isinstance(m, Image)},
                          images={t: m for t, m in msgs.items() if isinstance(m, Image)})
    return {"snapshots": out}


def check_out_dir(out, *, kind: str = "results", force: bool = False) -> None:
    """Fail before the work, not after it, when ``out`` cannot be made or is not ours to replace."""
    import os

    from .outputs.atomic import check_out_dir as _check

    target = _check(out, kind=kind, force=force)
    parent = target.parent
    while not parent.exists():
        parent = parent.parent
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{out}: cannot write the output directory here; choose another --out")


def summary_table(result: Result) -> str:
    """The table `clcgraph solve` / `clcgraph targetless` print (outputs/tables.py)."""
    from .outputs.tables import summary_table as _table

    return _table(result)


# ---------------------------------------------------------------- the rest of the public API


def simulate(rig_yaml, out_dir, **kwargs):
    """Simulate a capture session of a rig into bags (see clcgraph.sim.capture.simulate)."""
    from .sim.capture import simulate as _simulate

    return _simulate(rig_yaml, out_dir, **kwargs)


def calibrate_targetless(bags, *, mapping_topic: str, calibration_topics, base_frame: str | None = None,
                         out=None, config=None, force: bool = False) -> Result:
    """Targetless LIDAR-LIDAR (+ base_link) calibration from a drive (clcgraph.targetless.pipeline),
    written like `clcgraph solve`'s when ``out`` is given (checked before the drive is mapped)."""
    from .targetless.pipeline import calibrate_targetless as _targetless

    cfg = _config(config)
    if out is not None:
        check_out_dir(out, force=force)
    result = _targetless(expand_bags(bags), mapping_topic=mapping_topic, calibration_topics=list(calibration_topics),
                         base_frame=base_frame, config=cfg)
    if out is not None:
        with StageClock(result.stats["stage_time_s"])("report"):
            call = (f"clcgraph.calibrate_targetless({[str(b) for b in bags] if not isinstance(bags, (str, Path)) else str(bags)!r}, "
                    f"mapping_topic={mapping_topic!r}, calibration_topics={list(calibration_topics)!r}, "
                    f"base_frame={base_frame!r}, out={str(out)!r})")
            write_outputs(result, out, cfg, force=force, report_inputs=gather_report_inputs(result, cfg, bags=bags, call=call))
    return result


@single_threaded_blas()
def replay(dump, *, inject_noise: bool = False, fit_seed: bool = False, exclude=(), seed: int = 0) -> Result:
    """Re-solve a problem dump (problem.npz, or the --out directory holding it) with the dump's
    settings: `clcgraph replay` (backend/replay.py). A targetless output has no dump: InputError."""
    from .backend.replay import replay_problem
    from .outputs.dump import load_problem

    path = Path(dump)
    if path.is_dir():
        if not (path / "problem.npz").exists() and (path / "calibration.yaml").exists() \
                and load_result(path).method == "targetless":
            raise InputError(f"{path}: a targetless calibration has no problem dump to re-solve (that is "
                             "`clcgraph solve`'s problem.npz); its 1-sigmas are in calibration.yaml and report.html")
        path = path / "problem.npz"
    problem, config = load_problem(path)
    return replay_problem(problem, config.solve, inject_noise=inject_noise, fit_seed=fit_seed, exclude=exclude,
                          seed=seed)


def compare_to_truth(result: Result, truth: dict) -> list[dict]:
    """Per sensor: rotation error (deg), translation error (mm) and their 1-sigmas against a
    simulator truth.yaml (``truth``: its parsed dict).

    The errors compose (angle of R_truth^T R, distance between the origins); the sigmas are the
    root-sum-square of the per-axis sigmas (geometry.pose_stdevs): the RMS size of the error
    the uncertainty predicts.
    """
    from .geometry import T_from_rt, pose_difference, pose_stdevs

    want = {s["topic"]: np.asarray(s["rt_lidar0_sensor"], float) for s in truth["sensors"]}
    rows = []
    for i, sensor in enumerate(result.problem.sensors):
        if sensor.topic not in want:
            continue
        rt = np.asarray(result.rt_lidar0_sensor[i], float)
        rot, dist = pose_difference(T_from_rt(want[sensor.topic]), T_from_rt(rt))
        sd_rot, sd_pos = pose_stdevs(rt, result.covariance_block(i))
        rows.append({"topic": sensor.topic, "rotation_deg": float(np.degrees(rot)), "translation_mm": dist * 1e3,
                     "sigma_deg": float(np.degrees(np.linalg.norm(sd_rot))), "sigma_mm": float(np.linalg.norm(sd_pos) * 1e3)})
    return rows


def run_demo(out=None, *, config=None, seed: int = 0, force: bool = False) -> tuple[Result, list[dict]]:
    """`clcgraph demo`: simulate data/synthetic/demo if missing (or of another board), calibrate it,
    compare to truth."""
    import fcntl

    from .sim.capture import DEMO_DIR, DEMO_RIG, simulate_demo
    from .sim.rig import load_rig

    out = out or DEMO_DIR.parent / "demo-out"
    check_out_dir(out, kind="results", force=force)  # before a minute of simulating
    truth_path = DEMO_DIR / "truth.yaml"

    def stale() -> bool:  # simulated once; again when the rig's board changed (an older clcgraph's)
        return not truth_path.exists() or \
            read_yaml(truth_path, "demo truth", mapping="of sensors").get("board") != load_rig(DEMO_RIG).board.spec()

    if stale():
        # demos started at once (a test run's workers) wait for one simulation, not fail on its lock
        with open(DEMO_DIR.parent / ".demo-simulation.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if stale():
                simulate_demo(seed=seed)
    truth = read_yaml(truth_path, "demo truth", mapping="of sensors")
    topics = [s["topic"] for s in truth["sensors"]]
    models = [DEMO_RIG.parent / s["model"] for s in truth["sensors"] if s["kind"] == "camera"]
    result = calibrate_bags([DEMO_DIR / "*.bag"], topics, models, out=out,
                            config=config, force=force)
    return result, compare_to_truth(result, truth)


def compare(a, b, *, config=None):
    """Has the calibration changed? Per sensor pose difference, chi-square test, verdict
    (clcgraph.comparison.compare: a, b results, output directories, calibration.yaml or a bag)."""
    from .comparison import compare as _compare

    return _compare(a, b, config=config)


def write_comparison_yaml(comparison, path) -> Path:
    """``comparison.to_dict()`` as YAML (what `clcgraph compare --yaml` writes), whole or not at all:
    a new file, or one clcgraph may have written."""
    from .comparison import write_yaml
    from .outputs.atomic import check_out_file

    path = check_out_file(path, ".yaml", flag="--yaml")
    return write_yaml(comparison.to_dict(), path)


def calibrate_fleet(manifest, out, *, cluster: str | None = None, workers: int | None = None,
                    resume: bool = False) -> dict:
    """`clcgraph fleet`: the manifest and ``out`` are checked before a cluster is reached; then
    clcgraph.fleet.calibrate_fleet on the Dask cluster ``cluster`` (tcp://host:port or local:N),
    else in this process (``workers=0``) or on a local pool of ``workers`` processes."""
    import contextlib

    from .fleet import Manifest, SerialExecutor, calibrate_fleet as _fleet, dask_executor

    manifest = Manifest.load(manifest)
    check_out_dir(out, kind="fleet", force=None)
    with dask_executor(cluster) if cluster else contextlib.nullcontext() as ex:
        if ex is None and workers == 0:
            ex = SerialExecutor()
        return _fleet(manifest, out, ex, resume=resume, workers=workers or None)


def load_result(out_dir):
    """Read a calibration written by `clcgraph solve` or `clcgraph targetless` (calibration.yaml),
    schema-checked: an outputs.results.Calibration, the same type whichever method made it."""
    from .outputs.results import load_result as _load

    return _load(out_dir)


# ---------------------------------------------------------------- the commands' wiring (cli/ only parses and prints)


def lidar_scans(bags, topic: str, *, every: bool = False, limit: int | None = None,
                names: list | None = None, snapshot_options=None, still_intervals: bool = False) -> list:
    """The scans of a PointCloud2 topic: the first of each bag (or every one); InputError if the
    topic holds something else. ``names``: if given, filled with each scan's bag file name.
    ``snapshot_options``: the first of each bag averaged with its next still ones, as the solve's
    snapshots take it (``snapshots.still_average``); with ``still_intervals`` too, a continuous
    bag gives one scan per still interval, as the solve's snapshots do (judged by this LIDAR alone;
    named "BAG still START-ENDs")."""
    from .frontend.bag import leading_messages, read_messages
    from .frontend.snapshots import continuous_snapshots, recordings, still_average
    from .types import LidarScan

    paths = expand_bags(bags)[:limit]
    if every:
        msgs = list(read_messages(paths, [topic]))
        scans, where = [m.data for m in msgs], [m.bag for m in msgs]
    else:
        n = snapshot_options.max_scans_averaged if snapshot_options is not None else 1
        scans, where = [], []
        for group in (recordings(paths) if still_intervals else [[b] for b in paths]):
            still = continuous_snapshots(group, [topic], snapshot_options) if still_intervals else None
            if still:  # the solve's snapshots of a continuous recording
                scans += [s.scans.get(topic) for s in still]
                where += [s.source for s in still]
                continue
            for b in group:
                ms = leading_messages(b, [topic], {topic: n}).get(topic)
                scans.append(None if ms is None else still_average(ms, snapshot_options))
                where.append(b)
    if names is not None:
        names[:] = [_bag_name(b) for b in where]
    bad = next((i for i, x in enumerate(scans) if not isinstance(x, LidarScan)), None)
    if bad is not None:
        where = paths[bad] if not every else ", ".join(map(str, paths))
        what = "no message" if scans[bad] is None else type(scans[bad]).__name__
        raise InputError(f"{where}: topic {topic} holds {what}, not sensor_msgs/PointCloud2")
    return scans


def _bag_name(path) -> str:
    """A bag file's (or ROS 2 bag directory's) own name, for people."""
    return Path(str(path).rstrip("/")).name


def bag_summaries(paths) -> list:
    """`clcgraph show-bag`: per bag, (BagInfo, {PointCloud2 topic: its first raw message})."""
    from .frontend.bag import POINTCLOUD2, bag_info, first_raw_message

    out = []
    for path in paths:
        info = bag_info(path)
        out.append((info, {t.topic: first_raw_message(path, t.topic) for t in info.topics
                           if t.msgtype == POINTCLOUD2 and t.count}))
    return out


def write_bag_previews(paths, out_dir) -> list[Path]:
    """Each LIDAR's first scan and each camera's first image of every bag, as PNGs in ``out_dir``."""
    from .frontend.bag import DECODABLE, bag_info, first_messages
    from .outputs.atomic import check_out_folder, make_out_folder
    from .outputs.plots import plot_image_preview, plot_scan_preview
    from .types import LidarScan

    out = check_out_folder(out_dir, flag="--png")
    written = []
    for path in paths:
        topics = [t.topic for t in bag_info(path).topics if t.msgtype in DECODABLE and t.count]
        for topic, m in first_messages(path, topics).items():
            name = make_out_folder(out, flag="--png") / f"{Path(path).stem}{topic.replace('/', '_')}.png"
            (plot_scan_preview if isinstance(m, LidarScan) else plot_image_preview)(
                m, name, title=f"{Path(path).name} {topic}")
            written.append(name)
    return written


def segment_bags(bags, topic: str, *, every: bool = False, config=None, dump=None, png=None) -> list:
    """`clcgraph segment`: (scan, LidarBoardObservation | Rejected, bag name) per scan; ``dump``: an
    npz of the intermediate stages; ``png``: a directory for a picture of each scan's segmentation."""
    from .frontend.lidar_board import Debug, segment_many
    from .outputs.atomic import check_out_file, check_out_folder, make_out_folder
    from .outputs.debug import write_segmentation_dump
    from .outputs.plots import plot_segmentation

    cfg = _config(config)
    names: list = []
    if dump:
        check_out_file(dump, ".npz", flag="--dump")
    if png:
        check_out_folder(png, flag="--png")
    scans = lidar_scans(bags, topic, every=every, names=names, snapshot_options=cfg.snapshots, still_intervals=True)
    debugs = [Debug() for _ in scans]
    results = segment_many(scans, cfg.segmentation, cfg.lidar, board_geometry(cfg), debug=debugs)
    if dump:
        write_segmentation_dump(dump, debugs)
    if png:
        make_out_folder(png, flag="--png")
        for k, (scan, r, dbg) in enumerate(zip(scans, results, debugs)):
            plot_segmentation(scan, dbg, r, Path(png) / f"{k:05d}_{scan.stamp_ns}.png")
    return list(zip(scans, results, names))


def detect_bags(bags, topic: str, *, every: bool = False, config=None, png=None) -> list:
    """`clcgraph detect`: (image, (N,2) corners | Rejected, bag name) per image (the first of each
    bag unless ``every``); ``png``: a directory for an annotated picture of each."""
    from .frontend.camera_board import detect_in_bags, draw_detection
    from .outputs.atomic import check_out_folder, make_out_folder

    cfg = _config(config)
    if png:
        import cv2

        check_out_folder(png, flag="--png")
    out = []
    for k, (im, res, bag) in enumerate(detect_in_bags(expand_bags(bags), topic, cfg.detection, board_geometry(cfg),
                                                      every=every, with_bag=True)):
        out.append((im, res, _bag_name(bag)))
        if png:
            make_out_folder(png, flag="--png")
            cv2.imwrite(str(Path(png) / f"{k:05d}_{im.stamp_ns}.png"), draw_detection(im, res))
    return out


def infer_lidar_spacing(bags, topic: str) -> tuple[int, int]:
    """(number of rings, Npoints_per_rotation) of a LIDAR topic, from its first scans."""
    from .frontend.lidar_preprocess import infer_lidar_spacing as _infer

    return _infer(lidar_scans(bags, topic, limit=5))


def format_for_ros(bag, calibration, *, base_frame: str = "base_link", rt_vehicle_lidar0=None,
                   base_source: str = "auto", full_urdf: bool = False, out=None, force: bool = False):
    """`clcgraph format-for-ros`: (the transforms under ``base_frame``, with ``base`` (where
    base_frame <- lidar0 came from, see outputs.ros.choose_base) and ``notes``; the files written
    into ``out`` (none without it)). Frames from the bag's header frame_ids and /tf_static; the
    frame_ids need not be in /tf_static when base_frame <- lidar0 comes from elsewhere
    (``rt_vehicle_lidar0``, mrcal rt; the calibration's ground plane or the solve's own
    sectors.rt_vehicle_lidar0)."""
    from .frontend.bag import frame_id, read_tf_static
    from .outputs.ros import format_for_ros as _format
    from .outputs.ros import infer_frames, ros_files

    cal = load_result(calibration)
    resolved = Path(calibration) / "config.resolved.yaml"  # the solve's own rt_vehicle_lidar0, if any
    solve_rt = ((read_yaml(resolved, "resolved config") or {}).get("sectors") or {}).get("rt_vehicle_lidar0") \
        if resolved.is_file() else None
    tf = read_tf_static(bag)
    elsewhere = rt_vehicle_lidar0 is not None or any(solve_rt or ()) or bool(cal.get("base_link"))
    frames = infer_frames(cal.topics, tf.frames, frame_ids={t: frame_id(bag, t) for t in cal.topics},
                          need_tf=base_source == "tf-static" or not elsewhere)
    ros = _format(cal, tf, base_frame=base_frame, frames=frames, rt_vehicle_lidar0=rt_vehicle_lidar0,
                  solve_rt_vehicle_lidar0=solve_rt, base_source=base_source, tf_name=str(bag))
    if not out:
        return ros, []
    from .outputs.atomic import atomic_dir

    files = ros_files(ros, full_urdf=full_urdf)
    with atomic_dir(out, kind="ros", force=force) as tmp:
        for name, text in files.items():
            (tmp / name).write_text(text)
    return ros, [Path(out) / name for name in files]


def write_aligned_mcap(bags, calibration, out, **kwargs) -> dict:
    """`clcgraph show-aligned --mcap`: /tf_static from the calibration and the clouds and images of
    chosen snapshots as one MCAP file (see clcgraph.export_mcap.write_aligned_mcap)."""
    from .export_mcap import write_aligned_mcap as _write

    return _write(bags, calibration, out, **kwargs)


def show_aligned(bag, calibration, *, topics=None, png, threshold_range: float | None = None,
                 force: bool = False) -> dict:
    """`clcgraph show-aligned`: the first scan of each LIDAR topic (default: every LIDAR of the
    calibration) moved into lidar0 by the calibration, drawn into ``png`` (a new PNG, or one
    clcgraph may have written, unless ``force``); returns the clouds."""
    from .frontend.bag import first_messages
    from .outputs.atomic import check_out_file
    from .outputs.plots import align_clouds, render_aligned_clouds

    check_out_file(png, ".png", flag="--png", force=force)
    cal = load_result(calibration)
    topics = list(topics or [s["topic"] for s in cal["sensors"] if s["kind"] == "lidar"])
    rts = {t: cal.sensor(t)["rt_lidar0_sensor"] for t in topics}
    camera = next((t for t in topics if cal.sensor(t)["kind"] != "lidar"), None)
    if camera is not None:
        raise InputError(f"{camera}: a camera; the PNG draws LIDAR clouds (--mcap FILE.mcap shows the cameras too)")
    first = first_messages(bag, topics)
    clouds = {}
    for t in topics:
        if t not in first:
            raise InputError(f"{bag}: no message on {t}")
        pts = first[t].points[first[t].valid]
        clouds[t] = pts if threshold_range is None else pts[np.linalg.norm(pts, axis=1) < threshold_range]
    render_aligned_clouds(clouds, rts, png)
    return align_clouds(clouds, rts)


def view_clouds(clouds: dict, *, title: str = "clcgraph") -> None:
    """The Open3D viewer on clouds (topic -> (N,3)), one colour each; InputError without a display."""
    import os

    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        raise InputError("--viewer needs a display (DISPLAY is not set); the PNG was written")
    import open3d as o3d

    geoms = []
    for k, pts in enumerate(clouds.values()):
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        pc.paint_uniform_color(np.eye(3)[k % 3] * 0.8)
        geoms.append(pc)
    o3d.visualization.draw_geometries(geoms, window_name=title)


def uncertainty_grid_png(dump, png, *, sensors: tuple[int, int] | None = None, radius: float = 20.0,
                         gridn: int = 41, z: float = 0.0):
    """`clcgraph show-uncertainty`: the worst-direction stdev of a point moved from sensor i to j
    over a grid around lidar0 (default: lidar0 and the worst other sensor), drawn into ``png``;
    returns (title, (gridn, gridn) stdev in m). ``png``: a new PNG, or one clcgraph may have written."""
    from .backend.sectors import uncertainty_grid
    from .outputs.atomic import check_out_file
    from .outputs.plots import plot_uncertainty_grid

    check_out_file(png, ".png", flag="--png")
    res = replay(dump)
    n = len(res.problem.sensors)
    if sensors is not None:
        i, j = sensors
        if not (0 <= i < n and 0 <= j < n and i != j):
            raise InputError(f"--sensors {i},{j}: need two different indices in 0..{n - 1}")
    else:
        i = res.problem.reference
        j = max((k for k in range(n) if k != i), key=lambda k: np.trace(res.covariance_block(k)[3:, 3:]))
    xs, ys, stdev = uncertainty_grid(res, i, j, radius=radius, gridn=gridn, z=z)
    title = f"{res.problem.sensor_name(i)} -> {res.problem.sensor_name(j)}"
    plot_uncertainty_grid(stdev, xs, ys, png, title=title)
    return title, stdev


def simulate_drive(out, *, duration_s: float = 60.0, small: bool = False, format: str = "ros1",
                   layout: str = "velodyne", seed: int = 0, force: bool = False):
    """`clcgraph simulate-drive`: a street drive into ``out`` (bag + truth.yaml); returns (the
    bag's path, the DrivePlan)."""
    from .outputs.atomic import atomic_dir
    from .sim.drive import DrivePlan, simulate_drive as _simulate, write_drive_bag, write_truth

    check_out_dir(out, kind="session", force=force)  # before the ray casting
    plan = DrivePlan.small(duration_s=duration_s) if small else DrivePlan(duration_s=duration_s)
    drive = _simulate(plan, seed=seed, progress=lambda items, desc: progress(items, desc=desc, total=len(items), unit="scan"))
    with atomic_dir(Path(out), kind="session", force=force) as tmp:
        bag = tmp / ("drive.bag" if format == "ros1" else "drive")
        write_drive_bag(drive, bag, format=format, layout=layout)
        write_truth(drive, tmp / "truth.yaml")
    return Path(out) / bag.name, plan
