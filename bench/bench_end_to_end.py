"""End-to-end wall time of `clcgraph demo` (20 ROS1 bags: a VLP-16, a 32-ring LIDAR, two
cameras), split by stage. The demo data are simulated first if missing (not timed)."""

from __future__ import annotations

import tempfile
import time


def main() -> str:
    from clcgraph import api
    from clcgraph.sim.capture import DEMO_DIR, simulate_demo

    if not (DEMO_DIR / "truth.yaml").exists():
        simulate_demo()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        result, errors = api.run_demo(f"{tmp}/out")
        total = time.perf_counter() - t0
    stages = result.stats["stage_time_s"]
    rows = [f"{'stage':12s} {'s':>7s}"]
    rows += [f"{k:12s} {v:7.2f}" for k, v in stages.items()]
    rows.append(f"{'total':12s} {total:7.2f}")
    worst = max(errors, key=lambda e: e["rotation_deg"])
    rows.append(f"worst sensor error: {worst['rotation_deg']:.3f} deg, "
                f"{max(e['translation_mm'] for e in errors):.1f} mm")
    return "\n".join(rows)
