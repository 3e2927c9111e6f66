"""bench/trace.py, the timeline of a command's CPU use: a process tree's CPU time counts its live
descendants' and those already waited for, and the totals are the command's."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from bench import trace

BUSY = "import time\nt = time.process_time()\nwhile time.process_time() - t < {s}: pass\n"


def test_the_tree_counts_a_live_child_and_one_waited_for(tmp_path):
    # the parent waits for one busy child (0.3 s CPU), then starts another (0.4 s) that stays alive
    done = tmp_path / "done"
    second = BUSY.format(s=0.4) + f"import pathlib, time\npathlib.Path({str(done)!r}).touch()\ntime.sleep(30)\n"
    parent = (f"import subprocess, sys\nsubprocess.run([sys.executable, '-c', {BUSY.format(s=0.3)!r}])\n"
              f"subprocess.run([sys.executable, '-c', {second!r}])\n")
    p = subprocess.Popen([sys.executable, "-c", parent])
    try:
        t = time.perf_counter()
        while not done.exists() and time.perf_counter() - t < 60:
            time.sleep(0.05)
        cpu = trace.tree_cpu_s(p.pid)
        assert done.exists() and 0.65 <= cpu <= 2.0, cpu  # 0.7 s of busy loops and three interpreters' start-up
    finally:
        for pid in (int(x) for x in os.listdir("/proc") if x.isdigit()):  # the child left sleeping
            if (trace._stat(pid) or (None,))[0] == p.pid:
                os.kill(pid, signal.SIGKILL)
        p.kill()
        p.wait()


def test_the_totals_are_the_commands(capsys):
    code = trace.main(["--every", "0.05", "--", sys.executable, "-c", BUSY.format(s=0.3) + "import sys\nsys.exit(3)"])
    out = capsys.readouterr().out
    assert code == 3
    cpu = float(out.split("CPU ")[1].split(" s")[0])
    assert 0.3 <= cpu <= 1.0, out


def test_a_command_that_cannot_run_is_one_line(capsys):
    with pytest.raises(SystemExit) as e:
        trace.main(["--", "/no/such/program"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "cannot run /no/such/program" in err and "Traceback" not in err
