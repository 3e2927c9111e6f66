"""The factor graph of a Problem: keys, factors for the active observations, initial values.

Variables: ``sensor_key(i)`` = T_lidar0_sensor for every sensor but lidar0 (the reference
has no variable), ``board_key(k)`` = T_lidar0_board for every snapshot still in use.
Factors: one per (sensor, snapshot) observation (LIDAR plane or range over its active
points, on the board face it sees: lidar_face; camera corners over its active corners), with
``solve.lidar_edges`` one more per LIDAR
observation on where it saw the board's outline (factors/lidar_edge.py), the in-plane prior on
boards only LIDARs saw, and the nominal-pose priors of Problem.priors.

SYNOPSIS
    active = Active.all(problem)
    g, v = build(problem, active, rt_sensor, rt_board, lidar="range", sigma_lidar_m=0.02,
                 sigma_camera_px=0.3, options=solve_options)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..factors.board_prior import board_prior_factor
from ..factors.camera_corners import camera_corners_factor, camera_corners_residuals
from ..factors.lidar_edge import edge_sides, edge_sigmas, lidar_edge_factor
from ..factors.lidar_plane import lidar_plane_factor, lidar_plane_residuals
from ..factors.lidar_range import lidar_range_factor, lidar_range_residuals
from ..factors.pose_prior import pose_prior_factor
from ..geometry import pose3_from_rt
from ..types import Problem


def sensor_key(i: int) -> int:
    import gtsam

    return gtsam.symbol("s", i)


def board_key(k: int) -> int:
    import gtsam

    return gtsam.symbol("b", k)


def effect_key(kind: str, j: int) -> int:
    """Key of the board-pose error D of observation j (kind "lidar" or "camera"), backend/noise.py."""
    import gtsam

    return gtsam.symbol("d" if kind == "lidar" else "e", j)


def board_centre(problem: Problem):
    """Pose3 of the board's centre (margins included) in the board frame: where D tilts about."""
    import gtsam

    xmin, xmax, ymin, ymax = problem.board.extent()
    return gtsam.Pose3(gtsam.Rot3(), np.array([(xmin + xmax) / 2, (ymin + ymax) / 2, 0.0]))


@dataclass
class Active:
    """What the solve still uses: per observation index, a point/corner mask, or None if rejected."""

    lidar: list = field(default_factory=list)  # [(K,) bool | None] per problem.lidar_observations
    camera: list = field(default_factory=list)  # [(K,) bool | None] per problem.camera_observations

    @classmethod
    def all(cls, problem: Problem, dropped=frozenset()) -> "Active":
        lid = [None if (o.sensor, o.snapshot) in dropped else np.ones(len(o.points), bool)
               for o in problem.lidar_observations]
        cam = [None if (o.sensor, o.snapshot) in dropped else np.all(np.isfinite(o.corners_px), axis=1)
               for o in problem.camera_observations]
        return cls(lid, cam)

    def boards(self, problem: Problem) -> tuple[set, set]:
        """(snapshots with any active observation, those with an active camera observation)."""
        used = {o.snapshot for o, m in zip(problem.lidar_observations, self.lidar) if m is not None and m.any()}
        cam = {o.snapshot for o, m in zip(problem.camera_observations, self.camera) if m is not None and m.any()}
        return used | cam, cam


def from_behind(T_sensor, T_board) -> bool:
    """A sensor at ``T_sensor`` (None: lidar0) is behind the board at ``T_board`` (board frame z > 0;
    the pattern faces -z)."""
    import gtsam

    T_s = gtsam.Pose3() if T_sensor is None else T_sensor
    return bool(T_board.between(T_s).translation()[2] > 0)


def lidar_face(board, T_sensor, T_board) -> float:
    """The board face a LIDAR at ``T_sensor`` (None: lidar0) sees, as its z in the board frame: 0, the
    pattern's, from in front; the board's thickness, its back, from behind. Decided at the
    estimate a factor is built from (a board is never seen edge-on)."""
    return board.back_m if from_behind(T_sensor, T_board) else 0.0


def _key(problem: Problem, i: int):
    return None if i == problem.reference else sensor_key(i)


def sigma_of(sigma, sensor: int) -> float:
    """A sensor's noise sigma from a scalar (all sensors) or a per-sensor array."""
    return float(sigma[sensor]) if np.ndim(sigma) else float(sigma)


def build(problem: Problem, active: Active, rt_sensor: np.ndarray, rt_board: np.ndarray, *, lidar: str,
          sigma_lidar_m, sigma_camera_px, options, board_nominal: np.ndarray | None = None,
          effects: np.ndarray | None = None, effect_values=None, edge_factors: list | None = None,
          only: set | None = None):
    """(gtsam.NonlinearFactorGraph, gtsam.Values) for the active observations.

    ``lidar``: "plane" (point-to-plane) or "range" (maximum likelihood).
    ``sigma_lidar_m``, ``sigma_camera_px``: scalars, or per-sensor arrays (index = sensor).
    ``board_nominal``: (Nsnapshots,6) the in-plane prior's targets (default: ``rt_board``).
    ``effects``: (Nsensors,6) sigmas of each observation's own board-pose error D (board-centre
    tangent [omega, v]; backend/noise.py): every observation factor gets its D variable, with a
    zero-mean prior of these sigmas; None = independent noise only. ``effect_values``: gtsam.Values
    to start the D variables from (default: identity). ``edge_factors``: lidar_edge_factors made
    beforehand (they depend on the poses and edge rays only), for graphs built many times.
    ``only``: indices of the graph's factors wanted: ({index: factor}, None), the others not made
    (a few of a large graph, to be linearized again: noise.Linearization.relinearized).
    """
    import gtsam

    make = lidar_plane_factor if lidar == "plane" else lidar_range_factor
    g = gtsam.NonlinearFactorGraph()
    v = gtsam.Values()
    picked: dict = {}
    n_added = 0

    def add(factor_of):  # factor_of() makes the factor: not called for one ``only`` leaves out
        nonlocal n_added
        if only is None:
            g.add(factor_of())
        elif n_added in only:
            picked[n_added] = factor_of()
        n_added += 1

    centre = board_centre(problem)
    used, seen_by_camera = active.boards(problem)
    # each pose made once: the values, and which face each LIDAR observation sees
    T_s = [_pose(problem, rt_sensor, i) for i in range(len(problem.sensors))]
    T_b = {k: pose3_from_rt(rt_board[k]) for k in used}

    def effect(kind, j, sensor):
        if effects is None:
            return {}
        k = effect_key(kind, j)
        if only is None:
            start = effect_values.atPose3(k) if effect_values is not None and effect_values.exists(k) else gtsam.Pose3()
            v.insert(k, start)
        add(lambda: gtsam.PriorFactorPose3(k, gtsam.Pose3(), gtsam.noiseModel.Diagonal.Sigmas(
            np.asarray(effects[sensor], float))))
        return {"effect_key": k, "T_board_centre": centre}

    for j, (o, m) in enumerate(zip(problem.lidar_observations, active.lidar)):
        if m is not None and m.any():
            kw = effect("lidar", j, o.sensor)
            add(lambda: make(_key(problem, o.sensor), board_key(o.snapshot), o.points[m], sigma_of(sigma_lidar_m, o.sensor),
                             face_m=lidar_face(problem.board, T_s[o.sensor], T_b[o.snapshot]), **kw))
    for j, (o, m) in enumerate(zip(problem.camera_observations, active.camera)):
        if m is not None and m.any():
            kw = effect("camera", j, o.sensor)

            def corners(o=o, m=m, kw=kw):
                s = problem.sensors[o.sensor]
                q = np.where(m[:, None], o.corners_px, np.nan)
                return camera_corners_factor(sensor_key(o.sensor), board_key(o.snapshot), q, s.lensmodel,
                                             s.intrinsics, problem.board, sigma_of(sigma_camera_px, o.sensor), **kw)

            add(corners)
    if lidar == "range":  # from a rough seed (point-to-plane) the sides may be wrong
        made = lidar_edge_factors(problem, active, rt_sensor, rt_board, options) if edge_factors is None else edge_factors
        for f in made.values():
            add(lambda f=f: f)
    nominal = rt_board if board_nominal is None else board_nominal
    for k in sorted(used - seen_by_camera):
        add(lambda k=k: board_prior_factor(board_key(k), pose3_from_rt(nominal[k]), options.board_prior_sigma_rad,
                                           options.board_prior_sigma_m))
    for p in problem.priors:
        if p.sensor != problem.reference:
            add(lambda p=p: pose_prior_factor(sensor_key(p.sensor), pose3_from_rt(p.rt_lidar0_sensor), p.sigma_rt))
    if only is not None:
        return picked, None
    for i, T in enumerate(T_s):
        if T is not None:  # lidar0 has no variable
            v.insert(sensor_key(i), T)
    for k in sorted(used):
        v.insert(board_key(k), T_b[k])
    return g, v


def _pose(problem: Problem, rt_sensor: np.ndarray, i: int):
    return None if i == problem.reference else pose3_from_rt(rt_sensor[i])


def lidar_edge_factors(problem: Problem, active: Active, rt_sensor: np.ndarray, rt_board: np.ndarray, options, *,
                       reuse: tuple | None = None) -> dict:
    """{LIDAR observation index: its edge factor at the given poses (edge_factor)} of the active
    observations that have one; none unless ``options.lidar_edges``. ``reuse``: (another problem,
    its lidar_edge_factors at the same poses and masks): an observation with that problem's edge
    rays (the same array: a move of the points only) takes its factor from there."""
    out = {}
    if not getattr(options, "lidar_edges", False):
        return out
    for j, (o, m) in enumerate(zip(problem.lidar_observations, active.lidar)):
        if reuse is not None and o.edge_rays is reuse[0].lidar_observations[j].edge_rays:
            if j in reuse[1]:
                out[j] = reuse[1][j]
        elif m is not None and m.any() and o.edge_rays is not None and len(o.edge_rays):
            f = edge_factor(problem, o, _pose(problem, rt_sensor, o.sensor), pose3_from_rt(rt_board[o.snapshot]),
                            beam_rad=options.lidar_edge_beam_rad)
            if f is not None:
                out[j] = f
    return out


def edge_factor(problem: Problem, o, T_sensor, T_board, *, beam_rad: float):
    """The edge factor of LIDAR observation ``o`` (factors/lidar_edge.py), its intervals assigned
    to the board's sides at the pose estimate (T_sensor None: lidar0); None if none is usable."""
    face = lidar_face(problem.board, T_sensor, T_board)
    keep, axis, bounds, ends, rng = edge_sides(T_sensor, T_board, o.edge_rays, problem.board, face_m=face)
    if not keep.any():
        return None
    sig = edge_sigmas(ends[keep], rng[keep], axis[keep], bounds[keep], beam_rad=beam_rad)
    return lidar_edge_factor(_key(problem, o.sensor), board_key(o.snapshot), o.edge_rays[keep], axis[keep],
                             bounds[keep], sig, face_m=face)


def residuals(problem: Problem, rt_sensor: np.ndarray, rt_board: np.ndarray, *, lidar: str = "range"):
    """Unwhitened residuals of EVERY observation (active or not) at the given poses.

    Returns (lidar: list of (K,) m or None where the board pose is unknown,
             camera: list of (K,2) px or None).
    """
    poses = [None if i == problem.reference else pose3_from_rt(rt_sensor[i]) for i in range(len(problem.sensors))]
    lid = [residual_of(problem, "lidar", j, poses, rt_board, lidar=lidar) for j in range(len(problem.lidar_observations))]
    cam = [residual_of(problem, "camera", j, poses, rt_board) for j in range(len(problem.camera_observations))]
    return lid, cam


def residual_of(problem: Problem, kind: str, j: int, poses: list, rt_board: np.ndarray, *, lidar: str = "range"):
    """Unwhitened residuals of observation j of ``kind`` ("lidar": (K,) m, "camera": (K,2) px)
    at the sensor ``poses`` (gtsam.Pose3 per sensor, None for lidar0); None where its board
    pose is unknown."""
    o = (problem.lidar_observations if kind == "lidar" else problem.camera_observations)[j]
    b = rt_board[o.snapshot]
    if not np.all(np.isfinite(b)):
        return None
    if kind == "lidar":
        fn = lidar_plane_residuals if lidar == "plane" else lidar_range_residuals
        T_b = pose3_from_rt(b)
        return fn(poses[o.sensor], T_b, o.points, lidar_face(problem.board, poses[o.sensor], T_b))
    s = problem.sensors[o.sensor]
    return camera_corners_residuals(poses[o.sensor], pose3_from_rt(b), o.corners_px, s.lensmodel, s.intrinsics,
                                    problem.board)
