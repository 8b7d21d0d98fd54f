"""Blur-aware module estimation: every data module of a blurred sticker estimated by least squares.

The module grid is known exactly, so instead of sampling a blurred, noisy raster at module centres,
each quadrant's 64 data modules are estimated jointly: the raster (in linear light) is modelled as
black level + contrast * (PSF * sharp sticker), where the sharp sticker is known everywhere except
at the data modules (frame, quiet zones and every symbol's finder/timing border are fixed), and
the PSF is the lens + pixel spread mapped into the raster plus the motion measured on the frame
edges (:mod:`tagloc.vision.decode.blur`). That is linear in (black level, contrast, data modules),
so one small ridge-regularised least-squares solve per quadrant uses every pixel of every module
and undoes the blur's cross-talk between neighbouring modules.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from tagloc.core.camera import Camera
from tagloc.core.sticker import parse_payload
from tagloc.core.types import Detection
from tagloc.vision.decode.backends import zxing_read
from tagloc.vision.decode.config import DecodeConfig
from tagloc.vision.decode.grid import (
    FRAME_PX,
    MODULE_PX,
    QUAD_ORIGIN,
    QUAD_PX,
    RASTER_PX,
    Symbol,
    border_template,
    clean_symbols,
    module_samples,
)
from tagloc.vision.rectify import ideal_homography


def _line_kernel(dx: float, dy: float) -> np.ndarray:
    """Normalised box kernel along the segment (-dx/2, -dy/2)-(dx/2, dy/2), anti-aliased.

    The same segment as :func:`tagloc.vision.psf.motion_kernel` (identification's), sampled more
    coarsely (4 points per px) and accumulated in float32. Kept apart on purpose: the decoder's
    thresholds and flips were measured with it, and building the PSF from the shared kernel
    instead changed decode results (measured on the six ``tagloc eval`` walks: on s01 one read of
    the full mode's 249 fixes and one unmapped read were lost, which moved the baselines' s01
    figures), so merging them is a behaviour change to make on purpose, not in a tidy-up.
    """
    length = float(np.hypot(dx, dy))
    size = int(np.ceil(length)) // 2 * 2 + 3
    k = np.zeros((size, size), np.float32)
    c = (size - 1) / 2
    n = max(int(length * 4), 2)
    t = np.linspace(-0.5, 0.5, n)
    xs, ys = c + t * dx, c + t * dy
    x0, y0 = np.floor(xs).astype(int), np.floor(ys).astype(int)
    fx, fy = xs - x0, ys - y0
    # Bilinear splat of the sample points along the segment.
    np.add.at(k, (y0, x0), (1 - fx) * (1 - fy))
    np.add.at(k, (y0, x0 + 1), fx * (1 - fy))
    np.add.at(k, (y0 + 1, x0), (1 - fx) * fy)
    np.add.at(k, (y0 + 1, x0 + 1), fx * fy)
    return k / k.sum()


def blur_psf(cov: np.ndarray, motion: tuple[float, float]) -> np.ndarray:
    """Normalised raster-space PSF (odd square): Gaussian of covariance ``cov`` (2, 2) (raster px^2,
    (x, y) order) convolved with a line of extent ``motion`` (dx, dy) raster px."""
    r = int(np.ceil(3.0 * np.sqrt(np.linalg.eigvalsh(cov).max())))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1].astype(np.float64)
    inv = np.linalg.inv(cov)
    g = np.exp(-0.5 * (inv[0, 0] * xx * xx + 2 * inv[0, 1] * xx * yy + inv[1, 1] * yy * yy))
    if np.hypot(*motion) > 1.0:
        line = _line_kernel(*motion)  # point-symmetric, so correlation = convolution
        h = line.shape[0] // 2
        g = cv2.filter2D(np.pad(g, h).astype(np.float32), -1, line, borderType=cv2.BORDER_CONSTANT)
    return (g / g.sum()).astype(np.float32)


def _raster_cov(detection: Detection, camera: Camera, sigma_px: float) -> np.ndarray:
    """(2, 2) raster-space covariance of an isotropic image-space spread of ``sigma_px`` (image px),
    through the raster -> image mapping's Jacobian at the sticker centre."""
    H = ideal_homography(detection, camera, RASTER_PX)
    c = RASTER_PX / 2
    p = cv2.perspectiveTransform(np.array([[[c, c], [c + 1, c], [c, c + 1]]]), H)[0]
    A = np.column_stack([p[1] - p[0], p[2] - p[0]])  # d(image)/d(raster)
    Ai = np.linalg.inv(A)
    return sigma_px**2 * Ai @ Ai.T


_CANVAS = 2 * QUAD_PX + 1  # module-centred canvas covering every offset inside a quadrant


@lru_cache(maxsize=4)
def _design_index(step: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels used in a quadrant and where they fall relative to each data module's centre.

    Returns rows (P,), cols (P,) relative to the quadrant's origin and (P, 64) flat indices of the
    pixel-minus-module-centre offsets in a module-centred ``_CANVAS``-square image. The same for
    every quadrant, so the blurred module design is built once per PSF.
    """
    i, j = np.mgrid[1:9, 1:9]
    mr, mc = (MODULE_PX + MODULE_PX * i + MODULE_PX // 2).ravel(), (MODULE_PX + MODULE_PX * j + MODULE_PX // 2).ravel()
    g = np.arange(step // 2, QUAD_PX, step)
    rr, cc = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    # Flat index into a (_CANVAS, _CANVAS) image centred on the module: offsets never leave it.
    flat = (rr[:, None] - mr[None] + QUAD_PX) * _CANVAS + (cc[:, None] - mc[None] + QUAD_PX)
    return rr, cc, flat


def _known_sticker(k: int, shifts: np.ndarray) -> np.ndarray:
    """Sharp sticker reflectance (200, 200) float32 in raster orientation: 0 ink, 1 paper, 0.5 on
    every data module (unknown); symbol borders turned by ``k`` and moved by ``shifts`` (4, 2)."""
    mask, dark = border_template()
    sym = np.where(mask, np.where(dark, 0.0, 1.0), 0.5)
    sym = np.kron(np.rot90(sym, -k), np.ones((MODULE_PX, MODULE_PX)))
    s = np.zeros((RASTER_PX, RASTER_PX), np.float32)
    s[FRAME_PX : RASTER_PX - FRAME_PX, FRAME_PX : RASTER_PX - FRAME_PX] = 1.0
    for (r0, c0), (dy, dx) in zip(QUAD_ORIGIN, shifts):
        r, c = r0 + MODULE_PX + dy, c0 + MODULE_PX + dx
        s[r : r + 10 * MODULE_PX, c : c + 10 * MODULE_PX] = sym
    return s


def _blurred_module(psf: np.ndarray) -> np.ndarray:
    """One module (a MODULE_PX square of ones) blurred by ``psf``, on a ``_CANVAS`` square centred
    on the module's centre pixel: float32 (_CANVAS, _CANVAS).

    filter2D (correlation) of the module with the PSF is the PSF, flipped, summed over a module-sized
    box: a box filter of the small PSF instead of a large filter over the mostly empty canvas.
    """
    h = MODULE_PX // 2
    padded = np.pad(psf[::-1, ::-1].astype(np.float32), h)
    blurred = cv2.boxFilter(padded, -1, (MODULE_PX, MODULE_PX), normalize=False, borderType=cv2.BORDER_CONSTANT)
    canvas = np.zeros((_CANVAS, _CANVAS), np.float32)
    r = blurred.shape[0] // 2
    c = QUAD_PX  # the module's centre pixel
    if r > c:  # a PSF wider than the canvas (never at RASTER_PX: blur_psf stays under ~60 px)
        blurred, r = blurred[r - c : r + c + 1, r - c : r + c + 1], c
    canvas[c - r : c + r + 1, c - r : c + r + 1] = blurred
    return canvas


def module_estimates(
    rect: np.ndarray,
    psf: np.ndarray,
    k: int,
    shifts: np.ndarray,
    gamma: float = 2.2,
    ridge: float = 0.05,
    step: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares reflectance of every data module, in raster orientation.

    Args:
        rect: (200, 200) uint8 raster.
        psf: raster-space PSF (odd square, sums to 1).
        k, shifts: symbol turn and per-quadrant grid shifts from :func:`module_samples`.
        gamma: the image's tone curve, undone first so that the blur model is linear.
        ridge: Tikhonov weight pulling modules towards grey, relative to the PSF-blurred module's
            energy (keeps noise from exploding where the blur removes a module pattern).
        step: raster px between the pixels used (the raster oversamples the image ~4x).
    Returns:
        (4, 10, 10) float32 reflectance (0 ink .. 1 paper; the fixed border is filled in from the
        template, data modules estimated) and (4,) rms fit residual per quadrant.
    """
    lin = _linearise(rect, gamma)
    known = cv2.filter2D(_known_sticker(k, shifts), -1, psf, borderType=cv2.BORDER_REPLICATE)
    canvas = _blurred_module(psf)
    rr, cc, flat = _design_index(step)
    D = canvas.ravel()[flat]  # (P, 64) blurred data-module indicators at the pixels used
    DtD = (D.T @ D).astype(np.float64) + ridge * float(np.sum(canvas * canvas)) * np.eye(64)
    Dt1 = D.sum(0, dtype=np.float64)
    n = len(rr)
    mask, dark = border_template()
    border = np.rot90(np.where(dark, 0.0, 1.0), -k).astype(np.float32)
    # The four quadrants' systems at once (rows p): the same design D, their own pixels.
    origin = np.asarray(QUAD_ORIGIN) + np.asarray(shifts)  # (4, 2) row, col of each shifted grid
    r, cl = rr[None] + origin[:, 0:1], cc[None] + origin[:, 1:2]  # (4, P)
    kq, y = known[r, cl], lin[r, cl]  # (4, P)
    N = np.empty((4, 66, 66))
    N[:, 0, 0] = n
    N[:, 0, 1] = N[:, 1, 0] = kq.sum(axis=1, dtype=np.float64)
    N[:, 1, 1] = np.einsum("pi,pi->p", kq, kq, dtype=np.float64)
    N[:, 0, 2:] = N[:, 2:, 0] = Dt1
    N[:, 1, 2:] = N[:, 2:, 1] = kq @ D
    N[:, 2:, 2:] = DtD
    rhs = np.empty((4, 66))
    rhs[:, 0] = y.sum(axis=1, dtype=np.float64)
    rhs[:, 1] = np.einsum("pi,pi->p", kq, y, dtype=np.float64)
    rhs[:, 2:] = y @ D
    sol = np.linalg.solve(N, rhs[:, :, None])[:, :, 0]  # (4, 66)
    fit = sol[:, 0:1] + sol[:, 1:2] * kq + sol[:, 2:].astype(np.float32) @ D.T
    resid = np.sqrt(np.mean((fit - y) ** 2, axis=1))
    contrast = np.where(np.abs(sol[:, 1]) > 1e-6, sol[:, 1], 1e-6)
    out = np.repeat(border[None], 4, axis=0)
    # Data modules are the symbol's interior 8x8 (raster-oriented); the border is the template.
    out[:, 1:9, 1:9] = (sol[:, 2:] / contrast[:, None] + 0.5).reshape(4, 8, 8)
    return out, resid


@lru_cache(maxsize=4)
def _gamma_lut(gamma: float) -> np.ndarray:
    """(256,) float32: 8-bit code -> linear light (0..1) for a pure power-law tone curve."""
    return ((np.arange(256) / 255.0) ** gamma).astype(np.float32)


def _linearise(rect: np.ndarray, gamma: float) -> np.ndarray:
    """Raster in linear light (float32, 0..1)."""
    return cv2.LUT(rect, _gamma_lut(float(gamma)))  # numpy's fancy indexing costs 5x more


_FLIP_BATCH = 16  # flipped symbols rendered per batch (16 cost what ~11 rendered one by one did)


@lru_cache(maxsize=8)
def _flip_masks(n: int) -> np.ndarray:
    """(2**n, n) bool: every subset of n bits."""
    return (np.arange(2**n)[:, None] >> np.arange(n)[None] & 1).astype(bool)


def _decode_estimates(est: np.ndarray, k: int, flips: int, tag: str) -> list[Symbol]:
    """zxing (pure mode) on each quadrant's thresholded estimates, flipping up to the ``flips``
    least certain data modules (every subset, the least confidence overturned first); zxing's
    Reed-Solomon decoding decides. Stops once two symbols agree on ID and rotation."""
    out: list[Symbol] = []
    agree: dict[tuple[int, int], int] = {}
    for p in range(4):
        s = np.rot90(est[p], k)
        dark = s < 0.5
        conf = np.abs(s[1:9, 1:9] - 0.5).ravel()
        order = np.argsort(conf)[:flips]
        masks = _flip_masks(len(order))
        masks = masks[np.argsort(masks @ conf[order], kind="stable")]
        rows, cols = 1 + order // 8, 1 + order % 8
        # The flipped symbols' images a batch at a time (a numpy pass instead of a copy, index and
        # resize per attempt; most reads settle within the first few, a failing quadrant tries
        # them all); zxing, which decides, still reads them one by one, in the same order.
        bits = np.repeat(dark[None], len(masks), axis=0)
        bits[:, rows, cols] ^= masks
        images = (img for lo in range(0, len(masks), _FLIP_BATCH) for img in clean_symbols(bits[lo : lo + _FLIP_BATCH]))
        for img in images:
            res = zxing_read(img, pure=True)
            if res and res[0].text:
                out.append((res[0].text, p, tag))
                parsed = parse_payload(res[0].text)
                if parsed is not None:
                    key = (parsed[0], (p - parsed[1]) % 4)
                    agree[key] = agree.get(key, 0) + 1
                    if agree[key] >= 2:
                        return out
                break
    return out


def read_lsq(
    rect: np.ndarray,
    detection: Detection,
    camera: Camera,
    config: DecodeConfig,
    blur: tuple[float, float, float],
    grid: tuple[np.ndarray, int, np.ndarray] | None = None,
) -> tuple[list[Symbol], np.ndarray | None]:
    """Module least-squares stage: symbols read from :func:`module_estimates` and those estimates.

    ``blur`` is :func:`blur_estimate`'s (x extent, y extent, optics sigma). The image-space spread
    is the optics plus one pixel's integration (variance 1/12) plus the raster's bilinear
    resampling (1/6). Edge profiles cannot tell the motion's diagonal sign, so a diagonal blur is
    tried both ways, the better-fitting first. ``grid``: :func:`module_samples` of ``rect`` at
    ``config.align_search_px``, if already made.
    """
    lx, ly, sigma = blur
    samples, k, shifts = grid if grid is not None else module_samples(rect, config.align_search_px)
    cov = _raster_cov(detection, camera, float(np.sqrt(sigma**2 + 1 / 12 + 1 / 6)))
    signs = (1.0,) if min(lx, ly) < 2.0 else (1.0, -1.0)
    fits = [
        module_estimates(rect, blur_psf(cov, (lx, s * ly)), k, shifts, config.lsq_gamma, config.lsq_ridge)
        for s in signs
    ]
    fits.sort(key=lambda f: float(f[1].sum()))
    for est, _ in fits:
        symbols = _decode_estimates(est, k, config.lsq_flips, "zxing-lsq")
        if symbols:
            return symbols, est
    return [], None
