"""Settings: small validated dataclass sections, loaded from and dumped to YAML.

Unknown keys are rejected (with their dotted path); values are type-checked, range-checked
(``_RANGES`` and the tables beside it, at the bottom: NaN/inf, min > max pairs, regexes) and
never silently "fixed". ``Config().to_dict()`` is what ``clcgraph config dump`` prints.
Each section documents its fields in comments next to the defaults. This module
imports nothing of clcgraph but ``errors`` (which imports nothing at all).

SYNOPSIS
    cfg = Config.from_yaml("my.yaml")          # unknown key -> ConfigError naming it
    cfg = cfg.replace(solve={"max_outlier_sigma": 4.0})
    print(cfg.to_yaml())
"""

from __future__ import annotations

import dataclasses
import math
import re
import typing
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from .errors import InputError


class ConfigError(InputError, ValueError):
    """A bad configuration value or key (an InputError, so ``except ClcgraphError`` catches it)."""


@dataclass(frozen=True)
class SnapshotOptions:
    # One snapshot per bag (first message per topic), or one per period of a continuous bag.
    decimation_period_s: float | None = None
    # Drop a snapshot whose observations are further apart in time than this; None: no limit
    # (clc's default). A bag per pose is still by construction; in a continuous bag the motion
    # check decides whether the board was still, and every chosen message must lie inside the
    # interval it checked.
    max_time_spread_s: float | None = None
    # Time window, each as int s or ns since epoch, float s, or a date string.
    after: str | None = None
    before: str | None = None
    # Periods to skip: list of [start, end] in the same formats.
    exclude_time_periods: list = field(default_factory=list)
    # Snapshots to leave out: comma-separated bag names (path, file name or stem) and snapshot
    # indices (as calibration.yaml's snapshots.list numbers them; indices do not shift), or a regex:
    # bags whose path matches it are not read.
    exclude_bag: str | None = None
    # Continuous bags: drop a period whose board moved (LIDAR board points shift more than this).
    max_board_motion_m: float = 0.03
    # Motion check: compare the chosen scan with the scans this long before and after it.
    motion_window_s: float = 0.5
    # ... and call it motion if at least this many (ring, azimuth) cells changed (in runs; a
    # moving board changes ~100 or more, range noise a few at random).
    min_moving_cells: int = 20
    # A bag per pose or a still interval: average each LIDAR's first this many scans of the still
    # scene (range noise / sqrt(n); scans in which something moved are left out); 1: the first scan
    # alone (clc).
    max_scans_averaged: int = 5


@dataclass(frozen=True)
class LidarOptions:
    # Points closer/further than this are ignored by segmentation (boards are held 2-12 m away).
    min_range_m: float = 0.5
    max_range_m: float = 15.0
    # Inferred from the data when None (rounded to a power of 2, like the seed).
    npoints_per_rotation: int | None = None
    # Zero points at the per-(ring, azimuth) mode range over the session (walls, ground).
    suppress_static: bool = True
    static_range_quantum_m: float = 0.1


@dataclass(frozen=True)
class SegmentationOptions:
    # Stage 1: flat segments along each ring.
    points_per_segment: int = 8
    max_gap_points_stage1: int = 2
    # Straightness of a segment: RMS distance of its points from their line (a few range sigmas).
    max_rms_segment_m: float = 0.03
    # Neighbouring returns more than 5 cm + this many point spacings apart are separate objects
    # (stages 1 and 3; seed: threshold_distance_adjacent_points_cross_segment).
    max_jump_spacings: float = 3.0
    # Stage 2: clustering segments across rings. Neighbouring segments link when they run
    # within these angles of each other (same ring / across rings; seed: min_cos_angle_error_*),
    max_angle_same_ring_deg: float = 15.0
    max_angle_cross_ring_deg: float = 30.0
    # ... are at most this many rings apart (a ring may miss the board through dropouts),
    max_ring_step: int = 2
    # ... and lie at most this multiple of the ring spacing apart (seed: max_distance_across_rings,
    # here relative: ring spacing x range / cos(max_tilt)).
    ring_spacing_tolerance: float = 1.25
    # A segment belongs to a RANSAC plane of a mixed cluster when this share of its points fit.
    segment_inlier_share: float = 0.6
    min_rings: int = 3
    min_segments_per_cluster: int = 4
    max_segments_per_cluster: int = 5000
    # Planes seen more than this far off head-on are ignored (the ground is seen at grazing angles).
    max_tilt_deg: float = 60.0
    # Stage 3: accumulate points near the plane.
    point_plane_tolerance_m: float = 0.05
    max_gap_points_stage3: int = 5
    # Post-processing checks.
    # Board sizes come from the 'board' section (the physical board, border included).
    # A plane whose rings run on past the board's fitted rectangle by more than this share of
    # their returns continues past the board (a wall, a car); a smaller share touching it (a hand)
    # is cut off, and pieces of ring wholly beside it (a person in its plane) are dropped.
    max_outside_fraction: float = 0.1
    # ...and no board is larger than this across (m; None: the diagonal of board.size_m plus the
    # edges' blooming by a point spacing).
    max_plane_size_m: float | None = None
    # ...smaller than this fraction of the board's diagonal is something else (a crate, a sign).
    min_plane_size_fraction: float = 0.5
    # ...narrower than this fraction of the board's short side is a sliver (seed: 2nd dimension check).
    min_width_fraction: float = 0.2
    # ...and some ring must cross at least this fraction of the board's short side (and 0.6 x the
    # height seen, up to the side: a tall narrow plane is a body or a post).
    min_chord_fraction: float = 0.45
    # A board is flat: its plane-fit RMS (each laser's own range offset included) is at most this,
    max_plane_rms_m: float = 0.03
    # ...and, about each ring's mean offset from the plane (real lasers range with offsets of
    # 1-3 cm of their own), at most this many times the range noise seen along the scan's
    # straight segments.
    max_plane_rms_sigmas: float = 1.5
    # A scan counts only if exactly one board plane is found.
    require_unique: bool = True
    # [xmin, xmax, ymin, ymax] in the LIDAR frame (m): report every cluster and candidate plane
    # there, with its verdict, on stderr (the seed's --debug-xmin ... --debug-ymax).
    debug_region: list | None = None


def _pair(value, path: str, kind, *, positive: bool) -> list:
    """[a, b] of ints or numbers, checked (a 2-list in a ``board`` key)."""
    ok_type = (lambda v: isinstance(v, int) and not isinstance(v, bool)) if kind is int else \
        (lambda v: isinstance(v, (int, float)) and not isinstance(v, bool))
    if not (isinstance(value, (list, tuple)) and len(value) == 2 and all(map(ok_type, value))):
        raise ConfigError(f"'{path}' must be two {'integers' if kind is int else 'numbers'} [along the width, "
                          f"along the height], got {value!r}")
    if not all(math.isfinite(v) and abs(v) <= 1000 for v in value):
        raise ConfigError(f"'{path}' must be finite numbers of at most 1000, got {value!r}")
    if positive and min(value) <= 0:
        raise ConfigError(f"'{path}' must be positive, got {value!r}")
    return [kind(v) for v in value]


@dataclass(frozen=True)
class BoardOptions:
    # The chessboard as you measure it. Inner corners along the board's width and height (where
    # four squares meet; a 10x10 board has 11x11 squares).
    corners: list = field(default_factory=lambda: [10, 10])
    # Square size (m).
    square_m: float = 0.1
    # The physical board, width x height (m): the pattern plus its white border (the default has
    # a 0.1 m border beyond the outer squares). LIDARs see the whole board: measure its edges.
    size_m: list = field(default_factory=lambda: [1.3, 1.3])
    # The pattern's centre relative to the board's centre, along the width and height (m).
    pattern_offset_m: list = field(default_factory=lambda: [0.0, 0.0])
    # The board's thickness (m): a LIDAR behind the board sees its back face, this far behind
    # the pattern. None: not measured, taken for 10 mm (types.ASSUMED_THICKNESS_M) and known
    # to 5 mm (solve.board_thickness_sigma_m).
    thickness_m: float | None = None

    def __post_init__(self):
        corners = _pair(self.corners, "board.corners", int, positive=True)
        size = _pair(self.size_m, "board.size_m", float, positive=True)
        offset = _pair(self.pattern_offset_m, "board.pattern_offset_m", float, positive=False)
        if min(corners) < 2:
            raise ConfigError(f"'board.corners' must be >= 2 each (inner corners), got {self.corners!r}")
        if self.square_m <= 0:
            raise ConfigError(f"'board.square_m' must be positive, got {self.square_m!r}")
        for k, axis in enumerate(("width", "height")):
            pattern = (corners[k] + 1) * self.square_m
            if abs(offset[k]) + pattern / 2 > size[k] / 2 + 1e-9:
                raise ConfigError(f"'board.size_m': the pattern ({corners[k] + 1} squares of {self.square_m:g} m = "
                                  f"{pattern:.3f} m along the {axis}, offset {offset[k]:g} m) does not fit on a "
                                  f"{size[k]:g} m {axis}; size_m is the whole physical board")
        object.__setattr__(self, "corners", corners)  # tuples from the API become plain lists
        object.__setattr__(self, "size_m", size)
        object.__setattr__(self, "pattern_offset_m", offset)


@dataclass(frozen=True)
class DetectionOptions:
    # auto: mrgingham for square grids (NxN inner corners), OpenCV for the others (mrgingham
    # handles only square grids); or name one of them.
    detector: typing.Literal["auto", "mrgingham", "opencv"] = "auto"
    # With mrgingham: try OpenCV on the images where mrgingham found nothing (small boards).
    fallback_opencv: bool = True
    # Refine the detected corners to the image's saddle points (cv2.cornerSubPix).
    refine_subpix: bool = True
    jobs: int = 2
    # Reject a grid whose neighbour steps change by more than this fraction of a step.
    max_grid_irregularity: float = 0.5
    # Reject a blurred board: median edge blur (Gaussian sigma, px) above this.
    max_blur_sigma_px: float = 2.5


@dataclass(frozen=True)
class SolveOptions:
    # Initial noise sigmas; re-estimated from the residuals unless fixed.
    sigma_lidar_m: float = 0.03
    sigma_camera_px: float = 0.3
    reestimate_noise: bool = True
    # One sigma per sensor (rigs mix LIDAR models and cameras); False: one per kind, as the seed.
    noise_per_sensor: bool = True
    # Outliers: points and whole observations beyond this many sigmas are rejected.
    outlier_sigma: float = 4.0
    reject_outliers: bool = True
    # Regularization of LIDAR-only board poses: rad and m sigmas. It holds only the in-plane
    # DOFs, which no LIDAR residual touches, so its strength changes no answer; far weaker
    # than 1 it only makes the information matrix too ill-conditioned to factor.
    board_prior_sigma_rad: float = 1.0
    board_prior_sigma_m: float = 1.0
    max_iterations: int = 100
    # Seed: links with fewer shared snapshots are dropped.
    min_shared_snapshots: int = 3
    # Snapshots whose seed residuals exceed these are dropped whole.
    seed_max_normal_deg: float = 10.0
    seed_max_center_m: float = 0.5
    seed_max_corner_px: float = 50.0
    # Nominal-pose priors from /tf_static: 1-sigma of the rotation (rad, per axis) and of the
    # translation (m, per axis); both set, or both None (no priors).
    prior_from_tf_static_sigma_rad: float | None = None
    prior_from_tf_static_sigma_m: float | None = None  # the translation sigma (m), set together with _rad
    # A sensor whose 1-sigma exceeds these in some direction is not determined by the data:
    # a DegenerateError names it and the direction instead of returning a useless number
    # (checked on the graph's own covariance, and again with the consider terms, naming the
    # one that makes most of it). 3 cm / 1 deg: several times what a usable calibration has
    # (real ACFR captures of 11 boards: <= 15 mm, 0.2 deg), and a pose known to no better is
    # of no use to a fusion; a capture must not pass them as "calibrated".
    max_stdev_m: float = 0.03
    max_stdev_deg: float = 1.0
    # Self-consistency checks (backend/consistency.py): the chance that a consistent
    # calibration fails them; 0 turns the checks off.
    consistency_alpha: float = 1e-3
    # A result that fails them is refused (exit 2, one line naming the snapshot, sensor and
    # direction), including a direction one board alone determines (an error there would pass
    # every check); a snapshot that alone disagrees with the others is first left out (up to
    # one in ten, each named: docs/uncertainty.md). False: written with its verdict in
    # calibration.yaml, the report and a line under the summary table.
    refuse_inconsistent: bool = True
    # Along a principal axis where the leave-one-snapshot-out jackknife rejects the noise model
    # (its ratio above the range the model expects: ~2.5 % of the axes when the model is right),
    # the covariance is raised to the jackknife's spread (backend/jackknife.py). False: the
    # model's covariance as it is (the check is still reported).
    jackknife_floor: bool = True
    # Each observation's own board-pose error (a LIDAR's plane tilt and offset, a camera's
    # board-pose jitter), its sigmas estimated from the data: real errors are correlated
    # within one observation (docs/uncertainty.md; on the real ACFR captures it brings the
    # sigmas to the jackknife's spread, where independent noise is 3-8x too small). A
    # component is kept only if a likelihood-ratio test shows it, so on independent noise
    # the sigmas stay those of the independent model. False: independent noise only.
    observation_effects: bool = True
    # The board's in-plane position from where each LIDAR saw its outline (factors/lidar_edge.py):
    # the rings' ends at its left and right edges and the rings above and below it, where the next
    # ray passed behind the board's plane. Planes alone leave a camera's offset along the board
    # rest on the few tilted boards. The edge blur: the LIDAR's range sigma and its beam's
    # footprint, ``lidar_edge_beam_rad`` (rad, 1 sigma) times the range: 0.17-0.18 deg FWHM for an
    # Ouster OS1 or a VLP-16, / 2.355. On the real ACFR Ouster captures the edge residuals are the
    # quantisation alone (RMS 6.3-6.8 mm, L / sqrt(12) 7.0 mm), and run 2, whose camera height
    # rests on one pitched board without them (refused), is answered and agrees with run 1.
    # False: planes only (a board whose outline the LIDAR cannot see cleanly, e.g. a frame
    # around it that returns too).
    lidar_edges: bool = True
    lidar_edge_beam_rad: float = 0.0013
    # Errors fixed for the whole capture, which neither the per-observation model nor the
    # jackknife can see (they bias every board the same way), propagated into the covariance
    # as "consider" terms (backend/consider.py, docs/uncertainty.md); 0 = not included.
    # The board's bow (m): its centre this far off the plane of its edges, 1 sigma. 1 mm: a
    # rigid printed target; a large hand-held foam or plywood board bows 2-5 mm: state yours.
    board_flatness_m: float = 0.001
    # How well board.thickness_m is known (m, 1 sigma): it places the back face, which only a
    # LIDAR behind the board sees (no term without such a view). None: 1 mm where the
    # thickness is stated (measured), 5 mm where it is not (boards are 3-20 mm thick).
    board_thickness_sigma_m: float | None = None
    # One range offset common to all of a LIDAR's points (m, 1 sigma; its datasheet's
    # range accuracy is an upper bound, it includes the per-point noise).
    lidar_range_offset_m: float = 0.0
    # Each laser's (ring's) own range offset (m) and elevation error (deg), 1 sigma, independent
    # per ring. The frontend measures and removes the rings' relative range offsets; what no
    # board can show stays (a common offset and one linear in elevation, which tilt every board
    # alike) and is a consider term, as is the same part of the elevation errors.
    # 0 by default, like the lens field below: as defaults (1 cm, 0.1 deg, 0.1 px) they doubled
    # the median sigma of exact sensors (up to 16x; issue 12 forbids blanket inflation). The
    # range term takes, per LIDAR, the spread of the ring offsets the frontend measured on its
    # boards where that is larger (what the capture shows of the unit: none for an exact one).
    # State your units' figures: docs/uncertainty.md, "When to set a term to 0".
    lidar_ring_range_bias_m: float = 0.0
    lidar_ring_elevation_deg: float = 0.0
    # A camera's lens-model error: a smooth pixel-error field fixed in the image, the same for
    # every board at the same image position (RMS px of the error vector, 1 sigma).
    camera_lens_field_px: float = 0.0
    # A camera's focal length, relative error (1 sigma, e.g. 0.01 = 1 %), for cameras whose model
    # carries no covariance of its own (those that do have their intrinsics term). Boards all
    # at one distance cannot tell it from the camera's depth: on the real ACFR fisheye 1 % moves
    # the camera 31-35 mm (a 32 mm sigma, docs/uncertainty.md). 0: not included (the report says
    # so); state yours.
    camera_focal_scale_sigma: float = 0.0


@dataclass(frozen=True)
class SectorOptions:
    # Seed's sector feedback (backend/sectors.py): equal azimuth slices of the ground plane.
    n_sectors: int = 36
    # rt_vehicle_lidar0 (r, t); the sectors are slices of the vehicle's ground plane.
    rt_vehicle_lidar0: list = field(default_factory=lambda: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    # A LIDAR sees a sector if it has >= npoints visibility points beyond this range there.
    threshold_valid_lidar_range_m: float = 1.5
    threshold_valid_lidar_npoints: int = 100
    # Worst-pair stdev is evaluated on the ground this far from the vehicle origin (m).
    uncertainty_quantification_range_m: float = 10.0


@dataclass(frozen=True)
class TargetlessOptions:
    # Filled in by the targetless calibration; see targetless/ for the meaning of each.
    mapping_max_frames: int = 500
    local_map_num_keyframes: int = 15
    dense_pointcloud_num_keyframes: int = 10  # <= 31: a dense target voxel's submap label has 6 bits
    mapping_min_range: float = 0.5
    mapping_max_range: float = 60.0
    # Scans with fewer points in range are not mapped (partial or blocked scans).
    min_mapping_pointcloud_size: int = 10000
    min_calibration_pointcloud_size: int = 500
    mapping_lost_timeout: float = 1.0
    # Mapper (seed names). mapper_registrator: VGICP, voxelized GICP against an incremental map
    # of Gaussian voxels of mapper_resolution m (each keyframe inserted once; the NDT-like option,
    # "NDT" in a seed config means VGICP), or GICP against the local map's points and KD-tree,
    # rebuilt at every keyframe (~1.6x the mapping time). On the simulated 10 s / 60 s bench
    # drives, VGICP at 0.3 m maps as accurately as GICP (step-to-step and 1 m translation errors
    # smaller, rotation errors within ~10 % either way) and the calibrations are within 0.0015 deg
    # / 0.3 mm of GICP's (1-sigma 0.015-0.027 deg / 1.2-1.9 mm). The seed's 5 m NDT cells are far
    # too coarse for VGICP (0.2 deg per frame in a simulated street). NDT's step size and epsilon
    # are kept for the seed's config files but not used.
    mapper_registrator: typing.Literal["GICP", "VGICP", "NDT"] = "VGICP"
    mapper_resolution: float = 0.3
    mapper_step_size: float = 0.1
    mapper_max_iterations: int = 35
    mapper_epsilon: float = 0.01
    mapper_num_threads: int = 2
    mapper_max_correspondence_distance: float = 0.1  # seed default; the first pass uses 10x
    mapping_viz_leaf_size: float = 0.15
    calibration_viz_leaf_size: float = 0.15
    leaf_size_input: float = 0.1
    # Registration uses at most this many of a scan's input-voxel points (evenly thinned). On the
    # 64-ring bench drives 6000 maps as well as 12000 (10 s: 0.0039 deg / 0.70 mm against 0.0057 /
    # 0.72; 60 s: 0.0020 / 0.25 against 0.0013 / 0.30) in ~60 % of the time.
    mapping_max_source_points: int = 6000
    leaf_size_local_map: float = 0.1
    leaf_size_dense_map: float = 0.05
    new_keyframe_min_distance: float = 1.0
    new_frame_min_distance: float = 0.05
    frame_stopped_distance: float = 0.02
    frames_since_stopped_force_frame: int = 5
    calibration_skip_keyframes: int = 5
    # Deskew with per-point times and the estimated twist; iterations of (deskew, register).
    deskew: bool = True
    deskew_iterations: int = 2
    # Calibration-frame interpolation limits, "standard" criteria (s, m, deg, m/s, m/s^2).
    max_allowed_interpolated_time: float = 0.05
    max_allowed_interpolated_distance: float = 0.05
    max_allowed_interpolated_angle: float = 1.0
    max_allowed_interpolated_speed: float = 3.0
    max_allowed_interpolated_accel: float = 0.4
    # ... "straight" criteria (used when the turn is small).
    max_allowed_interpolated_distance_straight: float = 0.08
    max_allowed_interpolated_angle_straight: float = 0.5
    max_allowed_interpolated_speed_straight: float = 5.0
    max_allowed_interpolated_accel_straight: float = 0.1
    # The seed's camera-LIDAR targetless settings (detections, camera frames, image features) are
    # kept for its config files but not used: targetless calibration here is LIDAR-only.
    filter_detections: bool = True
    detection_max_time_tolerance: float = 0.5
    detection_size_tolerance: float = 0.4
    # Lost-frame detection between consecutive frames (deg, m, m/s^2).
    lost_frame_max_angle_diff: float = 25.0
    # ... and when the constant-velocity prediction misses the registered pose by more than this (m).
    lost_frame_interpolation_error: float = 0.05
    lost_frame_max_acceleration: float = 8.0
    # Report pictures: points beyond this range are left out, clouds voxelized to the viz leaf sizes.
    viz_max_range: float = 80.0
    crop_z_calibration_pointclouds: bool = True
    crop_z_calibration_pointclouds_value: float = 2.0
    calibration_use_only_stopped: bool = False
    # Choose calibration frames from the end of the drive only (2 x lidar_calibration_max_frames).
    calibration_use_only_last_frames: bool = False
    max_calibration_range: float = 80.0
    min_calibration_range: float = 1.5
    calibration_min_pca_eigenvalue: float = 0.25
    calibration_min_distance_between_frames: float = 5.0
    calibration_eval_max_corr_distance: float = 0.1
    # Registration ensemble.
    solver_iterations: int = 200
    max_corr_dist_coarse: float = 0.5
    max_corr_dist_fine: float = 0.1
    max_corr_dist_ultra_fine: float = 0.05
    lidar_calibration_min_frames: int = 2
    lidar_calibration_max_frames: int = 10
    # Final graph (clcgraph, not in the seed): prior covariance of the registration bias shared
    # by all frames, in units of one frame's covariance (0: trust the frames' scatter alone).
    registration_common_mode: float = 1.0
    # (camera targetless: not used, see above)
    camera_calibration_min_frames: int = 1
    camera_calibration_max_frames: int = 10
    pc_features_min_distance: float = 0.2
    pc_features_max_distance: float = 40.0
    # base_link-LIDAR ground plane (crop box in the LIDAR frame, m).
    base_lidar_crop_box_min_x: float = -20.0
    base_lidar_crop_box_min_y: float = -20.0
    base_lidar_crop_box_min_z: float = -20.0
    base_lidar_crop_box_max_x: float = 20.0
    base_lidar_crop_box_max_y: float = 20.0
    base_lidar_crop_box_max_z: float = 20.0
    base_lidar_max_inlier_distance: float = 0.01
    base_lidar_max_iterations: int = 1000
    base_lidar_min_plane_points: int = 1000
    base_lidar_min_plane_points_percentage: float = 10.0
    base_lidar_max_cos_distance: float = 0.5
    # False: x, y, yaw of base_link-LIDAR from the initial guess; True: base_link right below the
    # LIDAR, heading along its x axis.
    base_lidar_overwrite_xy_yaw: bool = False


@dataclass(frozen=True)
class CompareOptions:
    # `clcgraph compare` / fleet: a sensor "moved" when the chi-square test of its pose difference
    # against both calibrations' covariances gives p below this: the share of unchanged sensors
    # flagged anyway (false alarms), if the covariances are honest.
    false_alarm_rate: float = 0.01
    # Against a pose set without covariance (CAD, /tf_static) there is no test: "moved" beyond
    # these (a mounting tolerance; set your fleet's).
    max_rotation_deg: float = 1.0
    max_translation_mm: float = 20.0
    # Two calibrations of the same sensor units share the units' own errors (each LIDAR ring's range
    # bias and elevation error, a camera's lens-model field): each capture's solution moves with them
    # differently (its board poses differ), so their difference carries (J_A - J_B) e. calibration.yaml
    # names the errors and J (``unit_errors``); these are the units' 1-sigmas used here (whatever the
    # solves' own solve.lidar_ring_* / camera_lens_field_px). Defaults: typical of real units (16- to
    # 128-ring LIDARs: ~1 cm, 0.1 deg per ring; a well-fitted lens model: 0.1 px); state your units'.
    # 0 = that kind of error is not in the test (the covariances alone).
    unit_ring_range_bias_m: float = 0.01
    unit_ring_elevation_deg: float = 0.1
    unit_lens_field_px: float = 0.1
    # The two calibrations are of the same units (the usual recalibration). false: a unit was replaced
    # (or the vehicles differ): its errors are independent draws, J_A S J_A^T + J_B S J_B^T.
    same_units: bool = True


@dataclass(frozen=True)
class Config:
    snapshots: SnapshotOptions = field(default_factory=SnapshotOptions)
    lidar: LidarOptions = field(default_factory=LidarOptions)
    segmentation: SegmentationOptions = field(default_factory=SegmentationOptions)
    board: BoardOptions = field(default_factory=BoardOptions)
    detection: DetectionOptions = field(default_factory=DetectionOptions)
    solve: SolveOptions = field(default_factory=SolveOptions)
    sectors: SectorOptions = field(default_factory=SectorOptions)
    targetless: TargetlessOptions = field(default_factory=TargetlessOptions)
    compare: CompareOptions = field(default_factory=CompareOptions)

    @classmethod
    def from_dict(cls, d: dict | None) -> "Config":
        cfg = _build(cls, d or {}, "")
        _check_ranges(cfg)
        return cfg

    @classmethod
    def from_yaml(cls, path: str | Path) -> "Config":
        d = read_yaml(path, "config file", error=ConfigError, max_bytes=_MAX_YAML_BYTES)
        if d is not None and not isinstance(d, dict):
            raise ConfigError(f"{path}: a config file must be a mapping of sections")
        try:
            return cls.from_dict(d)
        except ConfigError as e:
            raise ConfigError(f"{path}: {e}") from None

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def to_yaml(self, *, comments: bool = False) -> str:
        """YAML of every setting; ``comments`` adds each field's comment from this file above it."""
        if not comments:
            return yaml.safe_dump(self.to_dict(), sort_keys=False)
        lines = ["# clcgraph settings (clcgraph config dump). Units: m, s, deg as named; unknown keys are errors."]
        for f in dataclasses.fields(self):
            section = getattr(self, f.name)
            notes = _field_comments(type(section))
            lines.append(f"{f.name}:")
            for name, value in dataclasses.asdict(section).items():
                lines += [f"  # {c}" for c in notes.get(name, [])]
                text = yaml.safe_dump({name: value}, default_flow_style=True, width=1000).strip()
                lines.append("  " + text[1:-1])  # drop the flow mapping's braces
        return "\n".join(lines) + "\n"

    def replace(self, **sections: dict) -> "Config":
        """A copy with some fields of some sections changed, validated like a file."""
        d = self.to_dict()
        for name, values in sections.items():
            if name not in d:
                raise ConfigError(f"unknown config section '{name}'")
            d[name].update(values)
        return Config.from_dict(d)


def _field_comments(cls) -> dict[str, list[str]]:
    """{field: the comment lines right above it in the class body} (the documentation of defaults)."""
    import inspect

    out, pending = {}, []
    for line in inspect.getsource(cls).splitlines()[1:]:
        s = line.strip()
        if s.startswith("#"):
            pending.append(s.lstrip("#").strip())
        elif ":" in s and not s.startswith(("@", "def ", '"')):
            name = s.split(":", 1)[0].strip()
            tail = s.split("#", 1)[1].strip() if "#" in s else None
            out[name] = pending + ([tail] if tail else [])
            pending = []
        else:
            pending = []
    return out


# Keys that existed once: a config that still has one gets where it went, not "unknown key".
_BOARD_HINT = ("moved to the 'board' section, which describes the physical board: board: {corners: [nx, ny], "
               "square_m: s, size_m: [width, height]} (the old margin_m was counted from the outer inner corners: "
               "width = (nx - 1) * s + 2 * margin_m)")
_REPLACED_KEYS = {
    "solve.prior_from_tf_static_sigma": "was one sigma for both radians and metres; set "
    "solve.prior_from_tf_static_sigma_rad and solve.prior_from_tf_static_sigma_m instead",
    **{f"detection.{k}": _BOARD_HINT for k in ("corners_x", "corners_y", "spacing_m", "margin_m")},
}


def _build(cls, d: dict, prefix: str):
    if not isinstance(d, dict):
        raise ConfigError(f"'{prefix.rstrip('.')}' must be a mapping")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - names)
    for key in unknown:
        if prefix + str(key) in _REPLACED_KEYS:
            raise ConfigError(f"'{prefix}{key}' {_REPLACED_KEYS[prefix + str(key)]}")
    if unknown:
        raise ConfigError(
            f"unknown config key '{prefix}{unknown[0]}' (known: {', '.join(sorted(names))})"
        )
    kwargs = {}
    for name, value in d.items():
        try:
            kwargs[name] = _check(hints[name], value, prefix + name)
        except ConfigError as e:
            e.key = getattr(e, "key", prefix + name)  # the innermost key (the CLI names its flag)
            raise
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
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"'{path}' must be one of {', '.join(map(str, args))}, got {value!r}")
        return value
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
        if not math.isfinite(value):  # NaN passes every comparison: refuse it here, once
            raise ConfigError(f"'{path}' must be a finite number, got {value!r}")
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


# ------------------------------------------------------------------ value ranges
# Every numeric setting's allowed range, checked whenever a Config is built (file, dict,
# replace, CLI flags). Interval notation: "[" / "]" include the bound, "(" / ")" exclude it;
# "inf" = unbounded. Integers are also bounded by _INT_MAX (they reach numpy as int32/int64).
# The ranges say what makes sense physically, not what the tests happen to use.
_RANGES = {
    "snapshots.decimation_period_s": "(0, inf)",
    "snapshots.max_time_spread_s": "[0, inf)",
    "snapshots.max_board_motion_m": "(0, inf)",
    "snapshots.motion_window_s": "(0, inf)",
    "snapshots.min_moving_cells": "[1, inf)",
    "snapshots.max_scans_averaged": "[1, 1000]",
    "lidar.min_range_m": "[0, inf)",
    # no LIDAR return comes from beyond 10 km (and the static-scene range bins stay int64)
    "lidar.max_range_m": "(0, 10000]",
    "lidar.npoints_per_rotation": "[16, 100000]",
    # a range bin finer than 1 mm is far below any LIDAR's noise (and overflows the cell keys)
    "lidar.static_range_quantum_m": "[0.001, 10]",
    "segmentation.points_per_segment": "[3, inf)",
    "segmentation.max_gap_points_stage1": "[0, inf)",
    "segmentation.max_rms_segment_m": "(0, inf)",
    "segmentation.max_jump_spacings": "[0, inf)",
    "segmentation.max_angle_same_ring_deg": "(0, 90]",
    "segmentation.max_angle_cross_ring_deg": "(0, 90]",
    "segmentation.max_ring_step": "[1, inf)",
    "segmentation.ring_spacing_tolerance": "(0, inf)",
    "segmentation.segment_inlier_share": "(0, 1]",
    "segmentation.min_rings": "[1, inf)",
    "segmentation.min_segments_per_cluster": "[1, inf)",
    "segmentation.max_segments_per_cluster": "[1, inf)",
    "segmentation.max_tilt_deg": "(0, 90]",
    "segmentation.point_plane_tolerance_m": "(0, inf)",
    "segmentation.max_gap_points_stage3": "[0, inf)",
    "segmentation.max_outside_fraction": "[0, 1]",
    "segmentation.max_plane_size_m": "(0, inf)",
    "segmentation.min_plane_size_fraction": "[0, 1]",
    "segmentation.min_width_fraction": "[0, 1]",
    "segmentation.min_chord_fraction": "[0, 1]",
    "segmentation.max_plane_rms_m": "(0, inf)",
    "segmentation.max_plane_rms_sigmas": "(0, inf)",
    "board.square_m": "(0, 10]",
    "board.thickness_m": "[0, 0.2]",
    "detection.jobs": "[1, 1024]",
    "detection.max_grid_irregularity": "(0, inf)",
    "detection.max_blur_sigma_px": "(0, inf)",
    "solve.sigma_lidar_m": "(0, inf)",
    "solve.sigma_camera_px": "(0, inf)",
    # below 1 sigma most good measurements would be "outliers"
    "solve.outlier_sigma": "[1, inf)",
    "solve.board_prior_sigma_rad": "(0, inf)",
    "solve.board_prior_sigma_m": "(0, inf)",
    "solve.max_iterations": "[1, inf)",
    "solve.min_shared_snapshots": "[1, inf)",
    "solve.seed_max_normal_deg": "(0, 180]",
    "solve.seed_max_center_m": "(0, inf)",
    "solve.seed_max_corner_px": "(0, inf)",
    "solve.prior_from_tf_static_sigma_rad": "(0, inf)",
    "solve.prior_from_tf_static_sigma_m": "(0, inf)",
    "solve.consistency_alpha": "[0, 1)",
    "solve.max_stdev_m": "(0, inf)",
    "solve.board_flatness_m": "[0, 0.1]",
    "solve.board_thickness_sigma_m": "[0, 0.1]",
    "solve.lidar_edge_beam_rad": "[0, 0.1]",
    "solve.lidar_range_offset_m": "[0, 1]",
    "solve.lidar_ring_range_bias_m": "[0, 1]",
    "solve.lidar_ring_elevation_deg": "[0, 5]",
    "solve.camera_lens_field_px": "[0, 10]",
    "solve.camera_focal_scale_sigma": "[0, 0.5]",
    "solve.max_stdev_deg": "(0, 180]",
    "sectors.n_sectors": "[1, 3600]",
    "sectors.threshold_valid_lidar_range_m": "[0, inf)",
    "sectors.threshold_valid_lidar_npoints": "[0, inf)",
    "sectors.uncertainty_quantification_range_m": "(0, inf)",
    "targetless.mapping_max_frames": "[2, inf)",
    "targetless.local_map_num_keyframes": "[1, inf)",
    "targetless.dense_pointcloud_num_keyframes": "[1, 31]",
    "targetless.mapping_min_range": "[0, inf)",
    "targetless.mapping_max_range": "(0, inf)",
    "targetless.min_mapping_pointcloud_size": "[1, inf)",
    "targetless.min_calibration_pointcloud_size": "[1, inf)",
    "targetless.mapping_lost_timeout": "(0, inf)",
    "targetless.mapper_resolution": "(0, inf)",
    "targetless.mapper_step_size": "(0, inf)",
    "targetless.mapper_max_iterations": "[1, inf)",
    "targetless.mapper_epsilon": "(0, inf)",
    "targetless.mapper_num_threads": "[1, 1024]",
    "targetless.mapper_max_correspondence_distance": "(0, inf)",
    "targetless.mapping_viz_leaf_size": "(0, inf)",
    "targetless.calibration_viz_leaf_size": "(0, inf)",
    "targetless.leaf_size_input": "(0, inf)",
    "targetless.mapping_max_source_points": "[1, inf)",
    "targetless.leaf_size_local_map": "(0, inf)",
    "targetless.leaf_size_dense_map": "(0, inf)",
    "targetless.new_keyframe_min_distance": "(0, inf)",
    "targetless.new_frame_min_distance": "[0, inf)",
    "targetless.frame_stopped_distance": "[0, inf)",
    "targetless.frames_since_stopped_force_frame": "[1, inf)",
    "targetless.calibration_skip_keyframes": "[0, inf)",
    "targetless.deskew_iterations": "[1, inf)",
    "targetless.max_allowed_interpolated_time": "(0, inf)",
    "targetless.max_allowed_interpolated_distance": "(0, inf)",
    "targetless.max_allowed_interpolated_angle": "(0, 180]",
    "targetless.max_allowed_interpolated_speed": "(0, inf)",
    "targetless.max_allowed_interpolated_accel": "(0, inf)",
    "targetless.max_allowed_interpolated_distance_straight": "(0, inf)",
    "targetless.max_allowed_interpolated_angle_straight": "(0, 180]",
    "targetless.max_allowed_interpolated_speed_straight": "(0, inf)",
    "targetless.max_allowed_interpolated_accel_straight": "(0, inf)",
    "targetless.detection_max_time_tolerance": "[0, inf)",
    "targetless.detection_size_tolerance": "[0, inf)",
    "targetless.lost_frame_max_angle_diff": "(0, 180]",
    "targetless.lost_frame_interpolation_error": "(0, inf)",
    "targetless.lost_frame_max_acceleration": "(0, inf)",
    "targetless.viz_max_range": "(0, inf)",
    "targetless.crop_z_calibration_pointclouds_value": "(0, inf)",
    "targetless.max_calibration_range": "(0, inf)",
    "targetless.min_calibration_range": "[0, inf)",
    "targetless.calibration_min_pca_eigenvalue": "[0, inf)",
    "targetless.calibration_min_distance_between_frames": "[0, inf)",
    "targetless.calibration_eval_max_corr_distance": "(0, inf)",
    "targetless.solver_iterations": "[1, inf)",
    "targetless.max_corr_dist_coarse": "(0, inf)",
    "targetless.max_corr_dist_fine": "(0, inf)",
    "targetless.max_corr_dist_ultra_fine": "(0, inf)",
    "targetless.lidar_calibration_min_frames": "[1, inf)",
    "targetless.lidar_calibration_max_frames": "[1, inf)",
    "targetless.registration_common_mode": "[0, inf)",
    "targetless.camera_calibration_min_frames": "[1, inf)",
    "targetless.camera_calibration_max_frames": "[1, inf)",
    "targetless.pc_features_min_distance": "[0, inf)",
    "targetless.pc_features_max_distance": "(0, inf)",
    "targetless.base_lidar_max_inlier_distance": "(0, inf)",
    "targetless.base_lidar_max_iterations": "[1, inf)",
    "targetless.base_lidar_min_plane_points": "[3, inf)",
    "targetless.base_lidar_min_plane_points_percentage": "[0, 100]",
    "targetless.base_lidar_max_cos_distance": "[0, 2]",
    "compare.false_alarm_rate": "(0, 0.5]",
    "compare.max_rotation_deg": "(0, 180]",
    "compare.max_translation_mm": "(0, inf)",
    "compare.unit_ring_range_bias_m": "[0, 1]",
    "compare.unit_ring_elevation_deg": "[0, 5]",
    "compare.unit_lens_field_px": "[0, 10]",
}
# Pairs that must be ordered: the first strictly below the second.
_ORDERED = (
    ("lidar.min_range_m", "lidar.max_range_m"),
    ("targetless.mapping_min_range", "targetless.mapping_max_range"),
    ("targetless.min_calibration_range", "targetless.max_calibration_range"),
    ("targetless.pc_features_min_distance", "targetless.pc_features_max_distance"),
    *((f"targetless.base_lidar_crop_box_min_{a}", f"targetless.base_lidar_crop_box_max_{a}") for a in "xyz"),
)
_ORDERED_OR_EQUAL = (
    ("segmentation.min_segments_per_cluster", "segmentation.max_segments_per_cluster"),
    ("targetless.lidar_calibration_min_frames", "targetless.lidar_calibration_max_frames"),
    ("targetless.camera_calibration_min_frames", "targetless.camera_calibration_max_frames"),
)
# String settings with a fixed set of values, and fixed-length number lists.
_CHOICES = {"detection.detector": ("auto", "mrgingham", "opencv")}
_NUMBER_LISTS = {"sectors.rt_vehicle_lidar0": 6, "segmentation.debug_region": 4}
_REGEXES = ("snapshots.exclude_bag",)
_INT_MAX = 2**31 - 1
_MAX_YAML_BYTES = 1 << 20


def _range_error(key: str, message: str) -> ConfigError:
    e = ConfigError(message)
    e.key = key  # the CLI names the flag the value came from
    return e


def _parse_interval(text: str) -> tuple[float, float, bool, bool]:
    lo, hi = text[1:-1].split(",")
    return float(lo), float(hi), text[0] == "[", text[-1] == "]"


def _get(cfg, key: str):
    section, name = key.split(".")
    return getattr(getattr(cfg, section), name)


def _check_ranges(cfg) -> None:
    """ConfigError naming the key and its allowed range for the first value out of range."""
    for key, interval in _RANGES.items():
        v = _get(cfg, key)
        if v is None:
            continue
        lo, hi, lo_in, hi_in = _parse_interval(interval)
        if isinstance(v, int) and hi > _INT_MAX:
            hi, hi_in, interval = _INT_MAX, True, f"{interval[:-4]}{_INT_MAX}]"
        ok = (v >= lo if lo_in else v > lo) and (v <= hi if hi_in else v < hi)
        if not ok:
            raise _range_error(key, f"'{key}' must be in {interval}, got {v!r}")
    for strict, pairs in ((True, _ORDERED), (False, _ORDERED_OR_EQUAL)):
        for a, b in pairs:
            va, vb = _get(cfg, a), _get(cfg, b)
            if (va >= vb) if strict else (va > vb):
                rel = "below" if strict else "at most"
                raise _range_error(a, f"'{a}' ({va!r}) must be {rel} '{b}' ({vb!r})")
    for key, choices in _CHOICES.items():
        if _get(cfg, key) not in choices:
            raise _range_error(key, f"'{key}' must be one of {', '.join(choices)}, got {_get(cfg, key)!r}")
    for key, n in _NUMBER_LISTS.items():
        v = _get(cfg, key)
        if v is None:
            continue
        if len(v) != n or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v):
            raise _range_error(key, f"'{key}' must be a list of {n} finite numbers, got {v!r}")
    region = cfg.segmentation.debug_region
    if region is not None and not (region[0] < region[1] and region[2] < region[3]):
        raise _range_error("segmentation.debug_region",
                           f"'segmentation.debug_region' must be [xmin, xmax, ymin, ymax] with min < max, got {region!r}")
    for key in _REGEXES:
        v = _get(cfg, key)
        if v is not None:
            try:
                re.compile(v)
            except re.error as e:
                raise _range_error(key, f"'{key}' is not a valid regular expression ({e}): {v!r}") from None


class SafeLoaderNoCollectionAliases(yaml.SafeLoader):
    """safe_load that refuses aliases of mappings and lists: nested ones expand exponentially
    when the settings are copied (the "billion laughs" bomb); aliases of scalars are harmless."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            node = self.anchors.get(event.anchor)
            if node is not None and not isinstance(node, yaml.ScalarNode):
                raise yaml.YAMLError(f"alias *{event.anchor} of a mapping or list (not supported in config files)")
        return super().compose_node(parent, index)


def read_yaml(path, what: str, *, error=InputError, loader=SafeLoaderNoCollectionAliases, max_bytes: int | None = None,
              mapping: str | None = None, hint: str = ""):
    """The content of the YAML file ``path`` (a ``what``: "config file", "rig file", ...), every
    failure one ``error`` line naming the file: unreadable (``hint`` appended), larger than
    ``max_bytes``, not UTF-8, not YAML; and, when ``mapping`` says what it holds, not a mapping."""
    path = Path(path)
    try:
        if max_bytes is not None and path.stat().st_size > max_bytes:
            raise error(f"{path}: larger than {max_bytes // 1024} KiB; not a {what}?")
        d = yaml.load(path.read_text(), Loader=loader)
    except UnicodeDecodeError:
        raise error(f"{path}: not a text (UTF-8) {what}") from None
    except OSError as e:
        raise error(f"{path}: cannot read the {what} ({e.strerror}){hint}") from None
    except yaml.YAMLError as e:
        raise error(f"{path}: not valid YAML: {' '.join(str(e).split())}") from None
    if mapping is not None and not isinstance(d, dict):
        raise error(f"{path}: a {what} is a mapping {mapping}")
    return d


class SafeDumperNoAliases(yaml.SafeDumper):
    """safe_dump that writes a list or mapping used twice out twice, never as an alias: the
    files clcgraph writes load with SafeLoaderNoCollectionAliases."""

    def ignore_aliases(self, data):
        return True


class CSafeDumperNoAliases(getattr(yaml, "CSafeDumper", yaml.SafeDumper)):
    """SafeDumperNoAliases with libyaml's emitter when PyYAML has it: the same text, 5x faster
    (calibration.yaml of 24 poses: 0.14 -> 0.03 s CPU)."""

    def ignore_aliases(self, data):
        return True
