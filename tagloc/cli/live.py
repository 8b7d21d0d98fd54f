"""tagloc live: localise from a camera, stream or video file and publish every pose."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tagloc.core.errors import InputError

NAME = "live"
HELP = "localise live from a camera (or a video/stream/session played as one) and publish poses"
DESCRIPTION = """Localise from a camera, a stream URL, a video file or a session directory, and publish one
JSON pose (schema tagloc.pose/1) per frame to stdout, UDP and/or MQTT. Files and sessions are played
at their own rate, dropping frames when processing falls behind, as a camera would (--no-pace: every
frame, as fast as possible). A summary (frames, fixes, drops, latency) goes to stderr at the end.

Camera control (a camera index through V4L2, or picam[:N] through picamera2 on a Raspberry Pi):
--exposure-ms, --gain, --fps, --resolution; what the driver accepted is printed and written into
--record's session.json.

examples:
  tagloc live --camera 0 --config site/ --publish udp://10.0.0.5:9000 --vest v07
  tagloc live --camera 0 --camera 2 --rig front_rear/rig.json --map map.csv --publish stdout
  tagloc live --camera picam --exposure-ms 2 --gain 8 --fps 30 --resolution 1296x972 --config site/ --record rec/
  tagloc live --camera walk.avi --map map.csv --calibration cam.yaml --rig rig.json \\
      --publish stdout --publish mqtt://broker:1883/tagloc/v07/pose --record rec/ --rerun-save live.rrd
  tagloc live --camera 0 --config site/ --record-bag out/v07.bag2 --vest v07"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--camera",
        required=True,
        action="append",
        metavar="SRC",
        help="camera index (0), picam[:N], video file, stream URL or session directory; "
        "repeat for rig cameras 1, 2, ... (one capture thread each)",
    )
    p.add_argument("--config", type=Path, metavar="DIR", help="directory with camera.yaml, rig.json, map.csv")
    p.add_argument("--map", type=Path, help="sticker map CSV (overrides --config's)")
    p.add_argument("--calibration", type=Path, help="camera calibration YAML (overrides --config's)")
    p.add_argument("--rig", type=Path, help="rig JSON (overrides --config's)")
    p.add_argument(
        "--publish",
        action="append",
        default=[],
        metavar="SINK",
        help="stdout | udp://HOST:PORT | mqtt://HOST[:PORT][/TOPIC] | FILE.jsonl | FILE.tum (repeatable)",
    )
    p.add_argument("--vest", default="vest-1", help="operator/vest ID put in every message (default vest-1)")
    p.add_argument("--record", type=Path, metavar="DIR", help="record the processed frames as a session in DIR")
    p.add_argument("--log", type=Path, metavar="FILE", help="per-frame JSON lines log (observations and tracker)")
    p.add_argument("--rerun", action="store_true", help="stream to a new Rerun viewer")
    p.add_argument("--rerun-connect", metavar="URL", help="stream to a running Rerun viewer at URL")
    p.add_argument("--rerun-save", type=Path, metavar="FILE.rrd", help="save a Rerun recording")
    p.add_argument("--max-seconds", type=float, help="stop after this many seconds")
    p.add_argument("--max-frames", type=int, help="stop after this many processed frames")
    p.add_argument("--no-pace", action="store_true", help="files/sessions: process every frame, as fast as possible")
    p.add_argument(
        "--no-stride",
        action="store_true",
        help="never let the floor odometry skip frames, or its flow after frames sticker fixes placed, "
        "when processing falls behind the camera",
    )
    p.add_argument("--buffer", type=int, default=1, help="frames the capture thread keeps (default 1)")
    p.add_argument(
        "--max-age",
        type=float,
        default=0.5,
        metavar="S",
        help="never send a pose older than S seconds over UDP/MQTT (default 0.5; see the README's Reliability)",
    )
    p.add_argument("--exposure-ms", type=float, metavar="MS", help="manual exposure, ms (see tagloc advise)")
    p.add_argument("--gain", type=float, help="sensor gain (picam: analogue gain; V4L2: the driver's units)")
    p.add_argument("--fps", type=float, help="camera frame rate")
    p.add_argument("--resolution", metavar="WxH", help="camera resolution, e.g. 1296x972")
    p.add_argument("--mode", default="full", choices=("full", "decoded-only", "orb-all"), help="localiser mode")
    p.add_argument("--record-bag", type=Path, metavar="DIR", help="write a rosbag2 (MCAP): pose, /tf, detections")
    p.add_argument("--bag-images", action="store_true", help="also put the camera images and CameraInfo in the bag")


def _outputs_apart_from_inputs(args: argparse.Namespace, checks) -> None:
    """Refuse an output that would overwrite what the run reads: ``--log``, ``--rerun-save`` or a
    ``--publish`` file naming an input file, or ``--record`` / ``--record-bag`` naming a directory that holds inputs (a
    recording writes its own map.csv, rig.json and calibrations there)."""
    import os

    from tagloc.io.session import FRAMES_DIR, SESSION_INPUTS

    sources = [Path(c) for c in args.camera if Path(c).exists()]
    dirs = [d for d in (args.config, *(c for c in sources if c.is_dir())) if d is not None]
    files = [args.map, args.rig, args.calibration, *(c for c in sources if c.is_file())]
    files += [d / name for d in dirs for name in SESSION_INPUTS]
    checks.outputs_apart(
        [("--log", args.log), ("--rerun-save", args.rerun_save), *checks.publish_files(args.publish)],
        files,
        [d / FRAMES_DIR for d in dirs],
    )
    setup = [f for f in (args.map, args.rig, args.calibration) if f is not None]
    holding = {os.path.realpath(d) for d in dirs} | {os.path.realpath(Path(f).parent) for f in setup}
    for option, out in (("--record", args.record), ("--record-bag", args.record_bag)):
        if out is not None and os.path.realpath(out) in holding:
            raise InputError(f"{out}: {option} names a directory holding the run's inputs; choose a new one")


def run(args: argparse.Namespace) -> int:
    from tagloc.apps.live import LiveConfig, run_live
    from tagloc.cli import checks

    for option, path in (("--log", args.log), ("--rerun-save", args.rerun_save)):
        checks.output_file(path, option)
    checks.output_dir(args.record, "--record")
    checks.new_dir(args.record_bag, "--record-bag", "rosbag2 writes a new directory")
    _outputs_apart_from_inputs(args, checks)
    if args.rerun_connect:
        from tagloc.io.rerun_view import viewer_address

        viewer_address(args.rerun_connect)  # a malformed URL is refused before the reference bank is built
    if args.gain is not None:
        # No upper bound: the units are the driver's. CameraSettings takes any gain >= 0, infinity too.
        checks.number(args.gain, "--gain", 0)
    from tagloc.io.capture import CameraSettings, parse_resolution

    settings = CameraSettings(
        exposure_ms=args.exposure_ms,
        gain=args.gain,
        fps=args.fps,
        resolution=parse_resolution(args.resolution) if args.resolution else None,
    )

    summary = run_live(
        LiveConfig(
            source=args.camera[0],
            more_cameras=args.camera[1:],
            config_dir=args.config,
            map=args.map,
            calibration=args.calibration,
            rig=args.rig,
            publish=args.publish,
            vest=args.vest,
            record=args.record,
            log=args.log,
            rerun_spawn=args.rerun,
            rerun_connect=args.rerun_connect,
            rerun_save=args.rerun_save,
            max_seconds=args.max_seconds,
            max_frames=args.max_frames,
            pace=not args.no_pace,
            stride_when_behind=not args.no_stride,
            buffer=args.buffer,
            mode=args.mode,
            record_bag=args.record_bag,
            bag_images=args.bag_images,
            max_age_s=args.max_age,
            camera_settings=settings,
        )
    )
    print(summary.format(), file=sys.stderr)
    failure = summary.failure(", ".join(args.camera))
    if failure is not None:
        raise failure
    return 0
