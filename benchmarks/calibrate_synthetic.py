"""Accuracy of ``tagloc calibrate camera`` on synthetic ChArUco views through known cameras.

Run: ``python benchmarks/calibrate_synthetic.py [--views 30] [--seeds 3]``. For each camera (the
Pi camera v1 default at 1296x972, and a 640x480 webcam with strong barrel distortion) and seed,
renders the board (``tagloc.sim.board``: exact OpenCV distortion, lens blur, noise) at views a person
would hold, writes them as PNGs, runs the same library call as the command and prints the errors
of fx, fy, cx, cy and the largest undistortion error over the image, against the true camera.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import cv2
import numpy as np

from tagloc.apps.calibrate import calibrate_camera
from tagloc.core.camera import Camera, default_camera
from tagloc.sim.board import board_poses, render_board_view

CAMERAS = {
    "pi-v1 1296x972": default_camera(),
    "webcam 640x480": Camera(
        np.array([[700.0, 0.0, 322.3], [0.0, 701.4, 238.7], [0.0, 0.0, 1.0]]),
        np.array([-0.28, 0.09, 0.001, -0.0015, 0.0]),
        640,
        480,
    ),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--views", type=int, default=30, help="images per calibration")
    ap.add_argument("--seeds", type=int, default=3, help="calibrations per camera")
    args = ap.parse_args()
    print(
        f"{'camera':<16}{'seed':>5}{'views':>6}{'RMS px':>8}{'fx %':>8}{'fy %':>8}{'cx px':>7}{'cy px':>7}{'undist px':>10}"
    )
    for name, cam in CAMERAS.items():
        grid = np.stack(np.meshgrid(np.linspace(0, cam.width - 1, 9), np.linspace(0, cam.height - 1, 7)), -1).reshape(
            -1, 2
        )
        for seed in range(args.seeds):
            with tempfile.TemporaryDirectory() as d:
                for i, T in enumerate(board_poses(cam, args.views, seed=seed)):
                    img = render_board_view(cam, T, rng=np.random.default_rng([seed, i]))
                    cv2.imwrite(str(Path(d) / f"{i:03d}.png"), img)
                res = calibrate_camera(d, Path(d) / "camera.yaml", progress=False)
            c = res.camera
            und = np.abs(c.undistort_pixels(grid) - cam.undistort_pixels(grid)).max()
            print(
                f"{name:<16}{seed:>5}{len(res.views):>6}{res.rms_px:>8.3f}{100 * (c.fx / cam.fx - 1):>8.3f}"
                f"{100 * (c.fy / cam.fy - 1):>8.3f}{c.K[0, 2] - cam.K[0, 2]:>7.2f}{c.K[1, 2] - cam.K[1, 2]:>7.2f}{und:>10.2f}"
            )


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("calibrate_synthetic.py", main))
