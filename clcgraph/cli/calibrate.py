"""Commands that calibrate: solve, targetless, replay, demo, config."""

from __future__ import annotations

from .common import (add_command, add_force, config_args, floats, in_range, load_config, section_flags,
                     section_overrides, topics_list)


def _print_result(result, out) -> int:
    from ..outputs.tables import summary_table

    print(summary_table(result))
    print(f"wrote {out}/calibration.yaml and report.html")
    return 0


def _solve(args) -> int:
    from .. import api

    bags, models = api.bags_and_models(args.bag, args.models)
    result = api.calibrate_bags(bags, topics_list(args.topics), models, out=args.out,
                                config=load_config(args), force=args.force)
    return _print_result(result, args.out)


def _solve_overrides(args, seg_flags) -> list:
    """(section, key, value) of the flags of `clcgraph solve` that were given."""
    from ..errors import InputError

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
            raise InputError(f"--prior-from-tf-static {args.prior_from_tf_static!r}: give two sigmas, "
                             "SIGMA_RAD,SIGMA_M (rotation in rad, translation in m), e.g. 0.02,0.05")
        rad, m = floats(args.prior_from_tf_static, 2, "--prior-from-tf-static")
        o += [("solve", "prior_from_tf_static_sigma_rad", rad), ("solve", "prior_from_tf_static_sigma_m", m)]
    if args.rt_vehicle_lidar0 is not None:
        o.append(("sectors", "rt_vehicle_lidar0", floats(args.rt_vehicle_lidar0, 6, "--rt-vehicle-lidar0")))
    if args.debug_region is not None:
        o.append(("segmentation", "debug_region", floats(args.debug_region, 4, "--debug-region")))
    return [x for x in o if x[2] is not None] + section_overrides(args, seg_flags)


def add_solve(sub):
    from ..config import SegmentationOptions

    p = add_command(sub, "solve", run=_solve, help="target-based calibration of LIDARs and cameras from bags (the clc fit)",
                    description="Calibrate LIDARs and cameras from bags of a moving chessboard. "
                    "Writes calibration.yaml, one .cameramodel per sensor, report.html and a replayable dump.")
    p.add_argument("models", nargs="*", metavar="MODEL",
                   help="one camera model per camera topic, in --topics order: an mrcal .cameramodel, a ROS camera "
                        "calibration .yaml (camera_calibration's ost.yaml: plumb_bob, rational_polynomial or "
                        "equidistant), or camera_info: the camera's CameraInfo in the bags (/ns/image_raw -> "
                        "/ns/camera_info); none: every camera's CameraInfo")
    p.add_argument("--bag", action="extend", nargs="+", required=True, metavar="GLOB",
                   help="bag files/dirs, globs, or directories of bags (repeatable; an unquoted glob the shell "
                        "expanded works too)")
    p.add_argument("--topics", required=True, help="comma-separated LIDAR and camera topics; the first LIDAR is lidar0")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory: new, empty or an earlier output of this command (replaced whole)")
    add_force(p)
    config_args(p)
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
    seg_flags = section_flags(p, SegmentationOptions, "segmentation", "LIDAR segmentation")
    p.set_defaults(overrides=lambda args: _solve_overrides(args, seg_flags))


def _targetless(args) -> int:
    from .. import api

    from ..errors import InputError

    calibration_topics = topics_list(args.calibration_topics)
    if args.mapping_topic in calibration_topics:
        raise InputError(f"--calibration-topics: {args.mapping_topic} is the mapping topic (the reference); "
                         "name the other LIDARs")
    result = api.calibrate_targetless(args.bag, mapping_topic=args.mapping_topic,
                                      calibration_topics=calibration_topics,
                                      base_frame=args.base_frame, out=args.out, config=load_config(args),
                                      force=args.force)
    return _print_result(result, args.out)


def add_targetless(sub):
    p = add_command(sub, "targetless", run=_targetless,
                    help="targetless LIDAR-LIDAR (and base_link-LIDAR) calibration from a drive")
    p.add_argument("--bag", action="extend", nargs="+", required=True, metavar="BAG",
                   help="bag files/dirs or globs (repeatable; an unquoted glob the shell expanded works too)")
    p.add_argument("--mapping-topic", required=True, help="the mapping LIDAR (reference, lidar0)")
    p.add_argument("--calibration-topics", required=True, help="comma-separated LIDAR topics to calibrate")
    p.add_argument("--base-frame", default=None, help="also calibrate base_link-LIDAR roll/pitch/z from the ground")
    p.add_argument("--out", required=True, help="output directory: new, empty or an earlier output of this command (replaced whole)")
    add_force(p)
    config_args(p, "settings (section 'targetless'; see `clcgraph config dump`)")


def _replay(args) -> int:
    from ..api import replay
    from ..outputs.tables import replay_lines

    in_range(args.seed, "--seed", 0, 2**63 - 1)
    exclude = [k.strip() for k in args.exclude.split(",") if k.strip()]  # indices or bag names
    print(replay_lines(replay(args.dump, inject_noise=args.inject_noise, fit_seed=args.fit_seed, exclude=exclude,
                              seed=args.seed)))
    return 0


def add_replay(sub):
    p = add_command(sub, "replay", run=_replay,
                    help="re-solve a problem dump (problem.npz), like the seed's fit-from-inputs-dump")
    p.add_argument("dump", help="problem.npz written with a calibration (or its --out directory)")
    p.add_argument("--inject-noise", action="store_true", help="re-noise the observations around the solve, re-solve (the LIDARs' "
                   "board outlines are not re-drawn: a sample has their planes alone, and its sigmas are those)")
    p.add_argument("--fit-seed", action="store_true", help="stop after the seed (initial estimate)")
    p.add_argument("--exclude", default="", metavar="K,BAG,...",
                   help="snapshots to leave out, comma-separated: indices or bag names (as calibration.yaml lists them)")
    p.add_argument("--seed", type=int, default=0, help="rng seed for --inject-noise")


def _demo(args) -> int:
    from .. import api
    from ..outputs.tables import summary_table, truth_table
    from ..sim.capture import DEMO_DIR

    result, errors = api.run_demo(args.out, config=load_config(args), force=args.force)
    print(summary_table(result))
    print(truth_table(errors, DEMO_DIR / "truth.yaml"))
    print(f"wrote {args.out or DEMO_DIR.parent / 'demo-out'}/calibration.yaml and report.html")
    return 0


def add_demo(sub):
    p = add_command(sub, "demo", run=_demo, help="calibrate the shipped synthetic demo rig (simulated on first use) and "
                                                 "compare with the simulator's truth")
    p.add_argument("--out", default=None, metavar="DIR", help="output directory (default data/synthetic/demo-out)")
    add_force(p)
    config_args(p)


def _config(args) -> int:
    cfg = load_config(args)
    print(cfg.to_yaml(comments=True) if args.action == "dump" else f"{args.config or 'defaults'}: OK\n", end="")
    return 0


def add_config(sub):
    p = add_command(sub, "config", run=_config, help="print the default settings (`config dump`) or check a config file")
    p.add_argument("action", choices=["dump", "check"], help="dump: defaults as YAML; check: validate --config")
    config_args(p, "start from this file")


COMMANDS = (add_solve, add_targetless, add_replay, add_demo, add_config)
