"""Re-read a bench_uncertainty log (CLCGRAPH_BENCH_LOG) and tabulate z per (rig, sensor, axis)
with the covariance recomposed from its terms: ``python -m bench.mc_table LOG [LOG ...] [TERM=SCALE ...]``
(a term by its name's first part: ``"board flatness=0"``, ``"range offset=2"``).

Each trial's log carries the final covariance and every consider term's 1-sigma columns
(backend/consider.py), so the same trials can be judged with a term removed (scale 0) or its
stated sigma scaled, without re-solving: what the defaults of the terms should be.
"""

from __future__ import annotations

import json
import sys

import numpy as np


def _covariances(trial: dict, scales: dict):
    """(the covariance with the terms scaled, the model's part alone)."""
    C = np.array(trial["covariance_rt"])
    model = C.copy()
    for name, cols in (trial.get("terms") or {}).get("sigma_rt", {}).items():
        s = scales.get(name.split(" /")[0], 1.0)  # "range offset /lidar0" -> "range offset"
        A = np.atleast_2d(cols)  # (m, ns)
        C = C + (s**2 - 1) * A.T @ A
        model = model - A.T @ A
    return C, model


def z_of(trial: dict, scales: dict, inflation: bool = False) -> np.ndarray:
    """z along each variable sensor's principal axes (rotation then position) with the terms
    scaled; or (``inflation``) the sigma along them over the model part's alone."""
    C, model = _covariances(trial, scales)
    e = np.array(trial["error_rt"])
    z = []
    for a in range(len(e) // 6):
        for part in (slice(0, 3), slice(3, 6)):
            blk = C[6 * a:6 * a + 6, 6 * a:6 * a + 6][part, part]
            lam, V = np.linalg.eigh(blk)
            if inflation:
                m = model[6 * a:6 * a + 6, 6 * a:6 * a + 6][part, part]
                z.extend(np.sqrt(lam / np.einsum("ia,ij,ja->a", V, m, V)))
            else:
                z.extend((e[6 * a:6 * a + 6][part] @ V) / np.sqrt(lam))
    return np.array(z)


def load(paths) -> list[dict]:
    """Every trial of the logs, each (case, rig, seed) once (logs of processes run side by side)."""
    seen, rows = set(), []
    for path in paths:
        for line in open(path):
            r = json.loads(line)
            key = (r["errors"], r["effects"], tuple(r["rig"]), r["seed"])
            if key not in seen:
                seen.add(key)
                rows.append(r)
    return rows


def table(paths, scales: dict) -> str:
    rows = load(paths)
    out = ["case              rig     trials  |z|<=3 all (worst axis)  mean z^2 all (min..max axis)  "
           "axes mean z^2 > 1.5  sigma/spread (max axis)  terms' inflation (median, 90 %, max)"]
    for case in sorted({(r["errors"], r["effects"]) for r in rows}):
        sel = [r for r in rows if (r["errors"], r["effects"]) == case]
        for rig in sorted({tuple(r["rig"]) for r in sel}) + ["all"]:
            rs = [r for r in sel if rig == "all" or tuple(r["rig"]) == rig]
            by_axis: dict = {}
            for r in rs:
                for a, x in enumerate(z_of(r, scales)):
                    by_axis.setdefault((tuple(r["rig"]), a), []).append(x)
            infl = np.concatenate([z_of(r, scales, inflation=True) for r in rs])
            A = [np.array(v) for v in by_axis.values()]
            Z = np.concatenate(A)
            m = [np.mean(a**2) for a in A]
            out.append(f"{case[0]:12s} {'on' if case[1] else 'off':3s} {str(rig):8s} {len(rs):5d}  "
                       f"{np.mean(np.abs(Z) <= 3):6.1%} ({min(np.mean(np.abs(a) <= 3) for a in A):6.1%})        "
                       f"{np.mean(Z**2):5.2f} ({min(m):4.2f}..{max(m):5.2f})             "
                       f"{sum(x > 1.5 for x in m):3d} of {len(m):3d}          {1 / np.sqrt(min(m)):5.2f}"
                       f"                {np.median(infl):5.3f}, {np.quantile(infl, 0.9):5.3f}, {np.max(infl):5.3f}")
    return "\n".join(out)


if __name__ == "__main__":
    logs = [a for a in sys.argv[1:] if "=" not in a]
    print(table(logs, {k: float(v) for k, v in (a.split("=") for a in sys.argv[1:] if "=" in a)}))
