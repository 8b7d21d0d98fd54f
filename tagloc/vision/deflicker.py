"""Lamp flicker bands in rolling-shutter frames: found by their known form, divided out.

Lamps on AC mains pulse at twice the mains frequency (100 Hz on 50 Hz mains, 120 Hz on 60 Hz).
The pulse depth is a few percent for well-smoothed LED drivers and 20-40 % for fluorescent tubes
on magnetic ballasts and poorly smoothed LED drivers. A rolling shutter exposes each row at its own
time, so a frame holds horizontal bands, 2.5-3.6 periods of them for a 25-30 ms read-out. The
floor odometry tracks image texture, and bands are a stronger texture than the floor's.

- When the flicker frequency is not a multiple of the frame rate (100 Hz at 30 fps), the bands move
  a third of a period from frame to frame. The odometry then reads part of the band motion.
- When it is (120 Hz at 30 fps), the bands stand still. The odometry then reads the floor's
  motion short, towards zero.

In a simulated 20 s walk at 300 lux with 30 % flicker (``benchmarks/flicker.py``), the position
was 12 cm RMS off at 50 Hz and 28 cm, overconfident, at 60 Hz, against 1.2 cm in steady light.

The bands' form is known: the light is ``1 + a cos(2 pi f t + phi)`` and row ``r`` is exposed at
``row_delay_s(r)``. With the exposure ``T`` short against the period, the bands keep most of the
depth ``a`` (times ``sinc(pi f T)``). The phase is free, because the camera's clock is not locked
to the mains. So each frame's robust row profile is fitted, in log, with a smooth trend (the
floor's own brightness from the near rows to the far ones: vignetting, light pools) plus one
sinusoid at each candidate frequency; the one that fits better is the frame's bands (in the 8-bit
image, whose tone curve keeps the bands multiplicative). A camera's frames are corrected all
alike, or none of them (:class:`Deflicker`): correcting one frame of a pair and not the other
would itself put a band between them. While the camera's fitted depth, averaged
over recent frames, is at least ``min_depth``, the sinusoid alone is divided out of every frame's
rows, and the floor's own brightness is kept.

A global-shutter frame gets no bands, only a brighter or darker frame: while a camera's frames
keep changing brightness from one to the next, each is scaled to their running average.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from tagloc.core.rig import row_delay_s
from tagloc.vision.detect import median_last  # np.median without its per-call overhead

__all__ = ["DeflickerConfig", "Bands", "Deflicker", "find_bands", "remove_bands"]


@dataclass(frozen=True)
class DeflickerConfig:
    """How flicker bands are found (see the module docstring).

    - ``frequencies_hz``: the flicker frequencies tried, twice the mains frequencies (50 and 60 Hz).
    - ``min_depth``, ``off_depth``, ``memory``: the depth is that of the 8-bit image, whose tone
      curve (gamma about 2.2) divides the light's depth by about 2.2. The camera's bands are
      divided out from when the fitted depth, averaged over fits (an exponential average with
      this ``memory`` in fits, started at the first), reaches ``min_depth``, until it falls below
      ``off_depth``. Measured on simulated 20 s walks at 300 lux with a 25 ms read-out
      (``benchmarks/flicker.py``), the light's flicker gave these fitted depths: 5 % -> 2.3 %,
      10 % -> 4.5 %, 30 % -> 14 %. In steady light the average stays at 1.2 % or less, on the five
      field walks and on two such walks; its median is 0.3-0.4 %, from the floor's own
      brightness. Already 5 % flicker, below IEEE 1789's low-risk limit, moved one such walk
      1.24 -> 1.98 cm, so it is corrected.
    - ``check_every``: while a camera's frames are not corrected, only every this-many-th is fitted
      (a fit costs 0.3-0.6 ms on one core, dividing out 0.4 ms): lamps do not start to flicker
      from one frame to the next.
    - ``frame_min_step``, ``frame_off_step``, ``frame_memory``: a global shutter gets no bands, but
      its frames brighten and darken with the flicker. With 100 Hz at 30 fps the pattern repeats
      every three frames. Lucas-Kanade takes brightness as constant, and on a 20 s walk with 30 %
      flicker the RMSE was 1.44 cm against 1.13 cm in steady light. The frame-to-frame change of
      the log mean brightness, averaged like the depth, was 0.4 % or less in steady light (six
      standard eval walks, two others) and 15 % or more with 30 % flicker. While it is at least
      ``frame_min_step`` (until below ``frame_off_step``), each frame is scaled to the brightness
      averaged over about ``frame_memory`` frames, which leaves 0.5 % of a three-frame ripple.
      120 Hz at 30 fps gives every frame the same light: nothing to do.
    - ``row_step``, ``strips``: the profile is taken on every ``row_step``-th row. Each such row is
      averaged in ``strips`` vertical strips, and the median of the strips is taken, so a sticker
      or a shadow in one strip does not move it. Bands span 250 rows or more.
    - ``trend_degree``: the degree of the polynomial (in the row) for the floor's own brightness.
      A read-out that holds a period or more (25-30 ms: 2.5-3.6 periods) gives bands the cubic
      cannot follow. Under about one period (a read-out under 10 ms at 100 Hz), the trend takes
      up the band, which is then not found.
    - ``min_periods``: a frequency is tried only when the read-out holds at least this many of its
      periods. Under that the sinusoid is nearly a cubic in the row, and the fit, unable to tell
      them apart, gave steady light bands of any depth: with a 5 ms read-out 3-70 %, the
      correction switched on and left the frames brighter or darker by half (at 2 ms the gain
      reached 1e-13). On the painted-line floor of ``tests/test_deflicker.py`` in steady light the
      deepest fitted band was 5 % at 1 period, 2.2 % at 1.25 and 1.2 % (``off_depth``) at 1.5,
      while 5 % bands were fitted within 0.3 % from 1.5 periods on. So a read-out under 15 ms
      gets no correction at 100 Hz, under 12.5 ms none at 120 Hz.
    - ``min_level``: rows whose profile is darker than this (grey levels) are left out of the fit:
      in the log their noise would dominate.
    - ``huber_k``, ``fit_iterations``: the fit is reweighted (Huber weights beyond ``huber_k``
      robust sigmas), so that what lies across a few rows only, such as a painted aisle line
      across the whole image, is not taken for a band. Plain least squares fitted 3-4 % bands to
      such lines on the 90 s field walk f03-long.
    """

    frequencies_hz: tuple[float, ...] = (100.0, 120.0)
    min_depth: float = 0.02
    off_depth: float = 0.012
    memory: float = 5.0
    check_every: int = 4
    frame_min_step: float = 0.015
    frame_off_step: float = 0.008
    frame_memory: float = 15.0
    row_step: int = 8
    strips: int = 8
    trend_degree: int = 3
    min_periods: float = 1.5
    min_level: float = 8.0
    huber_k: float = 1.5
    fit_iterations: int = 6


@dataclass(frozen=True)
class Bands:
    """Flicker bands fitted to one frame: ``gain`` (H,) float32, each row's light relative to the
    mean (1 + the sinusoid, the trend left out), ``depth`` (fraction) and ``frequency_hz``."""

    gain: np.ndarray
    depth: float
    frequency_hz: float


def find_bands(gray: np.ndarray, readout_s: float, config: DeflickerConfig | None = None) -> Bands | None:
    """The flicker bands of ``gray`` ((H, W) uint8) from a rolling shutter that reads its rows in
    ``readout_s`` s (the sinusoid that fits best, however shallow), or None when the frame has too
    few lit rows to tell, or there is no rolling shutter, or none long enough to tell a band from
    the floor's own brightness (``min_periods``)."""
    cfg = config or DeflickerConfig()
    H = gray.shape[0]
    frequencies = tuple(f for f in cfg.frequencies_hz if readout_s * f >= cfg.min_periods)
    if not readout_s > 0 or H < 8 * cfg.row_step or not frequencies:
        return None
    n = len(range(0, H, cfg.row_step))
    strips = cv2.resize(gray[:: cfg.row_step], (cfg.strips, n), interpolation=cv2.INTER_AREA)
    level = median_last(strips.astype(float))
    lit = level > cfg.min_level
    freqs, A = _designs(H, float(readout_s), cfg.row_step, cfg.trend_degree, frequencies)
    if int(lit.sum()) < 4 * A.shape[2]:
        return None
    y = np.log(np.maximum(level, 1.0))
    coef, loss = _robust_fit(A, y, lit.astype(float), cfg.huber_k, cfg.fit_iterations)  # (F, p), (F,)
    depths = np.hypot(coef[:, -2], coef[:, -1])
    # The frequency whose fit leaves the least (robust) residual, not the deepest: under two periods
    # or so a 120 Hz band was fitted deeper at 100 Hz, and that sinusoid left it as deep as before.
    k = int(np.argmin(loss))
    if not (np.isfinite(depths[k]) and np.isfinite(loss[k])):
        return None
    depth, f, b, c = float(depths[k]), freqs[k], float(coef[k, -2]), float(coef[k, -1])
    w = 2.0 * math.pi * f
    t_all = np.asarray(row_delay_s(np.arange(H, dtype=float), H, readout_s), float)
    gain = np.exp(b * np.cos(w * t_all) + c * np.sin(w * t_all)).astype(np.float32)
    return Bands(gain, depth, f)


@lru_cache(maxsize=16)
def _designs(
    H: int, readout_s: float, row_step: int, degree: int, frequencies: tuple[float, ...]
) -> tuple[tuple[float, ...], np.ndarray]:
    """The fit's designs over the profile's rows, (F, n, p) for the F flicker frequencies: the
    trend's powers of the row (scaled to [-1, 1]), then the cosine and sine of its read-out time."""
    rows = np.arange(0, H, row_step, dtype=float)
    trend = np.vander(rows / H * 2.0 - 1.0, degree + 1)
    t = np.asarray(row_delay_s(rows, H, readout_s), float)
    A = np.stack(
        [np.column_stack([trend, np.cos(2.0 * math.pi * f * t), np.sin(2.0 * math.pi * f * t)]) for f in frequencies]
    )
    A.flags.writeable = False
    return frequencies, A


def _robust_fit(
    A: np.ndarray, y: np.ndarray, w0: np.ndarray, k: float, iterations: int
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least squares of ``A[i] x = y`` for each design ``A`` (F, n, p) (row weights ``w0``
    (n,)), reweighted ``iterations`` times with Huber weights at ``k`` robust sigmas (1.4826
    median absolute residual of the rows kept): (F, p), NaN where singular, and each fit's Huber
    loss over the rows kept, on one scale for all (F,)."""
    F = A.shape[0]
    w = np.broadcast_to(w0, (F, len(w0)))
    kept = w0 > 0
    for _ in range(iterations + 1):
        Aw = A * w[:, :, None]
        AwT = Aw.transpose(0, 2, 1)
        try:
            coef = np.linalg.solve(AwT @ A, (AwT @ y)[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            return np.full((F, A.shape[2]), np.nan), np.full(F, np.nan)
        r = np.abs(y[None] - np.einsum("fnp,fp->fn", A, coef))
        sigma = 1.4826 * median_last(r[:, kept])[:, None] + 1e-6
        w = w0[None] * np.minimum(1.0, k * sigma / np.maximum(r, 1e-12))
    # Each fit's Huber loss on one common scale (the smaller sigma), over the rows kept.
    c = k * sigma.min()
    loss = np.where(r <= c, 0.5 * r**2, c * (r - 0.5 * c))
    return coef, (loss * w0[None]).sum(axis=1)


def remove_bands(gray: np.ndarray, bands: Bands) -> np.ndarray:
    """``gray`` ((H, W) uint8) with each row divided by its band gain: a new (H, W) uint8 array."""
    return cv2.convertScaleAbs(np.multiply(gray, (1.0 / bands.gain)[:, None], dtype=np.float32))


class Deflicker:
    """One camera's lamp flicker, divided out of its frames while the camera has it (see
    :class:`DeflickerConfig`). ``readout_s``: the camera's rolling-shutter read-out (s); 0 for a
    global shutter, whose frames flicker as a whole (see ``frame_min_step``)."""

    def __init__(self, readout_s: float, config: DeflickerConfig | None = None):
        self.readout_s = float(readout_s)
        self.config = config or DeflickerConfig()
        self.level: float | None = None  # the fitted depth (or frame step), averaged over recent frames
        self.on = False
        self._frames = 0
        self._log_mean: float | None = None  # global shutter: the last frame's log brightness
        self._log_ref: float | None = None  # and its slow average

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        """``gray`` ((H, W) uint8) with the camera's flicker divided out, or ``gray`` itself."""
        if not self.readout_s > 0:
            return self._whole_frames(gray)
        cfg = self.config
        self._frames += 1
        if not self.on and (self._frames - 1) % cfg.check_every:
            return gray
        bands = find_bands(gray, self.readout_s, cfg)
        depth = bands.depth if bands is not None else 0.0
        self._average(depth, cfg.min_depth, cfg.off_depth)
        return remove_bands(gray, bands) if self.on and bands is not None else gray

    def _whole_frames(self, gray: np.ndarray) -> np.ndarray:
        cfg = self.config
        lm = math.log(max(cv2.mean(gray[::8])[0], 1.0))  # every 8th row: 0.03 ms
        prev, self._log_mean = self._log_mean, lm
        if prev is None or self._log_ref is None:
            self._log_ref = lm
            return gray
        self._average(abs(lm - prev), cfg.frame_min_step, cfg.frame_off_step)
        self._log_ref += (lm - self._log_ref) / max(cfg.frame_memory, 1.0)
        return cv2.convertScaleAbs(gray, alpha=math.exp(self._log_ref - lm)) if self.on else gray

    def _average(self, x: float, on: float, off: float) -> None:
        m = max(self.config.memory, 1.0)
        self.level = x if self.level is None else self.level + (x - self.level) / m
        self.on = self.level >= (off if self.on else on)
