"""tagloc simulate: render a walking session over a sticker map, with ground truth."""

from __future__ import annotations

import argparse
from pathlib import Path

SENSOR_CHOICES = ("standard", "ov5647")  # tagloc.sim.render.SENSOR_PRESETS (not imported: --help stays fast)

NAME = "simulate"
HELP = "simulate a walking session over a sticker map (frames + ground truth)"
DESCRIPTION = """Simulate an operator walking along the map's sticker lines with the vest camera, and write a
session directory (frames/, frames.csv, map.csv, rig.json, camera.yaml, session.json) with
groundtruth.tum (body pose per frame) and groundtruth_frames.jsonl (camera pose, exposure, gain,
blur and every visible sticker's true image corners per frame).

The images are formed physically: floor reflectance, illuminance (lux) and f-number give photons;
motion-priority auto exposure (t = 0.3 lux*s / lux, capped), motion blur from the true motion
during the exposure, shot and read noise, gain, vignetting, lens distortion, gamma and JPEG.

Field conditions (all seeded): a rolling shutter, the driver's timestamp jitter and dropped frames,
a map with survey error (the frames show the true stickers), a dimmer sensor, flickering lamps,
the operator's own shadow under a grid of overhead lamps, the wearer's legs and feet in view.

example:
  tagloc simulate --map maps/demo.csv --seconds 20 --lux 100 --speed 1.3 --seed 1 -o logs/sim1
  tagloc simulate --map maps/demo.csv --seconds 20 --seed 1 --rolling-shutter --jitter-ms 2 \\
      --drop-fraction 0.04 --drop-bursts-per-min 3 --survey-sigma-cm 1 --survey-sigma-deg 1.5 \\
      --sensor ov5647 -o logs/field1
  tagloc simulate --map maps/demo.csv --seconds 20 --seed 1 --lux 300 --rolling-shutter \\
      --flicker 30 -o logs/flicker1        # fluorescent tubes on magnetic ballasts, 50 Hz mains
  tagloc simulate --map maps/demo.csv --seconds 20 --seed 1 --lux 300 --shadow -o logs/shadow1
  tagloc simulate --map maps/demo.csv --seconds 20 --seed 1 --pitch 65 --legs -o logs/legs1"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--map", required=True, type=Path, help="sticker map CSV (id,x_m,y_m,yaw_deg)")
    p.add_argument("-o", "--out", required=True, type=Path, help="session directory to create")
    p.add_argument("--seconds", type=float, default=20.0, help="session length, s (default 20)")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate (default 30)")
    p.add_argument("--lux", type=float, default=100.0, help="illuminance on the floor, lux (default 100)")
    p.add_argument("--speed", type=float, default=1.3, help="nominal walking speed, m/s (default 1.3)")
    p.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    p.add_argument("--pitch", type=float, default=55.0, help="camera pitch below horizontal, degrees (default 55)")
    p.add_argument("--height", type=float, default=1.3, help="camera height above the floor, m (default 1.3)")
    p.add_argument("--rolling-shutter", action="store_true", help="rows exposed at staggered times (see --readout-ms)")
    p.add_argument("--readout-ms", type=float, default=30.0, help="rolling shutter: top-to-bottom read-out, ms (30)")
    p.add_argument("--jitter-ms", type=float, default=0.0, help="timestamp jitter, uniform +-ms (default 0)")
    p.add_argument("--drop-fraction", type=float, default=0.0, help="share of frames lost on their own (default 0)")
    p.add_argument(
        "--drop-bursts-per-min", type=float, default=0.0, help="bursts of 3-8 lost frames per minute (default 0)"
    )
    p.add_argument(
        "--survey-sigma-cm", type=float, default=0.0, help="map survey error per sticker, cm per axis (default 0)"
    )
    p.add_argument("--survey-sigma-deg", type=float, default=0.0, help="map survey yaw error per sticker, deg (0)")
    p.add_argument("--survey-stated", action="store_true", help="state the survey sigmas in the map's columns")
    p.add_argument(
        "--sensor", choices=SENSOR_CHOICES, default="standard", help="sensor model (default standard; ov5647: dimmer)"
    )
    p.add_argument(
        "--distractors",
        type=float,
        default=0.05,
        help="dark squares (8-15 cm) on the floor per square metre (default 0.05)",
    )
    p.add_argument(
        "--missing-fraction",
        type=float,
        default=0.0,
        help="share of the map's stickers absent from the floor (default 0)",
    )
    p.add_argument("--unmapped", type=int, default=0, help="stickers on the floor that are not in the map (default 0)")
    p.add_argument(
        "--flicker",
        type=float,
        default=0.0,
        help="lamps' percent flicker at twice the mains frequency (default 0: steady; 8 is IEEE 1789's"
        " low-risk limit at 100 Hz, 20-40 magnetic-ballast fluorescents)",
    )
    p.add_argument("--mains-hz", type=float, default=50.0, help="mains frequency, Hz (default 50; 60 in the Americas)")
    p.add_argument(
        "--shadow",
        action="store_true",
        help="the operator's own shadow under high-bay lamps 6 m apart, 9 m up (default: no shadow)",
    )
    p.add_argument(
        "--legs",
        action="store_true",
        help="the wearer's legs and feet, stepping with the gait, where the camera sees them (default: none)",
    )
    p.add_argument(
        "--gait-scale",
        type=float,
        default=1.0,
        help="the walker's gait motions (bobbing, sway, torso twist and roll, pitch wobble) times this "
        "(default 1; 2: a walker who swings twice as much)",
    )
    p.add_argument(
        "--floor-contrast",
        type=float,
        default=1.0,
        help="the concrete's texture contrast times this (default 1: worn, unsealed concrete; 0.5, 0.25:"
        " sealed, polished or epoxy-coated floors), what the floor odometry tracks",
    )
    p.add_argument("--jpeg-quality", type=int, default=85, help="JPEG quality of the frames (default 85)")
    p.add_argument("--scale", type=float, default=1.0, help="image resolution factor (default 1: 1296x972)")
    p.add_argument("--calibration", type=Path, help="true camera calibration (OpenCV or ROS YAML); default Pi v1")
    p.add_argument("--rig", type=Path, help="rig.json to use instead of --height/--pitch (every camera rendered)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _out_apart_from_inputs(args: argparse.Namespace) -> None:
    """Refuse ``-o`` naming a directory that holds the run's map, rig or calibration: the session
    writes its own map.csv (with survey error, a perturbed one), rig.json and camera.yaml (scaled
    by ``--scale``) there, over the files it reads."""
    import os

    from tagloc.core.errors import InputError

    holding = {os.path.realpath(Path(f).parent) for f in (args.map, args.rig, args.calibration) if f is not None}
    if os.path.realpath(args.out) in holding:
        raise InputError(f"{args.out}: -o names a directory holding the run's inputs; choose a new one")


def run(args: argparse.Namespace) -> int:
    from tagloc.cli import checks
    from tagloc.sim.floor import FloorConfig
    from tagloc.sim.render import ExposureConfig
    from tagloc.sim.simulate import SimConfig, simulate_session
    from tagloc.sim.survey import SurveyConfig
    from tagloc.sim.timing import TimingConfig
    from tagloc.sim.walk import GAIT_SCALE_RANGE, WalkConfig

    for option, value in (
        ("--seconds", args.seconds),
        ("--lux", args.lux),
        ("--speed", args.speed),
        ("--pitch", args.pitch),
        ("--height", args.height),
        ("--scale", args.scale),
    ):
        checks.sim_option(value, option)
    checks.number(args.fps, "--fps", 0, 240, lo_open=True)
    checks.seed(args.seed)
    checks.number(args.distractors, "--distractors", 0, 100)
    checks.number(args.unmapped, "--unmapped", 0, 10_000)
    checks.number(args.jpeg_quality, "--jpeg-quality", 1, 100)
    checks.number(args.flicker, "--flicker", 0, 100)
    checks.number(args.mains_hz, "--mains-hz", 0, 1000, lo_open=True)
    checks.number(args.readout_ms, "--readout-ms", 0, 1000)
    checks.number(args.jitter_ms, "--jitter-ms", 0, 1000)
    checks.number(args.drop_fraction, "--drop-fraction", 0, 1, hi_open=True)
    # Ten bursts of 3 or more frames a second leave a 30 fps camera no frame.
    checks.number(args.drop_bursts_per_min, "--drop-bursts-per-min", 0, 600)
    checks.number(args.survey_sigma_cm, "--survey-sigma-cm", 0, 100)
    checks.number(args.survey_sigma_deg, "--survey-sigma-deg", 0, 180)
    checks.number(args.missing_fraction, "--missing-fraction", 0, 1)
    checks.number(args.gait_scale, "--gait-scale", *GAIT_SCALE_RANGE)
    checks.number(args.floor_contrast, "--floor-contrast", 0, 2)
    checks.output_dir(args.out, "-o")
    _out_apart_from_inputs(args)

    summary = simulate_session(
        args.map,
        args.out,
        SimConfig(
            seconds=args.seconds,
            fps=args.fps,
            lux=args.lux,
            speed_mps=args.speed,
            seed=args.seed,
            pitch_deg=args.pitch,
            height_m=args.height,
            rolling_shutter=args.rolling_shutter,
            jpeg_quality=args.jpeg_quality,
            distractors_per_m2=args.distractors,
            missing_fraction=args.missing_fraction,
            unmapped=args.unmapped,
            scale=args.scale,
            calibration=args.calibration,
            rig=args.rig,
            exposure=ExposureConfig(readout_s=args.readout_ms * 1e-3),
            sensor_preset=args.sensor,
            timing=TimingConfig(
                jitter_s=args.jitter_ms * 1e-3,
                drop_fraction=args.drop_fraction,
                bursts_per_min=args.drop_bursts_per_min,
            ),
            survey=SurveyConfig(args.survey_sigma_cm * 1e-2, args.survey_sigma_deg, args.survey_stated),
            flicker=args.flicker / 100.0,
            mains_hz=args.mains_hz,
            shadow=args.shadow,
            legs=args.legs,
            walk=WalkConfig().with_gait_scale(args.gait_scale),
            floor=FloorConfig(texture_contrast=args.floor_contrast),
        ),
        progress=not args.quiet,
    )
    print(
        f"{summary.path}: {summary.frames} frames in {summary.wall_s:.1f} s; exposure {summary.exposure_s * 1e3:.2f} ms,"
        f" gain {summary.gain:.1f}, blur {summary.blur_px:.1f} px (mean)"
    )
    return 0
