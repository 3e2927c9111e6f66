"""small_gicp, the same bytes whatever the thread count: every targetless call goes through here.

Two of small_gicp's multi-threaded steps depend on how the work was shared out between threads:
its OpenMP voxel-grid downsampling collects voxels per block and appends them in the order the
threads finish (the points come out in another order, so KD-trees and sums differ), and its
registration adds per-thread partial Hessians filled under a dynamic schedule (floating-point
sums in another order). Both changed the calibration in the last digits with the thread count,
and from run to run with 2 threads. So those run on one thread; the steps that compute each
point on its own (KD-tree construction: the same splits whatever the task order; per-point
covariances) keep ``threads``.

Memory (measured with the installed small_gicp): a PointCloud's points take 32 B per point, its KD-tree 32 B,
covariances 128 B (allocated only when estimated; normals, 32 B more, are not: GICP does not use them).
"""

from __future__ import annotations

import numpy as np

# Registration (correspondences + linearization + reduction) always runs single-threaded: its
# OpenMP reduction is order-dependent (see above). bench/bench_targetless.py measures the cost.
_REDUCTION_THREADS = 1
NUM_NEIGHBORS = 10  # neighbours of a point's normal and covariance


def preprocess(points: np.ndarray, leaf: float, *, threads: int):
    """(cloud, tree): (N,3) points voxel-downsampled to ``leaf`` (single-threaded: deterministic),
    then a KD-tree and per-point covariances (``threads``: order-independent)."""
    import small_gicp

    return prepared(small_gicp.voxelgrid_sampling(np.ascontiguousarray(points, float), leaf, num_threads=1),
                    threads=threads)


def prepared(points, *, threads: int, tree=None):
    """(cloud, tree) of points already downsampled ((N,3) array or a PointCloud), with covariances;
    ``tree``: a KD-tree already built on the same points in the same order."""
    import small_gicp

    cloud = points if isinstance(points, small_gicp.PointCloud) else small_gicp.PointCloud(
        np.ascontiguousarray(points, float))
    tree = small_gicp.KdTree(cloud, num_threads=threads) if tree is None else tree
    # covariances only: GICP uses no normals (the same covariances as estimate_normals_covariances')
    small_gicp.estimate_covariances(cloud, tree, num_neighbors=NUM_NEIGHBORS, num_threads=threads)
    return cloud, tree


def nearest(tree, points: np.ndarray, *, threads: int = 1):
    """(squared distance (N,), index (N,)) of each point's nearest neighbour in ``tree`` (each point
    searched on its own: the same answers whatever ``threads``)."""
    idx, d2 = tree.batch_nearest_neighbor_search(np.ascontiguousarray(points, float), num_threads=threads)
    return np.asarray(d2), np.asarray(idx, np.int64)


def align(target, source, tree=None, **kwargs):
    """small_gicp.align on preprocessed clouds (or a GaussianVoxelMap target, no tree), with a
    deterministic reduction; keyword arguments as small_gicp.align's, without num_threads."""
    import small_gicp

    if tree is None:
        return small_gicp.align(target, source, num_threads=_REDUCTION_THREADS, **kwargs)
    return small_gicp.align(target, source, tree, num_threads=_REDUCTION_THREADS, **kwargs)


def voxel_map(cloud, resolution: float):
    """A GaussianVoxelMap of a preprocessed cloud (VGICP's target); inserted on one thread."""
    import small_gicp

    voxels = small_gicp.GaussianVoxelMap(resolution)
    voxels.insert(cloud)
    return voxels
