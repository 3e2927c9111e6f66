"""Unit tests of the targetless stages: deskew, pose interpolation, ground plane, graph fusion, CLI errors."""

from __future__ import annotations

import numpy as np
import pytest

from clcgraph import geometry as geo
from clcgraph.config import Config
from clcgraph.targetless.calibration_frames import interpolate_pose
from clcgraph.geometry import T_exp as exp
from clcgraph.targetless.deskew import deskew, twist_between
from clcgraph.targetless.keyframe_graph import fuse
from clcgraph.targetless.ground import base_from_ground, fit_ground
from clcgraph.targetless.registration import FrameMeasurement


def test_deskew_matches_exact_motion():
    rng = np.random.default_rng(0)
    xi = np.r_[np.radians([1.0, -2.0, 6.0]), 0.6, 0.1, -0.05]  # deg/s and m/s
    p = rng.uniform(-30, 30, (500, 3))
    tau = rng.uniform(0, 0.1, 500)
    exact = np.array([exp(t * xi)[:3, :3] @ q + exp(t * xi)[:3, 3] for q, t in zip(p, tau)])
    assert np.abs(deskew(p, tau, xi) - exact).max() < 2e-5
    assert np.abs(deskew(p, None, xi) - p).max() == 0  # no time field: unchanged
    Ta = geo.T_from_rt(np.r_[0.1, 0.2, 0.3, 1, 2, 3])
    assert np.allclose(twist_between(Ta, Ta @ exp(0.1 * xi), 0.1), xi)


def test_interpolate_pose_slerp_linear():
    Ta = geo.T_from_rt(np.r_[0, 0, 0.1, 1, 0, 0])
    Tb = geo.T_from_rt(np.r_[0, 0, 0.3, 3, 2, 0])
    T = interpolate_pose(Ta, Tb, 0.25)
    assert np.allclose(geo.rt_from_T(T), [0, 0, 0.15, 1.5, 0.5, 0])


def test_ground_plane_roll_pitch_height_and_rejects_walls():
    rng = np.random.default_rng(1)
    o = Config().targetless
    T_true = geo.T_from_rt(np.r_[np.radians([0.7, -1.1, 20.0]), 0.3, -0.1, 1.85])  # base <- lidar
    g = np.c_[rng.uniform(-15, 15, (20000, 2)), rng.normal(0, 0.003, 20000)]  # ground in base
    wall = np.c_[rng.uniform(-15, 15, 30000), np.full(30000, 6.0), rng.uniform(0, 8, 30000)]  # a bigger wall
    pts_b = np.r_[g, wall]
    Tl = np.linalg.inv(T_true)
    pts_l = pts_b @ Tl[:3, :3].T + Tl[:3, 3]
    guess = T_true @ geo.T_from_rt(np.r_[np.radians([1.5, -1.0, 0.0]), 0, 0, 0.1])
    n, d, ninl = fit_ground(pts_l, np.linalg.inv(guess)[:3, :3] @ [0, 0, 1.0], o)
    T = base_from_ground(n, d, guess)
    up_err = np.degrees(np.arccos((T[:3, :3].T @ [0, 0, 1]) @ (T_true[:3, :3].T @ [0, 0, 1])))
    assert up_err < 0.05 and abs(T[2, 3] - 1.85) < 0.002 and ninl >= 15000
    assert np.allclose(T[:2, 3], guess[:2, 3])  # x, y from the guess
    # yaw (heading of the x axis in the ground plane) kept from the guess
    yaw = lambda T: np.arctan2(T[1, 0], T[0, 0])  # noqa: E731
    assert abs(np.degrees(yaw(T) - yaw(guess))) < 0.05


def test_fusion_covariance_covers_the_error_monte_carlo():
    """Independent per-frame errors with covariance H^-1*s (s unknown): consistent without the
    common-mode term, conservative with it."""
    rng = np.random.default_rng(2)
    T_true = geo.T_from_rt(np.r_[0.1, -0.2, 0.3, 0.5, 0.8, -0.4])
    z0, z1 = [], []
    for _ in range(40):
        meas = []
        for k in range(8):
            H = _spd(rng)
            xi = rng.multivariate_normal(np.zeros(6), 1e-6 * np.linalg.inv(H))
            meas.append(FrameMeasurement(T_true @ exp(xi), H, 1000, 0.0))
        for z, cm in ((z0, 0.0), (z1, 1.0)):
            est = fuse(meas, common_mode=cm)
            z.append((geo.rt_from_T(est.T) - geo.rt_from_T(T_true)) / np.sqrt(np.diag(est.cov_rt)))
    z0, z1 = np.array(z0), np.array(z1)
    assert 0.6 < np.mean(z0 ** 2) < 1.5 and np.mean(np.abs(z0) < 3) > 0.97
    assert np.mean(z1 ** 2) < np.mean(z0 ** 2) / 4  # the common-mode bound: one frame's covariance on top


def _spd(rng, scale=1.0):
    A = rng.normal(size=(6, 6))
    return scale * (A @ A.T + 6 * np.eye(6))


def _linked_world(rng, n_kf=10, n_frames=8, s_kf=1e-5, s_fr=1e-6):
    """Keyframe poses X, an extrinsic E, noisy keyframe edges, the map's chained estimates X^, and
    frames whose registrations are shifted by the map's errors of the keyframes they used
    (coherently: frames near the same keyframes see its error the same way)."""
    import gtsam

    from clcgraph.targetless.keyframe_graph import KeyframeEdge

    X = [gtsam.Pose3(gtsam.Rot3.Yaw(0.02 * j), np.array([1.0 * j, 0.1 * np.sin(j), 0.0])) for j in range(n_kf)]
    E = gtsam.Pose3(gtsam.Rot3.Ypr(0.3, -0.1, 0.05), np.array([0.5, 0.8, -0.4]))
    edges = []
    for a in range(n_kf):
        for b in (a + 1, a + 2):
            if b < n_kf:
                H = _spd(rng)
                n = rng.multivariate_normal(np.zeros(6), s_kf * np.linalg.inv(H))
                edges.append(KeyframeEdge(a, b, X[a].between(X[b]).compose(gtsam.Pose3.Expmap(n)).matrix(), H))
    Xh = [X[0]]
    for e in edges:
        if e.b == e.a + 1:
            Xh.append(Xh[-1].compose(gtsam.Pose3(e.T)))
    B_kf = [rng.normal(0, 0.3, (6, 6)) for _ in range(n_kf)]
    meas = []
    for _ in range(n_frames):
        i = int(rng.integers(1, n_kf - 1))
        infl = {j: B_kf[j] + rng.normal(0, 0.05, (6, 6)) for j in range(max(0, i - 3), min(n_kf, i + 4)) if j != i}
        shift = sum(B @ gtsam.Pose3.Logmap(Xh[i].between(Xh[j]).between(X[i].between(X[j]))) for j, B in infl.items())
        H = _spd(rng)
        n = rng.multivariate_normal(np.zeros(6), s_fr * np.linalg.inv(H))
        Z = E.compose(gtsam.Pose3.Expmap(shift)).compose(gtsam.Pose3.Expmap(n))
        meas.append(FrameMeasurement(Z.matrix(), H, 1000, 0.0, i, infl))
    return E.matrix(), meas, {j: x.matrix() for j, x in enumerate(Xh)}, edges


def test_keyframe_graph_covariance_is_consistent_where_independent_fusion_is_not():
    """Frames that share map errors: the keyframe graph's Marginals match the Monte-Carlo spread
    (scales unknown, estimated by variance components); fusing the frames as independent is
    overconfident by ~2x in sigma."""
    import gtsam

    rng = np.random.default_rng(5)
    zl, zi = [], []
    for _ in range(40):
        T, meas, kfs, edges = _linked_world(rng)
        for z, est in ((zl, fuse(meas, kfs, edges, common_mode=0)), (zi, fuse(meas, common_mode=0))):
            e = gtsam.Pose3.Logmap(gtsam.Pose3(T).between(gtsam.Pose3(est.T)))
            z.append(e / np.sqrt(np.diag(est.cov_xi)))
    zl, zi = np.array(zl), np.array(zi)
    assert 0.7 < np.mean(zl ** 2) < 1.5 and np.mean(np.abs(zl) < 3) > 0.97, np.mean(zl ** 2, axis=0)
    assert np.mean(zi ** 2) > 2.5


def test_keyframes_without_edges_stay_fixed():
    rng = np.random.default_rng(9)
    T, meas, kfs, edges = _linked_world(rng)
    alone, no_edges = fuse(meas), fuse(meas, kfs, [])
    assert np.allclose(alone.T, no_edges.T, atol=1e-9) and np.allclose(alone.cov_xi, no_edges.cov_xi, rtol=1e-6)
    linked = fuse(meas, kfs, edges)
    assert not np.allclose(alone.cov_xi, linked.cov_xi, rtol=1e-3)  # the edges do change the answer


def test_fusion_degenerate_hessian_raises():
    from clcgraph.errors import DegenerateError

    H = np.diag([1.0, 1.0, 1.0, 1.0, 1.0, 1e-9])
    with pytest.raises(DegenerateError, match="degenerate"):
        fuse([FrameMeasurement(np.eye(4), H, 10, 0.0)] * 3)
    with pytest.raises(DegenerateError, match="usable calibration frames"):
        fuse([FrameMeasurement(np.eye(4), np.eye(6), 10, 0.0)])


def test_cli_targetless_flat_field_one_line_error(tmp_path, capsys):
    from clcgraph.cli import main
    from clcgraph.sim.drive import DrivePlan, simulate_drive, write_drive_bag

    dr = simulate_drive(DrivePlan.small(duration_s=3.0, scene="flat"), seed=3)
    write_drive_bag(dr, tmp_path / "flat.bag")
    rc = main(["-q", "targetless", "--bag", str(tmp_path / "flat.bag"), "--mapping-topic", "/top/points",
               "--calibration-topics", "/side/points", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc != 0 and len(err) == 1 and "degenerate" in err[0] and "/top/points" in err[0]
    assert not (tmp_path / "out").exists()


def test_base_from_ground_overwrite_xy_yaw():
    guess = geo.T_from_rt(np.r_[np.radians([1.0, -2.0, 30.0]), 0.5, -0.3, 1.7])
    n_lidar = np.linalg.inv(guess)[:3, :3] @ np.array([0.0, 0.0, 1.0])  # the ground normal seen by the LIDAR
    kept = base_from_ground(n_lidar, 1.8, guess)
    assert np.allclose(kept[:3, 3], [0.5, -0.3, 1.8]) and np.allclose(kept[:3, :3], guess[:3, :3], atol=1e-9)
    over = base_from_ground(n_lidar, 1.8, guess, overwrite_xy_yaw=True)
    assert np.allclose(over[:3, 3], [0.0, 0.0, 1.8])
    x = over[:3, :3] @ [1.0, 0.0, 0.0]
    assert abs(np.arctan2(x[1], x[0])) < 1e-9 and np.allclose(over[:3, :3] @ n_lidar, [0, 0, 1])


def test_only_the_scans_nearest_to_keyframes_are_kept_and_they_give_the_same_frames():
    from types import SimpleNamespace

    from clcgraph.targetless.calibration_frames import make_calibration_frames, nearest_to_keyframes
    from clcgraph.targetless.mapping import Frame, MapResult

    rng = np.random.default_rng(3)
    mp = MapResult("/top")
    for k in range(200):  # 10 Hz, 5 cm per frame, a keyframe every 20 frames
        T = np.eye(4)
        T[0, 3] = 0.05 * k
        mp.frames.append(Frame(int(k * 1e8), np.zeros((1, 3), np.float32), T, np.r_[0, 0, 0, 0.5, 0, 0.0]))
    mp.keyframe_ids = list(range(0, 200, 20))
    stamps = np.sort(rng.uniform(0, 2e10, 180)).astype(np.int64)  # an unsynchronised 9 Hz LIDAR
    scans = [SimpleNamespace(stamp_ns=int(t)) for t in stamps]
    kept = nearest_to_keyframes(mp, iter(scans))
    assert len(kept) <= len(mp.keyframe_ids) and [s.stamp_ns for s in kept] == sorted(s.stamp_ns for s in kept)
    o = Config().replace(targetless=dict(calibration_skip_keyframes=1)).targetless
    full, reduced = make_calibration_frames(mp, scans, o), make_calibration_frames(mp, kept, o)
    assert [cf.scan for cf in full] == [cf.scan for cf in reduced] and len(full) >= 8


def test_cli_simulate_drive_writes_a_bag_to_try_targetless_on(tmp_path, capsys):
    import yaml

    from clcgraph.cli import main
    from clcgraph.frontend.bag import bag_info

    rc = main(["-q", "simulate-drive", "--out", str(tmp_path / "drv"), "--duration", "1", "--small",
               "--format", "ros2-sqlite3", "--layout", "ouster"])
    out = capsys.readouterr().out
    assert rc == 0 and "clcgraph targetless --bag" in out
    counts = {t.topic: t.count for t in bag_info(tmp_path / "drv" / "drive").topics}
    assert counts == {"/top/points": 10, "/side/points": 10, "/tf_static": 1}
    truth = yaml.safe_load((tmp_path / "drv" / "truth.yaml").read_text())
    assert truth["reference"] == "/top/points" and len(truth["sensors"]) == 2
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left behind


def test_dense_target_is_the_voxel_centroids_of_its_submaps_frames_and_knows_each_voxels_submaps():
    """DenseMap.target against a direct computation: the centroids of the map-frame voxels of the
    frames it uses (every step-th of the submaps within
    +-dense_pointcloud_num_keyframes), in lidar0 at the frame's pose; TargetParts' counts per
    submap are those voxels' points; the reach keeps only voxels near the source."""
    from clcgraph.targetless.mapping import Frame, MapResult
    from clcgraph.targetless.registration import DenseMap

    rng = np.random.default_rng(5)
    mp = MapResult("/top")
    for k in range(60):  # a keyframe every 6 frames
        T = geo.T_from_rt(np.r_[0.0, 0.0, 0.02 * k, 0.1 * k, 0.03 * k, 0.0])
        mp.frames.append(Frame(int(k * 1e8), rng.uniform(-6, 6, (400, 3)).astype(np.float32), T, np.zeros(6)))
    mp.keyframe_ids = list(range(0, 60, 6))
    o = Config().replace(targetless=dict(dense_pointcloud_num_keyframes=2, leaf_size_dense_map=0.5,
                                         min_calibration_range=0.0, max_calibration_range=100.0)).targetless
    dense = DenseMap(mp, o, max_frames=10)
    assert dense.step == 3  # the widest window: 5 submaps of 6 frames
    kid = 24
    T_map_lidar0 = geo.T_from_rt(np.r_[0.0, 0.1, 0.0, 1.0, 2.0, 0.5])
    pts, parts = dense.target(kid, T_map_lidar0)

    positions = list(range(2, 7))  # keyframe 24 is position 4
    ids = [j for j in range(12, 42) if j % 3 == 0]
    q = np.concatenate([mp.frames[j].points @ mp.frames[j].T_map_lidar[:3, :3].T + mp.frames[j].T_map_lidar[:3, 3]
                        for j in ids])
    label = np.concatenate([np.full(len(mp.frames[j].points), positions.index(j // 6)) for j in ids])
    vox = np.floor(q / 0.5).astype(np.int64)
    uniq, inv = np.unique(vox, axis=0, return_inverse=True)
    inv = inv.ravel()
    n = np.bincount(inv)
    want = np.stack([np.bincount(inv, q[:, i]) for i in range(3)], axis=1) / n[:, None]
    want = want @ np.linalg.inv(T_map_lidar0)[:3, :3].T + np.linalg.inv(T_map_lidar0)[:3, 3]
    assert len(pts) == len(uniq)
    order_got, order_want = np.lexsort(pts.T), np.lexsort(want.T)
    np.testing.assert_allclose(pts[order_got], want[order_want], atol=1e-6)
    per_submap = np.zeros((len(uniq), len(positions)))
    np.add.at(per_submap, (inv, label), 1)
    got = np.zeros((len(pts), len(positions)))
    rows, at = parts.pairs(np.arange(len(pts)))
    np.add.at(got, (rows, parts.group[at]), parts.counts[at])
    np.testing.assert_array_equal(got[order_got], per_submap[order_want])
    assert list(parts.positions) == positions and parts.anchor == 4

    # with a source: only voxels within reach of its points are kept, and they are the same voxels
    src = np.array([[20.0, 0.0, 0.0]])  # in lidar0; the map's points lie within ~8 m of its origin
    near, near_parts = dense.target(kid, T_map_lidar0, reach=dense.reach(T_map_lidar0, src, np.zeros(3)))
    assert len(near) == 0 and len(near_parts.start) == 1
    src = pts[:1] + 0.01
    reach = dense.reach(T_map_lidar0, src, np.zeros(3))
    near, _ = dense.target(kid, T_map_lidar0, reach=reach)
    assert 0 < len(near) < len(pts) and np.linalg.norm(near - src, axis=1).max() < 8.0
    assert np.isin(near.round(6), pts.round(6)).all()
    # submaps made within the frames' reach only: the same target
    dense.make_submaps([kid], within=reach)
    again, _ = dense.target(kid, T_map_lidar0, reach=reach)
    np.testing.assert_allclose(again, near, atol=1e-6)
