"""Problem dumps: save a Problem + Config to a versioned, pickle-free .npz and load it (re-solving
one is backend/replay.py's, joined by ``api.replay``).

File layout (``FORMAT_VERSION`` 2; version 1 dumps, whose board was corners_x/corners_y/
spacing_m/margin_m, are read and converted): one ``.npz`` (numpy's zip of ``.npy`` arrays, read with
``allow_pickle=False``) holding

- ``meta``: a 0-d unicode array with a JSON document: format name and version, the config
  dict, the sensors (topic, kind, lensmodel, imagersize), the board (the config's ``board``
  keys: corners, square_m, size_m, pattern_offset_m), rejections, and the
  scalar/ragged bookkeeping of the observations;
- plain numeric arrays: concatenated LIDAR points (with per-observation counts), planes,
  indices, optional per-point rings and edge intervals (ragged, with counts), camera corners,
  priors, visibility points, snapshot stamps, intrinsics (and their covariance, where the camera
  model gave one).

Floats are stored as float64 and so round-trip bit-exactly.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from clcgraph.config import BoardOptions, Config, ConfigError
from clcgraph.errors import DataError, InputError
from clcgraph.types import (
    BoardGeometry,
    CameraBoardObservation,
    LidarBoardObservation,
    PosePrior,
    Problem,
    Rejected,
    Sensor,
)

log = logging.getLogger(__name__)

FORMAT_NAME = "clcgraph-problem"
FORMAT_VERSION = 2
_READABLE_VERSIONS = (1, 2)


def _concat(arrays, shape_tail, dtype=float):
    if not arrays:
        return np.zeros((0,) + shape_tail, dtype), np.zeros(0, np.int64)
    counts = np.array([len(a) for a in arrays], np.int64)
    return np.concatenate([np.asarray(a, dtype).reshape((-1,) + shape_tail) for a in arrays]), counts


def _split(data, counts):
    return np.split(data, np.cumsum(counts)[:-1]) if len(counts) else []


def save_problem(path: str | Path, problem: Problem, config: Config | None = None) -> None:
    """Write ``problem`` and ``config`` (default Config()) to ``path`` (.npz, format v2)."""
    config = config or Config()
    arrays: dict[str, np.ndarray] = {}
    sensors = []
    for i, s in enumerate(problem.sensors):
        sensors.append(
            dict(topic=s.topic, kind=s.kind, lensmodel=s.lensmodel,
                 imagersize=None if s.imagersize is None else [int(v) for v in s.imagersize],
                 has_intrinsics=s.intrinsics is not None,
                 has_intrinsics_covariance=s.intrinsics_covariance is not None)
        )
        if s.intrinsics is not None:
            arrays[f"intrinsics_{i}"] = np.asarray(s.intrinsics, float)
        if s.intrinsics_covariance is not None:  # a replay keeps the intrinsics' uncertainty term
            arrays[f"intrinsics_covariance_{i}"] = np.asarray(s.intrinsics_covariance, float)
    lo = problem.lidar_observations
    arrays["lidar_points"], arrays["lidar_counts"] = _concat([o.points for o in lo], (3,))
    arrays["lidar_planes"] = np.array([o.plane for o in lo], float).reshape(-1, 4)
    arrays["lidar_sensor_snapshot"] = np.array([(o.sensor, o.snapshot) for o in lo], np.int64).reshape(-1, 2)
    arrays["lidar_rms"] = np.array([o.rms_m for o in lo], float)
    has_idx = [o.indices is not None for o in lo]
    arrays["lidar_indices"], arrays["lidar_indices_counts"] = _concat(
        [o.indices for o in lo if o.indices is not None], (), np.int64)
    # optional (older version-2 dumps lack them): each point's ring, the edge intervals
    has_ring = [o.ring is not None for o in lo]
    arrays["lidar_rings"], arrays["lidar_rings_counts"] = _concat([o.ring for o in lo if o.ring is not None], (),
                                                                  np.int64)
    has_edges = [o.edge_rays is not None for o in lo]
    arrays["lidar_edge_rays"], arrays["lidar_edge_counts"] = _concat(
        [np.asarray(o.edge_rays, float).reshape(-1, 3, 3) for o in lo if o.edge_rays is not None], (3, 3))
    co = problem.camera_observations
    arrays["camera_corners"], arrays["camera_counts"] = _concat([o.corners_px for o in co], (2,))
    arrays["camera_sensor_snapshot"] = np.array([(o.sensor, o.snapshot) for o in co], np.int64).reshape(-1, 2)
    arrays["snapshot_stamps_ns"] = np.asarray(problem.snapshot_stamps_ns, np.int64)
    arrays["prior_sensor"] = np.array([p.sensor for p in problem.priors], np.int64)
    arrays["prior_rt"] = np.array([p.rt_lidar0_sensor for p in problem.priors], float).reshape(-1, 6)
    arrays["prior_sigma"] = np.array([p.sigma_rt for p in problem.priors], float).reshape(-1, 6)
    vis_keys = sorted(int(k) for k in problem.lidar_visibility_points)
    for k in vis_keys:
        arrays[f"visibility_{k}"] = np.asarray(problem.lidar_visibility_points[k], float)
    ring_keys = sorted(int(k) for k in problem.lidar_ring_offsets)
    for k in ring_keys:
        arrays[f"ring_offsets_{k}"] = np.asarray(problem.lidar_ring_offsets[k], float).reshape(-1, 2)
    b = problem.board
    meta = dict(
        format=FORMAT_NAME,
        version=FORMAT_VERSION,
        config=config.to_dict(),
        sensors=sensors,
        board=b.spec(),
        rejected=[dict(reason=r.reason, stage=r.stage, sensor=r.sensor, snapshot=r.snapshot)
                  for r in problem.rejected],
        lidar_has_indices=has_idx,
        lidar_has_rings=has_ring,
        lidar_has_edges=has_edges,
        visibility_sensors=vis_keys,
        ring_offset_sensors=ring_keys,
        snapshot_bags=[str(b) for b in problem.snapshot_bags],
    )
    arrays["meta"] = np.array(json.dumps(meta))
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp.npz")
    # stored, not deflated: deflate took 0.07 s of the report stage to save a quarter of 2.5 MB
    # (the 24-pose bench capture: float points do not compress); np.load reads both
    np.savez(tmp, **arrays)
    tmp.replace(path)
    log.info("wrote problem dump %s", path)


# optional members: (counts, data, (dtype kind, trailing shape) of data)
_OPTIONAL = (("lidar_rings_counts", "lidar_rings", ("i", ())), ("lidar_edge_counts", "lidar_edge_rays", ("f", (3, 3))))

# Limits for reading a dump (a zip of .npy members): float measurements do not compress 200-fold,
# so more than that (beyond a small allowance) is a zip bomb, refused before anything is inflated.
_MAX_MEMBERS = 10_000
_INFLATE_ALLOWANCE = 64 << 20
_MAX_INFLATE_RATIO = 200

# member name -> (dtype kind, trailing shape) of the fixed arrays; intrinsics_i, intrinsics_covariance_i,
# visibility_k and ring_offsets_k below
_LAYOUT = {
    "meta": ("U", None),
    "lidar_points": ("f", (3,)), "lidar_counts": ("i", ()), "lidar_planes": ("f", (4,)),
    "lidar_sensor_snapshot": ("i", (2,)), "lidar_rms": ("f", ()),
    "lidar_indices": ("i", ()), "lidar_indices_counts": ("i", ()),
    "camera_corners": ("f", (2,)), "camera_counts": ("i", ()), "camera_sensor_snapshot": ("i", (2,)),
    "snapshot_stamps_ns": ("i", ()),
    "prior_sensor": ("i", ()), "prior_rt": ("f", (6,)), "prior_sigma": ("f", (6,)),
}


def _read_members(path: Path) -> dict[str, np.ndarray]:
    """Every .npy member of the dump, each checked (no pickles, header consistent with its size)
    before it is read; total inflated size checked before any member is."""
    import zipfile

    try:
        zf = zipfile.ZipFile(path)
    except FileNotFoundError:
        raise InputError(f"{path}: no such problem dump") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a directory, not a problem dump (give DIR/problem.npz)") from None
    except (zipfile.BadZipFile, OSError, ValueError) as e:
        raise DataError(f"{path}: not a problem dump (not a complete .npz: {e})") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > _MAX_MEMBERS:
            raise DataError(f"{path}: not a problem dump ({len(infos)} members)")
        total = sum(i.file_size for i in infos)
        limit = _INFLATE_ALLOWANCE + _MAX_INFLATE_RATIO * path.stat().st_size
        if total > limit:
            raise DataError(f"{path}: members would inflate to {total} bytes from {path.stat().st_size} "
                            f"(more than {limit}); a zip bomb, not a problem dump")
        out = {}
        for info in infos:
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            try:
                with zf.open(info) as f:
                    version = np.lib.format.read_magic(f)
                    read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                        np.lib.format.read_array_header_2_0
                    shape, fortran, dtype = read_header(f)
                    if dtype.hasobject:
                        raise DataError(f"{path}: member {name!r} holds Python objects (a pickle); refused")
                    if dtype.itemsize == 0 or int(np.prod(shape, dtype=object)) * dtype.itemsize != info.file_size - f.tell():
                        raise DataError(f"{path}: member {name!r} header says {shape} {dtype}, which does not "
                                        f"match its {info.file_size} bytes")
                    f.seek(0)
                    out[name] = np.lib.format.read_array(f, allow_pickle=False)
            except DataError:
                raise
            except Exception as e:  # truncated, bad CRC, bad header: zipfile / numpy raise many kinds
                raise DataError(f"{path}: member {name!r} unreadable ({type(e).__name__}: "
                                f"{str(e).splitlines()[0] if str(e) else ''})") from None
        return out


def _check_layout(a: dict, meta: dict, path: Path) -> None:
    """Dtypes, shapes, counts and indices consistent with each other; DataError naming the first
    that is not (a tampered dump must not reach the solver as an IndexError or a wrong answer)."""
    from clcgraph import cameras
    from clcgraph.errors import DependencyError

    def bad(what):
        raise DataError(f"{path}: corrupt problem dump ({what})")

    for name, (kind, tail) in _LAYOUT.items():
        if name not in a:
            bad(f"no member {name!r}")
        x = a[name]
        if x.dtype.kind != kind and not (kind == "i" and x.dtype.kind == "u"):
            bad(f"{name!r} has dtype {x.dtype}")
        if tail is not None and (x.ndim != 1 + len(tail) or x.shape[1:] != tail):
            bad(f"{name!r} has shape {x.shape}, expected (N, {', '.join(map(str, tail))})".replace(", )", ")"))
    if not isinstance(meta.get("sensors"), list) or not meta["sensors"]:
        bad("no sensors")
    nsens, nsnap = len(meta["sensors"]), len(a["snapshot_stamps_ns"])
    kinds = []
    for i, sd in enumerate(meta["sensors"]):
        if not isinstance(sd, dict) or sd.get("kind") not in ("lidar", "camera") or not isinstance(sd.get("topic"), str):
            bad(f"sensor {i} is not a lidar or camera with a topic")
        kinds.append(sd["kind"])
        if sd["kind"] == "camera":
            size = sd.get("imagersize")
            if not (isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size)):
                bad(f"camera {sd['topic']} imagersize {size!r}")
            if not sd.get("has_intrinsics") or f"intrinsics_{i}" not in a:
                bad(f"camera {sd['topic']} has no intrinsics")
            x = a[f"intrinsics_{i}"]
            try:
                n = cameras.num_intrinsics(sd.get("lensmodel"))
            except DependencyError:
                raise
            except Exception:
                bad(f"camera {sd['topic']} lens model {sd.get('lensmodel')!r}")
            if x.dtype.kind != "f" or x.shape != (n,) or not np.all(np.isfinite(x)):
                bad(f"camera {sd['topic']} intrinsics {x.dtype} {x.shape} for {sd['lensmodel']} ({n})")
            if sd.get("has_intrinsics_covariance"):  # optional: older dumps have none
                c = a.get(f"intrinsics_covariance_{i}")
                if c is None or c.dtype.kind != "f" or c.shape != (n, n) or not np.all(np.isfinite(c)) \
                        or not np.allclose(c, c.T, rtol=1e-9, atol=0):
                    bad(f"camera {sd['topic']} intrinsics covariance is not a symmetric {n}x{n} matrix")
    if "lidar" not in kinds:
        bad("no LIDAR")

    def counts(name, data, n_obs):
        c = a[name]
        if len(c) != n_obs or np.any(c < 0) or int(c.sum()) != len(a[data]):
            bad(f"{name!r} do not add up to the {len(a[data])} rows of {data!r}")

    nl, nc = len(a["lidar_sensor_snapshot"]), len(a["camera_sensor_snapshot"])
    for name in ("lidar_planes", "lidar_rms"):
        if len(a[name]) != nl:
            bad(f"{name!r} has {len(a[name])} rows for {nl} LIDAR observations")
    counts("lidar_counts", "lidar_points", nl)
    counts("camera_counts", "camera_corners", nc)
    has_idx = meta.get("lidar_has_indices")
    if not isinstance(has_idx, list) or len(has_idx) != nl or not all(isinstance(h, bool) for h in has_idx):
        bad("lidar_has_indices")
    counts("lidar_indices_counts", "lidar_indices", sum(has_idx))
    for flags, (name, data, tail) in (("lidar_has_rings", _OPTIONAL[0]), ("lidar_has_edges", _OPTIONAL[1])):
        if flags not in meta:  # a dump written before they were kept
            continue
        has = meta[flags]
        if not isinstance(has, list) or len(has) != nl or not all(isinstance(h, bool) for h in has):
            bad(flags)
        for m, (kind, t) in ((name, ("i", ())), (data, tail)):
            if m not in a or a[m].dtype.kind not in (kind, "u" if kind == "i" else kind) or a[m].shape[1:] != t:
                bad(f"member {m!r}")
        counts(name, data, sum(has))
    if "lidar_edge_rays" in a and not np.all(np.isfinite(a["lidar_edge_rays"])):
        bad("non-finite values in 'lidar_edge_rays'")
    for name, kind in (("lidar_sensor_snapshot", "lidar"), ("camera_sensor_snapshot", "camera")):
        ss = a[name]
        if len(ss) and (ss[:, 0].min() < 0 or ss[:, 0].max() >= nsens or ss[:, 1].min() < 0 or ss[:, 1].max() >= nsnap):
            bad(f"{name!r} names sensor {int(ss[:, 0].max())} or snapshot {int(ss[:, 1].max())} "
                f"({nsens} sensors, {nsnap} snapshots)")
        if len(ss) and any(kinds[i] != kind for i in np.unique(ss[:, 0])):
            bad(f"{name!r} names a sensor that is not a {kind}")
    np_ = len(a["prior_sensor"])
    if len(a["prior_rt"]) != np_ or len(a["prior_sigma"]) != np_:
        bad("priors of different lengths")
    if np_ and (a["prior_sensor"].min() < 0 or a["prior_sensor"].max() >= nsens):
        bad(f"a prior names sensor {int(a['prior_sensor'].max())} ({nsens} sensors)")
    if not np.all(a["prior_sigma"] > 0) or not np.all(np.isfinite(a["prior_rt"])) or not np.all(np.isfinite(a["prior_sigma"])):
        bad("prior sigmas must be finite and positive")
    for name in ("lidar_points", "lidar_planes", "lidar_rms"):
        if not np.all(np.isfinite(a[name])):
            bad(f"non-finite values in {name!r}")
    if np.any(np.isinf(a["camera_corners"])):  # NaN marks a missing corner; inf is nothing
        bad("infinite camera corners")
    if len(a["lidar_indices"]) and a["lidar_indices"].min() < 0:
        bad("negative point indices")
    # per-sensor arrays: (meta key listing the sensors, member prefix, columns, what; older dumps have no ring offsets)
    for key, prefix, cols, what in (("visibility_sensors", "visibility", 3, "visibility points"),
                                    ("ring_offset_sensors", "ring_offsets", 2, "ring offsets")):
        ks = meta.get(key, [] if prefix == "ring_offsets" else None)
        if not isinstance(ks, list) or not all(isinstance(k, int) and 0 <= k < nsens for k in ks):
            bad(f"{key} {ks!r}")
        for k in ks:
            x = a.get(f"{prefix}_{k}")
            if x is None or x.dtype.kind != "f" or x.ndim != 2 or x.shape[1] != cols or not np.all(np.isfinite(x)):
                bad(f"{what} of sensor {k}")
    board = meta.get("board")
    if meta.get("version") == 1:  # corners_x, corners_y, spacing_m, margin_m
        ok = isinstance(board, dict) and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                             and np.isfinite(v) and v >= 0 for v in board.values())
    else:  # the config's board section, checked as the config checks it
        try:
            ok = isinstance(board, dict) and BoardOptions(**board) is not None
        except (ConfigError, TypeError):
            ok = False
    if not ok:
        bad(f"board {board!r}")


def load_problem(path: str | Path) -> tuple[Problem, Config]:
    """Read a dump written by save_problem -> (Problem, Config). InputError if missing; DataError
    (one line) if unreadable, truncated, a zip bomb, pickled, or inconsistent."""
    path = Path(path)
    a = _read_members(path)
    try:
        meta = json.loads(str(a["meta"])) if "meta" in a and a["meta"].dtype.kind == "U" and a["meta"].ndim == 0 else None
    except (json.JSONDecodeError, RecursionError):
        meta = None
    if not isinstance(meta, dict):
        raise DataError(f"{path}: not a clcgraph problem dump (no metadata)")
    if meta.get("format") != FORMAT_NAME:
        raise DataError(f"{path}: not a clcgraph problem dump (format {meta.get('format')!r})")
    if meta.get("version") not in _READABLE_VERSIONS:
        raise DataError(
            f"{path}: problem dump format version {meta.get('version')!r} is not supported "
            f"(this clcgraph reads versions {', '.join(map(str, _READABLE_VERSIONS))})"
        )
    _check_layout(a, meta, path)
    try:
        if meta["version"] == 1:
            meta = _upgrade_v1(meta, path)
        sensors = tuple(
            Sensor(topic=s["topic"], kind=s["kind"], lensmodel=s["lensmodel"],
                   intrinsics=a[f"intrinsics_{i}"] if s["has_intrinsics"] else None,
                   intrinsics_covariance=a[f"intrinsics_covariance_{i}"] if s.get("has_intrinsics_covariance") else None,
                   imagersize=None if s["imagersize"] is None else tuple(s["imagersize"]))
            for i, s in enumerate(meta["sensors"])
        )
        pts = _split(a["lidar_points"], a["lidar_counts"])
        idx = iter(_split(a["lidar_indices"], a["lidar_indices_counts"]))
        nl = len(a["lidar_sensor_snapshot"])

        def optional(flags, counts, data):  # per observation the array, or None (older dumps: all None)
            if flags not in meta:
                return [None] * nl
            it = iter(_split(a[data], a[counts]))
            return [next(it) if h else None for h in meta[flags]]

        rings = optional("lidar_has_rings", "lidar_rings_counts", "lidar_rings")
        edges = optional("lidar_has_edges", "lidar_edge_counts", "lidar_edge_rays")
        lidar = tuple(
            LidarBoardObservation(sensor=int(ss[0]), snapshot=int(ss[1]), points=p, plane=pl,
                                  rms_m=float(rms), indices=next(idx) if h else None, ring=rg, edge_rays=e)
            for ss, p, pl, rms, h, rg, e in zip(a["lidar_sensor_snapshot"], pts, a["lidar_planes"],
                                                a["lidar_rms"], meta["lidar_has_indices"], rings, edges)
        )
        camera = tuple(
            CameraBoardObservation(sensor=int(ss[0]), snapshot=int(ss[1]), corners_px=c)
            for ss, c in zip(a["camera_sensor_snapshot"], _split(a["camera_corners"], a["camera_counts"]))
        )
        priors = tuple(
            PosePrior(sensor=int(s), rt_lidar0_sensor=rt, sigma_rt=sg)
            for s, rt, sg in zip(a["prior_sensor"], a["prior_rt"], a["prior_sigma"])
        )
        problem = Problem(
            sensors=sensors,
            board=BoardGeometry.from_spec(**meta["board"]),
            lidar_observations=lidar,
            camera_observations=camera,
            snapshot_stamps_ns=a["snapshot_stamps_ns"],
            rejected=tuple(Rejected(**r) for r in meta["rejected"]),
            priors=priors,
            lidar_visibility_points={k: a[f"visibility_{k}"] for k in meta["visibility_sensors"]},
            lidar_ring_offsets={k: a[f"ring_offsets_{k}"] for k in meta.get("ring_offset_sensors", [])},
            snapshot_bags=tuple(str(b) for b in meta.get("snapshot_bags", ())),  # older dumps have none
        )
        config = Config.from_dict(meta["config"])
    except ConfigError as e:
        raise DataError(f"{path}: the dump's settings are not valid ({e})") from None
    except (KeyError, TypeError, ValueError) as e:
        raise DataError(f"{path}: corrupt problem dump ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from None
    return problem, config


def _upgrade_v1(meta: dict, path: Path) -> dict:
    """A version 1 dump's metadata in version 2 terms: its board (margin_m counted from the outer
    inner corners, pattern centred) as the physical board, in the config too."""
    old = meta["board"]
    if old["margin_m"] < old["spacing_m"]:
        raise DataError(f"{path}: a version 1 dump whose board margin ({old['margin_m']:g} m) is narrower than a square "
                        f"({old['spacing_m']:g} m) describes a board smaller than its pattern: calibrate again "
                        "with the board: section")
    board = {"corners": [old["corners_x"], old["corners_y"]], "square_m": old["spacing_m"],
             "size_m": [(old["corners_x"] - 1) * old["spacing_m"] + 2 * old["margin_m"],
                        (old["corners_y"] - 1) * old["spacing_m"] + 2 * old["margin_m"]],
             "pattern_offset_m": [0.0, 0.0]}
    config = dict(meta["config"])
    config["detection"] = {k: v for k, v in config.get("detection", {}).items()
                           if k not in ("corners_x", "corners_y", "spacing_m", "margin_m")}
    config["board"] = board
    return {**meta, "board": board, "config": config, "version": 2}
