"""The benches' one stopwatch: a call repeated, its median wall time."""

from __future__ import annotations

import time

import numpy as np


def timed(fn, repeats: int) -> tuple[float, list]:
    """(median ms, [each call's result]) of ``fn()`` called ``repeats`` times."""
    ts, out = [], []
    for _ in range(repeats):
        t = time.perf_counter()
        out.append(fn())
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts)), out
