"""A rig to simulate, from YAML: LIDARs and cameras with their poses on the vehicle.

    lidars:
      - topic: /lidar/front/points
        model: vlp16                 # preset (vlp16, hdl32, os1-64, os1-128, vlp32c, pandar40p) ...
        # elevations_deg: [...]      # ... or an explicit ring table
        # npoints_per_rotation: 1800
        layout: velodyne             # velodyne (unorganised) | ouster (organised, padded) | hesai (absolute float64 times, ring 0 the top beam) | pcl_xyzi (a PCL filter's: no ring) | pcl_xyz (no intensity either)
        frame_id: lidar_front
        xyz: [1.2, 0.0, 1.8]         # pose in base_link: position (m) ...
        rpy_deg: [0, 0, 0]           # ... and roll, pitch, yaw (deg) of the front-left-up frame
        range_noise_m: 0.01
        ring_range_bias_m: 0.02          # optional: sd of each ring's fixed range bias (0 = off)
        ring_elevation_error_deg: 0.1    # optional: sd of each ring's fixed elevation error (0 = off)
        errors_seed: 3                   # optional: which unit (draws the per-ring errors)
        heavy_tail_fraction: 0.02        # optional: share of returns with heavy_tail_scale (10) x the noise
        dark_range_bias_m: 0.015         # optional: the board's dark squares return weak and this long
        dark_dropout: 0.5                # optional: this share of the dark squares' returns is lost
        mixed_pixel_m: 0.1               # optional: a ring's board-edge return up to this long
        dual_returns: false              # optional: two returns of every ray (velodyne: after each firing's; ouster: organised, each column then its second returns')
        clockwise: true                  # optional: the head spins clockwise seen from above (false: the other way)
        dropout: 0.005
    cameras:
      - topic: /cam/left/image
        model: left.cameramodel      # mrcal model, relative to this file
        encoding: mono8              # mono8 | bgr8 | bayer_rggb8 (bggr8, gbrg8, grbg8: a raw mosaic)
        compressed: null             # null | png | jpeg
        camera_info: false           # optional: its CameraInfo beside each image (OPENCV4/5/8 models)
        gain: 1.0                    # optional: exposure, the scene's grey levels scaled (0.25: dim)
        pixel_noise: 2.0             # optional: grey levels of pixel noise (high sensor gain: 5-10)
        blur_px: 0.0                 # optional: Gaussian blur sigma (px): defocus, a hand-held board moving
        frame_id: cam_left
        xyz: [1.3, 0.3, 1.6]
        rpy_deg: [0, 5, 10]          # of a front-left-up frame; the optical axes follow mrcal
    board: {corners: [10, 10], square_m: 0.1, size_m: [1.3, 1.3]}   # as the config's board:
                                     # section (default: this board); pattern_offset_m: [x, y] too
    scene:                           # optional: who holds the board
      person: edge                   # edge (default: 0.5 m behind a side edge) | behind | beside | none
      arm: false                     # an arm across the board's side edge, in front of it

The first LIDAR is lidar0. Errors name the file and the key.

SYNOPSIS
    rig = load_rig("data/synthetic/demo-rig.yaml")
    rig.lidars[0].T_base_sensor, rig.cameras[0].sensor.lensmodel
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .. import cameras
from ..config import Config, ConfigError, read_yaml
from ..errors import InputError
from ..geometry import T_from_xyz_rpy
from ..types import BoardGeometry, Sensor
from .bag_writer import LAYOUTS
from .camera import BAYER_ENCODINGS
from .lidar import LidarModel
from .scene import PERSON_PLACES

# camera optical axes (right-down-forward) in a front-left-up frame
R_FLU_CAMERA = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True, eq=False)
class RigLidar:
    topic: str
    frame_id: str
    model: LidarModel
    T_base_sensor: np.ndarray


@dataclass(frozen=True, eq=False)
class RigCamera:
    topic: str
    frame_id: str
    sensor: Sensor
    model_path: Path
    T_base_sensor: np.ndarray  # base_link <- camera (optical axes)
    encoding: str = "mono8"
    compressed: str | None = None
    camera_info: bool = False  # a CameraInfo beside each image, as drivers publish it (bag.camera_info_topic)
    gain: float = 1.0  # the exposure's scale of the scene's grey levels (0.25: dim)
    pixel_noise: float = 2.0  # grey levels (a high sensor gain: 5-10)
    blur_px: float = 0.0  # Gaussian sigma (px): defocus, or a hand-held board's motion during the exposure


@dataclass(frozen=True, eq=False)
class Rig:
    path: Path
    lidars: tuple[RigLidar, ...]
    cameras: tuple[RigCamera, ...]
    board: BoardGeometry
    person: str = "edge"  # sim.scene.PERSON_PLACES
    arm: bool = False

    @property
    def topics(self) -> list[str]:
        return [x.topic for x in self.lidars] + [c.topic for c in self.cameras]

    def T_lidar0_sensor(self, topic: str) -> np.ndarray:
        sensors = {x.topic: x.T_base_sensor for x in (*self.lidars, *self.cameras)}
        return np.linalg.inv(self.lidars[0].T_base_sensor) @ sensors[topic]


def _need(d: dict, key: str, where: str, path: Path):
    if not isinstance(d, dict) or key not in d:
        raise InputError(f"{path}: {where} needs '{key}'")
    return d[key]


def _number(d: dict, key: str, default: float, where: str, path: Path) -> float:
    try:
        return float(d.get(key, default))
    except (ValueError, TypeError):
        raise InputError(f"{path}: {where}.{key} must be a number") from None


def _pose(d, where, path) -> np.ndarray:
    try:
        xyz = np.asarray(_need(d, "xyz", where, path), float).reshape(3)
        rpy = np.asarray(d.get("rpy_deg", [0, 0, 0]), float).reshape(3)
    except (ValueError, TypeError):
        raise InputError(f"{path}: {where}: xyz and rpy_deg must be 3 numbers each") from None
    return T_from_xyz_rpy(xyz, rpy)


# a LIDAR's keys that override its model's fields (LidarModel), and the others
_LIDAR_MODEL_KEYS = ("layout", "range_noise_m", "dropout", "max_range_m", "npoints_per_rotation", "ring_range_bias_m",
                     "ring_elevation_error_deg", "errors_seed", "heavy_tail_fraction", "heavy_tail_scale",
                     "dark_range_bias_m", "dark_dropout", "mixed_pixel_m", "dual_returns", "clockwise")
_LIDAR_KEYS = {"topic", "model", "elevations_deg", "frame_id", "xyz", "rpy_deg", *_LIDAR_MODEL_KEYS}
_CAMERA_KEYS = {"topic", "model", "encoding", "compressed", "camera_info", "frame_id", "xyz", "rpy_deg", "gain",
                "pixel_noise", "blur_px"}


def _unknown(d: dict, known: set, where: str, path: Path):
    extra = sorted(set(d) - known)
    if extra:
        raise InputError(f"{path}: {where}: unknown key '{extra[0]}' (known: {', '.join(sorted(known))})")


def load_rig(path) -> Rig:
    """Parse and validate a rig YAML (module docstring)."""
    path = Path(path)
    d = read_yaml(path, "rig file", mapping="with 'lidars' (and 'cameras', 'board')")
    _unknown(d, {"lidars", "cameras", "board", "scene"}, "top level", path)
    lidars = []
    for k, L in enumerate(_need(d, "lidars", "top level", path) or []):
        where = f"lidars[{k}]"
        _unknown(L, _LIDAR_KEYS, where, path)
        topic = str(_need(L, "topic", where, path))
        try:
            if "elevations_deg" in L:
                model = LidarModel("custom", tuple(float(e) for e in L["elevations_deg"]),
                                   int(_need(L, "npoints_per_rotation", where, path)))
            else:
                model = LidarModel.preset(str(_need(L, "model", where, path)))
        except KeyError as e:
            raise InputError(f"{path}: {where}.model: {e.args[0]}") from None
        over = {k2: L[k2] for k2 in _LIDAR_MODEL_KEYS if k2 in L}
        if over.get("layout", model.layout) not in LAYOUTS:
            raise InputError(f"{path}: {where}.layout must be one of {', '.join(LAYOUTS)}")
        if over.get("dual_returns") and over.get("layout", model.layout).startswith("pcl_"):
            raise InputError(f"{path}: {where}.dual_returns needs a driver's layout (velodyne, ouster or hesai)")
        model = replace(model, **over)
        lidars.append(RigLidar(topic, str(L.get("frame_id", topic.strip("/").replace("/", "_"))), model,
                               _pose(L, where, path)))
    if not lidars:
        raise InputError(f"{path}: 'lidars' must list at least one LIDAR (lidar0 is the reference)")
    cams = []
    for k, C in enumerate(d.get("cameras") or []):
        where = f"cameras[{k}]"
        _unknown(C, _CAMERA_KEYS, where, path)
        topic = str(_need(C, "topic", where, path))
        model_path = (path.parent / str(_need(C, "model", where, path))).resolve()
        sensor = cameras.load_camera(topic, model_path)
        enc = str(C.get("encoding", "mono8"))
        if enc not in ("mono8", "bgr8", *BAYER_ENCODINGS):
            raise InputError(f"{path}: {where}.encoding must be mono8, bgr8 or one of {', '.join(BAYER_ENCODINGS)}")
        if enc in BAYER_ENCODINGS and C.get("compressed"):
            raise InputError(f"{path}: {where}: a Bayer mosaic is published raw (compressed: null)")
        comp = C.get("compressed")
        if comp not in (None, "png", "jpeg"):
            raise InputError(f"{path}: {where}.compressed must be null, png or jpeg")
        info = bool(C.get("camera_info", False))
        if info and sensor.lensmodel not in cameras.ROS_DISTORTION:
            raise InputError(f"{path}: {where}.camera_info needs an OPENCV4/5/8 model (ROS's plumb_bob, "
                             f"rational_polynomial), not {sensor.lensmodel}")
        exposure = {k: _number(C, k, getattr(RigCamera, k), where, path) for k in ("gain", "pixel_noise", "blur_px")}
        if exposure["gain"] <= 0 or exposure["pixel_noise"] < 0 or exposure["blur_px"] < 0:
            raise InputError(f"{path}: {where}: gain must be > 0, pixel_noise and blur_px >= 0")
        T = _pose(C, where, path)
        T[:3, :3] = T[:3, :3] @ R_FLU_CAMERA
        cams.append(RigCamera(topic, str(C.get("frame_id", topic.strip("/").replace("/", "_"))), sensor, model_path,
                              T, enc, comp, info, **exposure))
    b = d.get("board") or {}
    if not isinstance(b, dict):
        raise InputError(f"{path}: 'board' must be a mapping")
    try:  # the same keys and checks as the config's board section
        board = BoardGeometry.from_spec(**dataclasses.asdict(Config.from_dict({"board": b}).board))
    except ConfigError as e:
        raise InputError(f"{path}: {e}") from None
    topics = [x.topic for x in lidars] + [c.topic for c in cams]
    if len(set(topics)) != len(topics):
        raise InputError(f"{path}: a topic is listed twice")
    sc = d.get("scene") or {}
    if not isinstance(sc, dict):
        raise InputError(f"{path}: 'scene' must be a mapping")
    _unknown(sc, {"person", "arm"}, "scene", path)
    person = str(sc.get("person", "edge"))
    if person not in PERSON_PLACES:
        raise InputError(f"{path}: scene.person must be one of {', '.join(PERSON_PLACES)}")
    return Rig(path, tuple(lidars), tuple(cams), board, person, bool(sc.get("arm", False)))
