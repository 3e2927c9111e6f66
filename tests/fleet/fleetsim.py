"""Helpers of the fleet tests: a tiny simulated fleet (conftest.py makes it once per session) of
one rig, a VLP-16 and a 640x480 camera, eight board poses per capture:

- ``first``: the rig's first calibration (the `previous` of the others);
- ``same``: the rig captured again, nothing moved;
- ``knocked``: the camera turned 0.5 deg about lidar0's z (lidar0's axes are base_link's) and
  moved 5 mm along x;
- ``truncated``: the ``same`` capture with one bag cut in half (as a full disk leaves it).

and, for ``method: targetless``, two 6 s drives (sim/drive.py ``DrivePlan.small``: a 32-ring
mapping LIDAR and a 16-ring one, 512 columns, a street at ~2 km/h) of one rig:
``drive-first`` (calibrated: the `previous`) and ``drive-again``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

RIG = """
lidars:
  - {topic: /lidar, model: vlp16, layout: velodyne, frame_id: lidar, xyz: [0, 0, 1.9], rpy_deg: [0, 0, 0]}
cameras:
  - {topic: /cam, model: cam.cameramodel, encoding: mono8, frame_id: cam, xyz: [XCAM, -0.2, 1.5], rpy_deg: [0, 4, YAW]}
board: {corners: [10, 10], square_m: 0.1, size_m: [1.3, 1.3]}
"""
TOPICS = ["/lidar", "/cam"]
KNOCK_DEG, KNOCK_MM = 0.5, 5.0
N_POSES = 8
TARGETLESS_TOPICS = ["/top/points", "/side/points"]  # DrivePlan.small's LIDARs, the mapping one first
DRIVE_S = 6.0  # ~3 m of driving, 60 scans per LIDAR: ~25 s of CPU to calibrate (the 10 s drive takes ~36 s)


def write_rig(d: Path, *, knocked: bool) -> Path:
    import mrcal

    d.mkdir(parents=True, exist_ok=True)
    mrcal.cameramodel(intrinsics=("LENSMODEL_PINHOLE", np.array([400.0, 400.0, 319.5, 239.5])),
                      imagersize=np.array([640, 480])).write(str(d / "cam.cameramodel"))
    text = RIG.replace("XCAM", str(0.3 + (KNOCK_MM * 1e-3 if knocked else 0.0)))
    text = text.replace("YAW", str(-5.0 + (KNOCK_DEG if knocked else 0.0)))
    (d / "rig.yaml").write_text(text)
    return d / "rig.yaml"




def true_knock(data) -> np.ndarray:
    """(4,4) the knock in lidar0's frame, from the two rigs' truth: T_lidar0_cam(knocked) = D T_lidar0_cam."""
    from clcgraph.sim.rig import load_rig

    before = load_rig(data["root"] / "rig" / "rig.yaml").T_lidar0_sensor("/cam")
    after = load_rig(data["root"] / "rig-knocked" / "rig.yaml").T_lidar0_sensor("/cam")
    return after @ np.linalg.inv(before)


def manifest_text(data, vehicles=("same", "knocked", "truncated", "first")) -> str:
    """A manifest of these vehicles; each compared with ``first``'s calibration."""
    lines = ["defaults:", "  method: target", f"  topics: [{', '.join(TOPICS)}]", f"  models: [{data['model']}]",
             "vehicles:"]
    for v in vehicles:
        lines += [f"  - id: {v}", f"    bags: {data[v]}/*.bag", f"    previous: {data['previous']}"]
    return "\n".join(lines) + "\n"


def killed_once(marker: str, fn, *args):
    """Run ``fn(*args)`` in a pool worker, but the first time (no ``marker`` file yet) the worker
    is killed (SIGKILL) a second into it: a worker lost mid-vehicle."""
    import os
    import signal
    import threading

    if not os.path.exists(marker):
        open(marker, "w").close()
        threading.Timer(1.0, os.kill, (os.getpid(), signal.SIGKILL)).start()
    return fn(*args)


def kill_once_pool(marker: Path, workers: int = 2):
    """A factory of the fleet's own process pool whose first vehicle's worker gets killed."""
    from clcgraph.fleet import ScriptSafeProcessPool

    class KillOncePool(ScriptSafeProcessPool):
        def submit(self, fn, /, *args, **kwargs):
            return super().submit(killed_once, str(marker), fn, *args, **kwargs)

    return lambda: KillOncePool(workers)


def assert_same_bytes(a, b) -> None:
    """Files ``a`` and ``b`` byte-identical; a text file's first differing lines in the message."""
    import difflib
    from pathlib import Path

    ba, bb = Path(a).read_bytes(), Path(b).read_bytes()
    if ba == bb:
        return
    try:
        diff = difflib.unified_diff(ba.decode().splitlines(), bb.decode().splitlines(), str(a), str(b), n=0, lineterm="")
        detail = "\n".join(list(diff)[:12])
    except UnicodeDecodeError:
        detail = f"{len(ba)} vs {len(bb)} bytes"
    raise AssertionError(f"{a} differs from {b}:\n{detail}")
