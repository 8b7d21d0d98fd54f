"""tagloc session: convert recordings to the session layout."""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "session"
HELP = "convert a recording to a session directory (from-bag: a ROS 1 / rosbag2 camera topic)"
DESCRIPTION = """from-bag: read a camera topic (sensor_msgs/Image or CompressedImage) from a rosbag2 directory
(MCAP or SQLite) or a ROS 1 .bag and write it as a tagloc session: JPEG frames copied byte for byte,
other encodings as PNG, frame times from the image headers, calibration from the bag's CameraInfo
(beside the image topic, or --info-topic) unless --calibration is given, the map and rig copied in.
A recording made with an existing ROS camera driver then replays, evaluates and converts like any session.

examples:
  tagloc session from-bag rec.bag --topic /cam/image_raw/compressed --map map.csv --rig rig.json -o sessions/rec
  tagloc session from-bag rosbag2_2026_11_23/ --topic /camera/image_raw --map map.csv -o sessions/rec2"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    b = sub.add_parser(
        "from-bag",
        help="convert a bag's camera topic to a session",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="convert a bag's camera topic to a session\n\nexample:\n"
        "  tagloc session from-bag rec.bag --topic /cam/image_raw/compressed --map map.csv -o sessions/rec",
    )
    b.add_argument("bag", type=Path, help="rosbag2 directory or ROS 1 .bag file")
    b.add_argument("--topic", required=True, help="image topic, e.g. /cam/image_raw/compressed")
    b.add_argument("--map", type=Path, required=True, help="sticker map CSV")
    b.add_argument("--rig", type=Path, help="rig JSON (default: the default rig with the bag's calibration)")
    b.add_argument("--calibration", type=Path, help="calibration YAML (overrides the bag's CameraInfo)")
    b.add_argument("--info-topic", help="CameraInfo topic (default: camera_info beside --topic)")
    b.add_argument("-o", "--out", type=Path, required=True, help="session directory to create")
    b.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from tagloc.io.rosbag import bag_to_session

    written, skipped = bag_to_session(
        args.bag,
        args.topic,
        args.out,
        args.map,
        rig_path=args.rig,
        calibration=args.calibration,
        info_topic=args.info_topic,
        progress=not args.quiet,
    )
    print(
        f"{args.out}: {written} frames written, {skipped} skipped (corrupt, unsupported encoding, wrong size, wild stamp or not after the previous frame's time)"
    )
    return 0
