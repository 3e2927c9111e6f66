"""Drawing a report's pictures on two cores (``two_processes.TwoProcesses``: a forked child takes
jobs from the same list).

SYNOPSIS
    figures = draw_concurrently([lambda: [("a.png", "", png_bytes)], ...], first=lambda: ...)
    # [job's result, ...] in the jobs' order; ``first`` runs here before this process takes jobs
    with Drawing(jobs) as drawing:      # the same in two steps: the child starts at once
        ...                             # other work of this process
        figures = drawing.results()

Each job is a call returning a list (the pictures it drew); a job that raises is logged and gives
[] (a diagnostic picture must never lose the calibration). What the child did not deliver is drawn
here (two_processes.py).
"""

from __future__ import annotations

import logging
import os
import time
from typing import Callable, Sequence

from ..two_processes import TwoProcesses

log = logging.getLogger(__name__)


def _run(job: Callable[[], list], what: str) -> list:
    t0 = time.process_time()
    try:
        return list(job())
    except Exception:  # noqa: BLE001 - a picture less, never a lost calibration
        log.exception("could not draw %s", what)
        return []
    finally:
        log.debug("process %d drew %s in %.2f s CPU", os.getpid(), what, time.process_time() - t0)


class Drawing(TwoProcesses):
    """Jobs drawn by this process and a forked child together, the child starting at once.

    SYNOPSIS
        with Drawing(jobs, names=names, order=order) as drawing:   # the child starts drawing here
            ...                                   # this process's other work, overlapping it
            results = drawing.results()           # this process takes jobs too, then collects all

    ``names``: what each job draws (for the log when one fails); ``order``: the jobs' indices in
    the order they are taken (the longest first: the two processes then finish together). Leaving
    the block without ``results()`` (an error) stops the child.
    """

    def __init__(self, jobs: Sequence[Callable[[], list]], *, names: Sequence[str] | None = None,
                 order: Sequence[int] | None = None):
        jobs = list(jobs)
        self.names = list(names) if names is not None else [f"picture {k}" for k in range(len(jobs))]
        super().__init__([lambda job=job, name=name: _run(job, name) for job, name in zip(jobs, self.names)],
                         order=order, what="the report's drawing")


def draw_concurrently(jobs: Sequence[Callable[[], list]], *, names: Sequence[str] | None = None,
                      first: Callable[[], object] | None = None, order: Sequence[int] | None = None) -> list[list]:
    """``Drawing(jobs, names=names, order=order).results()``, with ``first`` (work of this process that
    the jobs do not need) done while the child already draws."""
    with Drawing(jobs, names=names, order=order) as drawing:
        if first is not None:
            first()
        return drawing.results()
