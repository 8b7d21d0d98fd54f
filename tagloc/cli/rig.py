"""tagloc rig: fit where the camera sits on the vest from a recorded walk; show a rig file's mounts."""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "rig"
HELP = "fit the camera mount (height, pitch, roll, yaw) from a recorded walk (fit) or show a rig file (show)"
DESCRIPTION = """fit: from a session walked over mapped stickers, estimate the camera's height, pitch (optical
axis below horizontal), roll (image turned clockwise) and yaw (left of the walking direction) on
the vest, with one-sigma uncertainties, and write rig.json. Decoded stickers give the camera's pose
in the world; height, pitch and roll come straight from it, the yaw from straight stretches of
walking. Walk at a normal pace along an aisle of mapped stickers and back, about a minute, with
straight stretches of several metres; the command warns when the walk does not constrain a value.
The camera's x, y on the vest (where the body point is) are kept from the prior rig.
show: each camera's mount in a rig.json as height, pitch, roll, yaw, x, y, and whether the floor
odometry takes it to see the wearer's feet (legs_in_view, or decided from the mount).

examples:
  tagloc rig fit logs/calib_walk -o rig.json
  tagloc rig fit logs/calib_walk -o rig.json --rig old_rig.json --camera 0
  tagloc rig show rig.json"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    f = sub.add_parser(
        "fit",
        help="fit the mount from a session",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="fit the mount from a session\n\nexample:\n  tagloc rig fit logs/calib_walk -o rig.json",
    )
    f.add_argument("session", type=Path, help="session directory (frames, frames.csv, map.csv, camera.yaml)")
    f.add_argument("-o", "--out", type=Path, required=True, help="rig.json to write")
    f.add_argument("--rig", type=Path, default=None, help="prior rig (default: the session's rig.json or default rig)")
    f.add_argument("--camera", type=int, default=0, help="rig camera to fit (default 0)")
    f.add_argument("--step", type=int, default=1, help="use every STEP-th frame (default 1)")
    f.add_argument("--decoder", default="zxing", choices=("zxing", "libdmtx", "both"), help="Data Matrix backend")
    f.add_argument("--no-progress", action="store_true", help="no progress bar")
    s = sub.add_parser(
        "show",
        help="print a rig file's mounts",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="print a rig file's mounts\n\nexample:\n  tagloc rig show rig.json",
    )
    s.add_argument("rig", type=Path, help="rig.json")


def _output_apart_from_inputs(args: argparse.Namespace, checks) -> None:
    """Refuse an ``-o`` naming what the fit reads: the session's own files (its rig.json is the
    rig its frames were recorded with), its frames, or the prior rig (``--rig``)."""
    from tagloc.io.session import FRAMES_DIR, SESSION_INPUTS

    inputs = [*(args.session / name for name in SESSION_INPUTS), args.rig]
    checks.outputs_apart([("-o", args.out)], inputs, [args.session / FRAMES_DIR])


def run(args: argparse.Namespace) -> int:
    from tagloc.cli import checks
    from tagloc.eval.rigfit import RigFitConfig, check_rig_file, fit_rig, format_fit

    if args.action == "show":
        print(check_rig_file(args.rig))
        return 0
    checks.number(args.step, "--step", 1, 10_000)
    checks.output_file(args.out, "-o")
    _output_apart_from_inputs(args, checks)
    fit = fit_rig(
        args.session,
        args.out,
        args.rig,
        RigFitConfig(camera=args.camera, decoder=args.decoder, step=args.step),
        progress=not args.no_progress,
    )
    print(format_fit(fit))
    print(f"wrote {args.out}")
    return 0
