"""`python -m clcgraph.cli ...`: the same entry point as the `clcgraph` command."""

from .main import run

if __name__ == "__main__":
    run()
