"""`clcgraph segment --dump`: the segmentation's intermediate stages of every scan in one npz.

Keys per scan k: ``scan{k}_segments`` (S,2,3) segment end points, ``scan{k}_segment_ring``,
``scan{k}_cluster{j}_segments`` (segment ids), ``scan{k}_candidate{j}_points`` (point indices)
and ``scan{k}_candidate{j}_verdict`` (text), ``scan{k}_accepted`` (point indices).
"""

from __future__ import annotations

import numpy as np


def write_segmentation_dump(path, debugs) -> None:
    """``debugs``: one frontend.lidar_board.Debug per scan, filled by segment_many."""
    dump = {}
    for k, dbg in enumerate(debugs):
        dump[f"scan{k}_segments"] = dbg.segments if dbg.segments is not None else np.zeros((0, 2, 3))
        dump[f"scan{k}_segment_ring"] = dbg.segment_rank if dbg.segment_rank is not None else np.zeros(0)
        for j, ids in enumerate(dbg.clusters):
            dump[f"scan{k}_cluster{j}_segments"] = ids
        for j, (idx, verdict) in enumerate(dbg.candidates):
            dump[f"scan{k}_candidate{j}_points"] = idx
            dump[f"scan{k}_candidate{j}_verdict"] = np.array(verdict)
        dump[f"scan{k}_accepted"] = dbg.accepted if dbg.accepted is not None else np.zeros(0, int)
    np.savez_compressed(path, **dump)
