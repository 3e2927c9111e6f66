"""The architecture's arrows go one way (DESIGN.md, "Layout"): checked two ways.

1. Statically, on every module of every package: the source is parsed with ``ast`` and
   every import (absolute or relative, at the top or inside a function) is resolved to a
   dotted name and checked against the rules below. The checker is run on a copy of the
   package with a planted bad import, to show that it fails.
2. In fresh interpreters: importing all modules of a package does not load the heavy
   libraries its layer must not depend on (an import through a third module counts too).
"""

from __future__ import annotations

import ast
import pkgutil
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "clcgraph"
_LIBRARY = ("clcgraph.api", "clcgraph.cli", "clcgraph.fleet", "clcgraph.export_mcap")  # the orchestration layer: nothing below imports it

# module-name prefix -> (import prefixes it must not use)
RULES: dict[str, tuple[str, ...]] = {
    "clcgraph.frontend": ("gtsam", "clcgraph.backend", "clcgraph.factors", "clcgraph.targetless",
                          "clcgraph.outputs", "clcgraph.sim", *_LIBRARY),
    "clcgraph.factors": ("open3d", "rosbags", "clcgraph.frontend", "clcgraph.backend", "clcgraph.targetless",
                         "clcgraph.outputs", "clcgraph.sim", *_LIBRARY),
    "clcgraph.backend": ("open3d", "rosbags", "clcgraph.frontend", "clcgraph.targetless", "clcgraph.outputs",
                         "clcgraph.sim", *_LIBRARY),
    "clcgraph.targetless": ("clcgraph.sim", *_LIBRARY),
    # outputs write and read files; they never run a solver
    "clcgraph.outputs": ("gtsam", "open3d", "rosbags", "clcgraph.backend", "clcgraph.frontend",
                         "clcgraph.targetless", "clcgraph.sim", *_LIBRARY),
    "clcgraph.sim": ("gtsam", "clcgraph.backend", "clcgraph.factors", "clcgraph.targetless", *_LIBRARY),
    "clcgraph.cameras": ("clcgraph.frontend", "clcgraph.backend", "clcgraph.outputs", *_LIBRARY),
    "clcgraph.planes": _LIBRARY,
    # the command parses, calls the API and prints: it wires no stage itself
    "clcgraph.cli": ("gtsam", "open3d", "rosbags", "clcgraph.frontend", "clcgraph.backend", "clcgraph.factors",
                     "clcgraph.targetless"),
    "clcgraph.progress": ("clcgraph",),
    "clcgraph.timing": ("clcgraph",),
    "clcgraph.two_processes": ("clcgraph",),
    "clcgraph.determinism": ("clcgraph",),
}
# types, geometry, config import nothing of ours; errors (which imports nothing) is allowed.
LEAVES = ("clcgraph.types", "clcgraph.geometry", "clcgraph.config", "clcgraph.errors")
LEAF_MAY_IMPORT = ("clcgraph.errors",)

# Known departures from DESIGN.md, each with its reason; an entry that no longer matches fails.
EXCEPTIONS: dict[tuple[str, str], str] = {}


def _modules(root: Path):
    """(dotted module name, is a package __init__, path) of every .py under root."""
    for f in sorted(root.rglob("*.py")):
        parts = f.relative_to(root.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            yield ".".join(parts[:-1]), True, f
        else:
            yield ".".join(parts), False, f


def imports_of(module: str, is_package: bool, source: str) -> list[tuple[str, int]]:
    """Every name ``module`` imports, resolved to absolute dotted names: ``from ..backend import
    solve`` in clcgraph.frontend.bag gives clcgraph.backend.solve. (name, line) pairs."""
    package = module if is_package else module.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                prefix = ".".join(base + ([node.module] if node.module else []))
            else:
                prefix = node.module
            out += [(f"{prefix}.{a.name}", node.lineno) for a in node.names]  # a submodule or a name in it
    return out


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def violations(root: Path = PACKAGE) -> list[str]:
    """'module:line imports name' for every import that breaks RULES / LEAVES (EXCEPTIONS aside)."""
    found, used = [], set()
    for module, is_pkg, path in _modules(root):
        banned = [b for prefix, bans in RULES.items() if _under(module, prefix) for b in bans]
        leaf = any(_under(module, leaf) for leaf in LEAVES)
        for name, line in imports_of(module, is_pkg, path.read_text()):
            bad = next((b for b in banned if _under(name, b) and not _under(name, module)), None)
            if leaf and _under(name, "clcgraph") and not any(_under(name, a) for a in LEAF_MAY_IMPORT):
                bad = "anything of clcgraph"
            if bad is None:
                continue
            key = next((k for k in EXCEPTIONS if k[0] == module and _under(name, k[1])), None)
            if key:
                used.add(key)
                continue
            found.append(f"{module}:{line} imports {name} (banned there: {bad})")
    if root == PACKAGE:
        found += [f"stale exception {k}: no such import any more" for k in EXCEPTIONS if k not in used]
    return found


def test_every_package_follows_the_rules():
    assert violations() == []


def test_the_rules_cover_every_package():
    packages = {m for m, is_pkg, _ in _modules(PACKAGE) if is_pkg and m != "clcgraph"}
    assert packages <= set(RULES), packages - set(RULES)
    for leaf in LEAVES:
        assert (PACKAGE.parent / (leaf.replace(".", "/") + ".py")).is_file(), leaf


@pytest.fixture(scope="module")
def copy(tmp_path_factory) -> Path:
    """A copy of the package, as clean as the original."""
    root = tmp_path_factory.mktemp("planted") / "clcgraph"
    shutil.copytree(PACKAGE, root, ignore=shutil.ignore_patterns("__pycache__"))
    assert violations(root) == []
    return root


@pytest.mark.parametrize("victim, planted", [
    ("frontend/bag.py", "from ..backend import solve"),                     # relative, a submodule
    ("frontend/bag.py", "from clcgraph.backend.solve import calibrate"),    # absolute
    ("frontend/pointcloud.py", "def f():\n    import gtsam"),               # inside a function
    ("factors/lidar_plane.py", "import open3d as o3d"),
    ("factors/lidar_plane.py", "from .. import frontend"),                  # the package itself
    ("backend/uncertainty.py", "from ..outputs.results import write_results"),
    ("outputs/plots.py", "from ..backend.solve import calibrate"),          # outputs never run a solver
    ("targetless/ground.py", "from ..api import calibrate"),
    ("sim/lidar.py", "import clcgraph.backend.seed"),
    ("types.py", "from .geometry import T_from_rt"),                       # leaves import nothing of ours
    ("geometry.py", "from clcgraph import types"),
    ("config.py", "from .frontend.bag import bag_info"),
])
def test_the_checker_flags_a_planted_bad_import(copy, victim, planted):
    f = copy / victim
    clean = f.read_text()
    f.write_text(clean + "\n\n" + planted + "\n")
    try:
        found = violations(copy)
    finally:
        f.write_text(clean)
    module = "clcgraph." + victim.removesuffix(".py").replace("/", ".")
    assert len(found) == 1 and found[0].startswith(f"{module}:"), found


def _all_modules(package: str) -> list[str]:
    path = PACKAGE.parent / package.replace(".", "/")
    if path.with_suffix(".py").is_file():
        return [package]
    return [package] + [f"{package}.{m.name}" for m in pkgutil.iter_modules([str(path)])]


def _loaded_after(modules: list[str]) -> set[str]:
    code = f"import sys; import {', '.join(modules)}; print(' '.join(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return set(out.split())


@pytest.mark.parametrize(
    "package, forbidden",
    [
        ("clcgraph.types", {"gtsam", "open3d", "rosbags", "cv2", "mrcal"}),
        ("clcgraph.geometry", {"open3d", "rosbags", "cv2"}),
        ("clcgraph.config", {"gtsam", "open3d", "rosbags", "cv2", "mrcal"}),
        ("clcgraph.frontend", {"gtsam"}),
        ("clcgraph.factors", {"open3d", "rosbags"}),
        ("clcgraph.outputs", {"open3d", "rosbags", "matplotlib.pyplot"}),
        ("clcgraph.cli", {"gtsam", "open3d", "rosbags", "cv2", "mrcal"}),  # `clcgraph --help` stays instant
    ],
)
def test_importing_a_layer_loads_no_forbidden_library(package, forbidden):
    loaded = _loaded_after(_all_modules(package))  # every module, not just an empty __init__
    assert not (loaded & forbidden), f"{package} pulls in {sorted(loaded & forbidden)}"
