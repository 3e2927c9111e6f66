"""The backend against another revision of itself: same answers, and the CPU time of each stage.

    python -m bench.backend_equivalence                  # against `main` (git archive into build/)
    python -m bench.backend_equivalence --reference 3cca1e0 --cases 24x2+3 240x3+5 --repeats 3
    python -m bench.backend_equivalence --rounds 4 --cases 24x2+3

Each case (poses x lidars+cameras, bench/bench_solve.py's simulated problems) is solved by the
reference revision and by this tree, each in its own process, and the results compared:
sensor and board poses within 1e-9 (rad / m), the covariance's sigmas within 1e-6 relative,
every other number of the result (noise, rms, consistency verdict, jackknife, uncertainty terms)
within 1e-6 relative, every string (verdicts, rejection reasons, directions) identical. It
prints a table per case: stage, CPU s before, CPU s after, ratio (solve.py's own stage timers
fed ``time.process_time``: the best of ``--repeats`` solves in each of ``--rounds`` alternating
processes; wall time on a loaded machine says little). Both solve with BLAS on one thread, as
``clcgraph.calibrate`` runs them (OpenBLAS's threads spinning on small matrices add CPU that
varies with the load).
Exit 1 if any result differs.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_CHILD = r"""
import json, sys, time, types
import numpy as np
from clcgraph.config import Config
from clcgraph.sim import observations as sim
import clcgraph.backend.solve as S
from threadpoolctl import threadpool_limits as _limits
single_threaded_blas = lambda: _limits(limits=1, user_api="blas")  # clcgraph.determinism's (older trees lack it)

n, nl, nc, repeats, out = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
rig = None if (nl, nc) == (2, 3) else sim.make_rig(n_lidars=nl, n_cameras=nc)
problem, _ = sim.simulate_problem(rig=rig, n_snapshots=n, seed=0)
S.time = types.SimpleNamespace(perf_counter=time.process_time)  # the stage timers count CPU
best = {}
for _ in range(repeats):
    c0 = time.process_time()
    with single_threaded_blas():  # as clcgraph.calibrate runs it
        r = S.calibrate(problem, Config().solve)
    cpu = time.process_time() - c0
    for k, v in {**r.stats["time_s"], "total": cpu}.items():
        best[k] = min(best.get(k, float("inf")), v)

def plain(x):
    if isinstance(x, dict):
        return {str(k): plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return plain(x.tolist())
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    return x

stats = {k: v for k, v in r.stats.items() if k not in ("time_s",)}
res = {"rt_lidar0_sensor": r.rt_lidar0_sensor, "rt_lidar0_board": r.rt_lidar0_board,
       "sigma": np.sqrt(np.diag(r.covariance_rt)), "covariance_rt": r.covariance_rt,
       "noise": r.noise, "rms": r.rms, "rejected": [[x.reason, x.stage, x.sensor, x.snapshot] for x in r.rejected],
       "stats": stats, "jackknife": r.jackknife}
json.dump({"cpu": best, "result": plain(res)}, open(out, "w"))
"""


def _run(tree: Path, case: tuple, repeats: int, keep: Path | None = None, reuse: bool = False) -> dict:
    """The child's JSON, also written to ``keep``; ``reuse``: read from ``keep`` if it is there."""
    if reuse and keep is not None and keep.exists():
        return json.loads(keep.read_text())
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "out.json"
        env = dict(os.environ, PYTHONPATH=str(tree))
        subprocess.run([sys.executable, "-c", _CHILD, *map(str, case), str(repeats), str(out)], env=env, check=True,
                       cwd=d)
        if keep is not None:
            keep.parent.mkdir(parents=True, exist_ok=True)
            keep.write_text(out.read_text())
        return json.loads(out.read_text())


def _differences(a, b, path="", tol=1e-6) -> list[str]:
    """Where ``a`` (reference) and ``b`` differ: numbers beyond ``tol`` relative (to the largest
    magnitude of the array they are in), strings and structure exactly."""
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [f"{path}: keys {sorted(set(a) ^ set(b))}"]
        return [d for k in a for d in _differences(a[k], b[k], f"{path}.{k}", tol)]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: length {len(a)} != {len(b)}"]
        rel = tol[0] if isinstance(tol, tuple) else tol
        flat = _numbers(a)
        if flat is not None:  # a numeric array: relative to its largest entry
            scale = max((abs(x) for x in flat if math.isfinite(x)), default=0.0)
            tol = (rel, max(scale, tol[1] if isinstance(tol, tuple) else 0.0))
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _differences(x, y, f"{path}[{i}]", tol)]
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        tol_rel, scale = tol if isinstance(tol, tuple) else (tol, 0.0)
        if math.isnan(a) and math.isnan(b):
            return []
        if not abs(a - b) <= tol_rel * max(abs(a), abs(b), scale) + 1e-300:
            return [f"{path}: {a!r} != {b!r}"]
        return []
    if isinstance(a, str) and isinstance(b, str) and _NOISE.sub("~0", a) == _NOISE.sub("~0", b):
        return []  # the same words; a number printed in them is at rounding level (a converged LM's decrease)
    return [] if a == b else [f"{path}: {a!r} != {b!r}"]


# numbers below 1e-10 written in a string (LM's "relative cost decrease 9.76e-15"): rounding noise
_NOISE = re.compile(r"\b\d(\.\d+)?e-(1[1-9]|[2-9]\d|\d{3})\b")


def _numbers(x):
    """Every number of a nested list, or None if it holds anything else."""
    if isinstance(x, list):
        out = []
        for v in x:
            n = _numbers(v)
            if n is None:
                return None
            out += n
        return out
    return [float(x)] if isinstance(x, (int, float)) and not isinstance(x, bool) else None


def _pose_error(a: list, b: list) -> float:
    import numpy as np

    a, b = np.asarray(a, float), np.asarray(b, float)
    ok = np.isfinite(a) & np.isfinite(b)
    if not np.array_equal(np.isfinite(a), np.isfinite(b)):
        return float("inf")
    return float(np.max(np.abs(a[ok] - b[ok]), initial=0.0))


def compare(ref: dict, new: dict) -> list[str]:
    """The differences beyond the tolerances (module docstring)."""
    bad = []
    for key in ("rt_lidar0_sensor", "rt_lidar0_board"):
        e = _pose_error(ref[key], new[key])
        if not e <= 1e-9:
            bad.append(f"{key}: max |difference| {e:.3g} > 1e-9")
    bad += _differences(ref["sigma"], new["sigma"], "sigma", 1e-6)
    rest = lambda r: {k: v for k, v in r.items() if k not in ("rt_lidar0_sensor", "rt_lidar0_board", "sigma")}  # noqa: E731
    return bad + _differences(rest(ref), rest(new), "", 1e-6)


def _reference_tree(rev: str) -> Path:
    dest = ROOT / "build" / "backend_equivalence" / rev
    if not (dest / "clcgraph").exists():
        dest.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "clcgraph"], check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.backend_equivalence", description=__doc__.splitlines()[0])
    ap.add_argument("--reference", default="main", help="git revision to compare against (default: main)")
    ap.add_argument("--reference-tree", type=Path, help="a source tree to compare against instead of a revision")
    ap.add_argument("--cases", nargs="+", default=["24x2+3", "240x3+5"], help="POSESxLIDARS+CAMERAS")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--rounds", type=int, default=1,
                    help="solve in alternating reference / this-tree processes this many times (best CPU per stage)")
    ap.add_argument("--keep-reference", action="store_true",
                    help="reuse the reference's results from an earlier run (build/backend_equivalence/)")
    args = ap.parse_args(argv)
    ref_tree = args.reference_tree or _reference_tree(
        subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", args.reference], check=True,
                       capture_output=True, text=True).stdout.strip())
    failed = False
    for c in args.cases:
        n, sensors = c.split("x")
        nl, nc = sensors.split("+")
        case = (int(n), int(nl), int(nc))
        keep = ROOT / "build" / "backend_equivalence" / f"{ref_tree.name}-{c}-r{args.repeats}.json"
        ref = _run(ref_tree, case, args.repeats, keep, args.keep_reference)
        new = _run(ROOT, case, args.repeats)
        for _ in range(args.rounds - 1):  # alternate the two processes: the load drifts between them
            for acc, tree in ((ref, ref_tree), (new, ROOT)):
                for stage, cpu in _run(tree, case, args.repeats)["cpu"].items():
                    acc["cpu"][stage] = min(acc["cpu"].get(stage, float("inf")), cpu)
        bad = compare(ref["result"], new["result"])
        failed |= bool(bad)
        print(f"== {c}: {'same results' if not bad else f'{len(bad)} DIFFERENCES'}")
        for line in bad[:20]:
            print("   ", line)
        stages = list(dict.fromkeys([*ref["cpu"], *new["cpu"]]))
        w = max(map(len, stages))
        print(f"{'stage':{w}s} | CPU s before | CPU s after | after/before")
        for s in stages:
            a, b = ref["cpu"].get(s, float("nan")), new["cpu"].get(s, float("nan"))
            print(f"{s:{w}s} | {a:12.3f} | {b:11.3f} | {b / a if a else float('nan'):12.2f}")
        print(flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
