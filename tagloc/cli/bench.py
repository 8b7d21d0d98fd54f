"""tagloc bench: per-frame stage benchmark on simulated frames."""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "bench"
HELP = "benchmark detection, decoding, identification and pose on simulated frames"
DESCRIPTION = """Render simulated 1296x972 frames (Pi v1 camera, fixed seeds) of a small map with distractor
stickers and measure, single-threaded: stage times on frames with 0, 1 and 3 stickers (and OpenCV's
ArUco detector as a reference), read/identification rates and wrong IDs vs blur and illuminance,
corner and camera position errors vs blur and distance, and the paper's detector against ours.
Prints aligned tables with PASS/MISS against the targets; --json stores everything as plain data.

examples:
  tagloc bench                          # 40 views per cell, ~2 minutes on one core
  tagloc bench --frames 10 --json bench.json
  tagloc bench --quick                  # tiny smoke run
  tagloc bench --profile out/walk300    # cProfile summary of a replay of that session instead"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--frames", type=int, default=None, help="views per cell (default 40; 3 with --quick)")
    p.add_argument("--seed", type=int, default=0, help="random seed of scene, views and noise (default 0)")
    p.add_argument("--json", type=Path, default=None, metavar="FILE", help="also write the results as JSON")
    p.add_argument("--quick", action="store_true", help="tiny run: 3 views per cell, blur 0 and 4 px only")
    p.add_argument(
        "--jpeg",
        type=int,
        default=None,
        metavar="Q",
        help="round-trip frames through JPEG at quality Q (default: raw frames)",
    )
    p.add_argument("--no-libdmtx", action="store_true", help="skip the (slow) libdmtx and 'both' decoders")
    p.add_argument("--no-paper", action="store_true", help="skip the paper's detector")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--profile",
        type=Path,
        default=None,
        metavar="SESSION",
        help="instead of the benchmark: replay SESSION under cProfile and print where the time goes",
    )


#: The benchmark's own options (flag, argument attribute): ``--profile`` replays a session instead and
#: would ignore them (``--json`` wrote no file), so it refuses them.
_BENCH_ONLY = (
    ("--frames", "frames"),
    ("--json", "json"),
    ("--quick", "quick"),
    ("--jpeg", "jpeg"),
    ("--no-libdmtx", "no_libdmtx"),
    ("--no-paper", "no_paper"),
)


def run(args: argparse.Namespace) -> int:
    if args.profile is not None:
        from tagloc.core.errors import InputError
        from tagloc.eval.profile import profile_replay

        given = [flag for flag, attr in _BENCH_ONLY if getattr(args, attr) not in (None, False)]
        if given:
            raise InputError(
                f"{', '.join(given)}: not with --profile (it replays SESSION under cProfile and prints a summary)"
            )

        print(profile_replay(args.profile).format())
        return 0
    from tagloc.cli import checks
    from tagloc.eval.bench import bench_command

    checks.seed(args.seed)
    if args.frames is not None:
        checks.number(args.frames, "--frames", 1, 10_000)
    if args.jpeg is not None:
        checks.number(args.jpeg, "--jpeg", 1, 100)
    checks.output_file(args.json, "--json")
    return bench_command(
        frames=args.frames,
        seed=args.seed,
        json_path=args.json,
        quick=args.quick,
        jpeg_quality=args.jpeg,
        libdmtx=not args.no_libdmtx,
        paper=not args.no_paper,
        progress=not args.no_progress,
    )
