"""The `clcgraph` command is a package of thin commands: a run body of at most ~30 lines that
parses, calls the API and prints; every command with a config takes --config and --set;
-v / -q work before or after the command name."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from clcgraph.cli import build_parser, main

CLI = Path(__file__).resolve().parents[2] / "clcgraph" / "cli"
_ALL = ["solve", "targetless", "replay", "demo", "config", "show-bag", "segment", "detect", "infer-lidar-spacing",
        "format-for-ros", "show-aligned", "show-uncertainty", "compare", "simulate", "simulate-drive", "fleet"]


def _subparsers():
    p = build_parser()
    return next(a for a in p._actions if a.dest == "command").choices


def test_every_command_is_registered_and_runs_a_short_body():
    subs = _subparsers()
    assert sorted(subs) == sorted(_ALL)
    lengths = {}
    for name, sp in subs.items():
        run = sp.get_default("func")
        src = Path(run.__code__.co_filename)
        assert src.parent == CLI, (name, src)
        fn = next(n for n in ast.walk(ast.parse(src.read_text())) if isinstance(n, ast.FunctionDef)
                  and n.name == run.__name__)
        lengths[name] = fn.end_lineno - fn.lineno + 1
    assert max(lengths.values()) <= 30, lengths


def test_commands_with_a_config_take_config_and_set():
    for name, sp in _subparsers().items():
        flags = {s for a in sp._actions for s in a.option_strings}
        if "--config" in flags:
            assert "--set" in flags, name
    with_config = {n for n, sp in _subparsers().items() if any("--config" in a.option_strings for a in sp._actions)}
    assert {"solve", "targetless", "demo", "config", "segment", "detect"} <= with_config


@pytest.mark.parametrize("argv", [["-v", "config", "dump"], ["config", "dump", "-v"], ["config", "-v", "dump"],
                                  ["config", "dump", "--verbose"]])
def test_verbose_before_or_after_the_command(argv):
    args = build_parser().parse_args(argv)
    assert args.verbose and not args.quiet and args.command == "config"


def test_quiet_after_the_command_and_set_on_detect(capsys):
    args = build_parser().parse_args(["detect", "b.bag", "--topic", "/c", "-q", "--set", "detection.detector=opencv"])
    assert args.quiet and not args.verbose and args.set == ["detection.detector=opencv"]
    # a bad --set is named in one line, exit 2, whichever side -v is on
    assert main(["config", "dump", "-q", "--set", "solve.no_such_key=1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "solve.no_such_key" in err[0]
