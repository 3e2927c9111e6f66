"""Errors fixed for a whole capture, in the covariance: "consider" terms (Schmidt-Kalman).

Some errors are the same in every snapshot: a board's bow is a property of the one physical
board; a LIDAR's common range offset is a property of the sensor. Each observation's own
error D (noise.py) is zero-mean per board, and the jackknife leaves one board out at a time,
so neither sees them: they bias every board the same way. They cannot be estimated from the
capture (one sample per capture), so they are *considered*: held at their nominal value
(zero), their stated sigma propagated through the solve's own linearization,

    Sigma_x += J_c sigma_c^2 J_c^T,    J_c = dx / dc = S^-1 dr/dc

with S, r the sensor-only normal equations (boards and D marginalized, noise.Linearization)
and dr/dc the change of r when the measurements move as the error c moves them (one
relinearization per term at the final solution, by a central difference of the measurements:
the measurements are linear in c to far below the noise).

Terms (0 / absent = not included):
- ``intrinsics <camera>``: where the camera model carries the calibration that made it
  (mrcal's optimization_inputs; cameras.intrinsics_covariance), its intrinsics' covariance,
  one relinearization pair per eigen-direction.
The sigmas stated by the user (solve options):
- ``board_flatness_m``: the board's bow, its centre this far off the plane of its edges (the
  lowest bending mode, 0 on the edges: ``(1-u^2)(1-v^2)`` over the board); LIDAR points move
  along their rays, corners off the plane and are reprojected.
- ``lidar_range_offset_m``: one range offset common to every point of a LIDAR (one term per
  LIDAR).

SYNOPSIS
    terms = consider_terms(problem, rebuild, values, options)   # {name: (ns, m) J_c sigma_c, tangent}
    cov_rt, record = add_terms(problem, rt_lidar0_sensor, cov_rt, terms)   # + J_rt J_c sigma_c^2 J_c^T J_rt^T
"""

from __future__ import annotations

import dataclasses

import numpy as np

from . import graph as G
from ..geometry import R_from_r, compose_rt, drt_dxi, invert_rt, rt_from_pose3, transform
from ..types import Problem


def bow_shape(board, xy: np.ndarray) -> np.ndarray:
    """(K,) the lowest bending mode of the board at board points (K,2): 1 at the centre, 0 on the edges."""
    xmin, xmax, ymin, ymax = board.extent()
    u = (2 * xy[:, 0] - xmin - xmax) / (xmax - xmin)
    v = (2 * xy[:, 1] - ymin - ymax) / (ymax - ymin)
    return np.clip(1 - u**2, 0, None) * np.clip(1 - v**2, 0, None)


def _poses(problem, values):
    rt_s = np.zeros((len(problem.sensors), 6))
    for i in range(len(problem.sensors)):
        if i != problem.reference:
            rt_s[i] = rt_from_pose3(values.atPose3(G.sensor_key(i)))
    return rt_s


def _board_rt(values, k):
    key = G.board_key(k)
    return rt_from_pose3(values.atPose3(key)) if values.exists(key) else None


def _bow_moves(problem: Problem, values, h: float):
    """The observations with the board bowed by ``h`` (m, +z of the board frame: away from the rig)."""
    from .. import cameras

    rt_s = _poses(problem, values)
    lidar = []
    for o in problem.lidar_observations:
        rt_b = _board_rt(values, o.snapshot)
        if rt_b is None:
            lidar.append(o)
            continue
        rt_board_sensor = compose_rt(invert_rt(rt_b), rt_s[o.sensor])
        q = transform(rt_board_sensor, o.points)  # board frame
        u = o.points / np.linalg.norm(o.points, axis=1, keepdims=True)
        cos = np.abs(u @ R_from_r(rt_board_sensor[:3])[2])  # the ray against the board's normal
        drho = h * bow_shape(problem.board, q[:, :2]) / np.maximum(cos, 0.05)
        lidar.append(dataclasses.replace(o, points=o.points + u * drho[:, None]))
    camera = []
    corners = problem.board.corners()
    bowed = np.c_[corners[:, :2], h * bow_shape(problem.board, corners[:, :2])]
    for o in problem.camera_observations:
        rt_b = _board_rt(values, o.snapshot)
        if rt_b is None:
            camera.append(o)
            continue
        s = problem.sensors[o.sensor]
        rt_c_b = compose_rt(invert_rt(rt_s[o.sensor]), rt_b)
        dq = cameras.project(transform(rt_c_b, bowed), s.lensmodel, s.intrinsics) - \
            cameras.project(transform(rt_c_b, corners), s.lensmodel, s.intrinsics)
        camera.append(dataclasses.replace(o, corners_px=o.corners_px + dq))
    return dataclasses.replace(problem, lidar_observations=tuple(lidar), camera_observations=tuple(camera))


def _range_moves(problem: Problem, sensor: int, h: float):
    """The observations with LIDAR ``sensor``'s every range ``h`` longer."""
    lidar = [dataclasses.replace(o, points=o.points * (1 + h / np.linalg.norm(o.points, axis=1, keepdims=True)))
             if o.sensor == sensor else o for o in problem.lidar_observations]
    return dataclasses.replace(problem, lidar_observations=tuple(lidar))


def _intrinsics_moved(problem: Problem, sensor: int, delta: np.ndarray):
    """The problem with camera ``sensor``'s intrinsics moved by ``delta``."""
    sensors = list(problem.sensors)
    sensors[sensor] = dataclasses.replace(sensors[sensor], intrinsics=np.asarray(sensors[sensor].intrinsics) + delta)
    return dataclasses.replace(problem, sensors=tuple(sensors))


def intrinsics_directions(covariance: np.ndarray) -> np.ndarray:
    """(m, N) the 1-sigma directions of an intrinsics covariance (its eigenvectors times the
    square roots of its eigenvalues), the negligible ones (< 1e-12 of the largest) left out."""
    lam, V = np.linalg.eigh(0.5 * (covariance + covariance.T))
    keep = lam > 1e-12 * max(lam.max(), 0.0)
    return (V[:, keep] * np.sqrt(lam[keep])).T


def consider_terms(problem: Problem, build, values, options, S: np.ndarray | None = None) -> dict:
    """{term name: (ns, m) columns sigma_c J_c in the sensors' tangent (noise.Linearization
    order)}: the term's covariance is their outer product.

    ``build(problem) -> g``: the final graph of ``problem`` (same active masks, sigmas, D), so
    only the measurements (or a camera's intrinsics) differ between the nominal and the
    perturbed linearizations. ``S``: the nominal sensor-only information, if already reduced.
    """
    from .noise import Linearization

    wanted = {}  # name -> [problem moved by +1 sigma along a direction, as a function of the sign]
    if options.board_flatness_m > 0:
        wanted["board flatness"] = [lambda sign: _bow_moves(problem, values, sign * options.board_flatness_m)]
    if options.lidar_range_offset_m > 0:
        for i, s in enumerate(problem.sensors):
            if s.is_lidar:
                wanted[f"range offset {s.topic}"] = [
                    lambda sign, i=i: _range_moves(problem, i, sign * options.lidar_range_offset_m)]
    for i, s in enumerate(problem.sensors):
        if s.is_camera and s.intrinsics_covariance is not None and np.any(s.intrinsics_covariance):
            wanted[f"intrinsics {s.topic}"] = [lambda sign, i=i, d=d: _intrinsics_moved(problem, i, sign * d)
                                              for d in intrinsics_directions(s.intrinsics_covariance)]
    if not wanted:
        return {}
    if S is None:
        S = Linearization(problem, build(problem), values).reduced()[0]

    def r_of(p):
        return Linearization(p, build(p), values).reduced()[1]

    # linear in c far beyond 1 sigma: a central difference at +-1 sigma
    return {name: np.stack([np.linalg.solve(S, (r_of(moved(1)) - r_of(moved(-1))) / 2) for moved in dirs], axis=1)
            for name, dirs in wanted.items()}


MODEL_TERM = "noise and per-observation errors"


def add_terms(problem: Problem, rt_lidar0_sensor: np.ndarray, covariance_rt: np.ndarray, terms: dict):
    """(covariance_rt with the terms added, the terms' record for Result.stats).

    The record: ``included`` (every term's name, the model's first), and per sensor topic its
    ``position`` / ``orientation`` variance shares (trace of each term's 3x3 block over the
    total's): how much of the final sigma each term is.
    """
    idx = [i for i in range(len(problem.sensors)) if i != problem.reference]
    J = np.zeros((6 * len(idx), 6 * len(idx)))
    for a, i in enumerate(idx):
        J[6 * a:6 * a + 6, 6 * a:6 * a + 6] = drt_dxi(rt_lidar0_sensor[i])
    parts = {MODEL_TERM: np.asarray(covariance_rt, float)}
    parts.update({name: (J @ j) @ (J @ j).T for name, j in terms.items()})
    total = sum(parts.values())
    shares = {}
    for a, i in enumerate(idx):
        shares[problem.sensors[i].topic] = {
            what: {name: float(np.trace(P[6 * a + o:6 * a + o + 3, 6 * a + o:6 * a + o + 3])
                               / max(np.trace(total[6 * a + o:6 * a + o + 3, 6 * a + o:6 * a + o + 3]), 1e-300))
                   for name, P in parts.items()}
            for what, o in (("orientation", 0), ("position", 3))}
    return 0.5 * (total + total.T), {"included": list(parts), "variance_share": shares,
                                     "sigma_rt": {name: (J @ j).T.tolist() for name, j in terms.items()}}
