"""The ground sticker of ``shared/STICKER.md``: geometry, payloads and the one renderer.

Every part of tagloc that needs a picture of a sticker (simulator, reference bank, printed sheets)
calls :func:`render_sticker`, so they cannot disagree.

Raster convention: a rendered sticker is a square greyscale image in the sticker's canonical
orientation, row 0 at the canonical top (+y of the sticker frame), column 0 at the canonical left
(-x). Pixel (col, row) of an ``n``-pixel raster covers sticker-frame point
``x = -0.05 + (col + 0.5) * 0.1 / n``, ``y = 0.05 - (row + 0.5) * 0.1 / n`` (metres).
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from tagloc.core.errors import InputError

#: Outer side of the sticker (m).
SIZE_M = 0.100
#: Thickness of the black frame (m).
FRAME_M = 0.008
#: Side of the white inner area (m).
INNER_M = SIZE_M - 2 * FRAME_M
#: Data Matrix module size (m) and symbol size in modules.
MODULE_M = 0.0035
SYMBOL_MODULES = 10
#: Largest sticker ID (5 digits).
MAX_ID = 99999

# The geometry is exact on a 0.5 mm grid: 200 cells per sticker, frame 16, quadrant 84,
# module 7, symbol 70, quiet zone 7. Rendering first on that grid and then area-resampling keeps
# every resolution faithful to the printed sticker.
_GRID = 200
_CELL_M = SIZE_M / _GRID
_FRAME_CELLS = 16
_QUAD_CELLS = 84
_MODULE_CELLS = 7
_QUIET_CELLS = (_QUAD_CELLS - SYMBOL_MODULES * _MODULE_CELLS) // 2

#: Outer corners in the sticker frame (4, 3), metres, in image order: canonical top-left,
#: top-right, bottom-right, bottom-left (clockwise as seen from above).
OUTER_CORNERS = np.array([[-0.05, 0.05, 0.0], [0.05, 0.05, 0.0], [0.05, -0.05, 0.0], [-0.05, -0.05, 0.0]])
#: Inner corners of the black frame (4, 3), metres, same order as :data:`OUTER_CORNERS`.
INNER_CORNERS = OUTER_CORNERS * (INNER_M / SIZE_M)
#: All 8 points (8, 3): outer then inner.
ALL_CORNERS = np.vstack([OUTER_CORNERS, INNER_CORNERS])

#: Quadrant q's top-left cell (row, col) on the 200-cell grid, canonical orientation.
_QUAD_ORIGIN = {
    0: (_FRAME_CELLS, _FRAME_CELLS),
    1: (_FRAME_CELLS, _FRAME_CELLS + _QUAD_CELLS),
    2: (_FRAME_CELLS + _QUAD_CELLS, _FRAME_CELLS + _QUAD_CELLS),
    3: (_FRAME_CELLS + _QUAD_CELLS, _FRAME_CELLS),
}


def check_id(sticker_id: int) -> int:
    """Return ``sticker_id`` as int, or raise :class:`InputError` if it is outside 0-99999."""
    sid = int(sticker_id)
    if sid != sticker_id or not 0 <= sid <= MAX_ID:
        raise InputError(f"sticker ID {sticker_id!r} is outside 0-{MAX_ID}")
    return sid


def payload(sticker_id: int, quadrant: int) -> str:
    """The 6-digit payload of one symbol: zero-padded ID followed by the quadrant digit."""
    if quadrant not in (0, 1, 2, 3):
        raise InputError(f"quadrant {quadrant!r} is not 0-3")
    return f"{check_id(sticker_id):05d}{quadrant}"


def payloads(sticker_id: int) -> list[str]:
    """The four payloads of a sticker, quadrants 0-3."""
    return [payload(sticker_id, q) for q in range(4)]


def parse_payload(text: str) -> tuple[int, int] | None:
    """Split a decoded payload into (sticker ID, quadrant), or None if it is not a valid payload."""
    if len(text) != 6 or not text.isascii() or not text.isdigit():
        return None
    quadrant = int(text[5])
    if quadrant > 3:
        return None
    return int(text[:5]), quadrant


@lru_cache(maxsize=4096)
def symbol_modules(text: str) -> np.ndarray:
    """The 10x10 ECC200 module matrix (bool, True = dark) encoding ``text``, via zxing-cpp."""
    import zxingcpp

    barcode = zxingcpp.create_barcode(text, zxingcpp.BarcodeFormat.DataMatrix)
    matrix = np.asarray(barcode.to_image(scale=1, add_quiet_zones=False)) < 128
    if matrix.shape != (SYMBOL_MODULES, SYMBOL_MODULES):
        raise InputError(f"payload {text!r} does not fit a 10x10 Data Matrix symbol")
    matrix.setflags(write=False)
    return matrix


@lru_cache(maxsize=1024)
def _sticker_grid(sticker_id: int) -> np.ndarray:
    """The sticker on its exact 0.5 mm grid (200x200 uint8, 0 black, 255 white)."""
    grid = np.zeros((_GRID, _GRID), np.uint8)
    grid[_FRAME_CELLS:-_FRAME_CELLS, _FRAME_CELLS:-_FRAME_CELLS] = 255
    for q in range(4):
        modules = symbol_modules(payload(sticker_id, q))
        cells = np.kron(modules, np.ones((_MODULE_CELLS, _MODULE_CELLS), bool))
        r0, c0 = _QUAD_ORIGIN[q]
        r0 += _QUIET_CELLS
        c0 += _QUIET_CELLS
        n = cells.shape[0]
        grid[r0 : r0 + n, c0 : c0 + n] = np.where(cells, 0, 255)
    grid.setflags(write=False)
    return grid


def render_sticker(sticker_id: int, size_px: int = 200) -> np.ndarray:
    """Render sticker ``sticker_id`` as a ``(size_px, size_px)`` uint8 image, canonical orientation.

    The image covers exactly the 100 mm outer square (no margin); values are 0 (black ink) to 255
    (white paper), area-averaged from the exact 0.5 mm geometry.
    """
    sid = check_id(sticker_id)
    if size_px < 1:
        raise InputError(f"sticker size {size_px} px must be positive")
    grid = _sticker_grid(sid)
    if size_px == _GRID:
        return grid.copy()
    if size_px % _GRID == 0:
        k = size_px // _GRID
        return np.kron(grid, np.ones((k, k), np.uint8))
    interp = cv2.INTER_AREA if size_px < _GRID else cv2.INTER_NEAREST
    return cv2.resize(grid, (size_px, size_px), interpolation=interp)


def sticker_pixel_to_metres(size_px: int) -> np.ndarray:
    """Affine (2, 3) mapping raster (col, row) of an ``size_px`` render to sticker-frame (x, y) m."""
    s = SIZE_M / size_px
    # Pixel centres sit half a pixel in from the sticker's edges.
    return np.array([[s, 0.0, -0.05 + 0.5 * s], [0.0, -s, 0.05 - 0.5 * s]])


# rotate_corners' orders by rotation: position i takes corner i + rotation (mod 4), of the outer
# corners and then of the inner ones.
_CORNER_ORDER = np.array([[(i + r) % 4 for i in range(4)] for r in range(4)])
_CORNER_ORDER_8 = np.hstack([_CORNER_ORDER, _CORNER_ORDER + 4])


def rotate_corners(corners: np.ndarray, rotation: int) -> np.ndarray:
    """Re-order 4 (or 4+4) image corners so index 0 is the canonical top-left.

    ``corners`` are in image order starting at whatever corner the detector called first;
    ``rotation`` (0-3) is how many positions the canonical top-left is shifted along that order.
    Works on (4, 2) or (8, 2) arrays (outer then inner).
    """
    corners = np.asarray(corners)
    # Indexed in a fixed order: np.roll's set-up cost more than the reordering (every detection
    # and fix of a frame goes through here).
    if len(corners) == 8:
        return corners[_CORNER_ORDER_8[rotation % 4]]
    if len(corners) == 4:
        return corners[_CORNER_ORDER[rotation % 4]]
    return np.roll(corners, -rotation, 0)
