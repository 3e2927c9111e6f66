"""Run every benchmark: ``python -m bench [name-substring ...]``.

Discovers the ``bench/bench_*.py`` modules, runs each one's ``main()`` in name order and
prints what it returns (a table as a string; a module may also print its own table and
return None). A failing benchmark is reported and the others still run.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
import time
import traceback
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    here = Path(__file__).resolve().parent
    names = sorted(m.name for m in pkgutil.iter_modules([str(here)]) if m.name.startswith("bench_"))
    if argv:
        names = [n for n in names if any(a in n for a in argv)]
    failed = 0
    for name in names:
        print(f"== {name}", flush=True)
        t0 = time.perf_counter()
        try:
            out = importlib.import_module(f"bench.{name}").main()
        except Exception:  # one broken benchmark must not hide the others
            failed += 1
            traceback.print_exc()
            continue
        if out is not None:
            print(out)
        print(f"({name}: {time.perf_counter() - t0:.1f} s)\n", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
