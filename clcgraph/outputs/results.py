"""Result files of both methods: calibration.yaml, one .cameramodel per sensor, timings.yaml,
config.resolved.yaml, the dump, ROS tf / URDF / launch files when the sensors' frames are known.

Everything is written into a temporary directory next to ``out_dir`` and renamed into
place at the end, so a failure leaves no half-written output.

SYNOPSIS
    paths = write_results(result, "out/", config=config, problem_dump=save_problem)
    cal = load_result("out/")              # Calibration, schema-checked, whichever method made it
    cal.method                             # "target" or "targetless"
    cal["sensors"][1]["T_lidar0_sensor"]   # (4,4) array; cal reads like the YAML's mapping
    cal.T_lidar0_sensor("/lidar1/points")  # the same by topic
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

from .. import __version__
from ..errors import DataError, InputError
from ..geometry import T_from_rt, invert_rt, pose_stdevs, rt_from_T
from ..config import CSafeDumperNoAliases, read_yaml
from ..types import Result, Sensor
from .atomic import atomic_dir

log = logging.getLogger(__name__)

CALIBRATION_FILE = "calibration.yaml"
CONFIG_FILE = "config.resolved.yaml"
TIMINGS_FILE = "timings.yaml"
METHODS = ("target", "targetless")
# Every calibration.yaml has the common keys and those of its method (a file without `method`
# is a target-based one of an older clcgraph). Targetless writes its graph instead of the fit
# statistics, and optionally base_link poses from the ground plane.
COMMON_KEYS = ("reference", "sensors", "covariance_rt_lidar0_sensor")
METHOD_KEYS = {"target": ("rms", "noise", "snapshots", "sectors"), "targetless": ("graph",)}
SENSOR_KEYS = ("topic", "kind", "rt_lidar0_sensor", "T_lidar0_sensor", "stdev_rt")

# The placeholder lens a LIDAR's .cameramodel carries (clc does the same): only its
# extrinsics mean anything.
LIDAR_PLACEHOLDER_LENS = ("LENSMODEL_PINHOLE", np.array([1.0, 1.0, 0.0, 0.0]))
LIDAR_PLACEHOLDER_IMAGERSIZE = (1, 1)


def _floats(a) -> list:
    """numpy -> nested lists of python floats (YAML-safe)."""
    return np.asarray(a, dtype=float).tolist()


def _scalar(v):
    if v is None:
        return None
    v = float(v)
    return None if not np.isfinite(v) else v


# What each uncertainty field means (written into calibration.yaml as `coordinates`).
COORDINATES = {
    "rt_lidar0_sensor": "mrcal rt of the sensor in lidar0: Rodrigues r [rad] (axis * angle), then t [m]; "
    "T_lidar0_sensor is the same as a 4x4",
    "covariance_rt_lidar0_sensor": "joint covariance of rt_lidar0_sensor (mrcal rt: Rodrigues r [rad], then t [m]) "
    "over the non-reference sensors in sensor order; for machines (mrcal, uncertainty propagation)",
    "stdev_rt": "sqrt of the diagonal of that covariance: rt coordinates, NOT per-axis angles (the Rodrigues "
    "chart inflates them by (th/2)/sin(th/2) across the rotation axis)",
    "stdev_orientation_deg": "1-sigma rotation about the sensor's own x, y, z axes: the tangent omega of "
    "R_lidar0_sensor = R_solved Exp(omega) (GTSAM's right perturbation)",
    "stdev_position_mm": "1-sigma of the sensor's origin along lidar0's x, y, z (the rt translation)",
}


def stdev_fields(sd_rot_rad: np.ndarray, sd_pos_m: np.ndarray) -> dict:
    """The per-axis sigmas for people, as calibration.yaml writes them (see COORDINATES)."""
    return {"stdev_orientation_deg": _floats(np.degrees(sd_rot_rad)), "stdev_position_mm": _floats(sd_pos_m * 1e3)}


def calibration_dict(result: Result) -> dict:
    """The calibration.yaml content as a plain dict: the common part, then the method's sections."""
    problem = result.problem
    sensors = []
    for i, s in enumerate(problem.sensors):
        rt = np.asarray(result.rt_lidar0_sensor[i], dtype=float)
        sd_rot, sd_pos = pose_stdevs(rt, result.covariance_block(i))
        entry = {
            "topic": s.topic,
            "kind": s.kind,
            "rt_lidar0_sensor": _floats(rt),
            "T_lidar0_sensor": _floats(T_from_rt(rt)),
            "stdev_rt": _floats(result.stdev_rt(i)),
            **stdev_fields(sd_rot, sd_pos),
        }
        if result.method == "target":  # this sensor's re-estimated noise: m (LIDAR range) or px (camera corners)
            entry["noise_sigma"] = _scalar(result.noise.get("per_sensor", {}).get(i))
        sensors.append(entry)
    d = {
        "clcgraph_version": __version__,
        "method": result.method,
        "reference": problem.sensors[problem.reference].topic,
        "sensors": sensors,
        # symmetrized: marginals come out of the solver symmetric only to rounding
        "covariance_rt_lidar0_sensor": _floats(0.5 * (np.asarray(result.covariance_rt, float) + np.asarray(result.covariance_rt, float).T)),
        "coordinates": COORDINATES,
    }
    if result.frames:
        d["frames"] = {t: str(f) for t, f in result.frames.items()}
    if result.T_base_sensor:
        d["base_link"] = [{"topic": t, "frame": result.base_frame, "T_base_link_sensor": _floats(T),
                           "rt_base_link_sensor": _floats(rt_from_T(np.asarray(T, float)))}
                          for t, T in result.T_base_sensor.items()]
    return {**d, **(_target_sections(result) if result.method == "target" else _targetless_sections(result))}


def _target_sections(result: Result) -> dict:
    problem = result.problem
    rejected = [
        {
            "index": None if r.snapshot is None else int(r.snapshot),
            "bag": None if r.snapshot is None else problem.snapshot_bag(int(r.snapshot)),
            "sensor": None if r.sensor is None else problem.sensors[r.sensor].topic,
            "stage": r.stage,
            "reason": r.reason,
        }
        for r in result.rejected
    ]
    used = np.flatnonzero(np.all(np.isfinite(np.asarray(result.rt_lidar0_board, float).reshape(-1, 6)), axis=1))
    used_set = set(used.tolist())
    return {
        # the chessboard as configured (inner corners, square, physical size, pattern offset)
        "board": problem.board.spec(),
        "rms": {k: _scalar(result.rms.get(k)) for k in ("normalized", "lidar_m", "camera_px")},
        "noise": {k: _scalar(result.noise.get(k)) for k in ("lidar_m", "camera_px")},
        "snapshots": {"used": int(len(used)), "used_indices": [int(k) for k in used],
                      "total": int(problem.n_snapshots),
                      # every snapshot: its index (what --exclude and the plots use), bag and stamp
                      "list": [{"index": k, "bag": problem.snapshot_bag(k), "stamp_ns": int(problem.snapshot_stamps_ns[k]),
                                "used": bool(k in used_set)} for k in range(problem.n_snapshots)],
                      "rejected": rejected},
        "sectors": sectors_dict(result),
        "convergence": dict(result.stats.get("convergence") or {}),
        # the self-consistency verdict (backend/consistency.py): the checks and their numbers
        # (6 significant digits: the checks' eigen-decompositions differ in the last digits
        # between BLAS thread counts, and the same inputs must give the same bytes)
        "consistency": _plain(result.stats.get("consistency"), digits=6),
        "uncertainty_check": uncertainty_check_dict(result),
        # per LIDAR: its boards' dark squares' range beyond the light ones' on the solved poses, and
        # whether it was taken out (backend/dark_squares.py: clouds without intensities keep it)
        "dark_squares": _plain(result.stats.get("dark_squares") or {}, digits=6),
        **unit_errors_dict(result),
    }


def _targetless_sections(result: Result) -> dict:
    run = result.targetless
    return {
        # per calibration LIDAR: the final graph (keyframe poses linked by submap registrations)
        # and how its solves stopped; how the calibration frames were taken from this drive
        "graph": _plain(dict(run.graph)),
        "calibration_frames": _plain(dict(run.frame_plan)),
        "convergence": _plain(dict(run.convergence)),
    }


def timings_dict(result: Result) -> dict:
    """timings.yaml: wall seconds (and peak RSS, MB) per stage; kept out of calibration.yaml
    so that the same inputs give the same calibration.yaml."""
    return {"timings_s": {k: float(v) for k, v in (result.stats.get("stage_time_s") or {}).items()},
            "peak_rss_mb": {k: float(v) for k, v in (result.stats.get("peak_rss_mb") or {}).items()}}


def _plain(v, digits: int | None = None):
    """numpy scalars/arrays inside dicts and lists -> python types (YAML-safe); floats rounded
    to ``digits`` significant digits if given."""
    if isinstance(v, dict):
        return {str(k): _plain(x, digits) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x, digits) for x in v]
    if isinstance(v, np.ndarray):
        return _plain(v.tolist(), digits)
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        x = _scalar(v)
        return x if x is None or digits is None else float(f"{x:.{digits}g}")
    return v


def uncertainty_terms_dict(result: Result) -> dict:
    """Which terms the sigmas include (backend/consider.py), each term's share of every sensor's
    final position / orientation variance, and per camera whether its intrinsics' uncertainty
    is in them (only where its .cameramodel carries the calibration that made it; its focal
    length's alone where solve.camera_focal_scale_sigma states it)."""
    terms = result.stats.get("uncertainty_terms") or {}
    included = set(terms.get("included", ()))
    cams = {s.topic: ("included" if f"intrinsics {s.topic}" in included else
                      "focal length only (solve.camera_focal_scale_sigma)" if f"focal length {s.topic}" in included else
                      "not included (the camera model carries no optimization_inputs)")
            for s in result.problem.sensors if s.is_camera}
    out = {"camera_intrinsics_uncertainty": cams}
    if terms:
        out["terms_included"] = list(terms["included"])
        out["variance_share"] = _plain(terms["variance_share"], digits=4)
    return out


UNIT_ERRORS_ABOUT = (
    "how each sensor's rt_lidar0_sensor moves with each named error of the sensor units (a LIDAR ring's range "
    "bias [m] or elevation error [rad], a camera's lens-field mode [px, RMS of a 1 px field]): per sensor one "
    "row d rt / d error (r, then t) per entry of 'errors'; what `clcgraph compare` pairs between two "
    "calibrations of the same units (docs/fleet.md). sigma_in_covariance: the 1-sigma of each kind already in "
    "covariance_rt_lidar0_sensor (solve.lidar_ring_range_bias_m [m] per LIDAR, or the spread of the ring offsets "
    "measured on its boards where larger, .lidar_ring_elevation_deg [as rad], .camera_lens_field_px [px]; 0 = not in it)")


def unit_errors_dict(result: Result) -> dict:
    """calibration.yaml's ``unit_errors`` block ({} without sensitivities: targetless): ``errors``
    one ``[sensor, error, at]`` per named error (at: the ring's elevation in deg, or the lens
    mode's index; error ``lens field x|y``: the pixel axis), ``sensitivity_rt`` per variable
    sensor one row of 6 per error (6 significant digits: same inputs, same bytes)."""
    u = result.stats.get("unit_errors")
    if not u:
        return {}
    p = result.problem
    errors = [[e["sensor"], e["error"], round(e["ring_elevation_deg"], 3)] if "ring_elevation_deg" in e
              else [e["sensor"], f"{e['error']} {e['axis']}", int(e["mode"])] for e in u["errors"]]
    J = np.asarray(u["sensitivity_rt"], float)
    topics = [s.topic for i, s in enumerate(p.sensors) if i != p.reference]
    return {"unit_errors": {
        "about": UNIT_ERRORS_ABOUT,
        "sigma_in_covariance": {k: {t: float(x) for t, x in v.items()} if isinstance(v, dict) else float(v)
                                for k, v in u["sigma_in_covariance"].items()},
        "errors": errors,
        "sensitivity_rt": {t: _plain(J[6 * a:6 * a + 6].T, digits=6) for a, t in enumerate(topics)}}}


def uncertainty_check_dict(result: Result) -> dict:
    """The noise model and its leave-one-snapshot-out check, YAML-safe ({} if not computed).

    Per sensor along the model covariance's principal axes (unit vectors in lidar0, rt
    coordinates; position in mm, orientation in deg): the model sigma, the jackknife sigma and
    their ratio (near 1: the sigma can be trusted; well above 1: it is too small), the factor
    the reported sigma was raised by where the ratio is above what the model expects
    (``*_raised``; 1: the model's), and the snapshot whose removal moves the sensor most.
    """
    jk = result.jackknife
    problem = result.problem
    effects = result.noise.get("observation_effects") or {}
    out = {
        "noise_model": {problem.sensors[i].topic: {k: float(v) for k, v in e.items()} for i, e in effects.items()},
        **uncertainty_terms_dict(result),
    }
    if not jk:
        return out
    out["jackknife"] = {
        "method": jk["method"],
        "axes": "principal axes of each sensor's model covariance (position: of t in lidar0; orientation: of r)",
        "n_snapshots": int(jk["n_snapshots"]),
        "indispensable_snapshots": [int(k) for k in jk["indispensable_snapshots"]],
        "sensors": {
            problem.sensors[i].topic: {
                **{k: _floats(v) for k, v in s.items() if k != "largest_influence"},
                "largest_influence": {k: (int(v) if k == "snapshot" else float(v)) for k, v in s["largest_influence"].items()},
            }
            for i, s in jk["sensors"].items()
        },
        "largest_influence": {"sensor": problem.sensors[jk["largest_influence"]["sensor"]].topic,
                              **{k: (int(v) if k == "snapshot" else float(v))
                                 for k, v in jk["largest_influence"].items() if k != "sensor"}},
    }
    return out


def sectors_dict(result: Result) -> dict:
    """The sector feedback as YAML-safe lists ({} when the result has none)."""
    s = result.sectors
    if s is None:
        return {}
    return {
        "n_sectors": int(s.n_sectors),
        "observations_per_sector": [int(x) for x in np.asarray(s.observations_per_sector)],
        "isvisible_per_sensor_per_sector": np.asarray(s.isvisible_per_sensor_per_sector, bool).tolist(),
        "stdev_worst_per_sector_m": _floats(s.stdev_worst_per_sector),
        "isensors_pair_stdev_worst": np.asarray(s.isensors_pair_stdev_worst, int).tolist(),
        "isector_of_last_snapshot": int(s.isector_of_last_snapshot),
    }


def write_cameramodels(result: Result, directory: str | Path) -> list[Path]:
    """One ``sensor{i}-mounted.cameramodel`` per sensor; extrinsics rt_sensor_lidar0.

    Cameras carry their intrinsics; LIDARs a placeholder pinhole lens (as clc does), so
    that mrcal tools (mrcal-show-geometry, ...) can show the whole rig.
    """
    from ..cameras import write_cameramodel

    directory = Path(directory)
    out = []
    for i, s in enumerate(result.problem.sensors):
        path = directory / f"sensor{i}-mounted.cameramodel"
        rt_sensor_lidar0 = invert_rt(np.asarray(result.rt_lidar0_sensor[i], dtype=float))
        if not s.is_camera:
            s = Sensor(topic=s.topic, kind=s.kind, lensmodel=LIDAR_PLACEHOLDER_LENS[0],
                       intrinsics=LIDAR_PLACEHOLDER_LENS[1].copy(), imagersize=LIDAR_PLACEHOLDER_IMAGERSIZE)
        write_cameramodel(path, s, rt_cam_ref=rt_sensor_lidar0)
        out.append(path)
    return out


def write_results(
    result: Result,
    out_dir: str | Path,
    *,
    config=None,
    problem_dump: Callable[[object, Path], None] | None = None,
    extra_files: dict | None = None,
    force: bool = False,
) -> dict[str, Path]:
    """Write all result files into ``out_dir`` atomically; returns {name: final path}.

    ``problem_dump(problem, path)`` writes the replayable dump (to ``problem.npz``);
    ``extra_files`` maps file names to str/bytes contents or to a callable(path) that
    writes the file (the report uses this). A previous clcgraph output in ``out_dir`` is
    replaced as a whole; anything else there is refused unless ``force`` (outputs/atomic.py).
    Raises InputError naming ``out_dir`` if it cannot be written.
    """
    out_dir = Path(out_dir).absolute()
    names: dict[str, Path] = {}
    with atomic_dir(out_dir, force=force) as tmp:
        cal = calibration_dict(result)
        (tmp / CALIBRATION_FILE).write_text(
            "# clcgraph calibration: rt_a_b maps points in frame b into frame a: x_a = R x_b + t, as mrcal's rt\n"
            "# (Rodrigues rotation vector r = axis * angle [rad], then translation t [m]); for people, the summary\n"
            "# table and the report give roll, pitch, yaw [deg] about fixed x-y-z (R = Rz(yaw) Ry(pitch) Rx(roll))\n"
            + yaml.dump(cal, Dumper=CSafeDumperNoAliases, sort_keys=False, default_flow_style=None, width=200)
        )
        names[CALIBRATION_FILE] = out_dir / CALIBRATION_FILE
        (tmp / TIMINGS_FILE).write_text(yaml.safe_dump(timings_dict(result), sort_keys=False))
        names[TIMINGS_FILE] = out_dir / TIMINGS_FILE
        extra_files = {**ros_tf_files(result, cal), **(extra_files or {})}
        if config is not None:
            (tmp / CONFIG_FILE).write_text(config.to_yaml())
            names[CONFIG_FILE] = out_dir / CONFIG_FILE
        for p in write_cameramodels(result, tmp):
            names[p.name] = out_dir / p.name
        if problem_dump is not None:
            problem_dump(result.problem, tmp / "problem.npz")
            names["problem.npz"] = out_dir / "problem.npz"
        for name, content in extra_files.items():
            path = tmp / name
            path.parent.mkdir(parents=True, exist_ok=True)
            if callable(content):
                content(path)
            elif isinstance(content, bytes):
                path.write_bytes(content)
            else:
                path.write_text(str(content))
            names[name] = out_dir / name
    log.info("wrote %d result files into %s", len(names), out_dir)
    return names


def ros_tf_files(result: Result, cal: dict) -> dict[str, str]:
    """{"ros/<name>": text}: tf, URDF and launch files (outputs/ros.py) under base_link when the
    result has base_link <- reference, else under the reference's frame; {} unless every sensor's
    frame_id is known (a target-based result leaves that to `clcgraph format-for-ros`)."""
    from .ros import format_for_ros, ros_files

    topics = [s.topic for s in result.problem.sensors]
    if not result.frames or any(t not in result.frames for t in topics):
        return {}
    ref = topics[result.problem.reference]
    parent = result.base_frame if ref in result.T_base_sensor else result.frames[ref]
    ros = format_for_ros(cal, None, base_frame=parent, frames=dict(result.frames))
    ros["transforms"] = {f: e for f, e in ros["transforms"].items() if f != parent}  # no parent <- parent
    return {f"ros/{name}": text for name, text in ros_files(ros).items()}


def _fail(path, msg):
    raise DataError(f"{path}: not a clcgraph calibration: {msg}")


class Calibration(Mapping):
    """A calibration.yaml read back (``load_result``), whichever method wrote it.

    Reads like the YAML's mapping (``cal["sensors"][1]["T_lidar0_sensor"]``, arrays where the
    file has matrices) and has the common part as attributes: ``method`` ("target" or
    "targetless"), ``reference`` (topic), ``topics``, ``covariance_rt`` ((6(N-1),6(N-1)), the
    reference excluded), ``base_link`` (topic -> (4,4) T_base_link_sensor, {} if none).
    """

    def __init__(self, data: dict, path: Path):
        self._d, self.path = data, path

    def __getitem__(self, key):
        return self._d[key]

    def __iter__(self):
        return iter(self._d)

    def __len__(self):
        return len(self._d)

    def __repr__(self):
        return f"Calibration({self.method}, {self.path}, sensors {self.topics})"

    @property
    def method(self) -> str:
        return self._d["method"]

    @property
    def reference(self) -> str:
        return self._d["reference"]

    @property
    def topics(self) -> list[str]:
        return [s["topic"] for s in self._d["sensors"]]

    @property
    def covariance_rt(self) -> np.ndarray:
        return self._d["covariance_rt_lidar0_sensor"]

    @property
    def base_link(self) -> dict[str, np.ndarray]:
        return {b["topic"]: b["T_base_link_sensor"] for b in self._d.get("base_link") or []}

    def sensor(self, topic: str) -> dict:
        """The ``sensors`` entry of a topic."""
        for s in self._d["sensors"]:
            if s["topic"] == topic:
                return s
        raise InputError(f"{topic} is not a sensor of the calibration in {self.path}")

    def T_lidar0_sensor(self, topic: str) -> np.ndarray:
        return self.sensor(topic)["T_lidar0_sensor"]


def load_result(out_dir: str | Path) -> Calibration:
    """Read ``out_dir/calibration.yaml`` (or that file itself) back, checking its schema; of
    `clcgraph solve` or of `clcgraph targetless` (its ``method``; none: an older target-based file).

    The Calibration has, per sensor, ``rt_lidar0_sensor`` as a (6,) array and
    ``T_lidar0_sensor`` as a (4,4) array; the covariance as a (6(N-1),6(N-1)) array (the
    reference excluded); ``base_link`` poses as arrays.
    """
    path = Path(out_dir)
    if path.is_dir():
        path = path / CALIBRATION_FILE
    return calibration_from_dict(read_yaml(path, "calibration", hint="; pass the --out directory of clcgraph solve"), path)


def calibration_from_dict(d, path: Path) -> Calibration:
    """``load_result`` of a calibration.yaml already parsed (``d``; changed in place), read from ``path``."""
    if not isinstance(d, dict):
        _fail(path, "not a mapping")
    d.setdefault("method", "target")
    if d["method"] not in METHODS:
        _fail(path, f"method {d['method']!r} is not one of {', '.join(METHODS)}")
    missing = [k for k in COMMON_KEYS + METHOD_KEYS[d["method"]] if k not in d]
    if missing:
        _fail(path, f"missing keys {missing}")
    if not isinstance(d["sensors"], list) or not d["sensors"]:
        _fail(path, "'sensors' must be a non-empty list")
    topics = []
    for k, s in enumerate(d["sensors"]):
        if not isinstance(s, dict) or any(key not in s for key in SENSOR_KEYS):
            _fail(path, f"sensors[{k}] needs keys {list(SENSOR_KEYS)}")
        if s["kind"] not in ("lidar", "camera"):
            _fail(path, f"sensors[{k}].kind must be lidar or camera")
        try:
            s["rt_lidar0_sensor"] = np.array(s["rt_lidar0_sensor"], dtype=float).reshape(6)
            s["T_lidar0_sensor"] = np.array(s["T_lidar0_sensor"], dtype=float).reshape(4, 4)
            s["stdev_rt"] = np.array(s["stdev_rt"], dtype=float).reshape(6)
        except (ValueError, TypeError):
            _fail(path, f"sensors[{k}] has arrays of the wrong shape")
        if not np.allclose(s["T_lidar0_sensor"], T_from_rt(s["rt_lidar0_sensor"]), atol=1e-6):
            _fail(path, f"sensors[{k}] T_lidar0_sensor disagrees with rt_lidar0_sensor")
        topics.append(s["topic"])
    if d["reference"] not in topics:
        _fail(path, f"reference {d['reference']} is not one of the sensors")
    n = 6 * (len(topics) - 1)
    try:
        C = np.array(d["covariance_rt_lidar0_sensor"], dtype=float).reshape(n, n)
    except (ValueError, TypeError):
        _fail(path, f"covariance_rt_lidar0_sensor must be {n}x{n}")
    if not np.allclose(C, C.T, atol=1e-12 + 1e-9 * np.abs(C).max(initial=0)):
        _fail(path, "covariance_rt_lidar0_sensor is not symmetric")
    d["covariance_rt_lidar0_sensor"] = C
    for key in METHOD_KEYS[d["method"]]:
        if not isinstance(d[key], dict):
            _fail(path, f"'{key}' must be a mapping")
    for k, b in enumerate(d.get("base_link") or []):
        try:
            b["T_base_link_sensor"] = np.array(b["T_base_link_sensor"], dtype=float).reshape(4, 4)
            b["rt_base_link_sensor"] = np.array(b["rt_base_link_sensor"], dtype=float).reshape(6)
        except (KeyError, ValueError, TypeError):
            _fail(path, f"base_link[{k}] needs T_base_link_sensor (4x4) and rt_base_link_sensor (6)")
    return Calibration(d, path)
