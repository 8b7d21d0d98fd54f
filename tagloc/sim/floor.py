"""The warehouse floor as the camera sees it: world-anchored reflectance, deterministic from a seed.

Two layers:

* **Tiles** (``tile_m`` square, ``res_m`` per texel, made lazily and kept in an LRU cache): concrete
  (reflectance ``base_reflectance`` with low-frequency mottling, aggregate speckle, fine grain and
  pits), worn painted lines (yellow/white, reflectance ~0.6-0.75) along world x and y, stains, and
  distractors: dark squares 8-15 cm, filled or as a hollow frame with a light inside (sticker-like).
  Every feature is drawn from one world-anchored list and the mottling comes from hashed lattice
  values, so a tile looks the same whichever order tiles are made in and neighbours join seamlessly.
* **Stickers** (drawn by the renderer straight from :func:`tagloc.core.sticker.render_sticker` rasters at
  their exact pose, so their corners are exact): the map's stickers except the ``missing_fraction``
  left off the floor, plus ``unmapped`` stickers with IDs not in the map. Paper white reflectance
  ``paper_white``, ink ``ink_black``; each sticker gets a small soiling factor.

Reflectance is stored as uint8 = reflectance * 255. Tile texel (col, row) of tile (tx, ty) covers
world ``x = tx * tile_m + (col + 0.5) * res_m``, ``y = ty * tile_m + (row + 0.5) * res_m``.
The illumination is not uniform either: :meth:`Floor.illumination` is a smooth factor around 1 from
overhead lights on a grid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from tagloc.core.errors import InputError
from tagloc.core.sticker import MAX_ID, render_sticker
from tagloc.core.stickermap import StickerMap


@dataclass
class FloorConfig:
    """Appearance of the floor. Reflectances are 0-1; lengths in metres.

    Attributes:
        tile_m, res_m: tile side and texel size.
        cache_tiles: tiles kept in memory (1 m at 2 mm: 250 kB each).
        texture: False gives a plain floor of ``base_reflectance`` with no features (for tests).
        base_reflectance: mean concrete reflectance.
        mottle: relative amplitude of the low-frequency mottling.
        grain: standard deviation of the per-texel grain (reflectance units).
        texture_contrast: the concrete's texture (mottling, grain, speckle and pits) times this:
            1 for the worn, unsealed concrete above; a sealed, polished or epoxy-coated floor shows
            less (0.5, 0.25; the painted lines, stains and distractors are unchanged). The floor
            odometry tracks this texture, so it sets how well it can.
        line_spacing_m: mean distance between painted lines (0: none).
        distractors_per_m2: dark squares (8-15 cm) per square metre.
        stains_per_m2: soft dark stains per square metre.
        missing_fraction: share of the map's stickers not on the floor.
        unmapped: number of stickers on the floor whose IDs are not in the map.
        paper_white, ink_black: sticker reflectances.
        illumination_variation: relative amplitude of the light-grid pattern.
        light_spacing_m: spacing of the overhead lights.
        margin_m: features are generated this far beyond the map's stickers.
    """

    tile_m: float = 1.0
    res_m: float = 0.002
    cache_tiles: int = 128
    texture: bool = True
    base_reflectance: float = 0.38
    mottle: float = 0.18
    grain: float = 0.025
    texture_contrast: float = 1.0
    line_spacing_m: float = 6.0
    distractors_per_m2: float = 0.05
    stains_per_m2: float = 0.2
    missing_fraction: float = 0.0
    unmapped: int = 0
    paper_white: float = 0.85
    ink_black: float = 0.05
    illumination_variation: float = 0.12
    light_spacing_m: float = 4.0
    margin_m: float = 4.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.missing_fraction <= 1.0:
            raise InputError(f"missing fraction {self.missing_fraction} is not in 0-1")
        if not 0.0 <= self.texture_contrast <= 2.0:
            raise InputError(f"floor texture contrast {self.texture_contrast} is not in 0-2")
        if self.unmapped < 0 or self.distractors_per_m2 < 0 or self.stains_per_m2 < 0:
            raise InputError("unmapped stickers, distractor and stain densities must be >= 0")
        if self.res_m <= 0 or self.tile_m <= 0 or self.tile_m / self.res_m < 8:
            raise InputError(f"tile {self.tile_m} m at {self.res_m} m/texel is not a usable tile")


def _hash_uniform(seed: int, octave: int, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Deterministic pseudo-random values in [-1, 1) for integer lattice points (i, j)."""
    # splitmix64 finaliser over a mix of the coordinates: numpy has no stateless lattice RNG.
    with np.errstate(over="ignore"):
        h = (
            (i.astype(np.int64).view(np.uint64) * np.uint64(0x9E3779B97F4A7C15))
            ^ (j.astype(np.int64).view(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F))
            ^ np.uint64((seed * 1_000_003 + octave * 7919) & 0xFFFFFFFFFFFFFFFF)
        )
        h ^= h >> np.uint64(30)
        h *= np.uint64(0xBF58476D1CE4E5B9)
        h ^= h >> np.uint64(27)
        h *= np.uint64(0x94D049BB133111EB)
        h ^= h >> np.uint64(31)
    return ((h >> np.uint64(11)).astype(np.float64) / 2.0**53 * 2.0 - 1.0).astype(np.float32)


@dataclass
class _Feature:
    """A flat shape painted on the floor: polygon (K, 2) world m, reflectance, kind."""

    poly: np.ndarray
    value: float
    kind: str  # "line", "fill", "frame", "stain"
    inner: np.ndarray | None = None  # frame: inner polygon, filled with inner_value
    inner_value: float = 0.0
    ellipse: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # stain: centre (2,), axes (2,), rotation (2, 2)


class Floor:
    """A seeded warehouse floor around ``smap`` (see the module docstring).

    Attributes:
        stickers: StickerMap of the stickers physically on the floor (true poses).
        in_map: (N,) bool, True where ``stickers.ids[k]`` is in the map.
        missing_ids: (M,) IDs in the map that are not on the floor.
        soiling: (N,) multiplicative reflectance factor of each sticker.
    """

    def __init__(self, smap: StickerMap, config: FloorConfig | None = None, seed: int = 0):
        self.config = cfg = config or FloorConfig()
        self.seed = int(seed)
        self.map = smap
        rng = np.random.default_rng([self.seed, 11])
        self._tile = lru_cache(maxsize=cfg.cache_tiles)(self._make_tile)
        self._raster = lru_cache(maxsize=512)(self._make_raster)
        self._n = int(round(cfg.tile_m / cfg.res_m))
        if len(smap):
            lo, hi = smap.xy.min(axis=0) - cfg.margin_m, smap.xy.max(axis=0) + cfg.margin_m
        else:
            lo, hi = np.array([-cfg.margin_m] * 2), np.array([cfg.margin_m] * 2)
        self.bounds = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))

        keep = np.ones(len(smap), bool)
        n_missing = int(round(cfg.missing_fraction * len(smap)))
        if n_missing:
            keep[rng.choice(len(smap), n_missing, replace=False)] = False
        self.missing_ids = smap.ids[~keep].copy()
        ids, xy, yaw = [smap.ids[keep]], [smap.xy[keep]], [smap.yaw[keep]]
        if cfg.unmapped:
            u_xy = self._free_spots(rng, cfg.unmapped, smap.xy, lo, hi)
            taken = set(map(int, smap.ids))
            u_ids = []
            while len(u_ids) < len(u_xy):
                c = int(rng.integers(0, MAX_ID + 1))
                if c not in taken:
                    taken.add(c)
                    u_ids.append(c)
            ids.append(np.array(u_ids, np.int64))
            xy.append(u_xy)
            yaw.append(rng.uniform(-math.pi, math.pi, len(u_xy)))
        self.stickers = StickerMap(np.concatenate(ids), np.vstack(xy), np.concatenate(yaw), "floor")
        self.in_map = np.array([int(i) in smap for i in self.stickers.ids], bool)
        self.soiling = rng.uniform(0.88, 1.0, len(self.stickers)) if cfg.texture else np.ones(len(self.stickers))
        self._features = self._make_features(rng, lo, hi) if cfg.texture else []
        self._feature_boxes = np.array([np.r_[f.poly.min(axis=0), f.poly.max(axis=0)] for f in self._features]).reshape(
            -1, 4
        )
        self._light_phase = rng.uniform(0, cfg.light_spacing_m, 2)

    # -- stickers -------------------------------------------------------------------------------

    def _free_spots(
        self, rng: np.random.Generator, count: int, taken: np.ndarray, lo: np.ndarray, hi: np.ndarray
    ) -> np.ndarray:
        """``count`` points in the box, mostly near the map's lines, at least 0.3 m from other stickers.

        Refused (InputError) when no room for all of them is found: a floor with fewer unmapped
        stickers than asked for is not the session asked for.
        """
        gap = 0.3
        cell = 1.01 * gap  # every sticker within ``gap`` of a point is in its cell or the 8 around it
        grid: dict[tuple[int, int], list[np.ndarray]] = {}

        def key(p: np.ndarray) -> tuple[int, int]:
            return int(math.floor(p[0] / cell)), int(math.floor(p[1] / cell))

        def free(p: np.ndarray) -> bool:
            i, j = key(p)
            near = [q for di in (-1, 0, 1) for dj in (-1, 0, 1) for q in grid.get((i + di, j + dj), ())]
            return not near or float(np.min(np.hypot(*(np.asarray(near) - p).T))) > gap

        for p in taken:
            grid.setdefault(key(p), []).append(p)
        out: list[np.ndarray] = []
        for _ in range(count * 200):
            if len(out) == count:
                break
            if len(taken) and rng.random() < 0.7:  # near the walked lines, where the camera looks
                p = taken[rng.integers(len(taken))] + rng.normal(0.0, 0.6, 2)
            else:
                p = rng.uniform(lo, hi)
            if free(p):
                out.append(p)
                grid.setdefault(key(p), []).append(p)
        if len(out) < count:
            raise InputError(
                f"floor: found room for only {len(out)} of {count} unmapped stickers {gap:g} m apart"
                f" around the map's stickers ({200 * count} tries)"
            )
        return np.array(out).reshape(-1, 2)

    def sticker_raster(self, row: int, size_px: int) -> np.ndarray:
        """Reflectance raster (size_px, size_px) uint8 of the floor sticker in row ``row`` (canonical orientation)."""
        return self._raster(int(row), int(size_px))

    def _make_raster(self, row: int, size_px: int) -> np.ndarray:
        cfg = self.config
        img = render_sticker(int(self.stickers.ids[row]), size_px).astype(np.float32) / 255.0
        refl = (cfg.ink_black + img * (cfg.paper_white - cfg.ink_black)) * self.soiling[row]
        return np.clip(refl * 255.0 + 0.5, 0, 255).astype(np.uint8)

    # -- features -------------------------------------------------------------------------------

    def _make_features(self, rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray) -> list[_Feature]:
        cfg = self.config
        feats: list[_Feature] = []
        area = float(np.prod(hi - lo))
        if cfg.line_spacing_m > 0:
            for axis in (0, 1):
                span_lo, span_hi = lo[1 - axis], hi[1 - axis]
                for _ in range(rng.poisson((span_hi - span_lo) / cfg.line_spacing_m)):
                    c = rng.uniform(span_lo, span_hi)
                    w = rng.uniform(0.05, 0.10)
                    a = rng.uniform(lo[axis], hi[axis] - 2.0)
                    b = min(hi[axis], a + rng.uniform(4.0, 30.0))
                    rect = np.array([[a, c - w / 2], [b, c - w / 2], [b, c + w / 2], [a, c + w / 2]])
                    feats.append(_Feature(rect if axis == 0 else rect[:, ::-1], rng.uniform(0.6, 0.75), "line"))
        for _ in range(rng.poisson(cfg.stains_per_m2 * area)):
            c = rng.uniform(lo, hi)
            ax = rng.uniform(0.03, 0.25, 2)
            a = rng.uniform(0, math.pi)
            R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
            # poly is the bounding box; the stain itself is a soft ellipse (centre, axes, angle).
            box = c + (np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * ax.max())
            feats.append(_Feature(box, rng.uniform(0.55, 0.85), "stain", ellipse=(c, ax, R)))
        for _ in range(rng.poisson(cfg.distractors_per_m2 * area)):
            c = rng.uniform(lo, hi)
            s = rng.uniform(0.08, 0.15)
            a = rng.uniform(0, math.pi / 2)
            R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
            sq = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * 0.5
            dark = rng.uniform(0.04, 0.15)
            if rng.random() < 0.5:
                feats.append(_Feature(c + (s * sq) @ R.T, dark, "fill"))
            else:
                t = rng.uniform(0.006, 0.015)
                feats.append(
                    _Feature(c + (s * sq) @ R.T, dark, "frame", c + ((s - 2 * t) * sq) @ R.T, rng.uniform(0.6, 0.85))
                )
        return feats

    # -- tiles ----------------------------------------------------------------------------------

    def _noise(self, tx: int, ty: int, cell_m: float, octave: int) -> np.ndarray:
        """Value noise in about [-1, 1] over tile (tx, ty), from hashed lattice values (seamless)."""
        cfg, n = self.config, self._n
        x0, y0 = tx * cfg.tile_m, ty * cfg.tile_m
        i0, j0 = math.floor(x0 / cell_m) - 1, math.floor(y0 / cell_m) - 1
        ni = int(math.ceil(cfg.tile_m / cell_m)) + 4
        ii, jj = np.meshgrid(np.arange(i0, i0 + ni), np.arange(j0, j0 + ni))
        lattice = _hash_uniform(self.seed, octave, ii, jj)
        u = ((x0 + (np.arange(n) + 0.5) * cfg.res_m) / cell_m - i0).astype(np.float32)
        v = ((y0 + (np.arange(n) + 0.5) * cfg.res_m) / cell_m - j0).astype(np.float32)
        mx, my = np.meshgrid(u, v)
        # OpenCV's bicubic kernel is local (no prefilter), so neighbouring tiles agree on shared values.
        return cv2.remap(lattice, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)

    def _make_tile(self, tx: int, ty: int) -> np.ndarray:
        cfg, n = self.config, self._n
        if not cfg.texture:
            tile = np.full((n, n), cfg.base_reflectance * 255.0 + 0.5, np.float32)
            return tile.astype(np.uint8)
        rng = np.random.default_rng([self.seed, 13, tx & 0xFFFFFFFF, ty & 0xFFFFFFFF])
        mottle = (
            0.55 * self._noise(tx, ty, 1.6, 0)
            + 0.3 * self._noise(tx, ty, 0.45, 1)
            + 0.15 * self._noise(tx, ty, 0.12, 2)
        )
        c = cfg.texture_contrast
        refl = cfg.base_reflectance * (1.0 + c * cfg.mottle * mottle)
        speckle = cv2.GaussianBlur(rng.standard_normal((n, n), np.float32), (0, 0), 1.2)
        refl += c * cfg.grain * (rng.standard_normal((n, n), np.float32) + 2.0 * speckle)
        pits = rng.random((n, n), np.float32) < 0.002
        refl[pits] *= 1.0 - 0.45 * c  # 45 % darker on the reference floor (c <= 2 keeps them lit)
        x0, y0 = tx * cfg.tile_m, ty * cfg.tile_m
        self._draw_features(refl, x0, y0)
        return np.clip(refl * 255.0 + 0.5, 0, 255).astype(np.uint8)

    def _draw_features(self, refl: np.ndarray, x0: float, y0: float) -> None:
        cfg, n = self.config, self._n
        if not len(self._features):
            return
        b = self._feature_boxes
        hit = np.flatnonzero(
            (b[:, 2] >= x0) & (b[:, 0] <= x0 + cfg.tile_m) & (b[:, 3] >= y0) & (b[:, 1] <= y0 + cfg.tile_m)
        )
        shift = 4

        def px(poly: np.ndarray) -> np.ndarray:
            # Texel centres sit at (k + 0.5) * res_m; fixed point with 4 fractional bits.
            return np.round(((poly - (x0, y0)) / cfg.res_m - 0.5) * (1 << shift)).astype(np.int32)

        for k in hit:
            f = self._features[k]
            if f.kind == "stain":
                # Evaluated per texel from the world-anchored ellipse, so it joins across tiles.
                c, ax, R = f.ellipse
                xs = x0 + (np.arange(n) + 0.5) * cfg.res_m - c[0]
                ys = y0 + (np.arange(n) + 0.5) * cfg.res_m - c[1]
                u = (xs[None, :] * R[0, 0] + ys[:, None] * R[1, 0]) / ax[0]
                v = (xs[None, :] * R[0, 1] + ys[:, None] * R[1, 1]) / ax[1]
                m = np.clip(1.0 - (u * u + v * v), 0.0, 1.0).astype(np.float32)
                refl *= 1.0 - (m * m * (3 - 2 * m)) * (1.0 - f.value)  # smoothstep edge
                continue
            mask = np.zeros((n, n), np.uint8)
            cv2.fillPoly(mask, [px(f.poly)], 255, cv2.LINE_AA, shift)
            m = mask.astype(np.float32) / 255.0
            if f.kind == "line":  # worn paint lets the concrete through in places
                m *= np.clip(
                    0.8 + 1.2 * self._noise(int(round(x0 / cfg.tile_m)), int(round(y0 / cfg.tile_m)), 0.05, 5), 0.0, 1.0
                )
            refl += m * (f.value - refl)
            if f.inner is not None:
                mask[:] = 0
                cv2.fillPoly(mask, [px(f.inner)], 255, cv2.LINE_AA, shift)
                m = mask.astype(np.float32) / 255.0
                refl += m * (f.inner_value - refl)

    def tile(self, tx: int, ty: int) -> np.ndarray:
        """Reflectance tile (n, n) uint8 at integer tile coordinates (cached; do not modify)."""
        return self._tile(int(tx), int(ty))

    def mosaic(self, xmin: float, ymin: float, xmax: float, ymax: float) -> tuple[np.ndarray, np.ndarray]:
        """Tiles covering the box, joined: (image uint8 (H, W), A (3, 3) world (x, y, 1) -> texel (col, row, 1))."""
        cfg, n = self.config, self._n
        tx0, ty0 = math.floor(xmin / cfg.tile_m), math.floor(ymin / cfg.tile_m)
        tx1, ty1 = math.floor(xmax / cfg.tile_m), math.floor(ymax / cfg.tile_m)
        img = np.empty(((ty1 - ty0 + 1) * n, (tx1 - tx0 + 1) * n), np.uint8)
        for ty in range(ty0, ty1 + 1):
            for tx in range(tx0, tx1 + 1):
                img[(ty - ty0) * n : (ty - ty0 + 1) * n, (tx - tx0) * n : (tx - tx0 + 1) * n] = self.tile(tx, ty)
        s = 1.0 / cfg.res_m
        A = np.array([[s, 0.0, -tx0 * cfg.tile_m * s - 0.5], [0.0, s, -ty0 * cfg.tile_m * s - 0.5], [0, 0, 1.0]])
        return img, A

    def illumination(self, xy: np.ndarray) -> np.ndarray:
        """Relative illuminance (N,) at floor points (N, 2): about 1, brighter under the light grid."""
        cfg = self.config
        if not cfg.texture or cfg.illumination_variation == 0:
            return np.ones(len(xy))
        k = 2 * math.pi / cfg.light_spacing_m
        p = np.asarray(xy, float) - self._light_phase
        return 1.0 + cfg.illumination_variation * 0.5 * (np.cos(k * p[:, 0]) + np.cos(k * p[:, 1]))

    @property
    def mean_reflectance(self) -> float:
        """Typical floor reflectance, for what lies outside the generated tiles."""
        return self.config.base_reflectance


def sticker_size_px(side_px: float) -> int:
    """Raster size to render a sticker that appears ``side_px`` wide: ~1.5x oversampled, on a short ladder."""
    for s in (50, 100, 150, 200, 300, 400, 600, 800):
        if s >= 1.5 * side_px:
            return s
    return 800
