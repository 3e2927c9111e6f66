"""A non-square bordered board end to end with default settings and only the board described:
7x5 inner corners of 95 mm squares on an 850 x 610 mm board, the pattern off-centre (a common
backing board). The detector follows the board (auto -> OpenCV); every sensor lands within
0.1 deg / 5 mm of the simulator's truth, and the board is repeated in calibration.yaml and the
report."""

import shutil

import numpy as np
import yaml

from clcgraph.api import load_result
from clcgraph.cli import main
from clcgraph.geometry import T_from_rt
from clcgraph.outputs.dump import load_problem
from clcgraph.sim.capture import DEMO_RIG

BOARD = {"corners": [7, 5], "square_m": 0.095, "size_m": [0.85, 0.61], "pattern_offset_m": [0.02, -0.01]}
RIG = f"""
lidars:
  - {{topic: /lidar/top, model: os1-64, layout: ouster, frame_id: top, xyz: [0, 0, 1.9], rpy_deg: [0, 0, 0]}}
  - {{topic: /lidar/front, model: hdl32, layout: velodyne, frame_id: front, xyz: [1.2, 0.3, 1.2], rpy_deg: [1, 5, 15]}}
cameras:
  - {{topic: /cam/front, model: front.cameramodel, encoding: mono8, frame_id: cam, xyz: [0.3, -0.2, 1.6],
     rpy_deg: [0, 4, -5]}}
board: {BOARD}
"""


def test_non_square_bordered_board(tmp_path, capsys):
    shutil.copy(DEMO_RIG.parent / "front.cameramodel", tmp_path / "front.cameramodel")
    (tmp_path / "rig.yaml").write_text(RIG)
    assert main(["simulate", str(tmp_path / "rig.yaml"), "--out", str(tmp_path / "bags"), "--poses", "14",
                 "--seed", "1", "--planned-tilts"]) == 0
    truth = yaml.safe_load((tmp_path / "bags" / "truth.yaml").read_text())
    assert truth["board"] == BOARD
    (tmp_path / "board.yaml").write_text(yaml.safe_dump({"board": BOARD}))
    solve = ["solve", "--bag", str(tmp_path / "bags"), "--topics", "/lidar/top,/lidar/front,/cam/front",
             str(tmp_path / "front.cameramodel"), "--config", str(tmp_path / "board.yaml")]
    capsys.readouterr()
    # naming a detector that cannot find this grid: one line, before any bag is read
    assert main(solve + ["--out", str(tmp_path / "bad"), "--detector", "mrgingham"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "mrgingham finds only square grids" in err[0] and "7x5" in err[0], err
    assert not (tmp_path / "bad").exists()

    assert main(solve + ["--out", str(tmp_path / "out")]) == 0
    cal = load_result(tmp_path / "out")
    assert cal["board"] == BOARD
    got = {s["topic"]: s for s in cal["sensors"]}
    for s in truth["sensors"]:
        T = np.linalg.inv(T_from_rt(np.asarray(s["rt_lidar0_sensor"]))) @ T_from_rt(got[s["topic"]]["rt_lidar0_sensor"])
        rot_deg = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1)))
        t_mm = 1e3 * np.linalg.norm(T[:3, 3])
        sd_deg, sd_mm = np.linalg.norm(got[s["topic"]]["stdev_orientation_deg"]), np.linalg.norm(
            got[s["topic"]]["stdev_position_mm"])
        assert rot_deg < 0.1 and t_mm < 5.0, (s["topic"], rot_deg, t_mm)
        assert rot_deg <= 4 * sd_deg + 1e-3 and t_mm <= 4 * sd_mm + 0.1, (s["topic"], rot_deg, sd_deg, t_mm, sd_mm)
    # the camera found (with OpenCV) every board the simulator saw it see
    problem, _ = load_problem(tmp_path / "out" / "problem.npz")
    visible = sum("/cam/front" in snap["corners_px"] for snap in truth["snapshots"])
    assert len(problem.camera_observations) == visible >= 5
    assert "7 x 5 inner corners, 95 mm squares, 850 x 610 mm" in (tmp_path / "out" / "report.html").read_text()
