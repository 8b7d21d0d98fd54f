"""Turning symbols into an ID, and checking an ID against the raster's modules."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from functools import lru_cache

import numpy as np

from tagloc.core.sticker import parse_payload, render_sticker
from tagloc.vision.decode.config import DecodeConfig
from tagloc.vision.decode.grid import LONE_LIBDMTX, MODULE_PX, QUAD_ORIGIN, RASTER_PX, Symbol, module_samples


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


@lru_cache(maxsize=4)
def _sample_index(rotation: int) -> np.ndarray:
    """(256,) flat indices into a sticker's exact render at ``RASTER_PX`` of its interior data
    modules' centres as the raster turned by ``rotation`` shows them (the canonical top-left at
    raster corner ``rotation``), quadrant-major as :func:`module_samples` orders them: the render is
    exact there, so these pixels are the modules a sharp raster's samples read."""
    idx = np.rot90(np.arange(RASTER_PX * RASTER_PX).reshape(RASTER_PX, RASTER_PX), -rotation)
    centres = MODULE_PX + MODULE_PX // 2 + MODULE_PX * np.arange(1, 9)  # interior rows/cols 1..8
    return np.concatenate([idx[r0 + centres[:, None], c0 + centres[None, :]].ravel() for r0, c0 in QUAD_ORIGIN])


def data_patterns(sticker_ids: Iterable[int], rotation: int = 0) -> np.ndarray:
    """(N, 256) int8 data-module patterns (-1 dark, +1 light) of the IDs at ``rotation``, in the
    order :func:`verify_id` correlates them."""
    index = _sample_index(rotation)
    ids = list(sticker_ids)
    out = np.empty((len(ids), index.size), np.int8)
    for k, sid in enumerate(ids):
        out[k] = np.where(render_sticker(int(sid), RASTER_PX).ravel()[index] < 128, -1, 1)
    return out


@lru_cache(maxsize=256)
def _expected_dark(sticker_id: int, rotation: int) -> np.ndarray:
    """(4, 8, 8) bool: interior modules of the raster quadrants for this ID and rotation."""
    return (data_patterns([sticker_id], rotation)[0] < 0).reshape(4, 8, 8)


# IDs whose decades show which modules a decade shares (any IDs do: the placement is fixed).
_DECADE_PROBES = (12340, 56780, 90120)


@lru_cache(maxsize=4)
def _decade_shared(rotation: int) -> np.ndarray:
    """(4, 8, 8) bool, raster orientation for ``rotation``: the interior modules every ID of a decade
    (the same first four digits) has alike, whichever decade: where each quadrant's symbol holds its
    first two data codewords (the digit pairs of those four digits). Found by rendering the ten IDs
    of a few decades (~15 ms, once per rotation)."""
    alike = np.ones((4, 8, 8), bool)
    for base in _DECADE_PROBES:
        stack = np.stack([_expected_dark(base + d, rotation) for d in range(10)])
        alike &= np.all(stack == stack[0], axis=0)
    return alike


def prepare() -> None:
    """Find the modules a decade shares for every rotation now (~40 ms), not in the first check."""
    for rotation in range(4):
        _decade_shared(rotation)


def verify_id(
    rect: np.ndarray,
    sticker_id: int,
    rotation: int,
    samples: np.ndarray | None = None,
    search_px: int = 4,
    distinct: bool = False,
) -> float:
    """Correlation (-1..1) between the raster's 256 data-module samples and those of the ID.

    The true ID and rotation score high even under blur; another ID differs in the Reed-Solomon
    codewords, hence in roughly half the modules, and scores near 0. An ID of the same decade (the
    same first four digits) shares each symbol's first two data codewords, a quarter of the
    modules, and scores up to ~0.4 under blur; ``distinct`` leaves those modules out, so such a
    neighbour scores near 0 too (:func:`_decade_shared`).
    """
    samples = module_samples(rect, search_px)[0] if samples is None else samples
    v = samples[:, 1:-1, 1:-1].astype(np.float64)
    e = np.where(_expected_dark(sticker_id, rotation), -1.0, 1.0)
    if distinct:
        keep = ~_decade_shared(rotation)
        v, e = v[keep], e[keep]
    v = v.ravel() - v.mean()
    e = e.ravel() - e.mean()
    return float(v @ e / (np.linalg.norm(v) * np.linalg.norm(e) + 1e-9))
