"""The seed's sector feedback: coverage and uncertainty in azimuth slices around the vehicle.

The vehicle ground plane (z = 0 of frame ``vehicle``, given by ``rt_vehicle_lidar0``) is cut
into ``n_sectors`` equal azimuth slices, sector k covering [k, k+1) * 2pi/n_sectors from the
vehicle +x axis, counter-clockwise. Each sector's evaluation point is on the ground at the
sector's centre azimuth and ``uncertainty_quantification_range_m`` from the vehicle origin.
"""

from __future__ import annotations

import itertools

import numpy as np

from clcgraph import cameras
from clcgraph.backend.uncertainty import worst_direction_stdev
from clcgraph.geometry import azimuth, compose_rt, invert_rt, transform
from clcgraph.types import Result, SectorReport


def _isector(p_vehicle: np.ndarray, n: int) -> np.ndarray:
    """(...,3) vehicle-frame points -> (...,) sector indices by azimuth."""
    az = np.mod(azimuth(p_vehicle), 2 * np.pi)
    return np.minimum((az / (2 * np.pi / n)).astype(int), n - 1)


def sector_points_lidar0(options, rt_vehicle_lidar0: np.ndarray | None = None) -> np.ndarray:
    """(Nsectors,3) evaluation points in lidar0: ground, centre azimuth, quantification range."""
    n = options.n_sectors
    rt_v0 = np.asarray(options.rt_vehicle_lidar0 if rt_vehicle_lidar0 is None else rt_vehicle_lidar0, float)
    az = (np.arange(n) + 0.5) * 2 * np.pi / n
    R = options.uncertainty_quantification_range_m
    p_v = np.stack([R * np.cos(az), R * np.sin(az), np.zeros(n)], -1)
    return transform(invert_rt(rt_v0), p_v)


def sector_report(result: Result, options) -> SectorReport:
    """SectorReport for a solved Result under config.SectorOptions ``options``."""
    problem = result.problem
    n = options.n_sectors
    rts = np.asarray(result.rt_lidar0_sensor, float)
    rt_v0 = np.asarray(options.rt_vehicle_lidar0, float)
    ns = len(problem.sensors)

    # Observations: centre of the physical board of every solved snapshot.
    xmin, xmax, ymin, ymax = problem.board.extent()
    centre_b = np.array([(xmin + xmax) / 2, (ymin + ymax) / 2, 0.0])
    obs = np.zeros(n, int)
    isector_last = -1
    boards = np.asarray(result.rt_lidar0_board, float)
    used = np.flatnonzero(np.all(np.isfinite(boards), axis=1))
    if len(used):
        centres = np.array([transform(compose_rt(rt_v0, boards[k]), centre_b[None])[0] for k in used])
        isec = _isector(centres, n)
        obs = np.bincount(isec, minlength=n)
        isector_last = int(isec[-1])

    # Visibility.
    p0 = sector_points_lidar0(options)
    visible = np.zeros((ns, n), bool)
    for i, s in enumerate(problem.sensors):
        if s.is_lidar:
            pts = problem.lidar_visibility_points.get(i)
            if pts is None or len(pts) == 0:
                continue
            pts = np.asarray(pts, float)
            far = pts[np.linalg.norm(pts, axis=1) > options.threshold_valid_lidar_range_m]
            p_v = transform(compose_rt(rt_v0, rts[i]), far)
            counts = np.bincount(_isector(p_v, n), minlength=n)
            visible[i] = counts >= options.threshold_valid_lidar_npoints
        else:
            p_c = transform(invert_rt(rts[i]), p0)
            q = cameras.project(p_c, s.lensmodel, s.intrinsics)
            w, h = s.imagersize
            visible[i] = (
                (p_c[:, 2] > 0)
                & np.all(np.isfinite(q), axis=1)
                & (q[:, 0] >= 0) & (q[:, 0] <= w - 1) & (q[:, 1] >= 0) & (q[:, 1] <= h - 1)
            )

    # Worst pair stdev at each sector's evaluation point.
    worst = np.zeros(n)
    pair = np.zeros((n, 2), int)
    ref = problem.reference
    for a, b in itertools.combinations(range(ns), 2):
        p_a = transform(invert_rt(rts[a]), p0)
        s = worst_direction_stdev(rts, result.covariance_rt, ref, a, b, p_a)
        better = s > worst
        worst[better] = s[better]
        pair[better] = (a, b)
    return SectorReport(
        n_sectors=n,
        observations_per_sector=obs,
        isvisible_per_sensor_per_sector=visible,
        stdev_worst_per_sector=worst,
        isensors_pair_stdev_worst=pair,
        isector_of_last_snapshot=isector_last,
    )


def uncertainty_grid(result: Result, i: int, j: int, *, radius: float, gridn: int, z: float = 0.0):
    """Worst-direction stdev of mapping points from sensor i to sensor j on a lidar0 grid.

    The grid spans [-radius, radius]^2 in lidar0's x, y at height z (gridn x gridn).
    Returns (x (gridn,), y (gridn,), stdev (gridn, gridn) indexed [iy, ix]) in metres.
    """
    x = np.linspace(-radius, radius, gridn)
    y = np.linspace(-radius, radius, gridn)
    X, Y = np.meshgrid(x, y)
    p0 = np.stack([X, Y, np.full_like(X, z)], -1)
    rts = np.asarray(result.rt_lidar0_sensor, float)
    p_i = transform(invert_rt(rts[i]), p0.reshape(-1, 3)).reshape(p0.shape)
    s = worst_direction_stdev(rts, result.covariance_rt, result.problem.reference, i, j, p_i)
    return x, y, s
