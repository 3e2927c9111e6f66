"""Replay and Monte-Carlo re-noising of a Problem: re-solve it (the seed's fit-from-inputs-dump),
leave snapshots out, or replace its observations by what a solution predicts plus fresh noise.

Reading and writing the dump is outputs/dump.py's; ``api.replay(path)`` joins the two.

SYNOPSIS
    problem, config = load_problem("out/problem.npz")              # outputs/dump.py
    res = replay_problem(problem, config.solve, exclude=[3])          # snapshot 3 left out
    res = replay_problem(problem, config.solve, inject_noise=True, seed=1)  # one Monte-Carlo sample
    noisy = renoise_problem(problem, rt_lidar0_sensor, rt_lidar0_board, sigma_lidar_m=0.02,
                            sigma_camera_px=0.3, rng=np.random.default_rng(0))
"""

from __future__ import annotations

import dataclasses

import numpy as np

from clcgraph.config import SolveOptions
from clcgraph.errors import InputError
from clcgraph.geometry import compose_rt, invert_rt, transform
from clcgraph.types import CameraBoardObservation, LidarBoardObservation, Problem, Rejected, Result, names_bag


def renoise_problem(
    problem: Problem,
    rt_lidar0_sensor: np.ndarray,
    rt_lidar0_board: np.ndarray,
    *,
    sigma_lidar_m: float,
    sigma_camera_px: float,
    rng: np.random.Generator,
) -> Problem:
    """A copy of ``problem`` whose observations are the ones the given geometry predicts plus noise.

    LIDAR points are moved along their rays onto the given board plane, then by N(0, sigma_lidar_m)
    in range (their edge intervals are dropped, not re-drawn: a sample's LIDARs have their planes
    alone); camera corners are the board corners projected through the given poses plus
    N(0, sigma_camera_px) per coordinate. Observations of snapshots without a finite board pose
    are dropped. Used for Monte-Carlo uncertainty checks (replay --inject-noise).
    """
    from clcgraph import cameras

    rts = np.asarray(rt_lidar0_sensor, float)
    boards = np.asarray(rt_lidar0_board, float)
    ok = np.all(np.isfinite(boards), axis=1)
    lidar = []
    for o in problem.lidar_observations:
        if not ok[o.snapshot]:
            continue
        rt_l_b = compose_rt(invert_rt(rts[o.sensor]), boards[o.snapshot])
        T_n = transform(np.r_[rt_l_b[:3], 0, 0, 0], np.array([[0.0, 0, 1]]))[0]
        u = o.points / np.linalg.norm(o.points, axis=1, keepdims=True)
        s = (T_n @ rt_l_b[3:]) / (u @ T_n)
        s = s + rng.normal(0.0, sigma_lidar_m, size=s.shape)
        p = u * s[:, None]
        d = T_n @ rt_l_b[3:]
        # normal towards the sensor (at the origin) means n . x = d < 0 on the board
        plane = np.r_[-T_n, -d] if d > 0 else np.r_[T_n, d]
        # the edge intervals are not re-drawn (their noise is where the rays fall on the board): a
        # re-noised sample has the planes alone
        lidar.append(LidarBoardObservation(o.sensor, o.snapshot, p, plane, sigma_lidar_m, o.indices, ring=o.ring))
    corners = problem.board.corners()
    camera = []
    for o in problem.camera_observations:
        if not ok[o.snapshot]:
            continue
        s = problem.sensors[o.sensor]
        p_c = transform(compose_rt(invert_rt(rts[o.sensor]), boards[o.snapshot]), corners)
        q = cameras.project(p_c, s.lensmodel, s.intrinsics)
        q = q + rng.normal(0.0, sigma_camera_px, size=q.shape)
        q[~np.all(np.isfinite(o.corners_px), axis=1)] = np.nan  # keep the same missing corners
        camera.append(CameraBoardObservation(o.sensor, o.snapshot, q))
    return dataclasses.replace(problem, lidar_observations=tuple(lidar), camera_observations=tuple(camera))


def snapshot_indices(problem: Problem, items, *, flag: str = "--exclude") -> list[int]:
    """Snapshot indices named by ``items``: each an index (int or digits) or a bag's file name or
    path (every snapshot of that bag). InputError naming an item that matches nothing."""
    out: set[int] = set()
    for item in items:
        text = str(item).strip()
        if isinstance(item, (int, np.integer)) or text.isdigit():
            k = int(text)
            if not 0 <= k < problem.n_snapshots:
                raise InputError(f"{flag}: no snapshot {k} (the problem has {problem.n_snapshots})")
            out.add(k)
            continue
        hits = [k for k, b in enumerate(problem.snapshot_bags) if names_bag(text, b)]
        if not hits:
            known = ", ".join(sorted({problem.snapshot_bag(k) for k in range(len(problem.snapshot_bags))})[:5])
            raise InputError(f"{flag}: {text!r} is neither a snapshot index (0..{problem.n_snapshots - 1}) nor a bag "
                             f"of this problem ({known or 'the dump names no bags'}{', ...' if len(problem.snapshot_bags) > 5 else ''})")
        out.update(hits)
    return sorted(out)


def exclude_snapshots(problem: Problem, exclude) -> Problem:
    """A copy of ``problem`` without the observations of the snapshots in ``exclude`` (indices or
    bag names, see snapshot_indices).

    Snapshot indices are kept (not renumbered), so results stay comparable with the full solve;
    the excluded snapshots get NaN board poses.
    """
    return without_snapshots(problem, snapshot_indices(problem, exclude), "excluded by the user", "snapshot")


def without_snapshots(problem: Problem, snapshots, reason: str, stage: str) -> Problem:
    """``problem`` without the observations of ``snapshots`` (indices kept), each named in its
    rejections with ``reason`` at ``stage``."""
    ex = set(snapshots)
    return dataclasses.replace(
        problem,
        lidar_observations=tuple(o for o in problem.lidar_observations if o.snapshot not in ex),
        camera_observations=tuple(o for o in problem.camera_observations if o.snapshot not in ex),
        rejected=problem.rejected + tuple(Rejected(reason, stage, None, k) for k in sorted(ex)),
    )


def replay_problem(
    problem: Problem,
    options: SolveOptions,
    *,
    inject_noise: bool = False,
    fit_seed: bool = False,
    exclude=(),
    seed: int = 0,
) -> Result:
    """Re-solve a (loaded) problem dump, like the seed's fit-from-inputs-dump -> types.Result.

    - ``exclude``: snapshots to drop (the seed's --exclude): indices or bag names; indices are not renumbered.
    - ``inject_noise``: solve once, then replace the observations by what that solution predicts
      plus fresh noise with the re-estimated sigmas (``renoise_problem``, rng seeded by ``seed``)
      and solve again: one Monte-Carlo sample for checking the reported uncertainty.
    - ``fit_seed``: stop after the seed (initial estimate): the Result carries the seed poses,
      a NaN covariance, empty noise/rms, and ``stats["stage"] == "seed"``.
    ``options``: the solve settings (the dump's config.solve for a replay).
    """
    from clcgraph.backend.solve import calibrate

    if exclude:
        problem = exclude_snapshots(problem, exclude)
    if fit_seed:
        return _seed_result(problem, options)
    result = calibrate(problem, options)
    if not inject_noise:
        return result
    noisy = renoise_problem(
        problem, result.rt_lidar0_sensor, result.rt_lidar0_board,
        sigma_lidar_m=float(result.noise["lidar_m"]),
        sigma_camera_px=float(result.noise.get("camera_px", options.sigma_camera_px)),
        rng=np.random.default_rng(seed),
    )
    return calibrate(noisy, options)


def _seed_result(problem: Problem, options: SolveOptions) -> Result:
    """The seed's estimate as a Result (no covariance: NaN; no noise/rms; stats["stage"] = "seed")."""
    from clcgraph.backend.seed import seed as seed_poses

    rt_sensor, rt_board = seed_poses(problem, options)[:2]
    nv = 6 * (len(problem.sensors) - 1)
    return Result(
        problem=problem,
        rt_lidar0_sensor=np.asarray(rt_sensor, float),
        covariance_rt=np.full((nv, nv), np.nan),
        rt_lidar0_board=np.asarray(rt_board, float),
        noise={},
        rms={},
        rejected=problem.rejected,
        stats={"stage": "seed"},
    )
