"""Turning symbols into an ID, and checking an ID against the raster's modules."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from functools import lru_cache

import numpy as np

from tagloc.core.sticker import parse_payload, render_sticker
from tagloc.vision.decode.config import DecodeConfig
from tagloc.vision.decode.grid import LONE_LIBDMTX, RASTER_PX, Symbol, module_samples


def combine_reads(
    symbols: Sequence[Symbol], config: DecodeConfig | None = None, candidates: Iterable[int] | None = None
) -> tuple[int | None, int | None, str | None]:
    """(ID, rotation, rejection reason) from the symbols read.

    Every payload must be a valid sticker payload and all must agree on ID and rotation
    r = (p - q) mod 4. A lone libdmtx symbol needs corroboration: a second agreeing symbol in another
    quadrant, a zxing read, or the ID being among the tracker's ``candidates``.
    """
    if not symbols:
        return None, None, None
    reads = []
    for text, p, backend in symbols:
        parsed = parse_payload(text)
        if parsed is None:
            return None, None, f"payload {text!r} ({backend}, quadrant {p}) is not a sticker payload"
        sid, q = parsed
        reads.append((sid, (p - q) % 4, p, backend))
    keys = {(sid, r) for sid, r, _, _ in reads}
    if len(keys) > 1:
        desc = ", ".join(f"{t}@{p}/{b}" for t, p, b in symbols)
        return None, None, f"symbols disagree on ID/rotation: {desc}"
    ((sid, rot),) = keys
    places = {p for _, _, p, _ in reads}
    backends = {b for _, _, _, b in reads}
    if backends == {"libdmtx"} and len(places) < 2 and sid not in set(candidates or ()):
        return None, None, f"{LONE_LIBDMTX} {symbols[0][0]!r} not corroborated"
    return sid, rot, None


@lru_cache(maxsize=256)
def _expected_dark(sticker_id: int, rotation: int) -> np.ndarray:
    """(4, 8, 8) bool: interior modules of the raster quadrants for this ID and rotation."""
    ref = np.rot90(render_sticker(sticker_id, RASTER_PX), -rotation)  # canonical TL goes to raster corner r
    return module_samples(np.ascontiguousarray(ref))[0][:, 1:-1, 1:-1] < 128


def verify_id(
    rect: np.ndarray, sticker_id: int, rotation: int, samples: np.ndarray | None = None, search_px: int = 4
) -> float:
    """Correlation (-1..1) between the raster's 256 data-module samples and those of the ID.

    The true ID and rotation score high even under blur; another ID differs in the Reed-Solomon
    codewords, hence in roughly half the modules, and scores near 0.
    """
    samples = module_samples(rect, search_px)[0] if samples is None else samples
    v = samples[:, 1:-1, 1:-1].ravel().astype(np.float64)
    e = np.where(_expected_dark(sticker_id, rotation).ravel(), -1.0, 1.0)
    v = v - v.mean()
    e = e - e.mean()
    return float(v @ e / (np.linalg.norm(v) * np.linalg.norm(e) + 1e-9))
