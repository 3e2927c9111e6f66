"""Compare clcgraph's solves of the two ACFR runs with each other, with the ACFR tool's own
result, and with a leave-one-board-out jackknife of each run.

SYNOPSIS
    python -m bench.real.acfr_compare OUT1 OUT2 --acfr RUN1/acfr_result.csv RUN2/acfr_result.csv
    # OUTk: a `clcgraph solve --out` directory (calibration.yaml, problem.npz) of run k

Prints, per run: boards used, T_lidar_camera (position, roll/pitch/yaw) with its 1-sigma, the
ACFR result and the difference (rotation angle of R_ours^T R_acfr, translation); the
jackknife spread of the camera's rt per principal axis of the reported covariance, next to
the reported sigma and their ratio; then the two runs' difference against their combined
sigma (per axis and Mahalanobis). The camera is sensor 1 (lidar0 is the reference).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from clcgraph.geometry import rpy_deg_from_R


def _T(rt: np.ndarray) -> np.ndarray:
    from clcgraph.geometry import T_from_rt

    return T_from_rt(rt)


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def jackknife(dump: Path, sensor: int = 1) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """(full rt (6,), leave-one-out rts (n,6), the snapshot left out of each)."""
    import dataclasses

    from clcgraph.backend.replay import replay_problem
    from clcgraph.outputs.dump import load_problem

    problem, config = load_problem(dump)
    # a board left out may leave a direction resting on one board (refused by default): still a sample
    options = dataclasses.replace(config.solve, refuse_inconsistent=False)
    full = replay_problem(problem, options)
    used = [int(k) for k in np.flatnonzero(np.isfinite(full.rt_lidar0_board).all(axis=1))]
    rts = [replay_problem(problem, options, exclude=[k]).rt_lidar0_sensor[sensor] for k in used]
    return full, np.array(rts), used


def principal(cov: np.ndarray, jk: np.ndarray) -> list[tuple[float, float]]:
    """Per principal axis of ``cov`` (ascending): (reported sigma, jackknife sigma along it)."""
    n = len(jk)
    d = jk - jk.mean(axis=0)
    cov_jk = (n - 1) / n * d.T @ d
    lam, vec = np.linalg.eigh(cov)
    return [(float(np.sqrt(lam[i])), float(np.sqrt(vec[:, i] @ cov_jk @ vec[:, i]))) for i in range(len(lam))]


def main(argv=None) -> int:
    from .acfr_to_bags import acfr_result

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("outs", nargs=2, type=Path)
    ap.add_argument("--acfr", nargs=2, type=Path, required=True)
    a = ap.parse_args(argv)
    res = []
    for k, (out, csv) in enumerate(zip(a.outs, a.acfr), 1):
        full, jk, used = jackknife(out / "problem.npz")
        rt = full.rt_lidar0_sensor[1]
        cov = full.covariance_block(1)
        T = _T(rt)
        Ta, sa = acfr_result(csv)
        sd = np.sqrt(np.diag(cov))
        print(f"run{k}: {len(used)} boards used (snapshots {used})")
        print(f"  clcgraph T_lidar_camera: t = {np.round(T[:3, 3] * 1e3, 1)} mm  1-sigma {np.round(sd[3:] * 1e3, 2)} mm; "
              f"roll, pitch, yaw (fixed x-y-z) = {np.round(rpy_deg_from_R(T[:3, :3]), 3)} deg  1-sigma(r) {np.round(np.degrees(sd[:3]), 3)} deg")
        print(f"  ACFR (mean of 50):       t = {np.round(Ta[:3, 3] * 1e3, 1)} mm  std {np.round(sa[3:] * 1e3, 1)} mm; "
              f"roll, pitch, yaw (fixed x-y-z) = {np.round(rpy_deg_from_R(Ta[:3, :3]), 3)} deg  std {np.round(np.degrees(sa[:3]), 3)} deg")
        dt = T[:3, 3] - Ta[:3, 3]
        print(f"  difference: rotation {_angle_deg(T[:3, :3], Ta[:3, :3]):.3f} deg, translation "
              f"{np.round(dt * 1e3, 1)} mm (|dt| {np.linalg.norm(dt) * 1e3:.1f} mm)")
        for name, sl, unit, f in (("position", slice(3, 6), "mm", 1e3), ("rotation", slice(0, 3), "deg", np.degrees(1.0))):
            rows = principal(cov[sl, sl], jk[:, sl])
            print(f"  {name} per principal axis: reported / jackknife [{unit}] = " + ", ".join(
                f"{s * f:.3g} / {j * f:.3g} (x{j / s:.2f})" for s, j in rows))
        moved = np.linalg.norm(jk[:, 3:] - rt[3:], axis=1)
        turned = [_angle_deg(_T(r)[:3, :3], T[:3, :3]) for r in jk]
        i = int(np.argmax(moved))
        print(f"  largest single-board influence: snapshot {used[i]} moves t by {moved[i] * 1e3:.1f} mm "
              f"(largest rotation change {max(turned):.3f} deg)")
        res.append((rt, cov))
    (rt1, c1), (rt2, c2) = res
    d = rt1 - rt2
    C = c1 + c2
    z = d / np.sqrt(np.diag(C))
    dt = _T(rt1)[:3, 3] - _T(rt2)[:3, 3]
    print(f"run1 - run2: translation {np.round(dt * 1e3, 1)} mm (|dt| {np.linalg.norm(dt) * 1e3:.1f} mm), rotation "
          f"{_angle_deg(_T(rt1)[:3, :3], _T(rt2)[:3, :3]):.3f} deg; per rt axis / combined sigma {np.round(z, 2)}; "
          f"Mahalanobis position {np.sqrt(d[3:] @ np.linalg.solve(C[3:, 3:], d[3:])):.2f}, "
          f"full rt {np.sqrt(d @ np.linalg.solve(C, d)):.2f} (6 dof)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
