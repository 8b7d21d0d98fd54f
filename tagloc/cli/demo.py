"""tagloc demo: simulate a walk on the demo map, localise it, report and visualise."""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "demo"
HELP = "simulate a walk on the demo map, localise it, print the accuracy and write a Rerun recording"
DESCRIPTION = """Needs no camera and no arguments: simulates a 20 s walk on maps/demo.csv, replays it through the
localiser, prints the error against ground truth, and writes out/demo/estimate.tum,
out/demo/frames.jsonl and out/demo/demo.rrd.

example:
  tagloc demo
  tagloc demo --lux 60 --seconds 30 -o out/dim"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--out", type=Path, default=Path("out/demo"), help="output directory (default out/demo)")
    p.add_argument("--map", type=Path, help="sticker map (default maps/demo.csv)")
    p.add_argument("--seconds", type=float, default=20.0, help="walk length, s (default 20)")
    p.add_argument("--lux", type=float, default=150.0, help="floor illuminance, lux (default 150)")
    p.add_argument("--speed", type=float, default=1.3, help="walking speed, m/s (default 1.3)")
    p.add_argument("--seed", type=int, default=1, help="simulation seed (default 1)")
    p.add_argument("--no-rerun", action="store_true", help="do not write the .rrd recording")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    from tagloc.apps.demo import DemoConfig, run_demo
    from tagloc.cli import checks

    for option, value in (("--seconds", args.seconds), ("--lux", args.lux), ("--speed", args.speed)):
        checks.sim_option(value, option)
    checks.seed(args.seed)
    checks.output_dir(args.out, "-o")

    print(
        run_demo(
            DemoConfig(
                out=args.out,
                map=args.map,
                seconds=args.seconds,
                lux=args.lux,
                speed=args.speed,
                seed=args.seed,
                rerun=not args.no_rerun,
                progress=not args.quiet,
            )
        )
    )
    return 0
