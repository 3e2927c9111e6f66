"""Does `clcgraph compare`'s "moved" fire at the chosen rate on re-solves of an unchanged rig,
and does it catch a 3-sigma knock? (``python -m bench fleet_false_alarms``;
``python -m bench.bench_fleet_false_alarms --pairs 200 --workers 2 [--log pairs.jsonl]``).

A pair is two independent captures of one rig (fresh board poses, tilted as planned (pitched up
and down, turned left and right in turn: random tilts are often refused), noise and correlated
errors, all drawn anew per capture; a capture the solve refuses (solve.refuse_inconsistent) is
captured again, up to RECAPTURES times, and counted), each solved by ``clcgraph.api.calibrate`` with the default
config (the per-observation noise model on), compared with ``clcgraph.compare``. A third
capture of the same rig with every variable sensor knocked by 3 sigma (of that pair's
difference, tangent coordinates) in rotation and 3 sigma in translation, each along its least
certain direction, compared with the pair's first solve, measures the power (every other
pair: the knocked capture costs a third solve). The noise models are bench_uncertainty's:
``independent`` (only the Gaussian noise the factors assume), ``per-observation`` (+ board
bow, mixed pixels, per-board corner bias: errors that differ from board to board) and ``all``
(+ per-ring range bias and elevation error and a lens-model field, fixed for a whole capture
and drawn anew for the next one: what the per-observation model does not describe); and, to
tell which of those three matters, ``+ring-bias``, ``+ring-elevation``, ``+lens-field``: the
per-observation errors plus that one alone (``--cases``). ``same-units`` (and ``+... same-units``)
draw the capture-fixed errors once per pair, equal in its captures (the knocked one too): the same
sensor units calibrated twice, as a fleet sees them, where the other cases are a unit swap;
``same-units same-boards`` also captures the same board poses again. Captures are
small (backend-level simulator: no scene, no bags; ``make_rig(2, 1)``: lidar0, a 32-ring
LIDAR and a camera, 12 snapshots), so hundreds of solves fit on two cores.

Each pair is compared three ways (VARIANTS): with the units' shared errors at the sigmas the capture
was simulated with ("units": what a team stating its units' figures gets), at the config's defaults
("default"), and without them ("none": the covariances alone). The knock is 3 sigma of the two
covariances alone, the same physical knock whichever way it is compared.
Prints per noise model, sensor and variant: "moved" at p < 0.01 and p < 0.05 over the unchanged pairs
with the Clopper-Pearson 95 % interval, the mean chi-square of the pairs (6 expected) and of
each solve against the truth with the Kolmogorov-Smirnov p-value of each set against chi2(6)
("all" pools both sensors, which are correlated within a pair: read its KS p loosely), and the power at the 3-sigma knock next to the power the
noncentral chi-square predicts (mean over pairs).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import numpy as np

RIG_SHAPE = (2, 1)  # lidar0, a 32-ring LIDAR tilted and offset, one camera
N_SNAPSHOTS = 12
RECAPTURES = 4  # a refused capture (solve.refuse_inconsistent, on by default) is captured again, up to this often
CASES = ("independent", "per-observation", "all")  # bench_uncertainty's noise models
# per-observation + one of the errors fixed for a whole capture, at its CorrelatedErrors.realistic() size
ONE_FIXED = {"+ring-bias": "ring_range_bias_m", "+ring-elevation": "ring_elevation_deg", "+lens-field": "lens_field_px"}
# the same errors, but the capture-fixed ones drawn once per pair (vehicle) and equal in its captures:
# the same sensor units calibrated twice, as a fleet sees them ("all" and "+..." draw them anew: a unit swap)
SAME_UNITS = {"same-units": "all", **{f"{c} same-units": c for c in ONE_FIXED}}
# ... and the same board poses too (noise and per-observation errors still drawn anew): does what is
# left of the fixed errors in the difference come from the two captures' different board poses?
SAME_BOARDS = {"same-units same-boards": "all"}
SAME_UNITS.update(SAME_BOARDS)
ALL_CASES = (*CASES, *ONE_FIXED, *SAME_UNITS)


def _errors(case: str):
    from bench.bench_uncertainty import _errors as errors_of
    from clcgraph.sim.observations import CorrelatedErrors

    case = SAME_UNITS.get(case, case)
    if case in ONE_FIXED:
        field = ONE_FIXED[case]
        return dataclasses.replace(errors_of("per-observation"), **{field: getattr(CorrelatedErrors.realistic(), field)})
    return errors_of(case)


def _knock(rt, delta) -> np.ndarray:
    """rt of the pose T Exp(delta) to first order: R Exp(omega), t + R v (the comparison's tangent)."""
    from clcgraph.geometry import R_from_r, rt_from_R_t

    R = R_from_r(rt[:3])
    return rt_from_R_t(R @ R_from_r(delta[:3]), rt[3:] + R @ delta[3:])


def three_sigma(Sd: np.ndarray) -> np.ndarray:
    """(6,) 3 sigma of Sd's rotation block and 3 sigma of its translation block, each along its least certain axis."""
    delta = np.zeros(6)
    for block in (slice(0, 3), slice(3, 6)):
        w, V = np.linalg.eigh(Sd[block, block])
        delta[block] = 3 * np.sqrt(w[-1]) * V[:, -1]
    return delta


# How `compare` takes the units' shared errors into account (compare.unit_*; docs/fleet.md): "units" = the
# sigmas the capture was simulated with (a fleet team that states its units' figures), "default" = the
# config's, "none" = 0 (the covariances alone: what compare did before the units' errors were paired)
VARIANTS = ("units", "default", "none")


def _compare_config(variant: str, errors):
    from clcgraph.config import Config

    if variant == "default":
        return Config()
    f = (errors.ring_range_bias_m, errors.ring_elevation_deg, errors.lens_field_px) if variant == "units" else (0, 0, 0)
    return Config.from_dict({"compare": dict(zip(("unit_ring_range_bias_m", "unit_ring_elevation_deg",
                                                  "unit_lens_field_px"), map(float, f)))})


def pair(case: str, k: int, *, seed0: int = 50_000, rig_shape=RIG_SHAPE, n_snapshots: int = N_SNAPSHOTS,
         knock: bool = True, planned_tilts: bool = True) -> dict:
    """One pair (and its knocked capture): per variable sensor the comparisons' chi2 and p, and each solve's chi2 to the truth.
    ``planned_tilts``: the boards tilted as a careful person plans them (simulate_problem), else at random."""
    from scipy.stats import chi2, ncx2

    from clcgraph import api
    from clcgraph.comparison import compare, sensor_change
    from clcgraph.config import Config
    from clcgraph.errors import DegenerateError, SolveError
    from clcgraph.geometry import T_from_rt, tangent_covariance_from_rt
    from clcgraph.sim.observations import make_rig, simulate_problem

    rig, errors, cfg = make_rig(*rig_shape), _errors(case), Config()
    seed = seed0 + 1000 * ALL_CASES.index(case) + 3 * k
    units = seed + 1_000_000 if case in SAME_UNITS else None  # the pair's sensor units, in all its captures
    boards = seed + 2_000_000 if case in SAME_BOARDS else None  # ... and its board poses
    cpu = time.process_time()

    refused = []

    def solve(r, s, boards):
        """A capture that is refused is captured again (fresh board poses and noise, the same units), as a
        fleet team does; up to RECAPTURES times, each refusal counted."""
        for j in range(RECAPTURES + 1):
            problem, truth = simulate_problem(rig=r, n_snapshots=n_snapshots, seed=s + 7919 * j, errors=errors,
                                              fixed_errors_seed=units, board_poses_seed=boards, planned_tilts=planned_tilts)
            try:
                return api.calibrate(problem, cfg), truth
            except (DegenerateError, SolveError) as e:
                refused.append(f"{type(e).__name__}: {str(e).splitlines()[0][:120]}")
                if j == RECAPTURES or boards is not None:  # the same boards again would be refused again
                    raise

    for j in range(RECAPTURES + 1 if boards is not None else 1):  # the same boards refused: both captured again
        try:
            (ra, truth), (rb, _) = solve(rig, seed, boards), solve(rig, seed + 1, boards)
            break
        except (DegenerateError, SolveError) as e:  # counted, never hidden
            if boards is None or j == RECAPTURES:
                return {"case": case, "k": k, "skipped": f"{type(e).__name__}: {str(e).splitlines()[0]}", "refused": refused}
            boards += 7919
    same = {v: compare(ra, rb, config=_compare_config(v, errors)) for v in VARIANTS}
    out = {"case": case, "k": k, "sensors": {}}
    deltas = {}
    for i in ra.variable_sensors():
        topic = ra.problem.sensors[i].topic
        rows = {v: next(s for s in c.sensors if s.topic == topic) for v, c in same.items()}
        row = rows["units"]
        Sd = sum(tangent_covariance_from_rt(np.asarray(r.rt_lidar0_sensor[i]), r.covariance_block(i)) for r in (ra, rb))
        to_truth = [sensor_change(topic, T_from_rt(truth.rt_lidar0_sensor[i]), 1e-12 * np.eye(6),
                                  T_from_rt(r.rt_lidar0_sensor[i]), r.covariance_block(i), false_alarm_rate=0.01,
                                  max_rotation_deg=1, max_translation_mm=1).chi2 for r in (ra, rb)]
        deltas[i] = three_sigma(Sd)
        lam = float(deltas[i] @ np.linalg.solve(Sd, deltas[i]))
        out["sensors"][topic] = {"chi2": row.chi2, "p": row.p_value, "to_truth": to_truth, "lam": lam,
                                 "variants": {v: {"chi2": r.chi2, "p": r.p_value} for v, r in rows.items()},
                                 "power_predicted": {str(a): float(ncx2.sf(chi2.isf(a, 6), 6, lam)) for a in (0.01, 0.05)},
                                 "cond": float(np.linalg.cond(Sd))}
    if knock:
        rts = np.array(rig.rt_lidar0_sensor, float)
        for i, d in deltas.items():
            rts[i] = _knock(rts[i], d)
        try:
            rc, _ = solve(dataclasses.replace(rig, rt_lidar0_sensor=rts), seed + 2, boards)
        except (DegenerateError, SolveError) as e:
            out["knock_skipped"] = f"{type(e).__name__}: {str(e).splitlines()[0]}"
        else:
            for v in VARIANTS:
                for s in compare(ra, rc, config=_compare_config(v, errors)).sensors:
                    if s.topic in out["sensors"]:
                        out["sensors"][s.topic]["variants"][v].update(chi2_knocked=s.chi2, p_knocked=s.p_value)
                        if v == "units":
                            out["sensors"][s.topic].update(chi2_knocked=s.chi2, p_knocked=s.p_value)
    out["cpu_s"] = time.process_time() - cpu
    out["refused"] = refused
    return out


def run(n_pairs: int, *, workers: int = 2, cases=CASES, log: str | None = None, knock_every: int = 2) -> list[dict]:
    """All pairs on a spawn process pool of ``workers`` (0: in this process); ``log``: one JSON line per pair as it ends."""
    import concurrent.futures as cf
    import multiprocessing

    done = []
    if log and os.path.exists(log):  # a run stopped early goes on where it was
        with open(log) as fh:
            done = [json.loads(line) for line in fh if line.strip()]
    have = {(r["case"], r["k"]) for r in done}
    jobs = [(c, k) for k in range(n_pairs) for c in cases if (c, k) not in have]  # interleaved: a run stopped early covers all
    if workers == 0:
        futures = [cf.Future() for _ in jobs]
        for f, (c, k) in zip(futures, jobs):
            f.set_result(pair(c, k, knock=k % knock_every == 0))
        ex = None
    else:
        ex = cf.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
        futures = [ex.submit(pair, c, k, knock=k % knock_every == 0) for c, k in jobs]
    rows = [r for r in done if r["case"] in cases and r["k"] < n_pairs]
    try:
        for f in cf.as_completed(futures):
            rows.append(f.result())
            if log:
                with open(log, "a") as fh:
                    fh.write(json.dumps(rows[-1]) + "\n")
    finally:
        if ex is not None:
            ex.shutdown(wait=True, cancel_futures=True)
    return sorted(rows, key=lambda r: (ALL_CASES.index(r["case"]), r["k"]))


def _rate(k: int, n: int) -> str:
    from scipy.stats import binomtest

    if n == 0:
        return "-"
    ci = binomtest(k, n).proportion_ci(0.95)
    return f"{k}/{n} = {k / n:5.1%} [{ci.low:5.1%}, {ci.high:5.1%}]"


def _mean_ks(x) -> str:
    """Mean of chi-square statistics, and the Kolmogorov-Smirnov p-value of them against chi2(6)."""
    from scipy.stats import chi2, kstest

    return f"{np.mean(x):.2f} ({kstest(x, chi2(6).cdf).pvalue:.2g})"


def table(rows: list[dict]) -> str:
    head = ("noise model", "sensor", "compare's unit errors", "pairs", "moved at p<0.01 [95% CI]", "moved at p<0.05 [95% CI]",
            "mean chi2 pair (KS p vs chi2(6))", "mean chi2 to truth (KS p)", "power 3-sigma at 0.01", "power at 0.05",
            "skipped")
    cells = [head]
    for case in ALL_CASES:
        mine = [r for r in rows if r["case"] == case]
        if not mine:
            continue
        ok = [r for r in mine if "sensors" in r]
        topics = sorted({t for r in ok for t in r["sensors"]})
        for topic in [*topics, "all"]:
            S = [s for r in ok for t, s in r["sensors"].items() if topic in ("all", t)]
            for v in VARIANTS:
                V = [s.get("variants", {}).get(v) or (s if v == "units" else None) for s in S]
                V = [x for x in V if x is not None]
                if not V:
                    continue
                p = np.array([x["p"] for x in V])
                pk = np.array([x["p_knocked"] for x in V if "p_knocked" in x])

                def power(a):
                    return _rate(int(np.sum(pk < a)), len(pk))

                cells.append((case, topic, v, str(len(V)), _rate(int(np.sum(p < 0.01)), len(p)),
                              _rate(int(np.sum(p < 0.05)), len(p)), _mean_ks([x["chi2"] for x in V]),
                              _mean_ks([x for s in S for x in s["to_truth"]]), power(0.01), power(0.05),
                              str(len(mine) - len(ok) if topic == "all" else "")))
    cpu = [r["cpu_s"] for r in rows if "cpu_s" in r]
    n_refused = sum(len(r.get("refused", ())) for r in rows)
    n_captures = sum(2 + ("knock_skipped" in r or any("p_knocked" in s for s in r.get("sensors", {}).values()))
                     for r in rows if "sensors" in r) + n_refused
    widths = [max(len(c[k]) for c in cells) for k in range(len(head))]
    text = "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in cells)
    return text + (f"\n(CPU per pair (2 or 3 solves): mean {np.mean(cpu):.1f} s over {len(cpu)} pairs; captures refused and "
                   f"captured again: {n_refused} of about {n_captures})")


def main(argv: list[str] | None = None) -> str:
    p = argparse.ArgumentParser(prog="python -m bench.bench_fleet_false_alarms")
    p.add_argument("--pairs", type=int, default=200, help="pairs per noise model")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--cases", nargs="*", default=list(CASES), choices=ALL_CASES)
    p.add_argument("--knock-every", type=int, default=2, help="a knocked capture for every N-th pair")
    p.add_argument("--log", help="append one JSON line per pair to this file (the pairs it has are not run again)")
    p.add_argument("--from-log", help="only print the table of the pairs in this log")
    a = p.parse_args(argv if argv is not None else [])
    if a.from_log:
        with open(a.from_log) as f:
            return table([json.loads(line) for line in f if line.strip()])
    return table(run(a.pairs, workers=a.workers, cases=tuple(a.cases), log=a.log, knock_every=a.knock_every))


if __name__ == "__main__":
    import sys

    print(main(sys.argv[1:]))
