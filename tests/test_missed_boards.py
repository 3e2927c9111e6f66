"""Why a camera found no chessboard, told from where the solve put the board: out of view,
partly outside the image, too small, or in full view (then the detector's fault or the image's)."""

from __future__ import annotations

import numpy as np

from clcgraph.api import explain_not_found
from clcgraph.frontend.camera_board import not_found_text
from clcgraph.geometry import r_from_R
from clcgraph.types import BoardGeometry, LidarBoardObservation, Problem, Rejected, Result, Sensor

# camera right-down-forward looking along lidar0's +x; f = 600 px, 1280 x 800
_R_CAM = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)
CAMERA_RT = np.r_[r_from_R(_R_CAM), 0, 0, 0]
_R_BOARD = np.array([[0, 0, -1], [1, 0, 0], [0, -1, 0]], float)  # board facing lidar0 (its z toward -x)


def _result(centres) -> Result:
    board = BoardGeometry()  # 10x10 corners of 0.1 m, 1.3 m square
    cam = Sensor("/cam", "camera", "LENSMODEL_PINHOLE", np.array([600.0, 600, 639.5, 399.5]), (1280, 800))
    sensors = (Sensor("/lidar", "lidar"), cam)
    rt_board, lidar, rejected = [], [], []
    x0, x1, y0, y1 = board.extent()
    area = np.array([[x, y, 0.0] for x in np.linspace(x0, x1, 21) for y in np.linspace(y0, y1, 21)])
    for k, c in enumerate(centres):
        # the physical board's centre at c
        rt = np.r_[r_from_R(_R_BOARD), np.asarray(c, float) - _R_BOARD @ board.centre()]
        rt_board.append(rt)
        pts = area @ _R_BOARD.T + rt[3:]
        lidar.append(LidarBoardObservation(0, k, pts, np.r_[1.0, 0, 0, 0], 0.01))
        rejected.append(Rejected(not_found_text(board), "detection", 1, k))
    rejected.append(Rejected("blurred board (edge sigma 2.1 px > 1.5)", "detection", 1, 0))
    problem = Problem(sensors, board, tuple(lidar), (), np.arange(len(centres), dtype=np.int64), tuple(rejected))
    return Result(problem, np.array([np.zeros(6), CAMERA_RT]), np.eye(6) * 1e-8, np.array(rt_board), {}, {},
                  problem.rejected)


def test_reasons_say_what_was_seen():
    # at 4 m the image spans +-640/600*4 = 4.27 m sideways: a board centred there is half in view
    res = _result([(4, 0, 0), (4, -640 / 600 * 4, 0), (-4, 0, 0), (4, 9, 0), (70, 0, 0)])
    reasons = [r.reason for r in explain_not_found(res)]
    assert reasons[0].startswith("board in view, 195 px wide") and "no full 10x10 chessboard found" in reasons[0]
    pct = float(reasons[1].split("(")[1].split(" %")[0])
    assert reasons[1].startswith("board partly outside the image") and 40 <= pct <= 60, reasons[1]
    assert reasons[2].startswith("no board in view") and reasons[3].startswith("no board in view")  # behind, beside
    # 1.3 m at 70 m: 11 px, squares ~0.9 px
    assert reasons[4].startswith("board 11 px wide: too small (squares ~0.9 px"), reasons[4]
    # a specific detector reason stays as it was
    assert reasons[5] == "blurred board (edge sigma 2.1 px > 1.5)"


def test_no_board_pose_keeps_the_detectors_reason():
    res = _result([(4, 0, 0)])
    res = Result(res.problem, res.rt_lidar0_sensor, res.covariance_rt, np.full((1, 6), np.nan), {}, {}, res.rejected)
    assert explain_not_found(res)[0].reason == "no full 10x10 chessboard found"
