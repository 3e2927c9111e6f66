"""Commands that look at bags before a calibration: show-bag, segment, detect, infer-lidar-spacing."""

from __future__ import annotations

from .common import add_command, config_args, floats, load_config, section_flags, section_overrides

_BAGS_HELP = "bag files/dirs, globs, or directories of bags"


def _show_bag(args) -> int:
    from .. import api
    from ..outputs.tables import bag_table

    paths = api.expand_bags(args.bags)
    for path in api.write_bag_previews(paths, args.png) if args.png else ():
        print(f"wrote {path}")
    for info, clouds in api.bag_summaries(paths):
        print(bag_table(info, clouds))
    return 0


def add_show_bag(sub):
    p = add_command(sub, "show-bag", run=_show_bag,
                    help="topics, types, counts, time spans and PointCloud2 layouts of bags")
    p.add_argument("bags", nargs="+", metavar="BAG",
                   help="ROS1 .bag files, ROS2 bag directories, globs, or directories of bags")
    p.add_argument("--png", default=None, metavar="DIR",
                   help="also draw each LIDAR's first scan and each camera's first image into DIR")


def _print_found(found: list, line, what: str) -> int:
    """One line per (item, result, bag name), then how many found something."""
    from ..outputs.tables import found_count

    for item, r, bag in found:
        print(line(item, r, bag))
    print(found_count(found, what))
    return 0


def _segment(args) -> int:
    from .. import api
    from ..outputs.tables import segmentation_line

    found = api.segment_bags(args.bags, args.topic, every=args.every, config=load_config(args), dump=args.dump,
                             png=args.png)
    return _print_found(found, segmentation_line, "scans with a board")


def add_segment(sub):
    from ..config import SegmentationOptions

    p = add_command(sub, "segment", run=_segment,
                    help="LIDAR board segmentation of a topic: the board's plane or why not, per scan")
    p.add_argument("bags", nargs="+", metavar="BAG", help=_BAGS_HELP + " (the scans the solve takes unless --every: the "
                   "first of each bag averaged with the next still ones, snapshots.max_scans_averaged; one per "
                   "still interval of a continuous bag, judged by this LIDAR)")
    p.add_argument("--topic", required=True, help="the PointCloud2 topic")
    p.add_argument("--every", action="store_true", help="every scan, each alone, not just those the solve takes")
    p.add_argument("--dump", default=None, metavar="FILE.npz",
                   help="intermediate stages: segments, clusters, candidate planes with verdicts, accepted points")
    p.add_argument("--png", default=None, metavar="DIR", help="a picture of each scan's segmentation here")
    config_args(p, "settings (sections 'board', 'lidar', 'segmentation', 'snapshots'; see `clcgraph config dump`)")
    p.add_argument("--debug-region", default=None, metavar="XMIN,XMAX,YMIN,YMAX",
                   help="report every candidate board plane in this region of the LIDAR's frame, with its verdict")
    seg_flags = section_flags(p, SegmentationOptions, "segmentation", "LIDAR segmentation")

    def overrides(a):
        region = [] if a.debug_region is None else \
            [("segmentation", "debug_region", floats(a.debug_region, 4, "--debug-region"))]
        return section_overrides(a, seg_flags) + region

    p.set_defaults(overrides=overrides)


def _detect(args) -> int:
    from .. import api
    from ..outputs.tables import detection_line

    found = api.detect_bags(args.bags, args.topic, every=args.every, config=load_config(args), png=args.png)
    return _print_found(found, detection_line, "images with a chessboard")


def add_detect(sub):
    p = add_command(sub, "detect", run=_detect,
                    help="chessboard detection in the images of a topic: found or rejected (why)",
                    overrides=lambda a: [("detection", "detector", a.detector)] if a.detector else [])
    p.add_argument("bags", nargs="+", metavar="BAG", help=_BAGS_HELP)
    p.add_argument("--topic", required=True, help="the image topic")
    p.add_argument("--png", default=None, metavar="DIR", help="write an annotated PNG per image here")
    p.add_argument("--detector", default=None, choices=["auto", "mrgingham", "opencv"], help="override the config")
    p.add_argument("--every", action="store_true", help="every image, not just the first of each bag")
    config_args(p, "settings (sections 'board', 'detection'; see `clcgraph config dump`)")


def _infer_lidar_spacing(args) -> int:
    from .. import api

    n_rings, npoints = api.infer_lidar_spacing(args.bags, args.topic)
    print(f"{args.topic}: {n_rings} rings, Npoints_per_rotation {npoints}")
    return 0


def add_infer_lidar_spacing(sub):
    p = add_command(sub, "infer-lidar-spacing", run=_infer_lidar_spacing,
                    help="number of rings and Npoints_per_rotation of a LIDAR topic")
    p.add_argument("bags", nargs="+", metavar="BAG", help=_BAGS_HELP)
    p.add_argument("--topic", required=True, help="the PointCloud2 topic")


COMMANDS = (add_show_bag, add_segment, add_detect, add_infer_lidar_spacing)
