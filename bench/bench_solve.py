"""Backend solve time vs problem size (``python -m bench solve``).

Cases: the demo-sized rig (2 LIDARs + 3 cameras, 24 board poses) up to 240 poses x 8 sensors,
each with the LIDAR board-edge factors off and on (solve.lidar_edges).
The solve runs with BLAS on one thread, as ``clcgraph.calibrate`` runs it (clcgraph/determinism.py).
Prints a table with the time per solve (best of a few runs for the small cases; wall and this
process's CPU), the number of observations, and the growth exponent between consecutive cases
of the same edge setting: CPU time ~ Nobs^exponent (CPU: wall time on a loaded machine says little).
Goals on the 2-core reference machine (issue 16): <= 0.5 s (24 poses) and <= 10 s (240 x 8), growing
linearly (exponent ~1); each goal's row prints the measured time, the goal and their ratio.
A second table splits each solve into its stages (calibrate's ``stats["time_s"]``, wall s of the
best run): seed, the LMs, the noise/outlier rounds, the noise components (REML), the board checks
(backend/board_check.py), Marginals, the jackknife (with the consider terms' known columns), the
consider terms, the consistency checks and the units' error sensitivities (for `compare`: worked out
by a second process during the checks, so the time waited for them after the checks).
"""

from __future__ import annotations

import dataclasses
import math
import time

from clcgraph.config import Config


def _problem(n_snapshots: int, n_lidars: int, n_cameras: int, seed: int = 0):
    from clcgraph.sim import observations as sim

    rig = None if (n_lidars, n_cameras) == (2, 3) else sim.make_rig(n_lidars=n_lidars, n_cameras=n_cameras)
    problem, _ = sim.simulate_problem(rig=rig, n_snapshots=n_snapshots, seed=seed)
    return problem


def _time(problem, options, repeats: int) -> tuple[float, float, dict]:
    """(wall s, CPU s, stage times) of the best of ``repeats`` solves (CPU: this process's, the
    figure that means something on a loaded machine; stages: calibrate's, of the best run)."""
    from clcgraph.backend.solve import calibrate
    from clcgraph.determinism import single_threaded_blas

    best, best_cpu, stages = math.inf, math.inf, {}
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        with single_threaded_blas():  # as clcgraph.calibrate runs it
            res = calibrate(problem, options)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        if cpu < best_cpu:
            stages = res.stats["time_s"]
        best, best_cpu = min(best, wall), min(best_cpu, cpu)
    return best, best_cpu, stages


CASES = [  # (snapshots, lidars, cameras, repeats, target_s)
    (24, 2, 3, 3, 0.5),
    (72, 2, 3, 1, None),
    (240, 2, 3, 1, None),
    (240, 3, 5, 1, 10.0),
]
STAGES = [("seed", "seed"), ("lm", "LM"), ("noise_and_outliers", "noise rounds"), ("noise_components", "REML"),
          ("board_checks", "board checks"), ("covariance", "marginals"), ("jackknife", "jackknife"),
          ("consider", "consider"), ("consistency", "consistency"), ("unit_error_sensitivities", "unit errors")]


def _table(head, rows) -> list[str]:
    w = [max(len(r[i]) for r in rows + [head]) for i in range(len(head))]
    fmt = lambda r: " | ".join(c.rjust(w[i]) for i, c in enumerate(r))  # noqa: E731
    return [fmt(head), "-+-".join("-" * x for x in w)] + [fmt(r) for r in rows]


def main() -> str:
    rows, stage_rows = [], []
    for edges in (False, True):
        options = dataclasses.replace(Config().solve, lidar_edges=edges)
        prev = None
        for n, nl, nc, reps, target in CASES:
            problem = _problem(n, nl, nc)
            nobs = len(problem.lidar_observations) + len(problem.camera_observations)
            t, cpu, st = _time(problem, options, reps)
            growth = "" if prev is None else f"{math.log(cpu / prev[1]) / math.log(nobs / prev[0]):.2f}"
            status = "" if target is None else ("ok" if t <= target else "MISSED")
            on = "on" if edges else "off"
            rows.append((f"{n}", f"{nl}+{nc}", on, f"{nobs}", f"{t:.3f}", f"{cpu:.3f}", growth,
                         "" if target is None else f"{target:g}", "" if target is None else f"{t / target:.2f}", status))
            stage_rows.append((f"{n}", f"{nl}+{nc}", on, *(f"{st.get(k, 0.0):.3f}" for k, _ in STAGES),
                               f"{st.get('total', 0.0):.3f}"))
            prev = (nobs, cpu)
    head = ("poses", "lidars+cams", "edges", "observations", "solve s", "cpu s", "growth exp (cpu)", "goal s", "ratio", "")
    stage_head = ("poses", "lidars+cams", "edges", *(name for _, name in STAGES), "total")
    return "\n".join(_table(head, rows) + ["", "stages (wall s, best run):"] + _table(stage_head, stage_rows))


if __name__ == "__main__":
    print(main())
