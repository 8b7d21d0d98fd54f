"""tagloc replay: run the localiser over a recorded session."""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "replay"
HELP = "replay a session through the localiser (TUM trajectory, frame log, Rerun, metrics vs ground truth)"
DESCRIPTION = """Run the localiser over a session directory as fast as possible (or at the recorded rate with
--realtime). Writes the body trajectory (TUM), the per-frame JSON lines log and a Rerun recording on
request; prints accuracy metrics when the session has groundtruth.tum. Replays are deterministic:
the same session gives byte-identical TUM and log files.

examples:
  tagloc replay rec/ --out est.tum --log frames.jsonl
  tagloc replay sim/walk01 --rerun walk01.rrd      # then: rerun walk01.rrd
  tagloc replay logs/walk2s --bag out/walk2s.bag2  # a rosbag2 (MCAP) of poses, /tf and detections
  tagloc replay rec.bag --topic /cam/image_raw/compressed --map map.csv --rig rig.json --out est.tum"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("session", type=Path, help="session directory, or a rosbag2 directory / ROS 1 .bag with --topic")
    p.add_argument("--out", type=Path, metavar="FILE.tum", help="write the estimated body trajectory (TUM)")
    p.add_argument("--log", type=Path, metavar="FILE.jsonl", help="write the per-frame JSON lines log")
    p.add_argument("--log-times", action="store_true", help="add stage timings to the log (makes it vary run to run)")
    view = p.add_mutually_exclusive_group()
    view.add_argument("--rerun", type=Path, metavar="FILE.rrd", help="save a Rerun recording")
    view.add_argument("--spawn", action="store_true", help="stream to a new Rerun viewer")
    p.add_argument("--realtime", action="store_true", help="pace frames at their timestamps")
    p.add_argument("--png", type=Path, metavar="FILE.png", help="write the walk's floor plan as a PNG (matplotlib)")
    p.add_argument(
        "--publish",
        action="append",
        default=[],
        metavar="SINK",
        help="also publish poses: stdout | udp://HOST:PORT | mqtt://HOST[:PORT][/TOPIC] (repeatable)",
    )
    p.add_argument("--vest", default="replay", help="vest ID in published messages (default replay)")
    p.add_argument("--mode", default="full", choices=("full", "decoded-only", "orb-all"), help="localiser mode")
    p.add_argument(
        "--detector",
        default="contour",
        choices=("contour", "paper"),
        help="sticker detector: ours (contour, default) or the paper's ORB + k-means",
    )
    p.add_argument(
        "--decoder",
        default="zxing",
        choices=("zxing", "libdmtx", "both"),
        help="Data Matrix backend (default zxing; libdmtx needs the system library)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    b = p.add_argument_group("ROS bags")
    b.add_argument("--bag", type=Path, metavar="DIR", help="write a rosbag2 (MCAP): pose, /tf, detections")
    b.add_argument("--bag-images", action="store_true", help="also put the camera images and CameraInfo in --bag")
    b.add_argument("--topic", help="replaying a bag: its image topic (sensor_msgs/Image or CompressedImage)")
    b.add_argument("--map", type=Path, help="replaying a bag: the sticker map CSV")
    b.add_argument("--rig", type=Path, help="replaying a bag: rig JSON (default rig otherwise)")
    b.add_argument("--calibration", type=Path, help="replaying a bag: calibration YAML (overrides its CameraInfo)")
    b.add_argument("--info-topic", help="replaying a bag: CameraInfo topic (default: camera_info beside --topic)")


def run(args: argparse.Namespace) -> int:
    from tagloc.apps.replay import ReplayConfig, replay
    from tagloc.cli import checks
    from tagloc.io.rosbag import is_bag
    from tagloc.io.session import FRAMES_DIR, SESSION_INPUTS

    outputs = [("--out", args.out), ("--log", args.log), ("--rerun", args.rerun)]
    for option, path in outputs:
        checks.output_file(path, option)
    checks.output_file(args.png, "--png", suffixes=(".png",))
    checks.new_dir(args.bag, "--bag", "rosbag2 writes a new directory")
    outputs.append(("--png", args.png))
    outputs += checks.publish_files(args.publish)
    checks.outputs_apart(
        [*outputs, ("--bag", args.bag)],
        [*(args.session / name for name in SESSION_INPUTS), args.map, args.rig, args.calibration],
        [args.session / FRAMES_DIR] if args.session.is_dir() and not is_bag(args.session) else [args.session],
    )

    res = replay(
        ReplayConfig(
            session=args.session,
            out=args.out,
            log=args.log,
            log_times=args.log_times,
            rerun_save=args.rerun,
            spawn=args.spawn,
            realtime=args.realtime,
            publish=args.publish,
            vest=args.vest,
            mode=args.mode,
            detector=args.detector,
            decoder=args.decoder,
            progress=not args.quiet,
            bag=args.bag,
            bag_images=args.bag_images,
            topic=args.topic,
            map=args.map,
            rig=args.rig,
            calibration=args.calibration,
            info_topic=args.info_topic,
            png=args.png,
        )
    )
    print(res.format())
    return 0
