"""`python -m clcgraph ...`: the same entry point as the `clcgraph` command."""

import sys

from clcgraph.cli import main

sys.exit(main())
