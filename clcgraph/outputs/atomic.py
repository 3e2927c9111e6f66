"""Output directories that appear whole or not at all, and never over what clcgraph did not write.

SYNOPSIS
    with atomic_dir("calib/") as tmp:      # a fresh hidden directory beside calib/
        (tmp / "calibration.yaml").write_text(...)
    # calib/ now holds exactly what was written (a previous calib/ is replaced as a whole);
    # after an error calib/ is as it was and the temporary directory is gone

The rules (DESIGN.md, "Promises to users"):
- ``out_dir`` may be new, empty, or a previous clcgraph output of the same kind: every
  directory clcgraph writes holds a marker file, ``.clcgraph-output``, naming its kind
  ("results" of solve / targetless, "session" of simulated bags, "ros" of format-for-ros,
  "fleet" of `clcgraph fleet`, whose per-vehicle folders are "results" each):
  so a calibration never replaces the bags it was computed from, nor ROS files a calibration.
  Anything else is an InputError naming the directory, unless ``force=True``.
- ``out_dir`` a symlink: the link stays, its target is written (under the same rules).
- One writer per ``out_dir`` at a time (an ``flock`` on ``.NAME.clcgraph-lock`` beside it);
  a second one gets an InputError at once instead of racing the first.
- Temporary directories are ``.NAME.clcgraph-tmp-PID-XXXX`` beside ``out_dir``: one left by
  a killed run (its PID is gone) is removed by the next run into the same ``out_dir``.
- SIGINT / SIGTERM arriving while the directory is swapped in or cleaned up wait until
  that is done, so an interrupted run leaves the previous output or the new one, whole.
"""

from __future__ import annotations

import fcntl
import os
import re
import shutil
import signal
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from ..errors import InputError

MARKER = ".clcgraph-output"
_WHAT = {"results": "calibration results", "session": "simulated bags", "ros": "ROS files",
         "fleet": "a fleet calibration"}
KINDS = tuple(_WHAT)
_MARKER_TEXT = ("clcgraph-output: {kind}\n"
                "# written by clcgraph; a later clcgraph run with this --out may replace this directory whole\n")


def _cannot(shown, e: OSError) -> InputError:
    return InputError(f"{shown}: cannot write the output directory ({e.strerror}); choose another --out")


def marker_kind(directory: Path) -> str | None:
    """The kind named by ``directory``'s clcgraph marker, or None without one."""
    try:
        first = (Path(directory) / MARKER).read_text().partition("\n")[0]
    except (OSError, UnicodeDecodeError):
        return None
    m = re.fullmatch(r"clcgraph-output: (\w+)", first.strip())
    return m.group(1) if m else None


def check_out_dir(out_dir, *, kind: str = "results", force: bool | None = False) -> Path:
    """The directory to write for ``out_dir`` (a symlink's target), or InputError saying why not
    (``force`` None: the command has no --force, as `clcgraph fleet`, which never removes).

    Call it before long work so a bad ``--out`` fails at once; ``atomic_dir`` checks again.
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    shown = out_dir
    target = Path(out_dir).absolute()
    if target.is_symlink():
        target = target.resolve()
    if target.exists() and not target.is_dir():
        raise InputError(f"{shown}: exists and is not a directory; choose another --out")
    if not target.is_dir() or force:
        return target
    try:
        entries = sorted(os.listdir(target))
    except OSError as e:
        raise _cannot(shown, e) from None
    if not entries:
        return target
    found = marker_kind(target)
    if found == kind:
        return target
    what = (f"clcgraph's {_WHAT.get(found, found)}, not {_WHAT[kind]}" if found
            else f"not a clcgraph output ({len(entries)} entries, e.g. {entries[0]!r})")
    raise InputError(f"{shown}: exists and is {what}; clcgraph replaces only its own outputs: "
                     "choose a new or empty --out" + (", or pass --force to replace it" if force is not None else ""))


@contextmanager
def atomic_dir(out_dir, *, kind: str = "results", force: bool = False) -> Iterator[Path]:
    """Yield a temporary directory (marked as a clcgraph ``kind``); on success it becomes
    ``out_dir`` (mode 755). ``force``: replace ``out_dir`` even if clcgraph did not write it."""
    shown = out_dir
    target = check_out_dir(out_dir, kind=kind, force=force)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise _cannot(shown, e) from None
    with _lock(target, shown):
        _remove_stale(target)
        target = check_out_dir(out_dir, kind=kind, force=force)  # again, now that no other run writes it
        try:
            tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.clcgraph-tmp-{os.getpid()}-", dir=target.parent))
        except OSError as e:
            raise _cannot(shown, e) from None
        try:
            (tmp / MARKER).write_text(_MARKER_TEXT.format(kind=kind))
            yield tmp
            with _signals_deferred():
                os.chmod(tmp, 0o755)
                _replace_dir(tmp, target, shown)
        except BaseException:
            with _signals_deferred():
                shutil.rmtree(tmp, ignore_errors=True)
            raise


def _replace_dir(tmp: Path, target: Path, shown) -> None:
    """Move tmp to target; an existing target is moved aside first, then removed."""
    old = None
    try:
        if target.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{target.name}.clcgraph-old-{os.getpid()}-", dir=target.parent))
            os.rename(target, old)  # onto the fresh empty directory: atomic
        os.rename(tmp, target)
    except OSError as e:
        if old is not None and not target.exists():
            os.rename(old, target)  # put the previous output back
        raise _cannot(shown, e) from None
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@contextmanager
def _lock(target: Path, shown) -> Iterator[None]:
    """Exclusive, non-blocking: a second writer of ``target`` fails at once with one line.

    The lock file is removed on release; a run that opened it just before then finds a
    different (or no) file at the path and retries, so two runs never both hold "the" lock.
    """
    path = target.with_name(f".{target.name}.clcgraph-lock")
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as e:
            raise _cannot(shown, e) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip()
            os.close(fd)
            raise InputError(f"{shown}: another clcgraph run{f' (pid {holder})' if holder.isdigit() else ''} "
                             "is writing this directory; wait for it or choose another --out") from None
        try:
            st = os.stat(path)
            mine = os.fstat(fd)
            if (st.st_dev, st.st_ino) == (mine.st_dev, mine.st_ino):
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        yield
    finally:
        try:
            os.unlink(path)
        except FileNotFoundError:
            pass
        os.close(fd)


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def _remove_stale(target: Path) -> None:
    """Remove temporary directories of ``target`` left by runs that were killed: their PID is
    gone and they hold our marker (so nothing that clcgraph did not write is touched)."""
    pattern = re.compile(rf"\.{re.escape(target.name)}\.clcgraph-(?:tmp|old)-(\d+)-\w+")
    try:
        names = os.listdir(target.parent)
    except OSError:
        return
    for name in names:
        m = pattern.fullmatch(name)
        if m and not _pid_alive(int(m.group(1))) and marker_kind(target.parent / name) is not None:
            shutil.rmtree(target.parent / name, ignore_errors=True)


@contextmanager
def _signals_deferred() -> Iterator[None]:
    """Hold SIGINT / SIGTERM until the block is done, then act on them as before (main thread
    only: Python runs signal handlers there, so elsewhere nothing interrupts the block)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    saved = {s: h for s, h in saved.items() if h is not None}  # None: a handler not set from Python
    for s in saved:
        signal.signal(s, lambda signum, frame: pending.append(signum))
    try:
        yield
    finally:
        for s, h in saved.items():
            signal.signal(s, h)
        if pending:
            h = saved[pending[0]]
            if callable(h):
                h(pending[0], None)
            elif h == signal.SIG_DFL:
                os.kill(os.getpid(), pending[0])


@contextmanager
def open_out_dir(out_dir, *, kind: str) -> Iterator[Path]:
    """Hold ``out_dir`` (new, empty or a previous ``kind`` output) for a run that fills it piece by
    piece, as `clcgraph fleet` does: created with its marker, locked against a second writer for
    the duration. Its pieces are written with ``atomic_dir`` / ``atomic_file``; nothing is removed."""
    shown = out_dir
    target = check_out_dir(out_dir, kind=kind, force=None)
    try:
        target.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise _cannot(shown, e) from None
    with _lock(target, shown):
        target = check_out_dir(out_dir, kind=kind, force=None)
        if marker_kind(target) is None:
            try:
                (target / MARKER).write_text(_MARKER_TEXT.format(kind=kind))
            except OSError as e:
                raise _cannot(shown, e) from None
        yield target


# how the files clcgraph writes begin: PNG, NumPy's zip, YAML with its header ("a: " began a
# `compare --yaml` before the header)
_SIGNATURES = {".png": (b"\x89PNG\r\n\x1a\n",), ".npz": (b"PK\x03\x04",), ".yaml": (b"# clcgraph", b"a: ")}


def check_out_file(path, suffix: str, *, flag: str, force: bool | None = None) -> Path:
    """``path`` as an output file of type ``suffix`` (".png", ".npz", ".yaml"), named by the
    option ``flag``: InputError if it is a directory, names another type, sits in a directory that
    does not exist, or exists and is not a file of its type that clcgraph may have written (how it
    begins), unless ``force`` (None: the command has no --force)."""
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{flag} {path}: a directory; name a *{suffix} file")
    if path.suffix.lower() not in ({suffix, ".yml"} if suffix == ".yaml" else {suffix}):
        raise InputError(f"{flag} {path}: name the file *{suffix}")
    if not path.parent.is_dir():
        raise InputError(f"{flag} {path}: its directory {path.parent} does not exist")
    if path.exists() and not force:
        try:
            with open(path, "rb") as f:
                head = f.read(16)
        except OSError as e:
            raise InputError(f"{flag} {path}: cannot read it ({e.strerror})") from None
        if not head.startswith(_SIGNATURES[suffix]):
            raise InputError(f"{flag} {path}: exists and is not a {suffix} file clcgraph wrote; choose another name"
                             + (" (or --force to replace it)" if force is not None else ""))
    return path


def check_out_folder(path, *, flag: str) -> Path:
    """``path`` as a folder for pictures, made when the first is written (``make_out_folder``):
    InputError if it is a file, or if it is new and its nearest existing parent is not a
    directory this user may write."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{flag} {path}: a file; name a directory for the pictures")
    parent = next(p for p in (path, *path.absolute().parents) if p.exists())
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{flag} {path}: cannot make the directory ({parent} is not a writable directory)")
    return path


def make_out_folder(path, *, flag: str) -> Path:
    """Make the folder ``check_out_folder`` accepted (a no-op once made); InputError where the
    system still refuses (a read-only or virtual file system)."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"{flag} {path}: cannot make the directory ({e.strerror})") from None
    return path


def atomic_file(path, content: str | bytes) -> Path:
    """Write one file whole or not at all: a temporary file beside it, renamed over it."""
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.clcgraph-tmp-{os.getpid()}-", dir=path.parent)
    except OSError as e:
        raise InputError(f"{path}: cannot write ({e.strerror})") from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(content.encode() if isinstance(content, str) else content)
        with _signals_deferred():
            os.chmod(tmp, 0o644)
            os.replace(tmp, path)
    except BaseException:
        with _signals_deferred():
            Path(tmp).unlink(missing_ok=True)
        raise
    return path
