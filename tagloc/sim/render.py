"""Image formation of the vest camera: floor -> optics -> exposure (with motion) -> sensor -> 8-bit.

Pipeline of one frame (all in linear light until the tone curve):

1. **Geometry.** The floor plane maps to the ideal (undistorted) image by the homography
   ``K [r1 r2 t]``, composed with the floor mosaic's texel affine, through ``cv2.warpPerspective``.
   Stickers are warped separately from their own high-resolution rasters (exact corners) and
   composited with an anti-aliased coverage mask. The ideal image lives on a canvas slightly larger
   than the sensor so that the lens distortion, applied afterwards with one precomputed
   ``cv2.remap`` (sensor pixel -> ideal position, from ``cv2.undistortPoints``), has data everywhere.
2. **Exposure and motion blur.** The shutter is open for ``t_exp`` around the frame's time. The
   true camera poses over that window are rendered as sub-frames and averaged in linear light, so the
   blur follows the real motion (translation, bobbing, rotation) rather than a fixed kernel. The
   number of sub-frames follows the expected blur length (one per ``px_per_subframe`` = 0.5 px,
   at least two above ``sharp_blur_px`` = 0.3 px, at most ``max_subframes``), each at the middle of
   its slice of the exposure (:func:`subframe_offsets`). With a rolling shutter the sensor reads one row every
   ``readout_s / height`` seconds, top first (:func:`row_delay_s`); the image is cut into
   ``bands`` row bands, each rendered with the poses at its middle row's time (96 bands of ~10 rows
   at 972 rows: a row is at most 0.15 ms off its own time, 0.3 px of image motion at a brisk turn).
3. **Optics.** Image-plane illuminance from the Lambertian floor: ``E_img = rho * E * T / (4 N^2)``
   (f-number ``N`` = 2.9 of the Pi camera v1 lens, transmission ``T``), times a natural vignetting
   ``cos^(4*v)`` of the field angle (``v`` < 1: the ISP's lens-shading correction undoes part of it),
   times the world-anchored illumination pattern. A Gaussian PSF stands for lens blur, Bayer
   demosaicing and the ISP's smoothing.
4. **Sensor.** Photo-electrons = image-plane lux * ``PHOTONS_PER_LUX_S_M2`` * pixel area * QE * t_exp
   (+ dark current), with per-pixel response non-uniformity (PRNU). Shot noise (Poisson, drawn as
   its Gaussian limit together with read noise), full-well clipping, analog gain, 10-bit ADC,
   then a gamma tone curve to 8 bits. The session writer adds JPEG compression.
5. **Light flicker** (:class:`Flicker`, off by default). Lamps on AC mains pulse at twice the
   mains frequency (100 Hz on 50 Hz mains). Each row collects the light of its own exposure window,
   so a row's signal is scaled by the flicker averaged over that window. A global shutter makes
   the whole frame brighter or darker. A rolling shutter reads rows at staggered times, which
   gives horizontal bands (a 30 ms read-out spans three periods at 100 Hz) that move from frame
   to frame. Exposures of a whole period or more average the flicker out. The auto exposure
   sets the gain from the mean light, because the camera's loop spans many frames.
   The wearer's legs and feet (:mod:`tagloc.sim.legs`, ``legs``, off by default) are painted over
   each sub-frame's floor at that sub-frame's time, so they blur with their own motion.
6. **Auto exposure (motion priority).** ``t_exp = e0_lux_s / lux`` capped at ``max_exposure_s`` and
   the frame interval; gain brings the frame's mean signal to ``target_mean`` of full scale, capped
   at ``max_gain``. Dimmer light: longer exposure (more blur), and once capped, more gain (more noise).

Constants and where they come from:
    * Pixel: OV5647 1.4 um pixels, 2x2 binned in the 1296x972 mode -> 2.8 um, full well about
      4 x 4000 e-, read noise about 2 x 3 e- (four reads summed), 10-bit ADC with full scale at the
      full well at unity gain; sensor analog gain up to 16x, ISP digital gain to 32x in total.
    * ``target_mean`` = 0.16 of full scale (linear), the Raspberry Pi AGC's usual luminance target.
    * ``PHOTONS_PER_LUX_S_M2`` = 1e16: white LED / fluorescent light has a luminous efficacy of
      radiation near 300 lm/W and a mean photon energy near 3.6e-19 J (550 nm) -> 1 lux = 9.3e15
      photons/(s m^2) in the visible band.
    * QE 0.25: peak silicon QE about 0.5-0.6, times about 0.45 passed by the Bayer filters for white
      light, averaged over the binned RGGB quad.
    * ``e0_lux_s`` = 0.3: 300 lux -> 1 ms, 100 lux -> 3 ms, 50 lux -> 6 ms.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import numpy as np

from tagloc.core.camera import Camera
from tagloc.core.errors import InputError
from tagloc.core.rig import row_delay_s
from tagloc.core.sticker import sticker_pixel_to_metres
from tagloc.sim.floor import Floor, sticker_size_px
from tagloc.sim.lamps import Lamps
from tagloc.sim.legs import Legs

#: Photons per second per square metre per lux of white (LED/fluorescent) light, visible band.
PHOTONS_PER_LUX_S_M2 = 1.0e16

PoseFn = Callable[[np.ndarray], np.ndarray]
"""Maps times (N,) in seconds to true camera poses ``T_world_camera`` (N, 4, 4)."""


@dataclass
class OpticsConfig:
    """Lens. ``psf_sigma_px``: Gaussian blur of lens + demosaicing (px); ``vignetting``: exponent factor on cos^4."""

    f_number: float = 2.9
    transmission: float = 0.9
    psf_sigma_px: float = 0.6
    vignetting: float = 0.5


@dataclass
class SensorConfig:
    """Sensor and read-out (per output pixel, i.e. after 2x2 binning). ``noise=False`` gives the mean image."""

    pixel_pitch_m: float = 2.8e-6
    quantum_efficiency: float = 0.25
    full_well_e: float = 16000.0
    read_noise_e: float = 6.0
    dark_current_e_s: float = 20.0
    prnu: float = 0.01
    adc_bits: int = 10
    max_gain: float = 32.0
    gamma: float = 2.2
    noise: bool = True


#: Sensor models by name (see :func:`sensor_preset`).
SENSOR_PRESETS = ("standard", "ov5647")


def sensor_preset(name: str) -> SensorConfig:
    """The named sensor model.

    ``standard``: the model tagloc's figures were measured with (:class:`SensorConfig` defaults).
    ``ov5647``: the Raspberry Pi camera v1 from its datasheet-level figures (OmniVision OV5647:
    1.4 um pixels, full well 4.3 ke-, 68 dB dynamic range), binned 2x2 as in the 1296x972 mode:

    * full well 4 x 4300 = 17 200 e- (four pixels averaged in the analog domain hold four wells);
    * read noise: 68 dB of dynamic range is a full well 2 500 times the noise floor, 1.7 e- per
      pixel; four reads averaged add in quadrature, 2 x 1.7 = 3.4 e- in binned electrons;
    * quantum efficiency for white light, averaged over the RGGB quad: a BSI pixel of that
      generation peaks near 0.5; within each colour band silicon reaches about 0.85 of its peak;
      each colour filter passes about a third of a white spectrum (the three bands split it, with
      ~0.9 peak transmission), and the IR-cut filter 0.9 of the visible: 0.5 x 0.85 x 0.33 x 0.9 =
      0.126. The ``standard`` model's 0.25 took 0.45 for the filters, 1 for the in-band response
      and no IR-cut loss.

    So the ``ov5647`` pixel gathers 0.126 / 0.25 = 0.50 of the electrons: at the same light the
    auto exposure needs 2.0x the exposure (:func:`exposure_for_sensor`), and the blur grows with
    it. A cross-check from the datasheet's photosensitivity (680 mV/lux-s without a lens), with
    the full well spanning an assumed ~1 V swing (0.23 mV/e-): 2 900 e-/lux-s per native pixel at
    the sensor face against the ``standard`` model's 4 900, a factor 1.7 (under the datasheet's
    light source, not stated).
    """
    if name == "standard":
        return SensorConfig()
    if name == "ov5647":
        return SensorConfig(quantum_efficiency=0.126, full_well_e=17200.0, read_noise_e=3.4)
    raise InputError(f"unknown sensor preset {name!r} (want one of {', '.join(SENSOR_PRESETS)})")


def exposure_for_sensor(exposure: ExposureConfig, sensor: SensorConfig) -> ExposureConfig:
    """``exposure`` with its policy scaled to ``sensor``'s sensitivity relative to the ``standard`` one.

    The motion-priority policy (``e0_lux_s``, ``max_exposure_s``) was set for the ``standard``
    sensor; a sensor gathering ``k`` times fewer electrons per lux-second needs ``k`` times the
    exposure for the same signal before gain, so both are scaled by ``k`` (capped at the frame
    interval when rendering, as always). For the ``standard`` sensor this is ``exposure`` unchanged.
    """
    ref = SensorConfig()
    k = (ref.quantum_efficiency * ref.pixel_pitch_m**2) / (sensor.quantum_efficiency * sensor.pixel_pitch_m**2)
    if abs(k - 1.0) < 1e-12:
        return exposure
    return replace(exposure, e0_lux_s=exposure.e0_lux_s * k, max_exposure_s=exposure.max_exposure_s * k)


@dataclass
class ExposureConfig:
    """Auto-exposure policy and motion sampling.

    Attributes:
        e0_lux_s: exposure time * illuminance the policy aims for (motion priority).
        max_exposure_s: longest exposure the policy allows (beyond it: more gain).
        target_mean: mean signal the gain aims for, as a fraction of full scale (linear).
        px_per_subframe: blur length between sub-frames (px); see :func:`subframe_offsets`.
        sharp_blur_px: blur up to this (px) is rendered from one sub-frame, longer blur from two or more.
        max_subframes: cap on sub-frames per frame (longer blurs are sampled more coarsely).
        rolling_shutter: expose rows at staggered times.
        readout_s: rolling shutter: time from the first row to the last.
        bands: rolling shutter: row bands rendered with their own times.
        max_range_m: floor farther than this from the camera is not rendered (mean floor instead).
    """

    e0_lux_s: float = 0.3
    max_exposure_s: float = 0.008
    target_mean: float = 0.16
    px_per_subframe: float = 0.5
    sharp_blur_px: float = 0.3
    max_subframes: int = 16
    rolling_shutter: bool = False
    readout_s: float = 0.030
    bands: int = 96
    max_range_m: float = 8.0


@dataclass(frozen=True)
class Flicker:
    """The lamps' light output ``1 + depth * cos(2 pi frequency_hz t + phase)`` (t in s, session time).

    ``depth`` is the percent flicker as a fraction, ``(max - min) / (max + min)``. IEEE 1789-2015
    rates up to 8 % at 100 Hz (0.08 times the frequency) as low risk. Fluorescent tubes on magnetic
    ballasts, and LED drivers with little smoothing, are commonly measured at 20-40 %; electronic
    ballasts and well-smoothed LED drivers at a few percent. ``frequency_hz`` is twice the mains
    frequency. ``phase`` (rad) is where the mains stood at session time 0: a camera's clock is not
    locked to it.
    """

    depth: float = 0.0
    frequency_hz: float = 100.0
    phase: float = 0.0

    def mean_over(self, t: np.ndarray, exposure_s: float) -> np.ndarray:
        """The light, relative to its mean, averaged over exposure windows of ``exposure_s`` centred
        on the times ``t`` (s): ``1 + depth sinc(pi f exposure) cos(2 pi f t + phase)``."""
        w = 2.0 * math.pi * self.frequency_hz
        half = 0.5 * w * exposure_s
        damp = math.sin(half) / half if half > 1e-12 else 1.0
        return 1.0 + self.depth * damp * np.cos(w * np.asarray(t, float) + self.phase)


@dataclass
class RenderResult:
    """One rendered frame.

    Attributes:
        image: (H, W) uint8 greyscale, before JPEG.
        exposure_s: shutter time.
        gain: analog+digital gain (1 = full well at ADC full scale).
        blur_px: estimated blur length over the exposure (largest displacement of floor points), px.
        subframes: sub-frames averaged per row band.
        mean_signal_e: mean photo-electrons per pixel (noise-free).
    """

    image: np.ndarray
    exposure_s: float
    gain: float
    blur_px: float
    subframes: int
    mean_signal_e: float


def exposure_time(lux: float, cfg: ExposureConfig, frame_interval_s: float | None = None) -> float:
    """Motion-priority shutter time (s): ``e0 / lux``, capped at ``max_exposure_s`` and the frame interval."""
    if not lux > 0:
        raise InputError(f"illuminance {lux} lux must be positive")
    t = cfg.e0_lux_s / lux
    t = min(t, cfg.max_exposure_s)
    if frame_interval_s:
        t = min(t, frame_interval_s)
    return t


def electrons_per_lux_s(optics: OpticsConfig, sensor: SensorConfig) -> float:
    """Photo-electrons per pixel per (floor lux x second) for reflectance 1 on the optical axis."""
    image_lux_per_lux = optics.transmission / (4.0 * optics.f_number**2)
    return image_lux_per_lux * PHOTONS_PER_LUX_S_M2 * sensor.pixel_pitch_m**2 * sensor.quantum_efficiency


def choose_gain(mean_signal_e: float, sensor: SensorConfig, cfg: ExposureConfig) -> float:
    """Gain that brings a mean signal of ``mean_signal_e`` to ``target_mean`` of full scale, in [1, max_gain]."""
    if mean_signal_e <= 0:
        return sensor.max_gain
    return float(np.clip(cfg.target_mean * sensor.full_well_e / mean_signal_e, 1.0, sensor.max_gain))


def subframe_offsets(blur_px: float, exposure_s: float, cfg: ExposureConfig) -> np.ndarray:
    """Times (n,) s, from the middle of the exposure, of the sub-frames that render ``blur_px`` of blur.

    ``n`` = ``blur_px / px_per_subframe`` rounded up, at least 2 once the blur exceeds
    ``sharp_blur_px`` and at most ``max_subframes``; the sub-frames sit at the middles of ``n``
    equal slices of the exposure (the midpoint rule for the exposure's integral), each standing for
    its slice. For a uniform motion of ``L`` px their average is ``L`` px of box blur sampled ``L / n``
    apart, whose variance ``L^2 / 12 (1 - 1 / n^2)`` falls short of the box's ``L^2 / 12`` by one
    step's own, ``(L / n)^2 / 12``: at most 0.02 px^2 at 0.5 px steps, 6 % of the 0.6 px lens PSF's
    0.36 px^2 (blur beyond ``max_subframes`` steps, 8 px by default, is sampled in longer steps). Sub-frames at the exposure's two ends would span all ``L`` px but give the kernel
    ``(n + 1) / (n - 1)`` times the box's variance (three times with two): measured against renders
    sampled every 0.02 px (``benchmarks/blur_sampling.py``) they were 4-7 times as far off as these at
    0.4-3 px of blur, and with two sub-frames further off than no blur at all.

    Why 0.5 px: at 3 px of blur (10.4 DN RMS from the sharp render at a sticker's edges), steps of
    1 / 0.75 / 0.5 px left 1.5 / 0.7 / 0.56 DN against that reference; 0.4-0.9 DN remain at any step,
    the renderer's own resolution (each sub-frame's reflectance is held in 8 bits, ~1 DN there). Why 0.3 px:
    a box blur of 0.3 px has a variance of 0.0075 px^2, 2 % of the PSF's, so the two together are
    1 % wider than the PSF alone; shorter blur is rendered sharp. Up to simulator revision 5 blur
    up to 1.5 px was not rendered at all (one sub-frame), and longer blur with one sub-frame per 1.5 px.
    """
    n = math.ceil(blur_px / cfg.px_per_subframe - 1e-9)
    if blur_px > cfg.sharp_blur_px:
        n = max(n, 2)
    n = int(np.clip(n, 1, cfg.max_subframes))
    return exposure_s * ((np.arange(n) + 0.5) / n - 0.5)


def expected_blur_px(focal_px: float, speed_mps: float, exposure_s: float, distance_m: float) -> float:
    """Blur length (px) of a point at ``distance_m`` moving ``speed_mps`` parallel to the image plane:
    ``f * v * t / D`` (the paper's condition: 2571 px, 1 m/s, 1 m -> 1/2571 s for 1 px)."""
    return focal_px * speed_mps * exposure_s / distance_m


@lru_cache(maxsize=8)
def _undistort_grid(key: tuple) -> tuple[np.ndarray, np.ndarray]:
    """(map_x, map_y) float32 (H, W): ideal pixel position of every distorted sensor pixel."""
    K = np.array(key[0]).reshape(3, 3)
    dist = np.array(key[1])
    w, h = key[2], key[3]
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    if not np.any(dist):
        return uu.astype(np.float32), vv.astype(np.float32)
    pts = np.stack([uu.ravel(), vv.ravel()], axis=1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pts, K, dist, P=K).reshape(h, w, 2)
    return und[..., 0].astype(np.float32), und[..., 1].astype(np.float32)


@dataclass
class _Band:
    rows: slice
    roi: tuple[int, int, int, int]  # x0, y0, w, h on the ideal canvas
    map1: np.ndarray  # fixed-point remap maps (cv2.convertMaps), 1/32 px interpolation steps
    map2: np.ndarray
    dt: float  # exposure-centre delay of this band relative to the frame time


def _floor_hits(
    T_world_camera: np.ndarray, K_inv: np.ndarray, pix: np.ndarray, max_range: float
) -> tuple[np.ndarray, np.ndarray]:
    """World floor points (N, 2) seen at canvas pixels (N, 2), and which rays really hit the floor."""
    d = (np.c_[pix, np.ones(len(pix))] @ K_inv.T) @ T_world_camera[:3, :3].T
    c = T_world_camera[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(d[:, 2] < 0, -c[2] / d[:, 2], np.inf)
    s_max = max_range / np.linalg.norm(d, axis=1)
    ok = np.isfinite(s) & (s <= s_max)
    s = np.minimum(s, s_max)
    return c[:2] + s[:, None] * d[:, :2], ok


class Renderer:
    """Renders frames of one camera over one floor (see the module docstring).

    ``camera`` is the true calibration the frames are formed with; its distortion is applied exactly.
    """

    def __init__(
        self,
        floor: Floor,
        camera: Camera,
        optics: OpticsConfig | None = None,
        sensor: SensorConfig | None = None,
        exposure: ExposureConfig | None = None,
        seed: int = 0,
        flicker: Flicker | None = None,
        lamps: Lamps | None = None,
        legs: Legs | None = None,
    ):
        self.floor = floor
        self.lamps = lamps
        self.legs = legs
        self.flicker = flicker if flicker is not None and flicker.depth > 0 else None
        self.camera = camera
        self.optics = optics or OpticsConfig()
        self.sensor = sensor or SensorConfig()
        self.exposure = exposure or ExposureConfig()
        key = (tuple(camera.K.ravel()), tuple(camera.dist.ravel()), camera.width, camera.height)
        mx, my = _undistort_grid(key)
        x0, y0 = math.floor(float(mx.min())) - 2, math.floor(float(my.min())) - 2
        x1, y1 = math.ceil(float(mx.max())) + 3, math.ceil(float(my.max())) + 3
        self.canvas_origin = (x0, y0)
        self.canvas_size = (x1 - x0, y1 - y0)
        self.K_canvas = camera.K.copy()
        self.K_canvas[0, 2] -= x0
        self.K_canvas[1, 2] -= y0
        self._K_inv = np.linalg.inv(self.K_canvas)
        mx, my = mx - x0, my - y0
        H, W = camera.height, camera.width
        n_bands = max(1, min(self.exposure.bands, H)) if self.exposure.rolling_shutter else 1
        edges = np.linspace(0, H, n_bands + 1).round().astype(int)
        self._bands = []
        for r0, r1 in zip(edges[:-1], edges[1:]):
            bx, by = mx[r0:r1], my[r0:r1]
            ax0, ay0 = max(0, math.floor(float(bx.min())) - 1), max(0, math.floor(float(by.min())) - 1)
            ax1 = min(self.canvas_size[0], math.ceil(float(bx.max())) + 2)
            ay1 = min(self.canvas_size[1], math.ceil(float(by.max())) + 2)
            dt = float(row_delay_s((r0 + r1 - 1) / 2, H, self.exposure.readout_s)) if n_bands > 1 else 0.0
            m1, m2 = cv2.convertMaps(np.ascontiguousarray(bx - ax0), np.ascontiguousarray(by - ay0), cv2.CV_16SC2)
            self._bands.append(_Band(slice(r0, r1), (ax0, ay0, ax1 - ax0, ay1 - ay0), m1, m2, dt))
        # Fixed per-pixel response: natural vignetting (field angle from the ideal ray) and PRNU.
        xn = (mx - self.K_canvas[0, 2]) / self.K_canvas[0, 0]
        yn = (my - self.K_canvas[1, 2]) / self.K_canvas[1, 1]
        cos2 = 1.0 / (1.0 + xn * xn + yn * yn)
        self._fixed = (cos2 ** (2.0 * self.optics.vignetting)).astype(np.float32)
        if self.sensor.noise and self.sensor.prnu > 0:
            prnu = np.random.default_rng([seed, 17]).standard_normal((H, W), np.float32)
            self._fixed *= 1.0 + self.sensor.prnu * prnu
        self._mosaic: tuple[np.ndarray, np.ndarray, tuple[float, float, float, float]] | None = None
        self._raster2 = lru_cache(maxsize=256)(self._make_raster2)
        levels = 2**self.sensor.adc_bits
        self._lut = np.clip(
            255.0 * (np.arange(levels) / (levels - 1)) ** (1.0 / self.sensor.gamma) + 0.5, 0, 255
        ).astype(np.uint8)

    # -- geometry -------------------------------------------------------------------------------

    def _canvas_corners(self, roi: tuple[int, int, int, int] | None = None, n: int = 5) -> np.ndarray:
        x0, y0, w, h = roi or (0, 0, *self.canvas_size)
        t = np.linspace(0, 1, n)
        xs, ys = x0 - 0.5 + t * w, y0 - 0.5 + t * h
        return np.vstack(
            [
                np.c_[xs, np.full(n, ys[0])],
                np.c_[np.full(n, xs[-1]), ys],
                np.c_[xs[::-1], np.full(n, ys[-1])],
                np.c_[np.full(n, xs[0]), ys[::-1]],
            ]
        )

    def footprint(self, T_world_camera: np.ndarray) -> np.ndarray:
        """Floor polygon (M, 2) seen by the canvas at this pose (clipped at ``max_range_m``)."""
        xy, _ = _floor_hits(T_world_camera, self._K_inv, self._canvas_corners(), self.exposure.max_range_m)
        return xy

    def _ensure_mosaic(self, poses: np.ndarray) -> None:
        boxes = np.vstack([self.footprint(T) for T in poses])
        lo, hi = boxes.min(axis=0), boxes.max(axis=0)
        if self._mosaic is not None:
            b = self._mosaic[2]
            if lo[0] >= b[0] and lo[1] >= b[1] and hi[0] <= b[2] and hi[1] <= b[3]:
                return
        tile = self.floor.config.tile_m
        # A margin of one tile lets the next frames reuse the mosaic while the camera moves on.
        xmin, ymin = math.floor(lo[0] / tile) * tile - tile, math.floor(lo[1] / tile) * tile - tile
        xmax, ymax = math.ceil(hi[0] / tile) * tile + tile, math.ceil(hi[1] / tile) * tile + tile
        img, A = self.floor.mosaic(xmin, ymin, xmax - 1e-9, ymax - 1e-9)
        self._mosaic = (img, A, (xmin, ymin, xmax, ymax))

    def _make_raster2(self, row: int, size: int) -> tuple[np.ndarray, np.ndarray]:
        """Sticker raster with its coverage mask as 2 channels, and raster px -> world floor (3, 3)."""
        r = self.floor.sticker_raster(row, size)
        two = cv2.merge([r, np.full_like(r, 255)])
        A = np.vstack([sticker_pixel_to_metres(size), [0.0, 0.0, 1.0]])
        c, s = math.cos(self.floor.stickers.yaw[row]), math.sin(self.floor.stickers.yaw[row])
        x, y = self.floor.stickers.xy[row]
        P = np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])
        return two, P @ A

    def homography(self, T_world_camera: np.ndarray) -> np.ndarray:
        """(3, 3) floor (x, y, 1) in world metres -> ideal canvas pixel."""
        T_cw = np.linalg.inv(T_world_camera)
        return self.K_canvas @ np.column_stack([T_cw[:3, 0], T_cw[:3, 1], T_cw[:3, 3]])

    def _render_roi(self, T_world_camera: np.ndarray, roi: tuple[int, int, int, int], rows: np.ndarray) -> np.ndarray:
        """Reflectance (h, w) uint8 of the canvas ROI at one pose (floor plus stickers)."""
        x0, y0, w, h = roi
        img, A, _ = self._mosaic
        Hw = self.homography(T_world_camera)
        S = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
        mean = float(self.floor.mean_reflectance * 255.0)
        out = cv2.warpPerspective(
            img,
            S @ Hw @ np.linalg.inv(A),
            (w, h),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=mean,
        )
        # Rays that miss the floor (above the horizon) would see the plane behind the camera.
        corners = self._canvas_corners(roi, 2)
        d_z = ((np.c_[corners, np.ones(len(corners))] @ self._K_inv.T) @ T_world_camera[:3, :3].T)[:, 2]
        if np.any(d_z >= 0):
            uu, vv = np.meshgrid(np.arange(x0, x0 + w), np.arange(y0, y0 + h))
            row = (self._K_inv.T @ T_world_camera[:3, :3].T)[:, 2]
            out[(uu * row[0] + vv * row[1] + row[2]) >= -1e-3] = int(mean)
        for r in rows:
            self._composite(out, Hw, S, int(r), w, h)
        return out

    def _composite(self, out: np.ndarray, Hw: np.ndarray, S: np.ndarray, row: int, w: int, h: int) -> None:
        """Draw floor sticker ``row`` over ``out`` (in place)."""
        xy = self.floor.stickers.xy[row]
        c, s = math.cos(self.floor.stickers.yaw[row]), math.sin(self.floor.stickers.yaw[row])
        half = 0.05
        corners = xy + np.array([[-half, -half], [half, -half], [half, half], [-half, half]]) @ np.array(
            [[c, s], [-s, c]]
        )
        p = np.c_[corners, np.ones(4)] @ (S @ Hw).T
        if np.any(p[:, 2] <= 1e-6):
            return
        p = p[:, :2] / p[:, 2:]
        bx0, by0 = max(0, math.floor(p[:, 0].min()) - 1), max(0, math.floor(p[:, 1].min()) - 1)
        bx1, by1 = min(w, math.ceil(p[:, 0].max()) + 2), min(h, math.ceil(p[:, 1].max()) + 2)
        if bx1 <= bx0 or by1 <= by0:
            return
        side = float(np.max(np.hypot(*(p - np.roll(p, 1, axis=0)).T)))
        two, P = self._raster2(row, sticker_size_px(side))
        M = np.array([[1.0, 0.0, -bx0], [0.0, 1.0, -by0], [0.0, 0.0, 1.0]]) @ S @ Hw @ P
        warped = cv2.warpPerspective(
            two, M, (bx1 - bx0, by1 - by0), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )
        m = warped[..., 1].astype(np.float32) * (1.0 / 255.0)
        roi = out[by0:by1, bx0:bx1]
        base = roi.astype(np.float32)
        roi[:] = np.clip(base + m * (warped[..., 0].astype(np.float32) - base) + 0.5, 0, 255).astype(np.uint8)

    def visible_rows(self, poses: np.ndarray) -> np.ndarray:
        """Rows of ``floor.stickers`` that may appear at any of ``poses`` (N, 4, 4)."""
        rows: set[int] = set()
        for T in poses:
            poly = self.footprint(T)
            centre = poly.mean(axis=0)
            grown = centre + (poly - centre) * 1.05 + np.sign(poly - centre) * 0.1
            rows.update(map(int, self.floor.stickers.in_polygon(grown)))
        return np.array(sorted(rows), np.int64)

    def blur_px(self, pose_at: PoseFn, t_mid: float, exposure_s: float) -> float:
        """Largest image displacement (canvas px) of floor points seen at ``t_mid`` over the exposure."""
        W, H = self.canvas_size
        grid = np.array([[u, v] for u in (0.2 * W, 0.5 * W, 0.8 * W) for v in (0.2 * H, 0.5 * H, 0.8 * H)])
        T0, T_mid, T1 = pose_at(np.array([t_mid - exposure_s / 2, t_mid, t_mid + exposure_s / 2]))
        xy, ok = _floor_hits(T_mid, self._K_inv, grid, self.exposure.max_range_m)
        if not ok.any():
            return 0.0
        pts = np.c_[xy[ok], np.ones(int(ok.sum()))]
        a, b = pts @ self.homography(T0).T, pts @ self.homography(T1).T
        return float(np.max(np.hypot(*(a[:, :2] / a[:, 2:] - b[:, :2] / b[:, 2:]).T)))

    # -- frame ----------------------------------------------------------------------------------

    def render(
        self,
        pose_at: PoseFn,
        t_mid: float,
        lux: float,
        rng: np.random.Generator,
        frame_interval_s: float | None = None,
        exposure_s: float | None = None,
        gain: float | None = None,
        body: np.ndarray | None = None,
    ) -> RenderResult:
        """Render the frame whose exposure is centred on ``t_mid`` (s) under ``lux`` on the floor.

        ``pose_at`` gives the true camera pose at any time; ``rng`` draws the noise. ``exposure_s``
        and ``gain`` override the auto exposure. ``body`` (3,): where the operator's body axis
        stands at ``t_mid`` and its heading, (x, y, yaw) m and rad (:meth:`tagloc.sim.lamps.Lamps.axis`),
        for its shadow under ``lamps`` (none without either).
        """
        cfg = self.exposure
        t_exp = exposure_s if exposure_s is not None else exposure_time(lux, cfg, frame_interval_s)
        blur = self.blur_px(pose_at, t_mid, t_exp)
        offsets = subframe_offsets(blur, t_exp, cfg)
        n_sub = len(offsets)
        times = np.concatenate([t_mid + b.dt + offsets for b in self._bands])
        poses = pose_at(times).reshape(len(self._bands), n_sub, 4, 4)
        self._ensure_mosaic(poses[:, [0, -1]].reshape(-1, 4, 4))
        rows = self.visible_rows(
            poses[:, [0, -1]].reshape(-1, 4, 4)[:: max(1, len(self._bands) // 4)]
            if len(self._bands) > 1
            else poses[0, [0, -1]]
        )
        H, W = self.camera.height, self.camera.width
        lin = np.empty((H, W), np.float32)
        for b, band_poses, band_times in zip(self._bands, poses, times.reshape(len(self._bands), n_sub)):
            acc = np.zeros((b.roi[3], b.roi[2]), np.float32)
            for T, t_sub in zip(band_poses, band_times):
                view = self._render_roi(T, b.roi, rows)
                if self.legs is not None:
                    self.legs.paint(view, T, self.K_canvas, float(t_sub), offset=b.roi[:2])
                acc += view
            acc *= 1.0 / (255.0 * n_sub)
            lin[b.rows] = cv2.remap(acc, b.map1, b.map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        if self.optics.psf_sigma_px > 0:
            lin = cv2.GaussianBlur(lin, (0, 0), self.optics.psf_sigma_px)
        lin *= self._fixed
        lin *= self._illumination(pose_at(np.array([t_mid]))[0], body)
        e = lin
        e *= electrons_per_lux_s(self.optics, self.sensor) * lux * t_exp
        e += self.sensor.dark_current_e_s * t_exp
        mean_e = float(e.mean())
        g = gain if gain is not None else choose_gain(mean_e, self.sensor, cfg)
        if self.flicker is not None:
            H = self.camera.height
            # Each row's exposure window is centred on its own read-out time (0 for a global shutter).
            rows = np.arange(H)
            readout = cfg.readout_s if cfg.rolling_shutter else 0.0
            light = self.flicker.mean_over(t_mid + row_delay_s(rows, H, readout), t_exp).astype(np.float32)
            dark = np.float32(self.sensor.dark_current_e_s * t_exp)  # the sensor's own: not the lamps'
            e -= dark
            e *= light[:, None]
            e += dark
        return RenderResult(self._read_out(e, g, rng), t_exp, g, blur, n_sub, mean_e)

    def _illumination(self, T_world_camera: np.ndarray, body: np.ndarray | None = None) -> np.ndarray | float:
        """The floor's illumination pattern in this view, times the body's shadow if there is one."""
        shadow = self.lamps is not None and body is not None
        pattern = self.floor.config.texture and self.floor.config.illumination_variation != 0
        if not (shadow or pattern):
            return 1.0
        H, W = self.camera.height, self.camera.width
        # The shadow's penumbra is 11-14 cm wide on the floor, ~100 px in the image: a finer grid for it.
        nx, ny = (33, 25) if shadow else (17, 13)
        gx, gy = np.meshgrid(np.linspace(0, W - 1, nx), np.linspace(0, H - 1, ny))
        pix = np.c_[gx.ravel(), gy.ravel()] - self.canvas_origin
        xy, _ = _floor_hits(T_world_camera, self._K_inv, pix, self.exposure.max_range_m)
        coarse = self.floor.illumination(xy) if pattern else np.ones(len(xy))
        if shadow:
            coarse = coarse * self.lamps.shadow(xy, body)
        coarse = coarse.reshape(gx.shape).astype(np.float32)
        return cv2.resize(coarse, (W, H), interpolation=cv2.INTER_LINEAR)

    def _read_out(self, e: np.ndarray, gain: float, rng: np.random.Generator) -> np.ndarray:
        """Electrons (H, W) float32 (modified) -> noisy 8-bit image."""
        s = self.sensor
        if s.noise:
            # Shot noise (Poisson, variance = mean) and read noise, drawn together as their Gaussian
            # limit. OpenCV's generator is ~5x faster than numpy's; it is seeded from ``rng``.
            sigma = cv2.sqrt(e + np.float32(s.read_noise_e**2))
            noise = np.empty_like(e)
            cv2.setRNGSeed(int(rng.integers(1, 2**31 - 1)))
            cv2.randn(noise, 0.0, 1.0)
            e += cv2.multiply(sigma, noise)
        levels = 2**s.adc_bits
        np.clip(e, 0.0, s.full_well_e, out=e)
        dn = cv2.multiply(e, gain * (levels - 1) / s.full_well_e)
        np.clip(dn + 0.5, 0, levels - 1, out=dn)
        return np.take(self._lut, dn.astype(np.uint16))
