"""Backend solve time vs problem size (``python -m bench solve``).

Cases: the demo-sized rig (2 LIDARs + 3 cameras, 24 board poses) up to 240 poses x 8 sensors.
The solve runs with BLAS on one thread, as ``clcgraph.calibrate`` runs it (clcgraph/determinism.py).
Prints a table with the time per solve (best of a few runs for the small cases; wall and this
process's CPU), the number of observations, and the growth exponent between consecutive cases:
CPU time ~ Nobs^exponent (CPU: wall time on a loaded machine says little).
Goals on the 2-core reference machine (issue 16): <= 0.5 s (24 poses) and <= 10 s (240 x 8), growing
linearly (exponent ~1); each goal's row prints the measured time, the goal and their ratio.
"""

from __future__ import annotations

import math
import time

from clcgraph.config import Config


def _problem(n_snapshots: int, n_lidars: int, n_cameras: int, seed: int = 0):
    from clcgraph.sim import observations as sim

    rig = None if (n_lidars, n_cameras) == (2, 3) else sim.make_rig(n_lidars=n_lidars, n_cameras=n_cameras)
    problem, _ = sim.simulate_problem(rig=rig, n_snapshots=n_snapshots, seed=seed)
    return problem


def _time(problem, repeats: int) -> tuple[float, float]:
    """(wall s, CPU s) of the best of ``repeats`` solves (CPU: this process's, the figure that
    means something on a loaded machine)."""
    from clcgraph.backend.solve import calibrate
    from clcgraph.determinism import single_threaded_blas

    best, best_cpu = math.inf, math.inf
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        with single_threaded_blas():  # as clcgraph.calibrate runs it
            calibrate(problem, Config().solve)
        best, best_cpu = min(best, time.perf_counter() - t0), min(best_cpu, time.process_time() - c0)
    return best, best_cpu


CASES = [  # (snapshots, lidars, cameras, repeats, target_s)
    (24, 2, 3, 3, 0.5),
    (72, 2, 3, 1, None),
    (240, 2, 3, 1, None),
    (240, 3, 5, 1, 10.0),
]


def main() -> str:
    rows = []
    prev = None
    for n, nl, nc, reps, target in CASES:
        problem = _problem(n, nl, nc)
        nobs = len(problem.lidar_observations) + len(problem.camera_observations)
        t, cpu = _time(problem, reps)
        growth = "" if prev is None else f"{math.log(cpu / prev[1]) / math.log(nobs / prev[0]):.2f}"
        status = "" if target is None else ("ok" if t <= target else "MISSED")
        rows.append((f"{n}", f"{nl}+{nc}", f"{nobs}", f"{t:.3f}", f"{cpu:.3f}", growth,
                     "" if target is None else f"{target:g}", "" if target is None else f"{t / target:.2f}", status))
        prev = (nobs, cpu)
    head = ("poses", "lidars+cams", "observations", "solve s", "cpu s", "growth exp (cpu)", "goal s", "ratio", "")
    w = [max(len(r[i]) for r in rows + [head]) for i in range(len(head))]
    fmt = lambda r: " | ".join(c.rjust(w[i]) for i, c in enumerate(r))  # noqa: E731
    return "\n".join([fmt(head), "-+-".join("-" * x for x in w)] + [fmt(r) for r in rows])


if __name__ == "__main__":
    print(main())
