"""Output directories that appear whole or not at all.

SYNOPSIS
    with atomic_dir("calib/") as tmp:      # a fresh hidden directory beside calib/
        (tmp / "calibration.yaml").write_text(...)
    # calib/ now holds exactly what was written (a previous calib/ is replaced as a whole);
    # after an error calib/ is as it was and the temporary directory is gone

A directory that cannot be created or replaced is an InputError naming it.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from ..errors import InputError


def _cannot(out_dir: Path, e: OSError) -> InputError:
    return InputError(f"{out_dir}: cannot write the output directory ({e.strerror}); choose another --out")


@contextmanager
def atomic_dir(out_dir) -> Iterator[Path]:
    """Yield a temporary directory; on success it becomes ``out_dir`` (mode 755)."""
    out_dir = Path(out_dir).absolute()
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-", dir=out_dir.parent))
    except OSError as e:
        raise _cannot(out_dir, e) from None
    try:
        yield tmp
        os.chmod(tmp, 0o755)
        _replace_dir(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _replace_dir(tmp: Path, out_dir: Path) -> None:
    """Move tmp to out_dir; an existing out_dir is moved aside first, then removed."""
    old = None
    try:
        if out_dir.exists() or out_dir.is_symlink():
            if not out_dir.is_dir():
                raise InputError(f"{out_dir}: exists and is not a directory; choose another --out")
            old = out_dir.with_name(f".{out_dir.name}.old-{os.getpid()}")
            os.rename(out_dir, old)
        os.rename(tmp, out_dir)
    except OSError as e:
        if old is not None and not out_dir.exists():
            os.rename(old, out_dir)  # put the previous results back
        raise _cannot(out_dir, e) from None
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
