"""The same bytes out whatever the thread count (BLAS side; small_gicp's side is in targetless/gicp.py;
numpy's SVML kernels on strided columns: geometry.contiguous_arctan2)."""

from __future__ import annotations

from contextlib import contextmanager



@contextmanager
def single_threaded_blas():
    """BLAS / LAPACK on one thread while a calibration runs, frontend included (also usable as a
    decorator).

    OpenBLAS splits long dot products (and the LAPACK steps built on them) between its threads
    and adds the partial sums in thread order: with OMP_NUM_THREADS=2 instead of 1 the graph's
    covariances and costs changed in the 15th digit (and the target-based noise components'
    variance estimates in the 10th). The BLAS work of both is small (6x6 blocks, per-snapshot
    normal equations, (N,3) point sets against 3x3 rotations). In the frontend (many short numpy
    calls on (N,3) clouds) OpenBLAS's threads gained nothing and spun between the calls: the
    segmentation took ~1.5x the CPU time it takes on one thread. The previous limit is restored
    on exit."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield
