"""Run a Monte Carlo of bench_uncertainty in a pool of two processes and tabulate it
(bench/mc_correlated.py, bench/mc_independent.py: one command each).

Each process runs every rig in turn from its own first seed and appends one JSON line per trial
to ``build/mc/<name>-<seed0>.jsonl`` (kept: ``python -m bench.mc_table`` re-reads and re-judges
them); the table is bench/mc_table.py's over the merged logs. CPU seconds are reported, not
wall-clock (the machine is shared).
"""

from __future__ import annotations

import os
import resource
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _one(args):
    trials, case, seed0, log, settings = args
    os.environ["CLCGRAPH_BENCH_SET"] = settings
    from bench import bench_uncertainty

    bench_uncertainty.run(trials, cases=[case], seed0=seed0, log=log)
    return resource.getrusage(resource.RUSAGE_SELF).ru_utime


def monte_carlo(name: str, case: tuple[str, bool], trials_per_rig: int, settings: str = "", processes: int = 2,
                seed0: int = 1000) -> str:
    """``trials_per_rig`` x 3 trials of ``case`` (errors, effects), solve ``settings`` as
    ``CLCGRAPH_BENCH_SET``; the logs are started afresh."""
    from bench import mc_table

    out = ROOT / "build" / "mc"
    out.mkdir(parents=True, exist_ok=True)
    per = -(-trials_per_rig // processes)
    jobs = []
    for k in range(processes):
        n = min(per, trials_per_rig - k * per)
        log = out / f"{name}-{seed0 + k * per}.jsonl"
        log.unlink(missing_ok=True)
        jobs.append((n, case, seed0 + k * per, str(log), settings))
    with ProcessPoolExecutor(processes) as ex:
        cpu = sum(ex.map(_one, jobs))
    logs = [j[3] for j in jobs]
    return (f"{name}: {case[0]} errors, effects {'on' if case[1] else 'off'}, solve settings "
            f"{settings or '(defaults)'}; {cpu:.0f} CPU s\n" + mc_table.table(logs, {}))


def trials_from_argv(default: int) -> int:
    return int(sys.argv[1]) if len(sys.argv) > 1 and sys.argv[1].isdigit() else default
