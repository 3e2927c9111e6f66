"""The ``clcgraph`` command: parses arguments, calls the API, reports errors in one line.

Each subcommand is an ``_add_<name>(subparsers)`` that registers a parser whose
``func`` does its heavy imports inside, so ``clcgraph --help`` is instant.
Known errors (``ClcgraphError``) print one line and exit 2; anything else exits 1.
A traceback is printed only with ``--verbose``.
"""

from __future__ import annotations

import argparse
import logging
import sys

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
    p.add_argument("bags", nargs="+", metavar="BAG", help="ROS1 .bag files or ROS2 bag directories")

    def run(args):
        from .frontend.bag import POINTCLOUD2, bag_info, first_raw_message

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


@_command
def _add_targetless(sub):
    p = sub.add_parser("targetless", help="targetless LIDAR-LIDAR (and base_link-LIDAR) calibration from a drive")
    p.add_argument("--bag", action="append", required=True, metavar="BAG", help="bag file/dir (repeatable)")
    p.add_argument("--mapping-topic", required=True, help="the mapping LIDAR (reference, lidar0)")
    p.add_argument("--calibration-topics", required=True, help="comma-separated LIDAR topics to calibrate")
    p.add_argument("--base-frame", default=None, help="also calibrate base_link-LIDAR roll/pitch/z from the ground")
    p.add_argument("--out", required=True, help="output directory (replaced atomically)")
    p.add_argument("--config", default=None, help="YAML config (section 'targetless')")

    def run(args):
        from .config import Config, ConfigError
        from .errors import InputError
        from .targetless.pipeline import calibrate_targetless, write_targetless_outputs

        try:
            cfg = Config.from_yaml(args.config) if args.config else Config()
        except ConfigError as e:
            raise InputError(str(e)) from None
        topics = [t for t in args.calibration_topics.split(",") if t]
        res = calibrate_targetless(args.bag, mapping_topic=args.mapping_topic, calibration_topics=topics,
                                   base_frame=args.base_frame, config=cfg)
        paths = write_targetless_outputs(res, args.out, config=cfg)
        print(f"wrote {paths['calibration']}")
        return 0

    p.set_defaults(func=run)


@_command
def _add_replay(sub):
    p = sub.add_parser("replay", help="re-solve a problem dump (problem.npz), like the seed's fit-from-inputs-dump")
    p.add_argument("dump", help="problem.npz written with a calibration")
    p.add_argument("--inject-noise", action="store_true", help="re-noise the observations around the solve, re-solve")
    p.add_argument("--fit-seed", action="store_true", help="stop after the seed (initial estimate)")
    p.add_argument("--exclude", default="", help="comma-separated snapshot indices to leave out")
    p.add_argument("--seed", type=int, default=0, help="rng seed for --inject-noise")

    def run(args):
        import numpy as np

        from .errors import InputError
        from .outputs.dump import replay

        try:
            exclude = [int(k) for k in args.exclude.split(",") if k.strip()]
        except ValueError:
            raise InputError(f"--exclude: expected comma-separated integers, got '{args.exclude}'") from None
        res = replay(args.dump, inject_noise=args.inject_noise, fit_seed=args.fit_seed, exclude=exclude, seed=args.seed)
        for i, s in enumerate(res.problem.sensors):
            sd = res.stdev_rt(i) if np.all(np.isfinite(res.covariance_rt)) else np.full(6, np.nan)
            print(f"{s.topic}: rt_lidar0_sensor {np.array2string(res.rt_lidar0_sensor[i], precision=6)}"
                  f"  stdev {np.array2string(sd, precision=6)}")
        for k, v in res.noise.items():
            print(f"noise {k}: {v:.4g}")
        print(f"{len(res.rejected)} rejected")
        return 0

    p.set_defaults(func=run)


@_command
def _add_detect(sub):
    p = sub.add_parser("detect", help="chessboard detection in the images of a topic: found or rejected (why)")
    p.add_argument("bags", nargs="+", metavar="BAG", help="bag files/dirs")
    p.add_argument("--topic", required=True, help="the image topic")
    p.add_argument("--png", default=None, metavar="DIR", help="write an annotated PNG per image here")
    p.add_argument("--detector", default=None, choices=["mrgingham", "opencv"], help="override the config")
    p.add_argument("--every", action="store_true", help="every image, not just the first of each bag")
    p.add_argument("--config", default=None, help="YAML config (section 'detection')")

    def run(args):
        from dataclasses import replace
        from pathlib import Path

        import cv2
        import numpy as np

        from .config import Config, ConfigError
        from .errors import InputError
        from .frontend.camera_board import detect_in_bags, draw_detection

        try:
            cfg = Config.from_yaml(args.config) if args.config else Config()
        except ConfigError as e:
            raise InputError(str(e)) from None
        opts = cfg.detection if args.detector is None else replace(cfg.detection, detector=args.detector)
        outdir = Path(args.png) if args.png else None
        if outdir:
            outdir.mkdir(parents=True, exist_ok=True)
        nfound = ntotal = 0
        for k, (im, res) in enumerate(detect_in_bags(args.bags, args.topic, opts, every=args.every)):
            ntotal += 1
            if isinstance(res, np.ndarray):
                nfound += 1
                print(f"{im.stamp_ns * 1e-9:.6f} found {len(res)} corners")
            else:
                print(f"{im.stamp_ns * 1e-9:.6f} rejected: {res.reason}")
            if outdir:
                cv2.imwrite(str(outdir / f"{k:05d}_{im.stamp_ns}.png"), draw_detection(im, res))
        print(f"{nfound}/{ntotal} images with a chessboard")
        return 0

    p.set_defaults(func=run)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="clcgraph",
        description="Calibrate the extrinsics of a rig of LIDARs and cameras.",
    )
    parser.add_argument("--verbose", "-v", action="store_true", help="debug logging; tracebacks on errors")
    parser.add_argument("--quiet", "-q", action="store_true", help="only warnings and errors; no progress bars")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for add in _COMMANDS:
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO
    logging.basicConfig(level=level, format="%(message)s" if not args.verbose else "%(levelname)s %(name)s: %(message)s")
    from . import progress

    progress.set_enabled(not args.quiet)
    from .errors import ClcgraphError

    try:
        return int(args.func(args) or 0)
    except ClcgraphError as e:
        if args.verbose:
            log.exception("clcgraph %s failed", args.command)
        print(f"clcgraph {args.command}: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print(f"clcgraph {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # an internal error: still one line unless --verbose
        if args.verbose:
            log.exception("clcgraph %s: internal error", args.command)
        print(
            f"clcgraph {args.command}: internal error: {type(e).__name__}: {e} (rerun with --verbose for a traceback)",
            file=sys.stderr,
        )
        return 1


if __name__ == "__main__":
    sys.exit(main())
