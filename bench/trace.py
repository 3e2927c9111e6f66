"""Where a command's time goes on the cores: ``python -m bench.trace [--every S] -- COMMAND ...``
(e.g. ``-- clcgraph solve ... --verbose``: its log lines mark the stages).

Every ``--every`` seconds (0.1) the cores the command's process tree keeps busy: user + system
time of the process and of every descendant alive (forked workers, the mrgingham command), with
the time of those already waited for, from /proc; printed beside the command's stderr lines as
they come (its stdout is passed through). Then the totals and the stretches where it used less
than one core and a half for at least half a second: on 2 cores, where one stood idle. Other
programs' load does not enter (unlike /proc/stat's).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

_HZ = os.sysconf("SC_CLK_TCK")


def _stat(pid: int) -> tuple[int, float] | None:
    """(parent pid, CPU s of the process and of its children waited for) from /proc/PID/stat."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:  # gone meanwhile
        return None
    fields = text[text.rindex(")") + 2:].split()  # after "pid (comm) ": state ppid ...
    utime, stime, cutime, cstime = (int(x) for x in fields[11:15])
    return int(fields[1]), (utime + stime + cutime + cstime) / _HZ


def tree_cpu_s(root: int) -> float:
    """CPU seconds of process ``root`` and all its descendants, alive or waited for."""
    stats = {int(p): s for p in os.listdir("/proc") if p.isdigit() and (s := _stat(int(p))) is not None}
    children: dict[int, list[int]] = {}
    for pid, (ppid, _) in stats.items():
        children.setdefault(ppid, []).append(pid)
    total, todo = 0.0, [root]
    while todo:
        pid = todo.pop()
        if pid in stats:
            total += stats[pid][1]
            todo += children.get(pid, [])
    return total


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--every", type=float, default=0.1, help="seconds between samples")
    p.add_argument("command", nargs=argparse.REMAINDER, help="-- then the command and its arguments")
    args = p.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        p.error("no command given (after --)")
    before = os.times()
    t0 = time.perf_counter()
    try:
        proc = subprocess.Popen(command, stderr=subprocess.PIPE, text=True, errors="replace")
    except OSError as e:  # no such program, not executable: one line, as argparse's errors
        p.error(f"cannot run {command[0]}: {e.strerror}")
    lock = threading.Lock()

    def show(line: str) -> None:
        with lock:
            print(line, flush=True)

    def relay():
        for line in proc.stderr:
            show(f"{time.perf_counter() - t0:7.2f}        {line.rstrip()[:160]}")

    reader = threading.Thread(target=relay, daemon=True)
    reader.start()
    samples, last_t, last_cpu = [], t0, 0.0
    while proc.poll() is None:
        time.sleep(args.every)
        now, cpu = time.perf_counter(), tree_cpu_s(proc.pid)
        if proc.poll() is not None:  # exited (its CPU time with it) between the two reads
            break
        cores = (cpu - last_cpu) / (now - last_t)
        samples.append((now - t0, cores))
        show(f"{now - t0:7.2f} {cores:4.1f}  {'#' * round(10 * cores)}")
        last_t, last_cpu = now, cpu
    reader.join()
    proc.stderr.close()
    wall = time.perf_counter() - t0
    after = os.times()  # the whole tree, once it is waited for
    cpu = after.children_user + after.children_system - before.children_user - before.children_system
    print(f"\nwall {wall:.2f} s, CPU {cpu:.2f} s ({cpu / wall:.2f} cores on average); exit code {proc.returncode}")
    idle, start = [], None
    for t, cores in samples + [(wall, 2.0)]:
        if cores < 1.5 and start is None:
            start = t - args.every
        elif cores >= 1.5 and start is not None:
            if t - args.every - start >= 0.5:
                idle.append((start, t - args.every))
            start = None
    for a, b in idle:
        mean = [c for t, c in samples if a < t <= b]
        print(f"under 1.5 cores from {a:.2f} to {b:.2f} s ({b - a:.2f} s, {sum(mean) / max(len(mean), 1):.1f} cores)")
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
