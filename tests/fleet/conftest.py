"""The simulated fleet of fleetsim.py, made once per test session."""

import shutil

import pytest

from fleetsim import DRIVE_S, N_POSES, TARGETLESS_TOPICS, TOPICS, write_rig


@pytest.fixture(scope="session")
def fleet_data(tmp_path_factory):
    """{name: bag folder} of the captures (fleetsim.py), the camera model, and ``first``'s calibration."""
    from clcgraph import api
    from clcgraph.sim.capture import simulate

    root = tmp_path_factory.mktemp("fleet")
    rig = write_rig(root / "rig", knocked=False)
    knocked = write_rig(root / "rig-knocked", knocked=True)
    for name, r, seed in (("first", rig, 1), ("same", rig, 2), ("knocked", knocked, 3)):
        simulate(r, root / name, n_poses=N_POSES, seed=seed, clutter=False, planned_tilts=True)
    shutil.copytree(root / "same", root / "truncated")
    bag = root / "truncated" / "pose003.bag"
    bag.write_bytes(bag.read_bytes()[: bag.stat().st_size // 2])
    model = root / "rig" / "cam.cameramodel"
    api.calibrate_bags([root / "first" / "*.bag"], TOPICS, [model], out=root / "first-calibration")
    return {"root": root, "model": model, "previous": root / "first-calibration",
            **{n: root / n for n in ("first", "same", "knocked", "truncated")}}



@pytest.fixture(scope="session")
def drive_data(tmp_path_factory):
    """Two short simulated drives of one targetless rig (fleetsim.py) and the first one's calibration."""
    from clcgraph import api
    from clcgraph.sim.drive import DrivePlan, simulate_drive, write_drive_bag

    root = tmp_path_factory.mktemp("drives")
    drives = {}
    for name, seed in (("drive-first", 0), ("drive-again", 1)):
        drives[name] = simulate_drive(DrivePlan.small(duration_s=DRIVE_S), seed=seed)
        (root / name).mkdir()
        write_drive_bag(drives[name], root / name / "drive.bag")
    api.calibrate_targetless([root / "drive-first" / "drive.bag"], mapping_topic=TARGETLESS_TOPICS[0],
                             calibration_topics=TARGETLESS_TOPICS[1:], out=root / "drive-first-calibration")
    return {"root": root, "drives": drives, "previous": root / "drive-first-calibration",
            **{n: root / n for n in drives}}
