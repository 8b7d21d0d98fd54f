"""One camera against front + rear cameras on the same simulated walks (issue 16, several cameras).

Run: ``nice python benchmarks/two_cameras.py [--seeds 1 2 3] [--seconds 20] [--fps 15] [--odometry-cameras 0]
[--out out/multicam]``.
Simulates each walk once with a rear-down camera added to the default front one
(:func:`tagloc.eval.multicam.front_rear_rig`), localises it with the front camera's frames alone and
with both, and prints per walk and rig the fraction of frame times with a mapped sticker in view,
the fraction of frames with a pose, the fixes, the odometry steps fused, the horizontal RMSE / max
error against ground truth and the position NEES. Sessions, ``report.md`` and a PNG are kept under
``--out``. ``tagloc eval --preset two-camera`` runs the default walks.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tagloc.eval.multicam import MultiCamConfig, run_two_camera


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--lux", type=float, default=100.0)
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--rolling-shutter", action="store_true", help="simulate a rolling shutter (30 ms read-out)")
    ap.add_argument(
        "--odometry-cameras", type=int, nargs="+", default=None, help="rig cameras running floor odometry (default all)"
    )
    ap.add_argument("--out", type=Path, default=Path("out/multicam"))
    args = ap.parse_args()
    cfg = MultiCamConfig(
        seeds=tuple(args.seeds),
        seconds=args.seconds,
        fps=args.fps,
        lux=args.lux,
        scale=args.scale,
        out=args.out,
        progress=False,
        sim_extra={"rolling_shutter": True} if args.rolling_shutter else {},
        odometry_cameras=None if args.odometry_cameras is None else tuple(args.odometry_cameras),
    )
    print(run_two_camera(cfg))


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("two_cameras.py", main))
