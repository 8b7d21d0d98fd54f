"""Read a sticker's four Data Matrix symbols and turn them into (ID, in-plane rotation).

Pipeline on the rectified raster (:mod:`tagloc.vision.rectify`, 200 px, 7 px per module), cheapest first,
stopping as soon as the read is decided:

1. zxing-cpp on the whole raster (finds each symbol on its own; ~1 ms).
2. Grid sampling (when 1 read fewer than two symbols): the module geometry is known exactly, so
   each quadrant's 10x10 module centres are sampled, on a grid shifted by up to 4 raster px to
   where the symbol's fixed finder/timing border fits best (absorbing detector corner error); the
   symbols' common orientation comes from that border too. The modules are thresholded at levels
   learnt from the border and the clean, upright symbol is handed to zxing-cpp in pure mode. zxing
   still does the Reed-Solomon decoding: the payload always comes from a real Data Matrix decoder.
3. Module least squares (when 1-2 found nothing; :func:`module_estimates`): the raster, in linear
   light, is modelled as black level + contrast * (PSF * sticker), where the sticker is known
   except for its 256 data modules and the PSF is the lens + pixel spread mapped into the raster
   plus the motion blur fitted to the black frame's four edge profiles (:func:`blur_estimate`).
   One ridge-regularised solve per quadrant estimates every data module from all of its pixels,
   undoing the blur's cross-talk; each symbol is thresholded and handed to zxing (pure mode), also
   with its least certain modules flipped (Reed-Solomon still decides). On the physical simulator
   this lifts the read rate from 40 % to ~90 % at 4 px of motion blur and to 100 % up to 2 px.
   Before it, when the caller (the localiser, from the tracker) says which sticker it expects
   there, that ID's data modules are checked against the module samples stage 2 made, as in the
   final verification below; a clear match in one rotation names the sticker without the
   least-squares stage (stage "expected": a match to an expectation, not a read).
libdmtx (pylibdmtx) is an alternative backend, imported only when asked for, run per quadrant with
a time bound. libdmtx has been seen returning wrong payloads that look valid, so a single libdmtx
symbol is never accepted unless corroborated (a second agreeing symbol, zxing, or a tracker
candidate).

Every accepted read is finally verified: the decoded ID is re-rendered in the decoded rotation and
the raster's 256 data-module samples (the 8x8 interior of the four symbols; for stage 3 its own
module estimates) must correlate with it (:func:`verify_id`, accepted from 0.5). Wrong IDs differ
from the true one in most Reed-Solomon codewords, hence in many modules: measured, they score
<= 0.44 while true IDs score >= 0.9 up to 2 px of motion blur (stage 3 estimates on simulator
frames: wrong IDs and wrong rotations <= 0.45, true median 0.95).

Modules: :mod:`~tagloc.vision.decode.grid` (the raster's module grid), :mod:`~tagloc.vision.decode.backends`
(zxing, grid sampling, libdmtx), :mod:`~tagloc.vision.decode.blur` (blur measured on the frame edges),
:mod:`~tagloc.vision.decode.lsq` (blur-aware module estimation), :mod:`~tagloc.vision.decode.verify`
(combining symbols, verifying IDs); this module runs them in order.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Sequence

import numpy as np

from tagloc.core.camera import Camera
from tagloc.core.errors import InputError
from tagloc.core.types import Detection
from tagloc.vision.decode.backends import read_grid, read_libdmtx, read_zxing_whole
from tagloc.vision.decode.blur import blur_estimate, blur_extent
from tagloc.vision.decode.config import DecodeConfig, DecodeResult
from tagloc.vision.decode.grid import LONE_LIBDMTX, RASTER_PX, Symbol, module_samples
from tagloc.vision.decode.lookalike import best_scores
from tagloc.vision.decode.lsq import module_estimates, read_lsq
from tagloc.vision.decode.verify import combine_reads, verify_id
from tagloc.vision.image import require_gray
from tagloc.vision.rectify import rectify

__all__ = [
    "BACKENDS",
    "DecodeConfig",
    "DecodeResult",
    "Symbol",
    "blur_estimate",
    "blur_extent",
    "combine_reads",
    "decode",
    "module_estimates",
    "module_samples",
    "verify_id",
    "verify_detection",
]

BACKENDS = ("zxing", "libdmtx", "both")


def _decide(
    rect: np.ndarray,
    symbols: list[Symbol],
    config: DecodeConfig,
    candidates,
    stage: str,
    result: DecodeResult,
    samples: np.ndarray | None = None,
    grid: Callable[[], tuple[np.ndarray, int, np.ndarray]] | None = None,
) -> bool:
    """Fill ``result`` from ``symbols``; True when the read is settled (accepted or rejected).

    ``rect`` is the raster the symbols were read from; ``samples`` (4, 10, 10), when given, are the
    module values to verify instead (the least-squares estimates); ``grid`` returns the raster's
    :func:`module_samples` (made once per decode and shared by the stages).
    """
    sid, rot, why = combine_reads(symbols, config, candidates)
    result.symbols = list(symbols)
    if sid is None:
        result.rejected = why
        return why is not None and not why.startswith(LONE_LIBDMTX)
    if config.verify:
        if samples is None and grid is not None:
            samples = grid()[0]
        score = verify_id(rect, sid, rot, samples=samples, search_px=config.align_search_px)
        result.verify_score = score
        if score < config.min_verify:
            result.rejected = f"decoded {sid} (rotation {rot}) fails module verification ({score:.2f})"
            return True
    result.sticker_id, result.rotation, result.rejected, result.stage = sid, rot, None, stage
    return True


def decode(
    gray: np.ndarray,
    detection: Detection,
    camera: Camera,
    backend: str = "zxing",
    config: DecodeConfig | None = None,
    candidates: Iterable[int] | None = None,
    expected: Callable[[], Sequence[int]] | None = None,
) -> DecodeResult:
    """Decode the sticker at ``detection`` in ``gray``, the (H, W) uint8 frame of ``camera``.

    Args:
        backend: "zxing" (default: best measured read rate and speed), "libdmtx", or "both"
            (zxing first, libdmtx when zxing read nothing).
        candidates: IDs the tracker expects here; they may corroborate a lone libdmtx symbol.
        expected: gives the ID the tracker finds most likely here, then its rivals (the tracker's
            other candidates, the map's look-alikes of it: :mod:`~tagloc.vision.decode.lookalike`);
            empty: none. Asked only when stages 1-2 read nothing: the first ID's module check may
            then name the sticker before the least-squares stage, if it leads every rival
            (``DecodeConfig.expected_min_score``, ``expected_min_margin``; stage "expected").
    Returns:
        A :class:`DecodeResult`; ``sticker_id`` is None unless the symbols agree and verify, or
        the expected ID's modules match.
    """
    if backend not in BACKENDS:
        raise InputError(f"decode: unknown backend {backend!r} (choose from {', '.join(BACKENDS)})")
    require_gray(gray, "decode")
    config = config or DecodeConfig()
    candidates = list(candidates) if candidates is not None else None
    result = DecodeResult()
    rect = rectify(gray, detection, camera, RASTER_PX)
    # The raster's module grid is sampled at most once, by whichever stage needs it first.
    grid = functools.cache(lambda: module_samples(rect, config.align_search_px))
    if backend in ("zxing", "both"):
        if _read_raster(rect, config, candidates, "zxing", result, grid):
            return result
        if expected is not None and _check_expected(rect, expected(), config, result, grid):
            return result
        if config.lsq:
            blur = blur_estimate(gray, detection, camera)
            symbols, est = read_lsq(rect, detection, camera, config, blur, grid())
            if symbols and _decide(rect, symbols, config, candidates, "lsq", result, samples=est):
                return result
    if backend in ("libdmtx", "both"):
        symbols = read_libdmtx(rect, config)
        if backend == "both":
            symbols = result.symbols + symbols
        if symbols:
            _decide(rect, symbols, config, candidates, "libdmtx", result, grid=grid)
    return result


def _check_expected(
    rect: np.ndarray,
    sticker_ids: Sequence[int],
    config: DecodeConfig,
    result: DecodeResult,
    grid: Callable[[], tuple[np.ndarray, int, np.ndarray]],
) -> bool:
    """Fill ``result`` with ``sticker_ids[0]`` if its modules match the raster in one rotation clearly
    (``expected_min_score``, ``expected_min_margin``) and lead every other ID's (its rivals) in
    any rotation by ``expected_min_margin``; True then."""
    if not sticker_ids:
        return False
    sticker_id = int(sticker_ids[0])
    samples = grid()[0]
    # On the modules that tell the ID from its decade (a neighbour's symbols share the rest) ...
    scores = np.array([verify_id(rect, sticker_id, r, samples=samples, distinct=True) for r in range(4)])
    best = int(np.argmax(scores))
    margin = float(scores[best] - np.delete(scores, best).max())
    if scores[best] < config.expected_min_score or margin < config.expected_min_margin:
        return False
    # ... and on all of them, as a decode's final check: a sticker blurred past that is not named
    # (its corners, hence its fix, are as poor as its modules).
    whole = verify_id(rect, sticker_id, best, samples=samples)
    if whole < config.expected_min_score:
        return False
    # A look-alike seen where the expected sticker should be scores about their modules'
    # correlation (up to ~0.65) against the expected one; seen itself, it scores higher still.
    rivals = list(dict.fromkeys(int(i) for i in sticker_ids[1:] if int(i) != sticker_id))
    if rivals:
        others = best_scores(samples, rivals)
        worst = int(np.argmax(others))
        if scores[best] - others[worst] < config.expected_min_margin:
            result.rival = rivals[worst]
            return False
    result.sticker_id, result.rotation, result.stage = int(sticker_id), best, "expected"
    result.verify_score, result.rejected = float(min(scores[best], whole)), None
    return True


def verify_detection(
    gray: np.ndarray, detection: Detection, camera: Camera, sticker_id: int, rotation: int, search_px: int = 4
) -> float:
    """:func:`verify_id` of an expected ID and rotation on the detection's raster (no decoding).

    What re-checking a tracked sticker needs: rectifying and correlating the 256 data modules costs
    about a quarter of a decode that zxing reads at once, and a twentieth of one that falls through to
    the least-squares stage. The score separates the true ID (>= 0.9 up to 2 px of blur) from any
    other ID or rotation (<= 0.45), like a decode's final check.
    """
    require_gray(gray, "verify")
    return verify_id(rectify(gray, detection, camera, RASTER_PX), sticker_id, rotation, search_px=search_px)


def _read_raster(
    img: np.ndarray,
    config: DecodeConfig,
    candidates,
    stage: str,
    result: DecodeResult,
    grid: Callable[[], tuple[np.ndarray, int, np.ndarray]],
) -> bool:
    """Stages 1-2 on one raster; True when the read is settled."""
    symbols = read_zxing_whole(img)
    # Two agreeing symbols already decide; fewer: sample the grid of the quadrants left.
    if config.grid_sampling and len(symbols) < 2:
        symbols += read_grid(img, config, skip={p for _, p, _ in symbols}, grid=grid())
    if stage == "zxing" and symbols and all(b == "zxing-grid" for _, _, b in symbols):
        stage = "grid"
    return bool(symbols) and _decide(img, symbols, config, candidates, stage, result, grid=grid)
