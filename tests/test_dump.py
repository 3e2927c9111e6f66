import json

import numpy as np
import pytest

from clcgraph.config import Config
from clcgraph.errors import DataError, InputError
from clcgraph.backend.replay import exclude_snapshots, renoise_problem
from clcgraph.outputs.dump import load_problem, save_problem
from clcgraph.geometry import compose_rt, invert_rt, transform
from clcgraph.types import (BoardGeometry, CameraBoardObservation, LidarBoardObservation, PosePrior, Problem,
                            Rejected, Sensor)


def _problem():
    rng = np.random.default_rng(3)
    cam = Sensor("/cam0/image", "camera", "LENSMODEL_OPENCV8", rng.normal(size=12), (1280, 1024))
    M = rng.normal(size=(12, 12))
    cam2 = Sensor("/cam1/image", "camera", "LENSMODEL_OPENCV8", rng.normal(size=12), (640, 480),
                  intrinsics_covariance=M @ M.T)  # from mrcal's optimization_inputs
    sensors = (Sensor("/l0", "lidar"), Sensor("/l1", "lidar"), cam, cam2)
    lidar = (
        LidarBoardObservation(0, 0, rng.normal(size=(17, 3)), rng.normal(size=4), 0.011, np.arange(17) * 3),
        LidarBoardObservation(1, 0, rng.normal(size=(5, 3)), rng.normal(size=4), 0.02, None),
        LidarBoardObservation(0, 2, rng.normal(size=(9, 3)), rng.normal(size=4), 1 / 3, np.arange(9)),
    )
    corners = rng.normal(size=(12, 2)) * 100
    corners[3] = np.nan
    camera = (CameraBoardObservation(2, 0, corners), CameraBoardObservation(2, 2, rng.normal(size=(12, 2))))
    return Problem(
        sensors, BoardGeometry(4, 3, 0.0254, 0.2, 0.15, (0.01, -0.005)), lidar, camera, np.array([10, 2**62 + 7, 30], np.int64),
        rejected=(Rejected("no board", "segmentation", 1, 2), Rejected("blurry", "snapshot")),
        priors=(PosePrior(1, rng.normal(size=6), np.full(6, 0.1)),),
        lidar_visibility_points={0: rng.normal(size=(100, 3)), 1: np.zeros((0, 3))},
        snapshot_bags=("/cap/a.bag", "/cap/b.bag", "/cap/ros2bag/"),
        lidar_ring_offsets={1: np.c_[np.arange(5), rng.normal(0, 0.02, 5)]},
    )


def _same(a, b):
    if a is None or b is None:
        assert a is None and b is None
        return
    a, b = np.asarray(a), np.asarray(b)
    assert a.dtype.kind == b.dtype.kind and a.shape == b.shape
    np.testing.assert_array_equal(a, b)


def test_round_trip_exact(tmp_path):
    p = _problem()
    cfg = Config().replace(solve=dict(sigma_lidar_m=0.017), sectors=dict(n_sectors=12))
    save_problem(tmp_path / "p.npz", p, cfg)
    q, cfg2 = load_problem(tmp_path / "p.npz")
    assert cfg2 == cfg
    assert [(s.topic, s.kind, s.lensmodel, s.imagersize) for s in q.sensors] == \
        [(s.topic, s.kind, s.lensmodel, s.imagersize) for s in p.sensors]
    for s, t in zip(p.sensors, q.sensors):
        _same(s.intrinsics, t.intrinsics)
        _same(s.intrinsics_covariance, t.intrinsics_covariance)  # a replay keeps the intrinsics' term
    assert q.sensors[3].intrinsics_covariance is not None
    assert q.board == p.board
    for o, r in zip(p.lidar_observations, q.lidar_observations, strict=True):
        assert (o.sensor, o.snapshot, o.rms_m) == (r.sensor, r.snapshot, r.rms_m)
        _same(o.points, r.points), _same(o.plane, r.plane), _same(o.indices, r.indices)
    for o, r in zip(p.camera_observations, q.camera_observations, strict=True):
        assert (o.sensor, o.snapshot) == (r.sensor, r.snapshot)
        _same(o.corners_px, r.corners_px)
    _same(p.snapshot_stamps_ns, q.snapshot_stamps_ns)
    assert q.rejected == p.rejected
    assert len(q.priors) == 1 and q.priors[0].sensor == 1
    _same(p.priors[0].rt_lidar0_sensor, q.priors[0].rt_lidar0_sensor)
    _same(p.priors[0].sigma_rt, q.priors[0].sigma_rt)
    assert sorted(q.lidar_visibility_points) == [0, 1]
    for k in (0, 1):
        _same(p.lidar_visibility_points[k], q.lidar_visibility_points[k])
    assert q.snapshot_bags == p.snapshot_bags and q.snapshot_bag(2) == "ros2bag"
    assert sorted(q.lidar_ring_offsets) == [1]  # the ring range term's sigma replays with it
    _same(p.lidar_ring_offsets[1], q.lidar_ring_offsets[1])


def test_no_pickle_and_versioning(tmp_path):
    save_problem(tmp_path / "p.npz", _problem())
    with np.load(tmp_path / "p.npz", allow_pickle=False) as z:  # would raise on object arrays
        arrays = {k: z[k] for k in z.files}
    assert all(a.dtype != object for a in arrays.values())
    meta = json.loads(str(arrays["meta"]))
    assert meta["version"] == 2
    meta["version"] = 3
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "new.npz", **arrays)
    with pytest.raises(DataError, match=r"new\.npz.*version 3"):
        load_problem(tmp_path / "new.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(DataError, match="junk.npz"):
        load_problem(tmp_path / "junk.npz")


def _as_version_1(path, out, margin_m):
    """A copy of dump ``path`` in format version 1 (board and config as version 1 wrote them)."""
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    b = meta["board"]
    old = dict(corners_x=b["corners"][0], corners_y=b["corners"][1], spacing_m=b["square_m"], margin_m=margin_m)
    meta["config"].pop("board")
    meta["config"]["detection"].update(old, detector="mrgingham")
    meta.update(version=1, board=old)
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(out, **arrays)
    return out


def test_version_1_dumps_still_load(tmp_path):
    """A version 1 dump (board margin counted from the outer inner corners) loads as the physical
    board it described; one whose margin is narrower than a square (a board smaller than its
    pattern) is refused in one line."""
    save_problem(tmp_path / "p.npz", _problem())
    q, cfg = load_problem(_as_version_1(tmp_path / "p.npz", tmp_path / "v1.npz", 0.05))
    s = 0.0254
    assert (q.board.corners_x, q.board.corners_y, q.board.square_m) == (4, 3, s)
    assert np.allclose(q.board.extent(), (-0.05, 3 * s + 0.05, -0.05, 2 * s + 0.05))
    assert cfg.board.corners == [4, 3] and np.allclose(cfg.board.size_m, [3 * s + 0.1, 2 * s + 0.1])
    with pytest.raises(DataError, match=r"v1bad\.npz: a version 1 dump whose board margin \(0\.01 m\)"):
        load_problem(_as_version_1(tmp_path / "p.npz", tmp_path / "v1bad.npz", 0.01))


def test_exclude_snapshots_keeps_indices():
    q = exclude_snapshots(_problem(), [2])
    assert {o.snapshot for o in q.lidar_observations} == {0}
    assert {o.snapshot for o in q.camera_observations} == {0}
    assert q.n_snapshots == 3 and q.rejected[-1].snapshot == 2
    # by bag name (file name, stem or path) as well as by index; an unknown name is one line naming it
    for name in ("ros2bag", "/cap/ros2bag", "b.bag,2", "b"):
        q = exclude_snapshots(_problem(), name.split(","))
        want = {2} if name != "b" else {1}
        if name == "b.bag,2":
            want = {1, 2}
        assert {r.snapshot for r in q.rejected if r.reason == "excluded by the user"} == want, name
    with pytest.raises(InputError, match="'c.bag' is neither a snapshot index .* nor a bag of this problem .*a.bag"):
        exclude_snapshots(_problem(), ["c.bag"])
    with pytest.raises(InputError, match="no snapshot 3"):
        exclude_snapshots(_problem(), ["3"])


def test_renoise_puts_points_on_the_plane():
    p = _problem()
    cam = Sensor("/cam", "camera", "LENSMODEL_PINHOLE", np.array([500.0, 500, 640, 512]), (1280, 1024))
    p = Problem((p.sensors[0], p.sensors[1], cam), p.board, p.lidar_observations,
                (CameraBoardObservation(2, 0, np.zeros((12, 2))),), p.snapshot_stamps_ns)
    rts = np.array([[0, 0, 0, 0, 0, 0], [0, 0, 0.3, 0, 1, 0], [-1.2, 1.2, -1.2, 0, 0, 0.]])
    boards = np.array([[0, 1.3, 0, 5, 0, 0], [np.nan] * 6, [0.2, 1.2, 0, 6, 1, 0]])
    # zero noise: points exactly on the board plane, corners exactly at the projections
    q = renoise_problem(p, rts, boards, sigma_lidar_m=0.0, sigma_camera_px=0.0, rng=np.random.default_rng(0))
    for o in q.lidar_observations:
        n, d = o.plane[:3], o.plane[3]
        assert d < 0
        np.testing.assert_allclose(o.points @ n, d, atol=1e-12)
        p_b = transform(compose_rt(invert_rt(boards[o.snapshot]), rts[o.sensor]), o.points)
        np.testing.assert_allclose(p_b[:, 2], 0, atol=1e-12)
    from clcgraph import cameras
    c = q.camera_observations[0]
    pc = transform(compose_rt(invert_rt(rts[2]), boards[0]), p.board.corners())
    np.testing.assert_allclose(c.corners_px, cameras.project(pc, cam.lensmodel, cam.intrinsics), atol=1e-9)
    # with noise: range residual std ~ sigma
    o = p.lidar_observations[0]
    big = Problem(p.sensors, p.board, (LidarBoardObservation(0, 0, np.tile(o.points, (300, 1)), o.plane, 0, None),),
                  (), p.snapshot_stamps_ns)
    q = renoise_problem(big, rts, boards, sigma_lidar_m=0.02, sigma_camera_px=0.0, rng=np.random.default_rng(1))
    r0 = renoise_problem(big, rts, boards, sigma_lidar_m=0.0, sigma_camera_px=0.0, rng=np.random.default_rng(1))
    dr = np.linalg.norm(q.lidar_observations[0].points, axis=1) - np.linalg.norm(r0.lidar_observations[0].points, axis=1)
    assert abs(dr.std() / 0.02 - 1) < 0.05
