"""The rectified raster's module grid: where the four symbols and their modules are, and sampling it.

The raster is :func:`tagloc.vision.rectify.rectify` at ``RASTER_PX`` (200 px, exact on the sticker's
0.5 mm grid): a 16 px black frame, four 84 px quadrants each holding a 10x10 symbol of 7 px modules
behind a 7 px quiet zone.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from tagloc.core.errors import InputError
from tagloc.core.sticker import symbol_modules
from tagloc.vision.rectify import DEFAULT_SIZE_PX

# Raster geometry at DEFAULT_SIZE_PX (exact on the 0.5 mm grid): frame 16 px, quadrant 84 px,
# quiet zone 7 px, module 7 px.
RASTER_PX = DEFAULT_SIZE_PX
FRAME_PX = 16
QUAD_PX = 84
MODULE_PX = 7
#: Top-left (row, col) of raster quadrant p (0 TL, 1 TR, 2 BR, 3 BL).
QUAD_ORIGIN = (
    (FRAME_PX, FRAME_PX),
    (FRAME_PX, FRAME_PX + QUAD_PX),
    (FRAME_PX + QUAD_PX, FRAME_PX + QUAD_PX),
    (FRAME_PX + QUAD_PX, FRAME_PX),
)

Symbol = tuple[str, int, str]  # (payload text, raster quadrant 0-3, backend name)
LONE_LIBDMTX = "lone libdmtx symbol"


@lru_cache(maxsize=1)
def border_template() -> tuple[np.ndarray, np.ndarray]:
    """Finder/timing border of every 10x10 symbol, upright: (mask (10,10) bool, dark (10,10) bool)."""
    m = symbol_modules("000000")
    mask = np.zeros((10, 10), bool)
    mask[0, :] = mask[-1, :] = mask[:, 0] = mask[:, -1] = True
    return mask, m.copy()


@lru_cache(maxsize=1)
def _border_targets() -> np.ndarray:
    """(4, 36) zero-mean unit-norm border patterns as seen in a raster where the symbol is turned
    by ``np.rot90(., -k)`` (so ``np.rot90(sample, k)`` is upright)."""
    mask, dark = border_template()
    e = np.where(dark, -1.0, 1.0)
    t = np.stack([np.rot90(e, -k)[mask] for k in range(4)])
    t -= t.mean(1, keepdims=True)
    return t / np.linalg.norm(t, axis=1, keepdims=True)


def module_samples(rect: np.ndarray, search_px: int = 0) -> tuple[np.ndarray, int, np.ndarray]:
    """Module values of the raster's quadrants p = 0..3, aligned on their finder/timing borders.

    Each value is the mean of the module's central 3x3 pixels, away from its blurred edges. With
    ``search_px`` > 0, each quadrant's 10x10 sampling grid is shifted by up to that many raster px
    to where its border best matches the fixed Data Matrix border; this absorbs corner errors of
    the detector (1 image px is ~2 raster px, a third of a module).

    Returns:
        samples (4, 10, 10) float32 in raster orientation; k, the symbol turn shared by all
        quadrants (``np.rot90(samples[p], k)`` is upright); shifts (4, 2) (dy, dx) raster px used.
    """
    if rect.shape != (RASTER_PX, RASTER_PX):
        raise InputError(f"decode: raster must be {RASTER_PX}x{RASTER_PX}, got {rect.shape}")
    box = cv2.blur(rect.astype(np.float32), (3, 3))
    mask, _ = border_template()
    d = np.arange(-search_px, search_px + 1)
    dy, dx = (a.ravel() for a in np.meshgrid(d, d, indexing="ij"))
    centres = MODULE_PX + MODULE_PX // 2 + MODULE_PX * np.arange(10)
    vals, scores = [], []
    for r0, c0 in QUAD_ORIGIN:
        rows = r0 + centres[None, :] + dy[:, None]  # (D, 10)
        cols = c0 + centres[None, :] + dx[:, None]
        v = box[rows[:, :, None], cols[:, None, :]]  # (D, 10, 10)
        b = v[:, mask]
        b = b - b.mean(1, keepdims=True)
        b /= np.linalg.norm(b, axis=1, keepdims=True) + 1e-9
        vals.append(v)
        scores.append(b @ _border_targets().T)  # (D, 4)
    scores = np.stack(scores)  # (4 quadrants, D, 4 turns)
    k = int(np.argmax(scores.max(axis=1).sum(axis=0)))
    best = np.argmax(scores[:, :, k], axis=1)
    samples = np.stack([vals[p][best[p]] for p in range(4)])
    return samples, k, np.stack([dy[best], dx[best]], 1)


def clean_symbol(modules_dark: np.ndarray, scale: int = 4, quiet: int = 2) -> np.ndarray:
    """Upright binary symbol image (uint8) with a quiet zone, as zxing's pure mode wants it."""
    n = modules_dark.shape[0] + 2 * quiet
    img = np.full((n, n), 255, np.uint8)
    img[quiet : n - quiet, quiet : n - quiet][modules_dark] = 0
    return cv2.resize(img, (n * scale, n * scale), interpolation=cv2.INTER_NEAREST)


def clean_symbols(modules_dark: np.ndarray, scale: int = 4, quiet: int = 2) -> np.ndarray:
    """:func:`clean_symbol` of k symbols (k, m, m) at once: (k, n scale, n scale) uint8, n = m + 2 quiet
    (an integer nearest-neighbour upscale is a repeat of each module: the same pixels)."""
    k, m = modules_dark.shape[:2]
    n = m + 2 * quiet
    img = np.full((k, n, n), 255, np.uint8)
    img[:, quiet : n - quiet, quiet : n - quiet][modules_dark] = 0
    return np.ascontiguousarray(img.repeat(scale, axis=1).repeat(scale, axis=2))
