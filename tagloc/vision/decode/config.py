"""Options and outcome of :func:`tagloc.vision.decode.decode`."""

from __future__ import annotations

from dataclasses import dataclass, field

from tagloc.vision.decode.grid import Symbol


@dataclass
class DecodeConfig:
    """Options of :func:`decode`.

    Attributes:
        grid_sampling: run stage 2 (module grid sampling + zxing pure mode) when stage 1 fails.
        align_search_px: how far (raster px) each quadrant's module grid may shift to fit its
            finder/timing border (absorbs detector corner error); 0 disables the search.
        thresholds: where to cut between the finder's dark and light levels (0 dark, 1 light).
        verify: check accepted IDs against the re-rendered modules.
        min_verify: smallest :func:`verify_id` score accepted.
        libdmtx_timeout_ms: time bound of one libdmtx call (one quadrant).
        libdmtx_shrink: libdmtx's own down-sampling (2: 3.5 px per module).
        lsq: run the module least-squares stage (:func:`module_estimates`) when 1-2 fail.
        lsq_gamma: tone curve of the camera's 8-bit output, undone before the linear blur model.
        lsq_ridge: regularisation of the module estimates (see :func:`module_estimates`).
        lsq_flips: how many of a symbol's least certain modules may be flipped (2**n zxing attempts,
            each ~10 us; Reed-Solomon still decides, and symbols must agree and verify).
        expected_min_score, expected_min_margin: when :func:`decode` is given the ID the tracker
            expects and stages 1-2 read nothing, that ID's data modules (already sampled by stage
            2) are correlated with the raster in each rotation (:func:`verify_id`), on the modules
            that tell it from the other IDs of its decade (``distinct``: a decade shares each
            symbol's first two data codewords); the best rotation at or above
            ``expected_min_score``, leading the other three by ``expected_min_margin``, and at or
            above ``expected_min_score`` on all 256 modules too (the decode's own final check,
            ``min_verify``: a sticker blurred past that has poor corners too; on the standard walk
            s01, one named at 0.51 distinct but 0.44 on all modules gave four fixes ~10 cm off,
            accepted, and the track stayed 8 cm off for 3 s), names the sticker without the
            least-squares stage. On the eval and dense walks (``benchmarks/candidate_check.py``,
            the lower of the two scores) the expected sticker's best rotation scored 0.62
            (median; 88 % of events >= 0.5), its other rotations <= 0.20, another sticker <=
            0.22; on the same walks with every third sticker mapped under its decade neighbour's
            ID, the 2013 neighbour events scored <= 0.23 (<= 0.42 on all 256 modules, hence
            ``distinct``). The margin 0.2 is identification's own
            (:class:`tagloc.vision.identify.IdentifyConfig`).
    """

    grid_sampling: bool = True
    align_search_px: int = 4
    thresholds: tuple[float, ...] = (0.5, 0.4, 0.6)
    verify: bool = True
    min_verify: float = 0.5
    libdmtx_timeout_ms: int = 30
    libdmtx_shrink: int = 2
    lsq: bool = True
    lsq_gamma: float = 2.2
    lsq_ridge: float = 0.02
    lsq_flips: int = 6
    expected_min_score: float = 0.5
    expected_min_margin: float = 0.2


@dataclass
class DecodeResult:
    """Outcome of :func:`decode`.

    Attributes:
        sticker_id: decoded ID, or None.
        rotation: r (0-3): the canonical top-left corner is ``detection.outer[r]``; None if no ID.
        symbols: every symbol read: (payload, raster quadrant 0 TL..3 BL, backend), including the
            ones of a rejected read (so a caller can corroborate them itself).
        rejected: why symbols that were read did not give an ID (None if accepted or nothing read).
        verify_score: :func:`verify_id` of the accepted (or rejected-by-verification) ID, else None.
        stage: which stage decided ("zxing", "grid", "lsq", "libdmtx", or "expected": no symbol was
            read, the expected ID's modules matched; not a Data Matrix read), or None.
        rival: the ID that kept the expected ID from being named (its modules scored within
            ``expected_min_margin`` of the expected one's), else None.
    """

    sticker_id: int | None = None
    rotation: int | None = None
    symbols: list[Symbol] = field(default_factory=list)
    rejected: str | None = None
    verify_score: float | None = None
    stage: str | None = None
    rival: int | None = None
