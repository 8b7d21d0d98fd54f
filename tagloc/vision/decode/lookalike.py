"""Stickers whose data modules look alike, for the expected-ID check's rivals.

The expected-ID check (:func:`tagloc.vision.decode.decode`, stage "expected") names a sticker no
symbol of which was read when the one ID the tracker expects there matches the raster's data
modules. Two IDs from different decades normally share about half their modules by chance
(correlation ~0), but Reed-Solomon codewords of some pairs agree far more: on a sharp raster 12867
scores 0.65 against 43247's modules (both on ``maps/demo.csv``, 1.87 m apart), above the check's
0.5. A sticker seen where the tracker expects its look-alike, blurred past the symbol readers, was
then named as the look-alike. So the check also scores the expected ID's look-alikes in the map
(:class:`LookAlikes`) and names the sticker only when it leads every one of them.

Patterns are ±1 vectors of the 256 interior data modules in the raster's orientation (dark -1),
exactly the modules :func:`tagloc.vision.decode.verify.verify_id` correlates
(:func:`~tagloc.vision.decode.verify.data_patterns`).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from tagloc.vision.decode.verify import _decade_shared, data_patterns

__all__ = ["LookAlikes", "best_scores"]


class LookAlikes:
    """The look-alikes of each sticker of a map among the map's other stickers.

    ``rivals(y)``: the mapped IDs whose modules, in some rotation, correlate with ``y``'s at or
    above ``min_corr`` on the modules the expected-ID check compares (those that tell ``y`` from its
    decade: ``verify_id(..., distinct=True)``). A raster of such a sticker scores about that
    correlation times its own quality against ``y``, so a rival below ``min_corr`` cannot reach the
    check's 0.5 with its 0.2 lead (see :class:`tagloc.vision.decode.config.DecodeConfig`).

    The map's patterns are made once (``prepare``: ~0.13 ms a sticker, 25 ms for 200 stickers,
    2.3 s for 20,000), each sticker's rivals when first asked for (four (N, 256) products: 0.4 ms
    for 200 stickers, 13 ms for 20,000, on the first expected-ID check of that sticker) and kept.
    """

    def __init__(self, map_ids: Iterable[int], min_corr: float = 0.3):
        self.ids = np.array(sorted({int(i) for i in map_ids}), np.int64)
        self.min_corr = float(min_corr)
        self._patterns: np.ndarray | None = None
        self._norms: np.ndarray | None = None
        self._rivals: dict[int, list[int]] = {}

    def prepare(self) -> None:
        """Make the map's patterns now (``Localiser.warm_up``), not at the first check: (N, 256) ±1
        and, per rotation's compared modules, the norm of each pattern less its mean there (a ±1
        vector of n modules summing to s: sqrt(n - s^2 / n))."""
        if self._patterns is not None:
            return
        self._patterns = data_patterns(self.ids, 0).astype(np.float32)
        norms = []
        for r in range(4):
            keep = ~_decade_shared(r).ravel()
            n, total = float(keep.sum()), self._patterns[:, keep].sum(axis=1)
            norms.append(np.sqrt(np.maximum(n - total**2 / n, 1e-9)))
        self._norms = np.stack(norms)

    def rivals(self, sticker_id: int) -> list[int]:
        """Mapped IDs (other than ``sticker_id``) that look like it in some rotation, most alike first."""
        sid = int(sticker_id)
        hit = self._rivals.get(sid)
        if hit is not None:
            return hit
        self.prepare()
        assert self._patterns is not None and self._norms is not None
        best = np.full(len(self.ids), -1.0, np.float32)
        # y turned by r against every mapped sticker upright: the same as y upright against each
        # turned by -r (a correlation is unchanged when both vectors' modules are permuted alike).
        # y is centred on the compared modules and zero on the rest, so its product with a pattern
        # is that pattern's centred product there, without a masked copy of the map's patterns.
        for r in range(4):
            keep = ~_decade_shared(r).ravel()
            y = np.zeros(keep.size, np.float32)
            yk = data_patterns([sid], r)[0][keep].astype(np.float32)
            y[keep] = yk - yk.mean()
            best = np.maximum(best, (self._patterns @ y) / (self._norms[r] * (np.linalg.norm(y) + 1e-9)))
        found = np.flatnonzero((best >= self.min_corr) & (self.ids != sid))
        out = [int(self.ids[k]) for k in found[np.argsort(-best[found])]]
        self._rivals[sid] = out
        return out


def best_scores(samples: np.ndarray, sticker_ids: Iterable[int]) -> np.ndarray:
    """(k,) each ID's best :func:`~tagloc.vision.decode.verify.verify_id` over the four rotations on
    the modules that tell it from its decade (``distinct``), from the raster's module ``samples``
    (4, 10, 10): the same numbers, for many IDs at once."""
    ids = [int(i) for i in sticker_ids]
    if not ids:
        return np.zeros(0)
    v = np.asarray(samples, np.float64)[:, 1:-1, 1:-1].ravel()
    best = np.full(len(ids), -np.inf)
    for r in range(4):
        keep = ~_decade_shared(r).ravel()
        vk = v[keep] - v[keep].mean()
        e = data_patterns(ids, r)[:, keep].astype(np.float64)
        e -= e.mean(axis=1, keepdims=True)
        scores = (e @ vk) / (np.linalg.norm(vk) * np.linalg.norm(e, axis=1) + 1e-9)
        best = np.maximum(best, scores)
    return best
