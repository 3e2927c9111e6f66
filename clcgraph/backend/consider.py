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
- ``board_thickness_sigma_m``: how well the board's thickness is known (board_thickness_sigma),
  which places its back face: the points of the observations made from behind the board
  (graph.lidar_face) move along their rays as the back face moves (none seen from behind: no
  term). The edge factors' crossings with that face move too, little against their
  quantisation, and are not included.
- ``lidar_range_offset_m``: one range offset common to every point of a LIDAR (one term per
  LIDAR).
- ``lidar_ring_range_bias_m``, ``lidar_ring_elevation_deg``: each laser's (ring's) own range
  offset and elevation error, independent per ring with that sigma. The frontend measures the
  rings' range offsets on the boards and takes them out (frontend/lidar_board.py,
  ``ring_range_offsets``), all but what no set of planes can tell apart from the board poses:
  their point-weighted fit ``a + b e`` over the rings' elevations e. That part stays, and so
  does the same fit of the elevation errors (their relative part is either taken for range
  offsets or differs from board to board: the per-observation model's). So per LIDAR two
  terms of two directions each: the 1-sigma directions of ``Cov(a, b) = sigma^2 (A'WA)^-1
  A'W^2A (A'WA)^-1`` (A = [1, e] over the rings the boards met, W their point counts).

- ``camera_focal_scale_sigma``: a camera's focal length (fx and fy together) off by this
  fraction, for cameras without an intrinsics covariance (those have the term above).
- ``camera_lens_field_px``: a lens-model error field, the same at the same image position in
  every board (RMS of the pixel error vector; lens_field_kernel's smoothness): the leading
  eigenmodes of its covariance, per pixel axis (the residuals are linear in the corners: a
  one-sided difference per mode).

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
        lidar.append(_farther(o, rt_board_sensor, h * bow_shape(problem.board, q[:, :2])))
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


def _farther(o, rt_board_sensor: np.ndarray, dn):
    """LIDAR observation ``o`` with the board's surface ``dn`` (m, one or per point) farther from the
    sensor along the board's normal: each point along its ray, by dn / cos(the ray against the normal)."""
    u = o.points / np.linalg.norm(o.points, axis=1, keepdims=True)
    cos = np.abs(u @ R_from_r(rt_board_sensor[:3])[2])
    return dataclasses.replace(o, points=o.points + u * (dn / np.maximum(cos, 0.05))[:, None])


def _seen_from_behind(problem: Problem, values) -> list:
    """Per LIDAR observation: its sensor is behind its board at ``values`` (graph.lidar_face)."""
    out = []
    for o in problem.lidar_observations:
        kb = G.board_key(o.snapshot)
        T_s = None if o.sensor == problem.reference else values.atPose3(G.sensor_key(o.sensor))
        out.append(values.exists(kb) and G.from_behind(T_s, values.atPose3(kb)))
    return out


def _thickness_moves(problem: Problem, values, behind: list, h: float):
    """The observations with the board ``h`` (m) thicker: its back face that much nearer to the
    LIDARs behind it."""
    rt_s = _poses(problem, values)
    lidar = [_farther(o, compose_rt(invert_rt(_board_rt(values, o.snapshot)), rt_s[o.sensor]), -h) if b else o
             for o, b in zip(problem.lidar_observations, behind)]
    return dataclasses.replace(problem, lidar_observations=tuple(lidar))


def _range_moves(problem: Problem, sensor: int, h: float):
    """The observations with LIDAR ``sensor``'s every range ``h`` longer."""
    lidar = [dataclasses.replace(o, points=o.points * (1 + h / np.linalg.norm(o.points, axis=1, keepdims=True)))
             if o.sensor == sensor else o for o in problem.lidar_observations]
    return dataclasses.replace(problem, lidar_observations=tuple(lidar))


# Rings are told apart by their elevations: within one ring the points' elevations differ by far
# less (a beam's origin offset from the sensor's: < 0.02 deg over a board) than between rings
# (>= 0.125 deg on the densest 128-ring units); merged rings only make the terms larger.
RING_GAP_RAD = np.radians(0.06)


def _elevations(points: np.ndarray) -> np.ndarray:
    return np.arcsin(np.clip(points[:, 2] / np.linalg.norm(points, axis=1), -1.0, 1.0))


def lidar_rings(problem: Problem, sensor: int) -> tuple[np.ndarray, np.ndarray]:
    """(R,) elevations (rad) of the rings of LIDAR ``sensor`` that met its boards, and (R,) their
    point counts: by each point's ring (LidarBoardObservation.ring, the frontend's); for
    observations without rings (dumps from before they were kept), by gaps in the elevations."""
    obs = [o for o in problem.lidar_observations if o.sensor == sensor]
    e = np.concatenate([_elevations(o.points) for o in obs])
    if all(o.ring is not None for o in obs):
        _, ring = np.unique(np.concatenate([np.asarray(o.ring) for o in obs]), return_inverse=True)
    else:
        order = np.argsort(e)
        e = e[order]
        ring = np.r_[0, np.cumsum(np.diff(e) > RING_GAP_RAD)]
    counts = np.bincount(ring).astype(float)
    return np.bincount(ring, e) / counts, counts


def ring_trend_directions(elevations: np.ndarray, counts: np.ndarray, sigma: float) -> tuple[np.ndarray, float]:
    """((m, 2) the 1-sigma directions (a, b) of what is left of per-ring errors of ``sigma`` each
    once their relative part is taken out: their point-weighted least-squares fit a + b e
    (b per rad of elevation) over the rings (``elevations``, ``counts``); ``e`` from the
    rings' weighted mean e0, so a and b are nearly independent; m = 1 with a single ring), e0."""
    e = elevations - np.average(elevations, weights=counts)
    A = np.c_[np.ones_like(e), e] if len(e) > 1 and np.ptp(e) > 0 else np.ones((len(e), 1))
    Ninv = np.linalg.inv(A.T @ (counts[:, None] * A))
    C = sigma**2 * Ninv @ (A.T @ (counts[:, None] ** 2 * A)) @ Ninv
    out = intrinsics_directions(C)
    return np.c_[out, np.zeros((len(out), 2 - out.shape[1]))], np.average(elevations, weights=counts)


def _ring_range_moves(problem: Problem, sensor: int, e0: float, ab: np.ndarray):
    """The observations with LIDAR ``sensor``'s ranges ``a + b (e - e0)`` longer at elevation e."""
    def moved(o):
        r = np.linalg.norm(o.points, axis=1, keepdims=True)
        return dataclasses.replace(o, points=o.points * (1 + (ab[0] + ab[1] * (_elevations(o.points) - e0))[:, None] / r))
    lidar = [moved(o) if o.sensor == sensor else o for o in problem.lidar_observations]
    return dataclasses.replace(problem, lidar_observations=tuple(lidar))


def _raised(u: np.ndarray, e0: float, ab: np.ndarray, sign: float = 1.0) -> np.ndarray:
    """(M,3) unit rays ``u`` (M,3) turned ``sign (a + b (e - e0))`` (rad) up in elevation, azimuth kept."""
    e = np.arcsin(np.clip(u[:, 2], -1.0, 1.0))
    up = np.c_[-np.sin(e)[:, None] * u[:, :2] / np.maximum(np.cos(e), 1e-9)[:, None], np.cos(e)]  # du/de
    de = sign * (ab[0] + ab[1] * (e - e0))
    return np.cos(de)[:, None] * u + np.sin(de)[:, None] * up


def _ring_elevation_moves(problem: Problem, values, sensor: int, e0: float, ab: np.ndarray):
    """The observations with LIDAR ``sensor``'s rays really leaving ``a + b (e - e0)`` (rad) higher
    than reported: each range is where the raised ray meets its board's plane (at the solution),
    the point still reported along the nominal ray; the board's outline is crossed by the same
    real rays, so its intervals are reported that much lower."""
    rt_s = _poses(problem, values)
    lidar = []
    for o in problem.lidar_observations:
        rt_b = _board_rt(values, o.snapshot)
        if o.sensor != sensor or rt_b is None:
            lidar.append(o)
            continue
        rt_sensor_board = compose_rt(invert_rt(rt_s[sensor]), rt_b)
        n = R_from_r(rt_sensor_board[:3])[:, 2]
        r = np.linalg.norm(o.points, axis=1)
        u = o.points / r[:, None]
        cos, cos_raised = u @ n, _raised(u, e0, ab) @ n
        ratio = np.where(np.abs(cos_raised) > 0.05, cos / np.where(np.abs(cos_raised) > 0.05, cos_raised, 1.0), 1.0)
        edges = o.edge_rays
        if edges is not None and len(edges):  # (E,3,3): two rays and the side's normal, kept
            edges = np.array(edges, float)
            edges[:, :2] = _raised(edges[:, :2].reshape(-1, 3), e0, ab, -1.0).reshape(-1, 2, 3)
        lidar.append(dataclasses.replace(o, points=o.points * ratio[:, None], edge_rays=edges))
    return dataclasses.replace(problem, lidar_observations=tuple(lidar))


def lens_field_kernel(d: np.ndarray) -> np.ndarray:
    """Correlation along one image axis of a lens-model error field, at ``d`` (fractions of the
    image): a field of spatial frequencies between 0.5 and 1.5 cycles across the image (what a
    lens model's fit leaves: no constant shift or scale, which the intrinsics absorb; nothing as
    fine as the corners' spacing), i.e. ``E cos(2 pi f d)`` for f uniform in [0.5, 1.5]."""
    d = np.asarray(d, float)
    x = np.where(np.abs(d) < 1e-9, 1.0, d)
    return np.where(np.abs(d) < 1e-9, 1.0, (np.sin(3 * np.pi * x) - np.sin(np.pi * x)) / (2 * np.pi * x))


LENS_GRID = (16, 12)  # nodes over the image; >= 3 per cycle at the field's highest frequency
LENS_MODES_VARIANCE = 0.95  # share of the field's variance the modes kept carry


def _lens_kernel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(A, B) lens_field_kernel in x times in y between points (fractions of the image)."""
    return lens_field_kernel(a[:, None, 0] - b[None, :, 0]) * lens_field_kernel(a[:, None, 1] - b[None, :, 1])


@dataclasses.dataclass(frozen=True)
class LensFieldModes:
    """The leading eigenmodes of a smooth lens-model error field (lens_field_modes): called on
    image points (K,2) px, the (K, n) 1-sigma field of one pixel axis of each mode there, the
    grid's modes extended to any point by the field's own regression (Nystrom: the grid's kernel
    inverted over each mode). One kernel evaluation for every mode."""

    imagersize: tuple
    grid: np.ndarray  # (G,2) nodes, fractions of the image
    vectors: np.ndarray  # (G, n) the grid kernel's leading eigenvectors
    values: np.ndarray  # (n,) their eigenvalues
    sigma: float  # the field's 1-sigma per pixel axis

    def __len__(self) -> int:
        return len(self.values)

    def __call__(self, q: np.ndarray) -> np.ndarray:
        w, h = self.imagersize
        return self.sigma * (_lens_kernel(np.c_[q[:, 0] / w, q[:, 1] / h], self.grid) @ self.vectors) / np.sqrt(self.values)


def lens_field_modes(imagersize, rms_px: float) -> LensFieldModes:
    """The modes of a smooth lens-model error field of ``rms_px`` (RMS of the error vector, both
    axes; lens_field_kernel in x and y) that carry LENS_MODES_VARIANCE of its variance on a grid."""
    gx, gy = np.meshgrid(np.linspace(0, 1, LENS_GRID[0]), np.linspace(0, 1, LENS_GRID[1]))
    grid = np.c_[gx.ravel(), gy.ravel()]
    lam, V = np.linalg.eigh(_lens_kernel(grid, grid))
    lam, V = lam[::-1], V[:, ::-1]
    m = int(np.searchsorted(np.cumsum(lam) / lam.sum(), LENS_MODES_VARIANCE)) + 1
    return LensFieldModes(tuple(imagersize), grid, np.ascontiguousarray(V[:, :m]), lam[:m], float(np.sqrt(rms_px**2 / 2)))


def _lens_moves(problem: Problem, sensor: int, modes: LensFieldModes, mode: int, axis: int, h: float):
    """The observations with camera ``sensor``'s corners moved by ``h`` times lens-field mode
    ``mode`` along ``axis``."""
    def moved(o):
        dq = np.zeros_like(o.corners_px)
        dq[:, axis] = h * modes(o.corners_px)[:, mode]
        return dataclasses.replace(o, corners_px=o.corners_px + dq)
    camera = [moved(o) if o.sensor == sensor else o for o in problem.camera_observations]
    return dataclasses.replace(problem, camera_observations=tuple(camera))


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


def _nominal(problem: Problem, build, values, nominal):
    """(g, lin): the nominal graph ``build(problem)`` and its noise.Linearization at ``values``
    (``nominal``: the two if already made)."""
    from .noise import Linearization

    if nominal is not None:
        return nominal
    g = build(problem)
    return g, Linearization(problem, g, values)


def consider_terms(problem: Problem, build, values, options, nominal=None) -> dict:
    """{term name: (ns, m) columns sigma_c J_c in the sensors' tangent (noise.Linearization
    order)}: the term's covariance is their outer product.

    ``build(problem, only=None) -> g``: the final graph of ``problem`` (same active masks, sigmas,
    D), so only the measurements (or a camera's intrinsics) differ between the nominal and the
    perturbed linearizations; with ``only`` (factor indices) {index: factor} of those alone
    (graph.build's). ``nominal``: (that graph, its noise.Linearization at ``values``) if
    already made. Per direction only the factors whose measurements it moves are linearized again.
    """
    wanted, lens = _wanted(problem, values, options)
    if not wanted and not lens:
        return {}
    g, lin = _nominal(problem, build, values, nominal)
    S = lin.reduced()[0]
    out = {f"lens field {problem.sensors[i].topic}": np.linalg.solve(S, dr)
           for i, dr in _lens_field_dr(problem, lin, g, lens).items()}
    if not wanted:
        return out

    def r_of(p):
        return lin.relinearized(moved_graph(problem, p, lin, build)).reduced()[1]

    # linear in c far beyond 1 sigma: a central difference at +-1 sigma
    return {**{name: np.stack([np.linalg.solve(S, (r_of(moved(1)) - r_of(moved(-1))) / 2) for moved in dirs], axis=1)
               for name, dirs in wanted.items()}, **out}


def known_columns(problem: Problem, lin, g, build, options):
    """The consider terms' errors as columns of the linearized measurements, for the models that
    must know them (noise.Linearization.with_known, consistency.linearize): ({factor index of
    ``g``: (rows, m) the change of its whitened b when the measurements move by +1 sigma along
    each of the m directions}, m), or None when no term is stated. ``lin``: noise.Linearization
    of ``g`` (its b, and whose factor is which); ``build``: as consider_terms'. Per direction,
    only the factors whose measurements it moves are linearized again (the measurements are
    linear in c far below the noise); the lens field's in closed form."""
    wanted, lens = _wanted(problem, lin.values, options)
    if not wanted and not lens:
        return None
    cols: dict = {}  # factor index -> [(column, (rows,))]
    m = 0
    for dirs in wanted.values():
        for moved in dirs:
            for f, factor in moved_graph(problem, moved(1), lin, build).items():
                db = factor.linearize(lin.values).jacobian()[1] - lin.rows[lin.factors[f][3].start][2]
                if np.any(db):
                    cols.setdefault(f, []).append((m, db))
            m += 1
    first = {}  # camera -> its first lens-field column
    for i, modes in lens.items():
        first[i], m = m, m + 2 * len(modes)
    for f, i, db in _lens_field_db(problem, lin, g, lens):
        cols.setdefault(f, []).extend((first[i] + j, db[:, j]) for j in range(db.shape[1]))
    dense = {}
    for f, cs in cols.items():
        G_f = np.zeros((len(cs[0][1]), m))
        for j, c in cs:
            G_f[:, j] = c
        dense[f] = G_f
    return dense, m


def moved_graph(problem: Problem, moved: Problem, lin, build) -> dict:
    """{factor index: factor} of ``build(moved, only=...)`` for the factors ``moved`` changes
    (moved_factors): the others are not made."""
    return build(moved, only=set(moved_factors(problem, moved, lin)))


def moved_factors(problem: Problem, moved: Problem, lin) -> list:
    """The measurement factors of ``lin`` (a noise.Linearization of ``problem``'s graph) that
    ``moved`` changes: of its observations that are not ``problem``'s (by identity), and every
    one of a sensor it replaced (intrinsics). The others linearize the same in both."""
    sensors = {i for i, (a, b) in enumerate(zip(problem.sensors, moved.sensors)) if a is not b}
    obs = {(o.sensor, o.snapshot) for a, b in ((problem.lidar_observations, moved.lidar_observations),
                                                (problem.camera_observations, moved.camera_observations))
           for o, o_m in zip(a, b) if o is not o_m}
    return [f for f, (i, k, _, _) in enumerate(lin.factors) if i is not None and (i in sensors or (i, k) in obs)]


def _wanted(problem: Problem, values, options):
    """({term name: [sign -> the problem moved by sign x 1 sigma along each direction]},
    {camera: its lens field's modes}) of the terms ``options`` state."""
    wanted = {}  # name -> [problem moved by +1 sigma along a direction, as a function of the sign]
    if options.board_flatness_m > 0:
        wanted["board flatness"] = [lambda sign: _bow_moves(problem, values, sign * options.board_flatness_m)]
    thickness = board_thickness_sigma(problem.board, options)
    behind = _seen_from_behind(problem, values) if thickness > 0 else []
    if any(behind):
        wanted["board thickness"] = [lambda sign: _thickness_moves(problem, values, behind, sign * thickness)]
    if options.lidar_range_offset_m > 0:
        for i, s in enumerate(problem.sensors):
            if s.is_lidar:
                wanted[f"range offset {s.topic}"] = [
                    lambda sign, i=i: _range_moves(problem, i, sign * options.lidar_range_offset_m)]
    ring_terms = (("ring range bias", lambda i: ring_range_bias_sigma(problem, i, options), _ring_range_moves),
                  ("ring elevation", lambda i: np.radians(options.lidar_ring_elevation_deg),
                   lambda p, i, e0, ab: _ring_elevation_moves(p, values, i, e0, ab)))
    for i, s in enumerate(problem.sensors):
        if not s.is_lidar or not any(o.sensor == i for o in problem.lidar_observations):
            continue
        rings = lidar_rings(problem, i)
        for name, sigma_of, move in ring_terms:
            sigma = sigma_of(i)
            if sigma > 0:
                dirs, e0 = ring_trend_directions(*rings, sigma)
                wanted[f"{name} {s.topic}"] = [lambda sign, i=i, e0=e0, d=d, move=move: move(problem, i, e0, sign * d)
                                               for d in dirs]
    lens = {}  # camera -> its lens field's modes: residuals linear in the corners, done in closed form
    if options.camera_lens_field_px > 0:
        for i, s in enumerate(problem.sensors):
            if s.is_camera and any(o.sensor == i for o in problem.camera_observations):
                lens[i] = lens_field_modes(s.imagersize, options.camera_lens_field_px)
    for i, s in enumerate(problem.sensors):
        if not s.is_camera or not any(o.sensor == i for o in problem.camera_observations):
            continue
        if s.intrinsics_covariance is not None and np.any(s.intrinsics_covariance):
            wanted[f"intrinsics {s.topic}"] = [lambda sign, i=i, d=d: _intrinsics_moved(problem, i, sign * d)
                                              for d in intrinsics_directions(s.intrinsics_covariance)]
        elif options.camera_focal_scale_sigma > 0:  # fx, fy together (mrcal's first two intrinsics)
            d = np.zeros(len(s.intrinsics))
            d[:2] = options.camera_focal_scale_sigma * np.asarray(s.intrinsics[:2], float)
            wanted[f"focal length {s.topic}"] = [lambda sign, i=i, d=d: _intrinsics_moved(problem, i, sign * d)]
    return wanted, lens


def board_thickness_sigma(board, options) -> float:
    """The 1-sigma of the board's thickness (m): the one stated, else 1 mm for a measured board
    (``board.thickness_m`` given) and 5 mm for one taken for the assumed thickness."""
    if options.board_thickness_sigma_m is not None:
        return float(options.board_thickness_sigma_m)
    return 0.005 if board.thickness_m is None else 0.001


def ring_range_bias_sigma(problem: Problem, sensor: int, options) -> float:
    """The 1-sigma of LIDAR ``sensor``'s rings' own range offsets in its covariance (m): the
    one stated (``lidar_ring_range_bias_m``), or, where larger, the spread of the offsets the
    frontend measured on its boards and took out (Problem.lidar_ring_offsets). Those are the
    offsets' part no set of planes confuses with the board poses (their fit a + b e over the
    rings' elevations e removed): the unit's rings are that far apart, so its a + b e, which
    stays in every board, is drawn from the same spread. A unit whose rings showed no offsets
    (an exact one, a simulation without them) adds nothing."""
    stated = float(options.lidar_ring_range_bias_m)
    x = problem.lidar_ring_offsets.get(sensor)
    if x is None or len(x) < 4:
        return stated
    offsets = np.asarray(x, float)[:, 1]
    return max(stated, float(np.sqrt(np.sum(offsets**2) / (len(offsets) - 2))))


def _lens_field_dr(problem: Problem, lin, g, lens: dict) -> dict:
    """{camera: (ns, m) the change of the sensor-only vector r when its corners move along each
    of its lens-field modes (both pixel axes)}, in closed form: a camera factor's residual is
    linear in its corners (whitened ``(q - project) / sigma``), so only b moves, by the moved
    corners over sigma, and r by ``sum_k dv_s - B_k L_k^-1 dv_local`` over the snapshots (the
    Schur complement ``reduced`` uses). Same numbers as a relinearization per mode, far cheaper.
    ``lin``: noise.Linearization of the graph ``g`` at the final values (its factors' A and columns)."""
    if not lens:
        return {}
    ns = lin.ns
    _, batches, _ = lin._batches()
    gain = {}  # snapshot -> (K = B L^-1 (ns, nl), n)
    for ks, n, Mg, vg, *_ in batches:
        wv = np.ones(Mg.shape[1])
        S_k, r_k, iL, B, _ = lin._eliminate((Mg @ wv).reshape(len(ks), n, n), (vg @ wv).reshape(len(ks), n))
        for b, k in enumerate(ks):
            gain[k] = B[b] @ iL[b]
    out = {i: np.zeros((ns, 2 * len(modes))) for i, modes in lens.items()}
    for f, i, db in _lens_field_db(problem, lin, g, lens):
        _, k, cols, terms = lin.factors[f]
        A = lin.rows[terms.start][1]  # a corner factor is one term of every row
        dv = np.zeros((ns + 6 * len(lin.local[k]), db.shape[1]))
        np.add.at(dv, cols, A.T @ db)
        out[i] += dv[:ns] - gain[k] @ dv[ns:]
    return out


def _lens_field_db(problem: Problem, lin, g, lens: dict):
    """[(factor index, camera, (rows, 2 x modes) the change of its whitened b per unit of each of
    the camera's lens-field modes, both pixel axes)] over ``g``'s corner factors of the cameras
    in ``lens`` (``lin``: noise.Linearization of ``g``, which says whose factor is which): a camera
    residual is linear in its corners (whitened ``(q - project) / sigma``)."""
    obs = {(o.sensor, o.snapshot): o for o in problem.camera_observations}
    out = []
    for f, (i, k, _, _) in enumerate(lin.factors if lens else ()):
        if i not in lens or k is None:
            continue
        q = obs[(i, k)].corners_px
        F = lens[i](q)  # (K, modes)
        dq = np.zeros((len(q), 2, 2 * F.shape[1]))
        dq[:, 0, 0::2], dq[:, 1, 1::2] = F, F  # column 2 j + a: mode j along pixel axis a
        out.append((f, i, -_whiten(g.at(f), np.nan_to_num(dq.reshape(2 * len(q), -1)))))  # undetected corners: zero rows of A
    return out


def _whiten(factor, e: np.ndarray) -> np.ndarray:
    """(rows, m) columns of an unwhitened error change, whitened by the factor's noise model."""
    model = factor.noiseModel()
    return np.stack([model.whiten(np.ascontiguousarray(c)) for c in e.T], axis=1)


MODEL_TERM = "noise and per-observation errors"


def add_terms(problem: Problem, rt_lidar0_sensor: np.ndarray, covariance_rt: np.ndarray, terms: dict):
    """(covariance_rt with the terms added, the terms' record for Result.stats).

    The record: ``included`` (every term's name, the model's first), and per sensor topic its
    ``position`` / ``orientation`` variance shares (trace of each term's 3x3 block over the
    total's): how much of the final sigma each term is.
    """
    idx = problem.variable_sensors()
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


# ---------------------------------------------------------------- sensitivities to the units' errors
# For `compare` (comparison.py): two calibrations of the same sensor units share the units' fixed
# errors e, so their difference carries (J_A - J_B) e, J = dx/de of each capture (its board poses
# differ). Computed for every solve, whether or not a term is in the covariance: the same moves as
# consider_terms, but per named error of the unit (a ring, a lens-field mode), per unit of it.
UNIT_ERRORS = (("ring range bias", "m", 0.01), ("ring elevation", "rad", 1e-3))  # kind, unit, difference step
LENS_FIELD = "lens field"  # kind of a camera's lens-field mode (unit: px RMS of the field)


def ring_trend_projection(elevations: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, float]:
    """((m, R) P, e0): the fit ``a + b (e - e0)`` of ring_trend_directions is ``P @ c`` for per-ring
    errors c (R,), i.e. the part of them that stays after the frontend's correction; its
    covariance for errors of ``sigma`` each is ``sigma^2 P P^T`` (that function's)."""
    e0 = np.average(elevations, weights=counts)
    e = elevations - e0
    A = np.c_[np.ones_like(e), e] if len(e) > 1 and np.ptp(e) > 0 else np.ones((len(e), 1))
    return np.linalg.solve(A.T @ (counts[:, None] * A), (counts[:, None] * A).T), e0


def unit_error_sensitivities(problem: Problem, build, values, nominal=None) -> tuple[list, np.ndarray]:
    """([one dict per named error of a sensor unit], (ns, K) dx/de: how the sensors' tangent
    (noise.Linearization order) moves per unit of each error (m, rad, px)).

    The errors: per LIDAR and ring that met a board, its range bias (m) and elevation error (rad),
    ``{"sensor", "error", "unit", "ring_elevation_deg"}``; per camera, its lens field's modes
    (lens_field_modes of a 1 px RMS field; the error is the mode's coefficient in px),
    ``{"sensor", "error": "lens field", "unit": "px", "mode", "axis"}``. Same arguments as
    consider_terms.
    """
    ns = 6 * (len(problem.sensors) - 1)
    g, lin = _nominal(problem, build, values, nominal)
    S, r0, _ = lin.reduced()

    def r_of(p):  # only the factors p moves are linearized again: the others' terms are lin's
        return lin.relinearized(moved_graph(problem, p, lin, build)).reduced()[1]

    moves = {"ring range bias": _ring_range_moves,
             "ring elevation": lambda p, i, e0, ab: _ring_elevation_moves(p, values, i, e0, ab)}
    errors, columns = [], []
    for i, s in enumerate(problem.sensors):
        if not s.is_lidar or not any(o.sensor == i for o in problem.lidar_observations):
            continue
        elevations, counts = lidar_rings(problem, i)
        P, e0 = ring_trend_projection(elevations, counts)
        for kind, unit, h in UNIT_ERRORS:  # one-sided: a range bias moves the residuals linearly, an elevation
            # error to far below the noise at this step
            dr = [(r_of(moves[kind](problem, i, e0, h * u)) - r0) / h for u in np.eye(2)[:len(P)]]  # per unit of a, b
            columns.append(np.linalg.solve(S, np.stack(dr, axis=1)) @ P)
            errors += [{"sensor": s.topic, "error": kind, "unit": unit, "ring_elevation_deg": float(np.degrees(e))}
                       for e in elevations]
    lens = {i: lens_field_modes(s.imagersize, 1.0) for i, s in enumerate(problem.sensors)
            if s.is_camera and any(o.sensor == i for o in problem.camera_observations)}
    for i, dr in _lens_field_dr(problem, lin, g, lens).items():
        columns.append(np.linalg.solve(S, dr))
        errors += [{"sensor": problem.sensors[i].topic, "error": LENS_FIELD, "unit": "px", "mode": j, "axis": "xy"[a]}
                   for j in range(len(lens[i])) for a in (0, 1)]
    return errors, (np.concatenate(columns, axis=1) if columns else np.zeros((ns, 0)))
