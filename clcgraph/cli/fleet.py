"""The command that calibrates many vehicles: fleet (clcgraph.fleet through api.calibrate_fleet)."""

from __future__ import annotations

from .common import add_command, in_range


def _fleet(args) -> int:
    import os

    from .. import api
    from ..outputs.tables import fleet_table

    if args.workers is not None:
        in_range(args.workers, "--workers", 0, 1024)
    # Dask logs every connection at INFO (here and in its worker processes, which inherit this)
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "info" if args.verbose else "error")
    summary = api.calibrate_fleet(args.manifest, args.out, cluster=args.cluster, workers=args.workers,
                                  resume=args.resume)
    print(fleet_table(summary))
    print(f"wrote {args.out}/fleet.yaml, fleet.csv and fleet.html")
    return 0


def add_fleet(sub):
    p = add_command(sub, "fleet", run=_fleet,
                    help="calibrate many vehicles (a manifest) in parallel, compare each with its last calibration")
    p.add_argument("manifest", metavar="MANIFEST.yaml", help="defaults + vehicles (id, bags, previous); see docs/fleet.md")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="DIR/<id>/ per vehicle, DIR/fleet.yaml, .csv, .html: new, empty or an earlier fleet output")
    p.add_argument("--cluster", default=None, metavar="ADDRESS",
                   help="run on a Dask cluster: tcp://scheduler:8786, or local:N for N local worker processes")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="local process pool size (default: the CPUs available); 0: one vehicle after another in this process")
    p.add_argument("--resume", action="store_true", help="keep vehicles whose DIR/<id>/ is complete")


COMMANDS = (add_fleet,)
