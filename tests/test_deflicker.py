"""Lamp flicker bands: fitted by their form, divided out, and told apart from the floor's own rows."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tagloc.core.rig import row_delay_s
from tagloc.vision.deflicker import Deflicker, DeflickerConfig, find_bands, remove_bands

H, W, READOUT = 480, 640, 0.030


def floor_image(seed: int = 0, line: bool = False) -> np.ndarray:
    """A textured floor (grey 100 +- 15, darker towards the top like a far floor) as float (H, W);
    ``line``: a painted aisle line 40 rows high across the whole image (grey 180)."""
    rng = np.random.default_rng(seed)
    img = 100.0 + 15.0 * rng.standard_normal((H, W))
    img *= np.linspace(0.8, 1.05, H)[:, None]
    if line:
        img[300:340] = 180.0 + 10.0 * rng.standard_normal((40, W))
    return img


def banded(img: np.ndarray, depth: float, frequency_hz: float, phase: float) -> np.ndarray:
    t = np.asarray(row_delay_s(np.arange(H), H, READOUT))
    gain = 1.0 + depth * np.cos(2 * math.pi * frequency_hz * t + phase)
    return np.clip(img * gain[:, None] + 0.5, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("frequency_hz", [100.0, 120.0])
def test_bands_are_found_and_divided_out(frequency_hz):
    img = floor_image()
    frame = banded(img, 0.08, frequency_hz, 1.1)
    bands = find_bands(frame, READOUT)
    assert bands is not None and bands.frequency_hz == frequency_hz
    assert bands.depth == pytest.approx(0.08, abs=0.008)
    flat = remove_bands(frame, bands)
    assert flat.shape == frame.shape and flat.dtype == np.uint8
    # Row by row, the frame divided by the floor without bands: +-8 % before, under 1 % after.
    ratio = lambda a: a.astype(float).mean(axis=1) / img.mean(axis=1)  # noqa: E731
    assert np.ptp(ratio(frame)) > 0.14
    assert np.ptp(ratio(flat)) < 0.02


def test_steady_light_a_painted_line_and_a_global_shutter_give_no_bands():
    steady = np.clip(floor_image(seed=1, line=True) + 0.5, 0, 255).astype(np.uint8)
    cfg = DeflickerConfig()
    bands = find_bands(steady, READOUT, cfg)
    assert bands is not None and bands.depth < 0.5 * cfg.min_depth, bands.depth
    # The robust fit is what leaves the line alone: plain least squares takes it for bands.
    plain = find_bands(steady, READOUT, DeflickerConfig(fit_iterations=0))
    assert plain.depth > cfg.min_depth, plain.depth
    assert find_bands(steady, 0.0) is None  # no rolling shutter, no bands


def test_a_camera_is_corrected_on_every_frame_or_none():
    cfg = DeflickerConfig()
    steady = Deflicker(READOUT, cfg)
    frames = [np.clip(floor_image(seed=k, line=k % 2 == 0) + 0.5, 0, 255).astype(np.uint8) for k in range(12)]
    assert all(steady(f) is f for f in frames) and not steady.on
    flickering = Deflicker(READOUT, cfg)
    # 100 Hz at 30 fps: the bands move a third of a period a frame.
    out = [flickering(banded(floor_image(seed=k), 0.05, 100.0, 0.3 + k * 2 * math.pi / 3)) for k in range(12)]
    assert flickering.on and flickering.level == pytest.approx(0.05, abs=0.008)
    assert all(
        np.ptp(o.astype(float).mean(axis=1) / floor_image(seed=k).mean(axis=1)) < 0.03 for k, o in enumerate(out)
    )


def test_a_global_shutter_camera_has_its_brightness_swings_evened_out():
    """No bands, but 100 Hz at 30 fps brightens and darkens whole frames in a three-frame cycle
    (30 % flicker: +-14 % in the 8-bit image). Each frame is scaled to the running brightness; a
    steady camera's frames are left as they are."""
    steady, swinging = Deflicker(0.0), Deflicker(0.0)
    means = []
    for k in range(30):
        img = floor_image(seed=k)
        frame = np.clip(img + 0.5, 0, 255).astype(np.uint8)
        assert steady(frame) is frame
        gain = 1.0 + 0.14 * math.cos(0.3 + k * 2 * math.pi / 3)
        means.append(float(swinging(np.clip(img * gain + 0.5, 0, 255).astype(np.uint8)).mean()))
    assert not steady.on and swinging.on
    later = np.array(means[10:])
    # Frame to frame (what the odometry compares): within 1.5 %, against about 24 % before. The
    # running brightness itself settles slowly from the first frame's, which does not matter.
    assert np.abs(np.diff(later)).max() / later.mean() < 0.015


@pytest.mark.parametrize("readout_s", [0.002, 0.005, 0.008])
def test_a_short_read_out_gives_steady_light_no_bands(readout_s):
    """A read-out under a period or so holds no band the cubic trend could not take: the fit had
    given steady frames bands of 3-70 % at 5 ms (gain down to 1e-13 at 2 ms), switched the
    correction on and brightened or darkened every frame by up to a half."""
    d = Deflicker(readout_s)
    for k in range(12):
        frame = np.clip(floor_image(seed=k, line=k % 2 == 0) + 0.5, 0, 255).astype(np.uint8)
        assert d(frame) is frame
    assert not d.on


@pytest.mark.parametrize("frequency_hz", [100.0, 120.0])
def test_the_frequency_that_fits_best_is_taken_not_the_deepest(frequency_hz):
    """Over two periods or so of read-out, a 120 Hz band was fitted deeper at 100 Hz and that
    sinusoid taken: divided out, it left the +-8 % bands at +-9 % (3 of 8 frames at 20 ms)."""
    readout = 0.020
    t = np.asarray(row_delay_s(np.arange(H), H, readout))
    for k in range(8):
        img = floor_image(seed=k, line=k % 2 == 0)
        gain = 1.0 + 0.08 * np.cos(2 * math.pi * frequency_hz * t + 0.7 * k)
        frame = np.clip(img * gain[:, None] + 0.5, 0, 255).astype(np.uint8)
        bands = find_bands(frame, readout)
        assert bands.frequency_hz == frequency_hz, k
        flat = remove_bands(frame, bands).astype(float).mean(axis=1) / img.mean(axis=1)
        assert np.ptp(flat) < 0.03, k
