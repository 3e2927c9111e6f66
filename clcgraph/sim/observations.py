"""Observation-level simulator: board observations with known truth, no scene, no bags.

Fast and exact, for the backend's tests and benchmarks (the full simulator, which ray
casts a cluttered scene and writes bags, is clcgraph.sim.capture). LIDAR points are the
intersections of each ring's rays with the board rectangle (margin included) plus
Gaussian range noise along the ray; camera corners are mrcal projections plus Gaussian
pixel noise, kept only when the whole board is in view.

``errors=CorrelatedErrors.realistic()`` adds what real sensors correlate within one
observation and the solver's factors do not assume: per-ring range bias and elevation
error, a bowed board, mixed pixels at the board's edges, a per-board corner-detector bias
and a smooth lens-model error field (see CorrelatedErrors).

SYNOPSIS
    rig = make_rig(n_lidars=2, n_cameras=3)
    problem, truth = simulate_problem(rig=rig, n_snapshots=40, seed=1)
    truth.rt_lidar0_sensor, truth.rt_lidar0_board, truth.corrupted
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import cameras
from ..geometry import R_from_r, R_from_rpy, compose_rt, invert_rt, rt_from_R_t, transform
from ..types import BoardGeometry, CameraBoardObservation, LidarBoardObservation, Problem, Sensor
from .scene import planned_tilt

T0_NS = 1_700_000_000_000_000_000

# Camera looking along lidar0's +x: camera axes right-down-forward are -y, -z, +x of lidar0.
_R_FORWARD_CAMERA = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class SimLidar:
    elevations_rad: np.ndarray
    npoints_per_rotation: int = 1800
    max_range_m: float = 40.0


@dataclass(frozen=True, eq=False)
class Rig:
    """Sensors (lidar0 first) with their true poses and, per LIDAR, its ring model."""

    sensors: tuple[Sensor, ...]
    rt_lidar0_sensor: np.ndarray  # (N,6)
    lidars: dict = field(default_factory=dict)  # sensor index -> SimLidar


@dataclass(frozen=True)
class CorrelatedErrors:
    """Errors correlated within an observation (0 = off; the default is independent noise only).

    Each is drawn once per simulated capture: per LIDAR ring, per camera, per board.
    """

    ring_range_bias_m: float = 0.0  # sd of each ring's range bias (real LIDARs: 1-3 cm)
    ring_elevation_deg: float = 0.0  # sd of each ring's elevation error (~0.1 deg)
    board_warp_m: float = 0.0  # bow: the board's centre this far off the plane of its edges (2-5 mm)
    mixed_pixel_m: float = 0.0  # the board-edge point of each ring is up to this much farther
    corner_bias_px: float = 0.0  # sd of one shift of all corners, per (camera, board) (0.1-0.3 px)
    lens_field_px: float = 0.0  # amplitude of a smooth pixel-error field per camera (0.2-0.5 px)
    # the frontend's per-ring range-offset correction (frontend/lidar_board.ring_range_offsets)
    # applied to the LIDAR observations, as `clcgraph solve` applies it to a real capture's
    frontend_ring_correction: bool = True

    @classmethod
    def realistic(cls) -> "CorrelatedErrors":
        """Middle-of-the-range values of real sensors and boards (issue 12)."""
        return cls(ring_range_bias_m=0.02, ring_elevation_deg=0.1, board_warp_m=0.003, mixed_pixel_m=0.03,
                   corner_bias_px=0.2, lens_field_px=0.3)


def board_warp(board: BoardGeometry, xy: np.ndarray, bow_m: float) -> np.ndarray:
    """(K,) board-frame z of a board bowed by ``bow_m`` at (K,2) board points: 0 on the edges."""
    xmin, xmax, ymin, ymax = board.extent()
    u = (2 * xy[:, 0] - xmin - xmax) / (xmax - xmin)
    v = (2 * xy[:, 1] - ymin - ymax) / (ymax - ymin)
    return bow_m * np.clip(1 - u**2, 0, None) * np.clip(1 - v**2, 0, None)


def _lens_field(rng, imagersize, amplitude_px: float):
    """A smooth (K,2) -> (K,2) pixel-error field: two low-frequency waves per axis."""
    w, h = imagersize
    f = rng.uniform(0.5, 1.5, (2, 2, 2)) * rng.choice([-1, 1], (2, 2, 2))  # axis, wave, (x, y) cycles
    phase = rng.uniform(0, 2 * np.pi, (2, 2))

    def field(q):
        a = np.stack([np.sum(np.sin(2 * np.pi * (f[ax, :, 0] * q[:, :1] / w + f[ax, :, 1] * q[:, 1:] / h)
                                    + phase[ax]), axis=1) for ax in range(2)], -1)
        return amplitude_px / np.sqrt(2) * a

    return field


@dataclass(frozen=True, eq=False)
class Truth:
    rt_lidar0_sensor: np.ndarray  # (N,6)
    rt_lidar0_board: np.ndarray  # (Nsnapshots,6)
    corrupted: tuple = ()  # (sensor, snapshot) of deliberately corrupted observations


def _rt(yaw_deg=0.0, pitch_deg=0.0, roll_deg=0.0, xyz=(0.0, 0.0, 0.0), base=np.eye(3)):
    R = R_from_rpy(np.radians([roll_deg, pitch_deg, yaw_deg])) @ base
    return rt_from_R_t(R, np.asarray(xyz, float))


_LENSES = [
    ("LENSMODEL_OPENCV8", [1000.0, 1000.0, 511.5, 383.5, -0.05, 0.01, 1e-4, -1e-4, 0.001, 0.0, 0.0, 0.0], (1024, 768)),
    ("LENSMODEL_PINHOLE", [700.0, 700.0, 399.5, 299.5], (800, 600)),
    ("LENSMODEL_OPENCV4", [800.0, 805.0, 639.5, 479.5, -0.1, 0.02, 1e-3, -1e-3], (1280, 960)),
]


def make_rig(n_lidars: int = 2, n_cameras: int = 3) -> Rig:
    """A realistic front-facing rig: lidar0 level at the origin, the others offset and tilted
    (a 32-ring one pitched down 12 deg first), cameras fanned across the front."""
    if n_lidars < 1:
        raise ValueError("a rig needs at least one LIDAR")
    vlp16 = SimLidar(np.radians(np.linspace(-15, 15, 16)))
    ring32 = SimLidar(np.radians(np.linspace(-25, 15, 32)))
    sensors, rts, lidars = [], [], {}
    lidar_poses = [_rt(), _rt(8, 12, -3, (0.15, 0.6, -0.2)), _rt(-10, -6, 4, (0.1, -0.7, 0.3)),
                   _rt(20, 3, 2, (-0.2, 1.0, 0.1))]
    for i in range(n_lidars):
        sensors.append(Sensor(topic=f"/lidar{i}", kind="lidar"))
        rts.append(lidar_poses[i % len(lidar_poses)] + (0 if i < len(lidar_poses) else 0.05 * i))
        lidars[i] = vlp16 if i % 2 == 0 else ring32
    yaws = np.linspace(-20, 20, n_cameras) if n_cameras > 1 else [0.0]
    for j in range(n_cameras):
        lens, intr, size = _LENSES[j % len(_LENSES)]
        sensors.append(Sensor(topic=f"/cam{j}", kind="camera", lensmodel=lens,
                              intrinsics=np.array(intr, float), imagersize=size))
        rts.append(_rt(yaws[j], 2.0 * (j % 2), 0.0, (0.3, 0.25 * (j - (n_cameras - 1) / 2), 0.15 + 0.05 * j),
                       base=_R_FORWARD_CAMERA))
    return Rig(tuple(sensors), np.array(rts), lidars)


def _board_pose(rng, board: BoardGeometry, range_m, tilt_max_deg, vertical_only, vertical_jitter_deg,
                azimuth_rad=(-0.45, 0.45), origin=(0.0, 0.0, 0.0), tilt_towards_rad=None):
    """rt_lidar0_board for a board facing ``origin`` (lidar0 coordinates) from ``range_m``
    away, at an azimuth in ``azimuth_rad`` (lidar0's +x is 0); ``tilt_towards_rad``: a planned
    tilt (sim.scene.planned_tilt) by half to all of ``tilt_max_deg``, else a random one."""
    rho = rng.uniform(*range_m)
    az = rng.uniform(*azimuth_rad)
    c = np.array([rho * np.cos(az), rho * np.sin(az), rng.uniform(-0.4, 0.6)])
    z = np.array([c[0], c[1], 0.0 if vertical_only else c[2]])
    c = c + np.asarray(origin, float)
    z /= np.linalg.norm(z)  # board normal pointing away from the rig (mrcal's board convention)
    y = np.array([0.0, 0.0, -1.0]) - z[2] * -z
    y -= (y @ z) * z
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    R = np.c_[x, y, z]
    if vertical_only:  # a person holding it upright: yaw freely, pitch only a little
        tilt = _rt(rng.uniform(-tilt_max_deg, tilt_max_deg), rng.normal(0, vertical_jitter_deg), 0.0)[:3]
        R = R_from_r(tilt) @ R
    else:
        axis = rng.normal(size=3)
        tilt = rng.uniform(0, 1)  # drawn either way: the later draws stay those of the seed
        if tilt_towards_rad is not None:  # about the board's horizontal (pitch) or vertical (yaw) axis
            axis = np.cos(tilt_towards_rad) * x + np.sin(tilt_towards_rad) * y
            tilt = 0.5 + 0.5 * tilt
        axis -= (axis @ z) * z
        axis /= np.linalg.norm(axis)
        R = R_from_r(axis * np.radians(tilt * tilt_max_deg)) @ R
        R = R @ R_from_r(np.array([0, 0, np.radians(rng.uniform(-20, 20))]))  # roll in the board plane
    xmin, xmax, ymin, ymax = board.extent()
    centre_b = np.array([(xmin + xmax) / 2, (ymin + ymax) / 2, 0.0])
    return rt_from_R_t(R, c - R @ centre_b)


def _rays(elevations_rad, npoints: int) -> np.ndarray:
    el = np.asarray(elevations_rad)[:, None]
    az = np.linspace(-np.pi, np.pi, npoints, endpoint=False)[None, :]
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az)], -1).reshape(-1, 3)


def _lidar_hits(model: SimLidar, rt_sensor_board: np.ndarray, board: BoardGeometry, rng, sigma_m: float,
                errors: CorrelatedErrors = CorrelatedErrors(), ring_bias_m=None, ring_elevation_error_rad=None):
    """(points (K,3) in the sensor frame, rings (K,), edge intervals (E,2,3): _edge_rays) where the
    rays meet the board rectangle.

    With ``errors``: the rays really leave at the elevations plus ``ring_elevation_error_rad``
    but are reported at the nominal ones, each ring's range is off by ``ring_bias_m``, the
    board is bowed, and each ring's first and last board point is a mixed pixel (farther).
    """
    R, t = R_from_r(rt_sensor_board[:3]), rt_sensor_board[3:]
    n = R[:, 2]
    d = _face_offset(n, t, board)
    n_rings, n_az = len(model.elevations_rad), model.npoints_per_rotation
    u_nominal = _rays(model.elevations_rad, n_az)
    u = u_nominal if ring_elevation_error_rad is None else \
        _rays(np.asarray(model.elevations_rad) + ring_elevation_error_rad, n_az)
    ring = np.repeat(np.arange(n_rings), n_az)
    cos = u @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = d / cos
    ok = np.isfinite(rho) & (rho > 0.5) & (rho < model.max_range_m) & (np.abs(cos) > 0.05)
    rho = np.where(ok, rho, 0.0)
    q = (u * rho[:, None] - t) @ R  # board frame
    xmin, xmax, ymin, ymax = board.extent()
    inside = ok & (q[:, 0] >= xmin) & (q[:, 0] <= xmax) & (q[:, 1] >= ymin) & (q[:, 1] <= ymax)
    measured = rho.copy()
    if errors.board_warp_m:  # the bowed surface is this much farther along the normal
        measured[inside] += board_warp(board, q[inside, :2], errors.board_warp_m) / cos[inside]
    if ring_bias_m is not None:
        measured += ring_bias_m[ring]
    if errors.mixed_pixel_m:  # a ring's board points next to a miss: part of the beam hit the background
        grid = inside.reshape(n_rings, n_az)
        edge = (grid & ~(np.roll(grid, 1, axis=1) & np.roll(grid, -1, axis=1))).ravel()
        measured[edge] += rng.uniform(0, errors.mixed_pixel_m, int(edge.sum()))
    if sigma_m > 0:
        measured[inside] += rng.normal(0, sigma_m, int(inside.sum()))
    return (u_nominal[inside] * measured[inside, None], ring[inside],
            _edge_rays(model, u_nominal, inside, R, t, board))


def _face_offset(n: np.ndarray, t: np.ndarray, board: BoardGeometry) -> float:
    """d of the board face a sensor sees, n . x = d in its frame (n, t: the board's normal and
    origin there): the pattern's, or from behind (d < 0) the back, board.back_m behind it."""
    d = float(n @ t)
    return d + board.back_m if d < 0 else d


def _edge_rays(model: SimLidar, u: np.ndarray, inside: np.ndarray, R: np.ndarray, t: np.ndarray,
               board: BoardGeometry) -> np.ndarray:
    """(E,3,3) the board's edge intervals (frontend/board_edges.py) at the nominal rays ``u``:
    each ring's ends on the board with the next ray along the ring, and the middle of the highest
    (lowest) ring on the board with the ray of the ring above (below) it, with the outward normal
    of the board side between them (R, t: the board in the sensor frame), away from the corners.
    No scene: every ray off the board passed behind it."""
    from ..frontend.board_edges import exit_sides

    n_rings, n_az = len(model.elevations_rad), model.npoints_per_rotation
    grid = inside.reshape(n_rings, n_az)
    U = u.reshape(n_rings, n_az, 3)
    out = []
    for shift in (-1, 1):  # the ray after (before) each board return, along its ring
        r, c = np.nonzero(grid & ~np.roll(grid, shift, axis=1))
        out.append(np.stack([U[r, c], U[r, (c - shift) % n_az]], axis=1))
    rows = np.flatnonzero(grid.any(axis=1))
    if len(rows):
        by_el = np.argsort(model.elevations_rad)
        rank = np.empty(n_rings, np.int64)
        rank[by_el] = np.arange(n_rings)
        for ring, beyond in ((rows[np.argmax(rank[rows])], 1), (rows[np.argmin(rank[rows])], -1)):
            nb = rank[ring] + beyond
            if 0 <= nb < n_rings:
                cols = np.flatnonzero(grid[ring])
                c = cols[len(cols) // 2]
                if not grid[by_el[nb], c]:
                    out.append(np.stack([U[ring, c], U[by_el[nb], c]])[None])
    rays = np.concatenate(out)
    n = R[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = _face_offset(n, t, board) / (rays @ n)  # (E,2) where the rays meet the face seen
    q = (rays * np.where(rho > 0, rho, 0.0)[..., None] - t) @ R  # (E,2,3) in the board frame
    xmin, xmax, ymin, ymax = board.extent()
    ok, axis, sign = exit_sides(q[:, 0, :2], q[:, 1, :2], np.array([xmin, ymin]), np.array([xmax, ymax]))
    ok &= np.all(rho > 0, axis=1)
    normal = sign[:, None] * R[:, axis].T
    return np.concatenate([rays, normal[:, None]], axis=1)[ok]


def plane_fit(points: np.ndarray) -> tuple[np.ndarray, float]:
    """(n, d) with n . x = d, n pointing at the sensor (origin), and the fit RMS."""
    c = points.mean(axis=0)
    _, s, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[2]
    if n @ c > 0:
        n = -n
    return np.r_[n, n @ c], float(s[2] / np.sqrt(len(points)))


def simulate_problem(rig: Rig | None = None, n_snapshots: int = 24, seed: int = 0, *,
                     sigma_lidar_m: float = 0.015, sigma_camera_px: float = 0.3,
                     board: BoardGeometry = BoardGeometry(), tilt_max_deg: float = 45.0,
                     range_m: tuple[float, float] = (2.0, 8.0), vertical_only: bool = False,
                     vertical_jitter_deg: float = 2.0, corrupt_fraction: float = 0.0,
                     lidar_only: bool = False, min_rings: int = 3, min_points: int = 20,
                     azimuth_rad: tuple[float, float] = (-0.45, 0.45), origin=(0.0, 0.0, 0.0),
                     errors: CorrelatedErrors = CorrelatedErrors(), planned_tilts: bool = False,
                     fixed_errors_seed: int | None = None, board_poses_seed: int | None = None):
    """A Problem with noisy board observations of ``rig`` and its Truth (see module doc).

    ``sigma_lidar_m``: one range sigma, or one per LIDAR (in sensor order); ``sigma_camera_px``: one
    corner sigma, or one per camera (in sensor order).
    ``vertical_only``: the board is held upright (yaw up to ``tilt_max_deg``, pitch jitter
    ``vertical_jitter_deg``, 0 = exactly vertical). ``corrupt_fraction``: that share of each
    sensor's observations is corrupted (LIDAR: points of another surface 0.3 m off and 25 deg
    turned; camera: every corner shifted by ~12 px), listed in ``truth.corrupted``.
    ``lidar_only`` drops the rig's cameras. A snapshot is kept if >= 2 sensors saw it.
    ``azimuth_rad``, ``origin``: the boards face ``origin`` from those azimuths (lidar0 axes).
    ``errors``: the correlated errors to add (CorrelatedErrors; default none).
    ``planned_tilts``: boards tilted as a careful person plans them (sim.scene.planned_tilt:
    pitched up and down, turned left and right in turn) instead of about random axes.
    ``fixed_errors_seed``: draw the errors fixed for the capture (per ring, per camera) from this
    seed instead of ``seed``: two captures with the same one are made by the same sensor units.
    ``board_poses_seed``: draw the board poses from this seed instead (noise and the per-board
    errors still from ``seed``): the same boards captured again.
    """
    rig = rig or make_rig()
    rng = np.random.default_rng(seed)
    sensors = list(rig.sensors)
    rts = np.array(rig.rt_lidar0_sensor, float)
    if lidar_only:
        keep = [i for i, s in enumerate(sensors) if s.is_lidar]
        sensors = [sensors[i] for i in keep]
        rts = rts[keep]
        lidars = {keep.index(i): m for i, m in rig.lidars.items()}
    else:
        lidars = dict(rig.lidars)
    # the correlated errors' fixed parts: per LIDAR ring, per camera (properties of the sensor units)
    frng = rng if fixed_errors_seed is None else np.random.default_rng(fixed_errors_seed)
    ring_bias = {i: frng.normal(0, errors.ring_range_bias_m, len(m.elevations_rad)) if errors.ring_range_bias_m else None
                 for i, m in lidars.items()}
    ring_elevation = {i: frng.normal(0, np.radians(errors.ring_elevation_deg), len(m.elevations_rad))
                      if errors.ring_elevation_deg else None for i, m in lidars.items()}
    lens_field = {i: _lens_field(frng, s.imagersize, errors.lens_field_px) for i, s in enumerate(sensors)
                  if s.is_camera and errors.lens_field_px}
    camera_number = {i: c for c, i in enumerate(i for i, s in enumerate(sensors) if s.is_camera)}
    corners_b = board.corners()
    if errors.board_warp_m:
        corners_b = np.c_[corners_b[:, :2], board_warp(board, corners_b[:, :2], errors.board_warp_m)]
    brng = rng if board_poses_seed is None else np.random.default_rng(board_poses_seed)
    lidar_obs, camera_obs, boards = [], [], []
    rings_of = {}  # (sensor, snapshot) -> (K,) ring of each point
    k = 0
    attempts = 0
    while k < n_snapshots:
        attempts += 1
        if attempts > 50 * n_snapshots:
            raise RuntimeError("the rig sees too few of the simulated board poses")
        rt_b = _board_pose(brng, board, range_m, tilt_max_deg, vertical_only, vertical_jitter_deg, azimuth_rad, origin,
                           planned_tilt(k) if planned_tilts else None)
        lo, co = [], []
        for i, s in enumerate(sensors):
            rt_s_b = compose_rt(invert_rt(rts[i]), rt_b)
            if s.is_lidar:
                sigma = sigma_lidar_m[i] if np.ndim(sigma_lidar_m) else sigma_lidar_m  # per LIDAR, or one
                p, ring, edges = _lidar_hits(lidars[i], rt_s_b, board, rng, sigma, errors, ring_bias[i],
                                             ring_elevation[i])
                if len(p) >= min_points and len(np.unique(ring)) >= min_rings:
                    plane, rms = plane_fit(p)
                    lo.append(LidarBoardObservation(sensor=i, snapshot=k, points=p, plane=plane, rms_m=rms, ring=ring,
                                                    edge_rays=edges))
                    rings_of[(i, k)] = ring
            else:
                pc = transform(rt_s_b, corners_b)
                q = cameras.project(pc, s.lensmodel, s.intrinsics)
                w, h = s.imagersize
                if np.all(pc[:, 2] > 0.3) and np.all((q >= 0) & (q <= [w - 1, h - 1])):
                    if i in lens_field:
                        q = q + lens_field[i](q)
                    if errors.corner_bias_px:
                        q = q + rng.normal(0, errors.corner_bias_px, 2)
                    sigma = sigma_camera_px[camera_number[i]] if np.ndim(sigma_camera_px) else sigma_camera_px
                    if sigma > 0:
                        q = q + rng.normal(0, sigma, q.shape)
                    co.append(CameraBoardObservation(sensor=i, snapshot=k, corners_px=q))
        if len(lo) + len(co) < 2:
            continue
        lidar_obs += lo
        camera_obs += co
        boards.append(rt_b)
        k += 1
    ring_offsets = {}
    if errors.frontend_ring_correction and (errors.ring_range_bias_m or errors.ring_elevation_deg):
        lidar_obs, ring_offsets = _ring_corrected(lidar_obs, rings_of, sensors)
    corrupted = []
    if corrupt_fraction > 0:
        lidar_obs, camera_obs, corrupted = _corrupt(lidar_obs, camera_obs, corrupt_fraction, rng)
    vis = {i: _visibility_points(m) for i, m in lidars.items()}
    problem = Problem(
        sensors=tuple(sensors), board=board, lidar_observations=tuple(lidar_obs),
        camera_observations=tuple(camera_obs),
        snapshot_stamps_ns=T0_NS + np.arange(n_snapshots, dtype=np.int64) * 1_000_000_000,
        lidar_visibility_points=vis, lidar_ring_offsets=ring_offsets,
    )
    return problem, Truth(rts, np.array(boards), tuple(corrupted))


def _ring_corrected(lidar_obs: list, rings_of: dict, sensors) -> tuple[list, dict]:
    """``lidar_obs`` with each LIDAR's per-ring range offsets measured on its boards and taken out
    by the frontend's own correction (what `clcgraph solve` does after segmenting a capture), and
    {sensor: (R,2) ring, offset taken out} (Problem.lidar_ring_offsets)."""
    import dataclasses

    from ..frontend.lidar_board import correct_ring_offsets, offsets_table
    from ..types import LidarScan

    out, offsets = list(lidar_obs), {}
    for i in sorted({o.sensor for o in lidar_obs}):
        mine = [j for j, o in enumerate(lidar_obs) if o.sensor == i]
        found = [dataclasses.replace(lidar_obs[j], indices=np.arange(len(lidar_obs[j].points))) for j in mine]
        scans = [LidarScan(topic=sensors[i].topic, stamp_ns=0, points=o.points, valid=np.ones(len(o.points), bool),
                           ring=rings_of[(i, o.snapshot)]) for o in found]
        measured: dict = {}
        for j, o in zip(mine, correct_ring_offsets(found, scans, measured=measured)):
            out[j] = dataclasses.replace(o, indices=None)
        if measured:
            offsets[i] = offsets_table(measured)
    return out, offsets


def _corrupt(lidar_obs, camera_obs, fraction, rng):
    """Corrupt ``fraction`` of every sensor's observations: at most one per snapshot, and only
    in snapshots that >= 3 sensors saw (with two, nothing can tell which one is wrong); a
    camera's only where another camera saw the board too (LIDARs see its plane, not where on
    the plane it is: a shifted grid alone is just the board moved within its plane)."""
    count: dict[int, int] = {}
    cams: dict[int, int] = {}
    for o in [*lidar_obs, *camera_obs]:
        count[o.snapshot] = count.get(o.snapshot, 0) + 1
    for o in camera_obs:
        cams[o.snapshot] = cams.get(o.snapshot, 0) + 1
    lidar_obs, camera_obs = list(lidar_obs), list(camera_obs)
    allobs = [("l", i, o) for i, o in enumerate(lidar_obs)] + [("c", i, o) for i, o in enumerate(camera_obs)]
    corrupted, taken = [], set()
    for sensor in sorted({o.sensor for _, _, o in allobs}):
        mine = [x for x in allobs if x[2].sensor == sensor]
        want = int(round(fraction * len(mine)))
        for idx in rng.permutation(len(mine)):
            if want == 0:
                break
            kind, i, o = mine[idx]
            if o.snapshot in taken or count[o.snapshot] < 3 or (kind == "c" and cams[o.snapshot] < 2):
                continue
            taken.add(o.snapshot)
            want -= 1
            if kind == "l":
                # another surface: the points turned 25 deg about a vertical axis through their
                # centroid and pushed 0.3 m back along the ray
                c = o.points.mean(axis=0)
                Rw = R_from_r(np.array([0.0, 0.0, np.radians(25.0)]))
                p = (o.points - c) @ Rw.T + c * (1 + 0.3 / np.linalg.norm(c))
                plane, rms = plane_fit(p)
                lidar_obs[i] = LidarBoardObservation(o.sensor, o.snapshot, p, plane, rms)
            else:
                shift = rng.normal(0, 1, 2)
                camera_obs[i] = CameraBoardObservation(o.sensor, o.snapshot, o.corners_px + 12.0 * shift / np.linalg.norm(shift))
            corrupted.append((o.sensor, o.snapshot))
    return lidar_obs, camera_obs, corrupted


def _visibility_points(model: SimLidar) -> np.ndarray:
    """A LIDAR's rays meeting a 15 m cylinder (walls all around): what it can see, for sectors."""
    el = np.asarray(model.elevations_rad)[:, None]
    az = np.linspace(-np.pi, np.pi, 360, endpoint=False)[None, :]
    return np.stack([15 * np.cos(az) * np.ones_like(el), 15 * np.sin(az) * np.ones_like(el),
                     15 * np.tan(el) * np.ones_like(az)], -1).reshape(-1, 3)


__all__ = ["CorrelatedErrors", "Rig", "SimLidar", "Truth", "board_warp", "make_rig", "plane_fit", "simulate_problem"]
