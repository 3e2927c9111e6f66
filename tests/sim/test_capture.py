"""The simulated demo session is what the pipeline needs: every LIDAR scan shows the board
on the rings that geometry says cross it, and the detector finds every visible chessboard to
< 0.3 px RMS of the projected truth; bad rig files are one-line errors."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from clcgraph.config import DetectionOptions
from clcgraph.errors import InputError
from clcgraph.frontend.bag import first_messages
from clcgraph.frontend.camera_board import detect_corners
from clcgraph.geometry import T_from_rt
from clcgraph.sim.capture import DEMO_RIG, simulate
from clcgraph.sim.rig import load_rig


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "bags"
    truth = simulate(DEMO_RIG, out, n_poses=5, seed=7)
    return out, truth, load_rig(DEMO_RIG)


def _board_outline(board, n=200):
    xmin, xmax, ymin, ymax = board.extent()
    t = np.linspace(0, 1, n)
    edges = [np.c_[xmin + (xmax - xmin) * t, np.full(n, y)] for y in (ymin, ymax)]
    edges += [np.c_[np.full(n, x), ymin + (ymax - ymin) * t] for x in (xmin, xmax)]
    return np.c_[np.concatenate(edges), np.zeros(4 * n)]


def test_board_on_the_expected_rings(session):
    out, truth, rig = session
    sensors = {s["topic"]: s for s in truth["sensors"]}
    checked = 0
    for snap in truth["snapshots"]:
        for L in rig.lidars:
            scan = first_messages(out / snap["bag"], [L.topic])[L.topic]
            T = np.linalg.inv(T_from_rt(np.asarray(sensors[L.topic]["rt_lidar0_sensor"]))) @ \
                T_from_rt(np.asarray(snap["rt_lidar0_board"]))
            # rings whose elevation lies within the board's outline, as seen from the LIDAR
            p = _board_outline(rig.board) @ T[:3, :3].T + T[:3, 3]
            el = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
            ring_el = np.asarray(L.model.elevations_deg)
            expected = set(np.flatnonzero((ring_el > el.min() + 0.05) & (ring_el < el.max() - 0.05)))
            # returns on the board: on its plane and inside its rectangle
            q = (scan.points[scan.valid] - T[:3, 3]) @ T[:3, :3]
            xmin, xmax, ymin, ymax = rig.board.extent()
            on = (np.abs(q[:, 2]) < 0.05) & (q[:, 0] > xmin) & (q[:, 0] < xmax) & (q[:, 1] > ymin) & (q[:, 1] < ymax)
            seen = set(np.unique(scan.ring[scan.valid][on]))
            if snap["seen_by"] >= 2 and len(expected) >= 3:
                # a car or the person may hide a ring's part of the board, never add one
                assert seen <= expected | {min(expected) - 1, max(expected) + 1}, (snap["bag"], L.topic)
                assert len(seen) >= len(expected) - 1, (snap["bag"], L.topic, sorted(seen), sorted(expected))
                checked += 1
    assert checked >= 5


@pytest.mark.parametrize("fallback", [False, True], ids=["mrgingham", "mrgingham+opencv"])
def test_visible_chessboards_found_within_0p3px(session, fallback):
    out, truth, rig = session
    found = missed = 0
    for snap in truth["snapshots"]:
        for topic, corners in snap["corners_px"].items():
            im = first_messages(out / snap["bag"], [topic])[topic]
            r = detect_corners([im], DetectionOptions(fallback_opencv=fallback), rig.board)[0]
            if not isinstance(r, np.ndarray):
                missed += 1
                continue
            found += 1
            assert r.shape == (100, 2)
            assert np.sqrt(((r - np.asarray(corners)) ** 2).sum(axis=1).mean()) < 0.3, (snap["bag"], topic)
    # mrgingham (which retries small boards upsampled) finds every visible board here
    assert missed == 0 and found >= 3


def test_a_raw_bayer_mosaic_reads_back_and_its_corners_are_found_within_0p3px(session):
    """A camera publishing its raw mosaic (sim.camera.bayer_mosaic: red and blue at their raw
    response, half of green) as a machine-vision driver does: the reader demosaics it and the
    detector finds the same corners as in the colour image."""
    import cv2

    from clcgraph.frontend.images import decode_image
    from clcgraph.sim.camera import BAYER_ENCODINGS, bayer_mosaic

    out, truth, rig = session
    snap, topic, corners = next((s, t, c) for s in truth["snapshots"] for t, c in s["corners_px"].items())
    im = first_messages(out / snap["bag"], [topic])[topic]
    bgr = cv2.cvtColor(im.pixels, cv2.COLOR_GRAY2BGR) if im.pixels.ndim == 2 else im.pixels
    colour = dataclasses.replace(im, pixels=bgr, encoding="bgr8")
    for enc in BAYER_ENCODINGS:
        raw = bayer_mosaic(colour, enc)
        assert raw.pixels.shape == bgr.shape[:2] and raw.encoding == enc
        msg = SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(sec=1, nanosec=0)), encoding=enc,
                              height=raw.pixels.shape[0], width=raw.pixels.shape[1], step=raw.pixels.shape[1],
                              is_bigendian=0, data=raw.pixels.ravel())
        back = decode_image(msg, topic=topic)
        # demosaiced: each channel at its raw gain of the scene (a flat region keeps its ratios)
        assert back.pixels.shape == bgr.shape
        g = back.pixels[..., 1].astype(float)
        bright = g > 150
        ratio = back.pixels[..., 2][bright].mean() / g[bright].mean()
        assert 0.45 < ratio < 0.55, (enc, ratio)  # red at half of green (blue: 0.6): each filter where it belongs
        r = detect_corners([back], DetectionOptions(), rig.board)[0]
        assert isinstance(r, np.ndarray), (enc, r)
        assert np.sqrt(((r - np.asarray(corners)) ** 2).sum(axis=1).mean()) < 0.3, enc


def test_rig_errors_name_the_file(tmp_path):
    bad = tmp_path / "rig.yaml"
    bad.write_text(yaml.safe_dump({"lidars": [{"topic": "/l", "model": "hdl64-unknown", "xyz": [0, 0, 1],
                                               "rpy_deg": [0, 0, 0]}], "cameras": []}))
    with pytest.raises(InputError, match="rig.yaml"):
        load_rig(bad)
    bad.write_text("lidars: [")
    with pytest.raises(InputError, match="rig.yaml"):
        load_rig(bad)


def test_continuous_capture_15hz_camera_free_running_and_logged_like_drivers(tmp_path):
    """Cameras at 15 Hz (not a divisor of the LIDARs' 10 Hz) run on their own clock through holds
    and moves; log times follow the drivers' delays (a scan ~0.1 s after its stamp, a frame 20-35 ms)."""
    import mrcal

    from clcgraph.frontend.bag import _Bag, _stamp

    mrcal.cameramodel(intrinsics=("LENSMODEL_PINHOLE", np.array([30.0, 30.0, 31.5, 23.5])),
                      imagersize=np.array([64, 48])).write(str(tmp_path / "tiny.cameramodel"))
    rig = tmp_path / "rig.yaml"
    rig.write_text("""
lidars:
  - {topic: /a, model: vlp16, layout: velodyne, frame_id: a, xyz: [0, 0, 1.9], rpy_deg: [0, 0, 0]}
  - {topic: /b, model: vlp16, layout: ouster, frame_id: b, xyz: [1.0, 0.3, 1.5], rpy_deg: [0, 3, 10]}
cameras:
  - {topic: /cam, model: tiny.cameramodel, encoding: mono8, frame_id: cam, xyz: [0.5, 0, 1.5], rpy_deg: [0, 0, 0]}
board: {corners: [10, 10], square_m: 0.1, size_m: [1.3, 1.3]}
""")
    simulate(rig, tmp_path / "s", n_poses=2, seed=1, continuous=True, hold_s=1.0, move_s=0.5, camera_hz=15.0,
             clutter=False)
    with _Bag(tmp_path / "s" / "session.bag") as b:
        msgs = [(c.topic, t, _stamp(m, t)) for c, _, t, m in b.raw(b.connections(["/a", "/b", "/cam"]))]
    cam = np.array(sorted(s for topic, _, s in msgs if topic == "/cam"))
    assert len(cam) == pytest.approx(15 * 2.5, abs=1)  # 2 holds + 1 move
    assert np.allclose(np.diff(cam), 1e9 / 15, atol=2)  # one clock, no restart at each pose
    delay = {t: np.array([lt - s for topic, lt, s in msgs if topic == t]) * 1e-9 for t in ("/a", "/b", "/cam")}
    assert np.all((delay["/cam"] >= 0.020) & (delay["/cam"] <= 0.035))
    for t in ("/a", "/b"):
        assert np.all((delay[t] >= 0.1) & (delay[t] <= 0.112)), t
    stamps = [s for _, _, s in msgs]
    assert stamps != sorted(stamps)  # log order (as read) differs from stamp order across topics


def test_planned_tilts_pitch_boards_up_and_down():
    """A careful capture plan holds boards pitched up and boards pitched down (a LIDAR's height
    relative to another sensor comes from pitched boards only); the first board stands where the
    seed's random capture puts it (the plan changes the tilt, not the draws; later boards differ,
    as the noise draws follow the points each sensor sees)."""
    from clcgraph.geometry import R_from_r
    from clcgraph.sim.observations import make_rig, simulate_problem
    from clcgraph.types import BoardGeometry

    rig = make_rig(1, 1)
    _, planned = simulate_problem(rig=rig, n_snapshots=12, seed=4, planned_tilts=True)
    _, random = simulate_problem(rig=rig, n_snapshots=12, seed=4)
    nz = np.array([R_from_r(b[:3])[2, 2] for b in planned.rt_lidar0_board])
    assert (nz > 0.3).sum() >= 3 and (nz < -0.3).sum() >= 3, nz
    xmin, xmax, ymin, ymax = BoardGeometry().extent()
    centre = np.array([(xmin + xmax) / 2, (ymin + ymax) / 2, 0.0])
    at = [[R_from_r(b[:3]) @ centre + b[3:] for b in t.rt_lidar0_board] for t in (planned, random)]
    np.testing.assert_allclose(at[0][0], at[1][0], atol=1e-9)
    assert not np.allclose(planned.rt_lidar0_board[0], random.rt_lidar0_board[0])


def test_pair_boards_shows_the_board_to_every_pair_that_can_see_it(tmp_path):
    """``pair_boards`` records as the README asks: every pair of sensors sees the board together
    on that many poses; a pair that can never (cameras back to back) is left out, not a failure."""
    import itertools

    import mrcal

    mrcal.cameramodel(intrinsics=("LENSMODEL_PINHOLE", np.array([30.0, 30.0, 31.5, 23.5])),
                      imagersize=np.array([64, 48])).write(str(tmp_path / "tiny.cameramodel"))
    rig = tmp_path / "rig.yaml"
    rig.write_text("""
lidars:
  - {topic: /l, model: vlp16, frame_id: l, xyz: [0, 0, 1.9], rpy_deg: [0, 0, 0]}
cameras:
  - {topic: /front, model: tiny.cameramodel, encoding: mono8, frame_id: f, xyz: [0.5, 0, 1.5], rpy_deg: [0, 0, 0]}
  - {topic: /left, model: tiny.cameramodel, encoding: mono8, frame_id: s, xyz: [0.5, 0.2, 1.5], rpy_deg: [0, 0, 40]}
  - {topic: /rear, model: tiny.cameramodel, encoding: mono8, frame_id: r, xyz: [-0.5, 0, 1.5], rpy_deg: [0, 0, 180]}
board: {corners: [10, 10], square_m: 0.1, size_m: [1.3, 1.3]}
""")
    truth = simulate(rig, tmp_path / "s", n_poses=8, seed=2, clutter=False, pair_boards=2)
    seen = [set(s["seen_by_topics"]) for s in truth["snapshots"]]
    for s in truth["snapshots"]:  # the record agrees with the corners it keeps
        assert set(s["corners_px"]) == set(s["seen_by_topics"]) - {"/l"}
    together = {p: sum(set(p) <= s for s in seen) for p in itertools.combinations(["/l", "/front", "/left", "/rear"], 2)}
    for p in [("/l", "/front"), ("/l", "/left"), ("/l", "/rear"), ("/front", "/left")]:
        assert together[p] >= 2, together
    assert together[("/front", "/rear")] == together[("/left", "/rear")] == 0


def test_boards_on_ground_rest_a_corner_on_it_and_the_bumper_lidar_sees_them(tmp_path):
    """``boards_on_ground``: every board's lowest corner touches the ground (2 mm above it), where
    the simulator otherwise keeps boards >= 0.15 m above it; the scans show them."""
    rig = tmp_path / "rig.yaml"
    rig.write_text("""
lidars:
  - {topic: /roof, model: vlp16, frame_id: r, xyz: [0, 0, 1.9], rpy_deg: [0, 0, 0]}
  - {topic: /bumper, model: vlp16, frame_id: b, xyz: [1.5, 0, 0.6], rpy_deg: [0, 0, 0]}
board: {corners: [10, 10], square_m: 0.1, size_m: [1.3, 1.3]}
""")
    truth = simulate(rig, tmp_path / "s", n_poses=4, seed=3, clutter=False, boards_on_ground=True)
    r = load_rig(rig)
    x0, x1, y0, y1 = r.board.extent()
    corners = np.array([[x, y, 0.0, 1.0] for x in (x0, x1) for y in (y0, y1)])
    for s in truth["snapshots"]:
        T = r.lidars[0].T_base_sensor @ T_from_rt(np.array(s["rt_lidar0_board"]))
        assert (corners @ T.T)[:, 2].min() == pytest.approx(0.002, abs=1e-9)
    assert sum("/bumper" in s["seen_by_topics"] for s in truth["snapshots"]) >= 3


def test_a_counter_clockwise_lidar_fires_its_columns_with_rising_azimuth():
    """``clockwise: false``: the same rays, fired in the other order (time still rises along a ring)."""
    from clcgraph.sim.lidar import LidarModel

    cw = LidarModel.preset("vlp16")
    ccw = dataclasses.replace(cw, clockwise=False)
    az_cw, az_ccw = (np.unwrap(np.arctan2(m.directions()[0, :, 1], m.directions()[0, :, 0])) for m in (cw, ccw))
    step = 2 * np.pi / cw.npoints_per_rotation
    np.testing.assert_allclose(np.diff(az_cw), -step)
    np.testing.assert_allclose(np.diff(az_ccw), step)
    assert np.allclose(np.sort(np.mod(az_cw, 2 * np.pi)), np.sort(np.mod(az_ccw, 2 * np.pi)))
