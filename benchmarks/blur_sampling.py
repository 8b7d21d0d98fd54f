"""How closely the simulator's sub-frames render motion blur: against a render sampled every 0.02 px.

Run: ``PYTHONPATH=$PWD python benchmarks/blur_sampling.py``.

A sticker on a plain floor seen straight down from 1.3 m (the Pi camera v1, 1296x972) and one seen
at 55 degrees on the textured floor, blurred by ``L`` px along image direction 30 degrees at the
image centre, noise off, linear tone curve, fine ADC, gain 20 (white paper at ~195 DN), so that
only the sampling differs. For each
blur: the RMS difference (8-bit DN) between the sharp render and the reference (what the blur
does), then between each sampling and the reference, over the pixels the blur changes by more than
1 DN. Samplings: the sub-frames at the middles of equal slices of the exposure
(:func:`tagloc.sim.render.subframe_offsets`) at steps of 1, 0.75 and 0.5 px, the same at the steps
before simulator revision 6 (1.5 px, one sub-frame up to 1.5 px), and sub-frames spanning the
exposure end to end (the first and last at its ends) at 1 and 0.5 px steps.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import replace

import numpy as np

import tagloc.sim.render as render
from tagloc.core.camera import default_camera
from tagloc.core.stickermap import StickerMap
from tagloc.sim.floor import Floor, FloorConfig
from tagloc.sim.render import ExposureConfig, SensorConfig
from tagloc.sim.simulate import camera_pose_looking_at, render_view

BLURS_PX = (0.4, 0.7, 1.0, 1.4, 2.0, 3.0, 4.4, 6.0, 10.0)
#: name -> (step px, sub-frames at the exposure's ends, blur rendered sharp up to px)
SAMPLINGS = {
    "rev5 1.5": (1.5, False, 1.5),
    "mid 1": (1.0, False, 0.3),
    "mid 0.75": (0.75, False, 0.3),
    "mid 0.5": (0.5, False, 0.3),
    "ends 1": (1.0, True, 0.3),
    "ends 0.5": (0.5, True, 0.3),
}
REFERENCE_STEP_PX = 0.02
MIDPOINTS = render.subframe_offsets


def _ends(blur_px: float, exposure_s: float, cfg: ExposureConfig) -> np.ndarray:
    """Sub-frames from one end of the exposure to the other (the alternative to the midpoint rule)."""
    n = len(MIDPOINTS(blur_px, exposure_s, cfg))
    return np.zeros(1) if n == 1 else exposure_s * (np.arange(n) / (n - 1) - 0.5)


def main(argv: list[str] | None = None) -> None:
    # No options, but ``--help`` must say what the script does rather than start its renders (about
    # a minute of rendering at 500 sub-frames a view for the reference).
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args(argv)
    cam = default_camera()
    smap = StickerMap(np.array([7, 8]), np.array([[2.0, 0.0], [2.3, 0.25]]), np.array([0.0, 0.5]), "t")
    views = {
        "straight down, plain floor": (camera_pose_looking_at((2.0, 0.0), 1.3, 90.0), FloorConfig(texture=False)),
        "55 degrees, textured floor": (camera_pose_looking_at((2.0, 0.0), 1.3, 55.0), FloorConfig()),
    }
    sensor = SensorConfig(gamma=1.0, prnu=0.0, noise=False, adc_bits=16)
    for view, (T, fc) in views.items():
        floor = Floor(smap, replace(fc, distractors_per_m2=0.0), seed=0)

        def image(blur: float, cfg: ExposureConfig, ends: bool = False, floor=floor, T=T) -> tuple[np.ndarray, int]:
            render.subframe_offsets = _ends if ends else MIDPOINTS
            try:
                r = render_view(
                    floor, cam, T, 300.0, exposure_s=0.004, gain=20.0, sensor=sensor, exposure=cfg, blur_px=blur,
                    blur_direction_deg=30.0,
                )  # fmt: skip
            finally:
                render.subframe_offsets = MIDPOINTS
            return r.image.astype(float), r.subframes

        sharp, _ = image(0.0, ExposureConfig())
        print(f"{view}: RMS DN against the reference (sub-frames)")
        print(f"{'blur px':>8} {'blur itself':>11} " + " ".join(f"{k:>12}" for k in SAMPLINGS))
        for L in BLURS_PX:
            ref, _ = image(L, ExposureConfig(px_per_subframe=REFERENCE_STEP_PX, max_subframes=1000))
            changed = np.abs(ref - sharp) > 1.0
            cells = []
            for step, ends, sharp_px in SAMPLINGS.values():
                img, n = image(L, ExposureConfig(px_per_subframe=step, sharp_blur_px=sharp_px), ends)
                cells.append(f"{math.sqrt(((img - ref)[changed] ** 2).mean()):6.2f} ({n:2d})")
            itself = math.sqrt(((sharp - ref)[changed] ** 2).mean())
            print(f"{L:8.1f} {itself:11.2f} " + " ".join(f"{c:>12}" for c in cells), flush=True)


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("blur_sampling.py", main))
