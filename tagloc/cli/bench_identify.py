"""tagloc bench-identify: identification rates and where its thresholds sit, on synthetic views."""

from __future__ import annotations

import argparse

NAME = "bench-identify"
HELP = "measure identification among candidates and check IdentifyConfig's thresholds"
DESCRIPTION = """Render synthetic blurred views of stickers (tagloc.eval.bench_identify.synth_view), hand
identification K candidates (the true sticker among its nearest IDs, or only its neighbours), and print
two tables: right / wrong / refused and time per call vs blur, and the raw score and margin distributions
of right and wrong answers against IdentifyConfig's thresholds (the numbers they were chosen from).

examples:
  tagloc bench-identify                       # 100 views per cell, appearance and ORB
  tagloc bench-identify --trials 20 --methods appearance --blurs 0,4"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--trials", type=int, default=100, help="views per (method, blur, case) cell (default 100)")
    p.add_argument("--methods", default="appearance,orb", help="comma-separated methods (default appearance,orb)")
    p.add_argument("--blurs", default="0,2,4,8", help="comma-separated blur lengths, px (default 0,2,4,8)")
    p.add_argument("--candidates", type=int, default=5, help="K, candidates per view (default 5)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from tagloc.cli import checks
    from tagloc.eval.bench_identify import identify_bench_command
    from tagloc.vision.identify import METHODS

    checks.number(args.trials, "--trials", 1, 100_000)
    methods = checks.names(args.methods, "--methods", METHODS)
    # 100 px: ten times the blur that defeats decoding; at 1000 px one view took over 25 s.
    blurs = checks.numbers(args.blurs, "--blurs", 0, 100)
    # The bench's bank holds 200 consecutive IDs and hands out the true one's 2K nearest: K up to
    # 100 leaves enough of them even at the bank's ends.
    checks.number(args.candidates, "--candidates", 1, 100)
    checks.seed(args.seed)

    print(
        identify_bench_command(
            methods=methods,
            blurs_px=blurs,
            trials=args.trials,
            k=args.candidates,
            seed=args.seed,
            progress=not args.no_progress,
        )
    )
    return 0
