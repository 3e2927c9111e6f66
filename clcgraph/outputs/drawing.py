"""Drawing a report's pictures on two cores: a forked child process takes jobs from the same list.

SYNOPSIS
    figures = draw_concurrently([lambda: [("a.png", "", png_bytes)], ...], first=lambda: ...)
    # [job's result, ...] in the jobs' order; ``first`` runs here before this process takes jobs
    with Drawing(jobs) as drawing:      # the same in two steps: the child starts at once
        ...                             # other work of this process
        figures = drawing.results()

Each job is a call returning a list (the pictures it drew); a job that raises is logged and gives
[] (a diagnostic picture must never lose the calibration). The two processes take the next job
from a shared counter, so the split follows what each job costs on the machine as it is. The
child is forked (no imports, no copy of the data: it already has matplotlib and the result) and
sends its pictures back as bytes when the list is done; whatever it did not deliver (it died,
was killed, or sent nothing long after this process finished its share) is drawn here. Nothing is forked where fork is unavailable, in a daemonic
process (a pool's worker may not have children), or with one CPU: then every job runs here. A single
job is forked too: this process has other work meanwhile (the report: the other files).
"""

from __future__ import annotations

import logging
import os
import time
from typing import Callable, Sequence

log = logging.getLogger(__name__)

# How long this process waits for the child once its own share is drawn: this much, plus this
# factor times the time its own share took (on a loaded machine both processes are slow alike).
_PATIENCE_S = 30.0
_PATIENCE_FACTOR = 4.0


def _cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def _run(job: Callable[[], list], what: str) -> list:
    t0 = time.process_time()
    try:
        return list(job())
    except Exception:  # noqa: BLE001 - a picture less, never a lost calibration
        log.exception("could not draw %s", what)
        return []
    finally:
        log.debug("process %d drew %s in %.2f s CPU", os.getpid(), what, time.process_time() - t0)


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


class Drawing:
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
        import multiprocessing

        self.jobs = list(jobs)
        self.names = list(names) if names is not None else [f"picture {k}" for k in range(len(self.jobs))]
        self.order = list(order) if order is not None else list(range(len(self.jobs)))
        if sorted(self.order) != list(range(len(self.jobs))):
            raise ValueError(f"order {self.order} is not a permutation of the {len(self.jobs)} jobs")
        self.child = None
        if self.jobs and _cpus() > 1 and "fork" in multiprocessing.get_all_start_methods() \
                and not multiprocessing.current_process().daemon:
            ctx = multiprocessing.get_context("fork")
            self.counter = ctx.Value("i", 0)
            self.receive, send = ctx.Pipe(duplex=False)
            self.child = ctx.Process(target=_child, args=(self.jobs, self.names, self.order, self.counter, send),
                                     daemon=True, name="clcgraph-draw")
            self.child.start()
            send.close()

    def __enter__(self) -> "Drawing":
        return self

    def __exit__(self, *exc) -> bool:
        self.close(wait=False)
        return False

    def close(self, *, wait: bool = True) -> None:
        """Let the child end (``wait``: it has sent what it drew) or stop it (its pictures are not wanted)."""
        if self.child is None:
            return
        self.receive.close()
        if wait:
            self.child.join(timeout=10)
        if self.child.is_alive():
            self.child.kill()
            self.child.join()
        self.child = None

    def results(self) -> list[list]:
        """Every job's result (a list), in the jobs' order; this process draws its share now."""
        if self.child is None:
            return [_run(job, what) for job, what in zip(self.jobs, self.names)]
        done = {}
        t0 = time.perf_counter()
        while (n := _take(self.counter)) < len(self.jobs):
            k = self.order[n]
            done[k] = _run(self.jobs[k], self.names[k])
        # the child's last job takes about as long as one of ours: far longer means it is stuck (a
        # lock another thread held when it was forked), and its pictures are drawn here instead
        patience = _PATIENCE_S + _PATIENCE_FACTOR * (time.perf_counter() - t0)
        try:
            if self.receive.poll(patience):
                done.update(self.receive.recv())
            else:
                log.warning("the report's drawing process sent nothing in %.0f s: drawing its pictures here", patience)
        except (EOFError, OSError):
            log.warning("the report's drawing process ended early (exit code %s): drawing its pictures here",
                        self.child.exitcode)
        self.close(wait=len(done) == len(self.jobs))  # all delivered: it is exiting; else stop it
        return [done[k] if k in done else _run(self.jobs[k], self.names[k]) for k in range(len(self.jobs))]


def draw_concurrently(jobs: Sequence[Callable[[], list]], *, names: Sequence[str] | None = None,
                      first: Callable[[], object] | None = None, order: Sequence[int] | None = None) -> list[list]:
    """``Drawing(jobs, names=names, order=order).results()``, with ``first`` (work of this process that
    the jobs do not need) done while the child already draws."""
    with Drawing(jobs, names=names, order=order) as drawing:
        if first is not None:
            first()
        return drawing.results()
