"""The ``clcgraph`` command: one module per command group, each command a parser and a thin
``run(args)``: parse, call ``clcgraph.api``, print what ``clcgraph.outputs.tables`` formats.

- calibrate.py: solve, targetless, replay, demo, config
- bags.py: show-bag, segment, detect, infer-lidar-spacing (looking at bags before solving)
- results.py: format-for-ros, show-aligned, show-uncertainty, compare (using a calibration)
- simulate.py: simulate, simulate-drive
- fleet.py: fleet (many vehicles from a manifest)
- common.py: --config / --set, -v / -q in either position, --force, range checks
- main.py: the parser, logging, errors as one line (exit 2; 1 for an internal error; a
  traceback only with --verbose), SIGINT / SIGTERM as 130 / 143.

Heavy imports happen inside each ``run``, so ``clcgraph --help`` is instant.
"""

from .main import build_parser, main, run

__all__ = ["build_parser", "main", "run"]
