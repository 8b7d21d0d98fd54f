"""The blur a frame put on one sticker, measured on the black frame's four edges.

Each edge's profile (floor, black frame, white quiet zone, symbols) is fitted with five unknown
levels blurred by candidate motion lengths and lens spreads; the best fit gives the motion extent
along the raster's x and y and the optics' sigma (:func:`blur_estimate`). The module least-squares
stage (:mod:`tagloc.vision.decode.lsq`) builds its PSF from them.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from tagloc.core.camera import Camera
from tagloc.core.types import Detection
from tagloc.vision.decode.grid import FRAME_PX, MODULE_PX, RASTER_PX
from tagloc.vision.rectify import RectifyConfig, distorted_mapping

_MARGIN = 24  # raster px of floor kept around the sticker when measuring the blur


def _margin_raster(gray: np.ndarray, detection: Detection, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Raster at the decode scale with ``_MARGIN`` px of floor around the sticker, and its scale.

    Only used to measure blur, so the one-homography approximation of the distortion is enough.
    Returns the raster and (2,) raster px per image px along the raster's x and y at its centre.
    """
    H, _, _ = distorted_mapping(detection, camera, RASTER_PX, RectifyConfig(max_residual_px=np.inf))
    shift = np.array([[1.0, 0, -_MARGIN], [0, 1.0, -_MARGIN], [0, 0, 1.0]])
    n = RASTER_PX + 2 * _MARGIN
    raster = cv2.warpPerspective(
        gray, H @ shift, (n, n), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE
    )
    c = RASTER_PX / 2
    pts = cv2.perspectiveTransform(np.array([[[c, c], [c + 1, c], [c, c + 1]]]), H)[0]
    scale = 1.0 / np.linalg.norm(pts[1:] - pts[0], axis=1)
    return raster, scale


_BLUR_LENGTHS = tuple(range(30))  # candidate motion-blur lengths (raster px)
_EDGE_SHIFTS = tuple(range(-3, 4))  # candidate edge offsets (raster px) from detector corner error
_SCALE_STEP = 0.5  # raster-per-image px scale is quantised to this to share cached models
#: Candidate optics + resampling spreads (image px, Gaussian sigma) of the sharp image: a property of
#: the lens that the frame edges reveal together with the motion.
_OPTICS_SIGMAS = (0.5, 0.8)


def _box(width: float) -> np.ndarray:
    """Normalised 1-D box of (fractional) ``width`` samples, centred, ends weighted by the fraction."""
    if width <= 1.0:
        return np.ones(1)
    n = int(np.ceil(width)) | 1  # odd, so the box stays centred
    k = np.ones(n)
    k[0] = k[-1] = (width - (n - 2)) / 2
    return k / k.sum()


#: Raster-per-image-pixel scales whose edge models :func:`prepare` makes ahead: 1-12 covers the
#: scales seen on the eval and speed walks' ~4000 least-squares decodes (1.5-11, and one at 20.5).
_PREPARED_SCALES = tuple(np.arange(1.0, 12.01, _SCALE_STEP))
#: The profile length :func:`blur_estimate` fits (floor margin, black frame, quiet zone, one module
#: column and 30 px of symbols).
_PROFILE_PX = _MARGIN + FRAME_PX + MODULE_PX + 30


# 64 entries of (7, 30, 77, 5) float32 (323 kB each): every prepared model and a few more.
@lru_cache(maxsize=64)
def _level_bases(n: int, scale: float, optics_px: float) -> np.ndarray:
    """(S, L, n, 5) orthonormal bases of the blurred five-level frame-edge profile models.

    One per (edge shift, motion length): the columns span the blurred indicator profiles of the
    five levels (floor, black frame, white quiet zone, the symbols' first module column, which is
    finder or timing pattern and so not an average grey, and the rest of the symbols). Every model
    also carries the sharp image's own spread at this raster ``scale`` (raster px per image px):
    one image pixel's integration and ``optics_px`` (Gaussian sigma, image px) of optics.
    """
    x = np.arange(n)
    r = int(np.ceil(3 * optics_px * scale))
    base = np.convolve(_box(scale), np.exp(-0.5 * (np.arange(-r, r + 1) / (optics_px * scale)) ** 2))
    shifts = np.asarray(_EDGE_SHIFTS)[:, None]
    edges = _MARGIN + shifts + np.array([0, FRAME_PX, FRAME_PX + MODULE_PX, FRAME_PX + 2 * MODULE_PX])[None]  # (S, 4)
    out = np.empty((len(_EDGE_SHIFTS), len(_BLUR_LENGTHS), n, 5), np.float32)
    for li, length in enumerate(_BLUR_LENGTHS):
        k = np.convolve(_box(length), base)
        cdf = np.concatenate([[0.0], np.cumsum(k / k.sum())])
        c = (len(k) - 1) // 2
        # A step at e blurred by k is the kernel's CDF at x - e + c; each level's blurred
        # indicator is the difference of the blurred steps at its two ends.
        steps = cdf[np.clip(x[None, None] - edges[:, :, None] + c + 1, 0, len(k))]  # (S, 4, n)
        ones = np.ones((len(_EDGE_SHIFTS), 1, n))
        up = np.concatenate([ones, steps], 1)
        down = np.concatenate([steps, 0 * ones], 1)
        out[:, li] = np.linalg.qr(np.transpose(up - down, (0, 2, 1)))[0]
    return out


def _edge_fit(profiles: np.ndarray, scale: float, optics_px: float) -> tuple[np.ndarray, float]:
    """Best motion length (raster px) for each of ``profiles`` (P, n), and the summed residual.

    A profile runs from the floor (``_MARGIN`` px) across the black frame (16 px) and the white
    quiet zone (7 px) into the symbols, averaged along the edge so the symbols (past their first
    module column) average to a flat grey: five unknown levels. Each candidate (edge shift, length)
    is scored by the residual of the least-squares fit of those levels; the shift absorbs the
    detector's corner error.
    """
    q = max(_SCALE_STEP, round(scale / _SCALE_STEP) * _SCALE_STEP)
    Q = _level_bases(profiles.shape[1], q, optics_px)
    # (P, n) @ (S, L, n, 5) -> (S, L, P, 5): one batched BLAS product (einsum's loop is 6x slower).
    proj = np.matmul(profiles.astype(np.float32), Q)
    resid = np.sum(profiles**2, axis=1) - np.sum(proj.astype(np.float64) ** 2, axis=3)  # (S, L, P)
    flat = resid.reshape(-1, len(profiles))
    best = flat.argmin(axis=0)
    return np.asarray(_BLUR_LENGTHS, float)[best % len(_BLUR_LENGTHS)], float(flat.min(axis=0).sum())


def blur_extent(gray: np.ndarray, detection: Detection, camera: Camera) -> tuple[float, float]:
    """Motion-blur extent (raster px) along the raster's x and y, from the four frame edges.

    The lens's own spread is fitted too (shared by all four edges), so that it is not mistaken
    for motion.
    """
    lx, ly, _ = blur_estimate(gray, detection, camera)
    return lx, ly


def blur_estimate(gray: np.ndarray, detection: Detection, camera: Camera) -> tuple[float, float, float]:
    """(motion extent along raster x, along raster y (raster px), optics sigma (image px)) from the
    four frame edges; see :func:`blur_extent`."""
    m, scale = _margin_raster(gray, detection, camera)
    m = m.astype(np.float64)
    band = slice(_MARGIN + 40, _MARGIN + RASTER_PX - 40)
    depth = _PROFILE_PX
    px = np.stack([m[band, :depth].mean(0), m[band, ::-1][:, :depth].mean(0)])  # left, right
    py = np.stack([m[:depth, band].mean(1), m[::-1][:depth, band].mean(1)])  # top, bottom
    best = None
    for sigma in _OPTICS_SIGMAS:
        lx, rx = _edge_fit(px, float(scale[0]), sigma)
        ly, ry = _edge_fit(py, float(scale[1]), sigma)
        if best is None or rx + ry < best[0]:
            best = (rx + ry, float(lx.mean()), float(ly.mean()), sigma)
    return best[1], best[2], best[3]


def prepare() -> None:
    """Make now the edge models the first least-squares decodes would make (1.5 ms for each new
    scale and lens spread, up to four in one decode: 0.07 s in all): what a live loop does before
    its first frame (:meth:`tagloc.pipeline.localiser.Localiser.warm_up`)."""
    for scale in _PREPARED_SCALES:
        for sigma in _OPTICS_SIGMAS:
            _level_bases(_PROFILE_PX, float(scale), sigma)
