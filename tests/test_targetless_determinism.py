"""Targetless: the same calibration to the bit on one process and one thread as on two of each
(targetless/gicp.py: what small_gicp computes per point keeps the thread count, its
order-dependent reductions run on one thread; targetless/background.py: a forked child runs the
same function on the same data)."""

from __future__ import annotations

import numpy as np
import pytest

from clcgraph.config import Config
from clcgraph.sim.drive import DrivePlan, simulate_drive
from clcgraph.targetless import background
from clcgraph.targetless.pipeline import calibrate_targetless_scans

TOP, SIDE = "/top/points", "/side/points"


@pytest.mark.slow
def test_one_process_and_thread_gives_the_bytes_of_two(monkeypatch):
    drive = simulate_drive(DrivePlan.small(duration_s=10.0), seed=3)

    def run(threads):
        cfg = Config().replace(targetless=dict(calibration_skip_keyframes=1, calibration_min_distance_between_frames=1.0,
                                               mapper_num_threads=threads))
        return calibrate_targetless_scans(drive.scans, mapping_topic=TOP, calibration_topics=[SIDE],
                                          T_base_sensor_guess=drive.T_base_lidar_guess, base_frame="base_link",
                                          config=cfg)

    assert background._can_fork()  # the default run below forks its children (Linux)
    two = run(2)
    monkeypatch.setattr(background, "_can_fork", lambda: False)
    one = run(1)
    assert np.array_equal(one.rt_lidar0_sensor, two.rt_lidar0_sensor)
    assert np.array_equal(one.covariance_block(SIDE), two.covariance_block(SIDE))
    assert np.array_equal(one.T_base_sensor[TOP], two.T_base_sensor[TOP])
