"""The architecture's arrows go one way (DESIGN.md): checked in fresh interpreters."""

import subprocess
import sys

import pytest


def _loaded_after(import_stmt: str) -> set[str]:
    code = f"import sys; {import_stmt}; print(' '.join(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return set(out.split())


@pytest.mark.parametrize(
    "module, forbidden",
    [
        ("clcgraph.types", {"gtsam", "open3d", "rosbags", "cv2", "mrcal"}),
        ("clcgraph.geometry", {"gtsam", "open3d", "rosbags", "cv2"}),
        ("clcgraph.config", {"gtsam", "open3d", "rosbags", "cv2", "mrcal"}),
        ("clcgraph.frontend", {"gtsam"}),
        ("clcgraph.factors", {"open3d", "rosbags"}),
        ("clcgraph.cli", {"gtsam", "open3d", "rosbags", "cv2", "mrcal"}),
    ],
)
def test_imports_stay_in_their_layer(module, forbidden):
    loaded = _loaded_after(f"import {module}")
    assert not (loaded & forbidden), f"{module} pulls in {sorted(loaded & forbidden)}"


def test_frontend_modules_never_import_backend():
    import pathlib

    root = pathlib.Path(__file__).parents[1] / "clcgraph"
    for sub, banned in [("frontend", ("gtsam", "backend", "factors")), ("factors", ("open3d", "rosbags", "frontend"))]:
        for f in (root / sub).glob("*.py"):
            text = f.read_text()
            for b in banned:
                assert f"import {b}" not in text and f"from {b}" not in text and f"from ..{b}" not in text, (
                    f"{f.name} imports {b}"
                )
