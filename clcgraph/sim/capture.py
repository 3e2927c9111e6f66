"""Capture sessions: a person moves the chessboard in front of a simulated rig; bags + truth.

Two schemes, as people record them:
- one short bag per stationary board pose (clc's convention): each has /tf_static, two
  scans per LIDAR (10 Hz) and two images per camera (``camera_hz``), the first frame
  anywhere within the camera's period after the bag starts (recording starts at a random
  moment of each sensor's cycle);
- ``continuous=True``: one bag; the board holds each pose ``hold_s`` and moves to the next
  over ``move_s``; LIDARs at 10 Hz, cameras free-running at ``camera_hz`` (e.g. 5 or 15).
``log_delays`` (on by default): log times as drivers write them (``bag_writer.LogDelays``:
a scan one rotation after its stamp, a frame 20-35 ms after), so log order is not stamp
order across topics; off: log time = stamp.
Board poses are drawn 2.5-9 m from a sensor (a board smaller than 1.3 m proportionally
closer; half of them in front of a camera), tilted up to ``tilt_max_deg`` (about random axes, or
with ``planned_tilts`` as a careful person plans: pitched up and down, turned left and right in
turn), and kept if >= 2 sensors see the board (>= 3 rings / the whole corner
grid); with ``pair_boards`` = N, as the README asks of a capture, each pair of sensors sees it
together on >= N poses (where the rig lets them: a pair no draw puts the board before is
left out). /tf_static holds base_link -> every sensor frame, off the truth by ``tf_error``
(deg, m) like a CAD drawing. ``truth.yaml`` next to the bags has the true poses.

SYNOPSIS
    summary = simulate("rig.yaml", "out/", n_poses=20, seed=0, format="ros1")
    simulate_demo()            # data/synthetic/demo-rig.yaml -> data/synthetic/demo/
"""

from __future__ import annotations

import itertools
import logging
from pathlib import Path

import numpy as np
import yaml

from ..errors import InputError
from ..geometry import R_from_r, rt_from_T
from ..outputs.atomic import atomic_dir
from ..progress import progress
from .bag_writer import FORMATS, BagWriter, LogDelays, split_ros1_bag
from .camera import BAYER_ENCODINGS, bayer_mosaic, board_corners_px, render
from .lidar import simulate_scan
from .rig import Rig, load_rig
from .scene import make_scene, planned_tilt, random_board_pose, static_meshes

log = logging.getLogger(__name__)

T0_NS = 1_700_000_000_000_000_000
_RESTING_GAP_M = 0.002  # a board resting on the ground: its lowest corner this far above it
_PAIR_ATTEMPTS = 1000  # board poses drawn for a pair (pair_boards) before it is judged never to see one together
DEMO_RIG = Path(__file__).resolve().parents[2] / "data" / "synthetic" / "demo-rig.yaml"
DEMO_DIR = DEMO_RIG.parent / "demo"


def _board_pose(rng, rig: Rig, tilt_max_deg: float, vertical: bool = False, max_distance_m=None,
                tilt_towards_rad=None, aim=None) -> np.ndarray:
    """T_world_board: in front of a random camera (half the time) or anywhere around a LIDAR
    (``aim``: in front of this camera, or around this LIDAR);
    2.5-9 m away for a 1.3 m board, a smaller board proportionally closer (as people hold it).
    ``vertical``: the board plane exactly vertical (``random_board_pose``); ``max_distance_m``: at
    most this far (a capture plan for a low-resolution camera); ``tilt_towards_rad``: the planned
    tilt (``planned_tilt``)."""
    far = max(4.0, 9.0 * min(1.0, float(np.hypot(*rig.board.size_m)) / np.hypot(1.3, 1.3)))
    if max_distance_m is not None:
        far = min(far, float(max_distance_m))
    if any(aim is c for c in rig.cameras) or (aim is None and rig.cameras and rng.uniform() < 0.5):
        cam = aim if aim is not None else rig.cameras[rng.integers(len(rig.cameras))]
        fwd = cam.T_base_sensor[:3, :3] @ R_from_r(rng.normal(0, 0.25, 3)) @ np.array([0.0, 0.0, 1.0])
        return random_board_pose(rng, rig.board, cam.T_base_sensor[:3, 3], tilt_max_deg=tilt_max_deg, forward=fwd,
                                 distance_m=(2.5, far), vertical=vertical, tilt_towards_rad=tilt_towards_rad)
    L = aim if aim is not None else rig.lidars[rng.integers(len(rig.lidars))]
    return random_board_pose(rng, rig.board, L.T_base_sensor[:3, 3], tilt_max_deg=tilt_max_deg,
                             distance_m=(2.5, far), vertical=vertical, tilt_towards_rad=tilt_towards_rad)


def _pair_to_show(shown: dict, wanted: int, rng):
    """The pair of sensors that has seen the board together least, if fewer than ``wanted`` times
    (ties drawn at random), else None."""
    short = [p for p, n in shown.items() if n < wanted]
    if not short:
        return None
    least = min(shown[p] for p in short)
    short = [p for p in short if shown[p] == least]
    return short[rng.integers(len(short))]


def _aim(rig: Rig, pair, rng):
    """Where a person shows the board to both sensors of ``pair``: before its camera (one of
    them, at random, if both are), else around one of its LIDARs."""
    sensors = [s for s in (*rig.lidars, *rig.cameras) if s.topic in pair]
    cams = [s for s in sensors if any(s is c for c in rig.cameras)]
    pick = cams or sensors
    return pick[rng.integers(len(pick))]


def _lowest_z(rig: Rig, T: np.ndarray) -> float:
    xmin, xmax, ymin, ymax = rig.board.extent()
    corners = np.array([[x, y, 0.0] for x in (xmin, xmax) for y in (ymin, ymax)])
    return float((corners @ T[:3, :3].T + T[:3, 3])[:, 2].min())


def _rested_on_ground(rig: Rig, T: np.ndarray) -> np.ndarray:
    """``T`` moved straight down (or up) until the board's lowest corner touches the ground: a
    person steadying the board on the floor."""
    T = T.copy()
    T[2, 3] -= _lowest_z(rig, T) - _RESTING_GAP_M
    return T


def _observe(rig: Rig, T_board, static, rng, stamps, sway=(0.0, 0.0)):
    """Scans and images of one board pose, and the topics of the sensors that see the board (and
    the truth corners of each camera's first frame). ``sway``: (m, deg) standard deviations of the
    board's pose about its centre, drawn anew for every message: the tremor of the hands holding
    it (0: the board is still, one scene for every message)."""
    still = make_scene(rig.board, T_board, rng, static=static, person=rig.person, arm=rig.arm)
    # a swaying board's scenes: the same person holding it (their draws from one seed), moved with it
    person_seed = int(rng.integers(1 << 62)) if any(sway) else None

    c = rig.board.corners().mean(axis=0)

    def at_message():  # (scene, board pose) of one message
        if not any(sway):
            return still, T_board
        D = np.eye(4)
        D[:3, :3] = R_from_r(np.radians(sway[1]) * rng.normal(size=3))
        D[:3, 3] = c - D[:3, :3] @ c + sway[0] * rng.normal(size=3)  # turned about the board's centre
        T = T_board @ D
        return make_scene(rig.board, T, np.random.default_rng(person_seed), static=static, person=rig.person,
                          arm=rig.arm), T

    seen = set()
    scans = {}
    for i, L in enumerate(rig.lidars):
        scans[L.topic] = []
        for m, t in enumerate(stamps["lidar"][i]):
            scan, hit = simulate_scan(L.model, L.T_base_sensor, at_message()[0], rng, stamp_ns=t, topic=L.topic)
            scans[L.topic].append(scan)
            if m == 0 and len(np.unique(scan.ring[hit])) >= 3:
                seen.add(L.topic)
    images, truth_corners = {}, {}
    for j, C in enumerate(rig.cameras):
        images[C.topic] = []
        for m, t in enumerate(stamps["camera"][j]):
            if m == 0 or any(sway):
                scene, T = at_message()
                img, corners = _render(C, scene, rig.board, T, rng, noise_sigma=0.0)  # noise per frame below
            if m == 0 and _in_image(corners, C.sensor) and _corners_unoccluded(scene, rig.board, T, C.T_base_sensor):
                seen.add(C.topic)
                truth_corners[C.topic] = corners
            images[C.topic].append(_noisy(img, t, rng, C.pixel_noise))
    return scans, images, truth_corners, seen


def _in_image(corners, camera) -> bool:
    """Whether every corner (None: one behind the camera) is at least 3 px inside the image."""
    w, h = camera.imagersize
    return corners is not None and bool(np.all(np.isfinite(corners)) and np.all((corners >= 3) & (corners <= [w - 4, h - 4])))


def _may_see(rig: Rig, T_board, topics, site) -> bool:
    """Whether every sensor of ``topics`` may see the board at T_board: its corners project into
    each camera, and nothing of ``site`` (the static scene, no board) stands between a sensor and
    the corners (a camera) or the board's centre (a LIDAR). A cheap test before a pose is
    rendered and scanned (the person and the rings that cross the board are not checked)."""
    for C in rig.cameras:
        if C.topic in topics:
            if not (_in_image(board_corners_px(C.sensor, C.T_base_sensor, rig.board, T_board), C.sensor)
                    and _corners_unoccluded(site, rig.board, T_board, C.T_base_sensor)):
                return False
    centre = T_board[:3, :3] @ rig.board.corners().mean(axis=0) + T_board[:3, 3]
    for L in rig.lidars:
        if L.topic in topics:
            d = centre - L.T_base_sensor[:3, 3]
            t_hit, _ = site.cast(np.r_[L.T_base_sensor[:3, 3], d / np.linalg.norm(d)][None])
            if t_hit[0] < np.linalg.norm(d) - 0.02:
                return False
    return True


def _corners_unoccluded(scene, board, T_board, T_camera) -> bool:
    """Whether the camera has a clear line of sight to every chessboard corner."""
    pw = board.corners() @ T_board[:3, :3].T + T_board[:3, 3]
    o = T_camera[:3, 3]
    d = pw - o
    dist = np.linalg.norm(d, axis=1)
    t_hit, gid = scene.cast(np.c_[np.broadcast_to(o, d.shape), d / dist[:, None]])
    return bool(np.all((gid == scene.board_id) | (t_hit >= dist - 0.02)))


def _noisy(img, stamp_ns, rng, sigma=2.0):
    from ..types import Image

    px = np.clip(img.pixels + rng.normal(0, sigma, img.pixels.shape), 0, 255).astype(np.uint8)
    return Image(img.topic, stamp_ns, px, img.encoding)


def _tf_static(rig: Rig, rng, tf_error) -> list:
    out = []
    for s in (*rig.lidars, *rig.cameras):
        E = np.eye(4)
        E[:3, :3] = R_from_r(rng.normal(0, np.radians(tf_error[0]) / np.sqrt(3), 3))
        E[:3, 3] = rng.normal(0, tf_error[1] / np.sqrt(3), 3)
        out.append(("base_link", s.frame_id, s.T_base_sensor @ E))
    return out


def _write(w: BagWriter, rig: Rig, scans, images):
    for L in rig.lidars:
        for s in scans[L.topic]:
            w.write_pointcloud(L.topic, s, frame_id=L.frame_id, layout=L.model.layout)
    for C in rig.cameras:
        for im in images[C.topic]:
            _write_image(w, C, im)


def simulate(rig_yaml, out_dir, *, n_poses: int = 20, seed: int = 0, format: str = "ros1", continuous: bool = False,
             tilt_max_deg: float = 40.0, tf_error=(1.0, 0.03), hold_s: float = 2.0, move_s: float = 1.0,
             camera_hz: float = 5.0, clutter: bool = True, compress: bool = False, log_delays: bool = True,
             vertical_boards: bool = False, max_distance_m: float | None = None, planned_tilts: bool = False,
             pair_boards: int = 0, indoor: bool = False, room_m=(6.0, 9.0), split_s: float | None = None,
             clock_offsets_s: dict | None = None, hand_sway=(0.0, 0.0), boards_on_ground: bool = False,
             force: bool = False) -> dict:
    """Simulate a capture session of the rig in ``rig_yaml`` into ``out_dir`` (replaced atomically).
    ``compress``: lz4-compressed ROS1 bags (as `rosbag record --lz4` writes them); ROS2: the storage
    file zstd-compressed (`ros2 bag record --compression-mode file --compression-format zstd`).
    ``log_delays``: drivers' log times (see the module docstring); False: log time = stamp.
    ``vertical_boards``: every board plane exactly vertical (one LIDAR's height then unobservable).
    ``max_distance_m``: boards at most this far from the sensor they are shown to (default 9 m
    for a 1.3 m board), e.g. for a low-resolution camera whose squares must stay >= ~5 px.
    ``planned_tilts``: boards tilted as a careful person plans them (``planned_tilt``: pitched up
    and down, turned left and right in turn, by half to all of ``tilt_max_deg``); False: each
    about a random axis by up to ``tilt_max_deg`` (as the demo and the stress set were simulated).
    ``pair_boards``: each pose held, while some pair of sensors has seen the board together on
    fewer poses than this, where that pair (the fewest so far) both see it: before its camera, or
    around one of its LIDARs (``_pair_to_show``); 0: wherever >= 2 sensors see it.
    ``indoor``: in a hall closed all round (``scene.static_meshes``): every LIDAR ray returns;
    ``room_m``: how far its walls are from the rig (6-9 m; a small lab's: boards close to a wall).
    ``split_s``: a continuous ROS1 session cut into files of this many seconds, as `rosbag record
    --split --duration` writes a long recording (``bag_writer.split_ros1_bag``).
    ``clock_offsets_s``: {topic: s}: that sensor's header stamps on another clock (``BagWriter``).
    ``hand_sway``: (m, deg) a bag per pose: the held board's position and angle about its centre
    differ by these standard deviations from message to message (a person's hands are not still).
    ``boards_on_ground``: every board rests on the ground, its lowest corner touching it (as people
    steady a large board), instead of being held >= 0.15 m above it.
    ``force``: replace ``out_dir`` even if it is not a previous simulated session.

    Returns the truth dict that is also written to ``out_dir/truth.yaml``.
    """
    if format not in FORMATS:
        raise InputError(f"unknown bag format {format!r}; use one of {', '.join(FORMATS)}")
    if not camera_hz > 0:
        raise InputError(f"camera_hz must be > 0, got {camera_hz}")
    if split_s is not None and not (continuous and format == "ros1" and split_s > 0):
        raise InputError(f"split_s {split_s}: a continuous ROS1 session's files of > 0 s (a ROS2 bag's files are "
                         "split inside one bag)")
    rig = rig_yaml if isinstance(rig_yaml, Rig) else load_rig(rig_yaml)
    rng = np.random.default_rng(seed)
    # timing draws of their own: the scenes stay those of the seed whatever the rates
    clock = np.random.default_rng([seed, 1])
    phases = {"lidar": [13_000_000 * i for i in range(len(rig.lidars))],
              "camera": [int(clock.uniform(0, 1e9 / camera_hz)) for _ in rig.cameras]}
    delays = LogDelays(seed=seed) if log_delays else None
    offsets = {t: int(round(s * 1e9)) for t, s in (clock_offsets_s or {}).items()}
    with atomic_dir(out_dir, kind="session", force=force) as tmp:
        static = static_meshes(rng, clutter=clutter, indoor=indoor, room_m=room_m)
        tf = _tf_static(rig, rng, tf_error)
        ext = ".bag" if format == "ros1" else ""
        snapshots = []
        if continuous:
            writer = BagWriter(tmp / f"session{ext}", format=format, compress=compress, log_delays=delays,
                               clock_offsets_ns=offsets)
            writer.__enter__()
            writer.write_tf_static(tf, stamp_ns=T0_NS)
        poses = []
        t_ns = T0_NS
        shown = {pair: 0 for pair in itertools.combinations(rig.topics, 2)} if pair_boards > 0 else {}  # poses each pair saw together
        site = make_scene(rig.board, None, rng, static=static, person=False) if shown else None
        for k in progress(range(n_poses), desc="simulating board poses", unit="pose"):
            pair = _pair_to_show(shown, pair_boards, rng)
            for attempt in range(200 if pair is None else _PAIR_ATTEMPTS + 200):
                if pair is not None and attempt == _PAIR_ATTEMPTS:  # the pair never both see it: leave it out
                    shown.pop(pair)
                    pair = None
                aim = None if pair is None else _aim(rig, pair, rng)
                T_board = _board_pose(rng, rig, tilt_max_deg, vertical_boards, max_distance_m,
                                      planned_tilt(k) if planned_tilts else None, aim=aim)
                if boards_on_ground:
                    T_board = _rested_on_ground(rig, T_board)
                elif _lowest_z(rig, T_board) < 0.15:
                    continue
                if pair is not None and not _may_see(rig, T_board, pair, site):
                    continue
                if continuous:
                    stamps = _ticks(phases, t_ns, t_ns + int(hold_s * 1e9), camera_hz)
                else:
                    t_ns = T0_NS + k * 10_000_000_000
                    stamps = {"lidar": [[t_ns + ph + m * 100_000_000 for m in range(2)] for ph in phases["lidar"]],
                              "camera": [[t_ns + int(clock.uniform(0, 1e9 / camera_hz)) + int(m * 1e9 / camera_hz)
                                          for m in range(2)] for _ in rig.cameras]}
                scans, images, corners, seen = _observe(rig, T_board, static, rng, stamps,
                                                        (0.0, 0.0) if continuous else hand_sway)
                if len(seen) >= 2 and (pair is None or set(pair) <= seen):
                    break
            else:
                raise InputError(f"{rig.path}: could not place a board that >= 2 sensors see; check the sensor poses")
            rt_l0_b = rt_from_T(np.linalg.inv(rig.lidars[0].T_base_sensor) @ T_board)
            if continuous:
                if poses:  # the move from the previous pose: scans and images while the board travels
                    _write_move(writer, rig, poses[-1], T_board, static, rng,
                                _ticks(phases, t_ns - int(move_s * 1e9), t_ns, camera_hz), t_ns - int(move_s * 1e9),
                                move_s)
                _write(writer, rig, scans, images)
                snapshots.append({"start_ns": int(t_ns), "end_ns": int(t_ns + hold_s * 1e9),
                                  "rt_lidar0_board": rt_l0_b.tolist(), "seen_by": len(seen),
                                  "seen_by_topics": sorted(seen)})
                t_ns += int((hold_s + move_s) * 1e9)
            else:
                name = f"pose{k:03d}{ext}"
                with BagWriter(tmp / name, format=format, compress=compress, log_delays=delays,
                               clock_offsets_ns=offsets) as w:
                    w.write_tf_static(tf, stamp_ns=t_ns)
                    _write(w, rig, scans, images)
                snapshots.append({"bag": name, "stamp_ns": int(t_ns), "rt_lidar0_board": rt_l0_b.tolist(),
                                  "seen_by": len(seen), "seen_by_topics": sorted(seen),
                                  "corners_px": {t: c.tolist() for t, c in corners.items()}})
            poses.append(T_board)
            for p in shown:
                shown[p] += set(p) <= seen
        if continuous:
            writer.__exit__(None, None, None)
            if split_s is not None:  # the session's files in place of the one bag
                split_ros1_bag(tmp / f"session{ext}", split_s)
                (tmp / f"session{ext}").unlink()
        truth = _truth(rig, tf, snapshots, format, continuous, seed)
        (tmp / "truth.yaml").write_text(yaml.safe_dump(truth, sort_keys=False, default_flow_style=None, width=200))
    return truth


def _ticks(phases, start_ns: int, stop_ns: int, camera_hz: float) -> dict:
    """Stamps in [start_ns, stop_ns) of free-running sensors: LIDARs at 10 Hz, cameras at ``camera_hz``,
    each on its own phase from T0_NS."""
    def grid(phase, period_ns):
        m = np.arange(np.ceil((start_ns - T0_NS - phase) / period_ns), np.ceil((stop_ns - T0_NS - phase) / period_ns))
        return [T0_NS + int(phase + round(k * period_ns)) for k in m]
    return {"lidar": [grid(ph, 100_000_000) for ph in phases["lidar"]],
            "camera": [grid(ph, 1e9 / camera_hz) for ph in phases["camera"]]}


def _write_move(w, rig, T_a, T_b, static, rng, stamps, t0_ns, move_s):
    """Scans and images at ``stamps`` (``_ticks``) while the board moves from T_a (at t0_ns) to T_b."""
    from ..geometry import T_from_rt

    rt_a, rt_b = rt_from_T(T_a), rt_from_T(T_b)

    def board_at(t):
        f = (t - t0_ns) * 1e-9 / move_s
        return T_from_rt((1 - f) * rt_a + f * rt_b)

    for i, L in enumerate(rig.lidars):
        for t in stamps["lidar"][i]:
            scene = make_scene(rig.board, board_at(t + 50_000_000), rng, static=static,  # mid-rotation
                               person=rig.person, arm=rig.arm)
            scan, _ = simulate_scan(L.model, L.T_base_sensor, scene, rng, stamp_ns=t, topic=L.topic)
            w.write_pointcloud(L.topic, scan, frame_id=L.frame_id, layout=L.model.layout)
    for j, C in enumerate(rig.cameras):
        for t in stamps["camera"][j]:
            Tm = board_at(t)
            scene = make_scene(rig.board, Tm, rng, static=static, person=rig.person, arm=rig.arm)
            img, _ = _render(C, scene, rig.board, Tm, rng, stamp_ns=t, noise_sigma=C.pixel_noise)
            _write_image(w, C, img)


def _render(C, scene, board, T_board, rng, *, noise_sigma: float, stamp_ns: int = 0):
    """render() of rig camera ``C`` as the rig describes it (colour, exposure gain, blur)."""
    return render(C.sensor, C.T_base_sensor, scene, board, T_board, rng, topic=C.topic, stamp_ns=stamp_ns,
                  colour=C.encoding != "mono8", noise_sigma=noise_sigma, gain=C.gain, blur_sigma_px=C.blur_px)


def _write_image(w: BagWriter, C, image) -> None:
    """One frame of camera ``C`` (a raw Bayer mosaic where its encoding is one), and its CameraInfo
    where the rig says its driver publishes one."""
    if C.encoding in BAYER_ENCODINGS:
        image = bayer_mosaic(image, C.encoding)
    w.write_image(C.topic, image, frame_id=C.frame_id, compressed=C.compressed)
    if C.camera_info:
        from ..cameras import ROS_DISTORTION
        from ..frontend.bag import camera_info_topic

        fx, fy, cx, cy, *D = C.sensor.intrinsics
        w.write_camera_info(camera_info_topic(C.topic), stamp_ns=image.stamp_ns, frame_id=C.frame_id,
                            size=C.sensor.imagersize, K=[[fx, 0, cx], [0, fy, cy], [0, 0, 1]],
                            distortion_model=ROS_DISTORTION[C.sensor.lensmodel], D=D)


def _truth(rig: Rig, tf, snapshots, format, continuous, seed) -> dict:
    sensors = []
    for s in (*rig.lidars, *rig.cameras):
        sensors.append({"topic": s.topic, "kind": "lidar" if s in rig.lidars else "camera", "frame_id": s.frame_id,
                        "rt_lidar0_sensor": rt_from_T(rig.T_lidar0_sensor(s.topic)).tolist(),
                        "T_base_sensor": s.T_base_sensor.tolist(),
                        **({"model": str(s.model_path)} if s in rig.cameras else {})})
    return {"rig": str(rig.path), "format": format, "continuous": continuous, "seed": seed,
            "reference": rig.lidars[0].topic, "topics": rig.topics,
            "board": rig.board.spec(),  # the config's board: section for this session
            "sensors": sensors,
            "tf_static": [{"parent": p, "child": c, "T": T.tolist()} for p, c, T in tf],
            "snapshots": snapshots}


def simulate_demo(out_dir=None, *, seed: int = 0, n_poses: int = 20) -> dict:
    """The demo session: data/synthetic/demo-rig.yaml, 20 bag-per-pose ROS1 bags (lz4, ~95 MB).
    The default folder (git-ignored, written only by this function) is replaced even when an older
    clcgraph wrote it without the output marker."""
    return simulate(DEMO_RIG, out_dir or DEMO_DIR, n_poses=n_poses, seed=seed, compress=True,
                    force=out_dir is None)
