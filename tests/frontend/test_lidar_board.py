"""LIDAR board segmentation on simulated sessions: a calibration site (walls 12-25 m, parked
cars, poles, crates), a person holding the board (by default 10x10 corners of 0.1 m squares on
a 1.3 m square board: the pattern with a 0.1 m white border) at 2-12 m with tilts up to 45 deg,
and one scan in eight without a board. Detection, false positives and normal accuracy are
measured against the ray caster's truth."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from clcgraph.config import LidarOptions, SegmentationOptions
from clcgraph.frontend.lidar_board import Debug, segment_board, segment_many
from clcgraph.sim.lidar import LidarModel, simulate_scan
from clcgraph.sim.scene import make_scene, random_board_pose, static_meshes
from clcgraph.types import BoardGeometry, LidarBoardObservation, LidarScan, Rejected

BOARD = BoardGeometry()
T_LIDAR = np.eye(4)
T_LIDAR[2, 3] = 1.8  # on a vehicle roof


def session(model: str, n: int, seed: int, board: BoardGeometry = BOARD, person: bool = True):
    """n scans of one site: (scans, board-hit masks, T_world_board or None)."""
    rng = np.random.default_rng(seed)
    L = LidarModel.preset(model)
    static = static_meshes(rng)
    scans, hits, poses = [], [], []
    for k in range(n):
        Tb = None if k % 8 == 7 else random_board_pose(rng, board, T_LIDAR[:3, 3], distance_m=(2, 12), tilt_max_deg=45)
        scan, hit = simulate_scan(L, T_LIDAR, make_scene(board, Tb, rng, static=static, person=person), rng, topic="/lidar")
        scans.append(scan)
        hits.append(hit)
        poses.append(Tb)
    return scans, hits, poses


def _cut(scan, hit) -> bool:
    """Whether something in front (a pole) cuts the board: a ring's board returns (ray-caster
    truth) break off for more than 3 azimuth steps."""
    az, ring = np.arctan2(scan.points[hit, 1], scan.points[hit, 0]), scan.ring[hit]
    step = 2 * np.pi * (scan.ring.max() + 1) / len(scan.points)  # points per ring and rotation
    for r in np.unique(ring):
        a = az[ring == r]
        a = np.sort((a - np.arctan2(np.sin(a).mean(), np.cos(a).mean()) + np.pi) % (2 * np.pi))
        if len(a) > 1 and np.diff(a).max() > 3.5 * step:
            return True
    return False


def score(scans, hits, poses, results):
    """(detected, eligible, false positives, normal errors in deg, (detected, eligible) of boards
    cut by something in front). Eligible: >= 3 rings cross the board with at least a segment's
    worth (8) of points each, and nothing in front cuts it (such boards are counted apart: the
    segmentation keeps one unbroken piece per ring, and a board cut in two may then look like a
    post)."""
    detected = eligible = false = 0
    cut = np.zeros(2, int)
    errors = []
    for scan, hit, Tb, r in zip(scans, hits, poses, results):
        per_ring = np.bincount(scan.ring[hit]) if hit.any() else np.zeros(1, int)
        ok = isinstance(r, LidarBoardObservation)
        if ok:
            if hit[r.indices].mean() < 0.5:  # mostly not the board: a wrong plane
                false += 1
                continue
            n_true = T_LIDAR[:3, :3].T @ Tb[:3, 2]
            errors.append(np.degrees(np.arccos(min(1.0, abs(n_true @ r.plane[:3])))))
        if (per_ring >= 8).sum() >= 3:
            if _cut(scan, hit):
                cut += (ok, 1)
            else:
                eligible += 1
                detected += ok
    return detected, eligible, false, np.array(errors), cut


@pytest.mark.parametrize("seeds", [(3, 4, 5), (6, 7, 8)])
def test_board_found_never_a_wrong_plane(seeds):
    """VLP-16, HDL-32 and OS1-128 sessions (120 scans per seed set, 240 in all): >= 95% of the
    uncut boards crossed by >= 3 rings are found, no wrong plane is accepted, normals within
    0.5 deg (95th percentile; a board with a hand-sized patch of the body next to it may reach
    1.5 deg). Boards cut by a pole in front (~1 in 10 here) are found about 60% of the time."""
    totals = np.zeros(3, int)
    errors = []
    for model, n, seed in zip(("vlp16", "hdl32", "os1-128"), (48, 48, 24), seeds):
        scans, hits, poses = session(model, n, seed)
        results = segment_many(scans, SegmentationOptions(), LidarOptions(), BOARD, jobs=1)
        d, e, f, err, _ = score(scans, hits, poses, results)
        assert f == 0, f"{model}: {f} wrong planes accepted"
        assert d >= 0.9 * e, f"{model}: found {d} of {e} boards"
        totals += (d, e, f)
        errors.append(err)
        # a scan without a board is rejected with a reason, never an exception
        for r, Tb in zip(results, poses):
            if Tb is None:
                assert isinstance(r, Rejected) and r.reason and r.stage == "segmentation"
    err = np.concatenate(errors)
    assert totals[0] >= 0.95 * totals[1], f"found {totals[0]} of {totals[1]}"
    assert np.percentile(err, 95) < 0.5 and err.max() < 1.5, np.sort(err)[-5:]


def test_board_size_is_the_physical_board():
    """Scans of a bordered 1.3 m board: described as the physical board they are accepted; described
    by the pattern's corners plus a 0.1 m margin (1.1 m, the old margin_m reading of the same board)
    many are rejected as larger than the board. A non-square board (7x5 corners of 95 mm squares on
    850 x 610 mm, pattern off-centre) is found like a square one, in any roll."""
    scans, hits, poses = session("vlp16", 40, 12)
    right = segment_many(scans, SegmentationOptions(), LidarOptions(), BOARD, jobs=1)
    d, e, f, _, _ = score(scans, hits, poses, right)
    assert f == 0 and d >= 0.95 * e, (d, e, f)
    small = BoardGeometry(10, 10, 0.1, 1.1, 1.1)
    wrong = segment_many(scans, SegmentationOptions(), LidarOptions(), small, jobs=1)
    d_wrong, e_wrong, _, _, _ = score(scans, hits, poses, wrong)
    too_big = [r for r in wrong if isinstance(r, Rejected) and "outside any 1.10 x 1.10 m rectangle" in r.reason]
    assert d_wrong <= 0.8 * e_wrong and len(too_big) >= 0.2 * e_wrong, (d_wrong, e_wrong, len(too_big))
    # and each says what it measures: the true board's 1.3 m (a board the rings cross only in part, less)
    sides = np.array([re.search(r" m, ([\d.]+) x ([\d.]+) m \(", r.reason).groups() for r in too_big], float)
    assert np.all(np.abs(np.median(sides, axis=0) - 1.3) < 0.04), sides

    # (without the person: with one standing 0.5 m behind a board this small, a tilted board's
    # plane meets the body just beyond its edge, which the rectangle check rejects in ~1 of 5 scans)
    board = BoardGeometry.from_spec(corners=[7, 5], square_m=0.095, size_m=[0.85, 0.61], pattern_offset_m=[0.02, -0.01])
    scans, hits, poses = session("hdl32", 40, 13, board, person=False)
    res = segment_many(scans, SegmentationOptions(), LidarOptions(), board, jobs=1)
    d, e, f, _, _ = score(scans, hits, poses, res)
    assert f == 0 and d >= 0.9 * e and e >= 10, (d, e, f)


def test_ouster_organised_and_ringless_clouds():
    """An organised OS1-64 cloud (invalid returns as zeros) and the same cloud without its ring
    field (rings from elevation angles) give the same board. (One scan, so no static-scene
    suppression: the site without its clutter, whose car cabin ends, 1.6 x 0.6 m, pass as
    pieces of a 1.3 m board in a lone scan; sessions remove them, see the tests above.)"""
    rng = np.random.default_rng(11)
    L = LidarModel.preset("os1-64")
    Tb = random_board_pose(rng, BOARD, T_LIDAR[:3, 3], distance_m=(4, 6), tilt_max_deg=30)
    scan, hit = simulate_scan(L, T_LIDAR, make_scene(BOARD, Tb, rng, clutter=False), rng, topic="/os")
    assert scan.shape == (64, 2048) and not scan.valid.all()
    ringless = LidarScan(scan.topic, scan.stamp_ns, scan.points, scan.valid, None, None, None, scan.shape)
    a = segment_board(scan, SegmentationOptions(), LidarOptions(), BOARD)
    b = segment_board(ringless, SegmentationOptions(), LidarOptions(), BOARD)
    for r in (a, b):
        assert isinstance(r, LidarBoardObservation), getattr(r, "reason", "")
        assert hit[r.indices].mean() > 0.95 and r.indices.size > 0.8 * hit.sum()
    assert np.degrees(np.arccos(min(1.0, abs(a.plane[:3] @ b.plane[:3])))) < 0.1
    assert a.plane[3] < 0  # normal toward the sensor


def test_debug_records_every_stage():
    scans, hits, _ = session("vlp16", 2, 21)
    dbg = Debug()
    r = segment_board(scans[0], SegmentationOptions(), LidarOptions(), BOARD, debug=dbg)
    assert dbg.segments.shape[1:] == (2, 3) and len(dbg.segment_rank) == len(dbg.segments)
    assert dbg.clusters and dbg.candidates
    if isinstance(r, LidarBoardObservation):
        assert np.array_equal(dbg.accepted, r.indices)


def test_nothing_to_find():
    empty = LidarScan("/l", 0, np.zeros((10, 3)), np.zeros(10, bool))
    r = segment_board(empty, SegmentationOptions(), LidarOptions(), BOARD, sensor=2, snapshot=5)
    assert isinstance(r, Rejected) and (r.sensor, r.snapshot) == (2, 5) and "/l" in r.reason
    assert segment_many([], SegmentationOptions(), LidarOptions(), BOARD) == []


def _board_scan(seed: int, extra_noise_m: float, bow_m: float):
    """An OS1-64 scan (5 mm range noise) of a board at 4-6 m whose returns carry ``extra_noise_m``
    more range noise (a real chessboard: dark squares, range walk) and a bow of ``bow_m`` across
    its width (a warped board, or a curved surface)."""
    rng = np.random.default_rng(seed)
    L = LidarModel.preset("os1-64", range_noise_m=0.005)
    Tb = random_board_pose(rng, BOARD, T_LIDAR[:3, 3], distance_m=(4, 6), tilt_max_deg=20)
    # no clutter: a single scan of a cluttered site may hold crates as board-like as the board
    scan, hit = simulate_scan(L, T_LIDAR, make_scene(BOARD, Tb, rng, clutter=False), rng, topic="/os")
    p = scan.points.copy()
    ray = p[hit] / np.linalg.norm(p[hit], axis=1)[:, None]
    # across the board: along its in-plane horizontal axis, in the LIDAR frame
    n = T_LIDAR[:3, :3].T @ Tb[:3, 2]
    h = np.cross(n, [0.0, 0.0, 1.0])
    h /= np.linalg.norm(h)
    x = (p[hit] - p[hit].mean(axis=0)) @ h
    half = np.abs(x).max()
    dr = rng.normal(0.0, extra_noise_m, hit.sum()) + bow_m * (1 - (x / half) ** 2)
    p[hit] += ray * dr[:, None]
    return LidarScan(scan.topic, 0, p, scan.valid, scan.intensity, scan.ring, scan.time_s, scan.shape), hit


def test_noisier_board_returns_are_still_flat_a_bowed_surface_is_not():
    """Real chessboard returns are noisier than the scan's walls (12 mm vs 5 mm): the board is
    flat as far as its own along-ring noise says, and accepted; a surface bowed by 8 cm (a body,
    a curved panel) is straight along its rings but far off one plane, and rejected as not flat."""
    for seed in (1, 2, 3):
        noisy, hit = _board_scan(seed, 0.012, 0.0)
        r = segment_board(noisy, SegmentationOptions(), LidarOptions(), BOARD)
        assert isinstance(r, LidarBoardObservation), r.reason
        assert hit[r.indices].mean() > 0.95 and 0.010 < r.rms_m < 0.016
        bowed, _ = _board_scan(seed, 0.0, 0.08)
        r = segment_board(bowed, SegmentationOptions(), LidarOptions(), BOARD)
        assert isinstance(r, Rejected) and "not flat" in r.reason, getattr(r, "reason", r)


def test_a_ring_off_the_plane_of_the_others_is_not_the_board():
    """A short piece of ring 10 cm behind the board's plane (a head above its edge) is dropped; rings
    offset by real per-laser range biases (sd ~1 cm, up to 2.5 cm) are all kept (their leave-one-ring-out
    offsets reach 2.6 cm at the board's ends: a piece must be off by 4 of their robust spreads)."""
    from clcgraph.frontend.lidar_board import _off_plane_ring

    rng = np.random.default_rng(0)

    def board(offsets):
        y = np.linspace(-0.6, 0.6, 60)
        pts = [np.c_[np.full(60, 5.0 + o), y, np.full(60, 0.15 * r)] + rng.normal(0, 0.01, (60, 3))
               for r, o in enumerate(offsets)]
        return np.concatenate(pts), np.repeat(np.arange(len(offsets)), 60)

    for offsets in ([0.01, -0.012, 0.005, -0.008, 0.0, 0.004], [0.025, -0.01, 0.0, 0.008, -0.004, 0.012]):
        pts, ring = board(offsets)
        assert not _off_plane_ring(pts, ring, np.ones(len(pts), bool)).any(), offsets
    pts, ring = board([0.01, -0.012, 0.005, -0.008, 0.0, 0.004])
    head = np.c_[np.full(5, 5.10), np.linspace(0.4, 0.5, 5), np.full(5, 0.9)]
    pts2, ring2 = np.r_[pts, head], np.r_[ring, np.full(5, 6)]
    off = _off_plane_ring(pts2, ring2, np.ones(len(pts2), bool))
    assert np.array_equal(np.flatnonzero(off), np.arange(len(pts), len(pts2)))


def test_one_return_on_a_ring_beside_the_board_is_not_its_outline():
    """A hand held in the board's plane just above its top edge returns once on the ring above
    the board, and that return reached the candidate: the rectangle fits it (the board is taller
    than its rings show), but a ring's piece of one return cannot tell a board from anything
    coplanar beside it. Dropped, it does not join the board."""
    import sys
    from pathlib import Path

    from clcgraph.frontend.board_outline import scan_rays
    from clcgraph.frontend.lidar_board import _verdict

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "factors"))
    from test_lidar_edge import _scan_with_arm  # a 0.85 x 0.61 m board 3 m ahead, a wall at 6 m

    step = 2 * np.pi / 2048
    board = BoardGeometry.from_spec(corners=[7, 5], square_m=0.095, size_m=[0.85, 0.70])
    scan, rows, n, d, _ = _scan_with_arm(False)
    u = scan.points / np.linalg.norm(scan.points, axis=1, keepdims=True)
    q = u * (3.0 / np.where(u[:, 0] > 0.1, u[:, 0], np.nan))[:, None]  # where each ray meets the plane x = 3
    hand = np.flatnonzero(scan.valid & (q[:, 1] > 0.1) & (q[:, 1] < 0.1092) & (q[:, 2] > 0.34) & (q[:, 2] < 0.37))
    assert len(hand) == 1
    scan = dataclasses.replace(scan, points=np.where(np.isin(np.arange(len(q)), hand)[:, None], q, scan.points))
    cand = np.r_[rows, hand]
    every = scan_rays(scan, step)
    others = every.points[every.away_from(cand)]
    o = SegmentationOptions()
    why, _, keep, _ = _verdict(scan.points[cand], scan.ring[cand], board, step, 0.005, o, None, others)
    assert why is None, why
    assert keep[:-1].all() and not keep[-1]
