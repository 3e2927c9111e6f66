"""`clcgraph fleet` on a simulated fleet of four tiny vehicles (fleetsim.py): the knocked camera is
flagged with the right axis and size, the recalibration is "same", the truncated bag is one line
and the others finish; the same bytes serially, on the process pool (with a worker killed
mid-vehicle) and on a real Dask LocalCluster; --resume keeps complete vehicles; manifests are
validated with the line named."""

from __future__ import annotations

import csv
import io

import numpy as np
import pytest
import yaml

from clcgraph.cli import main
from clcgraph.errors import InputError
from clcgraph.fleet import Manifest, SerialExecutor, calibrate_fleet
from fleetsim import KNOCK_DEG, assert_same_bytes, kill_once_pool, manifest_text, true_knock

_RUN_FIELDS = ("time_s", "attempts", "resumed")  # how a run went, not what it found


def _found(summary: dict) -> list[dict]:
    return [{k: v for k, v in row.items() if k not in _RUN_FIELDS} for row in summary["vehicles"]]


def _by_id(summary):
    return {r["id"]: r for r in summary["vehicles"]}


@pytest.fixture(scope="module")
def serial(fleet_data, tmp_path_factory):
    root = tmp_path_factory.mktemp("serial")
    (root / "fleet.yaml").write_text(manifest_text(fleet_data))
    out = root / "out"
    return root / "fleet.yaml", out, calibrate_fleet(root / "fleet.yaml", out, SerialExecutor())


@pytest.mark.slow
def test_fleet_flags_the_knocked_camera_passes_the_recalibration_and_isolates_the_broken_bag(serial, fleet_data):
    from clcgraph.comparison import PoseSet, compare, poses_of

    _, out, summary = serial
    rows = _by_id(summary)
    assert summary["counts"] == {"vehicles": 4, "ok": 3, "failed": 1}
    assert summary["changed_since_previous"] == ["knocked"]

    cam = {s["topic"]: s for s in rows["knocked"]["previous"]["sensors"]}["/cam"]
    assert cam["status"] == "moved" and cam["p_value"] < 1e-6
    assert cam["rotation_deg"] == pytest.approx(KNOCK_DEG, abs=0.15)  # ~5 sigma of the difference
    assert np.argmax(np.abs(cam["axis_ref"])) == 2 and cam["axis_ref"][2] > 0.9  # about lidar0's +z, as knocked
    assert "about z" in cam["verdict"] and cam["verdict"].startswith("moved 0.")
    # what is left after undoing the true knock on the previous calibration is only noise
    prev = poses_of(fleet_data["previous"])
    T, C = prev.poses["/cam"]
    undone = PoseSet(prev.reference, {**prev.poses, "/cam": (true_knock(fleet_data) @ T, C)})
    rest = {s.topic: s for s in compare(undone, out / "knocked").sensors}["/cam"]
    assert rest.status == "same" and rest.p_value > 1e-3, rest.verdict

    same = {s["topic"]: s for s in rows["same"]["previous"]["sensors"]}["/cam"]
    assert same["status"] == "same" and same["p_value"] > 0.01, same["verdict"]
    assert same["verdict"].startswith("same within uncertainty")

    bad = rows["truncated"]
    assert bad["status"] == "failed" and "pose003.bag" in bad["error"] and "\n" not in bad["error"]
    assert not (out / "truncated").exists()  # nothing half-written
    for v in ("same", "knocked", "first"):
        assert (out / v / "calibration.yaml").is_file() and (out / v / "report.html").is_file()

    on_disk = yaml.safe_load((out / "fleet.yaml").read_text())
    assert _found(on_disk) == _found(summary)
    table = list(csv.DictReader(io.StringIO((out / "fleet.csv").read_text())))
    assert len(table) == 3 * 2 + 1  # a row per sensor of each calibrated vehicle, one for the failure
    knocked_cam = next(r for r in table if r["vehicle"] == "knocked" and r["sensor"] == "/cam")
    assert knocked_cam["previous_status"] == "moved"
    page = (out / "fleet.html").read_text()
    assert "data:image/png;base64," in page and "pose003.bag" in page and "<img" in page
    assert "src=\"http" not in page  # self-contained


@pytest.mark.slow
def test_fleet_is_bit_identical_on_a_process_pool_with_a_killed_worker_and_on_dask(serial, fleet_data, tmp_path,
                                                                                   monkeypatch):
    """The knocked and the broken vehicle again: the pool's first worker is SIGKILLed a second
    into its vehicle (retried once), then a real Dask LocalCluster of 2 worker processes."""
    distributed = pytest.importorskip("distributed")
    _, serial_out, serial_summary = serial
    (tmp_path / "fleet.yaml").write_text(manifest_text(fleet_data, vehicles=("knocked", "truncated")))
    want = [r for r in _found(serial_summary) if r["id"] in ("knocked", "truncated")]

    # the killed worker's temporary files cannot be removed: they go where the test's do
    (tmp_path / "scratch").mkdir()
    monkeypatch.setenv("TMPDIR", str(tmp_path / "scratch"))
    pool = calibrate_fleet(tmp_path / "fleet.yaml", tmp_path / "pool", kill_once_pool(tmp_path / "killed"))
    assert (tmp_path / "killed").exists()  # a worker was killed
    assert max(r["attempts"] for r in pool["vehicles"]) == 2
    assert _found(pool) == want

    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            distributed.Client(cluster) as client:
        dask = calibrate_fleet(tmp_path / "fleet.yaml", tmp_path / "dask", client.get_executor())
    assert _found(dask) == want
    for out in (tmp_path / "pool", tmp_path / "dask"):
        for name in ("calibration.yaml", "problem.npz", "config.resolved.yaml"):
            assert_same_bytes(out / "knocked" / name, serial_out / "knocked" / name)


@pytest.mark.slow
def test_resume_keeps_complete_vehicles_and_reruns_the_failed_one(serial, capsys):
    """Through the command, in this process (--workers 0): the table, then the same summary."""
    manifest, out, summary = serial
    before = {v: (out / v / "calibration.yaml").stat().st_mtime_ns for v in ("same", "knocked", "first")}
    assert main(["fleet", str(manifest), "--out", str(out), "--resume", "--workers", "0"]) == 0  # failures: in the summary
    printed = capsys.readouterr().out
    assert "3 of 4 vehicles calibrated, 1 failed; moved since previous: knocked" in printed
    lines = {line.split()[0]: line for line in printed.splitlines()[1:5]}
    assert "ok (kept)" in lines["same"] and "failed" in lines["truncated"] and "pose003.bag" in lines["truncated"]
    again = yaml.safe_load((out / "fleet.yaml").read_text())
    assert _found(again) == _found(summary)
    rows = _by_id(again)
    assert all(rows[v].get("resumed") for v in before) and not rows["truncated"].get("resumed")
    assert rows["same"]["time_s"] == _by_id(summary)["same"]["time_s"]  # from the earlier fleet.yaml
    assert before == {v: (out / v / "calibration.yaml").stat().st_mtime_ns for v in before}


def test_fleet_out_must_be_ours(tmp_path, capsys):
    (tmp_path / "m.yaml").write_text("vehicles: [{id: a, bags: x.bag, topics: [/l, /c]}]\n")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    assert main(["fleet", str(tmp_path / "m.yaml"), "--out", str(tmp_path / "mine")]) == 2
    err = capsys.readouterr().err
    assert "not a clcgraph output" in err and "--force" not in err  # fleet has none: it never removes
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep me"


@pytest.mark.parametrize("text, line, words", [
    ("vehicles:\n  - id: a\n    bags: x.bag\n    topics: [/l]\n    bagz: y\n", 5, "unknown key 'vehicles[0].bagz'"),
    ("defaults:\n  method: target\n  topic: [/l]\nvehicles: [{id: a, bags: x}]\n", 3, "unknown key 'defaults.topic'"),
    ("defaults:\n  method: magic\n  topics: [/l]\nvehicles:\n  - {id: a, bags: x}\n", 2, "must be one of target"),
    ("defaults: {topics: [/l]}\nvehicles:\n  - {id: a, bags: x}\n  - {id: a, bags: y}\n", 4, "is also vehicles[0]"),
    ("defaults: {topics: [/l]}\nvehicles:\n  - id: a\n", 3, "needs 'bags'"),
    ("defaults: {topics: [/l]}\nvehicles:\n  - {id: ../up, bags: x}\n", 3, "a folder name"),
    ("defaults:\n  topics: [/l]\n  config: {solve: {outlier_sigma: 0.5}}\nvehicles: [{id: a, bags: x}]\n", 3,
     "'solve.outlier_sigma' must be in [1, inf)"),
    ("defaults: {topics: [/l]}\nvehicles:\n  - id: a\n    bags: x\n    config: {solv: {}}\n", 5,
     "unknown config key 'solv'"),
    ("vehicles: []\n", 1, "non-empty list"),
])
def test_manifest_errors_name_the_file_and_line(tmp_path, capsys, text, line, words):
    (tmp_path / "fleet.yaml").write_text(text)
    with pytest.raises(InputError) as e:
        Manifest.load(tmp_path / "fleet.yaml")
    assert f"fleet.yaml:{line}:" in str(e.value) and words in str(e.value), str(e.value)
    assert main(["fleet", str(tmp_path / "fleet.yaml"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and words in err
    assert not (tmp_path / "out").exists()


def test_manifest_paths_are_relative_to_its_folder_and_vehicles_override_defaults(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "fleet.yaml").write_text(
        "defaults:\n  topics: [/l, /c]\n  models: [c.cameramodel]\n  config: {solve: {outlier_sigma: 5}}\n"
        "vehicles:\n  - {id: a, bags: [a/*.bag], previous: ../old/a}\n"
        "  - {id: b, bags: /abs/b.bag, method: targetless, topics: [/l, /m], models: [], config: {solve: {max_iterations: 7}}}\n")
    a, b = Manifest.load(tmp_path / "sub" / "fleet.yaml").jobs(tmp_path / "out")
    assert a.bags == (str(tmp_path / "sub" / "a/*.bag"),) and a.models == (str(tmp_path / "sub" / "c.cameramodel"),)
    assert a.previous == str(tmp_path / "sub" / "../old/a") and a.out == str(tmp_path / "out" / "a")
    assert a.config.solve.outlier_sigma == 5 and a.method == "target"
    assert b.method == "targetless" and b.bags == ("/abs/b.bag",) and b.topics == ("/l", "/m")
    assert b.config.solve.outlier_sigma == 5 and b.config.solve.max_iterations == 7  # sections merge
    assert np.isclose(b.config.compare.false_alarm_rate, 0.01)


class _LosingExecutor:
    """Every call's worker is lost (as a killed process pool reports it); counts the calls."""

    def __init__(self):
        self.calls = 0

    def __call__(self):  # as a factory: a fresh one each time, sharing the count
        return self

    def submit(self, fn, /, *args, **kwargs):
        import concurrent.futures as cf
        from concurrent.futures.process import BrokenProcessPool

        self.calls += 1
        f = cf.Future()
        f.set_exception(BrokenProcessPool("A process in the process pool was terminated abruptly"))
        return f

    def shutdown(self, wait=True, *, cancel_futures=False):
        pass


def test_a_vehicle_whose_worker_is_lost_twice_is_retried_once_then_reported(tmp_path):
    import concurrent.futures as cf

    class Losing(_LosingExecutor, cf.Executor):
        pass

    (tmp_path / "m.yaml").write_text("defaults: {topics: [/l, /c]}\nvehicles:\n  - {id: a, bags: a.bag}\n")
    ex = Losing()
    s = calibrate_fleet(tmp_path / "m.yaml", tmp_path / "out", ex)
    (row,) = s["vehicles"]
    assert ex.calls == 2 and row["attempts"] == 2 and row["status"] == "failed"
    assert row["error"].startswith("the worker failed 2 times: BrokenProcessPool: A process in the process pool")
    # a serial run of the same fleet: the vehicle's own error (no such bag), first attempt
    (row,) = calibrate_fleet(tmp_path / "m.yaml", tmp_path / "out", SerialExecutor())["vehicles"]
    assert row["attempts"] == 1 and "a.bag: no such bag" in row["error"]


def test_every_stage_of_a_vehicle_runs_with_single_threaded_blas_whatever_the_process_had(monkeypatch, tmp_path):
    """The engines start workers with different BLAS thread counts (a Dask nanny sets
    OPENBLAS_NUM_THREADS=1, a process pool inherits the caller's), and earlier work in a process
    can leave another count behind: reading and detection, not only the solve, must not see it."""
    from threadpoolctl import threadpool_info, threadpool_limits

    import clcgraph.api
    from clcgraph.errors import DataError
    from clcgraph.fleet import run_vehicle

    seen = []

    def read_problem(*args, **kwargs):  # the frontend's entry: record the BLAS threads, then stop
        seen.extend(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")
        raise DataError("stopped after reading")

    monkeypatch.setattr(clcgraph.api, "read_problem", read_problem)
    (tmp_path / "m.yaml").write_text("defaults: {topics: [/l, /c]}\nvehicles:\n  - {id: a, bags: a.bag}\n")
    (job,) = Manifest.load(tmp_path / "m.yaml").jobs(tmp_path / "out")
    with threadpool_limits(limits=2, user_api="blas"):  # what a pool worker on 2 cores starts with
        row = run_vehicle(job)
    assert row["error"] == "stopped after reading"
    assert seen and set(seen) == {1}, seen


def test_a_worker_running_other_clcgraph_code_refuses_the_vehicle(tmp_path):
    """A worker that imported clcgraph after its files changed (an update or a checkout during the
    run, another install on a cluster machine) would give other bytes without a word."""
    import dataclasses

    from clcgraph.fleet import CODE, code_fingerprint, run_vehicle

    (tmp_path / "m.yaml").write_text("defaults: {topics: [/l, /c]}\nvehicles:\n  - {id: a, bags: a.bag}\n")
    (job,) = Manifest.load(tmp_path / "m.yaml").jobs(tmp_path / "out")
    assert job.code == CODE == code_fingerprint()  # the caller's code travels with the job
    row = run_vehicle(dataclasses.replace(job, code="0123456789abcdef"))
    assert row["status"] == "failed" and "other clcgraph code than the caller" in row["error"]
    assert "0123456789abcdef" in row["error"] and CODE in row["error"] and "\n" not in row["error"]
    assert not (tmp_path / "out").exists()  # nothing started
    assert "a.bag: no such bag" in run_vehicle(job)["error"]  # the same code: the vehicle's own error
