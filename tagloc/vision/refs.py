"""Reference bank for identifying stickers whose Data Matrix symbols cannot be decoded.

For every sticker of a map the bank holds its ORB keypoints and descriptors, computed on the
rendered sticker (:func:`tagloc.core.sticker.render_sticker`) at the scale of the rectified raster that
:mod:`tagloc.vision.identify` extracts from a frame, and the mean sticker over a fixed population of IDs
(the structure every sticker shares: frame, Data Matrix finder patterns), which the appearance
test subtracts. Appearance templates are not stored: rendering one is ~0.05 ms (cached grid), so
they are re-rendered on demand and memoised.

The bank is cached next to the map as ``<map>.refs.npz`` (``np.savez_compressed``, loaded with
``allow_pickle=False``), keyed by a SHA-256 of the map file's bytes and the bank parameters, so it
is rebuilt automatically whenever the map or the parameters change.
"""

from __future__ import annotations

import hashlib
import json
import os
import zipfile
import zlib
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from tagloc.core.errors import InputError
from tagloc.core.sticker import FRAME_M, SIZE_M, check_id, render_sticker
from tagloc.core.stickermap import StickerMap, load_map

#: Bumped whenever the bank's content or layout changes, so old caches are rebuilt.
BANK_VERSION = 1


@dataclass(frozen=True)
class BankParams:
    """How references are made. Changing any field changes the cache key.

    Attributes:
        orb_size_px: side of the sticker in the ORB raster (px). 128 px puts a 3.5 mm module on
            4.5 px, about what a 100-px sticker in a frame shows, upsampled a little so ORB's FAST
            detector finds module corners.
        orb_pad_px: constant border added around the ORB raster so keypoints near the inner
            area's edge keep their full descriptor patch.
        orb_features: most ORB keypoints kept per reference.
        orb_levels: ORB pyramid levels (scale factor 1.2).
        template_size_px: side of the appearance raster (px).
        mean_population: number of pseudo-random IDs averaged into the mean sticker.
        mean_seed: seed of that population (fixed: the mean must not depend on the map).
    """

    orb_size_px: int = 128
    orb_pad_px: int = 16
    orb_features: int = 300
    orb_levels: int = 3
    template_size_px: int = 64
    mean_population: int = 256
    mean_seed: int = 20240531

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)


def make_orb(params: BankParams) -> cv2.ORB:
    """The ORB extractor shared by references and scenes (same settings on both sides)."""
    return cv2.ORB_create(
        nfeatures=params.orb_features,
        scaleFactor=1.2,
        nlevels=params.orb_levels,
        edgeThreshold=15,
        patchSize=31,
        fastThreshold=10,
    )


def inner_box(size_px: int, margin_px: float = 0.0) -> tuple[float, float]:
    """(lo, hi) raster coordinates bounding the white inner area of a ``size_px`` raster."""
    d = FRAME_M / SIZE_M * size_px
    return d - 0.5 + margin_px, size_px - 0.5 - d - margin_px


def orb_features(
    raster: np.ndarray, params: BankParams, mask: np.ndarray, orb: cv2.ORB | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """ORB keypoints of a sticker raster that lie where stickers differ.

    Args:
        raster: (orb_size_px, orb_size_px) uint8 frontal raster (outer square only).
        mask: (orb_size_px, orb_size_px) bool, True where stickers differ (:func:`variable_mask`).
    Returns:
        xy: (M, 2) float32 keypoint positions, raster px (col, row) of the unpadded raster.
        des: (M, 32) uint8 ORB descriptors.
    """
    orb = orb or make_orb(params)
    pad = params.orb_pad_px
    # The floor around a sticker is unknown; a mid-grey border is the same guess on both sides.
    img = cv2.copyMakeBorder(raster, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=128)
    kps, des = orb.detectAndCompute(img, None)
    if des is None or not kps:
        return np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8)
    xy = np.array([k.pt for k in kps], np.float32) - pad
    # Frame and finder patterns are the same on every sticker: their features would match any
    # candidate at the right place and only blur the scores.
    ij = np.clip(np.round(xy).astype(int), 0, params.orb_size_px - 1)
    keep = mask[ij[:, 1], ij[:, 0]]
    return xy[keep], des[keep]


def population(size_px: int, count: int, seed: int) -> np.ndarray:
    """(count, size_px, size_px) float32 renders of ``count`` pseudo-random IDs (fixed by ``seed``)."""
    ids = np.random.default_rng(seed).choice(100000, size=count, replace=False)
    return np.stack([render_sticker(int(sid), size_px).astype(np.float32) for sid in ids])


def variable_mask(size_px: int, count: int, seed: int, min_std: float = 60.0) -> np.ndarray:
    """(size_px, size_px) bool: where the population's local (5x5) grey-level std exceeds ``min_std``."""
    std = population(size_px, count, seed).std(axis=0)
    return cv2.blur(std, (5, 5)) > min_std


@dataclass
class ReferenceBank:
    """ORB references of a map's stickers, plus what the appearance test needs.

    Attributes:
        ids: (N,) int64 sticker IDs in the bank.
        offsets: (N + 1,) int64; sticker ``ids[k]``'s features are rows ``offsets[k]:offsets[k+1]``.
        xy: (M, 2) float32 keypoint positions in the canonical ORB raster (px, col/row).
        des: (M, 32) uint8 ORB descriptors.
        mean_template: (S, S) float32 mean sticker, S = ``params.template_size_px``, 0-255.
        orb_mask: (P, P) bool, P = ``params.orb_size_px``: where ORB features are kept.
        params: how the bank was built.
        key: cache key (SHA-256 hex of map bytes + params + version), "" if built in memory.
    """

    ids: np.ndarray
    offsets: np.ndarray
    xy: np.ndarray
    des: np.ndarray
    mean_template: np.ndarray
    orb_mask: np.ndarray
    params: BankParams = field(default_factory=BankParams)
    key: str = ""
    _row: dict[int, int] = field(init=False, repr=False)
    _extra: dict[int, tuple[np.ndarray, np.ndarray]] = field(init=False, repr=False)
    _templates: dict[int, np.ndarray] = field(init=False, repr=False)
    _decades: dict[int, np.ndarray] = field(init=False, repr=False)
    #: Memo for data other modules derive from the bank (e.g. identify's blur basis).
    derived: dict = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.derived = {}
        self._row = {int(i): k for k, i in enumerate(self.ids)}
        self._extra = {}
        self._templates = {}
        self._decades = {}

    def __len__(self) -> int:
        return len(self.ids)

    def __contains__(self, sticker_id: int) -> bool:
        return int(sticker_id) in self._row

    def features(self, sticker_id: int) -> tuple[np.ndarray, np.ndarray]:
        """(xy (M, 2) float32, des (M, 32) uint8) of a sticker; computed and memoised if not banked."""
        sid = int(sticker_id)
        k = self._row.get(sid)
        if k is not None:
            a, b = self.offsets[k], self.offsets[k + 1]
            return self.xy[a:b], self.des[a:b]
        if sid not in self._extra:
            self._extra[sid] = orb_features(
                render_sticker(check_id(sid), self.params.orb_size_px), self.params, self.orb_mask
            )
        return self._extra[sid]

    def template(self, sticker_id: int) -> np.ndarray:
        """Rendered sticker (S, S) float32, canonical orientation, memoised."""
        sid = int(sticker_id)
        t = self._templates.get(sid)
        if t is None:
            t = render_sticker(check_id(sid), self.params.template_size_px).astype(np.float32)
            t.setflags(write=False)
            self._templates[sid] = t
        return t

    def decade_mean(self, sticker_id: int) -> np.ndarray:
        """Mean (S, S) float32 of the 9 other stickers with the same first four ID digits, memoised.

        They share the first two of the sticker's three data codewords (digit pairs), so this is
        the part of its appearance that a neighbouring, possibly unmapped, sticker also shows.
        """
        sid = check_id(sticker_id)
        m = self._decades.get(sid)
        if m is None:
            base = sid - sid % 10
            m = np.mean([self.template(i) for i in range(base, base + 10) if i != sid], axis=0).astype(np.float32)
            m.setflags(write=False)
            self._decades[sid] = m
        return m


def _as_ids(stickers: StickerMap | Iterable[int]) -> np.ndarray:
    ids = stickers.ids if isinstance(stickers, StickerMap) else np.fromiter((check_id(i) for i in stickers), np.int64)
    return np.asarray(ids, np.int64)


def build_refs(
    stickers: StickerMap | Iterable[int], params: BankParams | None = None, progress: bool = True, key: str = ""
) -> ReferenceBank:
    """Render every sticker and compute its references (tqdm progress bar when ``progress``)."""
    from tqdm import tqdm

    params = params or BankParams()
    ids = _as_ids(stickers)
    orb = make_orb(params)
    mask = variable_mask(params.orb_size_px, params.mean_population, params.mean_seed)
    xys, dess, offsets = [], [], [0]
    for sid in tqdm(ids, desc="references", unit="sticker", disable=not progress):
        xy, des = orb_features(render_sticker(int(sid), params.orb_size_px), params, mask, orb)
        xys.append(xy)
        dess.append(des)
        offsets.append(offsets[-1] + len(xy))
    mean = population(params.template_size_px, params.mean_population, params.mean_seed).mean(axis=0)
    return ReferenceBank(
        ids=ids,
        offsets=np.asarray(offsets, np.int64),
        xy=np.concatenate(xys) if xys else np.zeros((0, 2), np.float32),
        des=np.concatenate(dess) if dess else np.zeros((0, 32), np.uint8),
        mean_template=mean,
        orb_mask=mask,
        params=params,
        key=key,
    )


def cache_key(map_bytes: bytes, params: BankParams) -> str:
    """SHA-256 hex over the map file's bytes, the parameters and :data:`BANK_VERSION`."""
    h = hashlib.sha256()
    h.update(map_bytes)
    h.update(params.to_json().encode())
    h.update(f"bank-v{BANK_VERSION}".encode())
    return h.hexdigest()


def default_cache_path(map_path: str | Path) -> Path:
    """``maps/demo.csv`` -> ``maps/demo.refs.npz``."""
    p = Path(map_path)
    return p.with_name(p.stem + ".refs.npz")


def save_refs(bank: ReferenceBank, path: str | Path) -> None:
    """Write the bank as a compressed npz of plain arrays (atomically: temp file then rename)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            np.savez_compressed(
                fh,
                ids=bank.ids,
                offsets=bank.offsets,
                xy=bank.xy,
                des=bank.des,
                mean_template=bank.mean_template,
                orb_mask=bank.orb_mask,
                params=np.array(bank.params.to_json()),
                key=np.array(bank.key),
                version=np.array(BANK_VERSION),
            )
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def load_refs(path: str | Path) -> ReferenceBank:
    """Read a bank written by :func:`save_refs`; :class:`InputError` if it is not one (truncated, foreign)."""
    path = Path(path)
    try:
        return _load_refs(path)
    except (OSError, ValueError, EOFError, KeyError, TypeError, IndexError, zipfile.BadZipFile, zlib.error) as exc:
        # np.load reads members lazily: a cut or damaged archive fails on any of these.
        raise InputError(f"{path}: not a readable reference bank ({type(exc).__name__}: {exc})"[:300]) from None


def _load_refs(path: Path) -> ReferenceBank:
    with np.load(path, allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    need = {"ids", "offsets", "xy", "des", "mean_template", "orb_mask", "params", "key", "version"}
    if not need <= data.keys():
        raise InputError(f"{path}: reference bank lacks {', '.join(sorted(need - data.keys()))}")
    if data["version"].shape != () or int(data["version"]) != BANK_VERSION:
        raise InputError(f"{path}: reference bank version is not {BANK_VERSION}")
    try:
        params = BankParams(**json.loads(str(data["params"])))
    except (TypeError, ValueError) as exc:
        raise InputError(f"{path}: reference bank parameters are malformed") from exc
    ids, offsets = data["ids"].astype(np.int64), data["offsets"].astype(np.int64)
    des = data["des"]
    if (
        ids.ndim != 1
        or offsets.shape != (len(ids) + 1,)
        or des.ndim != 2
        or offsets[-1] != len(des)
        or des.shape[1:] != (32,)
        or np.any(np.diff(offsets) < 0)
        or offsets[0] != 0
    ):
        raise InputError(f"{path}: reference bank arrays are inconsistent")
    return ReferenceBank(
        ids=ids,
        offsets=offsets,
        xy=data["xy"].astype(np.float32),
        des=des.astype(np.uint8),
        mean_template=data["mean_template"].astype(np.float32),
        orb_mask=data["orb_mask"].astype(bool),
        params=params,
        key=str(data["key"]),
    )


def load_or_build_refs(
    map_path: str | Path,
    params: BankParams | None = None,
    progress: bool = True,
    cache_path: str | Path | None = None,
    rebuild: bool = False,
) -> ReferenceBank:
    """The bank of a map file: the cache if its key matches, else built (and cached when writable).

    The map is validated first (:func:`tagloc.core.stickermap.load_map`), so a bad map fails here with
    its file and line. A stale, corrupt or foreign cache is silently replaced. A ``cache_path`` given
    is an output asked for: failing to write it is an :class:`InputError` naming it (checked for a
    missing directory before the build). A cache that is the map file itself is refused, never written.
    """
    map_path = Path(map_path)
    params = params or BankParams()
    smap = load_map(map_path)
    key = cache_key(map_path.read_bytes(), params)
    cache = Path(cache_path) if cache_path is not None else default_cache_path(map_path)
    if cache_path is not None and not cache.parent.is_dir():
        raise InputError(f"{cache}: cannot write (no directory {cache.parent})")
    if cache.exists() and cache.samefile(map_path):
        # ``refs build site.csv -o site.csv`` had replaced the map by the bank built from it.
        raise InputError(f"{cache}: is the map itself; the bank would overwrite it")
    if not rebuild and cache.exists():
        try:
            bank = load_refs(cache)
        except InputError:
            bank = None
        if bank is not None and bank.key == key:
            return bank
    bank = build_refs(smap, params, progress=progress, key=key)
    try:
        save_refs(bank, cache)
    except OSError as exc:
        if cache_path is not None:
            raise InputError(f"{cache}: cannot write ({exc.strerror or exc})") from None
        # The default cache beside the map: a read-only map directory only costs a rebuild next time.
    return bank
