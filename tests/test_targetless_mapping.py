"""Mapping accuracy on a motion-distorted drive: deskew is what makes the map consistent."""

from __future__ import annotations

import numpy as np
import pytest

from clcgraph import geometry as geo
from clcgraph.config import Config
from clcgraph.sim.drive import DrivePlan, base_pose, simulate_drive
from clcgraph.targetless.mapping import build_map

TOP = "/top/points"


def _rel_errors(drive, mp):
    """Per-step relative pose errors (deg, m) of the mapping poses against truth."""
    T_bl = drive.T_base_lidar[TOP]
    ts = (mp.stamps_ns() - drive.t0_ns) * 1e-9
    Tw = base_pose(drive.plan, ts) @ T_bl
    P = mp.poses()
    rot, tr = [], []
    for k in range(1, len(P)):
        d_true = np.linalg.inv(Tw[k - 1]) @ Tw[k]
        d_est = np.linalg.inv(P[k - 1]) @ P[k]
        e = geo.rt_from_T(np.linalg.inv(d_true) @ d_est)
        rot.append(np.degrees(np.linalg.norm(e[:3])))
        tr.append(np.linalg.norm(e[3:]))
    return np.array(rot), np.array(tr)


@pytest.mark.slow
def test_deskew_improves_mapping_under_yaw():
    plan = DrivePlan.small(duration_s=8.0, yaw_rate_amp_dps=8.0, yaw_period_s=8.0, speed_mps=1.0)
    drive = simulate_drive(plan, seed=4)
    res = {}
    for on in (True, False):
        o = Config().replace(targetless=dict(deskew=on)).targetless
        res[on] = _rel_errors(drive, build_map(drive.scans[TOP], o))
    # skip the warm-up (the constant-velocity model starts from rest while the vehicle is moving)
    r_on, t_on = (np.sqrt(np.mean(x[5:] ** 2)) for x in res[True])
    r_off, t_off = (np.sqrt(np.mean(x[5:] ** 2)) for x in res[False])
    # at up to 8 deg/s and 1 m/s the smear is ~0.8 deg / 10 cm over a revolution
    assert r_on < 0.5 * r_off and t_on < 0.8 * t_off, (r_on, r_off, t_on, t_off)
    assert r_on < 0.02 and t_on < 0.004, (r_on, t_on)


@pytest.mark.slow
@pytest.mark.parametrize("registrator", ["VGICP", "GICP"])
def test_both_registrators_map_accurately(registrator):
    """VGICP against the incremental Gaussian voxel map (the default), and GICP against the
    local map's points rebuilt at every keyframe."""
    plan = DrivePlan.small(duration_s=8.0, yaw_rate_amp_dps=8.0, yaw_period_s=8.0, speed_mps=1.0)
    drive = simulate_drive(plan, seed=4)
    o = Config().replace(targetless=dict(mapper_registrator=registrator)).targetless
    r, t = (np.sqrt(np.mean(x[5:] ** 2)) for x in _rel_errors(drive, build_map(drive.scans[TOP], o)))
    assert r < 0.02 and t < 0.004, (r, t)
