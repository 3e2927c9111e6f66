"""Commands that use a calibration: format-for-ros, show-aligned, show-uncertainty, compare."""

from __future__ import annotations

from .common import add_command, add_force, config_args, floats, in_range, load_config, topics_list



def _bag_and_calibration(p, bag_help: str) -> None:
    p.add_argument("bag", help=bag_help)
    p.add_argument("--calibration", required=True, metavar="DIR", help="the --out directory of clcgraph solve or targetless")


def _format_for_ros(args) -> int:
    import sys

    from .. import api
    from ..outputs.ros import ros_yaml

    rt = None if args.rt_vehicle_lidar0 is None else floats(args.rt_vehicle_lidar0, 6, "--rt-vehicle-lidar0")
    ros, written = api.format_for_ros(args.bag, args.calibration, base_frame=args.base_frame, rt_vehicle_lidar0=rt,
                                      base_source=args.base_source, full_urdf=args.full_urdf, out=args.out,
                                      force=args.force)
    b = ros["base"]  # where base_link <- lidar0 came from: on stdout unless stdout is the YAML
    print(f"{b['parent_frame']} <- {b['child_frame']} from {b['source']}", file=sys.stdout if args.out else sys.stderr)
    for note in ros["notes"]:
        print(f"note: {note}", file=sys.stderr)
    for path in written:
        print(f"wrote {path}")
    if not args.out:
        print(ros_yaml(ros), end="")
    return 0


def add_format_for_ros(sub):
    from ..outputs.ros import BASE_SOURCES

    p = add_command(sub, "format-for-ros", run=_format_for_ros,
                    help="base_link-relative transforms of a calibration, for ROS (YAML, URDF, launch)")
    _bag_and_calibration(p, "a bag with the sensor topics (their frame_ids) and, unless base_link <- lidar0 "
                            "comes from elsewhere, /tf_static")
    p.add_argument("--base-frame", default="base_link", help="parent frame of the published transforms")
    p.add_argument("--rt-vehicle-lidar0", default=None, metavar="r0,r1,r2,t0,t1,t2",
                   help="base_link <- lidar0 as mrcal rt (Rodrigues [rad], then translation [m]); the default is "
                        "the calibration's own (targetless ground plane, solve's --rt-vehicle-lidar0), else /tf_static")
    p.add_argument("--base-source", default="auto", choices=list(BASE_SOURCES),
                   help="where base_link <- lidar0 comes from (auto: the first available, in that order)")
    p.add_argument("--full-urdf", action="store_true", help="also write sensors.urdf, a whole <robot> of these frames")
    p.add_argument("--out", default=None, metavar="DIR", help="write ros-transforms.yaml, URDF and launch snippets here")
    add_force(p)


def _show_aligned(args) -> int:
    from .. import api
    from ..errors import InputError
    from ..outputs.atomic import check_out_file

    if args.threshold_range is not None:
        in_range(args.threshold_range, "--threshold-range", 0, 1e5, low_open=True)
    if not args.mcap and args.snapshots:
        raise InputError("--snapshots chooses what goes into --mcap; give --mcap FILE.mcap")
    if (args.png or not args.mcap) and len(args.bags) > 1:  # before the MCAP: a refused PNG must leave none
        raise InputError(f"the PNG shows one bag, {len(args.bags)} given: give one (or --mcap alone for several)")
    if args.mcap:
        if args.png:  # api.show_aligned checks it too, but after the MCAP
            check_out_file(args.png, ".png", flag="--png", force=args.force)
        _write_mcap(args)
        if not args.png:
            return 0
    png = args.png or "aligned.png"
    aligned = api.show_aligned(args.bags[0], args.calibration, topics=topics_list(args.topics) if args.topics else None,
                               png=png, threshold_range=args.threshold_range, force=args.force)
    print(f"wrote {png}")
    if args.viewer:  # after the PNG is written and reported: a missing display fails only the viewer
        api.view_clouds(aligned, title="clcgraph show-aligned")
    return 0


def _write_mcap(args) -> None:
    from .. import api
    from ..outputs.tables import mcap_lines

    info = api.write_aligned_mcap(args.bags, args.calibration, args.mcap, force=args.force,
                                  snapshots=[k for k in (args.snapshots or "").split(",") if k.strip()],
                                  topics=topics_list(args.topics) if args.topics else None)
    print(mcap_lines(info))


def add_show_aligned(sub):
    p = add_command(sub, "show-aligned", run=_show_aligned,
                    help="LIDAR clouds of a bag aligned by a calibration: a PNG, or an MCAP file for Foxglove / RViz")
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
    add_force(p)
    p.add_argument("--threshold-range", type=float, default=None, metavar="M", help="drop points farther than this")
    p.add_argument("--viewer", action="store_true", help="also open the Open3D viewer (needs a display)")


def _show_uncertainty(args) -> int:
    from .. import api
    from ..errors import InputError

    in_range(args.radius, "--radius", 0, 1e5, low_open=True)
    in_range(args.gridn, "--gridn", 2, 2000)
    in_range(args.z, "--z", -1e5, 1e5)
    sensors = None
    if args.sensors:
        try:
            sensors = tuple(int(x) for x in args.sensors.split(","))
        except ValueError:
            sensors = ()
        if len(sensors) != 2:
            raise InputError(f"--sensors {args.sensors!r}: expected two indices I,J")
    title, stdev = api.uncertainty_grid_png(args.dump, args.png, sensors=sensors, radius=args.radius,
                                            gridn=args.gridn, z=args.z)
    print(f"{title}: worst-direction stdev {1e3 * stdev.min():.2f} .. {1e3 * stdev.max():.2f} mm; wrote {args.png}")
    return 0


def add_show_uncertainty(sub):
    p = add_command(sub, "show-uncertainty", run=_show_uncertainty,
                    help="worst-direction uncertainty of points moved between two sensors, over a grid (PNG)")
    p.add_argument("dump", help="problem.npz of a calibration (its --out directory or the file)")
    p.add_argument("--sensors", default=None, metavar="I,J", help="sensor indices (default: lidar0 and the worst other sensor)")
    p.add_argument("--radius", type=float, default=20.0, help="half-width of the grid (m)")
    p.add_argument("--gridn", type=int, default=41, help="grid points per side")
    p.add_argument("--z", type=float, default=0.0, help="height of the grid in lidar0 (m)")
    p.add_argument("--png", default="uncertainty.png", help="output picture")


def _compare(args) -> int:
    from .. import api
    from ..outputs.tables import comparison_table

    c = api.compare(args.a, args.b, config=load_config(args))
    if args.yaml:  # first: a refused file is the one line printed
        api.write_comparison_yaml(c, args.yaml)
    print(comparison_table(c))
    return 3 if args.fail_on_change and c.changed else 0


def add_compare(sub):
    p = add_command(sub, "compare", run=_compare,
                    help="has the calibration changed? per sensor: pose difference, chi-square test, verdict")
    p.add_argument("a", metavar="A", help="output directory or calibration.yaml of solve / targetless, or a bag (/tf_static)")
    p.add_argument("b", metavar="B", help="the same for the other calibration (B is compared with A)")
    p.add_argument("--yaml", default=None, metavar="FILE", help="also write the comparison as YAML, for scripts")
    p.add_argument("--fail-on-change", action="store_true", help="exit 3 if any sensor moved significantly")
    config_args(p, "settings (section 'compare'; see `clcgraph config dump`)")


COMMANDS = (add_format_for_ros, add_show_aligned, add_show_uncertainty, add_compare)
