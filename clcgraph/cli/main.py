"""The parser of every command, the logging set-up, and errors as one line with an exit code."""

from __future__ import annotations

import argparse
import atexit
import logging
import os
import signal
import sys
import threading
from contextlib import contextmanager

from . import bags, calibrate, fleet, results, simulate
from .common import verbosity_args

log = logging.getLogger("clcgraph")

# command groups, in --help order; each module's COMMANDS register one parser per command
GROUPS = (calibrate, bags, results, simulate, fleet)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="clcgraph", description="Calibrate the extrinsics of a rig of LIDARs and cameras.")
    verbosity_args(parser, top=True)
    parser.add_argument("--version", action=_Version,
                        help="print the versions of clcgraph and what it runs on, and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for group in GROUPS:
        for add in group.COMMANDS:
            add(sub)
    return parser


# (name, distribution) of what a calibration's numbers depend on, for --version
_DEPENDENCIES = (("gtsam", "gtsam"), ("mrcal", "mrcal"), ("numpy", "numpy"), ("scipy", "scipy"),
                 ("opencv", "opencv-python-headless"), ("open3d", "open3d-cpu"), ("small_gicp", "small_gicp"),
                 ("rosbags", "rosbags"))


def versions() -> str:
    """clcgraph's version and its dependencies' (what a bug report needs): from the installed
    packages' metadata; mrcal, a Debian package without Python metadata, from dpkg."""
    import importlib.metadata
    import platform
    import subprocess

    from .. import __version__

    def version(dist):
        try:
            return importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            pass
        try:
            out = subprocess.run(["dpkg-query", "-W", "-f", "${Version}", f"python3-{dist}"], capture_output=True,
                                 text=True, timeout=10)
            return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() else "not found"
        except (OSError, subprocess.SubprocessError):
            return "not found"

    deps = ", ".join(f"{name} {version(dist)}" for name, dist in _DEPENDENCIES)
    return f"clcgraph {__version__} (Python {platform.python_version()}; {deps})"


class _Version(argparse.Action):
    """--version: ``versions()`` on stdout, exit 0 (argparse's own would format the text at parser build)."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        print(versions())
        parser.exit()


class _Terminated(BaseException):
    """SIGTERM, raised in the main thread like KeyboardInterrupt so that cleanups run."""


_EXIT_ON_SIGNAL = {signal.SIGINT: 130, signal.SIGTERM: 143}  # the shells' 128 + signal number


@contextmanager
def _signals_raise(received: list):
    """SIGINT -> KeyboardInterrupt, SIGTERM -> _Terminated, recording which came (a worker may
    turn the interruption into another exception); the previous handlers are put back."""

    def handler(signum, frame):
        received.append(signum)
        raise KeyboardInterrupt if signum == signal.SIGINT else _Terminated

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    saved = {s: signal.signal(s, handler) for s in _EXIT_ON_SIGNAL}
    try:
        yield
    finally:
        for s, h in saved.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


def run() -> None:
    """The ``clcgraph`` command (its console script and ``python -m clcgraph``): ``main()`` as the
    process's exit code, the process then ending without the interpreter's teardown of every
    module and object (gtsam's, matplotlib's, the solve's arrays: 0.1-0.2 s of each command). The
    exit handlers registered after this one (temporary directories' cleanup, child processes) run
    before it, those before it (logging's) it runs itself. (``main`` itself returns: the tests call it.)"""
    code = [1]

    def end_now():  # registered first, so run last
        logging.shutdown()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):  # a closed pipe (| head), a closed stream
                pass
        os._exit(code[0])

    atexit.register(end_now)
    try:
        code[0] = main()
    except SystemExit as e:  # argparse's --help (0) and usage errors (2)
        code[0] = e.code if isinstance(e.code, int) else 0 if e.code is None else 1
        raise
    sys.exit(code[0])


def main(argv: list[str] | None = None) -> int:
    # OpenMP workers (small_gicp, Open3D) otherwise spin after each parallel region and, on a
    # 2-core machine, starve the Python code between registrations (mapping ran 15-20 % slower).
    # A default for this process only, set before any OpenMP runtime loads; a user's value wins.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    received: list[int] = []
    # the handlers go in first: a Ctrl-C while the parser's imports load is one line too
    words = [w for w in (sys.argv[1:] if argv is None else argv) if not w.startswith("-")]
    args = argparse.Namespace(command=words[0] if words else "", verbose=False)  # until parsed
    try:
        with _signals_raise(received):
            args = build_parser().parse_args(argv)
            _set_up_logging(args)
            return int(args.func(args) or 0)
    except (KeyboardInterrupt, _Terminated, Exception) as e:
        return _failure(args, e, received)


def _set_up_logging(args) -> None:
    # progress notes are for someone watching: piped or logged runs get warnings and errors only
    quiet = args.quiet or not sys.stderr.isatty()
    level = logging.DEBUG if args.verbose else logging.WARNING if quiet else logging.INFO
    logging.basicConfig(level=level, format="%(message)s" if not args.verbose else "%(levelname)s %(name)s: %(message)s")
    from .. import progress

    progress.set_enabled(not args.quiet)


def _forget_unhandled_keyboard_interrupt() -> None:
    """CPython marks a KeyboardInterrupt that leaves an exec()/eval() of a *string* as unhandled
    (dataclasses, namedtuple and rosbags' message serializers run such code), even when a caller
    catches it, and under `python -m` (unlike a script or -c) the interpreter then ends the process
    by SIGINT instead of the exit code we return. Every exec() of a string clears that mark first;
    the interruption was handled here, so clear it."""
    exec("")  # noqa: S102 - an empty string: runs nothing


def _failure(args, e: BaseException, received: list) -> int:
    """One line on stderr for a command that did not finish (a traceback only with --verbose)."""
    from ..errors import ClcgraphError

    if received or isinstance(e, KeyboardInterrupt):
        if args.verbose:
            log.error("clcgraph %s interrupted", args.command, exc_info=e)
        signum = received[0] if received else signal.SIGINT
        left = "; nothing half-written in --out" if getattr(args, "out", None) else ""
        print(f"clcgraph {args.command}: interrupted by {signal.Signals(signum).name}{left}", file=sys.stderr)
        _forget_unhandled_keyboard_interrupt()
        return _EXIT_ON_SIGNAL[signum]
    if isinstance(e, ClcgraphError):
        if args.verbose:
            log.error("clcgraph %s failed", args.command, exc_info=e)
        print(f"clcgraph {args.command}: error: {e}", file=sys.stderr)
        return e.exit_code
    if args.verbose:  # an internal error: still one line unless --verbose
        log.error("clcgraph %s: internal error", args.command, exc_info=e)
    hint = "" if args.verbose else " (rerun with --verbose for a traceback)"
    print(f"clcgraph {args.command}: internal error: {type(e).__name__}: {e}{hint}", file=sys.stderr)
    return 1
