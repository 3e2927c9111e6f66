"""`clcgraph solve` through the real entry point with too few LM iterations: one warning line on
stderr, exit 0 (the last step is far below a sigma), the convergence block in calibration.yaml,
NOT CONVERGED in the printed table and the report."""

import os
import subprocess
import sys
from pathlib import Path

import yaml

from clcgraph.cli import main

ROOT = Path(__file__).resolve().parents[2]
RIG = """
lidars:
  - {topic: /lidar/a, model: vlp16, layout: velodyne, frame_id: a, xyz: [0, 0, 1.9], rpy_deg: [0, 0, 0]}
  - {topic: /lidar/c, model: hdl32, layout: ouster, frame_id: c, xyz: [-1.0, -0.4, 1.5], rpy_deg: [0, -3, 178]}
cameras: []
board: {corners: [10, 10], square_m: 0.1, size_m: [1.3, 1.3]}
"""


def test_solve_with_max_iterations_1_warns_in_one_line_and_records_it(tmp_path):
    (tmp_path / "rig.yaml").write_text(RIG)
    assert main(["simulate", str(tmp_path / "rig.yaml"), "--out", str(tmp_path / "bags"), "--poses", "8",
                 "--seed", "1"]) == 0
    cmd = [sys.executable, "-c", "import sys; from clcgraph.cli import main; sys.exit(main())", "solve",
           "--bag", str(tmp_path / "bags" / "*.bag"), "--topics", "/lidar/a,/lidar/c", "--out", str(tmp_path / "out"),
           "--set", "solve.max_iterations=1"]
    p = subprocess.run(cmd, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    err = [line for line in p.stderr.splitlines() if line.strip()]
    assert len(err) == 1 and "did not converge" in err[0] and "max_iterations=1" in err[0], err
    assert "NOT CONVERGED" in p.stdout
    cal = yaml.safe_load((tmp_path / "out" / "calibration.yaml").read_text())
    conv = cal["convergence"]
    assert conv["converged"] is False and conv["stages"][0]["iterations"] == 1 and not conv["stages"][0]["converged"]
    assert "max_iterations=1" in (tmp_path / "out" / "report.html").read_text()
