"""`python -m clcgraph.cli ...`: the same entry point as the `clcgraph` command."""

import sys

from .main import main

if __name__ == "__main__":
    sys.exit(main())
