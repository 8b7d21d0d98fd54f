"""tagloc advise: exposure/gain trade-off for a light level and walking speed, from the simulator."""

from __future__ import annotations

import argparse

NAME = "advise"
HELP = "recommend an exposure for a light level and walking speed (measured on simulated frames)"
DESCRIPTION = """Render the same simulated views at several exposure times with tagloc's own camera physics
(photons, motion blur at the walking speed, shot/read noise, auto gain capped at the sensor's maximum)
and run detection, decoding and identification on them. Prints, per exposure: gain, blur, SNR,
brightness against the AE target, and the fraction of stickers in view that are detected, read
(decoded) and give a fix (decoded or identified), then the exposure giving the most fixes. Pass it
to tagloc live --exposure-ms.

example:
  tagloc advise --lux 100 --speed 1.3
  tagloc advise --lux 40 --speed 1.6 --exposures 1 2 3 4 6 --frames 40"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--lux", type=float, default=100.0, help="illuminance on the floor, lux (default 100)")
    p.add_argument("--speed", type=float, default=1.3, help="walking speed, m/s (default 1.3)")
    p.add_argument("--exposures", type=float, nargs="+", default=[0.5, 1.0, 2.0, 4.0, 8.0], help="exposure times, ms")
    p.add_argument("--frames", type=int, default=24, help="simulated views per exposure (default 24)")
    p.add_argument("--height", type=float, default=1.3, help="camera height, m (default 1.3)")
    p.add_argument("--pitch", type=float, default=55.0, help="camera pitch below horizontal, degrees (default 55)")
    p.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    p.add_argument("--scale", type=float, default=1.0, help="image resolution factor (default 1: 1296x972)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from tagloc.cli import checks
    from tagloc.eval.advise import AdviseConfig, advise, best_row, format_advice

    for option, value in (
        ("--lux", args.lux),
        ("--pitch", args.pitch),
        ("--height", args.height),
        ("--scale", args.scale),
    ):
        checks.sim_option(value, option)
    # Unlike a simulated walk, advice may be for a camera standing still.
    checks.sim_option(args.speed, "--speed", lo_open=False)
    checks.seed(args.seed)
    checks.number(args.frames, "--frames", 1, 10_000)
    for exposure in args.exposures:
        # 100 ms: a 10 fps frame. The blurred view's canvas grows with the exposure (1e6 ms: 54 GB).
        checks.number(exposure, "--exposures", 0, 100, lo_open=True)

    cfg = AdviseConfig(
        lux=args.lux,
        speed_mps=args.speed,
        exposures_ms=tuple(args.exposures),
        frames=args.frames,
        height_m=args.height,
        pitch_deg=args.pitch,
        seed=args.seed,
        scale=args.scale,
    )
    rows = advise(cfg, progress=not args.no_progress)
    print(format_advice(rows, cfg))
    # No exposure gives a fix: the table stands, but there is no setting to pass on (exit 1, not 0).
    return 0 if best_row(rows) is not None else 1
