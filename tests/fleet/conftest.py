"""The simulated fleet of fleetsim.py, made once per test session."""

import shutil

import pytest

from fleetsim import N_POSES, TOPICS, write_rig


@pytest.fixture(scope="session")
def fleet_data(tmp_path_factory):
    """{name: bag folder} of the captures (fleetsim.py), the camera model, and ``first``'s calibration."""
    from clcgraph import api
    from clcgraph.sim.capture import simulate

    root = tmp_path_factory.mktemp("fleet")
    rig = write_rig(root / "rig", knocked=False)
    knocked = write_rig(root / "rig-knocked", knocked=True)
    for name, r, seed in (("first", rig, 1), ("same", rig, 2), ("knocked", knocked, 3)):
        simulate(r, root / name, n_poses=N_POSES, seed=seed, clutter=False)
    shutil.copytree(root / "same", root / "truncated")
    bag = root / "truncated" / "pose003.bag"
    bag.write_bytes(bag.read_bytes()[: bag.stat().st_size // 2])
    model = root / "rig" / "cam.cameramodel"
    api.calibrate_bags([root / "first" / "*.bag"], TOPICS, [model], out=root / "first-calibration")
    return {"root": root, "model": model, "previous": root / "first-calibration",
            **{n: root / n for n in ("first", "same", "knocked", "truncated")}}

