"""backend/consider.lidar_rings: the rings of a LIDAR's board points from each point's ring (the
frontend's, LidarBoardObservation.ring), not re-derived from elevation gaps; older observations
without rings fall back to the gaps."""

from __future__ import annotations

import dataclasses

import numpy as np

from clcgraph.backend import consider
from clcgraph.sim.observations import make_rig, simulate_problem


def test_rings_from_the_ring_field_and_without_it_the_same():
    problem, _ = simulate_problem(rig=make_rig(2, 0), n_snapshots=8, seed=2)
    no_rings = dataclasses.replace(problem, lidar_observations=tuple(
        dataclasses.replace(o, ring=None) for o in problem.lidar_observations))
    for sensor, model in make_rig(2, 0).lidars.items():
        el, counts = consider.lidar_rings(problem, sensor)
        rings = np.unique(np.concatenate([o.ring for o in problem.lidar_observations if o.sensor == sensor]))
        np.testing.assert_allclose(el, np.asarray(model.elevations_rad)[rings], atol=1e-9)
        el0, counts0 = consider.lidar_rings(no_rings, sensor)
        np.testing.assert_allclose(np.sort(el0), np.sort(el), atol=1e-9)
        np.testing.assert_array_equal(counts0[np.argsort(el0)], counts[np.argsort(el)])


def test_a_ring_whose_elevation_wanders_is_one_ring():
    """One laser whose elevation drifts by 0.1 deg along its sweep (a real unit's beam is not an
    exact cone): the elevation gaps split it in two, its ring number keeps it one."""
    problem, _ = simulate_problem(rig=make_rig(2, 0), n_snapshots=6, seed=3)
    o = next(o for o in problem.lidar_observations if o.sensor == 0)
    r = np.linalg.norm(o.points, axis=1)
    az = np.arctan2(o.points[:, 1], o.points[:, 0])
    k = o.ring[len(o.ring) // 2]
    drift = (o.ring == k) & (az > np.median(az[o.ring == k]))
    el = np.arcsin(o.points[:, 2] / r) + np.where(drift, np.radians(0.1), 0.0)
    p = np.c_[r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)]
    with_ring = dataclasses.replace(problem, lidar_observations=(dataclasses.replace(o, points=p),))
    without = dataclasses.replace(problem, lidar_observations=(dataclasses.replace(o, points=p, ring=None),))
    n = len(np.unique(o.ring))
    assert len(consider.lidar_rings(with_ring, 0)[0]) == n
    assert len(consider.lidar_rings(without, 0)[0]) == n + 1
