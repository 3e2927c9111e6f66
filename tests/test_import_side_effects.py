"""Importing clcgraph changes nothing global (environment, matplotlib backend), and every error
it raises on purpose, a bad config included, is a ClcgraphError."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

_PROBE = """
import json, os, sys
import matplotlib
backend_before = matplotlib.rcParams["backend"]
import clcgraph, clcgraph.api, clcgraph.outputs.plots, clcgraph.outputs.report, clcgraph.targetless.pipeline
import numpy as np
from clcgraph.types import Image
# drawing a plot must not touch pyplot either
clcgraph.outputs.plots.plot_image_preview(Image("/cam", 0, np.zeros((8, 8), np.uint8), "mono8"), sys.argv[1])
print(json.dumps({"omp": os.environ.get("OMP_WAIT_POLICY"), "backend": matplotlib.rcParams["backend"],
                  "backend_before": backend_before, "pyplot": "matplotlib.pyplot" in sys.modules}))
"""


def test_import_sets_no_environment_and_no_matplotlib_backend(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    env["MPLBACKEND"] = "svg"  # a user's choice that a forced Agg would overwrite
    r = subprocess.run([sys.executable, "-c", _PROBE, str(tmp_path / "p.png")], env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout.splitlines()[-1])
    assert got == {"omp": None, "backend": "svg", "backend_before": "svg", "pyplot": False}, got
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"  # drawn by the Agg canvas anyway


def test_the_command_sets_omp_wait_policy_unless_the_user_did(monkeypatch, capsys):
    from clcgraph.cli import main

    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    assert main(["config", "check"]) == 0
    assert os.environ["OMP_WAIT_POLICY"] == "PASSIVE"
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    assert main(["config", "check"]) == 0
    assert os.environ["OMP_WAIT_POLICY"] == "ACTIVE"


def test_a_bad_config_is_a_clcgraph_error(tmp_path):
    from clcgraph.config import Config, ConfigError
    from clcgraph.errors import ClcgraphError, InputError

    assert issubclass(ConfigError, InputError) and issubclass(ConfigError, ValueError)
    bad = tmp_path / "c.yaml"
    bad.write_text("solve: {no_such_key: 1}\n")
    with pytest.raises(ClcgraphError, match="no_such_key") as e:  # how a fleet script catches it
        Config.from_yaml(bad)
    assert e.value.exit_code == 2
    with pytest.raises(ClcgraphError, match="must be a number"):
        Config().replace(solve={"outlier_sigma": "four"})


def test_mrcal_is_imported_without_setuptools():
    """numpysane (under mrcal) imports distutils; served by setuptools' hook, that import pulls in
    pkg_resources (0.15-0.3 s of each start). cameras loads Python's own, and puts the hook back."""
    probe = ("import json, sys\n"
             "from clcgraph import cameras\n"
             "hooks = [type(f).__module__ for f in sys.meta_path].count('_distutils_hack')\n"
             "cameras.load_camera('/cam', sys.argv[1])\n"
             "print(json.dumps({'pkg_resources': 'pkg_resources' in sys.modules, 'setuptools': 'setuptools' in "
             "sys.modules, 'hooks': [hooks, [type(f).__module__ for f in sys.meta_path].count('_distutils_hack')]}))")
    model = next(p for p in (Path(__file__).parents[1] / "bench" / "capture").glob("*.cameramodel"))
    r = subprocess.run([sys.executable, "-c", probe, str(model)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout.splitlines()[-1])
    assert got["hooks"][0] == got["hooks"][1], got  # the hook (where installed) is back
    assert not got["pkg_resources"] and not got["setuptools"], got
