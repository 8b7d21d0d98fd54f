"""tagloc eval: tagloc and the paper's baselines over simulated walks."""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "eval"
HELP = "evaluate tagloc and the paper's baselines on simulated walking sessions"
DESCRIPTION = """Simulate walks, run tagloc and the two baselines on the same frames, print the table
and write a Markdown report with PNG plots.

Presets: standard (default) draws --sessions walks over the condition ranges (50-300 lux,
0.8-1.6 m/s, stickers 1.2-2.0 m apart, camera pitch 45-70 deg); field runs a fixed set of walks
with rolling shutter, jittered and dropped frames, survey error, missing/unmapped stickers, a 90 s
walk and a dim-sensor walk; all runs both (into OUT/standard and OUT/field) and prints both
summaries. two-camera renders three fixed 20 s walks with a front-down + rear-down rig and compares
one camera (the front one's frames alone) against both: time with a sticker in view, RMSE, NEES.

With --walks, sessions one already has (each with groundtruth.tum: walks recorded on a site, or
rendered by another simulator) are scored the same way instead; nothing is simulated.

examples:
  tagloc eval --sessions 6 --seconds 20 -o out/eval
  tagloc eval --preset all --modes full -o out/eval
  tagloc eval --preset field --scale 0.5 --modes full -o out/eval-half
  tagloc eval --preset field --gait-scale 2 --modes full -o out/eval-gait2
  tagloc eval --preset two-camera -o out/eval/two_camera
  tagloc eval --walks site/walks --modes full -o out/eval-site"""


# The options that choose a preset's walks, with their defaults: beside --walks, which scores the
# sessions given, any of them set otherwise is refused.
PRESET_OPTIONS = {
    "--preset": "standard",
    "--sessions": 6,
    "--seconds": 20.0,
    "--seed": 1,
    "--scale": 1.0,
    "--gait-scale": 1.0,
    "--no-hard": False,
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--preset",
        choices=("standard", "field", "all", "two-camera"),
        default=PRESET_OPTIONS["--preset"],
        help="set of walks (default standard)",
    )
    p.add_argument(
        "--sessions",
        type=int,
        default=PRESET_OPTIONS["--sessions"],
        help="number of simulated sessions (standard; default 6)",
    )
    p.add_argument(
        "--seconds",
        type=float,
        default=PRESET_OPTIONS["--seconds"],
        help="length of each session, s (standard; default 20)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=PRESET_OPTIONS["--seed"],
        help="seed for the scenario conditions (standard; default 1); field: other than 1, held-out walks "
        "with the field walks' conditions and fresh seeds",
    )
    p.add_argument(
        "--modes",
        default="full,decoded-only,orb-all",
        help="comma-separated localiser modes (default: full,decoded-only,orb-all; also full-live: "
        "tagloc in tagloc live's order, each frame's odometry step and least-squares decodes after "
        "its pose is published)",
    )
    p.add_argument(
        "--scale",
        type=float,
        default=PRESET_OPTIONS["--scale"],
        help="standard, field: every walk's camera at this resolution factor (default 1: 1296x972; 0.5: 648x486)",
    )
    p.add_argument(
        "--gait-scale",
        type=float,
        default=PRESET_OPTIONS["--gait-scale"],
        help="standard, field: every walker's gait motions (bobbing, sway, torso twist and roll, pitch wobble) "
        "times this (default 1: the simulator's walker; 2: a walker who swings twice as much)",
    )
    p.add_argument(
        "--walks",
        type=Path,
        nargs="+",
        metavar="DIR",
        help="score these sessions (or the sessions in these directories) instead of a preset's walks",
    )
    p.add_argument(
        "--no-hard",
        action="store_true",
        default=PRESET_OPTIONS["--no-hard"],
        help="no missing/unmapped stickers in the odd sessions (standard)",
    )
    p.add_argument("-o", "--out", type=Path, default=Path("out/eval"), help="output directory (default out/eval)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    from tagloc.cli import checks
    from tagloc.core.errors import InputError
    from tagloc.eval.baselines import EVAL_MODES
    from tagloc.eval.evaluate import SCALE_RANGE, EvalConfig, run_presets
    from tagloc.sim.walk import GAIT_SCALE_RANGE

    checks.number(args.sessions, "--sessions", 1, 1000)
    checks.number(args.seconds, "--seconds", 0, 3600, lo_open=True)
    checks.number(args.scale, "--scale", *SCALE_RANGE)
    checks.number(args.gait_scale, "--gait-scale", *GAIT_SCALE_RANGE)
    checks.seed(args.seed)
    modes = checks.names(args.modes, "--modes", EVAL_MODES)
    checks.output_dir(args.out, "-o")
    if args.walks:
        from tagloc.eval.walks import score_walks

        unused = [o for o, default in PRESET_OPTIONS.items() if getattr(args, o[2:].replace("-", "_")) != default]
        if unused:
            verb = "does" if len(unused) == 1 else "do"
            raise InputError(f"--walks scores the sessions given; {', '.join(unused)} {verb} not apply")
        print(score_walks(args.walks, args.out, modes, progress=not args.quiet))
        return 0

    cfg = EvalConfig(
        sessions=args.sessions,
        seconds=args.seconds,
        seed=args.seed,
        out=args.out,
        modes=modes,
        hard=not args.no_hard,
        progress=not args.quiet,
        scale=args.scale,
        gait_scale=args.gait_scale,
    )
    print(run_presets(cfg, args.preset))
    return 0
