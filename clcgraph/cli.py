"""The ``clcgraph`` command: parses arguments, calls the API, reports errors in one line.

Each subcommand is an ``_add_<name>(subparsers)`` that registers a parser whose
``func`` does its heavy imports inside, so ``clcgraph --help`` is instant.
Known errors (``ClcgraphError``) print one line and exit 2; anything else exits 1.
A traceback is printed only with ``--verbose``.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from contextlib import contextmanager

log = logging.getLogger("clcgraph")


# ---------------------------------------------------------------- subcommands


# ---------------------------------------------------------------- main

_COMMANDS: list = []  # filled by the @_command decorator below each _add_* function


def _command(add):
    _COMMANDS.append(add)
    return add


# (subcommands using @_command must come after its definition)
@_command
def _add_show_bag(sub):
    p = sub.add_parser("show-bag", help="topics, types, counts, time spans and PointCloud2 layouts of bags")
    p.add_argument("bags", nargs="+", metavar="BAG",
                   help="ROS1 .bag files, ROS2 bag directories, globs, or directories of bags")
    p.add_argument("--png", default=None, metavar="DIR",
                   help="also draw each LIDAR's first scan and each camera's first image into DIR")

    def run(args):
        from .api import expand_bags
        from .frontend.bag import POINTCLOUD2, bag_info, first_raw_message

        args.bags = expand_bags(args.bags)
        if args.png:
            _bag_previews(args.bags, args.png)

        _DT = {1: "int8", 2: "uint8", 3: "int16", 4: "uint16", 5: "int32", 6: "uint32", 7: "float32", 8: "float64"}
        for path in args.bags:
            info = bag_info(path)
            print(f"{info.path}: {info.message_count} messages, {info.duration_s:.3f} s")
            rows = [("topic", "type", "count", "first [s]", "last [s]", "span [s]")]
            for t in info.topics:
                f = "-" if t.first_ns is None else f"{t.first_ns * 1e-9:.3f}"
                l = "-" if t.last_ns is None else f"{t.last_ns * 1e-9:.3f}"
                span = "-" if t.first_ns is None else f"{(t.last_ns - t.first_ns) * 1e-9:.3f}"
                rows.append((t.topic, t.msgtype, str(t.count), f, l, span))
            widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
            for r in rows:
                print("  " + "  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip())
            for t in info.topics:
                if t.msgtype != POINTCLOUD2 or t.count == 0:
                    continue
                m = first_raw_message(path, t.topic)
                print(
                    f"  {t.topic}: PointCloud2 {m.height} x {m.width}, point_step {m.point_step}, "
                    f"row_step {m.row_step}, {'big' if m.is_bigendian else 'little'} endian, frame {m.header.frame_id}"
                )
                for fld in m.fields:
                    dt = _DT.get(int(fld.datatype), f"datatype {fld.datatype}")
                    print(f"      {fld.name:<14} offset {fld.offset:>3}  {dt}" + (f" x{fld.count}" if fld.count != 1 else ""))
            print()
        return 0

    p.set_defaults(func=run)


def _bag_previews(bags, out_dir) -> None:
    from pathlib import Path

    from .frontend.bag import DECODABLE, bag_info, first_messages
    from .outputs.plots import plot_image_preview, plot_scan_preview
    from .types import LidarScan

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for path in bags:
        topics = [t.topic for t in bag_info(path).topics if t.msgtype in DECODABLE and t.count]
        for topic, m in first_messages(path, topics).items():
            name = out / f"{Path(path).stem}{topic.replace('/', '_')}.png"
            (plot_scan_preview if isinstance(m, LidarScan) else plot_image_preview)(
                m, name, title=f"{Path(path).name} {topic}")
            print(f"wrote {name}")


@_command
def _add_targetless(sub):
    p = sub.add_parser("targetless", help="targetless LIDAR-LIDAR (and base_link-LIDAR) calibration from a drive")
    p.add_argument("--bag", action="extend", nargs="+", required=True, metavar="BAG",
                   help="bag files/dirs or globs (repeatable; an unquoted glob the shell expanded works too)")
    p.add_argument("--mapping-topic", required=True, help="the mapping LIDAR (reference, lidar0)")
    p.add_argument("--calibration-topics", required=True, help="comma-separated LIDAR topics to calibrate")
    p.add_argument("--base-frame", default=None, help="also calibrate base_link-LIDAR roll/pitch/z from the ground")
    p.add_argument("--out", required=True, help="output directory: new, empty or an earlier output of this command (replaced whole)")
    _add_force(p)
    _config_args(p, "settings (section 'targetless'; see `clcgraph config dump`)")

    def run(args):
        from .api import check_out_dir
        from .targetless.pipeline import calibrate_targetless, summary_table, write_targetless_outputs

        cfg = _load_config(args)
        check_out_dir(args.out, force=args.force)  # before the drive is mapped, not after
        topics = [t for t in args.calibration_topics.split(",") if t]
        res = calibrate_targetless(args.bag, mapping_topic=args.mapping_topic, calibration_topics=topics,
                                   base_frame=args.base_frame, config=cfg)
        paths = write_targetless_outputs(res, args.out, config=cfg, force=args.force)
        print(summary_table(res))
        print(f"wrote {paths['calibration']} and {paths['report']}")
        return 0

    p.set_defaults(func=run)


@_command
def _add_replay(sub):
    p = sub.add_parser("replay", help="re-solve a problem dump (problem.npz), like the seed's fit-from-inputs-dump")
    p.add_argument("dump", help="problem.npz written with a calibration")
    p.add_argument("--inject-noise", action="store_true", help="re-noise the observations around the solve, re-solve")
    p.add_argument("--fit-seed", action="store_true", help="stop after the seed (initial estimate)")
    p.add_argument("--exclude", default="", metavar="K,BAG,...",
                   help="snapshots to leave out, comma-separated: indices or bag names (as calibration.yaml lists them)")
    p.add_argument("--seed", type=int, default=0, help="rng seed for --inject-noise")

    def run(args):
        import numpy as np

        from .errors import InputError
        from .outputs.dump import replay

        _in_range(args.seed, "--seed", 0, 2**63 - 1)
        exclude = [k.strip() for k in args.exclude.split(",") if k.strip()]  # indices or bag names
        res = replay(args.dump, inject_noise=args.inject_noise, fit_seed=args.fit_seed, exclude=exclude, seed=args.seed)
        for i, s in enumerate(res.problem.sensors):
            sd = res.stdev_rt(i) if np.all(np.isfinite(res.covariance_rt)) else np.full(6, np.nan)
            print(f"{s.topic}: rt_lidar0_sensor {np.array2string(res.rt_lidar0_sensor[i], precision=6, max_line_width=10**4)}"
                  f"  stdev {np.array2string(sd, precision=6, max_line_width=10**4)}")  # one line a sensor
        for k, v in res.noise.items():
            if isinstance(v, dict):  # per sensor: {sensor index: sigma}
                v = ", ".join(f"{res.problem.sensor_name(int(i))} {s:.4g}" for i, s in v.items())
                print(f"noise {k}: {v}")
            else:
                print(f"noise {k}: {v:.4g}")
        print(f"{len(res.rejected)} rejected")
        return 0

    p.set_defaults(func=run)


@_command
def _add_detect(sub):
    p = sub.add_parser("detect", help="chessboard detection in the images of a topic: found or rejected (why)")
    p.add_argument("bags", nargs="+", metavar="BAG", help="bag files/dirs, globs, or directories of bags")
    p.add_argument("--topic", required=True, help="the image topic")
    p.add_argument("--png", default=None, metavar="DIR", help="write an annotated PNG per image here")
    p.add_argument("--detector", default=None, choices=["auto", "mrgingham", "opencv"], help="override the config")
    p.add_argument("--every", action="store_true", help="every image, not just the first of each bag")
    _config_args(p, "settings (sections 'board', 'detection'; see `clcgraph config dump`)")

    def run(args):
        from pathlib import Path

        import cv2
        import numpy as np

        from .api import board_geometry, expand_bags
        from .frontend.camera_board import detect_in_bags, draw_detection

        cfg = _load_config(args)
        outdir = Path(args.png) if args.png else None
        if outdir:
            outdir.mkdir(parents=True, exist_ok=True)
        nfound = ntotal = 0
        for k, (im, res, bag) in enumerate(detect_in_bags(expand_bags(args.bags), args.topic, cfg.detection,
                                                          board_geometry(cfg), every=args.every, with_bag=True)):
            ntotal += 1
            where = f"{os.path.basename(str(bag).rstrip('/'))} {im.stamp_ns * 1e-9:.6f}"
            if isinstance(res, np.ndarray):
                nfound += 1
                print(f"{where} found {len(res)} corners")
            else:
                print(f"{where} rejected: {res.reason}")
            if outdir:
                cv2.imwrite(str(outdir / f"{k:05d}_{im.stamp_ns}.png"), draw_detection(im, res))
        print(f"{nfound}/{ntotal} images with a chessboard")
        return 0

    p.set_defaults(func=run, overrides=lambda a: [("detection", "detector", a.detector)] if a.detector else [])


@_command
def _add_segment(sub):
    from .config import SegmentationOptions

    p = sub.add_parser("segment", help="LIDAR board segmentation of a topic: the board's plane or why not, per scan")
    p.add_argument("bags", nargs="+", metavar="BAG",
                   help="bag files/dirs, globs, or directories of bags (one scan per bag unless --every)")
    p.add_argument("--topic", required=True, help="the PointCloud2 topic")
    p.add_argument("--every", action="store_true", help="every scan, not just the first of each bag")
    p.add_argument("--dump", default=None, metavar="FILE.npz",
                   help="intermediate stages: segments, clusters, candidate planes with verdicts, accepted points")
    p.add_argument("--png", default=None, metavar="DIR", help="a picture of each scan's segmentation here")
    _config_args(p, "settings (sections 'board', 'lidar', 'segmentation'; see `clcgraph config dump`)")
    p.add_argument("--debug-region", default=None, metavar="XMIN,XMAX,YMIN,YMAX",
                   help="report every candidate board plane in this region of the LIDAR's frame, with its verdict")
    seg_flags = _section_flags(p, SegmentationOptions, "segmentation", "LIDAR segmentation")

    def run(args):
        from pathlib import Path

        import numpy as np

        from .api import board_geometry
        from .frontend.lidar_board import Debug, segment_many
        from .outputs.plots import plot_segmentation
        from .types import LidarBoardObservation

        cfg = _load_config(args)
        bag_names: list = []
        scans = _lidar_scans(args.bags, args.topic, every=args.every, names=bag_names)
        board = board_geometry(cfg)
        outdir = Path(args.png) if args.png else None
        if outdir:
            outdir.mkdir(parents=True, exist_ok=True)
        debugs = [Debug() for _ in scans]
        results = segment_many(scans, cfg.segmentation, cfg.lidar, board, debug=debugs)
        dump, nfound = {}, 0
        for k, (scan, r, dbg) in enumerate(zip(scans, results, debugs)):
            t = f"{bag_names[k]} {scan.stamp_ns * 1e-9:.6f}"
            if isinstance(r, LidarBoardObservation):
                nfound += 1
                c = r.points.mean(axis=0)
                print(f"{t} board: {len(r.indices)} points at {np.linalg.norm(c):.2f} m, normal "
                      f"{np.round(r.plane[:3], 3).tolist()}, RMS {r.rms_m * 1e3:.1f} mm")
            else:
                print(f"{t} rejected: {r.reason}")
            if args.dump:
                dump[f"scan{k}_segments"] = dbg.segments if dbg.segments is not None else np.zeros((0, 2, 3))
                dump[f"scan{k}_segment_ring"] = dbg.segment_rank if dbg.segment_rank is not None else np.zeros(0)
                for j, ids in enumerate(dbg.clusters):
                    dump[f"scan{k}_cluster{j}_segments"] = ids
                for j, (idx, verdict) in enumerate(dbg.candidates):
                    dump[f"scan{k}_candidate{j}_points"] = idx
                    dump[f"scan{k}_candidate{j}_verdict"] = np.array(verdict)
                dump[f"scan{k}_accepted"] = dbg.accepted if dbg.accepted is not None else np.zeros(0, int)
            if outdir:
                plot_segmentation(scan, dbg, r, outdir / f"{k:05d}_{scan.stamp_ns}.png")
        if args.dump:
            np.savez_compressed(args.dump, **dump)
        print(f"{nfound}/{len(scans)} scans with a board")
        return 0

    def overrides(a):
        o = [(s_, k_, getattr(a, d_)) for d_, s_, k_ in seg_flags if getattr(a, d_) is not None]
        if a.debug_region is not None:
            o.append(("segmentation", "debug_region", _floats(a.debug_region, 4, "--debug-region")))
        return o

    p.set_defaults(func=run, overrides=overrides)


@_command
def _add_infer_lidar_spacing(sub):
    p = sub.add_parser("infer-lidar-spacing", help="number of rings and Npoints_per_rotation of a LIDAR topic")
    p.add_argument("bags", nargs="+", metavar="BAG", help="bag files/dirs, globs, or directories of bags")
    p.add_argument("--topic", required=True, help="the PointCloud2 topic")

    def run(args):
        from .frontend.lidar_preprocess import infer_lidar_spacing

        scans = _lidar_scans(args.bags, args.topic, limit=5)
        n_rings, npoints = infer_lidar_spacing(scans)
        print(f"{args.topic}: {n_rings} rings, Npoints_per_rotation {npoints}")
        return 0

    p.set_defaults(func=run)


@_command
def _add_demo(sub):
    p = sub.add_parser("demo", help="calibrate the shipped synthetic demo rig (simulated on first use) and "
                                    "compare with the simulator's truth")
    p.add_argument("--out", default=None, metavar="DIR", help="output directory (default data/synthetic/demo-out)")
    _add_force(p)
    _config_args(p)

    def run(args):
        from . import api
        from .sim.capture import DEMO_DIR

        result, errors = api.run_demo(args.out, config=_load_config(args), force=args.force)
        print(api.summary_table(result))
        print(f"\nagainst the simulator's truth ({DEMO_DIR}/truth.yaml):")
        # errors as one angle and one distance; their sigmas root-sum-square over the three axes
        print(f"{'sensor':34s} {'rotation error [deg]':>21s} {'1-sigma rss':>12s} {'translation error [mm]':>23s} "
              f"{'1-sigma rss':>12s}")
        for e in errors:
            print(f"{e['topic']:34s} {e['rotation_deg']:21.3f} {e['sigma_deg']:12.3f} {e['translation_mm']:23.1f} "
                  f"{e['sigma_mm']:12.1f}")
        print(f"wrote {args.out or DEMO_DIR.parent / 'demo-out'}/calibration.yaml and report.html")
        return 0

    p.set_defaults(func=run)


@_command
def _add_simulate(sub):
    p = sub.add_parser("simulate", help="simulate a capture session of a rig (YAML) into bags, with truth.yaml")
    p.add_argument("rig", metavar="RIG.yaml", help="the rig: LIDARs, cameras, board (see data/synthetic/demo-rig.yaml)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory: new, empty or an earlier output of this command (replaced whole)")
    _add_force(p)
    p.add_argument("--poses", type=int, default=20, help="number of board poses")
    p.add_argument("--format", default="ros1", choices=["ros1", "ros2-sqlite3", "ros2-mcap"], help="bag format")
    p.add_argument("--continuous", action="store_true", help="one continuous bag (the board moves between poses)")
    p.add_argument("--compress", action="store_true", help="lz4-compressed ROS1 bags")
    p.add_argument("--camera-hz", type=float, default=5.0, help="camera frame rate (LIDARs run at 10 Hz)")
    p.add_argument("--no-log-delays", action="store_true",
                   help="log time = header stamp (default: as drivers log, a scan ~0.1 s and a frame 20-35 ms late)")
    p.add_argument("--seed", type=int, default=0)

    def run(args):
        from . import api

        _in_range(args.poses, "--poses", 1, 10000)
        truth = api.simulate(args.rig, args.out, n_poses=args.poses, format=args.format,
                             continuous=args.continuous, seed=args.seed, compress=args.compress,
                             camera_hz=args.camera_hz, log_delays=not args.no_log_delays, force=args.force)
        print(f"wrote {len(truth['snapshots'])} board poses of {len(truth['sensors'])} sensors into {args.out} "
              f"(truth in {args.out}/truth.yaml)")
        b = truth["board"]
        print(f"board: {{corners: {b['corners']}, square_m: {b['square_m']}, size_m: {b['size_m']}, "
              f"pattern_offset_m: {b['pattern_offset_m']}}}  (the config's board: section to solve these bags)")
        return 0

    p.set_defaults(func=run)


@_command
def _add_simulate_drive(sub):
    p = sub.add_parser("simulate-drive", help="simulate a drive through a street (for clcgraph targetless), with truth.yaml")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory: drive bag + truth.yaml (new, empty or an earlier simulation; replaced whole)")
    _add_force(p)
    p.add_argument("--duration", type=float, default=60.0, help="seconds of driving at ~2 km/h")
    p.add_argument("--small", action="store_true", help="test-sized LIDARs (32/16 rings x 512 columns)")
    p.add_argument("--format", default="ros1", choices=["ros1", "ros2-sqlite3", "ros2-mcap"], help="bag format")
    p.add_argument("--layout", default="velodyne", choices=["velodyne", "ouster"],
                   help="point layout: unorganised with float time (velodyne) or organised with t in ns (ouster)")
    p.add_argument("--seed", type=int, default=0)

    def run(args):
        from pathlib import Path

        from .outputs.atomic import atomic_dir, check_out_dir
        from .progress import progress
        from .sim.drive import DrivePlan, simulate_drive, write_drive_bag, write_truth

        _in_range(args.duration, "--duration", 0, 3600, low_open=True)
        check_out_dir(args.out, kind="session", force=args.force)  # before the ray casting
        plan = DrivePlan.small(duration_s=args.duration) if args.small else DrivePlan(duration_s=args.duration)
        drive = simulate_drive(plan, seed=args.seed,
                               progress=lambda items, desc: progress(items, desc=desc, total=len(items), unit="scan"))
        out = Path(args.out)
        with atomic_dir(out, kind="session", force=args.force) as tmp:
            bag = tmp / ("drive.bag" if args.format == "ros1" else "drive")
            write_drive_bag(drive, bag, format=args.format, layout=args.layout)
            write_truth(drive, tmp / "truth.yaml")
        top, side = plan.lidars[0].topic, plan.lidars[1].topic
        print(f"wrote {out / bag.name} ({args.duration:.0f} s, {top} and {side}; /tf_static off by "
              f"{plan.guess_rot_deg:g} deg / {100 * plan.guess_trans_m:g} cm) and {out}/truth.yaml\n"
              f"calibrate it with: clcgraph targetless --bag {out / bag.name} --mapping-topic {top} "
              f"--calibration-topics {side} --base-frame base_link --out {out}-calib")
        return 0

    p.set_defaults(func=run)


def _lidar_scans(bags, topic: str, *, every: bool = False, limit: int | None = None, names: list | None = None) -> list:
    """The scans of a PointCloud2 topic: the first of each bag (or every one); InputError if the
    topic holds something else. ``names``: if given, filled with each scan's bag file name."""
    from .api import expand_bags
    from .errors import InputError
    from .frontend.bag import first_messages, read_messages
    from .types import LidarScan

    paths = expand_bags(bags)[:limit]
    if every:
        msgs = list(read_messages(paths, [topic]))
        scans, where = [m.data for m in msgs], [m.path for m in msgs]
    else:
        scans, where = [first_messages(b, [topic]).get(topic) for b in paths], paths
    if names is not None:
        names[:] = [os.path.basename(str(b).rstrip("/")) for b in where]
    bad = next((i for i, x in enumerate(scans) if not isinstance(x, LidarScan)), None)
    if bad is not None:
        where = paths[bad] if not every else ", ".join(map(str, paths))
        what = "no message" if scans[bad] is None else type(scans[bad]).__name__
        raise InputError(f"{where}: topic {topic} holds {what}, not sensor_msgs/PointCloud2")
    return scans


def _bags_and_models(bags: list[str], models: list[str]) -> tuple[list[str], list[str]]:
    """`--bag a.bag b.bag cam.cameramodel` (an unquoted glob, expanded by the shell, before the
    models): --bag takes every word up to the next option, so the .cameramodel files among them
    are models (in order, before the later ones); a bag among the models is an InputError hint."""
    from .errors import InputError

    is_model = [str(b).endswith(".cameramodel") for b in bags]
    models = [b for b, m in zip(bags, is_model) if m] + list(models)
    bags = [b for b, m in zip(bags, is_model) if not m]
    stray = [m for m in models if str(m).endswith((".bag", ".mcap", ".db3"))]
    if stray:
        raise InputError(f"{stray[0]} is a bag, given where the camera models go: put every bag after --bag "
                         "(or quote the glob: --bag 'capture/*.bag')")
    return bags, models


def _config_args(p, config_help: str = "settings (see `clcgraph config dump`)") -> None:
    """--config FILE and --set SECTION.KEY=VALUE, the same on every command that has a config
    (read by ``_load_config``)."""
    p.add_argument("--config", default=None, metavar="FILE.yaml", help=config_help)
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE",
                   help="override one config key, after --config and the command's flags (repeatable)")


def _load_config(args):
    """Config from --config, then the command's own flags, then --set KEY=VALUE (last wins)."""
    import yaml

    from .config import Config, ConfigError
    from .errors import InputError

    try:
        overrides: dict = {}
        cfg = Config.from_yaml(args.config) if getattr(args, "config", None) else Config()
        for section, key, value in getattr(args, "overrides", lambda a: [])(args):
            overrides.setdefault(section, {})[key] = value
        for item in getattr(args, "set", None) or []:
            name, sep, value = item.partition("=")
            section, dot, key = name.partition(".")
            if not sep or not dot:
                raise InputError(f"--set {item!r}: expected SECTION.KEY=VALUE, e.g. solve.outlier_sigma=5")
            overrides.setdefault(section, {})[key] = yaml.safe_load(value)
        return cfg.replace(**overrides) if overrides else cfg
    except ConfigError as e:
        key = getattr(e, "key", None)
        flags = [f"--set {item}" for item in getattr(args, "set", None) or [] if item.partition("=")[0] == key]
        section, _, name = (key or "").partition(".")
        if not flags and name in overrides.get(section, {}):  # set by one of the command's flags
            flags = [_FLAG_OF.get(key, "--" + name.replace("_", "-"))]
        raise InputError(f"{flags[-1]}: {e}" if flags else str(e)) from None


# config keys set by a differently named flag of `clcgraph solve` (section flags are named after their keys)
_FLAG_OF = {
    "snapshots.exclude_bag": "--exclude-bag", "snapshots.decimation_period_s": "--decimation-period",
    "snapshots.max_time_spread_s": "--max-time-spread-s", "sectors.n_sectors": "--Nsectors",
    "sectors.threshold_valid_lidar_range_m": "--threshold-valid-lidar-range",
    "sectors.threshold_valid_lidar_npoints": "--threshold-valid-lidar-Npoints",
    "sectors.uncertainty_quantification_range_m": "--uncertainty-quantification-range",
    "sectors.rt_vehicle_lidar0": "--rt-vehicle-lidar0", "solve.prior_from_tf_static_sigma_rad": "--prior-from-tf-static",
    "solve.prior_from_tf_static_sigma_m": "--prior-from-tf-static",
    "segmentation.debug_region": "--debug-region",
}


def _in_range(value, flag: str, lo, hi, *, low_open: bool = False):
    """``value`` of a command-line flag, or InputError naming the flag and its range [lo, hi]
    ((lo, hi] when ``low_open``); NaN and inf are outside every range."""
    import math

    from .errors import InputError

    ok = math.isfinite(value) and (value > lo if low_open else value >= lo) and value <= hi
    if not ok:
        raise InputError(f"{flag} {value!r}: must be in {'(' if low_open else '['}{lo}, {hi}]")
    return value


def _floats(text: str, n: int, flag: str) -> list:
    from .errors import InputError

    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != n:
        raise InputError(f"{flag} {text!r}: expected {n} comma-separated numbers")
    return v


def _add_force(p) -> None:
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it is not a previous clcgraph output of this command (its contents "
                        "are deleted); without it, --out must be new, empty or such an output")


def _section_flags(p, section_cls, section: str, group_title: str):
    """One --flag per field of a config section (names follow the config keys)."""
    import dataclasses
    import typing

    g = p.add_argument_group(group_title, f"override config '{section}' keys (see `clcgraph config dump`)")
    hints = typing.get_type_hints(section_cls)
    flags = []
    for f in dataclasses.fields(section_cls):
        tp = hints[f.name]
        base = next((a for a in typing.get_args(tp) if a is not type(None)), tp)
        if base is bool or base is list or typing.get_origin(base) is list:
            continue
        dest = f"{section}__{f.name}"
        g.add_argument("--" + f.name.replace("_", "-"), dest=dest, type=base, default=None, metavar=f.name.upper())
        flags.append((dest, section, f.name))
    return flags


@_command
def _add_solve(sub):
    from .config import SegmentationOptions

    p = sub.add_parser("solve", help="target-based calibration of LIDARs and cameras from bags (the clc fit)",
                       description="Calibrate LIDARs and cameras from bags of a moving chessboard. "
                       "Writes calibration.yaml, one .cameramodel per sensor, report.html and a replayable dump.")
    p.add_argument("models", nargs="*", metavar="MODEL.cameramodel", help="one per camera topic, in --topics order")
    p.add_argument("--bag", action="extend", nargs="+", required=True, metavar="GLOB",
                   help="bag files/dirs, globs, or directories of bags (repeatable; an unquoted glob the shell "
                        "expanded works too)")
    p.add_argument("--topics", required=True, help="comma-separated LIDAR and camera topics; the first LIDAR is lidar0")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory: new, empty or an earlier output of this command (replaced whole)")
    _add_force(p)
    _config_args(p)
    p.add_argument("--exclude-bag", default=None, metavar="BAG,K,...|REGEX",
                   help="leave out snapshots: comma-separated bag names and snapshot indices (as calibration.yaml "
                   "lists them; indices do not shift), or a regex: bags whose path matches are not read")
    p.add_argument("--decimation-period", type=float, default=None, metavar="S",
                   help="continuous bags: one snapshot per this many seconds")
    p.add_argument("--after", default=None, help="start time: s or ns since epoch, or a date")
    p.add_argument("--before", default=None, help="end time: s or ns since epoch, or a date")
    p.add_argument("--exclude-time-period", action="append", default=None, metavar="START,END",
                   help="skip this time period (repeatable)")
    p.add_argument("--max-time-spread-s", type=float, default=None, help="drop snapshots spread wider in time (default: no limit)")
    p.add_argument("--Nsectors", type=int, default=None, help="number of sectors of the uncertainty feedback")
    p.add_argument("--threshold-valid-lidar-range", type=float, default=None, metavar="M")
    p.add_argument("--threshold-valid-lidar-Npoints", type=int, default=None, metavar="N")
    p.add_argument("--uncertainty-quantification-range", type=float, default=None, metavar="M")
    p.add_argument("--rt-vehicle-lidar0", default=None, metavar="r0,r1,r2,t0,t1,t2")
    p.add_argument("--prior-from-tf-static", default=None, metavar="SIGMA_RAD,SIGMA_M",
                   help="nominal poses from the bags' /tf_static as priors with these 1-sigmas: rotation (rad) "
                   "and translation (m), per axis")
    p.add_argument("--detector", choices=["auto", "mrgingham", "opencv"], default=None,
                   help="chessboard detector (default auto: mrgingham for square grids, else OpenCV)")
    p.add_argument("--debug-region", default=None, metavar="XMIN,XMAX,YMIN,YMAX",
                   help="report every candidate board plane in this region of a LIDAR's frame, with its verdict")
    seg_flags = _section_flags(p, SegmentationOptions, "segmentation", "LIDAR segmentation")

    def overrides(args):
        o = [("snapshots", "exclude_bag", args.exclude_bag), ("snapshots", "decimation_period_s", args.decimation_period),
             ("snapshots", "after", args.after), ("snapshots", "before", args.before),
             ("snapshots", "exclude_time_periods", args.exclude_time_period),
             ("snapshots", "max_time_spread_s", args.max_time_spread_s),
             ("sectors", "n_sectors", args.Nsectors),
             ("sectors", "threshold_valid_lidar_range_m", args.threshold_valid_lidar_range),
             ("sectors", "threshold_valid_lidar_npoints", args.threshold_valid_lidar_Npoints),
             ("sectors", "uncertainty_quantification_range_m", args.uncertainty_quantification_range),
             ("detection", "detector", args.detector)]
        if args.prior_from_tf_static is not None:
            if "," not in args.prior_from_tf_static:
                from .errors import InputError

                raise InputError(f"--prior-from-tf-static {args.prior_from_tf_static!r}: give two sigmas, "
                                 "SIGMA_RAD,SIGMA_M (rotation in rad, translation in m), e.g. 0.02,0.05")
            rad, m = _floats(args.prior_from_tf_static, 2, "--prior-from-tf-static")
            o += [("solve", "prior_from_tf_static_sigma_rad", rad), ("solve", "prior_from_tf_static_sigma_m", m)]
        if args.rt_vehicle_lidar0 is not None:
            o.append(("sectors", "rt_vehicle_lidar0", _floats(args.rt_vehicle_lidar0, 6, "--rt-vehicle-lidar0")))
        if args.debug_region is not None:
            o.append(("segmentation", "debug_region", _floats(args.debug_region, 4, "--debug-region")))
        o += [(section, key, getattr(args, dest)) for dest, section, key in seg_flags]
        return [x for x in o if x[2] is not None]

    def run(args):
        from . import api

        cfg = _load_config(args)
        topics = [t for t in args.topics.split(",") if t.strip()]
        bags, models = _bags_and_models(args.bag, args.models)
        result = api.calibrate_bags(bags, topics, models, out=args.out, config=cfg, force=args.force)
        print(api.summary_table(result))
        print(f"wrote {args.out}/calibration.yaml and report.html")
        return 0

    p.set_defaults(func=run, overrides=overrides)


@_command
def _add_config(sub):
    p = sub.add_parser("config", help="print the default settings (`config dump`) or check a config file")
    p.add_argument("action", choices=["dump", "check"], help="dump: defaults as YAML; check: validate --config")
    _config_args(p, "start from this file")

    def run(args):
        cfg = _load_config(args)
        if args.action == "dump":
            print(cfg.to_yaml(comments=True), end="")
        else:
            print(f"{args.config or 'defaults'}: OK")
        return 0

    p.set_defaults(func=run)


@_command
def _add_format_for_ros(sub):
    p = sub.add_parser("format-for-ros", help="base_link-relative transforms of a calibration, for ROS (YAML, URDF, launch)")
    p.add_argument("bag", help="a bag with the sensor topics (their frame_ids) and, unless base_link <- lidar0 "
                               "comes from elsewhere, /tf_static")
    p.add_argument("--calibration", required=True, metavar="DIR", help="the --out directory of clcgraph solve or targetless")
    p.add_argument("--base-frame", default="base_link", help="parent frame of the published transforms")
    p.add_argument("--rt-vehicle-lidar0", default=None, metavar="r0,r1,r2,t0,t1,t2",
                   help="base_link <- lidar0 as mrcal rt (Rodrigues [rad], then translation [m]); the default is "
                        "the calibration's own (targetless ground plane, solve's --rt-vehicle-lidar0), else /tf_static")
    p.add_argument("--base-source", default="auto", choices=["auto", "rt-vehicle-lidar0", "calibration", "tf-static"],
                   help="where base_link <- lidar0 comes from (auto: the first available, in that order)")
    p.add_argument("--full-urdf", action="store_true", help="also write sensors.urdf, a whole <robot> of these frames")
    p.add_argument("--out", default=None, metavar="DIR", help="write ros-transforms.yaml, URDF and launch snippets here")
    _add_force(p)

    def run(args):
        from pathlib import Path

        import yaml

        from .frontend.bag import frame_id, read_tf_static
        from .outputs.results import load_result
        from .outputs.ros import format_for_ros, infer_frames, ros_files, ros_yaml

        cal = load_result(args.calibration)
        rt_given = None if args.rt_vehicle_lidar0 is None else _floats(args.rt_vehicle_lidar0, 6, "--rt-vehicle-lidar0")
        resolved = Path(args.calibration) / "config.resolved.yaml"  # the solve's own rt_vehicle_lidar0, if any
        solve_rt = ((yaml.safe_load(resolved.read_text()) or {}).get("sectors") or {}).get("rt_vehicle_lidar0") \
            if resolved.is_file() else None
        tf = read_tf_static(args.bag)
        topics = [s["topic"] for s in cal["sensors"]]
        # the messages' own frame_ids need not be in /tf_static when base_link <- lidar0 comes from elsewhere
        elsewhere = rt_given is not None or any(solve_rt or ()) or bool(cal.get("base_link"))
        frames = infer_frames(topics, tf.frames, frame_ids={t: frame_id(args.bag, t) for t in topics},
                              need_tf=args.base_source == "tf-static" or not elsewhere)
        ros = format_for_ros(cal, tf, base_frame=args.base_frame, frames=frames, rt_vehicle_lidar0=rt_given,
                             solve_rt_vehicle_lidar0=solve_rt, base_source=args.base_source, tf_name=str(args.bag))
        b = ros["base"]
        print(f"{b['parent_frame']} <- {b['child_frame']} from {b['source']}", file=sys.stderr if not args.out else sys.stdout)
        for note in ros["notes"]:
            print(f"note: {note}", file=sys.stderr)
        if args.out:
            from .outputs.atomic import atomic_dir

            files = ros_files(ros, full_urdf=args.full_urdf)
            with atomic_dir(args.out, kind="ros", force=args.force) as tmp:
                for name, text in files.items():
                    (tmp / name).write_text(text)
            for name in files:
                print(f"wrote {Path(args.out) / name}")
        else:
            print(ros_yaml(ros), end="")
        return 0

    p.set_defaults(func=run)


@_command
def _add_show_aligned(sub):
    p = sub.add_parser("show-aligned", help="LIDAR clouds of a bag aligned by a calibration: a PNG, or an MCAP "
                                            "file for Foxglove / RViz")
    p.add_argument("bags", nargs="+", metavar="BAG", help="the bag to show (its first scan of each LIDAR); with --mcap, "
                                                          "bag files, globs or directories to take --snapshots from")
    p.add_argument("--calibration", required=True, metavar="DIR", help="the --out directory of clcgraph solve or targetless")
    p.add_argument("--topics", default=None, help="comma-separated LIDAR topics (default: every LIDAR of the calibration; "
                                                  "with --mcap every sensor)")
    p.add_argument("--png", default=None, help="output picture (default aligned.png unless --mcap)")
    p.add_argument("--mcap", default=None, metavar="FILE.mcap",
                   help="write /tf_static from the calibration and the clouds and images of --snapshots (ROS 2 "
                        "messages, each in its sensor's frame) for Foxglove or `ros2 bag play` + RViz")
    p.add_argument("--snapshots", default=None, metavar="K,BAG,...",
                   help="with --mcap: snapshot indices (as calibration.yaml lists them) or bag names (default: every bag)")
    _add_force(p)
    p.add_argument("--threshold-range", type=float, default=None, metavar="M", help="drop points farther than this")
    p.add_argument("--viewer", action="store_true", help="also open the Open3D viewer (needs a display)")

    def run(args):
        import os

        import numpy as np

        from .errors import InputError
        from .frontend.bag import first_messages
        from .outputs.plots import align_clouds, render_aligned_clouds
        from .outputs.results import load_result

        if args.threshold_range is not None:
            _in_range(args.threshold_range, "--threshold-range", 0, 1e5, low_open=True)
        if args.mcap:
            from .export_mcap import write_aligned_mcap

            info = write_aligned_mcap(args.bags, args.calibration, args.mcap, force=args.force,
                                      snapshots=[k for k in (args.snapshots or "").split(",") if k.strip()],
                                      topics=[t for t in (args.topics or "").split(",") if t] or None)
            print(f"/tf_static: {info['base_source']}")
            print(f"wrote {args.mcap}: {len(info['snapshots'])} snapshot(s) ("
                  f"{', '.join(s['bag'] for s in info['snapshots'][:5])}{', ...' if len(info['snapshots']) > 5 else ''}), "
                  f"/tf_static with {len(info['tf'])} transforms")
            if not args.png:
                return 0
        elif args.snapshots:
            raise InputError("--snapshots chooses what goes into --mcap; give --mcap FILE.mcap")
        if len(args.bags) > 1:
            raise InputError(f"the PNG shows one bag, {len(args.bags)} given: give one (or --mcap for several)")
        args.bag = args.bags[0]
        args.png = args.png or "aligned.png"
        cal = load_result(args.calibration)
        by_topic = {s["topic"]: s for s in cal["sensors"]}
        topics = [t for t in args.topics.split(",") if t] if args.topics else \
            [s["topic"] for s in cal["sensors"] if s["kind"] == "lidar"]
        missing = [t for t in topics if t not in by_topic]
        if missing:
            raise InputError(f"{missing[0]} is not a sensor of the calibration in {args.calibration}")
        first = first_messages(args.bag, topics)
        clouds = {}
        for t in topics:
            if t not in first:
                raise InputError(f"{args.bag}: no message on {t}")
            pts = first[t].points[first[t].valid]
            if args.threshold_range is not None:
                pts = pts[np.linalg.norm(pts, axis=1) < args.threshold_range]
            clouds[t] = pts
        rts = {t: by_topic[t]["rt_lidar0_sensor"] for t in topics}
        render_aligned_clouds(clouds, rts, args.png)
        print(f"wrote {args.png}")
        if args.viewer:
            if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
                raise InputError("--viewer needs a display (DISPLAY is not set); the PNG was written")
            import open3d as o3d

            geoms = []
            for k, (t, pts) in enumerate(align_clouds(clouds, rts).items()):
                pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
                pc.paint_uniform_color(np.eye(3)[k % 3] * 0.8)
                geoms.append(pc)
            o3d.visualization.draw_geometries(geoms, window_name="clcgraph show-aligned")
        return 0

    p.set_defaults(func=run)


@_command
def _add_show_uncertainty(sub):
    p = sub.add_parser("show-uncertainty", help="worst-direction uncertainty of points moved between two sensors, over a grid (PNG)")
    p.add_argument("dump", help="problem.npz of a calibration (its --out directory or the file)")
    p.add_argument("--sensors", default=None, metavar="I,J", help="sensor indices (default: lidar0 and the worst other sensor)")
    p.add_argument("--radius", type=float, default=20.0, help="half-width of the grid (m)")
    p.add_argument("--gridn", type=int, default=41, help="grid points per side")
    p.add_argument("--z", type=float, default=0.0, help="height of the grid in lidar0 (m)")
    p.add_argument("--png", default="uncertainty.png", help="output picture")

    def run(args):
        from pathlib import Path

        import numpy as np

        from .backend.sectors import uncertainty_grid
        from .errors import InputError
        from .outputs.dump import replay
        from .outputs.plots import plot_uncertainty_grid

        _in_range(args.radius, "--radius", 0, 1e5, low_open=True)
        _in_range(args.gridn, "--gridn", 2, 2000)
        _in_range(args.z, "--z", -1e5, 1e5)
        path = Path(args.dump)
        if path.is_dir():
            cal = path / "calibration.yaml"
            if not (path / "problem.npz").exists() and cal.exists() and "method: targetless" in cal.read_text():
                raise InputError(f"{path}: a targetless calibration has no sector uncertainty (that needs "
                                 "`clcgraph solve`'s problem.npz); its 1-sigmas are in calibration.yaml and report.html")
            path = path / "problem.npz"
        res = replay(path)
        n = len(res.problem.sensors)
        if args.sensors:
            try:
                i, j = (int(x) for x in args.sensors.split(","))
            except ValueError:
                raise InputError(f"--sensors {args.sensors!r}: expected two indices I,J") from None
            if not (0 <= i < n and 0 <= j < n and i != j):
                raise InputError(f"--sensors {args.sensors}: need two different indices in 0..{n - 1}")
        else:
            i = res.problem.reference
            j = max((k for k in range(n) if k != i), key=lambda k: np.trace(res.covariance_block(k)[3:, 3:]))
        xs, ys, stdev = uncertainty_grid(res, i, j, radius=args.radius, gridn=args.gridn, z=args.z)
        title = f"{res.problem.sensor_name(i)} -> {res.problem.sensor_name(j)}"
        plot_uncertainty_grid(stdev, xs, ys, args.png, title=title)
        print(f"{title}: worst-direction stdev {1e3 * stdev.min():.2f} .. {1e3 * stdev.max():.2f} mm; wrote {args.png}")
        return 0

    p.set_defaults(func=run)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="clcgraph",
        description="Calibrate the extrinsics of a rig of LIDARs and cameras.",
    )
    parser.add_argument("--verbose", "-v", action="store_true", help="debug logging; tracebacks on errors")
    parser.add_argument("--quiet", "-q", action="store_true",
                        help="only warnings and errors, no progress (the default when stderr is not a terminal)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for add in _COMMANDS:
        add(sub)
    return parser


class _Terminated(BaseException):
    """SIGTERM, raised in the main thread like KeyboardInterrupt so that cleanups run."""


_EXIT_ON_SIGNAL = {signal.SIGINT: 130, signal.SIGTERM: 143}  # the shells' 128 + signal number


@contextmanager
def _signals_raise(received: list):
    """SIGINT -> KeyboardInterrupt, SIGTERM -> _Terminated, recording which came (a worker may
    turn the interruption into another exception); the previous handlers are put back."""

    def handler(signum, frame):
        received.append(signum)
        raise KeyboardInterrupt if signum == signal.SIGINT else _Terminated

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    saved = {s: signal.signal(s, handler) for s in _EXIT_ON_SIGNAL}
    try:
        yield
    finally:
        for s, h in saved.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


def main(argv: list[str] | None = None) -> int:
    # OpenMP workers (small_gicp, Open3D) otherwise spin after each parallel region and, on a
    # 2-core machine, starve the Python code between registrations (mapping ran 15-20 % slower).
    # A default for this process only, set before any OpenMP runtime loads; a user's value wins.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    parser = build_parser()
    args = parser.parse_args(argv)
    # progress notes are for someone watching: piped or logged runs get warnings and errors only
    quiet = args.quiet or not sys.stderr.isatty()
    level = logging.DEBUG if args.verbose else logging.WARNING if quiet else logging.INFO
    logging.basicConfig(level=level, format="%(message)s" if not args.verbose else "%(levelname)s %(name)s: %(message)s")
    from . import progress

    progress.set_enabled(not args.quiet)
    from .errors import ClcgraphError

    received: list[int] = []
    try:
        with _signals_raise(received):
            return int(args.func(args) or 0)
    except (KeyboardInterrupt, _Terminated, Exception) as e:
        return _failure(args, e, received)


def _failure(args, e: BaseException, received: list) -> int:
    """One line on stderr for a command that did not finish (a traceback only with --verbose)."""
    from .errors import ClcgraphError

    if received or isinstance(e, KeyboardInterrupt):
        if args.verbose:
            log.error("clcgraph %s interrupted", args.command, exc_info=e)
        signum = received[0] if received else signal.SIGINT
        left = "; nothing half-written in --out" if getattr(args, "out", None) else ""
        print(f"clcgraph {args.command}: interrupted by {signal.Signals(signum).name}{left}", file=sys.stderr)
        return _EXIT_ON_SIGNAL[signum]
    if isinstance(e, ClcgraphError):
        if args.verbose:
            log.error("clcgraph %s failed", args.command, exc_info=e)
        print(f"clcgraph {args.command}: error: {e}", file=sys.stderr)
        return e.exit_code
    if args.verbose:  # an internal error: still one line unless --verbose
        log.error("clcgraph %s: internal error", args.command, exc_info=e)
    hint = "" if args.verbose else " (rerun with --verbose for a traceback)"
    print(f"clcgraph {args.command}: internal error: {type(e).__name__}: {e}{hint}", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
