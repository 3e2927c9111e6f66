"""Re-read a bench_uncertainty log (CLCGRAPH_BENCH_LOG) and tabulate z per (rig, sensor, axis)
with the covariance recomposed from its terms: ``python -m bench.mc_table LOG [TERM=SCALE ...]``.

Each trial's log carries the final covariance and every consider term's 1-sigma columns
(backend/consider.py), so the same trials can be judged with a term removed (scale 0) or its
stated sigma scaled, without re-solving: what the defaults of the terms should be.
"""

from __future__ import annotations

import json
import sys

import numpy as np


def z_of(trial: dict, scales: dict) -> np.ndarray:
    """z along each variable sensor's principal axes (rotation then position) with the terms scaled."""
    C = np.array(trial["covariance_rt"])
    for name, cols in (trial.get("terms") or {}).get("sigma_rt", {}).items():
        s = scales.get(name.split(" /")[0], 1.0)  # "range offset /lidar0" -> "range offset"
        A = np.atleast_2d(cols)  # (m, ns)
        C = C + (s**2 - 1) * A.T @ A
    e = np.array(trial["error_rt"])
    z = []
    for a in range(len(e) // 6):
        for part in (slice(0, 3), slice(3, 6)):
            blk = C[6 * a:6 * a + 6, 6 * a:6 * a + 6][part, part]
            lam, V = np.linalg.eigh(blk)
            z.extend((e[6 * a:6 * a + 6][part] @ V) / np.sqrt(lam))
    return np.array(z)


def table(path: str, scales: dict) -> str:
    rows = [json.loads(line) for line in open(path)]
    out = ["case              rig     trials  |z|<=3 all (worst axis)  mean z^2 all (min..max axis)  "
           "axes mean z^2 > 1.5  sigma/spread (max axis)"]
    for case in sorted({(r["errors"], r["effects"]) for r in rows}):
        sel = [r for r in rows if (r["errors"], r["effects"]) == case]
        for rig in sorted({tuple(r["rig"]) for r in sel}) + ["all"]:
            rs = [r for r in sel if rig == "all" or tuple(r["rig"]) == rig]
            by_axis: dict = {}
            for r in rs:
                for a, x in enumerate(z_of(r, scales)):
                    by_axis.setdefault((tuple(r["rig"]), a), []).append(x)
            A = [np.array(v) for v in by_axis.values()]
            Z = np.concatenate(A)
            m = [np.mean(a**2) for a in A]
            out.append(f"{case[0]:12s} {'on' if case[1] else 'off':3s} {str(rig):8s} {len(rs):5d}  "
                       f"{np.mean(np.abs(Z) <= 3):6.1%} ({min(np.mean(np.abs(a) <= 3) for a in A):6.1%})        "
                       f"{np.mean(Z**2):5.2f} ({min(m):4.2f}..{max(m):5.2f})             "
                       f"{sum(x > 1.5 for x in m):3d} of {len(m):3d}          {1 / np.sqrt(min(m)):5.2f}")
    return "\n".join(out)


if __name__ == "__main__":
    print(table(sys.argv[1], {k: float(v) for k, v in (a.split("=") for a in sys.argv[2:])}))
