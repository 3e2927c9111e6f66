"""Chessboard detection (mrgingham CLI and OpenCV) against rendered truth.

Images are rendered here by an area-sampled pinhole renderer (pixel centres at
integer coordinates, mrcal's convention), so corner truth is exact.
"""

import os

import cv2
import numpy as np
import pytest

from clcgraph.config import DetectionOptions
from clcgraph.frontend.camera_board import blur_sigma_px, canonicalize, detect_corners, to_gray8
from clcgraph.types import BoardGeometry, Image

W, H, F = 1024, 768, 700.0
BOARD = BoardGeometry()  # 10x10 corners, 0.1 m
DETECTORS = ["mrgingham", "opencv"]


def render(r, t, *, blur=0.0, noise=2.0, seed=0, S=3):
    """(H,W) uint8 image of the board at rt_cam_board = (r, t), and (100,2) truth corners."""
    R, _ = cv2.Rodrigues(np.asarray(r, float))
    t = np.asarray(t, float)
    s, n = BOARD.square_m, BOARD.corners_x
    cx, cy = (W - 1) / 2, (H - 1) / 2
    off = (np.arange(S) + 0.5) / S - 0.5
    uu, vv = np.meshgrid((np.arange(W)[:, None] + off).ravel(), (np.arange(H)[:, None] + off).ravel())
    d = np.stack([(uu - cx) / F, (vv - cy) / F, np.ones_like(uu)], -1)
    lam = (R[:, 2] @ t) / (d @ R[:, 2])
    pb = (d * lam[..., None] - t) @ R
    x, y = pb[..., 0], pb[..., 1]
    black = ((np.floor(x / s) + np.floor(y / s)) % 2 == 0) & (x >= -s) & (x <= n * s) \
        & (y >= -s) & (y <= n * s)
    board = (x >= -1.5 * s) & (x <= (n + 0.5) * s) & (y >= -1.5 * s) & (y <= (n + 0.5) * s) & (lam > 0)
    val = np.where(board, 230.0, 100.0)
    val[black] = 25.0
    img = val.reshape(H, S, W, S).mean(axis=(1, 3))
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    img += np.random.default_rng(seed).normal(0, noise, img.shape)
    pc = BOARD.corners() @ R.T + t
    q = F * pc[:, :2] / pc[:, 2:] + [cx, cy]
    return np.clip(img, 0, 255).astype(np.uint8), q


def poses(k):
    rng = np.random.default_rng(k)
    return rng.normal(0, 0.3, 3), (-0.5 + rng.normal(0, 0.3), -0.45 + rng.normal(0, 0.1),
                                   2.5 + rng.normal(0, 0.4))


@pytest.fixture(scope="module")
def clean():
    out = []
    for k in range(5):
        r, t = poses(k)
        out.append(render(r, t, seed=k))
    return out


@pytest.mark.parametrize("detector", DETECTORS)
def test_clean_images_found_within_0p3px(clean, detector):
    imgs = [Image("cam", k, px, "mono8") for k, (px, _) in enumerate(clean)]
    out = detect_corners(imgs, DetectionOptions(detector=detector), BOARD)
    for o, (_, q) in zip(out, clean):
        assert isinstance(o, np.ndarray), o
        err = o - q  # same order as the board frame: the board is seen upright
        rms = np.sqrt(np.mean(np.sum(err**2, axis=1)))
        assert rms < 0.3, rms
        assert np.all(np.abs(err.mean(axis=0)) < 0.05)  # no half-pixel convention offset


@pytest.mark.parametrize("detector", DETECTORS)
def test_blurred_and_half_visible_rejected(detector):
    r, t = poses(0)
    sharp_blur, _ = render(r, t, blur=1.0)
    blurred, _ = render(r, t, blur=4.0)
    half, _ = render(r, (1.3, t[1], t[2]))  # board crosses the right image edge
    imgs = [Image("cam", i, px, "mono8") for i, px in enumerate([sharp_blur, blurred, half])]
    out = detect_corners(imgs, DetectionOptions(detector=detector), BOARD)
    assert isinstance(out[0], np.ndarray)
    assert not isinstance(out[1], np.ndarray) and "blur" in out[1].reason
    assert not isinstance(out[2], np.ndarray) and "no full" in out[2].reason


@pytest.mark.parametrize("detector", DETECTORS)
def test_colour_and_16bit(clean, detector):
    px, q = clean[1]
    bgr = np.stack([px, px // 2 + 20, px], axis=-1)  # unequal channels
    # 12-bit data in 16-bit with a few hot pixels
    m16 = px.astype(np.uint16) * 16
    m16[5, 5:20] = 65535
    imgs = [Image("cam", 0, bgr, "bgr8"), Image("cam", 1, m16, "mono16")]
    out = detect_corners(imgs, DetectionOptions(detector=detector), BOARD)
    for o in out:
        assert isinstance(o, np.ndarray), o
        assert np.sqrt(np.mean(np.sum((o - q) ** 2, axis=1))) < 0.3
    assert to_gray8(m16).max() == 255 and np.percentile(to_gray8(m16), 99) > 200


def test_rolled_board_canonical_order():
    """A board rolled by ~100 deg: ordering rotated by 90 deg so rows run left-to-right."""
    r, t = np.array([0, 0, np.pi / 2 + 0.2]), (0.4, -0.5, 2.5)
    px, q = render(r, t)
    out = detect_corners([Image("cam", 0, px, "mono8")], DetectionOptions(), BOARD)[0]
    assert isinstance(out, np.ndarray), out
    g = q.reshape(10, 10, 2)
    expected = np.swapaxes(g, 0, 1)[:, ::-1].reshape(-1, 2)  # truth, rotated by 90 deg
    assert np.sqrt(np.mean(np.sum((out - expected) ** 2, axis=1))) < 0.3
    row = out.reshape(10, 10, 2)
    assert np.all(np.diff(row[..., 0], axis=1) > 0)  # rows left-to-right
    # every rotation of the same grid canonicalizes to the same order; mirrors are undone
    for gg in [g, g[::-1, ::-1], np.swapaxes(g, 0, 1)[::-1], g[:, ::-1]]:
        assert np.allclose(canonicalize(gg.reshape(-1, 2), 10, 10), out, atol=0.5)


def test_irregular_grid_rejected(clean):
    from clcgraph.frontend.camera_board import check_grid

    q = clean[0][1].copy()
    assert check_grid(q, 10, 10, (W, H), max_irregularity=0.5) is None
    q[44] += [8.0, 0.0]  # a corner jumping most of a cell
    assert "irregular" in check_grid(q, 10, 10, (W, H), max_irregularity=0.5)
    q2 = clean[0][1].copy()
    q2[[44, 45]] = q2[[45, 44]]  # swapped neighbours fold the grid
    assert check_grid(q2, 10, 10, (W, H), max_irregularity=0.5) is not None


def test_blur_estimate_tracks_truth(clean):
    r, t = poses(2)
    for sigma in (1.5, 3.0):
        px, q = render(r, t, blur=sigma, noise=0.5)
        est = blur_sigma_px(px, q, 10, 10)
        # ideal area-sampled step reads ~0.5 px, adding in quadrature
        assert abs(est - np.hypot(sigma, 0.5)) < 0.25 * sigma, (sigma, est)


def test_cli_detect(tmp_path, clean, capsys):
    from clcgraph.cli import main
    from clcgraph.sim.bag_writer import BagWriter

    r, t = poses(0)
    half, _ = render(r, (1.3, t[1], t[2]))
    bags = []
    for i, px in enumerate([clean[0][0], half]):
        p = tmp_path / f"b{i}.bag"
        with BagWriter(p) as w:
            w.write_image("/cam0", Image("/cam0", 10**18 + i, px, "mono8"), frame_id="cam0")
        bags.append(str(p))
    rc = main(["detect", *bags, "--topic", "/cam0", "--png", str(tmp_path / "png"), "--detector", "opencv"])
    out = capsys.readouterr().out
    assert rc == 0
    assert "found 100 corners" in out and "rejected: no full 10x10 chessboard" in out
    assert "1/2 images with a chessboard" in out
    assert len(list((tmp_path / "png").glob("*.png"))) == 2


def test_detector_follows_the_board(monkeypatch):
    """auto: mrgingham for a square grid, OpenCV for a non-square one (mrgingham finds only NxN
    grids) or when mrgingham is not installed; a named detector is used as named, and naming
    mrgingham for a non-square board is a one-line InputError."""
    from clcgraph.errors import InputError
    from clcgraph.frontend import camera_board

    nonsquare = BoardGeometry.from_spec(corners=[7, 5], square_m=0.095, size_m=[0.85, 0.61])
    assert camera_board.choose_detector(DetectionOptions(), BOARD) == "mrgingham"
    assert camera_board.choose_detector(DetectionOptions(), nonsquare) == "opencv"
    assert camera_board.choose_detector(DetectionOptions(detector="opencv"), BOARD) == "opencv"
    with pytest.raises(InputError, match=r"^detection.detector: mrgingham finds only square grids, the board has "
                                         r"7x5 inner corners: use detector auto or opencv$"):
        camera_board.choose_detector(DetectionOptions(detector="mrgingham"), nonsquare)
    monkeypatch.setattr(camera_board.shutil, "which", lambda name: None)
    assert camera_board.choose_detector(DetectionOptions(), BOARD) == "opencv"


def _cut_off_board():
    """A simulated image (clcgraph.sim) of a bordered 10x10 board whose last column of squares lies
    beyond the image's right edge (stress capture noisy-lidars, seed 8, snapshot 0), its truth corners."""
    from clcgraph.geometry import T_from_rt
    from clcgraph.sim.camera import render as sim_render
    from clcgraph.sim.scene import make_scene
    from clcgraph.types import Sensor

    camera = Sensor(topic="/cam", kind="camera", lensmodel="LENSMODEL_OPENCV8", imagersize=(1024, 768),
                    intrinsics=np.array([1000, 1000, 511.5, 383.5, -0.05, 0.01, 1e-4, -1e-4, 1e-3, 0, 0, 0]))
    T_lidar0_camera = T_from_rt(np.array([-1.2158, 1.3268, -1.2373, 0.6, -0.2, -0.4]))
    T_lidar0_board = T_from_rt(np.array([-0.9137, 1.6249, -1.2273, 3.6809, -1.2279, -0.4162]))
    rng = np.random.default_rng(1)
    scene = make_scene(BOARD, T_lidar0_board, rng, clutter=False, person=False)
    image, q = sim_render(camera, T_lidar0_camera, scene, BOARD, T_lidar0_board, rng)
    return image, q


def test_board_cut_off_by_the_image_edge_is_not_read_as_whole():
    """OpenCV's sector-based detector reads this board as whole, one square off: its left column
    of corners on the pattern's edge against the white border. That grid is rejected (by either
    detector setting), naming why; the squares' alternation along a side is what tells it."""
    from clcgraph.frontend.camera_board import off_board_side

    image, q = _cut_off_board()
    assert q[:, 0].max() > 1023  # the true last column is beyond the image
    found, c = cv2.findChessboardCornersSB(image.pixels, (10, 10))
    assert found  # what this test guards against: a grid where there is none whole
    grid = canonicalize(c.reshape(-1, 2).astype(float), 10, 10)
    off = grid.reshape(10, 10, 2) - q.reshape(10, 10, 2)[:, [0, *range(9)]]  # truth shifted one column
    assert np.sqrt(np.mean(np.sum((grid - q) ** 2, axis=1))) > 30 and np.abs(off[:, 1:]).max() < 1.0
    assert off_board_side(image.pixels, grid, 10, 10) == "left column"
    out = {d: detect_corners([image], DetectionOptions(detector=d), BOARD)[0] for d in ("opencv", "auto")}
    assert not any(isinstance(o, np.ndarray) for o in out.values()), out
    assert "cut off by the image's edge" in out["opencv"].reason and "left column" in out["opencv"].reason


def test_a_side_hidden_in_view_keeps_its_board(clean):
    """The same lack of alternation along a side, made by something in front of the board's edge,
    keeps a board whose other side's outer squares are in the image (the pattern cannot go on
    past the image there); cropped so they are not, it is the cut-off board above."""
    from clcgraph.frontend.camera_board import off_board_side, side_without_corners

    px, q = clean[0]
    assert off_board_side(px, q, 10, 10) is None
    g = q.reshape(10, 10, 2)
    step = g[:, 0] - g[:, 1]  # outward, per row
    hidden = px.copy()
    polygon = np.r_[g[3:, 0] + 0.3 * step[3:], (g[3:, 0] + 1.6 * step[3:])[::-1]].astype(np.int32)
    cv2.fillPoly(hidden, [polygon], 160)  # a grey arm over 7 of the 11 outer squares on the left
    assert off_board_side(hidden, q, 10, 10) is None
    assert side_without_corners(hidden, q, 10, 10) is None  # 3 of its 10 corners are still corners
    right = int(np.ceil(g[:, -1, 0].max())) + 3  # the image ends just past the right column of corners
    assert off_board_side(hidden[:, :right], q, 10, 10) == "left column"


@pytest.mark.parametrize("shift, width, expected", [
    ((5000, 0), 300, "no board in view"),
    ((1023, 767), 300, "board partly outside the image (< 1 % of"),   # one point of 400 in
    ((1024 - 150, 0), 300, "board partly outside the image (50 % of"),
    ((400, 300), 40, "board 40 px wide: too small (squares ~3.1 px"),
    ((400, 300), 300, "board in view, 300 px wide (squares ~23 px"),
])
def test_why_a_board_was_not_found(shift, width, expected):
    """The reason a camera found no board, from where the solved poses put it (the 1.3 m board's
    points, a grid 20 x 20, projected)."""
    from clcgraph.frontend.camera_board import not_found_reason

    u, v = np.meshgrid(np.linspace(0, width, 20), np.linspace(0, width, 20))
    q = np.c_[u.ravel(), v.ravel()] + shift
    assert not_found_reason(q, (W, H), BOARD, what="its LIDAR points").startswith(expected)


def test_a_part_of_a_larger_pattern_is_not_read_as_the_board(clean):
    """board.corners set short (9x9 for this 10x10 pattern, whose white border is half a square):
    a detector may return a 9x9 part of the pattern (mrgingham did, on one of 24 images of the
    bench capture), each corner then a square from the one it is taken for. Whichever 9x9 part,
    the pattern going on past one of its sides rejects it; the whole 10x10 grid passes."""
    from clcgraph.frontend.camera_board import _validate, pattern_goes_on

    options = DetectionOptions()
    for px, q in clean:
        full = q.reshape(10, 10, 2)
        assert pattern_goes_on(px, q, 10, 10) is None
        assert isinstance(_validate(q, px, 10, 10, options, "none"), np.ndarray)
        for i0, j0 in ((0, 0), (0, 1), (1, 0), (1, 1)):
            part = full[i0:i0 + 9, j0:j0 + 9].reshape(-1, 2)
            r = _validate(part, px, 9, 9, options, "none")
            assert not isinstance(r, np.ndarray) and "goes on past the grid's" in r.reason, (i0, j0, r)


@pytest.mark.parametrize("declared", [9, 11])
def test_a_wrong_corner_count_is_answered_with_the_count_the_images_show(clean, declared):
    """board.corners off by one or two (squares counted for corners, or a miscount): no image has
    the declared grid, and the images show the board's whole 10x10 one, which is what to set."""
    from clcgraph.frontend.camera_board import BoardDetection

    imgs = [Image("/cam", k, px, "mono8") for k, (px, _) in enumerate(clean)]
    wrong = BoardGeometry.from_spec(corners=[declared, declared], square_m=0.1, size_m=[1.6, 1.6])
    d = BoardDetection(imgs, DetectionOptions(), wrong)
    assert not any(isinstance(r, np.ndarray) for r in d.results)
    assert d.grid_shown_instead() == (10, ["/cam"] * 5, 5)
    assert BoardDetection(imgs, DetectionOptions(), BOARD).grid_shown_instead() is None  # found: nothing to say
    blank = [Image("/cam", k, np.full((H, W), 128, np.uint8), "mono8") for k in range(3)]
    assert BoardDetection(blank, DetectionOptions(), BOARD).grid_shown_instead() is None  # no board at all
    # the solve's first pass stops there, in one line naming the camera and the count to set
    from clcgraph.api import _first_detection_pass
    from clcgraph.errors import InputError

    with pytest.raises(InputError, match=rf"^/cam: its images show a whole 10x10 grid of inner corners \(5 of the 5 "
                                         rf"images checked\), none the {declared}x{declared} of board.corners: set "
                                         r"board.corners: \[10, 10\]"):
        _first_detection_pass(imgs, DetectionOptions(), wrong, None)


def test_a_grid_with_a_row_along_the_patterns_edge_is_rejected(clean):
    """board.corners one too many: OpenCV's sector-based detector completed a 9x6 board's grid to
    10x6 with a column along the pattern's edge, where its outer squares meet the white border (2
    of 16 simulated images). Such a row has no corner along it: rejected, naming the count; the
    board's own grid passes."""
    from clcgraph.frontend.camera_board import PATTERN_ENDS, _validate, side_without_corners

    for px, q in clean:
        g = q.reshape(10, 10, 2)
        edge = 2 * g[0] - g[1]  # a step out from the top row: the pattern's top edge (its outer squares end there)
        grid = np.concatenate([edge[None], g]).reshape(-1, 2)  # 10 wide, 11 high
        assert side_without_corners(px, q, 10, 10) is None
        assert side_without_corners(px, grid, 10, 11) in ("top row", "bottom row")
        r = _validate(grid, px, 10, 11, DetectionOptions(), "none")
        assert not isinstance(r, np.ndarray) and r.reason.startswith(PATTERN_ENDS), r


def test_mrgingham_images_go_to_the_users_tmpdir_when_set(clean, monkeypatch, tmp_path):
    """TMPDIR set: the scratch images go there (and leave nothing behind), not to /dev/shm."""
    from clcgraph.frontend import camera_board

    seen = []
    real = camera_board.tempfile.TemporaryDirectory

    def spy(*args, **kwargs):
        d = real(*args, **kwargs)
        seen.append(os.path.dirname(d.name))
        return d

    monkeypatch.setattr(camera_board.tempfile, "TemporaryDirectory", spy)
    monkeypatch.setattr(camera_board.tempfile, "tempdir", None)  # tempfile's choice made again, from TMPDIR
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    out = detect_corners([Image("cam", 0, clean[0][0], "mono8")], DetectionOptions(detector="mrgingham"), BOARD)
    assert isinstance(out[0], np.ndarray) and seen == [str(tmp_path)] and not list(tmp_path.iterdir())
    monkeypatch.setenv("TMPDIR", str(tmp_path / "missing"))  # unusable: tempfile's fallback, no failure
    monkeypatch.setattr(camera_board.tempfile, "tempdir", None)
    assert isinstance(detect_corners([Image("cam", 0, clean[0][0], "mono8")], DetectionOptions(detector="mrgingham"),
                                     BOARD)[0], np.ndarray)
    monkeypatch.delenv("TMPDIR")
    assert camera_board._scratch_dir() == ("/dev/shm" if os.access("/dev/shm", os.W_OK) else None)
