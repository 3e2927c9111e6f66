"""`python -m clcgraph ...`: the same entry point as the `clcgraph` command."""

from clcgraph.cli import run

run()
