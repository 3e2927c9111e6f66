"""Benchmarks (``python -m bench``). Like the `clcgraph` command, they run OpenMP workers with
OMP_WAIT_POLICY=PASSIVE unless the user chose otherwise (importing clcgraph no longer sets it)."""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
