"""Jobs shared by this process and a forked child: two cores for work that threads cannot share.

SYNOPSIS
    with TwoProcesses(jobs, what="the report's drawing") as work:  # the child starts at once
        ...                                    # other work of this process, overlapping it
        results = work.results()               # this process takes jobs too, then collects all

Each job is a call returning a picklable value; ``results()`` gives them in the jobs' order. The
two processes take the next job from a shared counter, so the split follows what each job costs on
the machine as it is. The child is forked (no imports, no copy of the data: it already has what the
jobs need) and sends its results back when the list is done. Where many small numpy steps make up a
job (the LIDAR segmentation, matplotlib's drawing), threads hold the GIL most of the time; two
processes use both cores.

Whatever the child did not deliver is done here: a job that raised in the child (run again here, so
that its exception, traceback and all, is raised here), a child that died, was killed, or sent
nothing long after this process finished its share (stuck on a lock another thread held at the
fork). Nothing is forked where fork is unavailable, in a daemonic process (a pool's worker may not
have children), or with one CPU: then every job runs here. A single job is forked too: this process
may have other work meanwhile.
"""

from __future__ import annotations

import logging
import os
import time
from typing import Callable, Sequence

log = logging.getLogger(__name__)

# How long this process waits for the child once its own share is done: this much, plus this
# factor times the time the child has had so far (on a loaded machine both processes are slow alike).
_PATIENCE_S = 30.0
_PATIENCE_FACTOR = 4.0


def _cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def _take(counter) -> int:
    with counter.get_lock():
        k = counter.value
        counter.value = k + 1
    return k


def _die_with(parent: int) -> None:
    """This process killed when ``parent`` dies (Linux; elsewhere nothing): a parent killed by
    SIGKILL (a pool's lost worker, the OOM killer) cannot stop its child, which would live on
    holding the parent's inherited pipes and locks (a process pool then waits for it forever)."""
    import ctypes
    import signal

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # died before the prctl
        os._exit(1)


def _child(jobs, order, counter, conn, other_end, parent: int) -> None:
    import signal

    _die_with(parent)
    # the parent's end of the pipe, inherited: held open here, a send to a parent gone would block
    # once the pipe is full instead of failing
    other_end.close()
    # Ctrl-C and SIGTERM are the parent's to handle (it kills this child): no second message or traceback
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    done = {}
    while (n := _take(counter)) < len(jobs):
        try:
            done[order[n]] = jobs[order[n]]()
        except Exception:  # noqa: BLE001 - the parent runs it again and raises it there
            pass
    try:
        conn.send(done)
    except OSError:  # the parent stopped listening (it failed or was interrupted)
        pass
    conn.close()


class TwoProcesses:
    """Jobs done by this process and a forked child together, the child starting at once (see the
    module). ``order``: the jobs' indices in the order they are taken (the longest first: the two
    processes then finish together); ``what``: the work, for the warnings; ``fork``: False, every job
    runs here (too little work to share). Leaving the block without ``results()`` (an error) stops
    the child."""

    def __init__(self, jobs: Sequence[Callable[[], object]], *, order: Sequence[int] | None = None,
                 what: str = "the work", fork: bool = True):
        import multiprocessing

        self.jobs = list(jobs)
        self.what = what
        self.order = list(order) if order is not None else list(range(len(self.jobs)))
        if sorted(self.order) != list(range(len(self.jobs))):
            raise ValueError(f"order {self.order} is not a permutation of the {len(self.jobs)} jobs")
        self.child = None
        if fork and self.jobs and _cpus() > 1 and "fork" in multiprocessing.get_all_start_methods() \
                and not multiprocessing.current_process().daemon:
            ctx = multiprocessing.get_context("fork")
            self.counter = ctx.Value("i", 0)
            self.receive, send = ctx.Pipe(duplex=False)
            self.child = ctx.Process(target=_child, args=(self.jobs, self.order, self.counter, send, self.receive,
                                                          os.getpid()), daemon=True, name="clcgraph-worker")
            self.child.start()
            self.started = time.perf_counter()
            send.close()

    def __enter__(self) -> "TwoProcesses":
        return self

    def __exit__(self, *exc) -> bool:
        self.close(wait=False)
        return False

    def close(self, *, wait: bool = True) -> None:
        """Let the child end (``wait``: it has sent what it did) or stop it (its results are not wanted)."""
        if self.child is None:
            return
        self.receive.close()
        if wait:
            self.child.join(timeout=10)
        if self.child.is_alive():
            self.child.kill()
            self.child.join()
        self.child = None

    def results(self, progress: Callable[[int], None] | None = None) -> list:
        """Every job's result, in the jobs' order; this process does its share now. ``progress``:
        called with the number of jobs taken so far by either process, after each job done here."""
        if self.child is None:
            out = []
            for job in self.jobs:
                out.append(job())
                if progress:
                    progress(len(out))
            return out
        done = {}
        try:
            while (n := _take(self.counter)) < len(self.jobs):
                k = self.order[n]
                done[k] = self.jobs[k]()
                if progress:
                    progress(min(self.counter.value, len(self.jobs)))
        except BaseException:
            self.close(wait=False)
            raise
        # the child's last job takes about as long as one of ours, its remaining work no longer than
        # what it did so far: far longer means it is stuck (a lock another thread held when it was
        # forked), and its jobs are done here instead
        patience = _PATIENCE_S + _PATIENCE_FACTOR * (time.perf_counter() - self.started)
        try:
            if self.receive.poll(patience):
                done.update(self.receive.recv())
            else:
                log.warning("%s: the second process sent nothing in %.0f s: doing its share here", self.what, patience)
        except (EOFError, OSError):
            log.warning("%s: the second process ended early (exit code %s): doing its share here", self.what,
                        self.child.exitcode)
        self.close(wait=len(done) == len(self.jobs))  # all delivered: it is exiting; else stop it
        return [done[k] if k in done else self.jobs[k]() for k in range(len(self.jobs))]
