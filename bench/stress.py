"""The stress set: simulated captures that vary what real recordings vary, run through the
CLI with DEFAULT settings (only the board described; one capture, vertical-boards-planes, also
what its user would set: ``Capture.settings``), judged against the simulator's truth.

Each capture either (a) returns every sensor within the accuracy bar (target-based 0.1 deg /
5 mm, targetless 0.02 deg / 3 mm) and within 3 of its reported sigmas, or (b) is refused:
exit 2 with one line naming the sensor or direction and why. Anything else fails the set;
a result off by more than 5 sigma or 5 cm is a *silent wrong answer*, the worst outcome.
Exact sigmas put some captures past 3 sigma by chance (one axis in 370; a capture has 12-30): the
table's last line (``honesty``) counts them over the set against that chance.

    python -m bench.stress                 # every capture, table on stdout
    python -m bench.stress lidar-only-3    # the named ones
    python -m bench.stress --set solve.refuse_inconsistent=true   # extra settings for every solve
    python -m bench.stress --seed 2        # the same recipes drawn again (build/stress-seed2/)
    python -m bench stress                 # the same, as one of the benchmarks

Captures are simulated once into build/stress/<name>/ (kept while the recipe is unchanged).
The CLI runs the code of the checkout this file is in (PYTHONPATH), as it is when each capture
starts: to keep editing during a run, run it from a worktree of the commit to judge
(``git worktree add --detach /tmp/st HEAD; cd /tmp/st; /path/to/.venv/bin/python -m bench.stress``).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from clcgraph.cameras import FROM_CAMERA_INFO

ROOT = Path(__file__).resolve().parents[1]
BUILD = ROOT / "build" / "stress"

# Lens models of the stress rigs (mrcal .cameramodel contents): name -> (lensmodel, intrinsics, imagersize)
LENSES = {
    "mono1024": ("LENSMODEL_OPENCV8", [1000, 1000, 511.5, 383.5, -0.05, 0.01, 0.0001, -0.0001, 0.001, 0, 0, 0],
                 (1024, 768)),
    "colour640": ("LENSMODEL_OPENCV4", [520, 520, 319.5, 239.5, -0.12, 0.03, 0.0003, -0.0002], (640, 480)),
    # a 640x480 sensor 2x2-binned: half the focal length and resolution
    "binned320": ("LENSMODEL_OPENCV4", [215, 215, 159.5, 119.5, -0.15, 0.04, 0.0002, 0.0001], (320, 240)),
    "wide800": ("LENSMODEL_OPENCV8", [430, 430, 399.5, 299.5, -0.2, 0.04, 0.0002, -0.0003, -0.002, 0, 0, 0],
                (800, 600)),
}


@dataclass(frozen=True)
class Capture:
    """One stress capture: a rig (the sim's rig YAML as a dict, lenses by LENSES name), how it
    is recorded (clcgraph.sim.capture.simulate keywords), and what counts as success."""

    name: str
    what: str  # what real recordings vary here
    rig: dict = field(default_factory=dict)
    simulate: dict = field(default_factory=dict)
    board: dict | None = None  # the board section of the config (None: the default board)
    # targetless captures: simulate-drive arguments instead of a rig
    drive: dict | None = None
    # a capture built so that a direction is unobservable: success is exit 2, not a result
    must_refuse: bool = False
    # settings a user would give for this recording beyond the board (``section.key=value``)
    settings: tuple[str, ...] = ()


def _lidar(topic, model, xyz, rpy=(0, 0, 0), **kw):
    return {"topic": topic, "model": model, "xyz": list(xyz), "rpy_deg": list(rpy), **kw}


def _camera(topic, lens, xyz, rpy=(0, 0, 0), **kw):
    return {"topic": topic, "model": f"{lens}.cameramodel", "xyz": list(xyz), "rpy_deg": list(rpy), **kw}


TOP = _lidar("/lidar/top/points", "vlp16", (1.0, 0.0, 1.9))
BUMPER = _lidar("/lidar/front/points", "hdl32", (2.3, 0.35, 0.9), (2, 8, 15), layout="ouster")
CAM_FRONT = _camera("/cam/front/image", "mono1024", (1.6, -0.2, 1.5), (0, 4, -5))
CAM_COLOUR = _camera("/cam/colour/image/compressed", "colour640", (1.5, 0.4, 1.55), (0, 2, 25),
                     encoding="bgr8", compressed="jpeg")

CAPTURES = [
    Capture("baseline", "the demo's kind of rig: 2 LIDARs + 2 cameras, bag per pose",
            rig={"lidars": [TOP, BUMPER], "cameras": [CAM_FRONT, CAM_COLOUR]}, simulate={"n_poses": 16}),
    Capture("careful-operator", "the same rig recorded as the README asks: boards pitched and turned in turn, "
            "every sensor pair seeing the board together on >= 3 of the 16 poses (`baseline` takes what the "
            "draw gives: its cameras often share 0-2 boards)",
            rig={"lidars": [TOP, BUMPER], "cameras": [CAM_FRONT, CAM_COLOUR]},
            simulate={"n_poses": 16, "planned_tilts": True, "pair_boards": 3}),
    Capture("lidar-only-3", "LIDAR-only rig: VLP-16 front, 64-ring organised Ouster on the roof, VLP-16 rear "
            "(front and rear never see the board together; the rear one sees some boards' backs: an 18 mm "
            "plywood board, its thickness described as the README asks)",
            rig={"lidars": [_lidar("/front/points", "vlp16", (3.6, 0.0, 0.7), (0, 3, 0)),
                            _lidar("/roof/points", "os1-64", (1.2, 0.0, 2.0), (0, 0, 90), layout="ouster"),
                            _lidar("/rear/points", "vlp16", (-1.0, 0.0, 0.7), (0, 3, 180))]},
            board={"corners": [10, 10], "square_m": 0.1, "size_m": [1.3, 1.3], "thickness_m": 0.018},
            simulate={"n_poses": 24}),
    Capture("upright-boards", "boards never tilted by the person (faced to the sensor, so only the height "
            "difference tilts them): the vertical offset rests on a few degrees of tilt",
            rig={"lidars": [TOP, BUMPER]}, simulate={"n_poses": 14, "tilt_max_deg": 0.0}),
    Capture("rolled-cameras", "cameras mounted portrait (rolled 90 deg) and upside-down",
            rig={"lidars": [TOP],
                 "cameras": [_camera("/cam/portrait/image", "mono1024", (1.6, -0.2, 1.5), (90, 4, -5)),
                             _camera("/cam/upside_down/image", "colour640", (1.5, 0.4, 1.55), (180, 2, 25),
                                     encoding="bgr8")]},
            simulate={"n_poses": 16}),
    Capture("small-colour-continuous", "a 320x240 2x2-binned colour camera in a continuous capture at 15 Hz",
            rig={"lidars": [TOP], "cameras": [_camera("/cam/small/image", "binned320", (1.5, 0.3, 1.5), (0, 3, 15),
                                                      encoding="bgr8")]},
            # held within 4.5 m, as a person watching this camera's preview would: its squares stay >= 5 px
            simulate={"n_poses": 10, "continuous": True, "camera_hz": 15.0, "hold_s": 1.2, "move_s": 0.6,
                      "format": "ros2-mcap", "max_distance_m": 4.5}),
    Capture("continuous-5hz", "one continuous ROS2 bag, cameras at 5 Hz",
            rig={"lidars": [TOP, BUMPER], "cameras": [CAM_FRONT]},
            simulate={"n_poses": 10, "continuous": True, "camera_hz": 5.0, "hold_s": 1.5, "move_s": 0.6,
                      "format": "ros2-sqlite3"}),
    Capture("noisy-lidars", "LIDARs noisier than the defaults assume, with 5 % dropouts",
            rig={"lidars": [dict(TOP, range_noise_m=0.025, dropout=0.05), dict(BUMPER, range_noise_m=0.03,
                                                                              dropout=0.05)],
                 "cameras": [CAM_FRONT]},
            simulate={"n_poses": 16}),
    Capture("wide-camera-far", "a wide 86-deg camera whose boards are small, beside a 64-ring LIDAR",
            rig={"lidars": [_lidar("/os/points", "os1-64", (1.0, 0.0, 1.8), layout="ouster")],
                 "cameras": [_camera("/cam/wide/image", "wide800", (1.4, 0.0, 1.5), (0, 6, 0))]},
            simulate={"n_poses": 16}),
    Capture("drive-short", "targetless: a 10 s drive", drive={"duration": 10.0}),
    Capture("person-behind-arm", "a non-square board, pattern off-centre on it (9x6 corners of 0.1 m on "
            "1.2 x 0.9 m) held by a person standing behind it, an arm across its edge",
            rig={"lidars": [_lidar("/os/points", "os1-64", (1.2, 0.0, 2.0), layout="ouster")], "cameras": [CAM_FRONT],
                 "scene": {"person": "behind", "arm": True}},
            board={"corners": [9, 6], "square_m": 0.1, "size_m": [1.2, 0.9], "pattern_offset_m": [0.03, -0.02]},
            simulate={"n_poses": 16}),
    Capture("person-beside-arm", "a square bordered board held by a person beside it, an arm across its edge",
            rig={"lidars": [TOP, BUMPER], "scene": {"person": "beside", "arm": True}},
            board={"corners": [8, 8], "square_m": 0.1, "size_m": [1.1, 1.1]}, simulate={"n_poses": 14}),
    Capture("bag-per-pose-5hz", "cameras at 5 Hz, a bag per pose (~0.2-0.4 s long), drivers' log delays",
            rig={"lidars": [TOP, BUMPER], "cameras": [CAM_COLOUR]}, simulate={"n_poses": 20, "camera_hz": 5.0}),
    Capture("vertical-boards", "every board exactly vertical: planes leave the LIDARs' relative height "
            "unobservable, the board's outline gives it",
            rig={"lidars": [TOP, BUMPER]}, simulate={"n_poses": 12, "vertical_boards": True}),
    Capture("vertical-boards-planes", "the same boards, planes only (a board whose outline the LIDAR cannot "
            "see, e.g. in a frame that returns too): the height must be refused, naming the direction",
            rig={"lidars": [TOP, BUMPER]}, simulate={"n_poses": 12, "vertical_boards": True}, must_refuse=True,
            settings=("solve.lidar_edges=false",)),
    Capture("ring-bias-elevation", "per-ring range bias (sd 2 cm) and ring elevation errors (sd 0.1 deg)",
            rig={"lidars": [dict(TOP, ring_range_bias_m=0.02, ring_elevation_error_deg=0.1, errors_seed=3),
                            dict(BUMPER, ring_range_bias_m=0.015, ring_elevation_error_deg=0.1, errors_seed=4)],
                 "cameras": [CAM_FRONT]}, simulate={"n_poses": 16}),
    Capture("tails-dark-mixed", "heavy-tailed returns (2 % at 10x the noise), dark squares returning 1.5 cm "
            "long, mixed pixels (up to 10 cm) at the board's edge",
            rig={"lidars": [dict(TOP, heavy_tail_fraction=0.02, dark_range_bias_m=0.015, mixed_pixel_m=0.1),
                            dict(BUMPER, heavy_tail_fraction=0.02, dark_range_bias_m=0.02, mixed_pixel_m=0.1)],
                 "cameras": [CAM_FRONT]}, simulate={"n_poses": 16}),
    Capture("dark-squares-lost", "a board whose dark squares mostly return nothing (8 in 10 of their returns lost: "
            "a black print that absorbs the laser, or a laminated one that mirrors it away), weak and 1.5 cm long "
            "where they do return",
            rig={"lidars": [dict(TOP, dark_range_bias_m=0.015, dark_dropout=0.8),
                            dict(BUMPER, dark_range_bias_m=0.015, dark_dropout=0.8)],
                 "cameras": [CAM_FRONT]}, simulate={"n_poses": 16}),
    Capture("pcl-xyz-dark-squares", "both LIDARs recorded after a PCL filter node as pcl::PointXYZ (no intensity, "
            "ring or time), their boards' dark squares returning 1.5 cm long: nothing in the clouds tells the squares "
            "apart", rig={"lidars": [dict(TOP, layout="pcl_xyz", dark_range_bias_m=0.015),
                                     dict(BUMPER, layout="pcl_xyz", dark_range_bias_m=0.015)],
                          "cameras": [CAM_FRONT]}, simulate={"n_poses": 16}),
    Capture("indoor-hall", "indoors: a hall closed all round, walls 6-9 m away up to a ceiling 3.4-4 m high (every "
            "LIDAR ray returns: no dropouts either), boards within 5 m",
            rig={"lidars": [dict(TOP, dropout=0.0), dict(BUMPER, dropout=0.0)], "cameras": [CAM_FRONT]},
            simulate={"n_poses": 16, "indoor": True, "max_distance_m": 5.0}),
    Capture("dual-return", "the roof VLP-16 left in dual-return mode: two returns of every ray in one cloud",
            rig={"lidars": [dict(TOP, dual_returns=True), BUMPER], "cameras": [CAM_FRONT]},
            simulate={"n_poses": 16}),
    Capture("continuous-split", "one continuous ROS1 recording split into 7 s files (rosbag record --split "
            "--duration 7): pauses cut by the file boundaries; /tf_static only in the first file",
            rig={"lidars": [TOP, BUMPER], "cameras": [CAM_FRONT]},
            simulate={"n_poses": 12, "continuous": True, "split_s": 7.0}),
    Capture("ouster-boot-clock", "one continuous ROS1 recording; the bumper LIDAR stamps its scans on its own clock "
            "(an Ouster's default TIME_FROM_INTERNAL_OSC: seconds since it booted), the others on ROS time",
            rig={"lidars": [TOP, BUMPER], "cameras": [CAM_FRONT]},
            simulate={"n_poses": 12, "continuous": True, "clock_offsets_s": {"/lidar/front/points": 42.0 - 1.7e9}}),
    Capture("unsynced-camera-clock", "one continuous ROS1 recording; the camera's computer is not time-synchronised: "
            "its frames are stamped 3 s behind ROS time (the LIDARs')",
            rig={"lidars": [TOP, BUMPER], "cameras": [CAM_FRONT]},
            simulate={"n_poses": 12, "continuous": True, "clock_offsets_s": {"/cam/front/image": -3.0}}),
    Capture("camera-info-no-models", "the cameras' drivers publish CameraInfo beside their images (plumb_bob and "
            "rational_polynomial) and the user gives no camera model file",
            rig={"lidars": [TOP, BUMPER], "cameras": [{**CAM_FRONT, "camera_info": True},
                                                      {**CAM_COLOUR, "camera_info": True}]},
            simulate={"n_poses": 16}),
    Capture("camera-info-mixed", "one camera's model from a file the user calibrated, the other's from the "
            "CameraInfo its driver publishes (camera_info given in its place among the models)",
            rig={"lidars": [TOP, BUMPER], "cameras": [CAM_FRONT, {**CAM_COLOUR, "camera_info": True}]},
            simulate={"n_poses": 16}),
    Capture("sideways-lidar", "a blind-spot VLP-16 mounted on its side (rolled 90 deg, its rings vertical fans), "
            "an upside-down one at the rear (rolled 180 deg), beside the roof LIDAR and a camera",
            rig={"lidars": [TOP, _lidar("/lidar/side/points", "vlp16", (1.5, -0.9, 1.0), (90, 0, -60)),
                            _lidar("/lidar/rear/points", "vlp16", (-0.5, 0.0, 1.2), (180, 10, 180))],
                 "cameras": [CAM_FRONT]},
            simulate={"n_poses": 18, "pair_boards": 3}),
    Capture("bayer-camera", "a machine-vision camera publishing its raw Bayer mosaic (bayer_rggb8, red and "
            "blue at half of green, as a FLIR / Basler driver does without on-camera debayering) beside the "
            "mono and the colour camera",
            rig={"lidars": [TOP, BUMPER], "cameras": [CAM_FRONT, CAM_COLOUR,
                                                      _camera("/cam/raw/image_raw", "mono1024", (1.6, 0.6, 1.5),
                                                              (0, 3, 20), encoding="bayer_rggb8")]},
            simulate={"n_poses": 16, "pair_boards": 3}),
    Capture("dim-noisy-blurred-camera", "a camera exposed for a dim site (grey levels at 30 %) at high sensor gain "
            "(pixel noise 7 grey levels) and slightly out of focus or shaken (blur sigma 0.8 px), beside a "
            "well-exposed one",
            rig={"lidars": [TOP, BUMPER], "cameras": [CAM_FRONT, {**CAM_COLOUR, "gain": 0.3, "pixel_noise": 7.0,
                                                                   "blur_px": 0.8}]},
            simulate={"n_poses": 16, "pair_boards": 3}),
    Capture("mixed-lidar-noise", "an older roof VLP-16 ranging at 3.5 cm (worn, or a weak-return surface mode) "
            "beside a bumper LIDAR at 0.6 cm, and a camera",
            rig={"lidars": [dict(TOP, range_noise_m=0.035), dict(BUMPER, range_noise_m=0.006)],
                 "cameras": [CAM_FRONT]},
            simulate={"n_poses": 16, "pair_boards": 3}),
    Capture("pcl-xyzi-clouds", "both LIDARs recorded after a PCL filter node (pcl::PointXYZI: no ring or time "
            "field, invalid points dropped), as pipelines that crop or downsample the drivers' clouds record them",
            rig={"lidars": [dict(TOP, layout="pcl_xyzi"), dict(BUMPER, layout="pcl_xyzi")],
                 "cameras": [CAM_FRONT, CAM_COLOUR]},
            simulate={"n_poses": 16, "pair_boards": 3}),
    Capture("dual-return-organised", "both LIDARs in dual-return mode, the bumper one's cloud kept organised "
            "(each column followed by its second returns' column, the same rows)",
            rig={"lidars": [dict(TOP, dual_returns=True), dict(BUMPER, dual_returns=True)],
                 "cameras": [CAM_FRONT, CAM_COLOUR]},
            simulate={"n_poses": 16, "pair_boards": 3}),
    Capture("uneven-beams-hesai", "LIDARs whose beams are not evenly spaced, as most real units' are: a roof "
            "VLP-32C (0.33 deg apart about the horizon, 9.7 deg at the bottom) and a bumper Hesai Pandar40P in "
            "its driver's layout (absolute float64 point times, ring 0 the top beam), and a camera",
            rig={"lidars": [dict(TOP, model="vlp32c"), dict(BUMPER, model="pandar40p", layout="hesai")],
                 "cameras": [CAM_FRONT]},
            simulate={"n_poses": 16, "pair_boards": 3}),
    Capture("boards-on-the-ground", "every board resting on the ground, its lowest corner touching it (people "
            "steady a large board on the floor; the simulator otherwise holds it >= 0.15 m above): ground returns "
            "run up to the board's edge, and the roof LIDAR sees a low board only from a few metres away",
            rig={"lidars": [TOP, BUMPER], "cameras": [CAM_FRONT, CAM_COLOUR]},
            simulate={"n_poses": 16, "pair_boards": 3, "boards_on_ground": True}),
    Capture("small-lab", "a small lab: walls 5.5-6 m from the rig's centre all round, boards 2.5-3 m from the "
            "sensor they are shown to, so a wall stands a few decimetres to 3 m behind each board (returns right "
            "behind its edges; the board never leaves the walls' neighbourhood)",
            rig={"lidars": [TOP, BUMPER], "cameras": [CAM_FRONT, CAM_COLOUR]},
            simulate={"n_poses": 16, "pair_boards": 3, "indoor": True, "room_m": (5.5, 6.0),
                      "max_distance_m": 3.0}),
    Capture("counter-clockwise-lidars", "LIDARs spinning the other way (counter-clockwise seen from above: the "
            "azimuth rises along each ring, where every other capture's falls as a Velodyne's does), one unorganised, "
            "one organised",
            rig={"lidars": [dict(TOP, clockwise=False), dict(BUMPER, clockwise=False)],
                 "cameras": [CAM_FRONT, CAM_COLOUR]},
            simulate={"n_poses": 16, "pair_boards": 3}),
    Capture("drive-long", "targetless: a 30 s drive", drive={"duration": 30.0}),
]

# Small captures for CI (tests/cli/test_stress_ci.py): seconds each, end to end through the CLI.
CI_CAPTURES = [
    Capture("ci-continuous-lidars", "two LIDARs, one continuous ROS1 bag, no setting: cut into still "
            "intervals by motion",
            rig={"lidars": [TOP, BUMPER]},
            simulate={"n_poses": 10, "continuous": True, "hold_s": 1.2, "move_s": 0.6}),
    Capture("ci-vertical-boards", "exactly vertical boards: the outline gives the relative height",
            rig={"lidars": [TOP, BUMPER]}, simulate={"n_poses": 8, "vertical_boards": True}),
    Capture("ci-camera-info", "a camera whose driver publishes CameraInfo, no camera model file given for it "
            "(camera_info in its place), beside one with a model file",
            rig={"lidars": [TOP], "cameras": [{**CAM_FRONT, "camera_info": True}, CAM_COLOUR]}, simulate={"n_poses": 10}),
    Capture("ci-hand-sway", "a bag per pose, the board held by hands that are not still: from message to message "
            "(0.1-0.3 s apart) it moves by 1.5 mm and turns by 0.1 deg (sd) about its centre",
            rig={"lidars": [TOP], "cameras": [CAM_FRONT]},
            simulate={"n_poses": 12, "hand_sway": [0.0015, 0.1]}),
]

# ----------------------------------------------------------------------------------- running

@dataclass
class Outcome:
    name: str
    verdict: str  # ok | refused | INACCURATE | WRONG | FAILED
    detail: str
    rot_deg: float = float("nan")
    trans_mm: float = float("nan")
    sigma_deg: float = float("nan")
    sigma_mm: float = float("nan")
    max_z: float = float("nan")
    seconds: float = 0.0
    z: tuple = ()  # every answered sensor's per-axis z (error / reported sigma)


def _recipe_key(c: Capture) -> str:
    return hashlib.sha256(json.dumps([c.rig, c.simulate, c.drive, c.board, LENSES], sort_keys=True).encode()).hexdigest()[:16]


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


# what the warnings module prints: "path/file.py:98: RuntimeWarning: invalid value encountered in sqrt"
_PYTHON_WARNING = re.compile(r"^\S+:\d+: \w*Warning: ")


def _clcgraph(*args, timeout=1800) -> subprocess.CompletedProcess:
    """The real entry point (the console script beside this Python), as a user runs it."""
    exe = Path(sys.executable).parent / "clcgraph"
    return subprocess.run([str(exe), *map(str, args)], capture_output=True, text=True, env=_env(), timeout=timeout)


def _write_lenses(d: Path, rig: dict) -> None:
    import mrcal

    for cam in rig.get("cameras", []):
        lens = Path(cam["model"]).stem
        model, intrinsics, size = LENSES[lens]
        mrcal.cameramodel(intrinsics=(model, np.asarray(intrinsics, float)), imagersize=size).write(str(d / cam["model"]))


def _prepare(c: Capture, build: Path = BUILD, seed: int = 1) -> Path:
    """The capture's bags (simulated once per recipe and seed) in ``build``/name."""
    d = Path(build) / c.name
    key = _recipe_key(c)
    if (d / "recipe").exists() and (d / "recipe").read_text() == key and (d / "data" / "truth.yaml").exists():
        return d
    shutil.rmtree(d, ignore_errors=True)  # build/stress is ours alone
    d.mkdir(parents=True)
    if c.drive is not None:
        r = _clcgraph("simulate-drive", "--out", d / "data", "--small", "--duration", c.drive["duration"],
                      *(["--seed", seed] if seed != 1 else []),
                      *(["--layout", c.drive["layout"]] if "layout" in c.drive else []))
    else:
        rig = {**c.rig}
        if c.board is not None:
            rig["board"] = c.board
        _write_lenses(d, rig)
        (d / "rig.yaml").write_text(yaml.safe_dump(rig, sort_keys=False))
        from clcgraph.sim.capture import simulate

        simulate(d / "rig.yaml", d / "data", seed=seed, **c.simulate)
        r = None
    if r is not None and r.returncode != 0:
        raise RuntimeError(f"{c.name}: simulating failed: {r.stderr.strip()[-500:]}")
    (d / "recipe").write_text(key)
    return d


def _tangent_z(rt_est, rt_true, cov_rt) -> np.ndarray:
    """Per-axis z of the error in the tangent space at the estimate (right perturbation,
    rotation first; clcgraph.geometry's chart Jacobian, exact near 180 deg where the
    Rodrigues chart folds)."""
    from clcgraph.geometry import T_from_rt, tangent_covariance_from_rt
    from scipy.spatial.transform import Rotation

    cov_xi = tangent_covariance_from_rt(rt_est, cov_rt)
    E = np.linalg.inv(T_from_rt(rt_est)) @ T_from_rt(rt_true)
    xi = np.r_[Rotation.from_matrix(E[:3, :3]).as_rotvec(), E[:3, 3]]
    return xi / np.sqrt(np.diag(cov_xi))


def _judge(c: Capture, out: Path, truth: dict, bar_deg: float, bar_mm: float) -> Outcome:
    from clcgraph.geometry import T_from_rt

    cal = yaml.safe_load((out / "calibration.yaml").read_text())
    from clcgraph.geometry import rt_from_T

    # a capture's truth.yaml has rt_lidar0_sensor, a drive's T_lidar0_sensor
    want = {s["topic"]: np.asarray(s["rt_lidar0_sensor"], float) if "rt_lidar0_sensor" in s
            else rt_from_T(np.asarray(s["T_lidar0_sensor"], float)) for s in truth["sensors"]}
    sensors = [s for s in cal["sensors"] if s["topic"] != cal.get("reference")]
    cov = np.asarray(cal.get("covariance_rt_lidar0_sensor") or np.zeros((0, 0)), float)
    worst = Outcome(c.name, "ok", "")
    rows, zs = [], []
    for k, s in enumerate(sensors):
        rt = np.asarray(s["rt_lidar0_sensor"], float)
        T_err = np.linalg.inv(T_from_rt(want[s["topic"]])) @ T_from_rt(rt)
        rot = float(np.degrees(np.arccos(np.clip((np.trace(T_err[:3, :3]) - 1) / 2, -1, 1))))
        trans = float(np.linalg.norm(T_from_rt(rt)[:3, 3] - T_from_rt(want[s["topic"]])[:3, 3]) * 1e3)
        block = cov[6 * k:6 * k + 6, 6 * k:6 * k + 6] if cov.shape[0] >= 6 * (k + 1) else None
        z = _tangent_z(rt, want[s["topic"]], block) if block is not None else np.full(6, np.nan)
        zs += [float(x) for x in z]
        sd_deg = np.asarray(s.get("stdev_orientation_deg", [np.nan] * 3), float)  # tangent, per axis
        sd_mm = np.asarray(s.get("stdev_position_mm", [np.nan] * 3), float)
        rows.append((s["topic"], rot, trans, float(np.linalg.norm(sd_deg)), float(np.linalg.norm(sd_mm)),
                     float(np.nanmax(np.abs(z)))))
    for topic, rot, trans, sdeg, smm, mz in rows:
        verdict = "ok"
        if trans > 50 or not mz <= 5:
            verdict = "WRONG"
        elif rot > bar_deg or trans > bar_mm or not mz <= 3:
            verdict = "INACCURATE"
        rank = ["ok", "INACCURATE", "WRONG"]
        if rank.index(verdict) > rank.index(worst.verdict) or (verdict == worst.verdict and mz > worst.max_z) \
                or worst.detail == "":
            worst = Outcome(c.name, verdict, f"worst: {topic}", rot, trans, sdeg, smm, mz)
    worst.z = tuple(zs)
    return worst


def run_capture(c: Capture, settings: tuple[str, ...] = (), build: Path = BUILD, seed: int = 1) -> Outcome:
    """``settings``: extra ``section.key=value`` settings passed to the command as ``--set``;
    ``build``: where the capture is simulated (with ``seed``) and solved."""
    t0 = time.perf_counter()
    try:
        d = _prepare(c, build, seed)
    except Exception as e:  # noqa: BLE001 - a broken recipe is reported, the others run
        return Outcome(c.name, "FAILED", f"simulation: {e}")
    data = d / "data"
    truth = yaml.safe_load((data / "truth.yaml").read_text())
    settings = (*c.settings, *settings)
    # each set of extra settings solves into its own folder (two settings can run at once)
    out = d / ("out-" + hashlib.sha256(repr(settings).encode()).hexdigest()[:8] if settings else "out")
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    if c.drive is not None:
        topics = [s["topic"] for s in truth["sensors"]]
        bag = next(p for p in data.iterdir() if p.name.startswith("drive"))
        r = _clcgraph("targetless", "--bag", bag, "--mapping-topic", topics[0],
                      "--calibration-topics", ",".join(topics[1:]), "--out", out,
                      *[a for kv in settings if not kv.startswith("solve.") for a in ("--set", kv)])
        bar = (0.02, 3.0)
    else:
        topics = truth["topics"]
        # cameras whose drivers publish CameraInfo are given no model file: the user relies on the bags
        # (no models at all when every camera's is there, else "camera_info" in those cameras' places)
        cams = c.rig.get("cameras", [])
        models = [] if cams and all(cam.get("camera_info") for cam in cams) else \
            [FROM_CAMERA_INFO if cam.get("camera_info") else d / cam["model"] for cam in cams]
        config = []
        if c.board is not None:
            (d / "board.yaml").write_text(yaml.safe_dump({"board": c.board}))
            config = ["--config", d / "board.yaml"]
        r = _clcgraph("solve", "--bag", data, "--topics", ",".join(topics),  # a directory of bags, as users give it
                      *models, "--out", out, *config, *[a for kv in settings for a in ("--set", kv)])
        bar = (0.1, 5.0)
    seconds = time.perf_counter() - t0
    err = r.stderr.strip().splitlines()
    warned = next((line for line in err if _PYTHON_WARNING.match(line)), None)
    if warned is not None:  # numpy's RuntimeWarning and the like: a user must never see one
        o = Outcome(c.name, "FAILED", f"exit {r.returncode}, a Python warning on stderr: {warned.strip()}")
    elif r.returncode == 2 and len(err) == 1:
        o = Outcome(c.name, "refused", err[0])
    elif r.returncode == 0:
        o = _judge(c, out, truth, *bar)
        if c.must_refuse:
            o.verdict = "WRONG" if o.verdict != "ok" else "INACCURATE"
            o.detail = "answered where a direction is unobservable; " + o.detail
    else:
        o = Outcome(c.name, "FAILED", f"exit {r.returncode}: " + (err[-1] if err else "(no stderr)")
                    + (f" [+{len(err) - 1} lines]" if len(err) > 1 else ""))
    o.seconds = seconds
    return o


def table(outcomes: list[Outcome]) -> str:
    head = f"{'capture':26s} {'outcome':10s} {'rot deg':>8s} {'1sig':>6s} {'mm':>7s} {'1sig':>6s} {'|z|max':>6s} {'s':>5s}  detail"
    rows = [head]
    for o in outcomes:
        rows.append(f"{o.name:26s} {o.verdict:10s} {o.rot_deg:8.3f} {o.sigma_deg:6.3f} {o.trans_mm:7.1f} "
                    f"{o.sigma_mm:6.1f} {o.max_z:6.2f} {o.seconds:5.0f}  {o.detail}")
    n_ok = sum(o.verdict in ("ok", "refused") for o in outcomes)
    n_wrong = sum(o.verdict == "WRONG" for o in outcomes)
    rows.append(f"{n_ok}/{len(outcomes)} right or refused; silent wrong answers: {n_wrong} (must be 0)")
    rows.append(honesty(outcomes))
    return "\n".join(rows)


# P(|z| > 3) of a standard normal
_P_BEYOND_3 = 0.0026998


def honesty(outcomes: list[Outcome]) -> str:
    """The reported sigmas judged over the whole set: mean z^2 over every answered axis (1 for exact
    sigmas), how many axes lie beyond 3 sigma, and how many answered captures have an axis there
    against what exact sigmas give by chance (a capture of n axes: 1 - (1 - 0.27 %)^n, about n x
    0.27 %; fewer where its axes are correlated). A capture judged INACCURATE by 3 sigma alone is a
    defect only where these counts exceed chance."""
    answered = [np.asarray(o.z, float) for o in outcomes if len(o.z)]
    answered = [z[np.isfinite(z)] for z in answered]
    z = np.concatenate(answered) if answered else np.zeros(0)
    if not len(z):
        return "sigmas: no answered capture"
    beyond = sum(bool(np.any(np.abs(a) > 3)) for a in answered)
    chance = sum(1 - (1 - _P_BEYOND_3) ** len(a) for a in answered)
    return (f"sigmas over {len(z)} axes of {len(answered)} answered captures: mean z^2 {np.mean(z**2):.2f} (exact: 1), "
            f"beyond 3 sigma {int(np.sum(np.abs(z) > 3))} axes (exact: {_P_BEYOND_3 * len(z):.1f}); captures with an "
            f"axis beyond 3 sigma {beyond} (exact sigmas, by chance: {chance:.1f})")


def main(argv: list[str] | None = None) -> str:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m bench.stress", description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", help="captures to run (default: all)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="an extra setting for every solve (targetless: all but solve.*)")
    ap.add_argument("--seed", type=int, default=1, help="draw the captures with this seed (default 1: the "
                    "set's own); another seed simulates into build/stress-seed<N>/")
    args = ap.parse_args(sys.argv[1:] if argv is None else argv)
    build = BUILD if args.seed == 1 else BUILD.with_name(f"stress-seed{args.seed}")
    every = CAPTURES + CI_CAPTURES
    unknown = sorted(set(args.names) - {c.name for c in every})
    if unknown:
        ap.error(f"unknown capture {unknown[0]!r}; known: {', '.join(c.name for c in every)}")
    by_name = {c.name: c for c in every}
    chosen = [by_name[n] for n in dict.fromkeys(args.names)] if args.names else CAPTURES  # in the order given
    outcomes = []
    for c in chosen:
        o = run_capture(c, tuple(args.set), build, args.seed)
        print(f"  {o.name}: {o.verdict} ({o.seconds:.0f} s) {o.detail}", file=sys.stderr, flush=True)
        outcomes.append(o)
    return table(outcomes)


if __name__ == "__main__":
    print(main())
