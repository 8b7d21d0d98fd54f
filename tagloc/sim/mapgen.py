"""Warehouse-like sticker maps: parallel aisles, cross aisles, random spacing, yaws and IDs.

The layout follows a robotised warehouse floor: aisle centre-lines run along world +y, spaced
``aisle_spacing_m`` apart in x and centred in the floor; along each, consecutive stickers are
``spacing_min_m`` to ``spacing_max_m`` apart. ``cross_aisles`` lines run along +x at even fractions
of the depth, with stickers between neighbouring aisles spaced as evenly as the aisle spacing allows
within the same range (the aisles' own stickers serve the crossings). Every sticker is shifted
sideways by up to ``jitter_m`` and turned to a uniformly random yaw (stickers are laid at any
orientation). A cross-aisle sticker that would land within
``min_separation_m`` (default ``spacing_min_m``) of an aisle sticker is dropped, so by default no
two stickers anywhere are closer than ``spacing_min_m``. Same config and seed, same map.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from tagloc.core.errors import InputError
from tagloc.core.sticker import MAX_ID, SIZE_M
from tagloc.core.stickermap import StickerMap, load_map, save_map


@dataclass(frozen=True)
class GridMapConfig:
    """Parameters of :func:`grid_map` (metres).

    Attributes:
        width_m, depth_m: floor extent in world x and y; the floor spans [0, width] x [0, depth].
        aisle_spacing_m: distance between neighbouring aisle centre-lines.
        spacing_min_m, spacing_max_m: range of the along-line distance between consecutive stickers.
        jitter_m: largest sideways offset of a sticker from its line.
        cross_aisles: number of cross aisles (along x).
        margin_m: no sticker line closer than this to the floor's edge.
        min_separation_m: a cross-aisle sticker this close to an aisle sticker is dropped
            (None: ``spacing_min_m``).
        ids: "random" (distinct random IDs in 0-99999) or "sequential" (from ``first_id``).
        first_id: first ID when ``ids == "sequential"``.
        seed: random seed.
    """

    width_m: float = 40.0
    depth_m: float = 25.0
    aisle_spacing_m: float = 3.0
    spacing_min_m: float = 1.2
    spacing_max_m: float = 2.0
    jitter_m: float = 0.05
    cross_aisles: int = 2
    margin_m: float = 1.0
    min_separation_m: float | None = None
    ids: str = "random"
    first_id: int = 1
    seed: int = 7


@dataclass(frozen=True)
class MapInfo:
    """Summary of a map: count, bounds (xmin, ymin, xmax, ymax) in m, nearest-neighbour distances
    in m (min, median, mean, max), and the ID range."""

    source: str
    count: int
    bounds: tuple[float, float, float, float]
    nn_min: float
    nn_median: float
    nn_mean: float
    nn_max: float
    id_min: int
    id_max: int

    def __str__(self) -> str:
        x0, y0, x1, y1 = self.bounds
        nn = (
            f"  nearest neighbour: min {self.nn_min:.3f}  median {self.nn_median:.3f}  "
            f"mean {self.nn_mean:.3f}  max {self.nn_max:.3f} m"
            if self.count > 1
            else "  nearest neighbour: none (a single sticker)"
        )
        return (
            f"{self.source}: {self.count} stickers, IDs {self.id_min}-{self.id_max}\n"
            f"  bounds x {x0:.3f} .. {x1:.3f} m, y {y0:.3f} .. {y1:.3f} m ({x1 - x0:.2f} x {y1 - y0:.2f} m)\n"
            f"{nn}"
        )


def _min_separation(c: GridMapConfig) -> float:
    return c.spacing_min_m if c.min_separation_m is None else c.min_separation_m


def _check(c: GridMapConfig) -> None:
    if not (c.width_m > 2 * c.margin_m and c.depth_m > 2 * c.margin_m and c.margin_m >= 0):
        raise InputError(f"floor {c.width_m} x {c.depth_m} m leaves no room inside a {c.margin_m} m margin")
    if not SIZE_M < c.spacing_min_m <= c.spacing_max_m:
        raise InputError(f"want {SIZE_M} m < spacing-min <= spacing-max, got {c.spacing_min_m} and {c.spacing_max_m}")
    if c.jitter_m < 0:
        raise InputError(f"jitter {c.jitter_m} m must be >= 0")
    sep = _min_separation(c)
    if sep < SIZE_M:
        raise InputError(f"minimum separation {sep} m is below the sticker width {SIZE_M} m")
    if c.aisle_spacing_m < sep + 2 * c.jitter_m:
        raise InputError(f"aisle spacing {c.aisle_spacing_m} m is below min separation + 2 x jitter")
    if c.cross_aisles < 0:
        raise InputError(f"cross aisles {c.cross_aisles} must be >= 0")
    if c.cross_aisles and (c.depth_m - 2 * c.margin_m) / (c.cross_aisles + 1) < sep + 2 * c.jitter_m:
        raise InputError(f"{c.cross_aisles} cross aisles do not fit in {c.depth_m} m")
    if c.ids not in ("random", "sequential"):
        raise InputError(f"ids {c.ids!r} must be 'random' or 'sequential'")


def _along(length: float, c: GridMapConfig, rng: np.random.Generator) -> np.ndarray:
    """Positions (K,) in [0, length] along one line, consecutive ones spacing_min..max apart."""
    # Enough draws to cover the line even at the smallest spacing, then cut at the end.
    n = int(np.ceil(length / c.spacing_min_m)) + 2
    start = rng.uniform(0.0, c.spacing_min_m / 2)
    t = start + np.concatenate([[0.0], np.cumsum(rng.uniform(c.spacing_min_m, c.spacing_max_m, n))])
    return t[t <= length]


def _between(a: float, b: float, c: GridMapConfig, rng: np.random.Generator) -> np.ndarray:
    """Cross-aisle positions strictly between aisle lines at x = a < b, keeping the along-line gaps
    (including those to the two aisle lines) within spacing_min..spacing_max where the gap allows."""
    n = int(np.ceil((b - a) / c.spacing_max_m - 1e-9)) - 1  # fewest inner stickers for gaps <= max
    step = (b - a) / (n + 1) if n > 0 else 0.0
    if n <= 0 or step < c.spacing_min_m:
        return np.zeros(0)
    # Nominal even spacing, each shifted by at most half the slack so no gap drops below spacing_min.
    slack = (step - c.spacing_min_m) / 2
    return a + step * np.arange(1, n + 1) + rng.uniform(-slack, slack, n)


def grid_map(config: GridMapConfig = GridMapConfig()) -> StickerMap:
    """A seed-deterministic warehouse map with aisles and cross aisles (see module docstring)."""
    c = config
    _check(c)
    rng = np.random.default_rng(c.seed)
    span_x = c.width_m - 2 * c.margin_m
    n_aisles = int(np.floor(span_x / c.aisle_spacing_m + 1e-9)) + 1
    x_aisles = c.width_m / 2 + (np.arange(n_aisles) - (n_aisles - 1) / 2) * c.aisle_spacing_m
    length_y = c.depth_m - 2 * c.margin_m
    points = []
    for x in x_aisles:
        t = _along(length_y, c, rng)
        points.append(np.column_stack([x + rng.uniform(-c.jitter_m, c.jitter_m, len(t)), c.margin_m + t]))
    aisle_xy = np.vstack(points)
    tree = cKDTree(aisle_xy)
    cross = []
    for k in range(c.cross_aisles):
        y = c.margin_m + length_y * (k + 1) / (c.cross_aisles + 1)
        x = np.concatenate([_between(a, b, c, rng) for a, b in zip(x_aisles[:-1], x_aisles[1:])] or [np.zeros(0)])
        xy = np.column_stack([x, y + rng.uniform(-c.jitter_m, c.jitter_m, len(x))])
        if len(xy):
            d, _ = tree.query(xy)
            cross.append(xy[d >= _min_separation(c)])
    xy = np.vstack([aisle_xy, *cross])
    yaw = rng.uniform(0.0, 2 * np.pi, len(xy))
    if c.ids == "random":
        if len(xy) > MAX_ID + 1:
            raise InputError(f"{len(xy)} stickers need more than the {MAX_ID + 1} available IDs")
        ids = rng.choice(MAX_ID + 1, size=len(xy), replace=False)
    else:
        if not 0 <= c.first_id or c.first_id + len(xy) - 1 > MAX_ID:
            raise InputError(f"{len(xy)} sequential IDs from {c.first_id} go beyond {MAX_ID}")
        ids = np.arange(c.first_id, c.first_id + len(xy))
    return StickerMap(ids, xy, yaw, f"grid(seed={c.seed})")


def summarise_map(smap: StickerMap) -> MapInfo:
    """Count, bounds and nearest-neighbour spacing statistics of ``smap``."""
    if len(smap) < 2:
        nn = np.full(1, np.nan)
    else:
        d, _ = cKDTree(smap.xy).query(smap.xy, k=2)
        nn = d[:, 1]
    return MapInfo(
        smap.source,
        len(smap),
        smap.bounds,
        float(nn.min()),
        float(np.median(nn)),
        float(nn.mean()),
        float(nn.max()),
        int(smap.ids.min()),
        int(smap.ids.max()),
    )


def map_info(path: str | Path) -> MapInfo:
    """Load and validate the map at ``path`` and summarise it."""
    return summarise_map(load_map(path))


def write_grid_map(config: GridMapConfig, path: str | Path) -> MapInfo:
    """Generate a :func:`grid_map`, write it as CSV and return the summary of the file as reloaded.

    Reloading runs the full map validation on exactly what was written.
    """
    path = Path(path)
    if not path.parent.exists():
        raise InputError(f"{path}: directory {path.parent} does not exist")
    save_map(grid_map(config), path)
    return map_info(path)
