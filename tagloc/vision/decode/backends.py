"""Data Matrix decoders on the raster: zxing-cpp on the whole raster, zxing on the sampled module
grid (pure mode), and libdmtx per quadrant. Each returns the symbols it read as :data:`Symbol`."""

from __future__ import annotations

import warnings
from collections.abc import Iterable

import numpy as np

from tagloc.core.errors import BackendUnavailable
from tagloc.vision.decode.config import DecodeConfig
from tagloc.vision.decode.grid import (
    QUAD_ORIGIN,
    QUAD_PX,
    RASTER_PX,
    Symbol,
    border_template,
    clean_symbol,
    module_samples,
)


def zxing_read(img: np.ndarray, pure: bool = False) -> list:
    import zxingcpp

    return zxingcpp.read_barcodes(
        img,
        formats=zxingcpp.BarcodeFormat.DataMatrix,
        try_rotate=not pure,
        try_downscale=False,
        try_invert=False,
        is_pure=pure,
    )


def _quadrant_of(x: float, y: float) -> int:
    """Raster quadrant (0 TL, 1 TR, 2 BR, 3 BL) of raster point (x, y)."""
    right, bottom = x >= RASTER_PX / 2, y >= RASTER_PX / 2
    return (3, 2)[right] if bottom else (0, 1)[right]


def read_zxing_whole(rect: np.ndarray, tag: str = "zxing") -> list[Symbol]:
    """Symbols zxing-cpp finds anywhere in the raster, each placed by its centre."""
    out = []
    for b in zxing_read(rect):
        pos = b.position
        cx = (pos.top_left.x + pos.top_right.x + pos.bottom_right.x + pos.bottom_left.x) / 4
        cy = (pos.top_left.y + pos.top_right.y + pos.bottom_right.y + pos.bottom_left.y) / 4
        out.append((b.text, _quadrant_of(cx, cy), tag))
    return out


def read_grid(
    rect: np.ndarray,
    config: DecodeConfig,
    skip: Iterable[int] = (),
    tag: str = "zxing-grid",
    grid: tuple[np.ndarray, int, np.ndarray] | None = None,
) -> list[Symbol]:
    """Stage 2: sample the module grid, orient, threshold, decode the clean symbols with zxing.
    ``grid``: :func:`module_samples` of ``rect`` at ``config.align_search_px``, if already made."""
    samples, k, _ = grid if grid is not None else module_samples(rect, config.align_search_px)
    mask, dark = border_template()
    out = []
    for p in range(4):
        if p in skip:
            continue
        s = np.rot90(samples[p], k)
        lo, hi = float(s[mask & dark].mean()), float(s[mask & ~dark].mean())
        if hi - lo < 10:  # no contrast: nothing to threshold
            continue
        tried = set()
        for f in config.thresholds:
            bits = s < lo + f * (hi - lo)
            key = bits.tobytes()
            if key in tried:
                continue
            tried.add(key)
            res = zxing_read(clean_symbol(bits), pure=True)
            if res and res[0].text:
                out.append((res[0].text, p, tag))
                break
    return out


def read_libdmtx(rect: np.ndarray, config: DecodeConfig) -> list[Symbol]:
    """libdmtx on each quadrant crop, time-bounded. Raises BackendUnavailable without libdmtx."""
    try:
        with warnings.catch_warnings():  # pylibdmtx's own distutils deprecation noise
            warnings.simplefilter("ignore", DeprecationWarning)
            from pylibdmtx import pylibdmtx
    except (ImportError, OSError) as exc:  # the Python wrapper or the shared library is missing
        raise BackendUnavailable(
            f"libdmtx backend unavailable ({exc}): pip install pylibdmtx and apt-get install libdmtx0b "
            "(Debian/Ubuntu) or brew install libdmtx (macOS)"
        ) from exc
    out = []
    for p, (r0, c0) in enumerate(QUAD_ORIGIN):
        crop = np.ascontiguousarray(rect[r0 : r0 + QUAD_PX, c0 : c0 + QUAD_PX])
        with warnings.catch_warnings():  # pylibdmtx's own distutils deprecation noise
            warnings.simplefilter("ignore", DeprecationWarning)
            res = pylibdmtx.decode(crop, timeout=config.libdmtx_timeout_ms, max_count=1, shrink=config.libdmtx_shrink)
        for d in res:
            out.append((d.data.decode("ascii", errors="replace"), p, "libdmtx"))
    return out
