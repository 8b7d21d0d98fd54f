"""Pairing detections with true sticker corners, for the detection scores of ``tagloc bench`` and
``tagloc advise`` (frames with known corners, from the simulator or the tests' synthetic frames).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from tagloc.core.types import Detection


@dataclass
class Match:
    """A detection paired with a true sticker: per-corner errors (px) after the best cyclic shift."""

    truth: int
    detection: int
    rotation: int
    outer_err: np.ndarray  # (4,)
    inner_err: np.ndarray | None  # (4,) or None when either side has no inner corners


def match_detections(
    detections: Sequence[Detection],
    outer: Sequence[np.ndarray],
    inner: Sequence[np.ndarray | None] | None = None,
    max_px: float = 8.0,
) -> list[Match]:
    """Pair detections with true stickers (greedy on mean corner error, at most ``max_px``).

    The detector's starting corner is arbitrary, so each pair is compared under the cyclic shift
    that fits best; ``rotation`` r means detection.outer[r] is true corner 0.
    """
    cands = []
    for ti, t in enumerate(outer):
        t = np.asarray(t, float)
        for di, d in enumerate(detections):
            errs = [np.linalg.norm(np.roll(d.outer, -r, axis=0) - t, axis=1) for r in range(4)]
            r = int(np.argmin([e.mean() for e in errs]))
            if errs[r].mean() <= max_px:
                cands.append((float(errs[r].mean()), ti, di, r, errs[r]))
    cands.sort(key=lambda c: c[0])
    used_t, used_d, out = set(), set(), []
    for _, ti, di, r, err in cands:
        if ti in used_t or di in used_d:
            continue
        used_t.add(ti)
        used_d.add(di)
        ie = None
        ti_inner = None if inner is None else inner[ti]
        if ti_inner is not None and detections[di].inner is not None:
            ie = np.linalg.norm(np.roll(detections[di].inner, -r, axis=0) - np.asarray(ti_inner, float), axis=1)
        out.append(Match(ti, di, r, err, ie))
    return out
