"""Registration of calibration-LIDAR scans to dense mapping clouds: ensemble, scoring, per-frame refinement.

SYNOPSIS
    prob = prepare_frames(chosen, map_result, T_lidar0_sensor_guess, opts)  # dense targets + deskewed sources
    T_best, cands = ensemble(prob, T_guess, opts)     # best candidate on ALL frames (the guess stays one)
    deskew_sources(prob, T_best)                      # the sensor's motion seen through the better extrinsic
    meas = refine_per_frame(prob, T_best, opts)       # per-frame T_k (4,4), Hessian H_k (6,6), graph links
    edges = keyframe_edges(map_result, positions, opts)  # submap-to-submap registrations (graph.KeyframeEdge)

All clouds of one frame are expressed in the mapping LIDAR frame at the calibration
scan's stamp (the interpolated pose), so every registration directly estimates
T_lidar0_sensor. A dense target is made of keyframe submaps (each keyframe's frames up to
the next keyframe); each frame's measurement records how its registration would move if a
submap moved (``influence``), which is how targetless/keyframe_graph.py ties frames to keyframe poses.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np

from . import gicp
from .deskew import deskew
from .mapping import crop_range

log = logging.getLogger(__name__)


@dataclass
class TargetParts:
    """Which keyframe submaps made each point of a dense target (for the graph's links): point i
    is the centroid of a voxel holding ``counts[start[i]:start[i + 1]]`` raw points of the
    submaps ``positions[group[start[i]:start[i + 1]]]``."""
    start: np.ndarray  # (M+1,) int64
    group: np.ndarray  # (P,) int64 index into positions, per (voxel, submap) pair
    counts: np.ndarray  # (P,) int32 raw points per (voxel, submap) pair
    positions: np.ndarray  # group index -> keyframe position (index into MapResult.keyframe_ids)
    anchor: int  # keyframe position of the calibration frame's own keyframe
    T_anchor_kf: dict  # keyframe position -> (4,4) pose of its submap in the target's frame

    def pairs(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row into ``idx`` (P',), pair index (P',)) of every (voxel, submap) pair of points ``idx``."""
        lo = self.start[idx]
        cnt = self.start[idx + 1] - lo
        rows = np.repeat(np.arange(len(idx)), cnt)
        return rows, np.repeat(lo - (np.cumsum(cnt) - cnt), cnt) + np.arange(cnt.sum())

    def subset(self, keep: np.ndarray) -> "TargetParts":
        """The parts of the points where ``keep`` (a mask over the target's points) holds."""
        idx = np.flatnonzero(keep)
        _, at = self.pairs(idx)
        cnt = self.start[idx + 1] - self.start[idx]
        return dataclasses.replace(self, start=np.r_[0, np.cumsum(cnt)], group=self.group[at],
                                   counts=self.counts[at])


@dataclass
class FrameData:
    """One calibration frame's registration problem. Its dense target (~300k points within the
    source's reach on the 10 s bench drive) is kept light: points, a KD-tree and the normals used
    so far (~90 B per point); the GICP covariances (128 B per point) are built once, when the
    frame is first registered (``gicp_target``), and freed by ``release`` after its refinement.
    Source clouds are downsampled once per leaf size."""
    cf: object  # CalibrationFrame
    target_pts: np.ndarray  # (M,3) float32 dense, lidar0 frame at the scan stamp (5 um at 80 m)
    source_pts: np.ndarray  # (N,3) deskewed sensor points
    tree: object = None  # small_gicp.KdTree of target_pts (same order)
    parts: TargetParts | None = None
    normals: np.ndarray | None = None  # (M,3) float32 target normals, computed where first needed (NaN before)
    raw_pts: np.ndarray | None = None  # (N,3) the cropped source before deskew, and its per-point times
    raw_time: np.ndarray | None = None
    threads: int = 1
    cloud: object = field(default=None, repr=False)  # small_gicp.PointCloud of target_pts (the tree's)
    _sources: dict = field(default_factory=dict, repr=False)  # leaf -> preprocessed source cloud
    _gicp: object = field(default=None, repr=False)  # target cloud with covariances, while registering

    @classmethod
    def make(cls, cf, target_pts: np.ndarray, source_pts: np.ndarray, *, threads: int = 1, **kw) -> "FrameData":
        """A frame with the KD-tree of its (already downsampled) dense target."""
        import small_gicp

        tgt = np.ascontiguousarray(target_pts, np.float32)
        cloud = small_gicp.PointCloud(tgt.astype(float))  # the same rounded points as target_pts
        return cls(cf, tgt, np.asarray(source_pts, float), small_gicp.KdTree(cloud, num_threads=threads),
                   normals=np.full(tgt.shape, np.nan, np.float32), threads=threads, cloud=cloud, **kw)

    def set_source(self, source_pts: np.ndarray) -> None:
        self.source_pts = source_pts
        self._sources.clear()

    def source_cloud(self, leaf: float):
        if leaf not in self._sources:
            self._sources[leaf] = gicp.preprocess(self.source_pts, leaf, threads=self.threads)[0]
        return self._sources[leaf]

    def gicp_target(self):
        """The target with covariances (built on first use, until ``release``)."""
        if self._gicp is None:
            import small_gicp

            self._gicp = gicp.prepared(small_gicp.PointCloud(self.target_pts.astype(float)), threads=self.threads,
                                       tree=self.tree)[0]
        return self._gicp

    def release(self) -> None:
        """Free what only registration needs (covariances, source clouds)."""
        self._gicp = None
        self._sources.clear()

    def nearest(self, points: np.ndarray, max_dist: float):
        """(distance (N,), target index (N,)) of each point's nearest target point; inf and -1
        beyond ``max_dist``."""
        d2, idx = gicp.nearest(self.tree, points, threads=self.threads)
        far = ~(d2 <= max_dist * max_dist)
        d = np.sqrt(d2)
        d[far], idx[far] = np.inf, -1
        return d, idx

    def normals_at(self, idx: np.ndarray) -> np.ndarray:
        """(N,3) float32 normals of target points ``idx``, from their ``gicp.NUM_NEIGHBORS`` nearest
        target points (computed once per point, where first needed)."""
        new = np.unique(idx[np.isnan(self.normals[idx, 0])])
        if len(new):
            nb, _ = self.tree.batch_knn_search(self.target_pts[new].astype(float), gicp.NUM_NEIGHBORS,
                                               num_threads=self.threads)
            q = self.target_pts[nb.astype(np.int64)].astype(float)
            q -= q.mean(axis=1, keepdims=True)
            self.normals[new] = np.linalg.eigh(np.einsum("pki,pkj->pij", q, q))[1][:, :, 0]  # least spread
        return self.normals[idx]


def voxel_index(points: np.ndarray, leaf: float) -> np.ndarray:
    """(N,3) int64 voxel of each point (floor of points / leaf)."""
    return np.floor(points * (1.0 / leaf)).astype(np.int64)


def pack(index: np.ndarray) -> np.ndarray:
    """(N,) int64 code of (N,3) voxel indices, 19 bits per axis (+-13 km at 5 cm)."""
    c = (index[:, 0] + (1 << 18)) << 38
    c |= (index[:, 1] + (1 << 18)) << 19
    c |= index[:, 2] + (1 << 18)
    return c


def voxel_codes(points: np.ndarray, leaf: float) -> np.ndarray:
    """(N,) int64 voxel code of each point (``pack`` of ``voxel_index``)."""
    return pack(voxel_index(points, leaf))


def reach_cells(source_pts: np.ndarray, origin: np.ndarray, *, cell: float = 1.0, margin_m: float = 1.0,
                margin_per_m: float = np.tan(np.radians(3.0)), max_cells: int = 16) -> np.ndarray:
    """Sorted ``voxel_codes`` at ``cell`` of the cells a registration of ``source_pts`` (placed by
    the initial guess) can use: those within ``margin_m + margin_per_m * range`` (range from
    ``origin``, the source sensor) of a source point's cell, so a guess that is off by up to ~3
    deg and a few decimetres still finds all its correspondences."""
    if len(source_pts) == 0:
        return np.zeros(0, np.int64)
    own = np.unique(voxel_codes(source_pts, cell))
    centre = (_decode(own) + 0.5) * cell
    k = np.minimum(np.ceil((margin_m + margin_per_m * np.linalg.norm(centre - origin, axis=1)) / cell),
                   max_cells).astype(np.int64)
    reach = []
    for kk in np.unique(k):  # a cube of +-kk cells, dilated one axis at a time
        c = own[k == kk]
        for shift in (1 << 38, 1 << 19, 1):
            c = np.unique((c[:, None] + shift * np.arange(-kk, kk + 1)).ravel())
        reach.append(c)
    return np.unique(np.concatenate(reach))


def _member(codes: np.ndarray, sorted_codes: np.ndarray) -> np.ndarray:
    """(N,) whether each of ``codes`` is in ``sorted_codes``."""
    if len(sorted_codes) == 0:
        return np.zeros(len(codes), bool)
    return sorted_codes[np.minimum(np.searchsorted(sorted_codes, codes), len(sorted_codes) - 1)] == codes


def _decode(codes: np.ndarray) -> np.ndarray:
    """(N,3) integer cell indices of voxel_codes."""
    m = (1 << 19) - 1
    return np.c_[(codes >> 38) & m, (codes >> 19) & m, codes & m] - (1 << 18)


@dataclass
class _Submap:
    """One keyframe submap's dense frames as voxels of the map frame (``DenseMap.leaf``), grouped
    by reach cell (``DenseMap.n`` voxels a side), 24 B a voxel."""
    codes: np.ndarray  # (V,) int64 voxel_codes
    offsets: np.ndarray  # (V,3) float32 centroid of the voxel's points, from its corner
    counts: np.ndarray  # (V,) int32 points in each voxel
    cells: np.ndarray  # (C,) int64 sorted voxel_codes of the reach cells
    cell_sizes: np.ndarray  # (C,) voxels of each cell (in order)


class DenseMap:
    """The calibration frames' dense targets of one map. A frame's target is the centroids of
    the map-frame voxels (``leaf_size_dense_map``) of the mapping frames within
    +-dense_pointcloud_num_keyframes keyframe submaps of its own, within reach of its source
    (``reach``), in lidar0 at its stamp. The mapping frames used are every ``step``-th, the
    same for every target (``step``: at most ``max_frames`` in the widest window), so
    neighbouring targets share their submaps' voxels, made once for all frames
    (``make_submaps``) and only where some frame's source reaches."""

    def __init__(self, mp, o, *, max_frames: int = 40):
        self.mp, self.o = mp, o
        self.leaf = max(o.leaf_size_dense_map, 0.02)
        self.n = max(1, round(0.5 / self.leaf))  # reach cells of whole voxels: 0.5 m at 5 cm
        kf = np.asarray(mp.keyframe_ids, np.int64)
        self._ends = np.r_[kf[1:], len(mp.frames)]
        widest = max(self._ends[w[-1]] - kf[w[0]] for w in map(self.window, range(len(kf))))
        self.step = max(1, -(-int(widest) // max_frames))
        self._submaps: dict = {}
        self._within = None

    def window(self, kpos: int) -> range:
        """Keyframe positions of the submaps in the dense target of a frame at keyframe ``kpos``."""
        N = self.o.dense_pointcloud_num_keyframes
        return range(max(0, kpos - N), min(len(self.mp.keyframe_ids), kpos + N + 1))

    def reach(self, T_map_lidar0: np.ndarray, source_pts: np.ndarray, origin: np.ndarray) -> np.ndarray:
        """Sorted map-frame codes of the reach cells (``reach_cells``) of a source (N,3) placed in
        lidar0 by the guess, ``origin`` its sensor's position in lidar0; the margin: the coarse
        correspondence distance and 0.5 m of guess error and point neighbourhood."""
        R, t = T_map_lidar0[:3, :3], T_map_lidar0[:3, 3]
        return reach_cells(source_pts @ R.T + t, R @ origin + t, cell=self.leaf * self.n,
                           margin_m=self.o.max_corr_dist_coarse + 0.5)

    def make_submaps(self, kids, within: np.ndarray | None = None) -> None:
        """Make the submaps of the targets of frames at keyframes ``kids`` (before a fork: both
        processes then share them), of the points in the reach cells ``within`` only (sorted codes,
        e.g. the union of the frames' ``reach``; None: all)."""
        self._submaps, self._within = {}, within
        for kid in kids:
            for pos in self.window(self.mp.keyframe_ids.index(kid)):
                self.submap(pos)

    def submap(self, pos: int) -> _Submap:
        if pos not in self._submaps:
            first = self.mp.keyframe_ids[pos]
            frames = [self.mp.frames[j] for j in range(first, int(self._ends[pos])) if j % self.step == 0]
            # none where a submap is shorter than step: its neighbours' frames cover it
            q = np.concatenate([np.zeros((0, 3))] + [f.points @ f.T_map_lidar[:3, :3].T + f.T_map_lidar[:3, 3]
                                                     for f in frames])
            index = voxel_index(q, self.leaf)
            if self._within is not None:
                keep = _member(pack(np.floor_divide(index, self.n)), self._within)
                q, index = q[keep], index[keep]
            code, order = _sorted(pack(index))
            start = np.flatnonzero(np.diff(code, prepend=code[:1] - 1))
            codes, counts = code[start], np.diff(np.r_[start, len(code)]).astype(np.int32)
            index = index[order[start]]
            offsets = np.add.reduceat(q[order], start) / counts[:, None] - index * self.leaf
            cell, by = _sorted(pack(np.floor_divide(index, self.n)))
            first = np.flatnonzero(np.diff(cell, prepend=cell[:1] - 1))
            self._submaps[pos] = _Submap(codes[by], offsets[by].astype(np.float32), counts[by], cell[first],
                                         np.diff(np.r_[first, len(cell)]))
        return self._submaps[pos]

    def target(self, kid: int, T_map_lidar0: np.ndarray, *, reach: np.ndarray | None = None,
               z_max: float = np.inf):
        """(M,3) dense target of a frame at keyframe ``kid`` whose lidar0 pose is T_map_lidar0, in
        lidar0, and its TargetParts; only the voxels in the cells ``reach`` (sorted codes, see
        ``reach``; None: all) and up to ``z_max`` (lidar0)."""
        o = self.o
        kpos = self.mp.keyframe_ids.index(kid)
        positions = np.asarray(self.window(kpos))
        keys, offsets, counts = [], [], []
        for label, pos in enumerate(positions):
            s = self.submap(int(pos))
            keep = np.repeat(_member(s.cells, reach), s.cell_sizes) if reach is not None else slice(None)
            keys.append(s.codes[keep] * 64 + label)  # (voxel, submap label): unique, a submap's voxels are
            offsets.append(s.offsets[keep])
            counts.append(s.counts[keep])
        key, order = _sorted(np.concatenate(keys))
        offsets, counts = np.concatenate(offsets)[order], np.concatenate(counts)[order]
        start = np.flatnonzero(np.diff(key >> 6, prepend=(key[:1] >> 6) - 1))  # of each voxel
        Tinv = np.linalg.inv(T_map_lidar0)
        parts = TargetParts(np.r_[start, len(key)], key & 63, counts, positions, kpos,
                            {int(p): Tinv @ self.mp.frames[self.mp.keyframe_ids[p]].T_map_lidar for p in positions})
        if len(key) == 0:
            return np.zeros((0, 3)), parts
        n = np.add.reduceat(counts, start)
        corner = _decode(key[start] >> 6) * self.leaf
        centroids = np.add.reduceat(offsets * counts[:, None], start) / n[:, None] + corner
        pts = centroids @ Tinv[:3, :3].T + Tinv[:3, 3]
        r = np.linalg.norm(pts, axis=1)
        keep = (r >= o.min_calibration_range) & (r <= o.max_calibration_range) & (pts[:, 2] <= z_max)
        return pts[keep], parts.subset(keep)


def _sorted(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sorted a, the order that sorts it), stable: a merge of sorted runs is fast (timsort)."""
    order = np.argsort(a, kind="stable")
    return a[order], order


def _adjoint_to_sensor(T_lidar0_sensor: np.ndarray, xi: np.ndarray) -> np.ndarray:
    import gtsam

    return gtsam.Pose3(np.linalg.inv(T_lidar0_sensor)).AdjointMap() @ xi


def _source(cf, T_guess: np.ndarray, o, deskew_on: bool):
    """(cropped raw source, its times, deskewed source, the same in lidar0 at the guess) of one calibration frame."""
    s = cf.scan
    m = crop_range(s.points, s.valid, o.min_calibration_range, o.max_calibration_range)
    raw, tau = s.points[m], (s.time_s[m] if (deskew_on and s.time_s is not None) else None)
    src = deskew(raw, tau, _adjoint_to_sensor(T_guess, cf.twist_lidar0))
    return raw, tau, src, src @ T_guess[:3, :3].T + T_guess[:3, 3]


def prepare_frames(chosen, mp, T_guess: np.ndarray, o, *, deskew_on: bool = True, progress=None) -> list:
    """Dense targets and deskewed, cropped sources for the selected calibration frames. The
    submaps are made once, within reach of some frame's source; every other frame's target is
    then made in a forked child (the other core; background.py), the same function on the same
    data, so the same frames as one process would make. The submaps are freed on return."""
    from .background import Background

    chosen = list(chosen)
    sources = [_source(cf, T_guess, o, deskew_on) for cf in chosen]
    dense = DenseMap(mp, o)
    reach = [dense.reach(cf.T_map_lidar0, src0, T_guess[:3, 3]) for cf, (*_, src0) in zip(chosen, sources)]
    dense.make_submaps([cf.keyframe_id for cf in chosen], within=np.unique(np.concatenate(reach)))

    def targets(frames):
        z_top = [src0[:, 2].max() + o.crop_z_calibration_pointclouds_value if o.crop_z_calibration_pointclouds
                 else np.inf for *_, src0 in (sources[i] for i in frames)]
        return [dense.target(chosen[i].keyframe_id, chosen[i].T_map_lidar0, reach=reach[i], z_max=z)
                for i, z in zip(frames, z_top)]

    other = Background(targets, range(1, len(chosen), 2))
    try:
        mine = targets(range(0, len(chosen), 2))
        theirs = other.result()
    finally:
        other.cancel()  # only where an error left it running
    out = []
    for i, cf in enumerate(chosen):
        (raw, tau, src, _), (tgt, parts) = sources[i], (theirs if i % 2 else mine)[i // 2]
        out.append(FrameData.make(cf, tgt, src, threads=o.mapper_num_threads, parts=parts, raw_pts=raw, raw_time=tau))
        log.debug("frame at keyframe %d: dense target of %d points, source of %d", cf.keyframe_id, len(tgt), len(src))
        if progress is not None:
            progress(1)
    return out


def deskew_sources(frames, T_lidar0_sensor: np.ndarray) -> None:
    """Deskew the sources again with the mapping twist seen through T_lidar0_sensor: the guess's
    error tilts the sensor's velocity (2 deg of it biased every frame by ~0.7 mm in the simulator)."""
    for fd in frames:
        fd.set_source(deskew(fd.raw_pts, fd.raw_time, _adjoint_to_sensor(T_lidar0_sensor, fd.cf.twist_lidar0)))


def score(frames, T: np.ndarray, o, *, sub: int = 4) -> float:
    """Mean truncated squared source-to-target distance over all frames (lower is better)."""
    return truncated_score(squared_distances(frames, T, sub=sub), o)


def squared_distances(frames, T: np.ndarray, *, sub: int = 4) -> list:
    """Per frame, (N,) squared distance of every ``sub``-th source point, placed by T_lidar0_sensor
    = T, to its nearest target point."""
    return [gicp.nearest(fd.tree, fd.source_pts[::sub] @ T[:3, :3].T + T[:3, 3], threads=fd.threads)[0]
            for fd in frames]


def truncated_score(d2s: list, o) -> float:
    """``score`` of the frames' squared_distances: their mean, each truncated at
    ``calibration_eval_max_corr_distance`` squared."""
    c2 = o.calibration_eval_max_corr_distance ** 2
    n = sum(len(d2) for d2 in d2s)
    return sum(float(np.minimum(d2, c2).sum()) for d2 in d2s) / max(n, 1)


def _run(fd, T0, kind, corr, o, leaf):
    """T_lidar0_sensor from one registration of frame ``fd``'s source (downsampled to ``leaf``) from T0."""
    kw = dict(init_T_target_source=T0, max_correspondence_distance=corr, max_iterations=min(o.solver_iterations, 60))
    src = fd.source_cloud(leaf)
    if kind == "VGICP":  # Gaussian voxels of the correspondence distance's size
        return gicp.align(gicp.voxel_map(fd.gicp_target(), corr), src, **kw).T_target_source
    target = fd.cloud if kind == "ICP" else fd.gicp_target()  # point-to-point ICP needs no covariances
    return gicp.align(target, src, fd.tree, registration_type=kind, **kw).T_target_source


# The ensemble stops once this many frames in a row (each registered from the best so far)
# left the best where it was, within their own uncertainty: more frames from the same start
# find the same pose.
_AGREEING_FRAMES = 3
_CHI2_6DOF_99 = 16.81  # 99 % quantile of chi-square with 6 degrees of freedom


def agrees(fd: FrameData, T_best: np.ndarray, Ts, o) -> bool:
    """Whether every T of ``Ts`` (T_lidar0_sensor) lies within frame ``fd``'s 99 % uncertainty of
    T_best: d = Log(T_best^-1 T) (right perturbation, [omega, v]) with d^T H d / sigma^2 under the
    6-DOF chi-square quantile, H the point-to-plane information at T_best and sigma^2 its mean
    squared residual. Independent point errors make H optimistic, so the test errs on the strict side."""
    import gtsam

    J, r, _ = plane_residuals(fd, T_best, o.max_corr_dist_fine)
    if len(r) < 6:
        return False
    H = J.T @ J / max(float(np.mean(r * r)), 1e-12)
    Tinv = np.linalg.inv(T_best)
    ds = [np.asarray(gtsam.Pose3.Logmap(gtsam.Pose3(Tinv @ T))) for T in Ts]
    return all(float(d @ H @ d) < _CHI2_6DOF_99 for d in ds)


def _largest_shift(points: np.ndarray, T_a: np.ndarray, T_b: np.ndarray) -> float:
    """Largest distance (m) between a point of ``points`` placed by T_a and by T_b."""
    D = T_b - T_a
    return float(np.max(np.linalg.norm(points @ D[:3, :3].T + D[:3, 3], axis=1))) if len(points) else 0.0


def ensemble(frames, T_guess: np.ndarray, o, *, progress=None):
    """Best T_lidar0_sensor among the guess, per-frame registrations (VGICP, GICP, ICP
    coarse-to-fine) and a batched ICP over all frames.

    Each registration starts from the best candidate so far; every candidate is scored
    on all frames. Point-to-point ICP coarse-to-fine (the widest basin, ~4x the cost of the
    others together) runs on a frame only where VGICP and GICP moved the best beyond that frame's
    own uncertainty (``agrees``) and moved some source point by more than the ultra-fine
    correspondence distance: where they left it, the best is already at the frame's optimum, and
    where they moved it less, it started inside the finest basin, which ICP's coarse stages only
    widen; either way ICP from there finds nothing better (point-to-point ICP is biased by
    decimetres on a 16-ring scan). Once ``_AGREEING_FRAMES`` frames in a row left the best where
    it was, the other frames are not registered one by one.
    Returns (T_best (4,4), list of (name, frame index (-1: all), score)).
    """
    best, best_s = T_guess, score(frames, T_guess, o)
    cands = [("initial guess", -1, best_s)]
    leaf = 0.1
    in_a_row = 0

    def candidate(name, i, T):
        nonlocal best, best_s
        s = score(frames, T, o)
        cands.append((name, i, s))
        if s < best_s:
            best, best_s = T, s

    for i, fd in enumerate(frames):
        before = best
        candidate("VGICP", i, _run(fd, best, "VGICP", o.max_corr_dist_coarse, o, leaf))
        T = _run(fd, best, "GICP", o.max_corr_dist_coarse, o, leaf)
        candidate("GICP", i, _run(fd, T, "GICP", o.max_corr_dist_fine, o, leaf))
        settled = agrees(fd, before, [best], o)
        if not settled and _largest_shift(fd.source_pts, before, best) > o.max_corr_dist_ultra_fine:
            T = _run(fd, best, "ICP", o.max_corr_dist_coarse, o, leaf)
            T = _run(fd, T, "ICP", o.max_corr_dist_fine, o, leaf)
            candidate("ICP coarse-to-fine", i, _run(fd, T, "ICP", o.max_corr_dist_ultra_fine, o, leaf))
            settled = agrees(fd, before, [best], o)
        # the target's covariances stay for refine_per_frame (built once; it releases them)
        if progress is not None:
            progress(1)
        in_a_row = in_a_row + 1 if settled else 0
        if in_a_row >= _AGREEING_FRAMES and i + 1 < len(frames):
            log.info("ensemble: %d frames in a row left the best within their uncertainty; "
                     "%d of %d frames registered", in_a_row, i + 1, len(frames))
            break
    T = batched_icp(frames, best, o)  # all frames at once, from the best single-frame result
    s = score(frames, T, o)
    cands.append(("batched ICP", -1, s))
    if s < best_s:
        best, best_s = T, s
    return best, cands


@dataclass
class FrameMeasurement:
    T: np.ndarray  # (4,4) T_lidar0_sensor from this frame alone
    H: np.ndarray  # (6,6) GICP Hessian, tangent [omega, v] right perturbation
    n_inliers: int
    error: float
    anchor: int | None = None  # keyframe position whose pose anchors the target (graph link)
    influence: dict = field(default_factory=dict)  # keyframe position -> B (6,6), see factors/map_registration.py


def plane_residuals(fd: FrameData, T: np.ndarray, max_corr: float, sub: int = 1):
    """Point-to-plane residuals of every ``sub``-th source point at T_lidar0_sensor = T against its
    nearest target point (within max_corr): (J (N,6) w.r.t. T's right perturbation, r (N,) m,
    target indices (N,)). Normals from the 10 nearest target points."""
    R, t = T[:3, :3], T[:3, 3]
    p = fd.source_pts[::sub]
    x = p @ R.T + t
    d, idx = fd.nearest(x, max_corr)
    ok = np.isfinite(d)
    p, x, idx = p[ok], x[ok], idx[ok]
    n = fd.normals_at(idx).astype(float)
    m = n @ R  # R^T n
    J = np.c_[np.cross(p, m), m]  # d(n . (R p + t)) / d[omega, v]
    return J, np.einsum("pi,pi->p", n, x - fd.target_pts[idx]), idx


def batched_icp(frames, T0: np.ndarray, o, *, iterations: int = 15, sub: int = 2) -> np.ndarray:
    """The seed's Batched ICP: one T_lidar0_sensor registering all frames at once (point-to-plane
    Gauss-Newton over the stacked residuals, Huber-weighted), fine then ultra-fine correspondences."""
    from ..geometry import T_exp

    T = np.asarray(T0, float)
    for corr in (o.max_corr_dist_fine, o.max_corr_dist_ultra_fine):
        for _ in range(iterations):
            H, g = np.zeros((6, 6)), np.zeros(6)
            for fd in frames:
                J, r, _ = plane_residuals(fd, T, corr, sub)
                w = np.minimum(1.0, 0.5 * corr / np.maximum(np.abs(r), 1e-12))  # Huber at corr / 2
                H += (J * w[:, None]).T @ J
                g += (J * w[:, None]).T @ r
            if not np.isfinite(H).all() or np.linalg.cond(H) > 1e12:
                return T
            dx = -np.linalg.solve(H, g)
            T = T @ T_exp(dx)
            # 0.06 mdeg / 0.01 mm: far below a frame's sigma; changing correspondences can make the
            # steps cycle at ~1e-7 rad / 2e-6 m (measured) instead of shrinking further
            if np.linalg.norm(dx[:3]) < 1e-6 and np.linalg.norm(dx[3:]) < 1e-5:
                break
    return T


def influence(fd: FrameData, T: np.ndarray, o) -> dict:
    """Keyframe position -> B_j = -H^-1 H_j Ad(T^-1 T_anchor_kf_j): how the registration moves
    when keyframe j's submap moves. H_j is the point-to-plane information of the correspondences
    at T, split among submaps by their share of each target voxel's points."""
    import gtsam

    pa = fd.parts
    J, _, idx = plane_residuals(fd, T, o.max_corr_dist_fine)
    # share of each submap in each corresponding target voxel
    frac = np.zeros((len(idx), len(pa.positions)))
    rows, at = pa.pairs(idx)
    np.add.at(frac, (rows, pa.group[at]), pa.counts[at])
    frac /= frac.sum(axis=1, keepdims=True)
    Hj = np.einsum("pg,pi,pk->gik", frac, J, J)
    H = Hj.sum(axis=0)
    w = np.linalg.eigvalsh(H)
    if w[0] <= 1e-12 * max(w[-1], 1e-300):  # degenerate frame: no links (fuse reports the degeneracy)
        return {}
    Hinv = np.linalg.inv(H)
    Tinv = np.linalg.inv(T)
    return {int(pos): -Hinv @ Hj[g] @ gtsam.Pose3(Tinv @ pa.T_anchor_kf[int(pos)]).AdjointMap()
            for g, pos in enumerate(pa.positions) if Hj[g].trace() > 0}


def _refine(frames, T0: np.ndarray, o, threads: int | None = None) -> list:
    """FrameMeasurement per frame of ``frames``: fine GICP from T0 (``threads``: the frames' own
    thread count replaced, e.g. by 1 in a forked child, where OpenMP cannot start threads)."""
    out = []
    kw = dict(registration_type="GICP", max_iterations=min(o.solver_iterations, 60))
    for fd in frames:
        if threads is not None:
            fd.threads = threads
        tgt, src = fd.gicp_target(), fd.source_cloud(0.05)
        r = gicp.align(tgt, src, fd.tree, init_T_target_source=T0, max_correspondence_distance=o.max_corr_dist_fine, **kw)
        r = gicp.align(tgt, src, fd.tree, init_T_target_source=r.T_target_source,
                       max_correspondence_distance=o.max_corr_dist_ultra_fine, **kw)
        fd.release()
        T = np.asarray(r.T_target_source)
        links = influence(fd, T, o) if fd.parts is not None else {}
        out.append(FrameMeasurement(T, np.asarray(r.H), int(r.num_inliers), float(r.error),
                                    fd.parts.anchor if fd.parts is not None else None, links))
    return out


def refine_per_frame(frames, T0: np.ndarray, o) -> list:
    """Fine GICP of each frame from T0; returns FrameMeasurement per frame (with its graph links).
    Every other frame is refined in a forked child (background.py; per-point covariances are the
    same on one thread): the same measurements as one process makes."""
    from .background import Background

    frames = list(frames)
    other = Background(_refine, frames[1::2], T0, o, 1)
    for fd in frames[1::2]:
        # the child has them (forked) and frees each after use; this process's copy is not needed
        # (without fork the child's part runs here at result() and builds them again, the same)
        fd.release()
    try:
        mine = _refine(frames[0::2], T0, o)
        theirs = other.result()
    finally:
        other.cancel()  # only where an error left it running
    return [(theirs if i % 2 else mine)[i // 2] for i in range(len(frames))]


def submap(mp, pos: int, *, max_frames: int = 3) -> np.ndarray:
    """(N,3) points of keyframe ``pos``'s frames (up to the next keyframe) in that keyframe's frame."""
    k = mp.keyframe_ids
    end = k[pos + 1] if pos + 1 < len(k) else len(mp.frames)
    ids = np.unique(np.linspace(k[pos], end - 1, max_frames).round().astype(int))
    Tinv = np.linalg.inv(mp.frames[k[pos]].T_map_lidar)
    clouds = []
    for j in ids:
        T = Tinv @ mp.frames[j].T_map_lidar
        clouds.append(mp.frames[j].points @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(clouds)


def all_keyframe_edges(mp, o) -> dict:
    """``keyframe_edges``' cache for every keyframe of the map: (a, b) -> KeyframeEdge or None,
    b = a + 1 and a + 2 (each registration depends on its two submaps only: the same edges as
    those computed for fewer keyframes)."""
    import dataclasses

    cache: dict = {}
    # one thread: run in a forked child (background.py), where OpenMP's thread team of the parent
    # is gone (2 threads hung there); the same bytes whatever the thread count (gicp.py)
    keyframe_edges(mp, range(len(mp.keyframe_ids)), dataclasses.replace(o, mapper_num_threads=1), cache=cache)
    return cache


def keyframe_edges(mp, positions, o, *, cache: dict | None = None, max_cond: float = 1e6,
                   min_inlier_share: float = 0.3) -> list:
    """Registrations of keyframe submaps j+1 and j+2 to j's, for the keyframe positions given
    (KeyframeEdge list); a failed or degenerate registration gives no edge. The mapping's
    relative poses are the initial guesses (millimetres off), so one fine GICP pass suffices.
    ``cache``: (a, b) -> KeyframeEdge or None, shared between calibration LIDARs."""
    from .keyframe_graph import KeyframeEdge
    from .mapping import degeneracy

    cache = {} if cache is None else cache
    leaf = 2 * max(o.leaf_size_local_map, 0.05)  # neighbouring submaps overlap almost entirely: coarse is enough
    positions = sorted(set(int(p) for p in positions))
    pairs = [(a, b) for a in positions for b in (a + 1, a + 2) if b in positions and (a, b) not in cache]
    clouds = {}  # the submaps of a and after (pairs go by a), each preprocessed once
    pose = {p: mp.frames[mp.keyframe_ids[p]].T_map_lidar for ab in pairs for p in ab}
    for a, b in pairs:
        for p in [p for p in clouds if p < a]:
            del clouds[p]
        for p in (a, b):
            if p not in clouds:
                clouds[p] = gicp.preprocess(submap(mp, p), leaf, threads=o.mapper_num_threads)
        r = gicp.align(clouds[a][0], clouds[b][0], clouds[a][1],
                       init_T_target_source=np.linalg.inv(pose[a]) @ pose[b], registration_type="GICP",
                       max_correspondence_distance=o.max_corr_dist_fine, max_iterations=min(o.solver_iterations, 60))
        H = np.asarray(r.H)
        ok = r.converged and r.num_inliers >= min_inlier_share * clouds[b][0].size() and degeneracy(H) <= max_cond
        cache[a, b] = KeyframeEdge(a, b, np.asarray(r.T_target_source), H) if ok else None
        if not ok:
            log.info("keyframes %d-%d: submap registration failed or degenerate; no edge", a, b)
    return [cache[a, b] for a in positions for b in (a + 1, a + 2) if cache.get((a, b)) is not None]
