"""cli.main.run, the `clcgraph` command's entry: the exit code is main()'s (argparse's for --help
and usage errors), and everything printed reaches a pipe or file, though the process ends
without the interpreter's teardown (os._exit once the exit handlers have run)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from clcgraph.cli import main


def _command(*args):
    return subprocess.run([sys.executable, "-m", "clcgraph", *map(str, args)], capture_output=True, text=True,
                          timeout=120)


def test_what_the_command_prints_reaches_the_pipe_whole(capsys):
    assert main(["config", "dump"]) == 0
    in_process = capsys.readouterr().out
    r = _command("config", "dump")
    assert r.returncode == 0 and r.stdout == in_process and len(in_process) > 2000


@pytest.mark.parametrize("args, code", [(["--help"], 0), (["solve", "--no-such-flag"], 2),
                                        (["solve", "--bag", "/no/such.bag", "--topics", "a,b", "--out"], 2)])
def test_exit_codes_are_mains_and_argparses(args, code, tmp_path):
    r = _command(*args, *([tmp_path / "out"] if args[-1] == "--out" else []))
    assert r.returncode == code, r.stderr
    assert "Traceback" not in r.stderr


def test_version_names_clcgraph_and_what_it_runs_on():
    import importlib.metadata

    from clcgraph import __version__

    r = _command("--version")
    assert r.returncode == 0 and "Traceback" not in r.stderr
    line = r.stdout.strip()
    assert line.startswith(f"clcgraph {__version__} (Python ")
    for dist in ("gtsam", "numpy"):
        assert f"{dist} {importlib.metadata.version(dist)}" in line
    assert "mrcal " in line and "mrcal not found" not in line  # Debian's package, no Python metadata: dpkg's
