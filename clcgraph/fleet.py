"""Calibrate a fleet: every vehicle's captures on an Executor, each compared with its last calibration.

SYNOPSIS
    from clcgraph.fleet import calibrate_fleet
    summary = calibrate_fleet("fleet.yaml", "out/")                     # local process pool
    summary = calibrate_fleet("fleet.yaml", "out/", executor=SerialExecutor())
    with dask_executor("tcp://scheduler:8786") as ex:                    # or "local:4"
        summary = calibrate_fleet("fleet.yaml", "out/", executor=ex)
    summary["vehicles"][0]["status"], summary["vehicles"][0]["previous"]["changed"]

The manifest (``Manifest.load``; paths relative to its folder; unknown keys are errors naming
their line)::

    defaults:                     # any of these, per vehicle too (a vehicle's own wins)
      method: target              # target (clcgraph solve) | targetless
      topics: [/lidar/top, /cam/front]   # targetless: the mapping LIDAR first, then those to calibrate
      models: [front.cameramodel]        # target: one per camera topic
      base_frame: base_link              # targetless only: also base_link from the ground
      config: {board: {corners: [7, 5], square_m: 0.095, size_m: [0.85, 0.61]}}   # or a file
    vehicles:
      - id: van-017               # DIR/van-017/ gets the usual outputs of solve / targetless
        bags: [van-017/*.bag]
        previous: ../2026-11/van-017   # optional: a calibration output to compare with

Each vehicle runs ``run_vehicle`` (api.calibrate_bags / the targetless API, the code path of
solve / targetless) on the executor. A vehicle's own failure (a broken bag) is its one-line
error in the summary; a failure of the worker (killed, out of memory, lost) is retried once,
then reported. The summary rows are plain data (``vehicle_row``): per sensor its pose and
sigmas, the comparison with ``previous`` and with the first bag's /tf_static.
"""

from __future__ import annotations

import collections
import concurrent.futures as cf
import contextlib
import dataclasses
import logging
import os
import re
import sys
import time
import types
from pathlib import Path

import numpy as np

from .cameras import FROM_CAMERA_INFO
from .errors import ClcgraphError, DependencyError, InputError

log = logging.getLogger(__name__)

SUMMARY_YAML, SUMMARY_CSV, SUMMARY_HTML = "fleet.yaml", "fleet.csv", "fleet.html"
_SHARED_KEYS = ("method", "topics", "models", "base_frame", "config")
_VEHICLE_KEYS = ("id", "bags", "previous", *_SHARED_KEYS)
_METHODS = ("target", "targetless")
_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")
_RETRIES = 1  # a worker lost mid-vehicle: run it once more, then report it


# ---------------------------------------------------------------- the manifest


@dataclasses.dataclass(frozen=True)
class VehicleJob:
    """One vehicle's calibration, everything resolved (absolute paths, a validated config)."""

    id: str
    method: str
    bags: tuple  # absolute globs / paths
    topics: tuple
    models: tuple = ()
    base_frame: str | None = None
    config: object = None  # clcgraph.config.Config
    previous: str | None = None
    out: str = ""
    code: str | None = None  # the caller's code_fingerprint(): a worker running other code refuses the job


class _LineDict(dict):
    line: int = 0
    key_lines: dict


def _line_loader():
    from .config import SafeLoaderNoCollectionAliases

    class Loader(SafeLoaderNoCollectionAliases):  # a manifest is user input: no alias bombs
        pass

    def mapping(loader, node):
        d = _LineDict(loader.construct_mapping(node, deep=True))
        d.line = node.start_mark.line + 1
        d.key_lines = {loader.construct_object(k, deep=True): k.start_mark.line + 1 for k, _ in node.value}
        return d

    Loader.add_constructor("tag:yaml.org,2002:map", mapping)
    return Loader


class Manifest:
    """A validated fleet manifest: ``jobs(out)`` gives one VehicleJob per vehicle."""

    def __init__(self, data: dict, *, base: Path, where: str):
        self.where, self.base = where, base
        self._check_keys(data, ("defaults", "vehicles"), "")
        defaults = data.get("defaults") or _LineDict()
        if not isinstance(defaults, dict):
            self._fail(data, "defaults", "'defaults' must be a mapping")
        self._check_keys(defaults, _SHARED_KEYS, "defaults.")
        vehicles = data.get("vehicles")
        if not isinstance(vehicles, list) or not vehicles:
            self._fail(data, "vehicles", "'vehicles' must be a non-empty list")
        self.vehicles = []
        seen: dict[str, str] = {}
        for k, v in enumerate(vehicles):
            at = f"vehicles[{k}]"
            if not isinstance(v, dict):
                raise InputError(f"{where}: {at} must be a mapping with id and bags")
            self._check_keys(v, _VEHICLE_KEYS, f"{at}.")
            for key in ("id", "bags"):
                if key not in v:
                    raise InputError(f"{where}:{getattr(v, 'line', '?')}: {at} needs '{key}'")
            vid = v["id"]
            if not isinstance(vid, str) or not _ID.fullmatch(vid):
                self._fail(v, "id", f"{at}.id {vid!r}: a folder name of letters, digits, '.', '_', '-'")
            if vid in seen:
                self._fail(v, "id", f"{at}.id {vid!r} is also {seen[vid]}'s")
            seen[vid] = at
            merged = {key: (v[key] if key in v else defaults.get(key)) for key in _SHARED_KEYS}
            src = {key: (v, key, f"{at}.{key}") if key in v else (defaults, key, f"defaults.{key}") for key in _SHARED_KEYS}
            self.vehicles.append(self._vehicle(v, at, merged, src, defaults))

    # ---- validation helpers: every error names the file and line
    def _fail(self, d, key, msg):
        line = getattr(d, "key_lines", {}).get(key, getattr(d, "line", "?"))
        raise InputError(f"{self.where}:{line}: {msg}")

    def _check_keys(self, d: dict, known, prefix: str):
        for key in d:
            if key not in known:
                self._fail(d, key, f"unknown key '{prefix}{key}' (known: {', '.join(known)})")

    def _strings(self, d, key, what, value, *, at, empty_ok=False):
        items = [value] if isinstance(value, str) else value
        if not isinstance(items, list) or not (items or empty_ok) or not all(isinstance(x, str) and x.strip() for x in items):
            self._fail(d, key, f"{at}: {what}")
        return [x.strip() for x in items]

    def _path(self, p: str) -> str:
        return str(Path(p) if Path(p).is_absolute() else self.base / p)

    def _vehicle(self, v, at, merged, src, defaults) -> dict:
        from .config import Config, ConfigError

        method = merged["method"] or "target"
        if method not in _METHODS:
            self._fail(*src["method"][:2], f"{src['method'][2]}: must be one of {', '.join(_METHODS)}, got {method!r}")
        if merged["topics"] is None:
            raise InputError(f"{self.where}:{v.line}: {at} has no 'topics' (give them here or in defaults)")
        topics = self._strings(*src["topics"][:2], "a list of topics", merged["topics"], at=src["topics"][2])
        models = [] if merged["models"] is None else \
            self._strings(*src["models"][:2], "a list of camera models (files, or camera_info)", merged["models"], at=src["models"][2],
                          empty_ok=True)
        if method == "targetless" and models:
            self._fail(*src["models"][:2], f"{src['models'][2]}: targetless calibrates LIDARs only: no models")
        if method == "targetless" and len(topics) < 2:
            self._fail(*src["topics"][:2], f"{src['topics'][2]}: targetless needs the mapping LIDAR and >= 1 other")
        base_frame = merged["base_frame"]
        if base_frame is not None and (method != "targetless" or not isinstance(base_frame, str)):
            self._fail(*src["base_frame"][:2], f"{src['base_frame'][2]}: a frame name, for targetless only")
        bags = self._strings(v, "bags", "a glob or a list of globs", v["bags"], at=f"{at}.bags")
        previous = v.get("previous")
        if previous is not None and not isinstance(previous, str):
            self._fail(v, "previous", f"{at}.previous: a calibration output directory")
        # the vehicle's config sections update the defaults' (each a mapping or a YAML file)
        sections: dict = {}
        for d, where in ((defaults, "defaults.config"), (v, f"{at}.config")):
            c = d.get("config")
            if c is None:
                continue
            if isinstance(c, str):
                try:
                    c = Config.from_yaml(self._path(c)).to_dict()
                except ConfigError as e:
                    self._fail(d, "config", f"{where}: {e}")
            if not isinstance(c, dict):
                self._fail(d, "config", f"{where}: a mapping of config sections or a config file")
            for name, values in c.items():
                if not isinstance(values, dict):
                    self._fail(c, name, f"{where}.{name}: must be a mapping")
                sections.setdefault(name, {}).update(values)
        try:
            cfg = Config.from_dict(sections)
        except ConfigError as e:
            d = v if "config" in v else defaults
            self._fail(d, "config", f"{at}: config: {e}")
        return {"id": v["id"], "method": method, "bags": tuple(self._path(b) for b in bags), "topics": tuple(topics),
                "models": tuple(m if m == FROM_CAMERA_INFO else self._path(m) for m in models), "base_frame": base_frame, "config": cfg,
                "previous": None if previous is None else self._path(previous)}

    @classmethod
    def load(cls, manifest) -> "Manifest":
        """From a YAML file (paths relative to its folder) or a dict (relative to the working directory)."""
        from .config import read_yaml

        if isinstance(manifest, Manifest):
            return manifest
        if isinstance(manifest, dict):
            return cls(manifest, base=Path.cwd(), where="manifest")
        path = Path(manifest)
        data = read_yaml(path, "fleet manifest", loader=_line_loader(), mapping="with 'defaults' and 'vehicles'")
        return cls(data, base=path.absolute().parent, where=str(path))

    def jobs(self, out) -> list[VehicleJob]:
        out = Path(out).absolute()
        return [VehicleJob(**v, out=str(out / v["id"]), code=CODE) for v in self.vehicles]


# ---------------------------------------------------------------- one vehicle (runs on a worker)


def code_fingerprint() -> str:
    """A hash of clcgraph's source files as they are on disk now (16 hex digits)."""
    import hashlib

    root = Path(__file__).parent
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()[:16]


# Taken when this module is imported: the code this process runs. A worker started later (a pool
# process, a Dask worker) imports it again; if the files changed in between (an update, a checkout
# during a run, another install on a cluster machine) the two differ, and the worker would give
# other numbers without a word.
CODE = code_fingerprint()


def run_vehicle(job: VehicleJob) -> dict:
    """Calibrate one vehicle into ``job.out`` and return its summary row (``vehicle_row``); a
    failure of the vehicle's own (bad bag, degenerate capture) is the row's one-line ``error``.

    Every stage (reading, detection, solve, writing, comparisons) runs with single-threaded
    BLAS: the engines start their workers with different BLAS thread counts (Dask's set
    OPENBLAS_NUM_THREADS=1, a process pool inherits the caller's), and so can earlier work in
    the same process; the same vehicle must give the same bytes on each of them."""
    from . import progress
    from .determinism import single_threaded_blas

    if job.code is not None and job.code != CODE:
        return {**_failed(job, f"this worker runs other clcgraph code than the caller (code {CODE}, the caller's "
                               f"{job.code}): every worker needs the same install, started after the last update"),
                "time_s": 0.0}
    t0 = time.perf_counter()
    was = progress.is_enabled()
    progress.set_enabled(False)  # one bar, the fleet's, in the calling process
    try:
        with single_threaded_blas():
            _calibrate(job)
            row = vehicle_row(job)
    except ClcgraphError as e:
        row = _failed(job, str(e))
    except Exception as e:  # noqa: BLE001 - a bug on one vehicle must not stop the fleet
        log.debug("%s: internal error", job.id, exc_info=True)
        row = _failed(job, f"internal error: {type(e).__name__}: {e}")
    finally:
        progress.set_enabled(was)
    row["time_s"] = round(time.perf_counter() - t0, 3)
    return row


def _calibrate(job: VehicleJob) -> None:
    from . import api

    if job.method == "target":
        api.calibrate_bags(list(job.bags), list(job.topics), list(job.models), out=job.out, config=job.config)
        return
    api.calibrate_targetless(list(job.bags), mapping_topic=job.topics[0], calibration_topics=list(job.topics[1:]),
                             base_frame=job.base_frame, out=job.out, config=job.config)


def _failed(job: VehicleJob, error: str) -> dict:
    return {"id": job.id, "method": job.method, "status": "failed", "error": error.splitlines()[0] if error else "?",
            "out": None, "sensors": [], "previous": None, "nominal": None}


def vehicle_row(job: VehicleJob) -> dict:
    """The summary row of a vehicle whose output is in ``job.out``: per sensor pose and sigmas, the
    comparison with ``job.previous`` and with the first bag's /tf_static (each None, or its error)."""
    from .comparison import compare, poses_of
    from .geometry import pose_stdevs, rt_from_T

    mine = poses_of(job.out)
    sensors = []
    for topic, (T, C) in mine.poses.items():
        rt = rt_from_T(T)
        s = {"topic": topic, "rt_lidar0_sensor": _digits(rt)}
        if C is not None:
            rot, pos = pose_stdevs(rt, C)
            s["stdev_orientation_deg"] = _digits(np.degrees(rot))
            s["stdev_position_mm"] = _digits(1e3 * pos)
        sensors.append(s)
    row = {"id": job.id, "method": job.method, "status": "ok", "error": None, "out": job.id, "sensors": sensors}

    def against(other):
        try:
            c = compare(other, job.out, config=job.config).to_dict()
            return {**c, "b": f"{job.id}/calibration.yaml"}  # relative to the fleet's folder
        except ClcgraphError as e:
            return {"error": str(e).splitlines()[0]}

    row["previous"] = None if job.previous is None else against(job.previous)
    from .api import expand_bags

    try:
        first_bag = expand_bags(job.bags)[0]
    except ClcgraphError as e:
        row["nominal"] = {"error": str(e)}
    else:
        row["nominal"] = against(first_bag)
    return row


def _digits(a) -> list:
    """9 significant digits: BLAS thread counts (a Dask worker runs single-threaded) change the last ones."""
    return [float(f"{float(x):.9g}") for x in np.asarray(a, float).ravel()]


def output_complete(job: VehicleJob) -> bool:
    """A vehicle's output is whole once its calibration.yaml is there (written atomically) and ours."""
    from .outputs.atomic import marker_kind

    return marker_kind(Path(job.out)) == "results" and (Path(job.out) / "calibration.yaml").is_file()


# ---------------------------------------------------------------- engines


class SerialExecutor(cf.Executor):
    """Runs each call at once in the calling process (the reference for the other engines).
    An interruption (KeyboardInterrupt, SystemExit) is raised at once, not kept in the future."""

    _max_workers = 1

    def submit(self, fn, /, *args, **kwargs):
        f = cf.Future()
        try:
            f.set_result(fn(*args, **kwargs))
        except Exception as e:  # noqa: BLE001 - handed to the caller through the future
            f.set_exception(e)
        return f


class ScriptSafeProcessPool(cf.ProcessPoolExecutor):
    """A spawn process pool that works from a script without an ``if __name__ == "__main__"`` guard.

    A spawned worker re-runs the calling script as ``__mp_main__`` (multiprocessing's preparation);
    a script that calls calibrate_fleet at top level would then start a fleet in every worker.
    Workers here start while ``__main__`` is an empty module, so they import only what the calls
    need (clcgraph.fleet): nothing of the script runs twice. Spawn, not fork: no inherited
    threads or OpenMP state.
    """

    def __init__(self, max_workers: int | None = None):
        import multiprocessing

        super().__init__(max_workers=max_workers, mp_context=multiprocessing.get_context("spawn"))

    def submit(self, fn, /, *args, **kwargs):
        main = sys.modules.get("__main__")
        sys.modules["__main__"] = types.ModuleType("__main__")  # spawn's preparation reads it here
        try:
            return super().submit(fn, *args, **kwargs)
        finally:
            if main is not None:
                sys.modules["__main__"] = main


def default_workers() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def dask_executor(address: str):
    """An Executor on a Dask distributed cluster: ``tcp://host:8786`` (a running scheduler), or
    ``local:N`` (a LocalCluster of N single-threaded worker processes, stopped afterwards)."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise DependencyError("--cluster needs Dask distributed: pip install 'clcgraph[fleet]'") from None
    cluster = None
    m = re.fullmatch(r"local:(\d+)", address)
    try:
        if m:
            n = int(m.group(1))
            if not 1 <= n <= 1024:
                raise InputError(f"--cluster {address}: N must be 1..1024 worker processes")
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0")
            client = Client(cluster)
        else:
            client = Client(address, timeout="20s")
    except (OSError, TimeoutError) as e:
        if cluster is not None:
            cluster.close()
        raise InputError(f"--cluster {address}: cannot reach the Dask scheduler ({e})") from None
    except ValueError as e:  # Dask's parse of the address
        raise InputError(f"--cluster {address}: not a scheduler address, e.g. tcp://host:8786 or local:4 ({e})") from None
    try:
        yield client.get_executor()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


# ---------------------------------------------------------------- the fleet


def calibrate_fleet(manifest, out, executor=None, *, resume: bool = False, workers: int | None = None) -> dict:
    """Calibrate every vehicle of ``manifest`` (a path or a dict, see ``Manifest``) into ``out/<id>/``
    and write ``out/fleet.yaml``, ``fleet.csv``, ``fleet.html``; returns the fleet.yaml content.

    ``executor``: any concurrent.futures.Executor (a ProcessPoolExecutor, a Dask
    ``Client.get_executor()``, ``SerialExecutor()``), or a zero-argument callable that makes one
    (then a pool broken by a dead worker is replaced); default: a local spawn process pool of
    ``workers`` processes (default: the CPUs this process may use). ``resume``: keep the vehicles
    whose ``out/<id>/`` is complete. ``out`` must be new, empty or an earlier fleet output.
    """
    from .outputs.atomic import open_out_dir

    m = Manifest.load(manifest)
    with open_out_dir(out, kind="fleet") as target:
        jobs = m.jobs(target)
        old_times = _previous_times(target) if resume else {}
        rows: dict[str, dict] = {}
        todo = []
        for job in jobs:
            if resume and output_complete(job):
                rows[job.id] = {**vehicle_row(job), "time_s": old_times.get(job.id), "resumed": True}
                log.info("%s: complete in %s, kept (--resume)", job.id, job.out)
            else:
                todo.append(job)
        if executor is None:
            n = workers or default_workers()
            executor = (lambda: ScriptSafeProcessPool(min(n, max(1, len(todo))))) if todo else SerialExecutor
        for row in _run(todo, executor, total=len(jobs), done=len(rows)):
            rows[row["id"]] = row
        summary = _summary(m, [rows[j.id] for j in jobs])
        _write_summary(summary, target)
    return summary


def _run(jobs, executor, *, total: int, done: int):
    """Yield each job's row as it finishes, under one progress bar; worker failures retried once."""
    from .progress import progress

    owned = callable(executor) and not isinstance(executor, cf.Executor)
    ex = executor() if owned else executor
    attempts = {j.id: 0 for j in jobs}
    order = {j.id: k for k, j in enumerate(jobs)}
    futures: dict = {}

    def submit(job):
        nonlocal ex
        attempts[job.id] += 1
        try:
            futures[ex.submit(run_vehicle, job)] = job
            return None
        except cf.BrokenExecutor as e:
            if not owned:
                return {**_failed(job, f"the executor is broken (a worker died): {e or type(e).__name__}"),
                        "attempts": attempts[job.id]}
            ex.shutdown(wait=False, cancel_futures=True)
            ex = executor()  # a fresh pool for the rest
            futures[ex.submit(run_vehicle, job)] = job
            return None

    # no more vehicles in flight than the executor runs at once (all of them for Dask, which
    # schedules them itself): the bar moves as vehicles finish, and a pool that loses a worker
    # costs an attempt only to the vehicles that were running
    window = getattr(ex, "_max_workers", None) or len(jobs)
    queue = collections.deque(jobs)

    def completions():
        while queue or futures:
            while queue and len(futures) < window:
                row = submit(queue.popleft())
                if row is not None:
                    yield row
            if not futures:
                continue
            finished, _ = cf.wait(list(futures), return_when=cf.FIRST_COMPLETED)
            for f in sorted(finished, key=lambda f: order[futures[f].id]):  # the same log order every run
                job = futures.pop(f)
                try:
                    row = f.result()
                except Exception as e:  # noqa: BLE001 - the worker, not the vehicle, failed
                    why = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else 'worker lost'}"
                    if attempts[job.id] <= _RETRIES:
                        log.warning("%s: the worker failed (%s); running it again", job.id, why)
                        row = submit(job)
                        if row is None:
                            continue
                    else:
                        row = _failed(job, f"the worker failed {attempts[job.id]} times: {why}")
                row["attempts"] = attempts[job.id]
                yield row

    try:
        for k, row in enumerate(progress(completions(), desc="calibrating vehicles", total=total - done,
                                         unit="vehicle")):
            _log_row(row, done + k + 1, total)
            yield row
    except BaseException:  # interrupted: what is queued never starts; what runs is not waited for
        for f in futures:
            f.cancel()
        if owned:
            ex.shutdown(wait=False, cancel_futures=True)
        raise
    if owned:
        ex.shutdown(wait=True)


def _log_row(row: dict, k: int, n: int) -> None:
    if row["status"] != "ok":
        log.warning("[%d/%d] %s: failed: %s", k, n, row["id"], row["error"])
        return
    moved = [s["topic"] for c in (row.get("previous"),) if c and "sensors" in c
             for s in c["sensors"] if s["status"] == "moved"]
    log.info("[%d/%d] %s: ok in %.1f s%s", k, n, row["id"], row.get("time_s") or 0.0,
             f"; moved since previous: {', '.join(moved)}" if moved else "")


def _previous_times(target: Path) -> dict:
    from .config import read_yaml

    try:
        d = read_yaml(target / SUMMARY_YAML, "fleet summary")
        return {v["id"]: v.get("time_s") for v in d["vehicles"] if v.get("status") == "ok"}
    except Exception:  # noqa: BLE001 - no usable earlier summary: times unknown
        return {}


def _summary(m: Manifest, rows: list[dict]) -> dict:
    from . import __version__

    def changed(key):
        return [r["id"] for r in rows if (r.get(key) or {}).get("changed")]

    return {"clcgraph_version": __version__, "manifest": m.where,
            "counts": {"vehicles": len(rows), "ok": sum(r["status"] == "ok" for r in rows),
                       "failed": sum(r["status"] != "ok" for r in rows)},
            "changed_since_previous": changed("previous"), "off_nominal": changed("nominal"),
            "vehicles": rows}


def _write_summary(summary: dict, target: Path) -> None:
    import yaml

    from .outputs.atomic import atomic_file
    from .outputs.fleet_report import fleet_csv, fleet_html

    atomic_file(target / SUMMARY_YAML, yaml.safe_dump(summary, sort_keys=False, width=200))
    atomic_file(target / SUMMARY_CSV, fleet_csv(summary))
    atomic_file(target / SUMMARY_HTML, fleet_html(summary))
