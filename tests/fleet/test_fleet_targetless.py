"""A fleet of two vehicles, one calibrated with the board and one targetless from a 6 s drive
(fleetsim.py), the targetless one compared with its previous drive's calibration: per-sensor
pose against the simulator's truth within its sigmas, "same within uncertainty" since the
previous calibration, and "moved" from the bag's /tf_static (the simulator's guess, 2 deg and
0.2 m off the truth)."""

from __future__ import annotations

import csv
import io

import numpy as np
import pytest
import yaml

from clcgraph import geometry as geo
from clcgraph.fleet import SerialExecutor, calibrate_fleet
from fleetsim import TARGETLESS_TOPICS, TOPICS

TOP, SIDE = TARGETLESS_TOPICS


@pytest.mark.slow
def test_a_targetless_vehicle_beside_a_target_one_with_its_previous_calibration(fleet_data, drive_data, tmp_path):
    manifest = tmp_path / "fleet.yaml"
    manifest.write_text(f"""\
defaults:
  method: target
  topics: [{', '.join(TOPICS)}]
vehicles:
  - id: same
    bags: {fleet_data['same']}/*.bag
    models: [{fleet_data['model']}]
    previous: {fleet_data['previous']}
  - id: drive-again
    method: targetless
    topics: [{TOP}, {SIDE}]
    bags: {drive_data['drive-again']}/drive.bag
    previous: {drive_data['previous']}
""")
    summary = calibrate_fleet(manifest, tmp_path / "out", SerialExecutor())
    assert summary["counts"] == {"vehicles": 2, "ok": 2, "failed": 0}
    rows = {r["id"]: r for r in summary["vehicles"]}
    tl = rows["drive-again"]
    assert tl["method"] == "targetless" and tl["status"] == "ok" and tl["error"] is None
    assert rows["same"]["method"] == "target" and rows["same"]["status"] == "ok"

    # the pose of the calibrated LIDAR: within 3 of its own per-axis sigmas of the truth, sigmas useful
    side = {s["topic"]: s for s in tl["sensors"]}[SIDE]
    T = geo.T_from_rt(np.array(side["rt_lidar0_sensor"]))
    T_true = drive_data["drives"]["drive-again"].T_lidar0_lidar(SIDE, TOP)
    err = np.r_[np.degrees(geo.r_from_R(T_true[:3, :3].T @ T[:3, :3])), 1e3 * (T[:3, 3] - T_true[:3, 3])]
    sd = np.r_[side["stdev_orientation_deg"], side["stdev_position_mm"]]
    assert np.all(np.abs(err) <= 3 * sd), (err, sd)
    assert np.all(sd[:3] < 0.05) and np.all(sd[3:] < 5.0), sd
    assert {s["topic"]: s for s in tl["sensors"]}[TOP]["rt_lidar0_sensor"] == [0.0] * 6  # the reference

    # since the previous drive's calibration: nothing moved, by the chi-square test
    prev = {s["topic"]: s for s in tl["previous"]["sensors"]}[SIDE]
    assert prev["test"] == "chi-square, 6 DoF" and prev["status"] == "same" and prev["p_value"] > 0.01, prev
    assert prev["rotation_deg"] < 3 * np.sqrt(2) * np.max(sd[:3])  # two calibrations' difference
    # against the bag's /tf_static (the guess): the thresholds decide, and it is the simulator's 2 deg off
    nominal = {s["topic"]: s for s in tl["nominal"]["sensors"]}[SIDE]
    assert nominal["test"] == "thresholds" and nominal["status"] == "moved"
    assert nominal["rotation_deg"] == pytest.approx(2.0, abs=0.05)
    assert np.linalg.norm(nominal["translation_mm"]) == pytest.approx(200.0, abs=10.0)
    assert summary["changed_since_previous"] == [] and "drive-again" in summary["off_nominal"]

    out = tmp_path / "out"
    cal = yaml.safe_load((out / "drive-again" / "calibration.yaml").read_text())
    assert cal["method"] == "targetless" and cal["reference"] == TOP
    on_disk = yaml.safe_load((out / "fleet.yaml").read_text())
    assert [r["id"] for r in on_disk["vehicles"]] == ["same", "drive-again"]
    assert on_disk["vehicles"][1]["previous"]["sensors"] == tl["previous"]["sensors"]
    table = list(csv.DictReader(io.StringIO((out / "fleet.csv").read_text())))
    tl_side = next(r for r in table if r["vehicle"] == "drive-again" and r["sensor"] == SIDE)
    assert tl_side["previous_status"] == "same"
    assert "drive-again" in (out / "fleet.html").read_text()
