"""The ``clcgraph`` command: parses arguments, calls the API, reports errors in one line.

Each subcommand is an ``_add_<name>(subparsers)`` that registers a parser whose
``func`` does its heavy imports inside, so ``clcgraph --help`` is instant.
Known errors (``ClcgraphError``) print one line and exit 2; anything else exits 1.
A traceback is printed only with ``--verbose``.
"""

from __future__ import annotations

import argparse
import logging
import sys

log = logging.getLogger("clcgraph")


# ---------------------------------------------------------------- subcommands


# ---------------------------------------------------------------- main

_COMMANDS: list = []  # filled by the @_command decorator below each _add_* function


def _command(add):
    _COMMANDS.append(add)
    return add


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="clcgraph",
        description="Calibrate the extrinsics of a rig of LIDARs and cameras.",
    )
    parser.add_argument("--verbose", "-v", action="store_true", help="debug logging; tracebacks on errors")
    parser.add_argument("--quiet", "-q", action="store_true", help="only warnings and errors; no progress bars")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for add in _COMMANDS:
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO
    logging.basicConfig(level=level, format="%(message)s" if not args.verbose else "%(levelname)s %(name)s: %(message)s")
    from . import progress

    progress.set_enabled(not args.quiet)
    from .errors import ClcgraphError

    try:
        return int(args.func(args) or 0)
    except ClcgraphError as e:
        if args.verbose:
            log.exception("clcgraph %s failed", args.command)
        print(f"clcgraph {args.command}: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print(f"clcgraph {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # an internal error: still one line unless --verbose
        if args.verbose:
            log.exception("clcgraph %s: internal error", args.command)
        print(
            f"clcgraph {args.command}: internal error: {type(e).__name__}: {e} (rerun with --verbose for a traceback)",
            file=sys.stderr,
        )
        return 1


if __name__ == "__main__":
    sys.exit(main())
