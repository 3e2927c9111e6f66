"""`clcgraph fleet --cluster` end to end, the way docs/fleet.md says to run it: ``local:2`` (a
LocalCluster the command starts), and a separately started ``dask scheduler`` with two
``dask worker`` processes at tcp://127.0.0.1:PORT. Both give the bytes of a serial run."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from clcgraph.cli import main
from fleetsim import assert_same_bytes, manifest_text

_RUN_FIELDS = ("time_s", "attempts", "resumed")  # how a run went, not what it found
_SAME_BYTES = ("calibration.yaml", "problem.npz", "config.resolved.yaml")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def scheduler_and_two_workers(tmp_path_factory):
    """``dask scheduler`` and two single-threaded ``dask worker`` processes (docs/fleet.md), each in its
    own session so that stopping one stops its nanny's children too; yields the scheduler's address."""
    distributed = pytest.importorskip("distributed")
    dask = shutil.which("dask", path=str(Path(sys.executable).parent)) or shutil.which("dask")
    assert dask, "the dask command of the fleet extra"
    address = f"tcp://127.0.0.1:{_free_port()}"
    logs = tmp_path_factory.mktemp("dask-logs")
    env = {**os.environ, "DASK_LOGGING__DISTRIBUTED": "warning"}
    procs = []

    def start(name, *argv):
        with open(logs / f"{name}.log", "w") as log:
            procs.append(subprocess.Popen([dask, *argv], stdout=log, stderr=subprocess.STDOUT, env=env,
                                          start_new_session=True))

    try:
        start("scheduler", "scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1], "--no-dashboard")
        for k in range(2):
            start(f"worker{k}", "worker", address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
                  "--name", f"worker{k}")
        with distributed.Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=120)
        yield address
    finally:
        for p in procs[::-1]:  # workers first
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        deadline = time.monotonic() + 30
        for p in procs:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


def _found(out: Path) -> list[dict]:
    summary = yaml.safe_load((out / "fleet.yaml").read_text())
    return [{k: v for k, v in row.items() if k not in _RUN_FIELDS} for row in summary["vehicles"]]


@pytest.mark.slow
def test_cluster_local_2_and_a_separate_scheduler_with_two_workers_give_the_serial_bytes(
        fleet_data, scheduler_and_two_workers, tmp_path, capsys):
    import distributed

    manifest = tmp_path / "fleet.yaml"
    manifest.write_text(manifest_text(fleet_data, vehicles=("knocked", "truncated", "same")))
    runs = {"serial": ["--workers", "0"], "local": ["--cluster", "local:2"],
            "tcp": ["--cluster", scheduler_and_two_workers]}
    for name, argv in runs.items():
        assert main(["-q", "fleet", str(manifest), "--out", str(tmp_path / name), *argv]) == 0, name
        assert "2 of 3 vehicles calibrated, 1 failed; moved since previous: knocked" in capsys.readouterr().out, name
    want = _found(tmp_path / "serial")
    assert [r["status"] for r in want] == ["ok", "failed", "ok"]
    for name in ("local", "tcp"):
        assert _found(tmp_path / name) == want, name
        for v in ("knocked", "same"):
            for f in _SAME_BYTES:
                assert_same_bytes(tmp_path / name / v / f, tmp_path / "serial" / v / f)
    # the separate workers did the vehicles: each of the three ran on one of them, none in this process
    with distributed.Client(scheduler_and_two_workers, timeout="30s") as client:
        ran = client.run(lambda dask_worker: dask_worker.state.executed_count)
    assert len(ran) == 2 and sum(ran.values()) >= 3, ran


@pytest.mark.parametrize("address", ["bogus", "local:abc"])
def test_a_cluster_address_dask_cannot_parse_is_a_one_line_input_error(address):
    from clcgraph.errors import InputError
    from clcgraph.fleet import dask_executor

    with pytest.raises(InputError, match=f"--cluster {address}: not a scheduler address"):
        with dask_executor(address):
            pass
