"""One camera against front + rear cameras on the same simulated walks (issue 16, several cameras).

Run: ``python benchmarks/two_cameras.py [--seeds 1 2 3] [--seconds 20] [--fps 15] [--out out/multicam]``.
Simulates each walk with the default one-camera rig and with a rear-down camera added
(:func:`tagloc.eval.multicam.front_rear_rig`), localises both, and prints per walk and rig the
fraction of frame times with a mapped sticker in view, the fraction of frames with a pose, the fixes
and the horizontal RMSE / max error against ground truth. Sessions are kept under ``--out``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tagloc.eval.multicam import MultiCamConfig, compare_cameras, format_rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--out", type=Path, default=Path("out/multicam"))
    args = ap.parse_args()
    cfg = MultiCamConfig(
        seeds=tuple(args.seeds), seconds=args.seconds, fps=args.fps, scale=args.scale, out=args.out, progress=False
    )
    print(format_rows(compare_cameras(cfg)))


if __name__ == "__main__":
    main()
