"""Settings: small validated dataclass sections, loaded from and dumped to YAML.

Unknown keys are rejected (with their dotted path); values are type-checked and
never silently "fixed". ``Config().to_dict()`` is what ``clcgraph config dump`` prints.
Each section documents its fields in comments next to the defaults. This module
imports nothing of clcgraph.

SYNOPSIS
    cfg = Config.from_yaml("my.yaml")          # unknown key -> ConfigError naming it
    cfg = cfg.replace(solve={"max_outlier_sigma": 4.0})
    print(cfg.to_yaml())
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from pathlib import Path

import yaml


class ConfigError(ValueError):
    """A bad configuration value or key; errors.py wraps it into an InputError at the API."""


@dataclass(frozen=True)
class SnapshotOptions:
    # One snapshot per bag (first message per topic), or one per period of a continuous bag.
    decimation_period_s: float | None = None
    # Drop a snapshot whose observations are further apart in time than this.
    max_time_spread_s: float = 0.1
    # Time window, each as int s or ns since epoch, float s, or a date string.
    after: str | None = None
    before: str | None = None
    # Periods to skip: list of [start, end] in the same formats.
    exclude_time_periods: list = field(default_factory=list)
    # Bags whose path matches this regex are skipped.
    exclude_bag: str | None = None
    # Continuous bags: drop a period whose board moved (LIDAR board points shift more than this).
    max_board_motion_m: float = 0.03


@dataclass(frozen=True)
class LidarOptions:
    # Points closer/further than this are ignored by segmentation.
    min_range_m: float = 0.5
    max_range_m: float = 9.0
    # Inferred from the data when None (rounded to a power of 2, like the seed).
    npoints_per_rotation: int | None = None
    # Zero points at the per-(ring, azimuth) mode range over the session (walls, ground).
    suppress_static: bool = True
    static_range_quantum_m: float = 0.2


@dataclass(frozen=True)
class SegmentationOptions:
    # Stage 1: flat segments along each ring.
    points_per_segment: int = 8
    max_gap_points_stage1: int = 2
    max_rms_segment_m: float = 0.02
    # Stage 2: clustering segments across rings.
    min_rings: int = 3
    min_segments_per_cluster: int = 4
    max_segments_per_cluster: int = 250
    max_tilt_deg: float = 60.0
    # Stage 3: accumulate points near the plane.
    point_plane_tolerance_m: float = 0.05
    max_gap_points_stage3: int = 5
    # Post-processing checks.
    max_plane_size_m: float = 1.8
    max_plane_rms_m: float = 0.02
    edge_isolation_m: float = 0.3
    # A scan counts only if exactly one board plane is found.
    require_unique: bool = True


@dataclass(frozen=True)
class DetectionOptions:
    detector: str = "mrgingham"  # or "opencv"
    corners_x: int = 10
    corners_y: int = 10
    spacing_m: float = 0.1
    margin_m: float = 0.1
    jobs: int = 2


@dataclass(frozen=True)
class SolveOptions:
    # Initial noise sigmas; re-estimated from the residuals unless fixed.
    sigma_lidar_m: float = 0.03
    sigma_camera_px: float = 0.3
    reestimate_noise: bool = True
    # Outliers: points and whole observations beyond this many sigmas are rejected.
    outlier_sigma: float = 4.0
    reject_outliers: bool = True
    # Regularization of LIDAR-only board poses: rad and m sigmas.
    board_prior_sigma_rad: float = 100.0
    board_prior_sigma_m: float = 10000.0
    max_iterations: int = 100
    # Seed: links with fewer shared snapshots are dropped.
    min_shared_snapshots: int = 3
    # Snapshots whose seed residuals exceed these are dropped whole.
    seed_max_normal_deg: float = 10.0
    seed_max_center_m: float = 0.5
    seed_max_corner_px: float = 50.0
    # Sigma of nominal-pose priors from /tf_static (rad and m); None = no priors.
    prior_from_tf_static_sigma: float | None = None


@dataclass(frozen=True)
class SectorOptions:
    n_sectors: int = 36
    # rt_vehicle_lidar0 (r, t); the sectors are slices of the vehicle's ground plane.
    rt_vehicle_lidar0: list = field(default_factory=lambda: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    threshold_valid_lidar_range_m: float = 1.5
    threshold_valid_lidar_npoints: int = 100
    uncertainty_quantification_range_m: float = 10.0


@dataclass(frozen=True)
class TargetlessOptions:
    # Filled in by the targetless calibration; see targetless/ for the meaning of each.
    mapping_max_frames: int = 500
    local_map_num_keyframes: int = 15
    dense_pointcloud_num_keyframes: int = 10
    mapping_min_range: float = 0.5
    mapping_max_range: float = 60.0
    min_mapping_pointcloud_size: int = 10000
    min_calibration_pointcloud_size: int = 500
    mapping_lost_timeout: float = 1.0


@dataclass(frozen=True)
class Config:
    snapshots: SnapshotOptions = field(default_factory=SnapshotOptions)
    lidar: LidarOptions = field(default_factory=LidarOptions)
    segmentation: SegmentationOptions = field(default_factory=SegmentationOptions)
    detection: DetectionOptions = field(default_factory=DetectionOptions)
    solve: SolveOptions = field(default_factory=SolveOptions)
    sectors: SectorOptions = field(default_factory=SectorOptions)
    targetless: TargetlessOptions = field(default_factory=TargetlessOptions)

    @classmethod
    def from_dict(cls, d: dict | None) -> "Config":
        return _build(cls, d or {}, "")

    @classmethod
    def from_yaml(cls, path: str | Path) -> "Config":
        path = Path(path)
        try:
            d = yaml.safe_load(path.read_text())
        except OSError as e:
            raise ConfigError(f"{path}: cannot read config: {e.strerror}") from None
        except yaml.YAMLError as e:
            raise ConfigError(f"{path}: not valid YAML: {str(e).splitlines()[0]}") from None
        if d is not None and not isinstance(d, dict):
            raise ConfigError(f"{path}: a config file must be a mapping of sections")
        try:
            return cls.from_dict(d)
        except ConfigError as e:
            raise ConfigError(f"{path}: {e}") from None

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    def replace(self, **sections: dict) -> "Config":
        """A copy with some fields of some sections changed, validated like a file."""
        d = self.to_dict()
        for name, values in sections.items():
            if name not in d:
                raise ConfigError(f"unknown config section '{name}'")
            d[name].update(values)
        return Config.from_dict(d)


def _build(cls, d: dict, prefix: str):
    if not isinstance(d, dict):
        raise ConfigError(f"'{prefix.rstrip('.')}' must be a mapping")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - names)
    if unknown:
        raise ConfigError(
            f"unknown config key '{prefix}{unknown[0]}' (known: {', '.join(sorted(names))})"
        )
    kwargs = {}
    for name, value in d.items():
        kwargs[name] = _check(hints[name], value, prefix + name)
    return cls(**kwargs)


def _check(tp, value, path: str):
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, path + ".")
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _check(a, value, path)
            except ConfigError as e:
                errors.append(e)
        raise errors[0]
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"'{path}' must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"'{path}' must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"'{path}' must be a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"'{path}' must be a string, got {value!r}")
        return value
    if tp is list or origin is list:
        if not isinstance(value, list):
            raise ConfigError(f"'{path}' must be a list, got {value!r}")
        return list(value)
    raise ConfigError(f"'{path}': unsupported type {tp}")
