"""outputs/drawing.py: the report's pictures drawn by two processes give what one process draws."""

from __future__ import annotations

import logging
import os
import re
import time

import pytest

from clcgraph import two_processes
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
    monkeypatch.setattr(two_processes, "_cpus", lambda: cpus)

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
    monkeypatch.setattr(two_processes, "_cpus", lambda: 1)
    pids = []
    out = draw_concurrently([lambda k=k: (pids.append(os.getpid()), [k])[1] for k in range(3)])
    assert out == [[0], [1], [2]] and pids == [os.getpid()] * 3


def test_order_must_be_a_permutation():
    with pytest.raises(ValueError, match="permutation"):
        draw_concurrently([_job(0), _job(1)], order=[0, 0])


def test_leaving_a_drawing_early_stops_its_child():
    import multiprocessing

    t0 = time.perf_counter()
    with pytest.raises(RuntimeError, match="the solve failed"):
        with drawing.Drawing([lambda: time.sleep(60) or [], lambda: time.sleep(60) or []]):
            time.sleep(0.2)  # the child is in its first job
            raise RuntimeError("the solve failed")
    assert time.perf_counter() - t0 < 20 and not multiprocessing.active_children()


def test_report_writer_writes_the_report_write_report_writes(tmp_path):
    from test_outputs import make_result

    from clcgraph.outputs.report import report_writer, write_report

    result = make_result()
    a = write_report(result, tmp_path / "a", title="rig")
    with report_writer(result, title="rig") as write:
        (tmp_path / "other-files").write_text("written while the pictures are drawn")
        b = write(tmp_path / "b")
    assert b.name == "report.html" and a.read_bytes() == b.read_bytes()


def test_a_stuck_child_is_stopped_and_its_pictures_drawn_here(monkeypatch, caplog):
    import multiprocessing

    monkeypatch.setattr(two_processes, "_PATIENCE_S", 1.0)
    parent = os.getpid()

    def stuck_in_child():  # as on a lock another thread held at the fork
        if os.getpid() != parent:
            time.sleep(60)
        return [("s.png", "", b"s")]

    t0 = time.perf_counter()
    with caplog.at_level(logging.WARNING):
        out = draw_concurrently([stuck_in_child, _job(1)], first=lambda: time.sleep(0.5))
    assert out == [[("s.png", "", b"s")], _job(1)()]
    assert re.search(r"sent nothing in \d+ s", caplog.text)
    assert time.perf_counter() - t0 < 20 and not multiprocessing.active_children()
