"""A chessboard's dark squares ranging long, measured on the solved board poses.

LIDARs range weak returns late: a chessboard's dark squares come back 1-2 cm long (range walk).
Segmentation takes that out where the clouds carry intensities (frontend/lidar_board.py,
``dark_square_correction``). Clouds without them (pcl::PointXYZ, as a filter node republishes
them) keep it, and the board planes then sit behind the board the cameras see: on such a
simulated capture (bench/stress.py, ``pcl-xyz-dark-squares``) the camera was 7 mm off at 14 sigma.

Once the board poses are solved, each return's square on the pattern is known. Per LIDAR: the mean
range residual of the returns on the squares of one colour against the other's, the returns within
``MARGIN_M`` of a square's side left out (the pose's error and the beam's footprint may put them on
either side). The colours are told apart by the squares' parity, not by name: which one is printed
dark depends on the board, and the longer group is the dark one (weak returns come late). Where the
difference stands out of its standard error (``SIGNIFICANT``), the longer group's returns are moved
back along their rays by it, and the solve goes on with them.

SYNOPSIS
    found = measure(problem, rt_sensor, rt_board)   # {lidar: Offset}
    problem = corrected(problem, found, rt_sensor, rt_board)   # the significant ones taken out
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from ..geometry import T_from_rt, pose3_from_rt
from ..planes import fit_plane
from ..types import Problem
from . import graph as G

MARGIN_M = 0.02  # returns this close to a square's side are not counted
SIGNIFICANT = 4.0  # standard errors the difference must reach to be taken out
_MIN_RETURNS = 30  # of each colour, per LIDAR
_OUTLIER = 5.0  # robust sigmas beyond which a residual is not counted (a mixed pixel, a hand)


class Offset(NamedTuple):
    offset_m: float  # the longer colour's mean range beyond the other's (>= 0)
    se_m: float  # its standard error
    longer: int  # the parity (col + row) % 2 of the longer squares

    @property
    def significant(self) -> bool:
        return self.offset_m > SIGNIFICANT * self.se_m


def _squares(problem: Problem, o, T_sensor: np.ndarray, rt_board: np.ndarray):
    """(parity (K,), near a side (K,), on the pattern (K,)) of LIDAR observation ``o``'s points
    in the board at ``rt_board`` seen from the sensor at ``T_sensor`` (both in lidar0's frame;
    lidar0's own pose the identity)."""
    b = problem.board
    T = np.linalg.solve(T_from_rt(rt_board), T_sensor)  # sensor -> board frame
    q = np.asarray(o.points, float) @ T[:3, :3].T + T[:3, 3]
    u, v = q[:, 0] / b.square_m, q[:, 1] / b.square_m
    col, row = np.floor(u), np.floor(v)
    # the outer squares reach one square beyond the outer corners (types.BoardGeometry)
    on = (col >= -1) & (col <= b.corners_x - 1) & (row >= -1) & (row <= b.corners_y - 1)
    side = np.minimum(np.minimum(u - col, col + 1 - u), np.minimum(v - row, row + 1 - v)) * b.square_m
    return ((col + row) % 2).astype(np.int64), side < MARGIN_M, on


def measure(problem: Problem, rt_sensor: np.ndarray, rt_board: np.ndarray) -> dict[int, Offset]:
    """{LIDAR index: Offset} of the LIDARs with >= _MIN_RETURNS counted on each colour."""
    poses = [None if i == problem.reference else pose3_from_rt(rt_sensor[i]) for i in range(len(problem.sensors))]
    groups: dict[int, list] = {}
    for j, o in enumerate(problem.lidar_observations):
        r = G.residual_of(problem, "lidar", j, poses, rt_board)
        if r is None:
            continue
        parity, near, on = _squares(problem, o, T_from_rt(rt_sensor[o.sensor]), rt_board[o.snapshot])
        keep = on & ~near & np.isfinite(r)
        groups.setdefault(o.sensor, []).append((r[keep], parity[keep]))
    out = {}
    for i, parts in groups.items():
        r = np.concatenate([x for x, _ in parts])
        parity = np.concatenate([p for _, p in parts])
        a, b = (_robust(r[parity == k]) for k in (0, 1))
        if min(len(a), len(b)) < _MIN_RETURNS:
            continue
        d = float(a.mean() - b.mean())
        se = float(np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b)))
        out[i] = Offset(abs(d), se, 0 if d > 0 else 1)
    return out


def _robust(r: np.ndarray) -> np.ndarray:
    """``r`` without the residuals beyond _OUTLIER robust sigmas of its median."""
    if not len(r):
        return r
    dev = np.abs(r - np.median(r))
    return r[dev <= _OUTLIER * 1.4826 * np.median(dev)]


def corrected(problem: Problem, found: dict[int, Offset], rt_sensor: np.ndarray, rt_board: np.ndarray) -> Problem:
    """``problem`` with each significant offset of ``found`` taken out: the returns on the longer
    squares (near their sides too) moved back along their rays by it, and the plane refitted."""
    lidar = []
    for o in problem.lidar_observations:
        f = found.get(o.sensor)
        if f is None or not f.significant or not np.all(np.isfinite(rt_board[o.snapshot])):
            lidar.append(o)
            continue
        parity, _, on = _squares(problem, o, T_from_rt(rt_sensor[o.sensor]), rt_board[o.snapshot])
        move = on & (parity == f.longer)
        p = np.asarray(o.points, float).copy()
        r = np.linalg.norm(p[move], axis=1)
        p[move] *= ((r - f.offset_m) / r)[:, None]
        n, d, rms = fit_plane(p)  # the observation's plane as segmentation gives it: n toward the sensor
        plane = np.r_[-n, -d] if d > 0 else np.r_[n, d]
        lidar.append(dataclasses.replace(o, points=p, plane=plane, rms_m=rms))
    return dataclasses.replace(problem, lidar_observations=tuple(lidar))
