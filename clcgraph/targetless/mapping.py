"""Scan-to-local-map mapping with one LIDAR: deskew, crop, downsample, GICP, keyframes.

SYNOPSIS
    m = build_map(scans, opts)            # scans: list[LidarScan] of the mapping LIDAR, in time order
    m.frames[k].T_map_lidar               # (4,4) pose at the scan stamp
    m.keyframe_ids                        # indices into m.frames

The first frame defines the map frame. Reading, cropping and picking the registration points
of the next scans go on in a forked child process (background.Prefetched) while this one
registers. Each scan is deskewed with the twist of the last
registration (constant velocity), registered to the local map of the latest
``local_map_num_keyframes`` keyframes, then deskewed again with the twist implied by the
new pose and re-registered (``deskew_iterations``). Frames closer than
``new_frame_min_distance`` to the last frame are dropped (stopped frames kept every
``frames_since_stopped_force_frame``). A frame whose stamp gap, acceleration or heading
jump exceeds the seed's limits is a lost frame: the local map restarts there.
"""

from __future__ import annotations

import contextlib
import functools
import logging
from dataclasses import dataclass, field

import numpy as np

from ..errors import DegenerateError, DataError
from ..geometry import T_exp
from . import gicp
from .background import Prefetched
from .deskew import deskew, twist_between

log = logging.getLogger(__name__)


@dataclass
class Frame:
    """One kept mapping scan: deskewed points (lidar frame at the stamp) and its map pose."""

    stamp_ns: int
    points: np.ndarray  # (N,3) float32 deskewed, cropped (not downsampled)
    T_map_lidar: np.ndarray  # (4,4)
    twist: np.ndarray  # (6,) [omega, v] per second used for deskew
    keyframe: bool = False
    stopped: bool = False
    lost: bool = False
    H: np.ndarray | None = None  # (6,6) registration Hessian vs the local map
    T_prev_cur: np.ndarray | None = None  # (4,4) relative pose from the previous kept frame
    cond: float = np.inf  # registration condition number (degeneracy)


@dataclass
class MapResult:
    topic: str
    frames: list = field(default_factory=list)
    keyframe_ids: list = field(default_factory=list)
    n_scans: int = 0
    skipped: int = 0  # scans with fewer than min_mapping_pointcloud_size points

    def poses(self) -> np.ndarray:
        return np.array([f.T_map_lidar for f in self.frames])

    def stamps_ns(self) -> np.ndarray:
        return np.array([f.stamp_ns for f in self.frames], dtype=np.int64)


def crop_range(points: np.ndarray, valid: np.ndarray, rmin: float, rmax: float) -> np.ndarray:
    """(N,) mask of valid points with rmin <= range <= rmax."""
    r = np.linalg.norm(points, axis=1)
    return valid & np.isfinite(r) & (r >= rmin) & (r <= rmax)


def voxel_down(points: np.ndarray, leaf: float) -> np.ndarray:
    """(M,3) voxel-grid centroids (single-threaded: the same points in the same order every run)."""
    import small_gicp

    if len(points) == 0:
        return points
    cloud = small_gicp.voxelgrid_sampling(np.ascontiguousarray(points, float), leaf, num_threads=1)
    return np.asarray(cloud.points())[:, :3]


def voxel_pick(points: np.ndarray, leaf: float) -> np.ndarray:
    """Indices of one raw point per voxel (the first): downsampling that keeps each point's own
    time, so the picked points can still be deskewed (a centroid mixes times)."""
    if len(points) == 0:
        return np.zeros(0, np.int64)
    key = np.floor(points / leaf).astype(np.int64)
    key -= key.min(axis=0)
    span = key.max(axis=0) + 1
    flat = (key[:, 0] * span[1] + key[:, 1]) * span[2] + key[:, 2]
    return np.unique(flat, return_index=True)[1]


class LocalMap:
    """The mapping's registration target, the latest ``local_map_num_keyframes`` keyframes in the
    map frame: points with covariances and a KD-tree (GICP), rebuilt at every keyframe; or a
    Gaussian voxel map (VGICP, the NDT-like option; voxel size ``mapper_resolution``) that each
    new keyframe is inserted into (its points downsampled and their covariances estimated in its
    own frame), voxels no keyframe touched among the latest ``local_map_num_keyframes`` dropped."""

    def __init__(self, leaf: float, o):
        self.o, self.leaf = o, leaf
        self.incremental = o.mapper_registrator in ("VGICP", "NDT")
        self.cloud = self.tree = self.voxels = None

    def rebuild(self, frames, ids) -> None:
        """The map of ``frames[ids]`` alone."""
        if self.incremental:
            self.voxels = None
            for j in ids:
                self._insert(frames[j])
            return
        cloud = np.concatenate([frames[j].points @ frames[j].T_map_lidar[:3, :3].T + frames[j].T_map_lidar[:3, 3]
                                for j in ids])
        self.cloud, self.tree = gicp.preprocess(cloud, self.leaf, threads=self.o.mapper_num_threads)

    def add(self, frames, ids) -> None:
        """``ids[-1]`` became a keyframe (``ids``: the keyframes of the local map, the new one last)."""
        if self.incremental and self.voxels is not None:
            self._insert(frames[ids[-1]])
        else:
            self.rebuild(frames, ids)

    def _insert(self, f) -> None:
        import small_gicp

        if self.voxels is None:
            self.voxels = small_gicp.GaussianVoxelMap(self.o.mapper_resolution)
            self.voxels.set_lru(horizon=self.o.local_map_num_keyframes, clear_cycle=1)
        cloud, _ = gicp.preprocess(f.points, self.leaf, threads=self.o.mapper_num_threads)
        self.voxels.insert(cloud, f.T_map_lidar)

    def align(self, src, T0: np.ndarray, max_corr: float):
        kw = dict(init_T_target_source=T0, max_correspondence_distance=max_corr,
                  max_iterations=self.o.mapper_max_iterations)
        if self.voxels is not None:
            return gicp.align(self.voxels, src, **kw)
        return gicp.align(self.cloud, src, self.tree, registration_type="GICP", **kw)


def degeneracy(H: np.ndarray) -> float:
    """Condition number of the registration Hessian (large = some direction unconstrained)."""
    w = np.linalg.eigvalsh(0.5 * (H + H.T))
    return float(w[-1] / max(w[0], 1e-12))


@dataclass
class _Prepared:
    """What the mapping needs of a scan before its registration (see ``_prepare``)."""

    stamp_ns: int
    topic: str
    raw: np.ndarray | None  # (N,3) points in the mapping range (None: too few, the scan is skipped)
    tau: np.ndarray | None = None  # (N,) per-point times (None: no deskew)
    pick: np.ndarray | None = None  # indices into raw of the registration points
    r_max: float = 0.0  # farthest point's range
    span: float = 0.0  # time span of the points (s)


def _prepare(scan, o) -> _Prepared:
    """The scan's points in the mapping range, their times, and one raw point per input voxel
    (evenly thinned to ``mapping_max_source_points``): registration works on those (deskewed on
    each pass), the frame keeps every point for the map."""
    m = crop_range(scan.points, scan.valid, o.mapping_min_range, o.mapping_max_range)
    if m.sum() < o.min_mapping_pointcloud_size:
        return _Prepared(scan.stamp_ns, scan.topic, None)
    raw = scan.points[m]
    tau = scan.time_s[m] if (scan.time_s is not None and o.deskew) else None
    pick = voxel_pick(raw, max(o.leaf_size_input, 0.05))
    if len(pick) > o.mapping_max_source_points:  # evenly thinned: GICP needs thousands, not 40k
        pick = pick[np.linspace(0, len(pick) - 1, o.mapping_max_source_points).astype(np.int64)]
    return _Prepared(scan.stamp_ns, scan.topic, raw, tau, pick,
                     float(np.linalg.norm(raw, axis=1).max()) if len(raw) else 0.0,
                     float(tau.max() - tau.min()) if tau is not None and len(tau) else 0.0)


def build_map(scans, opts, *, progress=None, max_cond: float = 1e4) -> MapResult:
    """Map the mapping LIDAR's scans (a time-ordered iterable of LidarScan, read once: a bag can
    stream through); see the module doc."""
    o = opts
    res = MapResult(topic="?")
    leaf_in = max(o.leaf_size_input, 0.05)
    map_leaf = max(o.leaf_size_local_map, 0.05)
    twist = np.zeros(6)
    T_last = np.eye(4)
    last_stamp = None
    local_ids: list[int] = []
    local = None
    stopped_count = 0
    # reading, cropping and picking the registration points of the next scans go on in a child
    # process (the other core) while this one registers the scan before; progress: optional
    # wrapper of the scan iterable (the orchestration layer's bar)
    prepared = Prefetched(scans, functools.partial(_prepare, o=o))
    with contextlib.closing(prepared):
        for scan in (progress(prepared) if progress is not None else prepared):
            res.n_scans += 1
            res.topic = scan.topic
            if len(res.frames) >= o.mapping_max_frames:
                log.warning("%s: mapping stops at mapping_max_frames=%d (%.1f s into the drive); the rest is not used",
                            res.topic, o.mapping_max_frames, (scan.stamp_ns - res.frames[0].stamp_ns) * 1e-9)
                break
            if scan.raw is None:  # a partial or blocked scan: not worth a frame
                res.skipped += 1
                continue
            raw, tau, pick = scan.raw, scan.tau, scan.pick
            if last_stamp is None:
                pts = deskew(raw, tau, twist).astype(np.float32)
                f = Frame(scan.stamp_ns, pts, np.eye(4), twist.copy(), keyframe=True)
                res.frames.append(f)
                res.keyframe_ids.append(0)
                local_ids = [0]
                local = LocalMap(map_leaf, o)
                local.rebuild(res.frames, local_ids)
                first_raw = (raw, tau)  # re-deskewed once the first twist is known
                T_last, last_stamp = f.T_map_lidar, scan.stamp_ns
                prev_scan_ns = scan.stamp_ns
                continue
            dt = (scan.stamp_ns - last_stamp) * 1e-9
            lost = (scan.stamp_ns - prev_scan_ns) * 1e-9 > o.mapping_lost_timeout  # sensor gap, not a skipped frame
            prev_scan_ns = scan.stamp_ns
            T = T_last @ T_exp(twist * dt)
            T_pred = T
            xi = twist
            n_it = max(1, o.deskew_iterations if tau is not None else 1)
            for it in range(n_it + (n_it if first_raw is not None and first_raw[1] is not None else 0)):
                if first_raw is not None and first_raw[1] is not None and it == n_it:
                    # the first frame (the map origin) was deskewed with zero twist: redo it, then re-register
                    f0 = res.frames[0]
                    f0.points, f0.twist = deskew(first_raw[0], first_raw[1], xi).astype(np.float32), xi.copy()
                    local.rebuild(res.frames, [0])
                src, _ = gicp.preprocess(deskew(raw[pick], None if tau is None else tau[pick], xi), leaf_in,
                                         threads=o.mapper_num_threads)
                fine = max(o.mapper_max_correspondence_distance, 3 * leaf_in)
                r = local.align(src, T, fine)
                if it == 0 and (not r.converged or r.num_inliers < 0.5 * src.size()):
                    # the constant-velocity guess was off (a bump, a stop): coarse pass first
                    r = local.align(src, local.align(src, T, 1.0).T_target_source, fine)
                T = r.T_target_source
                xi_used, xi = xi, twist_between(T_last, T, dt)
                if tau is not None and first_raw is None and it + 1 < n_it:
                    # another deskew pass only if the twist changed enough to move points by > 1 mm
                    d = xi - xi_used
                    if (np.linalg.norm(d[:3]) * scan.r_max + np.linalg.norm(d[3:])) * scan.span < 1e-3:
                        break
            pts = deskew(raw, tau, xi).astype(np.float32)  # float32: a drive's frames are most of the memory
            first_raw = None
            H = np.asarray(r.H)
            cond = degeneracy(H)
            rel = np.linalg.inv(T_last) @ T
            dist = np.linalg.norm(rel[:3, 3])
            v_new, v_old = xi[3:], twist[3:]
            acc = np.linalg.norm(v_new - v_old) / max(dt, 1e-3)
            ang = np.degrees(np.linalg.norm(xi[:3] * dt))
            # the constant-velocity prediction missed by more than the seed's interpolation error
            pred_err = float(np.linalg.norm((np.linalg.inv(T_pred) @ T)[:3, 3]))
            lost = lost or acc > o.lost_frame_max_acceleration or ang > o.lost_frame_max_angle_diff \
                or (len(res.frames) >= 2 and pred_err > o.lost_frame_interpolation_error)
            if dist < o.new_frame_min_distance and not lost:
                if dist < o.frame_stopped_distance:
                    stopped_count += 1
                    if stopped_count != o.frames_since_stopped_force_frame:
                        twist = xi
                        continue
                else:
                    twist = xi
                    continue
            stopped = stopped_count >= o.frames_since_stopped_force_frame
            stopped_count = 0 if not stopped else stopped_count
            f = Frame(scan.stamp_ns, pts, T, xi.copy(), stopped=stopped, lost=lost, H=H, T_prev_cur=rel, cond=cond)
            res.frames.append(f)
            k = len(res.frames) - 1
            kf_T = res.frames[res.keyframe_ids[-1]].T_map_lidar
            if lost:
                log.warning("%s: lost frame at %.3f s (gap/accel/heading); local map restarts", res.topic,
                            scan.stamp_ns * 1e-9)
                local_ids = []
            if lost or np.linalg.norm(np.linalg.inv(kf_T)[:3] @ np.r_[T[:3, 3], 1]) >= o.new_keyframe_min_distance:
                f.keyframe = True
                res.keyframe_ids.append(k)
                local_ids = (local_ids + [k])[-o.local_map_num_keyframes:]
                if lost:
                    local.rebuild(res.frames, local_ids)  # the local map restarts
                else:
                    local.add(res.frames, local_ids)
            T_last, last_stamp, twist = T, scan.stamp_ns, xi
    if res.n_scans < 3:
        raise DataError(f"{res.topic}: only {res.n_scans} scans; mapping needs a drive")
    if len(res.frames) < 3 and res.skipped >= res.n_scans / 2:
        raise DegenerateError(f"{res.topic}: mapping is degenerate: {res.skipped} of {res.n_scans} scans have fewer "
                              f"than min_mapping_pointcloud_size={o.min_mapping_pointcloud_size} points within "
                              f"{o.mapping_min_range}-{o.mapping_max_range} m (an open field, a blocked LIDAR?)")
    conds = np.array([f.cond for f in res.frames[1:]])
    if len(conds) and np.median(conds) > max_cond:
        raise DegenerateError(f"{res.topic}: mapping is degenerate (median registration condition number "
                              f"{np.median(conds):.3g} > {max_cond:g}): the scene has no structure that fixes "
                              "the motion (open flat field?)")
    P = res.poses()
    path = float(np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1).sum()) if len(P) > 1 else 0.0
    if len(res.keyframe_ids) < 3 or path < 2 * o.new_keyframe_min_distance:
        raise DegenerateError(f"{res.topic}: the vehicle did not move (only {len(res.keyframe_ids)} keyframes, "
                              f"{path:.2f} m travelled over {res.n_scans} scans); drive through the scene")
    return res
