"""Fleet benchmark: vehicles per hour serially, on the local process pool and on a local Dask
cluster, and what each engine costs per vehicle.

Run: ``python -m bench.bench_fleet [--vehicles 4] [--poses 8] [--workers 2]``. The vehicles are
tiny simulated captures (a VLP-16 and a 640x480 camera, ``--poses`` bag-per-pose bags each, planned tilts,
no clutter), simulated once into a temporary folder. Prints per engine: wall time of the whole
fleet, vehicles per hour, the mean wall time of one vehicle inside its worker, and the engine's
overhead: its start-up (pool / cluster) and, per vehicle, the round trip of a vehicle that fails
at once (a missing bag: submit, pickle the job, run, return the row).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

RIG = """
lidars:
  - {topic: /lidar, model: vlp16, layout: velodyne, frame_id: lidar, xyz: [0, 0, 1.9], rpy_deg: [0, 0, 0]}
cameras:
  - {topic: /cam, model: cam.cameramodel, encoding: mono8, frame_id: cam, xyz: [0.3, -0.2, 1.5], rpy_deg: [0, 4, -5]}
"""


def _fleet(root: Path, n_vehicles: int, n_poses: int) -> Path:
    import mrcal

    from clcgraph.sim.capture import simulate

    mrcal.cameramodel(intrinsics=("LENSMODEL_PINHOLE", np.array([400.0, 400.0, 319.5, 239.5])),
                      imagersize=np.array([640, 480])).write(str(root / "cam.cameramodel"))
    (root / "rig.yaml").write_text(RIG)
    lines = ["defaults:", "  topics: [/lidar, /cam]", "  models: [cam.cameramodel]", "vehicles:"]
    for k in range(n_vehicles):
        simulate(root / "rig.yaml", root / f"v{k}", n_poses=n_poses, seed=k, clutter=False, planned_tilts=True)
        lines += [f"  - {{id: v{k}, bags: v{k}/*.bag}}"]
    (root / "fleet.yaml").write_text("\n".join(lines) + "\n")
    (root / "null.yaml").write_text("defaults: {topics: [/lidar, /cam]}\nvehicles:\n"
                                    + "".join(f"  - {{id: n{k}, bags: missing-{k}.bag}}\n" for k in range(n_vehicles)))
    return root


def _engines(workers: int):
    """(name, start() -> (executor, stop)) per engine."""
    from clcgraph.fleet import ScriptSafeProcessPool, SerialExecutor

    def serial():
        return SerialExecutor(), lambda: None

    def pool():
        ex = ScriptSafeProcessPool(workers)
        return ex, lambda: ex.shutdown(wait=True)

    def dask():
        import distributed

        cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                           dashboard_address=":0")
        client = distributed.Client(cluster)
        return client.get_executor(), lambda: (client.close(), cluster.close())

    out = [("serial (this process)", serial), (f"process pool ({workers})", pool)]
    try:
        import distributed  # noqa: F401
        out.append((f"dask LocalCluster ({workers})", dask))
    except ImportError:
        pass
    return out


def run(n_vehicles: int = 4, n_poses: int = 8, workers: int = 2) -> list[tuple]:
    from clcgraph import progress
    from clcgraph.fleet import calibrate_fleet

    progress.set_enabled(False)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = _fleet(Path(tmp), n_vehicles, n_poses)
        for k, (name, start) in enumerate(_engines(workers)):
            t = time.perf_counter()
            ex, stop = start()
            t_start = time.perf_counter() - t
            try:
                t = time.perf_counter()
                s = calibrate_fleet(root / "fleet.yaml", root / f"out{k}", ex)
                wall = time.perf_counter() - t
                t = time.perf_counter()
                calibrate_fleet(root / "null.yaml", root / f"null{k}", ex)
                null = (time.perf_counter() - t) / n_vehicles
            finally:
                stop()
            ok = sum(v["status"] == "ok" for v in s["vehicles"])
            inside = float(np.mean([v["time_s"] for v in s["vehicles"]]))
            rows.append((name, wall, 3600.0 * ok / wall, inside, t_start, null, ok))
    return rows


def table(rows) -> str:
    head = ("engine", "fleet wall [s]", "vehicles/hour", "one vehicle in its worker [s]", "engine start [s]",
            "overhead per vehicle [s]", "ok")
    cells = [head] + [(r[0], f"{r[1]:.1f}", f"{r[2]:.0f}", f"{r[3]:.1f}", f"{r[4]:.2f}", f"{r[5]:.3f}", str(r[6]))
                      for r in rows]
    widths = [max(len(c[k]) for c in cells) for k in range(len(head))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in cells)


def main(argv: list[str] | None = None) -> str:
    p = argparse.ArgumentParser(prog="python -m bench.bench_fleet")
    p.add_argument("--vehicles", type=int, default=4)
    p.add_argument("--poses", type=int, default=8)
    p.add_argument("--workers", type=int, default=2)
    a = p.parse_args(argv if argv is not None else [])
    return table(run(a.vehicles, a.poses, a.workers))


if __name__ == "__main__":
    import sys

    print(main(sys.argv[1:]))
