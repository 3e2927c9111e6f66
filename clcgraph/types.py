"""The data model: frozen dataclasses passed between the stages.

Conventions (see DESIGN.md): ``rt_a_b`` maps points in frame b to frame a, as mrcal's
6-vector (Rodrigues r, then t). Sensor indices refer to ``Problem.sensors``; snapshot
indices to ``Problem.snapshot_stamps_ns``. Arrays are float64 unless stated otherwise.
This module imports nothing of clcgraph.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import PurePath
from typing import Literal, Mapping

import numpy as np

SensorKind = Literal["lidar", "camera"]


def names_bag(name: str, bag) -> bool:
    """Whether ``name`` (what a person typed: --exclude, --exclude-bag, --snapshots) names ``bag`` (a path):
    its path as given or as an equal path, its file name, or its stem ("pose007" for pose007.bag)."""
    b = PurePath(str(bag))
    return name in (str(bag), b.name, b.stem) or PurePath(name) == b


@dataclass(frozen=True, eq=False)
class Sensor:
    """One sensor of the rig, named by its topic.

    Cameras carry their (fixed, pre-calibrated) mrcal intrinsics.
    """

    topic: str
    kind: SensorKind
    lensmodel: str | None = None  # mrcal lens model name, cameras only
    intrinsics: np.ndarray | None = None  # (Nintrinsics,)
    imagersize: tuple[int, int] | None = None  # (width, height)
    # (Nintrinsics, Nintrinsics) the intrinsics' covariance, when the model carries the
    # calibration that made it (cameras.intrinsics_covariance); None: taken as exact
    intrinsics_covariance: np.ndarray | None = None

    @property
    def is_lidar(self) -> bool:
        return self.kind == "lidar"

    @property
    def is_camera(self) -> bool:
        return self.kind == "camera"


@dataclass(frozen=True, eq=False)
class LidarScan:
    """One decoded PointCloud2 in the sensor frame.

    Rows are kept as decoded (organised clouds keep their (height, width) order);
    invalid returns (NaN, inf, (0,0,0)) are flagged in ``valid``, not dropped.
    """

    topic: str
    stamp_ns: int
    points: np.ndarray  # (N,3)
    valid: np.ndarray  # (N,) bool
    intensity: np.ndarray | None = None  # (N,) float32
    ring: np.ndarray | None = None  # (N,) int; None if the cloud has no ring field
    time_s: np.ndarray | None = None  # (N,) per-point time relative to stamp_ns
    shape: tuple[int, int] | None = None  # (height, width) of an organised cloud


@dataclass(frozen=True, eq=False)
class Image:
    """One decoded image: (H,W) mono8/mono16, or (H,W,3) uint8 in BGR order."""

    topic: str
    stamp_ns: int
    pixels: np.ndarray
    encoding: str  # the encoding it was decoded from


@dataclass(frozen=True, eq=False)
class Snapshot:
    """Synchronized observations of one stationary board pose."""

    index: int
    stamp_ns: int
    source: str  # bag path, plus the period for decimated continuous bags
    scans: Mapping[str, LidarScan] = field(default_factory=dict)
    images: Mapping[str, Image] = field(default_factory=dict)
    bag: str = ""  # the bag's path alone


# A board whose thickness was not measured is taken for this thick (boards are 3-20 mm): where
# a LIDAR sees its back, solve.board_thickness_sigma_m says how well that is known.
ASSUMED_THICKNESS_M = 0.01


@dataclass(frozen=True)
class BoardGeometry:
    """A chessboard as people measure it: ``corners_x`` by ``corners_y`` inner corners
    ``square_m`` apart, printed on a ``width_m`` x ``height_m`` board (pattern and white
    border) whose pattern centre sits ``pattern_offset_m`` (along the width, the height)
    from the board's centre, ``thickness_m`` thick (a LIDAR behind the board sees its back;
    None: not measured, taken for ``ASSUMED_THICKNESS_M``).

    Board frame: corner (row i, column j) at (j*square_m, i*square_m, 0), row-major like
    mrgingham and mrcal; x runs along the board's width, y along its height; the board is
    the plane z = 0 (the pattern's face; the back face is z = thickness_m). The pattern's outer
    squares reach one square beyond the outer corners.
    The default is a 10x10 board of 0.1 m squares with a 0.1 m border: 1.3 m square.

    SYNOPSIS
        b = BoardGeometry.from_spec(corners=[7, 5], square_m=0.095, size_m=[0.85, 0.61])
        b.extent()   # (xmin, xmax, ymin, ymax) of the physical board in the board frame
        b.spec()     # the same dict back, as the config's ``board:`` section writes it
    """

    corners_x: int = 10
    corners_y: int = 10
    square_m: float = 0.1
    width_m: float = 1.3
    height_m: float = 1.3
    pattern_offset_m: tuple[float, float] = (0.0, 0.0)
    thickness_m: float | None = None

    def __post_init__(self):
        pw, ph = self.pattern_size_m
        ox, oy = self.pattern_offset_m
        if min(self.corners_x, self.corners_y) < 2 or self.square_m <= 0:
            raise ValueError(f"a board needs >= 2x2 inner corners and a positive square size, got "
                             f"{self.corners_x}x{self.corners_y}, {self.square_m} m")
        if abs(ox) + pw / 2 > self.width_m / 2 + 1e-9 or abs(oy) + ph / 2 > self.height_m / 2 + 1e-9:
            raise ValueError(f"the {pw:.3f} x {ph:.3f} m pattern (offset {ox:g}, {oy:g} m) does not fit on the "
                             f"{self.width_m:g} x {self.height_m:g} m board")

    @classmethod
    def from_spec(cls, *, corners, square_m, size_m, pattern_offset_m=(0.0, 0.0), thickness_m=None) -> "BoardGeometry":
        """From the config's ``board:`` keys (corners [nx, ny], square_m, size_m [w, h], pattern_offset_m,
        thickness_m)."""
        return cls(int(corners[0]), int(corners[1]), float(square_m), float(size_m[0]), float(size_m[1]),
                   (float(pattern_offset_m[0]), float(pattern_offset_m[1])),
                   None if thickness_m is None else float(thickness_m))

    def spec(self) -> dict:
        """The config's ``board:`` keys (plain lists and floats, for YAML and JSON; the thickness where stated)."""
        out = {"corners": [self.corners_x, self.corners_y], "square_m": self.square_m,
               "size_m": [self.width_m, self.height_m], "pattern_offset_m": list(self.pattern_offset_m)}
        return out if self.thickness_m is None else {**out, "thickness_m": self.thickness_m}

    def corners(self) -> np.ndarray:
        """(corners_y*corners_x, 3) corner positions in the board frame."""
        i, j = np.mgrid[0 : self.corners_y, 0 : self.corners_x]
        xyz = np.zeros((self.corners_y, self.corners_x, 3))
        xyz[..., 0] = j * self.square_m
        xyz[..., 1] = i * self.square_m
        return xyz.reshape(-1, 3)

    @property
    def pattern_size_m(self) -> tuple[float, float]:
        """The printed squares' extent: (corners + 1) squares each way."""
        return ((self.corners_x + 1) * self.square_m, (self.corners_y + 1) * self.square_m)

    def centre(self) -> np.ndarray:
        """(3,) the physical board's centre in the board frame."""
        return np.array([(self.corners_x - 1) * self.square_m / 2 - self.pattern_offset_m[0],
                         (self.corners_y - 1) * self.square_m / 2 - self.pattern_offset_m[1], 0.0])

    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of the physical board in the board frame."""
        cx, cy, _ = self.centre()
        return (cx - self.width_m / 2, cx + self.width_m / 2, cy - self.height_m / 2, cy + self.height_m / 2)

    @property
    def back_m(self) -> float:
        """z of the board's back face in the board frame: its thickness, or, not measured, the assumed one."""
        return ASSUMED_THICKNESS_M if self.thickness_m is None else self.thickness_m

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the physical board."""
        return (self.width_m, self.height_m)

    @property
    def is_square_grid(self) -> bool:
        """NxN inner corners (what mrgingham can find)."""
        return self.corners_x == self.corners_y


@dataclass(frozen=True, eq=False)
class LidarBoardObservation:
    """The board's points as seen by one LIDAR in one snapshot (sensor frame)."""

    sensor: int
    snapshot: int
    points: np.ndarray  # (K,3)
    plane: np.ndarray  # (4,) unit normal n and offset d: n . x = d, n pointing at the sensor
    rms_m: float  # plane-fit RMS
    indices: np.ndarray | None = None  # (K,) indices into the LidarScan's rows
    ring: np.ndarray | None = None  # (K,) each point's ring (laser) number, None where unknown
    # (E,3,3) where the board's outline was seen (frontend/board_edges.py): per interval the unit
    # ray of a return on the board, the next ray past its edge (behind the plane or a miss), and
    # the outward normal of the board side between them
    edge_rays: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class CameraBoardObservation:
    """All chessboard corners detected by one camera in one snapshot, in board-corner order."""

    sensor: int
    snapshot: int
    corners_px: np.ndarray  # (corners_y*corners_x, 2)


@dataclass(frozen=True)
class Rejected:
    """Something that was not used, and why. Counted in reports, never raised mid-batch."""

    reason: str
    stage: str  # "snapshot", "segmentation", "detection", "seed", "outlier", ...
    sensor: int | None = None
    snapshot: int | None = None


@dataclass(frozen=True, eq=False)
class PosePrior:
    """A nominal pose of a sensor (CAD, tf_static) with 1-sigma in rt coordinates."""

    sensor: int
    rt_lidar0_sensor: np.ndarray  # (6,)
    sigma_rt: np.ndarray  # (6,) rad, rad, rad, m, m, m


@dataclass(frozen=True, eq=False)
class Problem:
    """Everything the solver needs; independent of bags. Dumped/replayed as a unit."""

    sensors: tuple[Sensor, ...]
    board: BoardGeometry | None  # None for a targetless calibration (no observations)
    lidar_observations: tuple[LidarBoardObservation, ...]
    camera_observations: tuple[CameraBoardObservation, ...]
    snapshot_stamps_ns: np.ndarray  # (Nsnapshots,) int64
    rejected: tuple[Rejected, ...] = ()
    priors: tuple[PosePrior, ...] = ()
    # sensor index -> (K,3) sample of far points in that LIDAR's frame (sector visibility)
    lidar_visibility_points: Mapping[int, np.ndarray] = field(default_factory=dict)
    # (Nsnapshots,) the bag each snapshot came from (path as given); () when unknown (old dumps)
    snapshot_bags: tuple[str, ...] = ()
    # LIDAR sensor index -> (R,2) ring number and the range offset (m) the frontend measured on the
    # boards and took out of that ring's ranges (frontend/lidar_board.ring_range_offsets); a LIDAR
    # whose rings showed none is absent. Their spread is the unit's ring bias (backend/consider.py).
    lidar_ring_offsets: Mapping[int, np.ndarray] = field(default_factory=dict)

    @property
    def reference(self) -> int:
        """Index of lidar0, the first LIDAR: the frame everything is expressed in."""
        for i, s in enumerate(self.sensors):
            if s.is_lidar:
                return i
        raise ValueError("a problem needs at least one LIDAR")

    def variable_sensors(self) -> list[int]:
        """Sensor indices the solve estimates (all but the reference), in the order of their
        6-blocks in covariances and tangent vectors."""
        ref = self.reference
        return [i for i in range(len(self.sensors)) if i != ref]

    @property
    def n_snapshots(self) -> int:
        return len(self.snapshot_stamps_ns)

    def sensor_name(self, i: int) -> str:
        return f"{self.sensors[i].kind} {self.sensors[i].topic}"

    def snapshot_bag(self, k: int) -> str | None:
        """The file (or ROS2 bag directory) name snapshot k came from, or None if unknown."""
        if not 0 <= k < len(self.snapshot_bags):
            return None
        return PurePath(self.snapshot_bags[k]).name

    def snapshot_label(self, k: int) -> str:
        """'snapshot 7 (0007.bag @1700000012.345 s)': the index with its bag and stamp, for people."""
        where = [self.snapshot_bag(k) or ""]
        if 0 <= k < self.n_snapshots:
            where.append(f"@{int(self.snapshot_stamps_ns[k]) * 1e-9:.3f} s")
        return f"snapshot {k} ({' '.join(w for w in where if w)})"


@dataclass(frozen=True, eq=False)
class SectorReport:
    """The seed's sector feedback around the vehicle (see backend/sectors.py)."""

    n_sectors: int
    observations_per_sector: np.ndarray  # (Nsectors,) int
    isvisible_per_sensor_per_sector: np.ndarray  # (Nsensors, Nsectors) bool
    stdev_worst_per_sector: np.ndarray  # (Nsectors,) m
    isensors_pair_stdev_worst: np.ndarray  # (Nsectors, 2) int
    isector_of_last_snapshot: int


@dataclass(frozen=True, eq=False)
class TargetlessRun:
    """What a targetless calibration measured besides the poses (``Result.targetless``).

    Per calibration LIDAR (keyed by topic): the /tf_static guess, the final graph's size and
    noise scales, how its solves stopped, per-frame scores; and the drawings' data, so that
    outputs/ only draws: ``pictures["map"]`` ("map_points" (M,3), "trajectory" (K,3) in the map
    frame, "keyframes" indices into it) and ``pictures["alignment"][topic]`` ("target" / "source_guess"
    / "source_final": one frame's dense map and its scan moved by the guess / the result, (M,3) in
    lidar0; "distances_guess" / "distances_final": every frame's points to the map, m).
    """

    T_lidar0_sensor_guess: Mapping[str, np.ndarray]  # topic -> (4,4)
    graph: Mapping[str, dict] = field(default_factory=dict)
    convergence: Mapping[str, dict] = field(default_factory=dict)
    per_frame: Mapping[str, list] = field(default_factory=dict)  # topic -> list of dicts (score, keyframe, ...)
    frame_plan: Mapping[str, object] = field(default_factory=dict)  # skipped keyframes, spacing, drive length
    candidates: Mapping[str, list] = field(default_factory=dict)  # topic -> registration ensemble candidates
    pictures: Mapping[str, object] = field(default_factory=dict, repr=False)
    map_result: object = field(default=None, repr=False)  # the mapping's poses and keyframes
    notes: tuple[str, ...] = ()  # what a person should know (non-convergence, guess kept)


@dataclass(frozen=True, eq=False)
class Result:
    """A calibration's answer with its uncertainty and diagnostics, whichever method made it.

    ``method`` "target" (chessboard, backend/solve.py) or "targetless" (a drive,
    targetless/pipeline.py). Both fill the poses, the covariance and ``problem.sensors``;
    a targetless problem has no observations (and no board), its details are in
    ``targetless``, and it may carry base_link poses from the ground plane.
    """

    problem: Problem
    rt_lidar0_sensor: np.ndarray  # (Nsensors,6); the reference row is zero
    covariance_rt: np.ndarray  # (6(N-1),6(N-1)) over non-reference sensors, in sensor order
    rt_lidar0_board: np.ndarray  # (Nsnapshots,6); NaN rows for unused snapshots
    noise: Mapping[str, float]  # re-estimated sigmas: lidar_m, camera_px
    rms: Mapping[str, float]  # normalized, lidar_m, camera_px
    rejected: tuple[Rejected, ...]  # frontend and solver rejections
    sectors: SectorReport | None = None
    stats: Mapping[str, object] = field(default_factory=dict)  # iterations, stage_time_s, peak_rss_mb, ...
    residuals: Mapping[str, object] = field(default_factory=dict)  # for plots
    method: str = "target"  # "target" | "targetless"
    frames: Mapping[str, str] = field(default_factory=dict)  # topic -> ROS frame_id, when known
    base_frame: str | None = None  # the frame of T_base_sensor (e.g. base_link)
    T_base_sensor: Mapping[str, np.ndarray] = field(default_factory=dict)  # topic -> (4,4), when known
    targetless: TargetlessRun | None = None

    def sensor_index(self, sensor: int | str) -> int:
        """Index of a sensor given by index or topic."""
        if isinstance(sensor, str):
            return next(i for i, s in enumerate(self.problem.sensors) if s.topic == sensor)
        return int(sensor)
    # leave-one-snapshot-out check of the covariance (backend/jackknife.py); {} if not computed
    jackknife: Mapping[str, object] = field(default_factory=dict)

    def variable_sensors(self) -> list[int]:
        """Sensor indices that have a block in covariance_rt, in block order."""
        return self.problem.variable_sensors()

    def covariance_block(self, sensor: int | str) -> np.ndarray:
        """(6,6) marginal covariance of rt_lidar0_sensor of a sensor (index or topic); zeros for the reference."""
        i = self.sensor_index(sensor)
        if i == self.problem.reference:
            return np.zeros((6, 6))
        k = self.variable_sensors().index(i)
        return self.covariance_rt[6 * k : 6 * k + 6, 6 * k : 6 * k + 6]

    def stdev_rt(self, sensor: int | str) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance_block(sensor)))
