"""targetless/background.py: work on the other core in a forked child, results as if computed here."""

import os

import numpy as np
import pytest

from clcgraph.targetless.background import Background, Prefetched


def _scan_like(i: int) -> dict:
    # the size of a prepared 64-ring scan (2 MB): larger than a pipe's buffer
    rng = np.random.default_rng(i)
    return {"raw": rng.normal(size=(60000, 3)), "tau": rng.random(60000), "pick": np.arange(i, 12000 + i)}


def test_prefetched_yields_every_item_in_order_bit_for_bit():
    got = list(Prefetched(range(6), _scan_like))
    assert len(got) == 6
    for i, g in enumerate(got):
        want = _scan_like(i)
        assert all(np.array_equal(g[k], want[k]) for k in want)


class _Boom(ValueError):
    pass


def _fails_at_three(i: int) -> int:
    if i == 3:
        raise _Boom(f"item {i}")
    return i * i


def test_prefetched_raises_an_error_where_it_happened_in_the_sequence():
    seen = []
    with pytest.raises(_Boom, match="item 3"):
        for x in Prefetched(range(6), _fails_at_three):
            seen.append(x)
    assert seen == [0, 1, 4]


def _children() -> set:
    """This process's child processes (zombies included: they keep their /proc entry until reaped)."""
    out = set()
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/stat") as f:
                stat = f.read()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == os.getpid():
            out.add(int(pid))
    return out


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="needs /proc")
def test_prefetched_closed_early_leaves_no_child():
    before = _children()
    p = Prefetched(range(100), _scan_like)
    it = iter(p)
    next(it)
    assert _children() - before  # the child prefetches
    p.close()
    assert not _children() - before  # killed and reaped: not even a zombie


def test_background_returns_the_value_or_raises_the_error_here():
    assert np.array_equal(Background(_scan_like, 7).result()["raw"], _scan_like(7)["raw"])
    with pytest.raises(_Boom, match="item 3"):
        Background(_fails_at_three, 3).result()
