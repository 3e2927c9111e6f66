"""Open3D for the LIDAR segmentation's stages, measured against ours (issue 11, docs/segmentation.md).

Run: ``python -m bench.bench_segmentation_open3d``. On the demo's scans (data/synthetic/demo) and
the real ACFR Ouster-64 scans (data/real/acfr-ouster/run1), per operation:

- plane RANSAC: ``planes.ransac_plane`` (what lidar_board uses) against a seeded
  ``PointCloud.segment_plane`` (``open3d.utility.random.seed(0)``), on the clusters our
  segmentation hands to RANSAC and on whole scans (ground, walls and board: many planes);
- clustering: our straight segments along the rings linked into clusters (stage 1 + links +
  connected components) against ``PointCloud.cluster_dbscan`` on the scan's points;
- KD-tree: stage 3's "within reach of the plane's rows" query, scipy ``cKDTree`` against
  Open3D's batched ``core.nns.NearestNeighborSearch``;
- voxel grid (not used by the segmentation; for completeness): numpy against
  ``voxel_down_sample``.

Deterministic = the same result (inlier set, labels, neighbours) in 3 repetitions in one process
(with OMP_NUM_THREADS=1, and with 2) and between those two processes (Open3D's threads are fixed
at start-up).
Times are medians over the repetitions in the 2-thread process (ms per call).
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from bench.timed import timed

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "data" / "synthetic" / "demo"
ACFR = ROOT / "data" / "real" / "acfr-ouster" / "run1"
REPEATS = 3
N_SCANS = 4  # per data set
MAX_CLUSTERS = 30  # RANSAC inputs per data set, evenly picked


def _digest(*arrays) -> str:
    h = hashlib.sha1()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:12]


def _timed(fn):
    return timed(fn, REPEATS)


def _scans():
    """{name: [LidarScan]}: the demo's two LIDARs and ACFR run 1, N_SCANS board poses each."""
    from bench.real.acfr_to_bags import _load_pose, _poses
    from clcgraph.frontend.bag import read_messages
    from clcgraph.types import LidarScan

    out = {}
    bags = sorted(DEMO.glob("pose*.bag"))[:N_SCANS]
    for topic in ("/lidar/top/points", "/lidar/front/points"):
        out[f"demo {topic}"] = [m.data for m in read_messages(bags, [topic])]
    acfr = []
    for k in _poses(ACFR)[:N_SCANS]:
        c, _ = _load_pose(ACFR, k)
        xyz = c["xyz"].reshape(-1, 3).astype(float)
        acfr.append(LidarScan(topic="/os1/points", stamp_ns=k, points=xyz, valid=(xyz != 0).any(axis=1),
                              ring=c["ring"].reshape(-1).astype(np.int64), shape=c["ring"].shape))
    out["ACFR OS-64"] = acfr
    return out


def _setup(scan, cfg):
    """Our segmentation's first stages on one scan: (Rings, rank, rank_el, step, segments, seg_pts)."""
    from clcgraph.frontend import lidar_board as lb
    from clcgraph.frontend.lidar_preprocess import prepare

    R = prepare(scan, min_range_m=cfg.lidar.min_range_m, max_range_m=cfg.lidar.max_range_m)
    rank, rank_el = lb._ring_ranks(R)
    step = lb._azimuth_step(R, cfg.lidar.npoints_per_rotation)
    seg, seg_pts, _ = lb._stage1(R, rank, step, cfg.segmentation)
    return R, rank, rank_el, step, seg, seg_pts


def _ransac_inputs(scans, cfg, board):
    """The point sets our segmentation gives RANSAC (recorded while it runs), and the boards found."""
    from clcgraph.frontend import lidar_board as lb
    from clcgraph.types import LidarBoardObservation

    seen, boards, real = [], [], lb.ransac_plane

    def record(points, tol, **kw):
        seen.append((np.array(points), tol))
        return real(points, tol, **kw)

    lb.ransac_plane = record
    try:
        for s in scans:
            r = lb.segment_board(s, cfg.segmentation, cfg.lidar, board)
            boards.append(r if isinstance(r, LidarBoardObservation) else None)
    finally:
        lb.ransac_plane = real
    return seen, boards


def _plane_angle_deg(n1, n2) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(float(np.dot(n1, n2)))))))


def worker() -> dict:
    """This process's measurements (run once per OMP_NUM_THREADS by main())."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    from clcgraph.api import board_geometry
    from clcgraph.config import Config
    from clcgraph.frontend import lidar_board as lb
    from clcgraph.planes import fit_plane, ransac_plane

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    res = {}
    for name, scans in _scans().items():
        cfg = Config() if not name.startswith("ACFR") else Config().replace(
            board={"corners": [7, 5], "square_m": 0.095, "size_m": [0.85, 0.61]})
        board = board_geometry(cfg)
        tol = cfg.segmentation.point_plane_tolerance_m
        clusters, boards = _ransac_inputs(scans, cfg, board)
        whole = [lb.prepare(s, min_range_m=cfg.lidar.min_range_m, max_range_m=cfg.lidar.max_range_m).points
                 for s in scans]
        pick = np.unique(np.linspace(0, len(clusters) - 1, min(len(clusters), MAX_CLUSTERS)).astype(int))
        clusters = [clusters[i][0] for i in pick] if clusters else []
        for kind, sets in (("RANSAC plane, clusters", clusters), ("RANSAC plane, whole scan", whole)):
            rows = []
            for pts in sets:
                t_ours, ours = _timed(lambda: ransac_plane(pts, tol))
                pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))

                def o3d_plane():
                    o3d.utility.random.seed(0)
                    p = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
                    return p.segment_plane(distance_threshold=tol, ransac_n=3, num_iterations=256)

                t_o3d, theirs = _timed(o3d_plane)
                del pcd
                m_o3d = np.zeros(len(pts), bool)
                m_o3d[np.asarray(theirs[0][1])] = True
                n_ours = fit_plane(pts[ours[0]])[0]
                rows.append(dict(n=len(pts), t_ours=t_ours, t_o3d=t_o3d,
                                 det_ours=len({_digest(m) for m in ours}) == 1,
                                 det_o3d=len({_digest(np.asarray(t[1])) for t in theirs}) == 1,
                                 h_ours=_digest(ours[0]), h_o3d=_digest(np.asarray(theirs[0][1])),
                                 inl_ours=int(ours[0].sum()), inl_o3d=int(m_o3d.sum()),
                                 same_plane=bool((ours[0] & m_o3d).sum() >= 0.5 * max(ours[0].sum(), 1)),
                                 angle_deg=_plane_angle_deg(n_ours, np.asarray(theirs[0][0])[:3])))
            res[f"{name}|{kind}"] = rows
        # clustering: ours (stage 1 + links + components) vs DBSCAN on the scan's points
        rows = []
        for s, b in zip(scans, boards):
            def ours_clusters():
                R, rank, rank_el, step, seg, seg_pts = _setup(s, cfg)
                return R, seg, lb._components(len(seg.first), lb._links(seg, rank_el, cfg.segmentation))

            t_ours, out = _timed(ours_clusters)
            R, seg, comp = out[0]
            eps = 3 * tol  # neighbouring returns on a board at 10 m are ~2-5 cm apart along a ring

            def dbscan():
                p = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(R.points))
                return np.asarray(p.cluster_dbscan(eps=eps, min_points=5))

            t_o3d, labels = _timed(dbscan)
            row = dict(n=len(R.points), t_ours=t_ours, t_o3d=t_o3d, det_ours=len({_digest(c) for _, _, c in out}) == 1,
                       det_o3d=len({_digest(x) for x in labels}) == 1, h_ours=_digest(out[0][2]), h_o3d=_digest(labels[0]))
            if b is not None:  # the board's points: one DBSCAN cluster, and nothing else in it?
                pos = {int(i): k for k, i in enumerate(R.index)}
                lab = labels[0][[pos[int(i)] for i in b.indices if int(i) in pos]]
                top = np.bincount(lab[lab >= 0]).argmax() if (lab >= 0).any() else -1
                row["board_share"] = float((lab == top).mean()) if top >= 0 else 0.0
                row["cluster_over_board"] = float((labels[0] == top).sum() / max(len(lab), 1)) if top >= 0 else 0.0
            rows.append(row)
        res[f"{name}|clustering"] = rows
        # KD-tree: stage 3's reach query (nearest row of a plane within reach) for every in-range
        # point; the plane: the scan's largest (ground), as RANSAC found it above
        rows = []
        for query in whole:
            data = query[ransac_plane(query, tol)]
            t_ours, ours = _timed(lambda: cKDTree(data).query(query, distance_upper_bound=0.2)[0])

            def o3d_nn():
                nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(data))
                nns.knn_index()
                return np.sqrt(nns.knn_search(o3d.core.Tensor(query), 1)[1].numpy()[:, 0])

            t_o3d, theirs = _timed(o3d_nn)
            d_ours = np.where(np.isfinite(ours[0]), ours[0], np.inf)
            agree = np.mean((d_ours <= 0.2) == (theirs[0] <= 0.2))
            rows.append(dict(n=len(query), t_ours=t_ours, t_o3d=t_o3d, det_ours=len({_digest(x) for x in ours}) == 1,
                             det_o3d=len({_digest(x) for x in theirs}) == 1, h_ours=_digest(ours[0]),
                             h_o3d=_digest(theirs[0]), agree=float(agree)))
        res[f"{name}|KD-tree"] = rows
        # voxel grid (0.05 m) of the whole in-range scan
        rows = []
        for pts in whole:
            def ours_voxel():
                key = np.floor(pts / 0.05).astype(np.int64)
                _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
                return np.stack([np.bincount(inv, pts[:, j]) / cnt for j in range(3)], axis=1)

            t_ours, ours = _timed(ours_voxel)

            def o3d_voxel():
                p = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
                return np.asarray(p.voxel_down_sample(0.05).points)

            t_o3d, theirs = _timed(o3d_voxel)
            rows.append(dict(n=len(pts), t_ours=t_ours, t_o3d=t_o3d, det_ours=len({_digest(x) for x in ours}) == 1,
                             det_o3d=len({_digest(x) for x in theirs}) == 1, h_ours=_digest(ours[0]),
                             h_o3d=_digest(theirs[0]), voxels_ours=len(ours[0]), voxels_o3d=len(theirs[0])))
        res[f"{name}|voxel grid"] = rows
    return res


def _accuracy(op: str, rows: list) -> str:
    if op.startswith("RANSAC"):
        same = sum(r["same_plane"] for r in rows)
        ratio = np.median([r["inl_o3d"] / max(r["inl_ours"], 1) for r in rows])
        ang = np.median([r["angle_deg"] for r in rows])
        return f"same plane {same}/{len(rows)}; inliers O3D/ours {ratio:.2f}; angle {ang:.2f} deg"
    if op == "clustering":
        b = [r for r in rows if "board_share" in r]
        if not b:
            return "no board found"
        return (f"board in one DBSCAN cluster: {np.median([r['board_share'] for r in b]):.2f} of its points; "
                f"that cluster {np.median([r['cluster_over_board'] for r in b]):.1f}x the board")
    if op == "KD-tree":
        return f"within-reach verdicts agree {min(r['agree'] for r in rows):.4f}" if rows else "-"
    return f"voxels O3D/ours {np.median([r['voxels_o3d'] / r['voxels_ours'] for r in rows]):.3f}"


def main() -> str:
    runs = {}
    for threads in (1, 2):
        env = {**os.environ, "OMP_NUM_THREADS": str(threads), "PYTHONPATH": str(ROOT)}
        p = subprocess.run([sys.executable, "-m", "bench.bench_segmentation_open3d", "--worker"], env=env,
                           capture_output=True, text=True, cwd=ROOT, timeout=3600)
        if p.returncode != 0:
            raise RuntimeError(p.stderr[-2000:])
        runs[threads] = json.loads(p.stdout.strip().splitlines()[-1])
    lines = [f"{'data':24s} {'operation':25s} {'calls':>5s} {'ours ms':>8s} {'O3D ms':>8s} {'ours det.':>9s} "
             f"{'O3D det. (1 thr / 2 thr / 1 vs 2)':>33s}  accuracy (O3D against ours)"]
    for key, rows in runs[2].items():
        if not rows:
            continue
        data, op = key.split("|")
        one = runs[1][key]

        def same(w):  # the same result in the 1- and the 2-thread process
            return [r[f"h_{w}"] for r in rows] == [r[f"h_{w}"] for r in one]

        ours = all(r["det_ours"] for r in rows + one) and same("ours")
        o3d = " / ".join("yes" if x else "NO" for x in (all(r["det_o3d"] for r in one),
                                                         all(r["det_o3d"] for r in rows), same("o3d")))
        t_ours = np.median([r["t_ours"] for r in rows])
        t_o3d = np.median([r["t_o3d"] for r in rows])
        lines.append(f"{data:24s} {op:25s} {len(rows):5d} {t_ours:8.2f} {t_o3d:8.2f} {'yes' if ours else 'NO':>9s} "
                     f"{o3d:>33s}  {_accuracy(op, rows)}")
    return "\n".join(lines)


if __name__ == "__main__":
    if "--worker" in sys.argv:
        print(json.dumps(worker()))
    else:
        print(main())
