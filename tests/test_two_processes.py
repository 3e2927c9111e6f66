"""two_processes.py: jobs shared with a forked child give what this process alone gives (the
report's Drawing on top of it: tests/test_drawing.py)."""

from __future__ import annotations

import logging
import os
import time

import pytest

from clcgraph import two_processes
from clcgraph.two_processes import TwoProcesses


def _slow(k, pids=None):
    time.sleep(0.05)
    if pids is not None:
        pids.append(os.getpid())
    return {"k": k, "data": bytes([k % 256]) * 50_000}  # larger than a pipe's buffer


def test_results_in_the_jobs_order_from_both_processes():
    pids = []
    with TwoProcesses([lambda k=k: _slow(k, pids) for k in range(12)]) as work:
        out = work.results()
    assert out == [_slow(k) for k in range(12)]
    assert 0 < len(pids) < 12  # the child did the others (its list is its own)


def test_a_job_that_raises_in_the_child_raises_here():
    parent = os.getpid()
    ran_here = []

    def fails_in_child():
        if os.getpid() != parent:
            raise ValueError("bad scan")
        ran_here.append(True)
        raise ValueError("bad scan")

    with pytest.raises(ValueError, match="bad scan"):
        with TwoProcesses([fails_in_child, lambda: 1]) as work:
            time.sleep(0.5)  # the child takes both jobs meanwhile
            work.results()
    assert ran_here == [True]  # run again here: its exception, traceback and all, is raised here


def test_progress_counts_every_job_taken(monkeypatch):
    for cpus in (1, 2):
        monkeypatch.setattr(two_processes, "_cpus", lambda: cpus)
        seen = []
        with TwoProcesses([lambda k=k: _slow(k) for k in range(8)]) as work:
            out = work.results(seen.append)
        assert [o["k"] for o in out] == list(range(8))
        assert seen == sorted(seen) and seen[-1] <= 8 and (cpus == 2 or seen == list(range(1, 9)))


def test_a_long_job_the_child_started_early_is_waited_for(monkeypatch, caplog):
    """The child's one job outlasts the fixed patience, but not what it has had so far (this
    process worked meanwhile): it is waited for, not done again here."""
    monkeypatch.setattr(two_processes, "_PATIENCE_S", 0.5)
    with caplog.at_level(logging.WARNING):
        with TwoProcesses([lambda: time.sleep(2.0) or os.getpid()]) as work:
            time.sleep(1.0)  # this process's other work
            (pid,) = work.results()
    assert pid != os.getpid() and not caplog.text


def test_a_child_does_not_outlive_a_killed_parent(tmp_path):
    """A parent killed by SIGKILL (a pool's lost worker) takes its child with it: an orphan held the
    parent's inherited pipes, and the process pool that lost the worker waited for it forever."""
    import signal
    import subprocess
    import sys

    script = tmp_path / "parent.py"
    script.write_text(
        "import os, signal, sys, time\n"
        "from clcgraph.two_processes import TwoProcesses\n"
        "work = TwoProcesses([lambda: time.sleep(60) or b'x' * 1_000_000])\n"
        "open(sys.argv[1], 'w').write(str(work.child.pid))\n"
        "time.sleep(0.5)\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n")
    # no pipes to wait on: an orphan would hold them open
    p = subprocess.run([sys.executable, str(script), str(tmp_path / "pid")], stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL, timeout=60)
    assert p.returncode == -signal.SIGKILL
    child = int((tmp_path / "pid").read_text())
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            return
        with open(f"/proc/{child}/stat") as f:  # a zombie waiting for init to reap it is gone too
            if f.read().split(")")[-1].split()[0] == "Z":
                return
        time.sleep(0.1)
    os.kill(child, signal.SIGKILL)
    raise AssertionError("the child outlived its killed parent")
