"""clcgraph: extrinsic calibration of rigs of rotating LIDARs and cameras.

The public API lives in ``clcgraph.api``; its names are re-exported here lazily so
that ``import clcgraph`` stays cheap (no gtsam/open3d until used).
"""

import logging

# Importing clcgraph changes nothing global: no environment variables, no matplotlib backend,
# no signal handlers (the `clcgraph` command sets OMP_WAIT_POLICY=PASSIVE and its handlers).

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())

_API = {
    "calibrate",
    "calibrate_bags",
    "calibrate_targetless",
    "read_problem",
    "segment",
    "detect",
    "simulate",
    "load_result",
    "write_outputs",
    "summary_table",
    "replay",
    "compare",
}


def __getattr__(name):
    if name in _API:
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'clcgraph' has no attribute '{name}'")
