"""Wall time (and peak memory) per stage: the one stage-timing helper of both methods.

SYNOPSIS
    timings, memory = {}, {}
    clock = StageClock(timings, memory)
    with clock("mapping"):
        ...                          # timings["mapping"] += wall seconds; memory["mapping"] = peak RSS (MB)
    clock.start("segment"); ...; clock.stop()

Stages of the same name add up. Without a dict (``StageClock(None)``) it does nothing.
Imports nothing of clcgraph.
"""

from __future__ import annotations

import contextlib
import time


def peak_rss_mb() -> float:
    """The process's peak resident memory so far, MB (Linux: ru_maxrss is in kB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class StageClock:
    """Adds wall seconds per stage into ``into`` (and the peak RSS after it into ``memory``)."""

    def __init__(self, into: dict | None, memory: dict | None = None):
        self.into, self.memory, self._name, self._t0 = into, memory, None, 0.0

    def start(self, name: str) -> None:
        self._name, self._t0 = name, time.perf_counter()

    def stop(self) -> None:
        if self.into is not None and self._name:
            self.into[self._name] = self.into.get(self._name, 0.0) + time.perf_counter() - self._t0
        if self.memory is not None and self._name:
            self.memory[self._name] = peak_rss_mb()
        self._name = None

    @contextlib.contextmanager
    def __call__(self, name: str):
        self.start(name)
        try:
            yield
        finally:
            self.stop()
