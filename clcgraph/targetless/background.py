"""One computation in a forked child while this process goes on (the second core of a 2-core machine).

SYNOPSIS
    job = Background(calibrate_base, mp, G0, o)   # starts fn(*args) in a child process (Linux)
    ...                                           # this process goes on (registration, graph)
    T, info = job.result()                        # fn's return value, or its exception raised here
    job.cancel()                                  # on the way out of an error: the child is killed

The child is a fork: it reads this process's memory as it was at the fork (no copy of a drive's
frames is sent), so ``fn`` must only read its arguments; its result comes back pickled through
a pipe. Where fork is not there (or not safe: not Linux), ``fn`` runs at ``result()`` in this
process. Either way the same function runs on the same data: the same result.

``fn`` must not start OpenMP threads (small_gicp with num_threads > 1): the parent's OpenMP
thread team does not survive the fork and a child asking for one hangs. One thread is fine.

The child resets SIGINT / SIGTERM to their defaults (an interrupted run's cleanup is the parent's)
and leaves with ``os._exit`` (no atexit handlers, no flush of the parent's buffers).
"""

from __future__ import annotations

import os
import pickle
import signal
import sys


def _can_fork() -> bool:
    return sys.platform.startswith("linux") and hasattr(os, "fork")


def _fork(child) -> tuple[int, int]:
    """Fork: the child resets SIGINT / SIGTERM, runs ``child(f)`` (f: the write end of a pipe to
    this process, binary) and leaves with ``os._exit`` (1 if it raised: the parent sees a short
    read). Returns (the child's pid, the read end's fd)."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child
        os.close(r)
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, signal.SIG_DFL)
        code = 0
        try:
            with os.fdopen(w, "wb") as f:
                child(f)
        except BaseException:  # noqa: BLE001 - the parent sees the short read
            code = 1
        os._exit(code)
    os.close(w)
    return pid, r


def _kill(pid: int) -> None:
    """Kill child ``pid`` if it still runs, and reap it."""
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    os.waitpid(pid, 0)


class Background:
    """``fn(*args)`` computed in a forked child; ``result()`` waits for it."""

    def __init__(self, fn, *args):
        self.fn, self.args = fn, args
        self.pid = None
        self.fd = None
        if _can_fork():
            def child(f):
                try:
                    out = (True, fn(*args))
                except BaseException as e:  # noqa: BLE001 - handed to the parent, raised there
                    out = (False, e)
                f.write(pickle.dumps(out, protocol=pickle.HIGHEST_PROTOCOL))

            self.pid, self.fd = _fork(child)

    def result(self):
        """fn's return value (its exception raised here)."""
        if self.pid is None:
            return self.fn(*self.args)
        with os.fdopen(self.fd, "rb") as f:
            data = f.read()
        self.fd = None
        _, status = os.waitpid(self.pid, 0)
        self.pid = None
        if not data:
            raise RuntimeError(f"{getattr(self.fn, '__name__', 'a background job')} died in its child process "
                               f"(exit status {os.waitstatus_to_exitcode(status)})")
        ok, value = pickle.loads(data)
        if not ok:
            raise value
        return value

    def cancel(self) -> None:
        """Kill the child if it still runs (nothing to do after ``result``)."""
        if self.pid is None:
            return
        _kill(self.pid)
        if self.fd is not None:
            os.close(self.fd)
        self.pid = self.fd = None


class Prefetched:
    """``fn(item)`` for each of ``items``, computed in a forked child one item ahead of the
    consumer (the child blocks once the pipe is full), yielded here in order; an exception of
    the child's iteration or of ``fn`` is raised here where it happened in the sequence. Inline
    where fork is not there. ``len()`` is the items' when they have one. Close it (or let it be
    garbage-collected) to stop the child early.

    SYNOPSIS
        for prepared in Prefetched(scans, prepare): ...   # prepare(scan) runs on the other core
    """

    def __new__(cls, items, fn):
        if cls is Prefetched and hasattr(items, "__len__"):
            return super().__new__(_SizedPrefetched)
        return super().__new__(cls)

    def __init__(self, items, fn):
        self.items, self.fn = items, fn
        self._gen = None

    def __iter__(self):
        if self._gen is None:
            self._gen = self._run()
        return self._gen

    def close(self) -> None:
        if self._gen is not None:
            self._gen.close()

    def _run(self):
        if not _can_fork():
            for item in self.items:
                yield self.fn(item)
            return

        def child(f):  # prepare and send, one pickle per item; (0, x) item, (1, e) error, (2,) end
            try:
                for item in self.items:
                    # pickled whole, then written: pickle.dump into the pipe sends a scan's arrays in
                    # pieces, each a wake-up of the reader (12 ms per 2 MB scan against 3 ms)
                    f.write(pickle.dumps((0, self.fn(item)), protocol=pickle.HIGHEST_PROTOCOL))
                pickle.dump((2,), f)
            except BaseException as e:  # noqa: BLE001 - raised in the parent, in sequence
                if isinstance(e, BrokenPipeError):  # the parent stopped reading
                    raise
                pickle.dump((1, e), f, protocol=pickle.HIGHEST_PROTOCOL)

        pid, r = _fork(child)
        f = os.fdopen(r, "rb")
        try:
            while True:
                try:
                    msg = pickle.load(f)
                except EOFError:
                    raise RuntimeError("the prefetching child process died") from None
                if msg[0] == 0:
                    yield msg[1]
                elif msg[0] == 1:
                    raise msg[1]
                else:
                    return
        finally:
            f.close()  # a child still writing gets a broken pipe
            _kill(pid)


class _SizedPrefetched(Prefetched):
    """A Prefetched of items with a length (a progress bar's total)."""

    def __len__(self):
        return len(self.items)
