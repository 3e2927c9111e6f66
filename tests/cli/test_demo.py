"""The README's demo: `clcgraph demo` simulates data/synthetic/demo when missing, calibrates it,
and the poses land within 0.1 deg and 1 cm of the simulator's truth (and within 4 sigma); every
output file loads."""

import mrcal
import numpy as np

from clcgraph.api import load_result
from clcgraph.cli import main


def test_demo(tmp_path, capsys):
    out = tmp_path / "demo-out"
    assert main(["demo", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    rows = [l.split() for l in text.split("against the simulator's truth")[1].splitlines()[2:6]]
    assert len(rows) == 4
    for topic, rot, sd_rot, trans, sd_trans in rows:
        rot, sd_rot, trans, sd_trans = map(float, (rot, sd_rot, trans, sd_trans))
        assert rot < 0.1 and trans < 10.0, (topic, rot, trans)
        assert rot <= 4 * sd_rot + 1e-3 and trans <= 4 * sd_trans + 0.1, (topic, rot, sd_rot, trans, sd_trans)
    cal = load_result(out)
    assert cal["reference"] == "/lidar/top/points" and len(cal["sensors"]) == 4
    for i, s in enumerate(cal["sensors"]):
        m = mrcal.cameramodel(str(out / f"sensor{i}-mounted.cameramodel"))
        assert np.allclose(m.extrinsics_rt_toref(), s["rt_lidar0_sensor"], atol=1e-9)
    assert (out / "report.html").exists() and (out / "problem.npz").exists() and (out / "config.resolved.yaml").exists()
