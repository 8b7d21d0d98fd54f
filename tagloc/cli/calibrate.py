"""tagloc calibrate: print a ChArUco board; calibrate a camera's intrinsics from views of it."""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "calibrate"
HELP = "print a ChArUco calibration board (board) or calibrate a camera from views of it (camera)"
DESCRIPTION = """board: a true-scale ChArUco board on one landscape page (PDF, PNG or SVG). Print at 100 %,
glue it flat to something rigid and measure one square.
camera: find the board (OpenCV's CharucoDetector) in a folder of images, a video file or a live camera
(an index such as 0), keep a well-spread subset of views, fit K and distortion (cv2.calibrateCameraExtended),
write OpenCV FileStorage YAML (what --calibration reads) and a coverage PNG next to it, and print
the RMS reprojection error and each parameter's standard deviation. Move the board over the whole
image, near and far, tilted 20-45 degrees each way: views that all show the board nearly parallel
to the image (no view tilted 3 degrees) cannot give the focal length and are refused.

examples:
  tagloc calibrate board -o board.pdf
  tagloc calibrate camera calib_images/ -o camera.yaml
  tagloc calibrate camera walk.mp4 -o camera.yaml --step 10 --square-mm 19.8
  tagloc calibrate camera 0 -o camera.yaml --max-frames 600"""


def _squares(text: str) -> tuple[int, int]:
    try:
        x, y = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not COLSxROWS such as 11x8") from None
    return x, y


def _board_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--squares", type=_squares, default=(11, 8), help="board squares COLSxROWS (default 11x8)")
    p.add_argument("--square-mm", type=float, default=20.0, help="side of a chessboard square, mm (default 20)")
    p.add_argument(
        "--marker-mm", type=float, default=None, help="side of an ArUco marker, mm (default 0.7 of the square)"
    )
    p.add_argument(
        "--dictionary", default="5x5_100", help="ArUco dictionary: 4x4_50, 5x5_100, 6x6_250 (default 5x5_100)"
    )


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    b = sub.add_parser(
        "board",
        help="write the printable board",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="write the printable board\n\nexample:\n  tagloc calibrate board -o board.pdf",
    )
    b.add_argument("-o", "--out", type=Path, required=True, help="output file: .pdf, .png or .svg")
    b.add_argument("--paper", default="a4", choices=("a4", "a3", "letter"), help="paper size (default a4)")
    b.add_argument("--dpi", type=int, default=600, help="PNG resolution (default 600)")
    _board_args(b)
    c = sub.add_parser(
        "camera",
        help="calibrate a camera",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="calibrate a camera\n\nexamples:\n  tagloc calibrate camera calib_images/ -o camera.yaml\n"
        "  tagloc calibrate camera calib.mp4 -o camera.yaml --step 10",
    )
    c.add_argument("source", help="folder of images, video file, or camera index (0, 1, ...)")
    c.add_argument("-o", "--out", type=Path, required=True, help="calibration YAML to write")
    c.add_argument("--coverage", type=Path, default=None, help="coverage PNG (default: OUT with _coverage.png)")
    c.add_argument("--step", type=int, default=5, help="use every STEP-th frame of a video or camera (default 5)")
    c.add_argument("--max-frames", type=int, default=3000, help="read at most this many frames (default 3000)")
    c.add_argument("--max-views", type=int, default=30, help="fit at most this many well-spread views (default 30)")
    c.add_argument("--rational", action="store_true", help="8-coefficient rational distortion (wide-angle lenses)")
    c.add_argument("--fix-k3", action="store_true", help="hold k3 at 0 (narrow lenses)")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")
    _board_args(c)


def run(args: argparse.Namespace) -> int:
    from tagloc.cli import checks
    from tagloc.core.charuco import BoardSpec

    checks.number(args.square_mm, "--square-mm", 0, 1000, lo_open=True)
    marker_mm = args.marker_mm if args.marker_mm is not None else 0.7 * args.square_mm
    # The marker sits inside its square, with a white border around it.
    checks.number(marker_mm, "--marker-mm", 0, args.square_mm, lo_open=True, hi_open=True)
    spec = BoardSpec(args.squares[0], args.squares[1], args.square_mm / 1000.0, marker_mm / 1000.0, args.dictionary)
    if args.action == "board":
        from tagloc.io.calibration_board import write_board

        checks.number(args.dpi, "--dpi", 72, 2400)
        print(write_board(args.out, spec, args.paper, args.dpi))
        return 0
    from tagloc.apps.calibrate import SourceConfig, calibrate_camera, format_report
    from tagloc.vision.calibration import CalibrationConfig

    checks.number(args.step, "--step", 1, 10_000)
    checks.number(args.max_frames, "--max-frames", 1, 10_000_000)
    # Fewer views than the fit needs could never calibrate.
    checks.number(args.max_views, "--max-views", CalibrationConfig.min_views, 1000)
    checks.output_file(args.out, "-o")
    checks.output_file(args.coverage, "--coverage", suffixes=(".png",))

    result = calibrate_camera(
        args.source,
        args.out,
        spec,
        CalibrationConfig(max_views=args.max_views, rational=args.rational, fix_k3=args.fix_k3),
        SourceConfig(step=args.step, max_frames=args.max_frames),
        args.coverage,
        progress=not args.no_progress,
    )
    print(format_report(result))
    print(f"wrote {args.out}")
    return 0
