"""The same bytes out whatever the thread count (BLAS side; small_gicp's side is in targetless/gicp.py)
and wherever the allocator puts the arrays (``contiguous_arctan2``)."""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np


def contiguous_arctan2(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``np.arctan2(y, x)`` with the same bits wherever numpy's output lands, e.g. the azimuths
    ``contiguous_arctan2(p[:, 1], p[:, 0])`` of (N,3) points.

    numpy 1.24 computes arctan2 with SVML's AVX-512 kernel unless input and output overlap, and
    its overlap check spans a strided column to ``start + step * len``, past the column's last
    element: an output that malloc places right after the points looks overlapping and gets
    libm's atan2, a bit off SVML's in a third of the values. Where malloc puts it changes from
    run to run (the LIDAR frontend's points moved by up to 5e-14 m between two processes).
    Contiguous copies never look overlapping, and cost less than SVML's strided loads save.
    np.sin, np.exp, np.power and the other SVML ufuncs share the check: pass them no strided columns."""
    return np.arctan2(np.ascontiguousarray(y), np.ascontiguousarray(x))


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
