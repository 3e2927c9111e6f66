"""outputs/drawing.py: the report's pictures drawn by two processes give what one process draws."""

from __future__ import annotations

import logging
import os
import time

import pytest

from clcgraph.outputs import drawing
from clcgraph.outputs.drawing import draw_concurrently


def _job(k):
    return lambda: [(f"{k}.png", "", bytes([k]) * (100_000 + k))]  # larger than a pipe's buffer


def test_two_processes_draw_what_one_draws_in_order():
    jobs = [_job(k) for k in range(7)]
    serial = [job() for job in jobs]
    pids = []

    def slow(k):  # long enough for the child to take some
        time.sleep(0.2)
        pids.append(os.getpid())
        return jobs[k]()

    both = draw_concurrently([lambda k=k: slow(k) for k in range(7)], first=lambda: None, order=[6, 5, 4, 3, 2, 1, 0])
    assert both == serial
    # the child's jobs ran elsewhere: this process's list holds only its own
    assert 0 < len(pids) < 7


@pytest.mark.parametrize("cpus", [1, 2])
def test_a_failing_job_is_logged_and_gives_nothing(caplog, monkeypatch, cpus):
    monkeypatch.setattr(drawing, "_cpus", lambda: cpus)

    def boom():
        raise RuntimeError("no such data")

    with caplog.at_level(logging.ERROR):
        out = draw_concurrently([_job(1), boom, _job(2)], names=["a", "b", "c"], first=lambda: None)
    assert out == [_job(1)(), [], _job(2)()]
    if cpus == 1:  # drawn here (the child's log goes to its own handlers)
        assert "could not draw b" in caplog.text


def test_pictures_of_a_dead_child_are_drawn_here(caplog):
    parent = os.getpid()

    def dies_in_child():
        if os.getpid() != parent:
            os._exit(3)
        return [("x.png", "", b"x")]

    # the child takes the first job while this process is busy in ``first``
    with caplog.at_level(logging.WARNING):
        out = draw_concurrently([dies_in_child, _job(1)], first=lambda: time.sleep(0.5))
    assert out == [[("x.png", "", b"x")], _job(1)()]
    assert "ended early (exit code 3)" in caplog.text


def test_one_cpu_or_a_daemon_draws_everything_here(monkeypatch):
    monkeypatch.setattr(drawing, "_cpus", lambda: 1)
    pids = []
    out = draw_concurrently([lambda k=k: (pids.append(os.getpid()), [k])[1] for k in range(3)])
    assert out == [[0], [1], [2]] and pids == [os.getpid()] * 3


def test_order_must_be_a_permutation():
    with pytest.raises(ValueError, match="permutation"):
        draw_concurrently([_job(0), _job(1)], order=[0, 0])
