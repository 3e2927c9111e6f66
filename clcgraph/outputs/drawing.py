"""Drawing a report's pictures on two cores: a forked child process takes jobs from the same list.

SYNOPSIS
    figures = draw_concurrently([lambda: [("a.png", "", png_bytes)], ...], first=lambda: ...)
    # [job's result, ...] in the jobs' order; ``first`` runs here before this process takes jobs

Each job is a call returning a list (the pictures it drew); a job that raises is logged and gives
[] (a diagnostic picture must never lose the calibration). The two processes take the next job
from a shared counter, so the split follows what each job costs on the machine as it is. The
child is forked (no imports, no copy of the data: it already has matplotlib and the result) and
sends its pictures back as bytes when the list is done; whatever it did not deliver (it died,
or was killed) is drawn here. Nothing is forked where fork is unavailable, in a daemonic
process (a pool's worker may not have children), or with one CPU: then every job runs here.
"""

from __future__ import annotations

import logging
import os
from typing import Callable, Sequence

log = logging.getLogger(__name__)


def _cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def _run(job: Callable[[], list], what: str) -> list:
    try:
        return list(job())
    except Exception:  # noqa: BLE001 - a picture less, never a lost calibration
        log.exception("could not draw %s", what)
        return []


def _take(counter) -> int:
    with counter.get_lock():
        k = counter.value
        counter.value = k + 1
    return k


def _child(jobs, names, order, counter, conn) -> None:
    import signal

    # Ctrl-C and SIGTERM are the parent's to handle (it kills this child): no second message or traceback
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    done = {}
    while (n := _take(counter)) < len(jobs):
        done[order[n]] = _run(jobs[order[n]], names[order[n]])
    try:
        conn.send(done)
    except OSError:  # the parent stopped listening (it failed or was interrupted)
        pass
    conn.close()


def draw_concurrently(jobs: Sequence[Callable[[], list]], *, names: Sequence[str] | None = None,
                      first: Callable[[], object] | None = None, order: Sequence[int] | None = None) -> list[list]:
    """Every job's result (a list), in order, drawn by this process and a forked child together.

    ``names``: what each job draws (for the log when one fails); ``first``: work of this process
    that the jobs do not need (it runs while the child already draws); ``order``: the jobs' indices
    in the order they are taken (the longest first: the two processes then finish together)."""
    import multiprocessing

    jobs = list(jobs)
    names = list(names) if names is not None else [f"picture {k}" for k in range(len(jobs))]
    order = list(order) if order is not None else list(range(len(jobs)))
    if sorted(order) != list(range(len(jobs))):
        raise ValueError(f"order {order} is not a permutation of the {len(jobs)} jobs")
    fork = len(jobs) > 1 and _cpus() > 1 and "fork" in multiprocessing.get_all_start_methods() \
        and not multiprocessing.current_process().daemon
    if not fork:
        if first is not None:
            first()
        return [_run(job, what) for job, what in zip(jobs, names)]
    ctx = multiprocessing.get_context("fork")
    counter = ctx.Value("i", 0)
    receive, send = ctx.Pipe(duplex=False)
    child = ctx.Process(target=_child, args=(jobs, names, order, counter, send), daemon=True, name="clcgraph-draw")
    child.start()
    send.close()
    try:
        if first is not None:
            first()
        done = {}
        while (n := _take(counter)) < len(jobs):
            done[order[n]] = _run(jobs[order[n]], names[order[n]])
        try:
            theirs = receive.recv()
        except (EOFError, OSError):
            theirs = {}
            log.warning("the report's drawing process ended early (exit code %s): drawing its pictures here",
                        child.exitcode)
        done.update(theirs)
    finally:
        receive.close()
        child.join(timeout=10)
        if child.is_alive():
            child.kill()
            child.join()
    return [done[k] if k in done else _run(jobs[k], names[k]) for k in range(len(jobs))]
