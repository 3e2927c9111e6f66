"""Snapshots: time parsing, filters, per-bag and continuous-bag assembly, board-motion rejection."""

import datetime as dt
from pathlib import Path
from dataclasses import replace

import numpy as np
import pytest

from clcgraph.config import SnapshotOptions
from clcgraph.errors import InputError
from clcgraph.frontend.snapshots import (
    TimeFilter, assemble_snapshots, parse_time_ns, range_image, scene_motion)
from clcgraph.sim.bag_writer import BagWriter
from clcgraph.types import Image, LidarScan

T0 = 1_700_000_000 * 10**9  # a plausible epoch in ns
NR, NA = 16, 1800


# ---------------------------------------------------------------- a tiny LIDAR scene


def _dirs():
    el = np.radians(np.linspace(-15, 15, NR))
    az = np.linspace(-np.pi, np.pi, NA, endpoint=False) + np.pi / NA
    e, a = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    ring = np.repeat(np.arange(NR), NA)
    return d, ring


DIRS, RING = _dirs()


def cast(board_c, *, rng, noise=0.01, stamp_ns=0, with_ring=True):
    """A 16x1800 scan: ground z=-1.5, a cylindrical wall r=15 m, a 1.2 m board facing -x."""
    d = DIRS
    lam = np.full(len(d), np.inf)
    g = d[:, 2] < -1e-6
    lam[g] = -1.5 / d[g, 2]
    lam = np.minimum(lam, 15.0 / np.hypot(d[:, 0], d[:, 1]))
    f = d[:, 0] > 1e-6
    lb = np.full(len(d), np.inf)
    lb[f] = board_c[0] / d[f, 0]
    hit = d * lb[:, None]
    on = f & (np.abs(hit[:, 1] - board_c[1]) < 0.6) & (np.abs(hit[:, 2] - board_c[2]) < 0.6)
    lam = np.where(on & (lb < lam), lb, lam)
    lam = lam + rng.normal(0, noise, lam.shape)
    return LidarScan("/lidar0", stamp_ns, d * lam[:, None], np.ones(len(d), bool),
                     ring=RING.copy() if with_ring else None)


# Continuous capture: board still, carried (0.25 m/s), still, carried, still.
STILL = [(0.0, 2.5), (4.0, 6.5), (8.0, 99.0)]


def board_at(t):
    c0 = np.array([4.0, -0.5, 0.0])
    v = np.array([0.1, 0.23, 0.0])  # ~0.25 m/s
    if t < 2.5:
        return c0
    if t < 4.0:
        return c0 + v * (t - 2.5)
    if t < 6.5:
        return c0 + v * 1.5
    if t < 8.0:
        return c0 + v * (1.5 + t - 6.5)
    return c0 + v * 3.0


@pytest.fixture(scope="module")
def continuous_bag(tmp_path_factory):
    """12 s bag: LIDAR at 10 Hz, camera at 7 Hz with an offset (unsynchronised)."""
    path = tmp_path_factory.mktemp("cont") / "cont.bag"
    rng = np.random.default_rng(1)
    with BagWriter(path) as w:
        for k in range(120):
            t = 0.013 + k * 0.1
            s = cast(board_at(t), rng=rng, stamp_ns=T0 + int(t * 1e9))
            w.write_pointcloud("/lidar0", s, frame_id="lidar0", layout="velodyne")
        for k in range(84):
            t = 0.05 + k / 7
            px = np.full((24, 32), 100 + k % 50, np.uint8)
            w.write_image("/cam0", Image("/cam0", T0 + int(t * 1e9), px, "mono8"), frame_id="cam0")
    return path


# ---------------------------------------------------------------- time parsing and filters


def test_parse_time_ns():
    assert parse_time_ns(1_700_000_000) == T0
    assert parse_time_ns(T0 + 5) == T0 + 5
    assert parse_time_ns(1_700_000_000.25) == T0 + 250_000_000
    assert parse_time_ns("1700000000") == T0
    assert parse_time_ns(str(T0)) == T0
    assert parse_time_ns("1700000000.5") == T0 + 500_000_000
    iso = dt.datetime.fromtimestamp(1_700_000_000, dt.timezone.utc).isoformat()
    assert parse_time_ns(iso) == T0
    assert parse_time_ns("2023-11-14T22:13:20") == T0  # naive = UTC
    assert parse_time_ns("2023-11-14T23:13:20+01:00") == T0
    with pytest.raises(InputError):
        parse_time_ns("yesterday-ish nonsense")


def test_time_filter():
    o = SnapshotOptions(after=1_700_000_001, before="1700000010.0",
                        exclude_time_periods=[[1_700_000_003, 1_700_000_004], "1700000006,1700000007"])
    f = TimeFilter.from_options(o)
    t = T0 + np.arange(12) * 10**9
    assert f.keeps(t).tolist() == [False, True, True, False, False, True, False, False, True, True,
                                   False, False]
    assert f.why_not(T0) == "before the 'after' time"
    assert f.why_not(T0 + 3 * 10**9) == "in an excluded time period"
    with pytest.raises(InputError):
        TimeFilter.from_options(SnapshotOptions(exclude_time_periods=[[5, 1]]))


# ---------------------------------------------------------------- motion on arrays


def test_scene_motion_physical_threshold():
    rng = np.random.default_rng(0)
    c = np.array([4.0, -0.5, 0.0])
    a = cast(c, rng=rng)
    still = cast(c, rng=rng)
    for with_ring in (True, False):  # rings from elevation bins too
        b = cast(c, rng=rng, with_ring=with_ring)
        moved, _, n = scene_motion(a, b, threshold_m=0.03, min_cells=4)
        assert not moved, n
    moved, mag, n = scene_motion(a, still, threshold_m=0.03, min_cells=4)
    assert not moved
    # 6 cm along the normal: the whole board face changes by ~6 cm
    moved, mag, n = scene_motion(a, cast(c + [0.06, 0, 0], rng=rng), threshold_m=0.03, min_cells=4)
    assert moved and abs(mag - 0.06) < 0.015 and n > 50
    # 1 cm: below the threshold
    moved, _, _ = scene_motion(a, cast(c + [0.01, 0, 0], rng=rng), threshold_m=0.03, min_cells=4)
    assert not moved
    # 10 cm sideways: only the board's edges change (board <-> wall)
    moved, mag, n = scene_motion(a, cast(c + [0, 0.10, 0], rng=rng), threshold_m=0.03, min_cells=4)
    assert moved and mag > 5


def test_range_image_shape():
    s = cast(np.array([4.0, 0, 0]), rng=np.random.default_rng(0), noise=0)
    rings, img = range_image(s)
    assert img.shape == (16, 1800) and np.isfinite(img).all()
    assert np.isclose(np.nanmin(img), 4.0 / np.cos(np.radians(1.0)), atol=0.02)


# ---------------------------------------------------------------- assembly from bags


def test_continuous_bag_drops_moving_periods(continuous_bag):
    o = SnapshotOptions(decimation_period_s=1.0, max_time_spread_s=0.1)
    snaps, rej = assemble_snapshots([continuous_bag], ["/lidar0"], ["/cam0"], o)
    # periods start at the first message (t=0.013 s); a period is still if the motion
    # window (its centre +- 0.5 s = the whole period) lies in a still interval
    t0 = 0.013
    still = [k for k in range(12)
             if any(a <= t0 + k and t0 + k + 1 <= b for a, b in STILL)]
    kept_periods = [int(s.source.split("period ")[1].split()[0]) for s in snaps]
    moving_rej = [r for r in rej if "moving" in r.reason]
    assert kept_periods == still, (kept_periods, [r.reason for r in rej])
    assert len(moving_rej) == 12 - len(still) == 4
    for s in snaps:
        st = [s.scans["/lidar0"].stamp_ns, s.images["/cam0"].stamp_ns]
        assert (max(st) - min(st)) * 1e-9 <= 0.1
        tb = (s.scans["/lidar0"].stamp_ns - T0) * 1e-9
        assert any(a <= tb <= b for a, b in STILL)
    assert [s.index for s in snaps] == list(range(len(snaps)))


def test_continuous_bag_spread_and_windows(continuous_bag):
    base = SnapshotOptions(decimation_period_s=1.0, max_board_motion_m=100.0)  # motion check off
    snaps, rej = assemble_snapshots([continuous_bag], ["/lidar0"], ["/cam0"], base)
    assert len(snaps) + len(rej) == 12
    # camera 7 Hz vs LIDAR 10 Hz: the nearest pair can be up to ~50 ms apart
    tight, rej_t = assemble_snapshots([continuous_bag], ["/lidar0"], ["/cam0"],
                                      replace(base, max_time_spread_s=0.01))
    assert len(tight) < len(snaps) and all("spread" in r.reason for r in rej_t)
    for s in tight:
        assert abs(s.scans["/lidar0"].stamp_ns - s.images["/cam0"].stamp_ns) <= 10**7
    w, rej_w = assemble_snapshots([continuous_bag], ["/lidar0"], ["/cam0"],
                                  replace(base, after=T0 + 3 * 10**9, before=(T0 * 1e-9 + 9.0),
                                          exclude_time_periods=[[T0 + 5_500_000_000, T0 + 5_600_000_000]]))
    for s in w:
        for m in list(s.scans.values()) + list(s.images.values()):
            assert T0 + 3 * 10**9 <= m.stamp_ns < T0 + 9 * 10**9
    assert any("excluded" in r.reason for r in rej_w)
    assert len(w) == 5  # 6 s window, one period overlaps the exclusion


def test_bag_per_pose(tmp_path):
    rng = np.random.default_rng(2)
    paths = []
    for i, cam_dt in enumerate([0.0, 0.02, 0.5, 0.0]):
        p = tmp_path / f"pose{i}.bag"
        t = T0 + i * 10 * 10**9
        with BagWriter(p) as w:
            for k in range(3):
                w.write_pointcloud("/lidar0", cast(np.array([4.0, 0, 0]), rng=rng, stamp_ns=t + k * 10**8),
                                   frame_id="lidar0", layout="velodyne")
                w.write_image("/cam0", Image("/cam0", t + int(cam_dt * 1e9) + k * 10**8,
                                             np.zeros((8, 8), np.uint8), "mono8"), frame_id="cam0")
        paths.append(p)
    o = SnapshotOptions(max_time_spread_s=0.1, exclude_bag=r"pose[3]")  # a regex: the bag is not read
    snaps, rej = assemble_snapshots(paths, ["/lidar0"], ["/cam0"], o)
    assert [s.source for s in snaps] == [str(paths[0]), str(paths[1])]
    assert snaps[1].scans["/lidar0"].stamp_ns == T0 + 10 * 10**9  # first message
    reasons = sorted(r.reason for r in rej)
    assert any("pose2" in r and "spread" in r for r in reasons)
    assert any("pose3" in r and "exclude_bag" in r for r in reasons)
    snaps, rej = assemble_snapshots(paths, ["/lidar0"], ["/cam0"],
                                    replace(o, exclude_bag=None, after=T0 + 5 * 10**9))
    assert [s.source for s in snaps] == [str(paths[1]), str(paths[3])]
    # bag names and snapshot indices: read, then emptied, every index kept (pose2 is rejected for
    # its spread, so pose3 is snapshot 2)
    snaps, rej = assemble_snapshots(paths, ["/lidar0"], ["/cam0"], replace(o, exclude_bag="pose0.bag,2"))
    assert [(s.index, Path(s.bag).name, bool(s.scans)) for s in snaps] == \
        [(0, "pose0.bag", False), (1, "pose1.bag", True), (2, "pose3.bag", False)]
    assert sorted(r.snapshot for r in rej if "excluded by the user" in r.reason) == [0, 2]
    with pytest.raises(InputError, match="no snapshot 5"):
        assemble_snapshots(paths, ["/lidar0"], ["/cam0"], replace(o, exclude_bag="pose1,5"))


# ---------------------------------------------------------------- bags as drivers log them


def _logged_like_drivers(path, *, seconds=6, lidar_offsets=(0.013, 0.063), camera_hz=5.0, camera_offset=0.03,
                         camera_gap=None):
    """A still scene; two unsynchronised 10 Hz LIDARs and a camera, logged as drivers do (a scan
    about a rotation after its stamp, a frame 20-35 ms after): log order != stamp order."""
    from clcgraph.sim.bag_writer import LogDelays

    rng = np.random.default_rng(5)
    c = np.array([4.0, -0.5, 0.0])
    with BagWriter(path, log_delays=LogDelays(seed=2)) as w:
        for k in range(seconds * 10):
            for i, off in enumerate(lidar_offsets):
                w.write_pointcloud(f"/lidar{i}", cast(c, rng=rng, stamp_ns=T0 + int((off + k * 0.1) * 1e9)),
                                   frame_id=f"lidar{i}", layout="velodyne")
        for k in range(int(seconds * camera_hz)):
            t = camera_offset + k / camera_hz
            if camera_gap and camera_gap[0] <= t < camera_gap[1]:
                continue
            w.write_image("/cam0", Image("/cam0", T0 + int(t * 1e9), np.full((24, 32), 100, np.uint8), "mono8"),
                          frame_id="cam0")
    return path


def _period_ids(snaps):
    return [int(s.source.split("period ")[1].split()[0]) for s in snaps]


def test_a_pause_is_one_snapshot_per_period_whatever_the_log_order(tmp_path, monkeypatch):
    from clcgraph.frontend import bag

    path = _logged_like_drivers(tmp_path / "still.bag")
    o = SnapshotOptions(decimation_period_s=1.0)
    snaps, rej = assemble_snapshots([path], ["/lidar0", "/lidar1"], ["/cam0"], o)
    assert _period_ids(snaps) == list(range(6)), [r.reason for r in rej]
    assert not rej and all(set(s.scans) == {"/lidar0", "/lidar1"} and set(s.images) == {"/cam0"} for s in snaps)
    for s in snaps:  # each topic's message nearest the period's centre (+-0.05 s LIDAR, +-0.1 s camera)
        centre = T0 + int((0.013 + _period_ids([s])[0] + 0.5) * 1e9)
        assert all(abs(m.stamp_ns - centre) <= 0.05e9 + 1 for m in s.scans.values())
        assert abs(s.images["/cam0"].stamp_ns - centre) <= 0.1e9 + 1
    # the same bag grouped in log order (the reader before stamp_ordered) splits the pause into
    # duplicate and one-sensor periods: the bag does exercise the re-ordering
    monkeypatch.setattr(bag, "stamp_ordered", lambda items, **kw: ((s, t, p) for _, s, t, p in items))
    old, _ = assemble_snapshots([path], ["/lidar0", "/lidar1"], ["/cam0"], o)
    ids = _period_ids(old)
    assert len(ids) > len(set(ids)) or any(len(s.scans) + len(s.images) < 3 for s in old), ids


def test_bag_per_pose_slow_cameras_need_no_spread_setting(tmp_path):
    """5 Hz cameras, 10 Hz LIDARs, 0.25 s bags: the first frame comes up to 0.2 s after the first
    scan. A bag per pose is still: no spread limit unless one is asked for."""
    rng = np.random.default_rng(3)
    paths = []
    for i, cam_dt in enumerate([0.224, 0.05, 0.19]):
        p = tmp_path / f"pose{i}.bag"
        t = T0 + i * 10 * 10**9
        with BagWriter(p) as w:
            for k in range(3):
                w.write_pointcloud("/lidar0", cast(np.array([4.0, 0, 0]), rng=rng, stamp_ns=t + k * 10**8),
                                   frame_id="lidar0", layout="velodyne")
            w.write_image("/cam0", Image("/cam0", t + int(cam_dt * 1e9), np.zeros((8, 8), np.uint8), "mono8"),
                          frame_id="cam0")
        paths.append(p)
    snaps, rej = assemble_snapshots(paths, ["/lidar0"], ["/cam0"], SnapshotOptions())
    assert len(snaps) == 3 and not rej
    snaps, rej = assemble_snapshots(paths, ["/lidar0"], ["/cam0"], SnapshotOptions(max_time_spread_s=0.1))
    assert [s.source for s in snaps] == [str(paths[1])]
    assert sorted(r.reason.split("time spread ")[1][:5] for r in rej) == ["0.190", "0.224"]


def test_continuous_camera_frame_outside_the_still_interval_is_dropped(tmp_path):
    """No spread limit by default, but a snapshot's frames must lie where the motion check looked:
    a camera silent around a period's centre gives no snapshot for that period."""
    path = _logged_like_drivers(tmp_path / "gap.bag", camera_gap=(2.1, 2.95))
    o = SnapshotOptions(decimation_period_s=1.0, motion_window_s=0.3)
    snaps, rej = assemble_snapshots([path], ["/lidar0", "/lidar1"], ["/cam0"], o)
    assert _period_ids(snaps) == [0, 1, 3, 4, 5]
    assert len(rej) == 1 and "period 2" in rej[0].reason and "/cam0 has no message while the LIDARs saw" in rej[0].reason


def test_single_continuous_bag_without_a_period_is_cut_at_the_motion(continuous_bag):
    """No decimation period given: the bag's scene moves, so it is a continuous bag, cut where the
    LIDAR saw motion; one snapshot per still interval, its messages inside that interval."""
    snaps, rej = assemble_snapshots([continuous_bag], ["/lidar0"], ["/cam0"], SnapshotOptions())
    assert len(snaps) == len(STILL), [s.source for s in snaps]
    for s, (a, b) in zip(snaps, STILL):
        for m in (s.scans["/lidar0"], s.images["/cam0"]):
            t = (m.stamp_ns - T0) * 1e-9
            assert a <= t <= min(b, 12.0), (s.source, t)
        # the message nearest the middle of the interval the motion check found (a scan every
        # 0.1 s: within half the interval of the true still interval's middle)
        t_scan = (s.scans["/lidar0"].stamp_ns - T0) * 1e-9
        assert abs(t_scan - (a + min(b, 11.9)) / 2) < 0.5, t_scan
    assert any("scene moved" in r.reason for r in rej)
    assert [s.index for s in snaps] == [0, 1, 2]


def test_segment_takes_a_continuous_bags_scans_as_the_solve_does(continuous_bag):
    """`clcgraph segment` (api.segment_bags) on a continuous bag: one scan per still interval, the
    scan the solve's snapshot holds, named by its interval; --every still gives every scan."""
    from clcgraph.api import segment_bags

    snaps, _ = assemble_snapshots([continuous_bag], ["/lidar0"], [], SnapshotOptions())
    out = segment_bags([continuous_bag], "/lidar0")
    assert len(out) == len(snaps) == len(STILL)
    for (scan, _, name), s in zip(out, snaps):
        assert scan.stamp_ns == s.scans["/lidar0"].stamp_ns
        np.testing.assert_array_equal(scan.points[scan.valid], s.scans["/lidar0"].points[s.scans["/lidar0"].valid])
        assert name.startswith("cont.bag still "), name
    assert len(segment_bags([continuous_bag], "/lidar0", every=True)) == 120


def test_a_recording_split_into_files_gives_the_snapshots_of_the_whole(continuous_bag, tmp_path):
    """`rosbag record --split`: the files of one recording are one time line (a pause cut by a file
    boundary is one snapshot, not two), and a file without a topic (the camera's last frame fell in
    the file before) is no error; the snapshots are those of the unsplit bag."""
    import shutil

    from clcgraph.frontend.snapshots import recordings
    from clcgraph.sim.bag_writer import split_ros1_bag

    from clcgraph.frontend.bag import bag_info

    whole, _ = assemble_snapshots([continuous_bag], ["/lidar0"], ["/cam0"], SnapshotOptions())
    # files of 3.3 s: boundaries inside the first two still intervals; of 3.966 s: the last file holds
    # the LIDAR's last scan alone (at 11.913 s, after the camera's last frame at 11.907 s)
    for every_s, names in ((3.3, ["rec_0.bag", "rec_1.bag", "rec_2.bag", "rec_3.bag"]),
                           (3.96567, ["rec_0.bag", "rec_1.bag", "rec_2.bag", "rec_3.bag"])):
        copy = tmp_path / str(every_s) / "rec.bag"
        copy.parent.mkdir()
        shutil.copy(continuous_bag, copy)
        parts = split_ros1_bag(copy, every_s)
        assert [p.name for p in parts] == names and copy.exists()  # the original left as it is
        if every_s > 3.5:
            assert [t.topic for t in bag_info(parts[-1]).topics] == ["/lidar0"]
        shuffled = [parts[2], parts[0], parts[3], parts[1]]
        assert recordings(shuffled) == [parts]
        split, _ = assemble_snapshots(shuffled, ["/lidar0"], ["/cam0"], SnapshotOptions())
        assert [s.stamp_ns for s in split] == [s.stamp_ns for s in whole] and len(split) == len(STILL)
        assert [s.source.split(" still ")[1] for s in split] == [s.source.split(" still ")[1] for s in whole]
    # bags of separate recordings (here two copies of one: the same times) stay apart
    assert recordings([continuous_bag, parts[0]]) == [[continuous_bag], [parts[0]]]


def _moving_board_bag(path, n_scans, rng):
    """A bag whose board stands still for ``n_scans // 2`` scans, jumps 1 m, and stands still again."""
    with BagWriter(path) as w:
        for k in range(n_scans):
            c = np.array([4.0, -0.5 if k < n_scans // 2 else 0.5, 0.0])
            w.write_pointcloud("/lidar0", cast(c, rng=rng, stamp_ns=T0 + k * 10**8), frame_id="lidar0",
                               layout="velodyne")
            w.write_image("/cam0", Image("/cam0", T0 + k * 10**8 + 10**7, np.full((8, 8), k, np.uint8), "mono8"),
                          frame_id="cam0")
    return path


def test_a_bag_too_short_for_two_still_intervals_is_not_decoded_for_them(tmp_path, monkeypatch):
    """Two still intervals need >= 2 scans of every LIDAR each: a bag of 3 scans (the board moved
    between them) is a bag per pose without its scans decoded and compared, and gives what the full
    still-interval search gives; one of 6 scans is searched and cut in two."""
    import clcgraph.frontend.snapshots as snapshots

    rng = np.random.default_rng(5)
    short = _moving_board_bag(tmp_path / "short.bag", 3, rng)
    long = _moving_board_bag(tmp_path / "long.bag", 6, rng)
    o = SnapshotOptions(motion_window_s=0.05)
    calls = []
    search = snapshots.still_intervals
    monkeypatch.setattr(snapshots, "still_intervals",  # given a recording's files
                        lambda bags, *a, **k: calls.append(",".join(Path(b).name for b in bags)) or search(bags, *a, **k))
    snaps, _ = assemble_snapshots([short, long], ["/lidar0"], ["/cam0"], o)
    assert calls == ["long.bag"]
    assert [s.source.split(" ")[0] for s in snaps] == [str(short), str(long), str(long)]
    assert snaps[0].scans["/lidar0"].stamp_ns == T0 and snaps[0].images["/cam0"].stamp_ns == T0 + 10**7
    # the full search on the short bag: it cannot find two still intervals, so the same snapshot
    monkeypatch.setattr(snapshots, "_may_hold_two_still_intervals", lambda *a: True)
    still, _ = search(short, ["/lidar0"], o)
    assert len(still) < 2
    full, _ = assemble_snapshots([short], ["/lidar0"], ["/cam0"], o)
    assert [(s.source, s.stamp_ns) for s in full] == [(snaps[0].source, snaps[0].stamp_ns)]
    assert np.array_equal(full[0].scans["/lidar0"].points, snaps[0].scans["/lidar0"].points)


def test_bag_per_pose_averages_the_still_scans_and_leaves_out_a_moved_one(tmp_path):
    """A bag per pose holding 4 scans, the board still in the first 3 and moved 0.3 m in the last:
    the snapshot's scan is the first one's rays at the mean range of the 3 still ones (noise /
    sqrt(3), the board where it was); ``max_scans_averaged=1`` keeps the first scan alone (clc)."""
    rng = np.random.default_rng(7)
    c = np.array([4.0, 0.0, 0.0])
    p = tmp_path / "pose0.bag"
    with BagWriter(p) as w:
        for k, at in enumerate([c, c, c, c + [0.0, 0.3, 0.0]]):
            w.write_pointcloud("/lidar0", cast(at, rng=rng, stamp_ns=T0 + k * 10**8), frame_id="lidar0",
                               layout="velodyne")
    truth = cast(c, rng=rng, noise=0.0)
    board = np.abs(truth.points[:, 0] - 4.0) < 1e-6  # the board's rays

    def board_noise(o):
        snaps, _ = assemble_snapshots([p], ["/lidar0"], [], o)
        scan = snaps[0].scans["/lidar0"]
        assert scan.stamp_ns == T0
        e = scan.points[board, 0] - 4.0
        return abs(e.mean()), e.std()

    bias, sd = board_noise(SnapshotOptions())
    bias1, sd1 = board_noise(SnapshotOptions(max_scans_averaged=1))
    assert bias < 0.002 and bias1 < 0.003
    assert 0.009 < sd1 < 0.011 and 0.5 < sd / sd1 < 0.65  # 1/sqrt(3) = 0.58; 1/2 had the moved scan counted
