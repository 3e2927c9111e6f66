"""What the targetless determinism costs: small_gicp's steps with 1 and 2 threads (issue 13 item 7).

Run: ``python -m bench.bench_gicp_threads``. On scans of a simulated drive (the small test rig),
per step: ms per call with small_gicp's multi-threaded version (what the pipeline used to run
with ``mapper_num_threads=2``) and with what it runs now (targetless/gicp.py: downsampling and
the registration's reduction on one thread, KD-tree and covariances on ``threads``), and whether
repeated calls give the same bytes. Scan-to-scan GICP at the mapper's settings (0.1 m leaf).
"""

from __future__ import annotations

import hashlib

import numpy as np

from bench.timed import timed

REPEATS = 7


def _digest(a) -> str:
    return hashlib.sha1(np.ascontiguousarray(a).tobytes()).hexdigest()[:12]


def _timed(fn):
    return timed(fn, REPEATS)


def main() -> str:
    import small_gicp

    from clcgraph.sim.drive import DrivePlan, simulate_drive
    from clcgraph.targetless import gicp

    drive = simulate_drive(DrivePlan.small(duration_s=1.0), seed=0)
    scans = drive.scans[drive.plan.lidars[0].topic]
    a, b = (np.asarray(s.points, float)[np.asarray(s.valid, bool)] for s in scans[:2])
    leaf = 0.1
    rows = [f"{'step':38s} {'threaded ms':>11s} {'now ms':>7s} {'threaded same bytes':>20s} {'now same bytes':>15s}"]

    def pts(cloud):
        return np.asarray(cloud.points())

    t_old, old = _timed(lambda: small_gicp.preprocess_points(a, leaf, num_neighbors=10, num_threads=2))
    t_new, new = _timed(lambda: gicp.preprocess(a, leaf, threads=2))
    rows.append(f"{'preprocess (downsample, tree, covs)':38s} {t_old:11.1f} {t_new:7.1f} "
                f"{str(len({_digest(pts(c)) for c, _ in old}) == 1):>20s} {str(len({_digest(pts(c)) for c, _ in new}) == 1):>15s}")
    tgt, tree = gicp.preprocess(a, leaf, threads=2)
    src, _ = gicp.preprocess(b, leaf, threads=2)
    kw = dict(registration_type="GICP", max_correspondence_distance=1.0, max_iterations=35)
    t_old, old = _timed(lambda: small_gicp.align(tgt, src, tree, num_threads=2, **kw).T_target_source)
    t_new, new = _timed(lambda: gicp.align(tgt, src, tree, **kw).T_target_source)
    rows.append(f"{'align (GICP, scan to scan)':38s} {t_old:11.1f} {t_new:7.1f} "
                f"{str(len({_digest(T) for T in old}) == 1):>20s} {str(len({_digest(T) for T in new}) == 1):>15s}")
    return "\n".join(rows)


if __name__ == "__main__":
    print(main())
