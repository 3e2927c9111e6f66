"""Commands that simulate: simulate (a rig's capture session), simulate-drive (for targetless)."""

from __future__ import annotations

from .common import add_command, add_force, in_range


def _simulate(args) -> int:
    from .. import api

    in_range(args.poses, "--poses", 1, 10000)
    in_range(args.pair_boards, "--pair-boards", 0, args.poses)
    truth = api.simulate(args.rig, args.out, n_poses=args.poses, format=args.format,
                         continuous=args.continuous, seed=args.seed, compress=args.compress,
                         camera_hz=args.camera_hz, log_delays=not args.no_log_delays,
                         planned_tilts=args.planned_tilts, pair_boards=args.pair_boards, force=args.force)
    print(f"wrote {len(truth['snapshots'])} board poses of {len(truth['sensors'])} sensors into {args.out} "
          f"(truth in {args.out}/truth.yaml)")
    b = truth["board"]
    print(f"board: {{corners: {b['corners']}, square_m: {b['square_m']}, size_m: {b['size_m']}, "
          f"pattern_offset_m: {b['pattern_offset_m']}}}  (the config's board: section to solve these bags)")
    return 0


def add_simulate(sub):
    p = add_command(sub, "simulate", run=_simulate,
                    help="simulate a capture session of a rig (YAML) into bags, with truth.yaml")
    p.add_argument("rig", metavar="RIG.yaml", help="the rig: LIDARs, cameras, board (see data/synthetic/demo-rig.yaml)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory: new, empty or an earlier output of this command (replaced whole)")
    add_force(p)
    p.add_argument("--poses", type=int, default=20, help="number of board poses")
    p.add_argument("--format", default="ros1", choices=["ros1", "ros2-sqlite3", "ros2-mcap"], help="bag format")
    p.add_argument("--continuous", action="store_true", help="one continuous bag (the board moves between poses)")
    p.add_argument("--compress", action="store_true",
                   help="compressed bags: ROS1 lz4 chunks, ROS2 the storage file zstd-compressed (.db3.zstd, .mcap.zstd)")
    p.add_argument("--camera-hz", type=float, default=5.0, help="camera frame rate (LIDARs run at 10 Hz)")
    p.add_argument("--no-log-delays", action="store_true",
                   help="log time = header stamp (default: as drivers log, a scan ~0.1 s and a frame 20-35 ms late)")
    p.add_argument("--planned-tilts", action="store_true",
                   help="boards tilted as a careful person plans them: pitched up and down, turned left and right "
                        "in turn (default: each about a random axis)")
    p.add_argument("--pair-boards", type=int, default=0, metavar="N",
                   help="hold the board so that every pair of sensors sees it together on >= N poses, as a careful "
                        "capture does (pairs that can never see it together left out; default 0: wherever any two "
                        "sensors see it)")
    p.add_argument("--seed", type=int, default=0)


def _simulate_drive(args) -> int:
    from .. import api

    in_range(args.duration, "--duration", 0, 3600, low_open=True)
    bag, plan = api.simulate_drive(args.out, duration_s=args.duration, small=args.small, format=args.format,
                                   layout=args.layout, seed=args.seed, force=args.force)
    top, side = plan.lidars[0].topic, plan.lidars[1].topic
    print(f"wrote {bag} ({args.duration:.0f} s, {top} and {side}; /tf_static off by "
          f"{plan.guess_rot_deg:g} deg / {100 * plan.guess_trans_m:g} cm) and {args.out}/truth.yaml\n"
          f"calibrate it with: clcgraph targetless --bag {bag} --mapping-topic {top} "
          f"--calibration-topics {side} --base-frame base_link --out {args.out}-calib")
    return 0


def add_simulate_drive(sub):
    p = add_command(sub, "simulate-drive", run=_simulate_drive,
                    help="simulate a drive through a street (for clcgraph targetless), with truth.yaml")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory: drive bag + truth.yaml (new, empty or an earlier simulation; replaced whole)")
    add_force(p)
    p.add_argument("--duration", type=float, default=60.0, help="seconds of driving at ~2 km/h")
    p.add_argument("--small", action="store_true", help="test-sized LIDARs (32/16 rings x 512 columns)")
    p.add_argument("--format", default="ros1", choices=["ros1", "ros2-sqlite3", "ros2-mcap"], help="bag format")
    p.add_argument("--layout", default="velodyne", choices=["velodyne", "ouster"],
                   help="point layout: unorganised with float time (velodyne) or organised with t in ns (ouster)")
    p.add_argument("--seed", type=int, default=0)


COMMANDS = (add_simulate, add_simulate_drive)
