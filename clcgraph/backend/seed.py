"""Initial estimate: every sensor's pose in lidar0 and every board pose, without iterating.

1. Each observation gives the board in its sensor's frame: a LIDAR its plane (n, d) and
   the centroid of its points; a camera the full board pose by PnP (on mrcal-unprojected
   corners, so any lens model works).
2. Each pair of sensors that saw >= ``min_shared_snapshots`` boards together gets a
   relative pose: cameras-only pairs by averaging the board-pose ratios (the second
   camera's corner ordering chosen per board among the grid's in-plane rotations, so a
   camera rolled by 90 or 180 deg to the other still links); any pair with a
   LIDAR from the board planes (rotation by Procrustes on the normals, translation by least
   squares on the plane offsets ``n_a . t = d_a - d_b``, which are unbiased, plus a weak pull
   of the centroids, which hold the directions the normals leave open). Each normal points at
   its own sensor, so a board between two sensors shows them opposite normals: each board's
   sign is chosen with the rotation, and the boards' centres pick between the hypotheses
   (``_sides``). Mismatched pairs
   (normal > ``seed_max_normal_deg``, offset > ``seed_max_center_m``) are dropped and refit.
3. A best-first spanning tree from lidar0 over the pairs (most shared boards first)
   chains the pairs into poses; a sensor it cannot reach is a DegenerateError naming it.
4. Board poses in lidar0: from a camera's PnP when a camera saw the board, else from a
   LIDAR plane (its in-plane position from the points' centroid, in-plane rotation
   arbitrary: the solve's board prior holds it). Observations that disagree with the board
   pose (beyond the seed thresholds) are rejected with the numbers; a snapshot left with
   fewer than 2 observations is dropped. A camera whose detected ordering disagrees but a
   rotated one agrees is relabelled (``Seed.problem`` carries the relabelled corners).

SYNOPSIS
    s = seed(problem, options)            # options: config.SolveOptions
    s.rt_lidar0_sensor, s.rt_lidar0_board, s.rejected, s.dropped, s.problem
    rt = sensor_poses(problem, options)   # steps 1-3 only: s.rt_lidar0_sensor
"""

from __future__ import annotations

import dataclasses
import heapq
import logging
from typing import NamedTuple

import numpy as np

from .. import cameras
from ..errors import DegenerateError
from ..geometry import R_from_r, compose_rt, invert_rt, rt_from_R_t, transform
from ..types import Problem, Rejected

log = logging.getLogger(__name__)

# Weight of the centroid equations relative to the plane offsets: centroids are biased when
# a LIDAR saw part of the board, so they only fill the directions the normals leave open.
_CENTROID_WEIGHT = 0.05


class Seed(NamedTuple):
    rt_lidar0_sensor: np.ndarray  # (Nsensors,6)
    rt_lidar0_board: np.ndarray  # (Nsnapshots,6), NaN rows for snapshots not used
    rejected: tuple  # Rejected(stage="seed") records
    dropped: frozenset  # (sensor, snapshot) of the observations the seed rejected
    problem: Problem  # the input, with camera corners relabelled where the seed turned them
    # {(camera, snapshot): rt_camera_board} by PnP of the corners as detected, of each camera
    # observation the seed did not reject (board_check.scale_seen: the pattern's centre, which
    # a relabelling of the corners leaves where it is)
    rt_camera_board: dict


class _Obs(NamedTuple):
    """One observation reduced to the board in its sensor's frame."""

    sensor: int
    snapshot: int
    n: np.ndarray  # unit normal toward the sensor
    d: float  # n . x = d
    centroid: np.ndarray
    rt_sensor_board: np.ndarray | None  # cameras only
    # cameras: (corner permutation, rt_sensor_board) for each in-plane rotation of the
    # detected ordering (the detection's own first); see corner_orderings
    alts: tuple = ()


def corner_orderings(board) -> list[np.ndarray]:
    """Permutations of the board-order corner array for every in-plane rotation of the
    grid a detector cannot tell apart (module camera_board): 4 for a square grid, 2
    otherwise; the identity first. ``corners_px[perm]`` relabels one view."""
    grid = np.arange(board.corners_x * board.corners_y).reshape(board.corners_y, board.corners_x)
    turns = (0, 1, 2, 3) if board.corners_x == board.corners_y else (0, 2)
    return [np.rot90(grid, k).ravel() for k in turns]


def board_pose_from_corners(corners_px, sensor, board, max_px: float):
    """rt_camera_board from one camera observation's corners, or a reason string (one where its
    corners reproject more than ``max_px`` off; inf: not checked)."""
    import cv2

    q = np.asarray(corners_px, float)
    ok = np.all(np.isfinite(q), axis=1)
    v = cameras.unproject(q[ok], sensor.lensmodel, sensor.intrinsics, normalize=True)
    front = v[:, 2] > 1e-3
    if front.sum() < 6:
        return "too few corners in front of the camera"
    obj = board.corners()[ok][front]
    img = v[front, :2] / v[front, 2:]
    good, rvec, tvec = cv2.solvePnP(obj, img, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
    if not good:
        return "PnP failed"
    good, rvec, tvec = cv2.solvePnP(obj, img, np.eye(3), None, rvec, tvec, True, cv2.SOLVEPNP_ITERATIVE)
    rt = np.r_[rvec.ravel(), tvec.ravel()]
    if max_px == np.inf:  # no reprojection check asked for
        return rt
    pred = cameras.project(transform(rt, board.corners()[ok]), sensor.lensmodel, sensor.intrinsics)
    err = np.linalg.norm(pred - q[ok], axis=1).max()
    if not np.isfinite(err) or err > max_px:
        return f"board pose from the corners reprojects {err:.1f} px off (> seed_max_corner_px {max_px:g})"
    return rt


def _turn(board, perm: np.ndarray) -> np.ndarray:
    """rt_board_turned: the in-plane turn of the grid that maps each corner to the one ``perm``
    puts in its place (``corners[perm] = transform(rt, corners)``; exact for the orderings of
    corner_orderings, which permute the grid onto itself)."""
    c = board.corners()
    a, b = c - c.mean(axis=0), c[perm] - c[perm].mean(axis=0)
    R = _procrustes(b, a)
    return rt_from_R_t(R, c[perm].mean(axis=0) - R @ c.mean(axis=0))


def _board_centre(board) -> np.ndarray:
    xmin, xmax, ymin, ymax = board.extent()
    return np.array([(xmin + xmax) / 2, (ymin + ymax) / 2, 0.0])


def _reduce(problem: Problem, options) -> tuple[list[_Obs], list[Rejected]]:
    out, rejected = [], []
    for o in problem.lidar_observations:
        n, d = np.asarray(o.plane[:3], float), float(o.plane[3])
        out.append(_Obs(o.sensor, o.snapshot, n, d, np.asarray(o.points, float).mean(axis=0), None))
    centre = _board_centre(problem.board)
    orders = corner_orderings(problem.board)
    turns = [(perm, _turn(problem.board, perm)) for perm in orders[1:]]
    for o in problem.camera_observations:
        s = problem.sensors[o.sensor]
        rt = board_pose_from_corners(o.corners_px, s, problem.board, options.seed_max_corner_px)
        if isinstance(rt, str):
            rejected.append(Rejected(rt, "seed", o.sensor, o.snapshot))
            continue
        # the grid's other orderings are the same board pose turned in its plane (no PnP each):
        # it fits their corners exactly as well as this one fits its own
        alts = [(orders[0], rt)] + [(perm, compose_rt(rt, rt_turn)) for perm, rt_turn in turns]
        R, t = R_from_r(rt[:3]), rt[3:]
        n = R[:, 2]
        d = float(n @ t)
        if d > 0:
            n, d = -n, -d
        out.append(_Obs(o.sensor, o.snapshot, n, d, transform(rt, centre[None])[0], rt, tuple(alts)))
    return out, rejected


def _mean_rotation(Rs: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(Rs.sum(axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _procrustes(na: np.ndarray, nb: np.ndarray) -> np.ndarray:
    """R minimizing sum |na - R nb|^2."""
    U, _, Vt = np.linalg.svd(na.T @ nb)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _pair(a_obs: list[_Obs], b_obs: list[_Obs], options):
    """rt_a_b from observations of the same boards (paired lists), or None if undetermined."""
    max_angle = np.radians(options.seed_max_normal_deg)
    keep = np.ones(len(a_obs), bool)
    for _ in range(3):
        A = [o for o, k in zip(a_obs, keep) if k]
        B = [o for o, k in zip(b_obs, keep) if k]
        if len(A) < options.min_shared_snapshots:
            return None
        if all(o.rt_sensor_board is not None for o in A + B):
            rts = _camera_ratios(A, B, options)
            R = _mean_rotation(R_from_r(rts[:, :3]))
            t = np.median(rts[:, 3:], axis=0)
        else:
            na, nb = np.array([o.n for o in A]), np.array([o.n for o in B])
            sv = np.linalg.svd(nb, compute_uv=False)
            if sv[1] < np.sin(np.radians(5.0)) * sv[0]:
                return None  # all boards parallel: the rotation about their normal is unknown
            best = None
            for R, side in _sides(na, nb):
                da = np.array([o.d for o in A]) - side * np.array([o.d for o in B])
                ca = np.array([o.centroid for o in A]) - np.array([o.centroid for o in B]) @ R.T
                M = np.vstack([na, _CENTROID_WEIGHT * np.tile(np.eye(3), (len(A), 1))])
                y = np.r_[da, _CENTROID_WEIGHT * ca.ravel()]
                t = np.linalg.lstsq(M, y, rcond=None)[0]
                miss = float(np.median(np.linalg.norm(ca - t, axis=1)))  # the boards' centres apart
                if best is None or miss < best[0]:
                    best = (miss, R, t)
            _, R, t = best
        # residuals of every shared observation under this estimate, each board on its side
        sign = np.array([1.0 if x.n @ (R @ y.n) >= 0 else -1.0 for x, y in zip(a_obs, b_obs)])
        ang = np.array([np.arccos(np.clip(s * x.n @ (R @ y.n), -1, 1)) for x, y, s in zip(a_obs, b_obs, sign)])
        off = np.array([abs(x.n @ t - (x.d - s * y.d)) for x, y, s in zip(a_obs, b_obs, sign)])
        new = (ang <= max_angle) & (off <= options.seed_max_center_m)
        if np.array_equal(new, keep):
            return rt_from_R_t(R, t), int(keep.sum())
        keep = new
    return (rt_from_R_t(R, t), int(keep.sum())) if keep.sum() >= options.min_shared_snapshots else None


def _sides(na: np.ndarray, nb: np.ndarray) -> list:
    """[(R, side (K,) +-1)]: rotations taking the normals ``nb`` to ``na``, each normal turned by its
    board's side (-1: the board is between the sensors, their normals opposite), from both
    sensors on the same side of every board and from the other side of every board, each
    board's side then taken from the rotation and the rotation refitted. Both are kept: where
    the normals lie in one plane (upright boards), the two fit them alike (a half turn about
    that plane's normal) and only where they put the boards' centres tells them apart."""
    out = []
    for start in (1.0, -1.0):
        side = np.full(len(na), start)
        for _ in range(3):
            R = _procrustes(na, nb * side[:, None])
            new = np.where(np.einsum("ki,ki->k", na, nb @ R.T) >= 0, 1.0, -1.0)
            if np.array_equal(new, side):
                break
            side = new
        else:
            R = _procrustes(na, nb * side[:, None])
        out.append((R, side))
    return out


def _rt_distance(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(rotation angle in deg, translation distance in m) between two rt poses."""
    d = compose_rt(invert_rt(a), b)
    return float(np.degrees(np.linalg.norm(d[:3]))), float(np.linalg.norm(a[3:] - b[3:]))


def _camera_ratios(A: list[_Obs], B: list[_Obs], options) -> np.ndarray:
    """rt_a_b from each shared board of two cameras, with b's corner ordering chosen per
    board so that the ratios agree (cameras rolled > 45 deg to each other see the grid
    rotated): the hypothesis most boards support wins, each board takes its nearest."""
    cands = [[compose_rt(x.rt_sensor_board, invert_rt(rt)) for _, rt in y.alts] for x, y in zip(A, B)]

    def near(h, c):
        ang, dist = _rt_distance(h, c)
        return ang <= options.seed_max_normal_deg and dist <= options.seed_max_center_m

    best = max((h for cs in cands for h in cs), key=lambda h: sum(any(near(h, c) for c in cs) for cs in cands))
    return np.array([min(cs, key=lambda c: _rt_distance(best, c)[0]) for cs in cands])


def _spanning_tree(problem: Problem, obs: list[_Obs], options) -> np.ndarray:
    ns = len(problem.sensors)
    ref = problem.reference
    by = {}
    for o in obs:
        by.setdefault(o.sensor, {})[o.snapshot] = o
    shared = {}
    for a in range(ns):
        for b in range(a + 1, ns):
            ks = sorted(set(by.get(a, {})) & set(by.get(b, {})))
            if len(ks) >= options.min_shared_snapshots:
                shared[(a, b)] = ks
    rts = np.full((ns, 6), np.nan)
    rts[ref] = 0.0
    done = {ref}
    heap = [(-len(ks), a, b) for (a, b), ks in shared.items() if ref in (a, b)]
    heapq.heapify(heap)
    tried = set()
    while heap:
        _, a, b = heapq.heappop(heap)
        src, dst = (a, b) if a in done else (b, a)
        if dst in done or (src, dst) in tried:
            continue
        tried.add((src, dst))
        ks = shared[(min(a, b), max(a, b))]
        est = _pair([by[src][k] for k in ks], [by[dst][k] for k in ks], options)
        if est is None:
            continue
        rts[dst] = compose_rt(rts[src], est[0])
        done.add(dst)
        log.debug("seed: %s from %s over %d boards", problem.sensors[dst].topic, problem.sensors[src].topic, est[1])
        for (p, q), kk in shared.items():
            if dst in (p, q) and (q if p == dst else p) not in done:
                heapq.heappush(heap, (-len(kk), p, q))
    missing = [i for i in range(ns) if i not in done]
    if missing:
        parts = []
        for i in missing:
            counts = [f"{problem.sensors[j].topic}: {len(set(by.get(i, {})) & set(by.get(j, {})))}"
                      for j in sorted(done)]
            parts.append(f"{problem.sensors[i].topic} (boards seen together with the solved sensors: "
                         f"{', '.join(counts)}; need >= {options.min_shared_snapshots} with varied orientations)")
        raise DegenerateError("cannot connect to lidar0 " + problem.sensors[ref].topic + ": " + "; ".join(parts))
    return rts


def _board_from_plane(o: _Obs, rt_sensor: np.ndarray, board) -> np.ndarray:
    R_s = R_from_r(rt_sensor[:3])
    z = -(R_s @ o.n)  # board z points away from the sensor
    c = transform(rt_sensor, o.centroid[None])[0]
    y = np.array([0.0, 0.0, -1.0])
    y = y - (y @ z) * z
    if np.linalg.norm(y) < 1e-3:
        y = np.array([1.0, 0.0, 0.0]) - z[0] * z
    y /= np.linalg.norm(y)
    R = np.c_[np.cross(y, z), y, z]
    return rt_from_R_t(R, c - R @ _board_centre(board))


def _disagreements(o: _Obs, cands: np.ndarray, rt_sensor: np.ndarray, problem: Problem, options) -> list:
    """Per candidate board pose rt_lidar0_board (cands (C,6)): (why observation ``o``
    disagrees with it, or None; the corner permutation of the camera ordering that agrees
    when it is not the detection's own, else None). Every candidate at once: the seed weighs
    each snapshot's candidates against each of its observations."""
    rt_sb = compose_rt(invert_rt(rt_sensor), cands)  # (C,6)
    R, t = R_from_r(rt_sb[:, :3]), rt_sb[:, 3:]
    n = R[:, :, 2]
    ang = np.degrees(np.arccos(np.minimum(1.0, np.abs(n @ o.n))))
    off = np.abs(np.einsum("ci,ci->c", n, o.centroid - t))
    err = None
    if o.rt_sensor_board is not None:
        s = problem.sensors[o.sensor]
        c = problem.board.corners()
        pred = cameras.project(np.einsum("cij,nj->cni", R, c) + t[:, None, :], s.lensmodel, s.intrinsics)  # (C,N,2)
        # the corners where each ordering's own board pose puts them (the detection's first)
        obs = np.array([cameras.project(transform(rt, c), s.lensmodel, s.intrinsics) for _, rt in o.alts])
        err = np.nanmax(np.linalg.norm(pred[:, None] - obs[None], axis=-1), axis=-1)  # (C, orderings)
    out = []
    for j in range(len(cands)):
        if ang[j] > options.seed_max_normal_deg:
            out.append((f"board normal {ang[j]:.1f} deg off the other sensors' (> seed_max_normal_deg)", None))
        elif off[j] > options.seed_max_center_m:
            out.append((f"board plane {off[j]:.2f} m off the other sensors' (> seed_max_center_m)", None))
        elif err is None or err[j, 0] <= options.seed_max_corner_px:
            out.append((None, None))
        else:  # another ordering of the grid may agree (a camera seeing it turned)
            turned = next((perm for (perm, _), e in zip(o.alts[1:], err[j, 1:]) if e <= options.seed_max_corner_px),
                          None)
            why = f"corners {err[j, 0]:.1f} px off the other sensors' board pose (> seed_max_corner_px)"
            out.append((None, turned) if turned is not None else (why, None))
    return out


def sensor_poses(problem: Problem, options) -> np.ndarray:
    """(Nsensors, 6) rt_lidar0_sensor of ``seed`` without the board poses and their vote (steps
    1-3): enough to predict where the boards are."""
    return _spanning_tree(problem, _reduce(problem, options)[0], options)


def seed(problem: Problem, options) -> Seed:
    """The initial estimate of every pose (module docstring); options: config.SolveOptions."""
    obs, rejected = _reduce(problem, options)
    rts = _spanning_tree(problem, obs, options)
    boards = np.full((problem.n_snapshots, 6), np.nan)
    by_snap: dict[int, list[_Obs]] = {}
    for o in obs:
        by_snap.setdefault(o.snapshot, []).append(o)
    dropped = {(r.sensor, r.snapshot) for r in rejected}
    reorder = {}  # (sensor, snapshot) -> corner permutation of a camera seeing the grid turned
    for k, group in sorted(by_snap.items()):
        # candidate board poses: every camera's PnP (in each of its corner orderings), then
        # every LIDAR plane; keep the one most observations agree with (a wrong plane or a
        # bad detection loses the vote), each camera in the ordering that agrees
        cands = [compose_rt(rts[o.sensor], rt) for o in group if o.rt_sensor_board is not None for _, rt in o.alts]
        cands += [_board_from_plane(o, rts[o.sensor], problem.board) for o in group if o.rt_sensor_board is None]
        verdicts = [_disagreements(o, np.array(cands), rts[o.sensor], problem, options) for o in group]
        best, best_bad, best_perm = None, None, None
        for j, c in enumerate(cands):
            bad, perms = [], {}
            for o, v in zip(group, verdicts):
                why, perm = v[j]
                if why:
                    bad.append((o, why))
                elif perm is not None:
                    perms[(o.sensor, k)] = perm
            if best is None or len(bad) < len(best_bad):
                best, best_bad, best_perm = c, bad, perms
        reorder.update(best_perm)
        keep = len(group) - len(best_bad)
        if keep < 2:
            for o in group:
                rejected.append(Rejected("sensors disagree on this board's pose (seed)", "seed", o.sensor, k))
                dropped.add((o.sensor, k))
            continue
        for o, why in best_bad:
            rejected.append(Rejected(why, "seed", o.sensor, k))
            dropped.add((o.sensor, k))
        boards[k] = best
    for key in dropped:
        reorder.pop(key, None)
    if reorder:
        log.info("seed: %d camera views relabelled (the grid seen turned by 90 or 180 deg)", len(reorder))
        cams = tuple(dataclasses.replace(o, corners_px=np.asarray(o.corners_px)[reorder[(o.sensor, o.snapshot)]])
                     if (o.sensor, o.snapshot) in reorder else o for o in problem.camera_observations)
        problem = dataclasses.replace(problem, camera_observations=cams)
    pnp = {(o.sensor, o.snapshot): o.rt_sensor_board for o in obs if o.rt_sensor_board is not None}
    return Seed(rts, boards, tuple(rejected), frozenset(dropped), problem, pnp)
