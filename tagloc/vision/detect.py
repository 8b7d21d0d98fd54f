"""Sticker detection: find each sticker's outer square and inner frame corners, sub-pixel.

Two stages:

1. Candidates, on an image ``downscale`` times smaller: adaptive threshold (dark = below the
   local mean), outer outlines of the dark blobs (filtered by size, fill and border contact), then
   each blob's convex hull approximated by a quadrilateral (a 5-6 sided polygon whose short edges
   cut corners off is extended back to a quad). A sticker's dark part (frame plus modules) covers
   20-80 % of its quad; a dark distractor square covers ~100 % and is rejected. A second pass with
   a wider closing (``group_px``) joins frames that heavy blur or a far, foreshortened view broke
   into pieces.
2. Refinement at full resolution, twice (the second pass re-aims at the first pass's lines):
   intensity profiles are sampled across each side in linear light (each averaged over a 3 px
   wide strip), the outer edge is placed where the profile crosses halfway between the floor
   level next to it and the sticker's ink level, the inner edge halfway between ink and paper.
   For a symmetric blur of a straight edge that crossing is the mid-exposure edge, unbiased as
   long as the blur across the edge is under twice the frame width (a 40 px sticker's 3.2 px
   frame tolerates 6.4 px) and the ink level is the one without blur, which the frame's darkest
   point is not under a blur of a few tenths of its width (:func:`_unblurred_ink`);
   a side blurred beyond that is located on the middle of the ramp from the dip to the paper,
   which lies over the frame's centre line. Edge points are undistorted, a line is fitted per side
   (Huber, gross outliers dropped), adjacent lines are intersected and the corners are distorted
   back to image pixels.

Corners are returned in distorted pixels, clockwise on screen, starting at an arbitrary corner
(decoding resolves the rotation). ``inner`` is None when the inner edges disagree with the outer
square's geometry (strong blur across a thin frame), so only trustworthy points reach the pose.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from tagloc.core.camera import REFERENCE_FOCAL_PX, Camera
from tagloc.core.errors import InputError
from tagloc.core.sticker import FRAME_M, INNER_M, MODULE_M, SIZE_M
from tagloc.core.types import Detection
from tagloc.vision.image import as_gray, clockwise

_FRAME_RATIO = FRAME_M / SIZE_M  # frame width as a fraction of the outer side
_INNER_RATIO = INNER_M / SIZE_M
_QUIET_RATIO = MODULE_M / SIZE_M  # white quiet zone inside the frame
_MAD_TO_SIGMA = 1.4826  # a normal distribution's sigma over its median absolute deviation
_NEXT = np.array([1, 2, 3, 0])  # side i runs from corner i to corner _NEXT[i]
_PREV = np.array([3, 0, 1, 2])
_UNIT_SQUARE = np.array([[-1, 1], [1, 1], [1, -1], [-1, -1]], np.float32)
HUBER_C = 1.345  # px: cv2.fitLine's Huber constant (95 % efficiency under Gaussian noise of 1 px)
_HUBER_ITERATIONS = 10  # reweighting passes; edge points converge in 3-5
_UNIT_INNER = (_UNIT_SQUARE.astype(float) * _INNER_RATIO).reshape(-1, 1, 2)


@dataclass
class DetectConfig:
    """Tuning of :func:`detect_stickers`. Pixel quantities are at full resolution.

    Attributes:
        downscale: the candidate stage runs on an image this many times smaller (1 or 2 ...).
        block_px: adaptive-threshold window; about half the largest expected sticker.
        dark_ratio, offset: a pixel is dark when below ``dark_ratio`` times its local mean and
            below the local mean minus ``offset`` grey levels.
        close_px: morphological closing of the dark mask (candidate resolution px; 0 = off).
        group_px: a second candidate pass closes the mask this much (candidate resolution px), so a
            frame broken into pieces by blur or foreshortening becomes one component (0 = off).
        min_side_px, max_side_px: accepted outer side lengths (longest side).
        border_px: all outer corners must be at least this far inside the image.
        min_dark_fraction, max_dark_fraction: dark share of the candidate quad (a sticker's frame
            alone is 0.29; closing can fill the code area). Plain dark squares are rejected later,
            by the paper level inside the frame.
        max_aspect: longest over shortest side, perspective included.
        max_candidates: largest components examined per frame (bounds the time on clutter).
        profiles_per_side: intensity profiles sampled across each side.
        coarse_profiles_per_side: the same for the first refinement pass, which only re-aims the
            second at the edges (its corners are not returned): half as many halve its cost.
        blur_allow_px: largest blur (px) the profiles are long enough for.
        min_contrast: least floor-to-ink and ink-to-paper difference (grey levels, linearised).
        min_paper_ratio: the paper inside the frame must be brighter than ink by at least this
            fraction of the floor-to-ink contrast.
        response_gamma: camera encoding exponent; values are raised to it before edge location,
            so halfway levels are taken in linear light (2.2: the Pi camera tone curve and the
            simulator; 1 = linear sensor output).
        inner_max_dev_px: largest disagreement between the measured inner corners and those
            implied by the outer square before ``inner`` is dropped.
        max_rms_px: largest RMS distance of edge points to their fitted line.
        profile_span: the profiles cover this central share of each side; the ends are left out
            because within a blur width of a corner the neighbouring side's edge mixes in.
        sample_step_px: spacing of the samples along a profile; half a pixel keeps the linear
            interpolation between samples well inside the bilinear image interpolation's own error.
        strip_half_px: each profile averages three parallel strips this far apart along the side
            (3 px wide), cutting pixel noise by sqrt(3) without bending the edge (a side's curvature
            over 2 px is nil).
        coarse_search_px: how far either side of a candidate quad's edge the first pass looks, in
            candidate-stage pixels (``downscale`` full-resolution px each), plus one full-resolution
            px: the candidate outline is within about a pixel of its resolution, twice that covers
            a corner cut or pulled by blur.
        refine_search_px: the same for the second pass, aimed at the first pass's lines (sub-pixel).
        max_refine_shift_px: the second pass may move a corner at most this far from the first;
            more means the first locked onto something else and the candidate is dropped.
        max_frame_fraction: a quad whose implied frame is wider than this share of its longest side
            is degenerate (the frame is 8 % of the side; perspective over 20-70 deg adds < 17 %).
        shallow_ratio: a side whose dip reaches less than this share of the floor-to-ink depth is
            blurred beyond twice the frame width and is located on the rise to the paper instead.
        shallow_ratio_sparse: the same, for a side whose halfway crossings are too few.
        ink_rounds: how many times the outer edges are located again at the ink level corrected
            for blur (:func:`_unblurred_ink`) in the final pass (0: the darkest level, as is);
            each round starts from the edges of the one before. On ideal renders (JPEG 85)
            under a 1 px Gaussian blur, 0 / 1 / 2 / 3 rounds leave the corners of a 40 px sticker
            0.41 / 0.23 / 0.20 / 0.18 px outward, and of a 50 px one 0.19 / 0.10 / 0.08 / 0.08.
        min_points_fraction: a side's line needs edge points on at least this share of its
            profiles (and at least 4).
        outlier_sigmas, outlier_floor_px: edge points further from the first line fit than this
            many robust sigmas, and at least this far, are dropped before the refit.
        full_score_contrast: floor-to-ink contrast (linear grey levels) at which a detection's
            score stops growing; a 300 lux floor under the Pi camera's exposure gives ~60-120.
    """

    downscale: int = 2
    block_px: int = 41
    dark_ratio: float = 0.8
    offset: int = 4
    close_px: int = 3
    group_px: int = 7
    min_side_px: float = 24.0
    max_side_px: float = 420.0
    border_px: float = 3.0
    min_dark_fraction: float = 0.2
    max_dark_fraction: float = 0.97
    max_aspect: float = 4.5
    max_candidates: int = 40
    profiles_per_side: int = 20
    coarse_profiles_per_side: int = 10
    blur_allow_px: float = 10.0
    min_contrast: float = 10.0
    min_paper_ratio: float = 0.5
    response_gamma: float = 2.2
    inner_max_dev_px: float = 0.8
    max_rms_px: float = 1.5
    profile_span: float = 0.7
    sample_step_px: float = 0.5
    strip_half_px: float = 1.0
    coarse_search_px: float = 2.0
    refine_search_px: float = 1.5
    max_refine_shift_px: float = 3.0
    max_frame_fraction: float = 0.25
    shallow_ratio: float = 0.45
    shallow_ratio_sparse: float = 0.75
    ink_rounds: int = 2
    min_points_fraction: float = 1 / 3
    outlier_sigmas: float = 3.0
    outlier_floor_px: float = 1.0
    full_score_contrast: float = 60.0

    @classmethod
    def for_camera(cls, camera: Camera) -> DetectConfig:
        """Defaults scaled to ``camera``: the sizes above are for a focal length of ~1286 px (the
        Pi camera v1 at 1296x972); a sticker's image size scales with the focal length, so the
        window and side limits do too, and below ~0.75 of it the candidate stage runs at full
        resolution, or a sticker 2 m away would be only ~15 px there."""
        scale = float(camera.K[0, 0]) / REFERENCE_FOCAL_PX
        if 0.9 <= scale <= 1.1:
            return cls()
        return cls(
            downscale=1 if scale < 0.75 else 2,
            block_px=max(15, int(round(41 * scale))),
            min_side_px=max(12.0, 24.0 * scale),
            max_side_px=420.0 * scale,
        )


def distort_ideal(camera: Camera, pixels: np.ndarray) -> np.ndarray:
    """Map ideal (undistorted) pixels (N, 2) to distorted pixels (N, 2): the inverse of undistort_pixels."""
    pts = np.asarray(pixels, float).reshape(-1, 2)
    if not np.any(camera.dist):
        return pts.copy()
    norm = (pts - camera.K[:2, 2]) / [camera.K[0, 0], camera.K[1, 1]]
    return camera.project(np.concatenate([norm, np.ones((len(norm), 1))], axis=1))


def median_last(a: np.ndarray) -> np.ndarray:
    """Median over the last axis of a NaN-free array: np.median's result at a fraction of its
    per-call overhead, which dominates on the few dozen values a side has."""
    n = a.shape[-1]
    srt = np.sort(a, axis=-1)
    return 0.5 * (srt[..., (n - 1) // 2] + srt[..., n // 2])


def masked_median_last(a: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median over the last axis of the values of ``a`` where ``mask`` (same shape) holds, NaN where
    none does, and how many there are: np.nanmedian's result without its per-call overhead."""
    n = mask.sum(axis=-1)
    # One row per set, its two middle values picked by index (np.take_along_axis's set-up cost more).
    srt = np.sort(np.where(mask, a, np.inf), axis=-1).reshape(n.size, a.shape[-1])
    rows = np.arange(n.size)
    lo, hi = srt[rows, (np.maximum(n - 1, 0) // 2).ravel()], srt[rows, (n // 2).ravel()]
    return np.where(n > 0, (0.5 * (lo + hi)).reshape(n.shape), np.nan), n


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (N, 3) arrays (np.cross's axis handling costs more than the product)."""
    return np.stack(
        [
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ],
        axis=1,
    )


def _side_lengths(quad: np.ndarray) -> np.ndarray:
    """Lengths (4,) of the sides of a quad (4, 2), side i from corner i to corner i + 1."""
    d = quad[_NEXT] - quad
    return np.sqrt(np.einsum("ij,ij->i", d, d))


def _polygon_area(quad: np.ndarray) -> float:
    x, y = quad[:, 0], quad[:, 1]
    return 0.5 * abs(float(np.dot(x, y[_NEXT]) - np.dot(x[_NEXT], y)))


def _fit_sides(contour: np.ndarray, quad: np.ndarray) -> np.ndarray:
    """Sharpen a polygon-approximated quad (4, 2): fit a line to the outline points (N, 2) along each
    side and intersect them. approxPolyDP keeps outline vertices, which can sit a few pixels inside
    a corner that blur or noise has rounded; the sides themselves are well defined."""
    d = quad[_NEXT] - quad  # (4, 2)
    length = np.sqrt(np.einsum("ij,ij->i", d, d))
    if length.min() < 4:
        return quad
    # x and y apart, (4, N) each: numpy is slow over a trailing axis of 2.
    rx, ry = contour[None, :, 0] - quad[:, 0:1], contour[None, :, 1] - quad[:, 1:2]
    along, normal = d / length[:, None] ** 2, d / length[:, None]
    u = rx * along[:, 0:1] + ry * along[:, 1:2]  # position along each side, 0-1
    off = np.abs(ry * normal[:, 0:1] - rx * normal[:, 1:2])
    near = (u > 0.15) & (u < 0.85) & (off < np.maximum(1.5, 0.06 * length)[:, None])
    if near.sum(axis=1).min() < 4:
        return quad
    corners = _intersect(huber_lines(np.broadcast_to(contour, (4, *contour.shape)), near))
    if not np.all(np.isfinite(corners)) or np.abs(corners - quad).max() > 0.25 * float(length.min()):
        return quad
    return corners


def cut_corners_back(poly: np.ndarray) -> np.ndarray | None:
    """Reduce a convex polygon (K, 2), K = 4-6, to a quad by extending the neighbours of its
    shortest edge until they meet, as often as needed: blur and small foreshortened stickers round
    corners off, and the outline's polygon then has a short edge across each. None if that fails."""
    p = poly
    while len(p) > 4:
        k = len(p)
        i = int(np.argmin(np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1)))
        a0, a1, b0, b1 = p[(i - 1) % k], p[i], p[(i + 1) % k], p[(i + 2) % k]
        if np.linalg.norm(b0 - a1) > 0.5 * min(np.linalg.norm(a1 - a0), np.linalg.norm(b1 - b0)):
            return None  # not a small cut across a corner
        x = np.cross(np.cross([*a0, 1.0], [*a1, 1.0]), np.cross([*b0, 1.0], [*b1, 1.0]))
        if abs(x[2]) < 1e-9:
            return None
        corner = x[:2] / x[2]
        # The new corner must lie beyond the cut edge, not far out (nearly parallel neighbours).
        if np.linalg.norm(corner - (a1 + b0) / 2) > np.linalg.norm(b0 - a1) + 0.25 * np.linalg.norm(a1 - a0):
            return None
        p = np.array([corner if j == i else p[j] for j in range(k) if j != (i + 1) % k])
    return p


def _outline_quads(
    mask: np.ndarray,
    cfg: DetectConfig,
    ds: int,
    skip: set[tuple[int, ...]] | None = None,
    dark_mask: np.ndarray | None = None,
    origin: tuple[int, int] = (0, 0),
    margins: tuple[int, int, int, int] = (0, 0, 0, 0),
) -> tuple[list[tuple[float, np.ndarray]], set[tuple[int, ...]]]:
    """Quads (4, 2) in full-resolution pixels of the mask's blobs (outer outlines) that can be stickers.

    Blobs whose bounding box (x, y, w, h) is in ``skip`` are ignored. The dark share of a quad is
    counted in ``dark_mask`` (default ``mask``) inside the blob's outline: a widely closed mask fills
    a sticker's inside. ``mask`` may be a cut-out of the candidate image whose top left pixel is
    ``origin`` there; a blob within ``margins`` (left, top, right, bottom) px of the cut-out's edges
    is left out (near a cut the cut-out's threshold differs from the whole image's; 0 at an image
    edge). Returns (blob area, quad) pairs, largest blob first, and the bounding boxes of their
    blobs (in ``mask``).
    """
    h, w = mask.shape
    # Outer outlines rather than labelled components: the outline is what the quad is fitted to,
    # and findContours costs a small fraction of connectedComponentsWithStats on a noisy mask.
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    dark_src = mask if dark_mask is None else dark_mask
    lo, hi = cfg.min_side_px / ds, cfg.max_side_px / ds
    found: set[tuple[int, ...]] = set()
    blobs = []
    # An outline round a blob spanning k pixels in x or y goes there and back in steps of at most one
    # pixel: at least 2 (k - 1) points. Most outlines are specks of floor texture; their length rules
    # them out before the (costlier) bounding box.
    min_len = 2 * (math.ceil(0.7 * lo) - 1)
    for c in contours:
        if len(c) < min_len:
            continue
        box = cv2.boundingRect(c)
        x0, y0, ww, hh = box
        if (
            not 0.7 * lo <= max(ww, hh) <= 1.2 * hi
            or x0 <= margins[0]
            or y0 <= margins[1]
            or x0 + ww >= w - margins[2]
            or y0 + hh >= h - margins[3]
            or (skip and box in skip)
        ):
            continue
        local = c.reshape(-1, 2) - [x0, y0]
        fill = np.zeros((hh, ww), np.uint8)
        cv2.drawContours(fill, [local.reshape(-1, 1, 2)], -1, 255, cv2.FILLED)
        area = cv2.countNonZero(cv2.bitwise_and(fill, dark_src[y0 : y0 + hh, x0 : x0 + ww]))
        # A quad's box is at most 2x its area (a square at 45 deg); its dark share is >= min_dark_fraction.
        if 0.5 * cfg.min_dark_fraction * min(ww, hh) ** 2 / cfg.max_aspect <= area <= 0.97 * ww * hh:
            blobs.append((area, local, box))
    blobs.sort(key=lambda b: -b[0])
    quads = []
    for area, local, (x0, y0, ww, hh) in blobs[: cfg.max_candidates]:
        hull = cv2.convexHull(local.reshape(-1, 1, 2).astype(np.int32))
        peri = cv2.arcLength(hull, True)
        quad = None
        for eps in (0.03, 0.05, 0.08):
            approx = cv2.approxPolyDP(hull, eps * peri, True)
            if 4 <= len(approx) <= 6:
                quad = cut_corners_back(approx.reshape(-1, 2).astype(float))
                if quad is not None:
                    break
        if quad is None:
            continue
        pts = local.astype(float)
        fitted = _fit_sides(pts, quad)
        if fitted is not quad:  # the second fit gathers what a skewed first missed (the same input: the same)
            fitted = _fit_sides(pts, fitted)
        hull_area = cv2.contourArea(hull)
        # Only a clearly cut corner is replaced (refinement, not this fit, sets the final accuracy; a
        # sub-pixel change only reshuffles its profiles), and not when the ring's inner outline
        # pulled a side in.
        if np.abs(fitted - quad).max() > 1.0 and _polygon_area(fitted) >= 0.85 * hull_area:
            quad = fitted
        qa = _polygon_area(quad)
        if qa < 0.85 * hull_area or not cv2.isContourConvex(quad.astype(np.float32)):
            continue
        dark = float(area) / max(qa, 1.0)
        if not cfg.min_dark_fraction <= dark <= cfg.max_dark_fraction:
            continue
        sides = _side_lengths(quad)
        if sides.max() > cfg.max_aspect * max(sides.min(), 1e-6):
            continue
        # Outline pixel centres sit half a pixel inside the blob's edge; refinement corrects the rest.
        quads.append((float(area), clockwise((quad + [x0 + origin[0] + 0.5, y0 + origin[1] + 0.5]) * ds - 0.5)))
        found.add((x0, y0, ww, hh))
    return quads, found


def _candidates(
    gray: np.ndarray, cfg: DetectConfig, regions: list[tuple[int, int, int, int]] | None = None
) -> list[np.ndarray]:
    """Coarse quads (4, 2), full-resolution pixels, clockwise, largest first: of the whole image, or of
    the blobs inside ``regions`` (see :func:`detect_stickers`)."""
    ds = max(1, int(cfg.downscale))
    if regions is None:
        first, group = _candidates_in(gray, cfg, ds, (0, 0), (0, 0, 0, 0))
    else:
        first, group = [], []
        h, w = gray.shape
        # Far enough from a cut edge, a pixel's threshold window and closings see only the cut-out:
        # there its mask is the whole image's.
        interior = _threshold_reach(cfg, ds)
        for x0, y0, x1, y1 in merge_boxes(regions):
            # Cut on whole candidate pixels (the downscaled cut-out is then the whole image's).
            cx0, cy0 = max(0, x0 // ds - interior), max(0, y0 // ds - interior)
            cx1, cy1 = min(w // ds, -(-x1 // ds) + interior), min(h // ds, -(-y1 // ds) + interior)
            if cx1 - cx0 <= 2 * interior or cy1 - cy0 <= 2 * interior:
                continue
            # A cut edge keeps blobs off it; an image edge only by the whole image's own rule.
            margins = (
                interior if cx0 > 0 else 0,
                interior if cy0 > 0 else 0,
                interior if cx1 < w // ds else 0,
                interior if cy1 < h // ds else 0,
            )
            cut = gray[cy0 * ds : cy1 * ds, cx0 * ds : cx1 * ds]
            f, g = _candidates_in(cut, cfg, ds, (cx0, cy0), margins)
            first += f
            group += g
        first.sort(key=lambda q: -q[0])
        group.sort(key=lambda q: -q[0])
    # Each pass (and each region's) keeps up to max_candidates; the frame's bound is on their sum,
    # or a floor of sticker-like clutter gets twice the examination (and decoding) it is allowed.
    return [q for _, q in (first + group)[: cfg.max_candidates]]


def _threshold_reach(cfg: DetectConfig, ds: int) -> int:
    """How far (candidate px) the adaptive threshold and closings reach: half the threshold window,
    half each closing, and a pixel for the outline."""
    block = max(3, int(round(cfg.block_px / ds)) | 1)
    return block // 2 + max(cfg.close_px, 0) // 2 + max(cfg.group_px, 0) // 2 + 2


def merge_boxes(boxes: list[tuple[int, int, int, int]]) -> list[tuple[int, int, int, int]]:
    """Boxes (x0, y0, x1, y1) with overlapping ones merged into their bounding box (so that no blob
    is found twice), until none overlap."""
    out = [[int(v) for v in b] for b in boxes]
    changed = True
    while changed:
        changed = False
        merged: list[list[int]] = []
        for b in out:
            for m in merged:
                if b[0] <= m[2] and m[0] <= b[2] and b[1] <= m[3] and m[1] <= b[3]:
                    m[0], m[1], m[2], m[3] = min(m[0], b[0]), min(m[1], b[1]), max(m[2], b[2]), max(m[3], b[3])
                    changed = True
                    break
            else:
                merged.append(b)
        out = merged
    return [(b[0], b[1], b[2], b[3]) for b in out]


def _candidates_in(
    gray: np.ndarray, cfg: DetectConfig, ds: int, origin: tuple[int, int], margins: tuple[int, int, int, int]
) -> tuple[list[tuple[float, np.ndarray]], list[tuple[float, np.ndarray]]]:
    """(blob area, quad) pairs of the first and the grouping pass on ``gray`` (a cut-out whose top
    left is candidate pixel ``origin``; blobs within ``margins`` of its edges left out)."""
    small = (
        gray if ds == 1 else cv2.resize(gray, (gray.shape[1] // ds, gray.shape[0] // ds), interpolation=cv2.INTER_AREA)
    )
    block = max(3, int(round(cfg.block_px / ds)) | 1)
    # Dark means below both a fraction of the local mean (a ratio holds at any exposure; 0.8 still
    # catches a thin frame smeared by 6-8 px of blur) and the mean minus an offset (keeps sensor
    # noise in black areas out).
    mean = cv2.blur(small, (block, block))
    thr = cv2.min(cv2.convertScaleAbs(mean, alpha=cfg.dark_ratio), cv2.subtract(mean, cfg.offset))
    mask = cv2.compare(small, thr, cv2.CMP_LT)
    if cfg.close_px > 1:
        # Blur across a thin frame leaves it as dashes; closing rejoins them into one ring.
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_RECT, (cfg.close_px,) * 2))
    quads, boxes = _outline_quads(mask, cfg, ds, origin=origin, margins=margins)
    group: list[tuple[float, np.ndarray]] = []
    if cfg.group_px > max(cfg.close_px, 1):
        # Heavy blur across a side, or a side seen nearly edge-on at 2-2.5 m, leaves the frame under
        # a pixel wide here and it breaks into pieces that no single blob spans. A wider closing
        # groups the pieces; a group that is a first-pass blob already made into a quad is not new.
        grouped = cv2.morphologyEx(
            mask, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_RECT, (cfg.group_px,) * 2)
        )
        group = _outline_quads(grouped, cfg, ds, skip=boxes, dark_mask=mask, origin=origin, margins=margins)[0]
    return quads, group


def huber_lines(
    points: np.ndarray, mask: np.ndarray, iterations: int = _HUBER_ITERATIONS, group: int | None = None
) -> np.ndarray:
    """Huber line fits of L point sets at once: points (L, N, 2), mask (L, N) of the points that count.

    Iteratively reweighted total least squares (what cv2.fitLine's DIST_HUBER does, one set per
    call): each pass fits the weighted principal axis in closed form for every set, then gives a
    point at distance r > C the weight C / r (C = 1.345 px, OpenCV's default). The passes stop
    once no weight moves by 1e-3 within a group of ``group`` consecutive sets (None: all L are one
    group); a group that stopped keeps that pass's lines, as if fitted on its own (refinement fits
    the four sides of several stickers at once, a group each). Returns homogeneous lines (L, 3)
    with unit normals; NaN rows for sets of fewer than two points.
    """
    w = mask.astype(float)
    L = len(points)
    g = L if group is None else group
    n_groups = L // max(g, 1)
    # x and y as rows (L, 2, N), so that each pass handles both coordinates in one array operation
    # (the few dozen points per set make numpy's per-call overhead the cost). The arithmetic is that
    # of the per-coordinate form: the same products, each summed over a set's points in the same order.
    xy = np.ascontiguousarray(points.transpose(0, 2, 1), dtype=float)
    out = np.empty((L, 3)) if n_groups > 1 else None
    done = np.zeros(n_groups, bool)
    with np.errstate(invalid="ignore", divide="ignore"):
        for _ in range(iterations):
            w3 = w[:, None, :]
            sw = w.sum(axis=1)
            m = (w3 * xy).sum(axis=2) / sw[:, None]  # (L, 2) weighted centroid
            d = xy - m[:, :, None]
            wd = w3 * d
            sxx, syy = (wd * d).sum(axis=2).T
            sxy = (wd[:, 0] * d[:, 1]).sum(axis=1)
            theta = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # direction of the principal axis
            nx, ny = -np.sin(theta), np.cos(theta)
            r = np.abs(d[:, 0] * nx[:, None] + d[:, 1] * ny[:, None])
            w_new = np.where(mask, np.minimum(1.0, HUBER_C / r), 0.0)  # Huber: 1 within C, C / r beyond
            if n_groups == 1:
                if float(np.abs(w_new - w).max()) < 1e-3:
                    break
            else:
                settled = np.abs(w_new - w).reshape(n_groups, -1).max(axis=1) < 1e-3
                now = settled & ~done
                if now.any():
                    rows = np.repeat(now, g)
                    out[rows] = np.stack([nx, ny, -(nx * m[:, 0] + ny * m[:, 1])], axis=1)[rows]
                    done |= settled
                    if done.all():
                        return out
            w = w_new
    lines = np.stack([nx, ny, -(nx * m[:, 0] + ny * m[:, 1])], axis=1)
    if out is None:
        return lines
    rest = np.repeat(~done, g)
    out[rest] = lines[rest]
    return out


def _line_residuals(points: np.ndarray, lines: np.ndarray) -> np.ndarray:
    """Absolute distances (L, N) of points (L, N, 2) to their set's line (L, 3)."""
    return np.abs(points[..., 0] * lines[:, 0:1] + points[..., 1] * lines[:, 1:2] + lines[:, 2:3])


def _robust_lines(
    points: np.ndarray, mask: np.ndarray, min_points: int, sigmas: float, floor_px: float, group: int | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`robust_line` for L point sets at once (points (L, N, 2), mask (L, N)), in groups of
    ``group`` consecutive sets (None: one group of all): lines (L, 3), inlier RMS (L,), inlier mask
    (L, N), and per group whether every set kept at least ``min_points`` (G,) (where not, its
    lines are not to be used)."""
    g = len(points) if group is None else group
    lines = huber_lines(points, mask, group=g)
    res = _line_residuals(points, lines)
    med = masked_median_last(res, mask)[0]  # NaN for an empty set, which keeps nothing
    keep = mask & (res <= np.maximum(floor_px, sigmas * _MAD_TO_SIGMA * med)[:, None])
    n_groups = len(points) // max(g, 1)
    ok = keep.sum(axis=1).reshape(n_groups, g).min(axis=1) >= min_points
    # A group without outliers keeps its fit (usually); the others are refitted on their inliers.
    refit = np.repeat(ok & (keep != mask).reshape(n_groups, -1).any(axis=1), g)
    if refit.any():
        lines[refit] = huber_lines(points[refit], keep[refit], group=g)
        res[refit] = _line_residuals(points[refit], lines[refit])
    # (A group refused above may keep no point; its RMS is not used.)
    rms = np.sqrt((np.where(keep, res, 0.0) ** 2).sum(axis=1) / np.maximum(keep.sum(axis=1), 1))
    return lines, rms, keep, ok


def robust_line(
    points: np.ndarray, min_points: int, sigmas: float = 3.0, floor_px: float = 1.0
) -> tuple[np.ndarray, float, np.ndarray] | None:
    """Line through (N, 2) edge points after dropping gross outliers; None if too few remain.

    A profile whose crossing locked onto a module, a noise spike or a floor mark lands pixels off the
    edge; one such point must not sink a side whose other points are on a line. Points further than
    ``sigmas`` robust sigmas (at least ``floor_px``) from the first Huber fit are dropped and the line
    refitted. Returns the line (3,), the inliers' RMS residual (px) and the inlier mask (N,).
    (One set of :func:`_robust_lines`, which refinement runs on the sides of several stickers at once.)
    """
    lines, rms, keep, ok = _robust_lines(points[None], np.ones((1, len(points)), bool), min_points, sigmas, floor_px)
    if not ok[0]:
        return None
    return lines[0], float(rms[0]), keep[0]


def _intersect(lines: np.ndarray) -> np.ndarray:
    """Corner i = side i-1 x side i, for (..., 4, 3) lines; returns (..., 4, 2)."""
    p = _cross(lines[..., _PREV, :].reshape(-1, 3), lines.reshape(-1, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        return (p[:, :2] / p[:, 2:3]).reshape(*lines.shape[:-1], 2)


def _implied_inner(outer_ideal: np.ndarray) -> np.ndarray:
    """Inner corners (4, 2) implied by the outer square through its homography (ideal pixels)."""
    H = cv2.getPerspectiveTransform(_UNIT_SQUARE, outer_ideal.astype(np.float32))
    return cv2.perspectiveTransform(_UNIT_INNER, H).reshape(4, 2)


def _crossings(prof: np.ndarray, level: np.ndarray, s: np.ndarray, expect: np.ndarray, rising: bool) -> np.ndarray:
    """Sub-sample position of the crossing of ``level`` nearest ``expect`` in each profile (NaN if none).

    prof (M, S) samples at positions s (S,), level (M,), expect (M,).
    """
    d = prof - level[:, None]
    a, b = d[:, :-1], d[:, 1:]
    hit = (a < 0) & (b >= 0) if rising else (a >= 0) & (b < 0)
    frac = a / np.where(a == b, 1.0, a - b)
    pos = s[:-1] + frac * (s[1] - s[0])
    dist = np.where(hit, np.abs(pos - expect[:, None]), np.inf)
    j = np.argmin(dist, axis=1)
    rows = np.arange(len(j))
    out = pos[rows, j]
    out[np.isinf(dist[rows, j])] = np.nan
    return out


@dataclass
class _Refined:
    outer: np.ndarray  # (4, 2) distorted
    inner: np.ndarray | None
    outer_ideal: np.ndarray
    score: float


@dataclass
class _Profiles:
    """Intensity profiles across the four sides of K quads, in linear light.

    base (K, 4, n, 2): profile origins on the sides (distorted px); inward (K, 4, 2): unit normals
    into the quads; s (S,): sample positions along ``inward`` (px), shared, each quad's own
    ``length`` (K,) first of them sampled (its profiles are NaN beyond); prof (K, 4, n, S):
    profiles (each the mean of a strip across the side); frame_w (K, 4, n): distance to the inner
    edge implied by the quad, px; fw (K,): its median; quiet (K,): width of the quiet zone inside
    the frame, px.
    """

    base: np.ndarray
    inward: np.ndarray
    s: np.ndarray
    length: np.ndarray
    prof: np.ndarray
    frame_w: np.ndarray
    fw: np.ndarray
    quiet: np.ndarray


class _Linearise:
    """The camera tone curve undone on interpolated 8-bit values: piecewise linear through
    ``255 (v / 255) ** gamma`` at the 256 codes (what np.interp over the table gives, without its
    per-call set-up)."""

    def __init__(self, gamma: float):
        lut = 255.0 * (np.arange(256) / 255.0) ** gamma
        self.lut = lut.astype(np.float32)
        self.slope = np.append(np.diff(lut), 0.0).astype(np.float32)

    def __call__(self, vals: np.ndarray) -> np.ndarray:
        i = vals.astype(np.int32)  # floor: the values are >= 0
        np.minimum(i, 254, out=i)
        return self.lut[i] + (vals - i) * self.slope[i]


@functools.lru_cache(maxsize=8)
def _lineariser(gamma: float) -> _Linearise | None:
    return None if gamma == 1.0 else _Linearise(gamma)


@functools.lru_cache(maxsize=32)
def _linspace(start: float, stop: float, num: int) -> np.ndarray:
    """np.linspace, made once per distinct call (read-only): its set-up costs more than the few values."""
    out = np.linspace(start, stop, num)
    out.flags.writeable = False
    return out


def _nan_to(a: np.ndarray, value: float) -> np.ndarray:
    """``a`` with NaNs replaced by ``value`` (np.nan_to_num's infinity handling is not needed here)."""
    return np.where(np.isnan(a), value, a)


#: cv2.remap refuses maps of 32767 rows or more (SHRT_MAX): a frame with many large candidates
#: (say 50 quads with 200 px sides) gives more profile rows than that.
_REMAP_MAX_ROWS = 32766


def _remap_rows(gray: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """``cv2.remap`` (bilinear, replicated border) of ``gray`` at the float32 maps (R, C), in blocks
    of rows that remap takes."""
    if len(map_x) <= _REMAP_MAX_ROWS:
        return cv2.remap(gray, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.concatenate(
        [
            cv2.remap(
                gray,
                map_x[r : r + _REMAP_MAX_ROWS],
                map_y[r : r + _REMAP_MAX_ROWS],
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )
            for r in range(0, len(map_x), _REMAP_MAX_ROWS)
        ]
    )


def _remap_linear(
    gray: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, lin: _Linearise, rows_per_quad: int
) -> np.ndarray:
    """Bilinear samples (R, C) float32 of 8-bit ``gray`` in linear light at the maps (R, C), each
    quad's ``rows_per_quad`` rows from the linearised pixels around its own samples.

    Pixels are linearised before they are interpolated: an edge between two pixel centres blends
    their light, not their codes. Interpolating the codes and then linearising puts the halfway
    level of a sharp ink edge a tenth of a pixel towards the bright side (measured on an ideal
    render: every corner 0.10 px outward at any size), the sticker seen larger. Only the box each
    quad's samples cover is linearised (a whole frame costs ~2 ms; a sticker's box ~0.05 ms)."""
    H, W = gray.shape[:2]
    out = np.empty(map_x.shape, np.float32)
    for r in range(0, len(map_x), rows_per_quad):
        mx, my = map_x[r : r + rows_per_quad], map_y[r : r + rows_per_quad]
        # Clipped to the image, the box keeps remap's replicated border where the samples leave it.
        x0 = min(max(int(np.floor(mx.min())), 0), W - 1)
        x1 = min(max(int(np.floor(mx.max())) + 2, x0 + 1), W)
        y0 = min(max(int(np.floor(my.min())), 0), H - 1)
        y1 = min(max(int(np.floor(my.max())) + 2, y0 + 1), H)
        box = cv2.LUT(gray[y0:y1, x0:x1], lin.lut)
        out[r : r + rows_per_quad] = _remap_rows(box, mx - np.float32(x0), my - np.float32(y0))
    return out


def _sample_profiles(
    gray: np.ndarray, quads: np.ndarray, cfg: DetectConfig, search_px: float, lin: _Linearise | None
) -> tuple[_Profiles | None, np.ndarray]:
    """Sample every profile of the four sides of each quad (K, 4, 2) with one cv2.remap: the
    profiles of the quads that are not degenerate (None if none is), and their indices into ``quads``."""
    n = cfg.profiles_per_side
    side_vec = quads[:, _NEXT] - quads  # (K, 4, 2)
    side_len = np.sqrt(np.einsum("kij,kij->ki", side_vec, side_vec))
    idx = np.arange(len(quads))
    # A quad with a corner far outside the image is no sticker in view: lines that meet at a
    # grazing angle put corners millions of pixels away, and its profiles would be as long.
    H, W = gray.shape[:2]
    reach = max(H, W)
    inside = np.isfinite(quads).all(axis=(1, 2)) & (quads >= -reach).all(axis=(1, 2))
    inside &= (quads[..., 0] <= W + reach).all(axis=1) & (quads[..., 1] <= H + reach).all(axis=1)
    short = ~inside | (side_len.min(axis=1) < 4)
    if short.any():
        idx, side_vec, side_len, quads = idx[~short], side_vec[~short], side_len[~short], quads[~short]
    along = side_vec / side_len[..., None]
    inward = np.stack([-along[..., 1], along[..., 0]], axis=-1)  # clockwise on screen, y down: left of travel is in
    margin = (1.0 - cfg.profile_span) / 2
    t = _linspace(margin, 1.0 - margin, n)
    base = quads[:, :, None, :] + t[None, None, :, None] * side_vec[:, :, None, :]  # (K, 4, n, 2)
    # Frame width along each profile, from the geometry implied by the current quad.
    a = np.array([_implied_inner(q) for q in quads]).reshape(-1, 4, 2)
    b = a[:, _NEXT]
    # The inner side through a and b: (a, 1) x (b, 1) = normal (ay - by, bx - ax), offset ax by - ay bx.
    normal = np.stack([a[..., 1] - b[..., 1], b[..., 0] - a[..., 0]], axis=-1)
    num = -(np.einsum("kinj,kij->kin", base, normal) + (a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0])[..., None])
    den = np.einsum("kij,kij->ki", inward, normal)[..., None]
    frame_w = np.maximum(num / den, 1.0)  # (K, 4, n) distance to the inner edge along ``inward``
    w_max = frame_w.max(axis=(1, 2))
    wide = w_max > cfg.max_frame_fraction * side_len.max(axis=1)  # a degenerate quad
    if wide.any():
        ok = ~wide
        idx, along, inward, base, frame_w, w_max = idx[ok], along[ok], inward[ok], base[ok], frame_w[ok], w_max[ok]
    if len(idx) == 0:
        return None, idx
    quiet = w_max * _QUIET_RATIO / _FRAME_RATIO
    step = cfg.sample_step_px
    start = -(search_px + cfg.blur_allow_px / 2 + 2)
    stops = [float(w) + float(q) + search_px + step for w, q in zip(w_max, quiet)]
    s = np.arange(start, max(stops), step)
    # Each quad's own samples are the first of the shared ones (np.arange's values are start + i step).
    length = [len(s) if stop == max(stops) else len(np.arange(start, stop, step)) for stop in stops]
    strip = _linspace(-cfg.strip_half_px, cfg.strip_half_px, 3)
    # Sample points base + strip * along + s * inward, (K, 4, n, 3, S) per coordinate, summed in
    # float32 (remap's own sub-pixel resolution is 1/32 px) from the small per-side offset grid
    # (K, 4, 3, S). x and y apart: numpy broadcasts over a trailing axis of 2 an order of magnitude slower.
    k = len(idx)
    base32 = base.astype(np.float32)
    maps = []
    for c in (0, 1):
        offs = (
            strip[None, None, :, None] * along[:, :, None, None, c]
            + s[None, None, None, :] * inward[:, :, None, None, c]
        ).astype(np.float32)
        maps.append(np.add(base32[:, :, :, None, None, c], offs[:, :, None]).reshape(k * 4 * n * 3, len(s)))
    if lin is not None and gray.dtype == np.uint8:
        vals = _remap_linear(gray, maps[0], maps[1], lin, 4 * n * 3)
    else:
        vals = _remap_rows(gray, maps[0], maps[1])
        vals = vals.astype(np.float32) if lin is None else lin(vals.astype(np.float32))
    strips = vals.reshape(k, 4, n, 3, len(s))
    prof = (strips[:, :, :, 0] + strips[:, :, :, 1] + strips[:, :, :, 2]) / np.float32(3.0)  # the strips' mean
    for j, end in enumerate(length):
        if end < len(s):
            prof[j, :, :, end:] = np.nan  # beyond the quad's own samples
    fw = median_last(frame_w.reshape(k, -1))
    return _Profiles(base, inward, s, np.array(length), prof, frame_w, fw, quiet), idx


def _outer_offsets(
    p: _Profiles, cfg: DetectConfig, search_px: float, ink_rounds: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Outer edge offsets (K, 4, n) along ``inward`` (NaN where not found), with the ink level
    (corrected for blur over ``ink_rounds``, see ``DetectConfig.ink_rounds``), the darkest level,
    the paper and median floor levels (K,) (float32), and which quads (K,) the contrast says are
    stickers."""
    s, prof, n = p.s, p.prof, cfg.profiles_per_side
    k = len(prof)
    med = median_last(prof.transpose(0, 1, 3, 2))  # (K, 4, S): each side's typical profile
    fw = p.fw[:, None]
    in_frame = (s >= 0) & (s <= fw)  # (K, S)
    ok = in_frame.any(axis=1)
    ink = np.where(in_frame[:, None], med, np.inf).min(axis=(1, 2))
    floor = median_last(prof[..., s < -(search_px + 0.5)])  # (K, 4, n)
    floor_med = median_last(floor.reshape(k, -1))
    inside = (s > fw) & (s <= fw + p.quiet[:, None] + 1.0) & (np.arange(len(s)) < p.length[:, None])
    paper = np.where(inside.any(axis=1), np.where(inside[:, None], med, -np.inf).max(axis=(1, 2)), ink)
    # (As float64, the contrast tests' arithmetic on single values.)
    ink64, paper64, floor64 = ink.astype(float), paper.astype(float), floor_med.astype(float)
    ok &= ~(floor64 - ink64 < cfg.min_contrast)
    # Inside the frame there must be paper, far brighter than ink: a plain dark square has none
    # (adaptive thresholding marks only its rim, which otherwise looks like a frame).
    ok &= ~(paper64 - ink64 < np.maximum(cfg.min_contrast, cfg.min_paper_ratio * (floor64 - ink64)))
    # Halfway between floor and ink is the true edge under any symmetric blur shorter than twice the
    # frame width w. Longer blur L across a side keeps that side's dip above halfway (a bar under a
    # box blur darkens to r = w / L of its full depth) and too shallow to locate in noise. Such a
    # side is located on the steep rise from the dip to the paper instead: for a floor | ink (w) |
    # paper step under a box blur longer than w, that rise is a straight ramp whose middle,
    # ((F + P)(1 - r) + 2 I r) / 2, lies over the frame's centre line, whatever L is.
    near = (s >= -cfg.blur_allow_px / 2) & (s <= fw)  # (K, S)
    floor_side = median_last(floor)  # (K, 4)
    ink_col = ink[:, None]
    dip = np.where(near[:, None], med, np.inf).min(axis=2)
    # (np.clip's wrapper costs more than the arithmetic on these few values.)
    ratio = np.minimum(np.maximum((floor_side - dip) / np.maximum(floor_side - ink_col, 1e-6), 0.0), 1.0)
    flat = prof.reshape(k * 4 * n, len(s))
    level = ((floor + ink[:, None, None]) / 2).ravel()
    outer_s = _crossings(flat, level, s, np.zeros(k * 4 * n), rising=False).reshape(k, 4, n)
    outer_s[(floor - ink[:, None, None]) < cfg.min_contrast / 2] = np.nan
    # The darkest point of a blurred frame is not the ink's level (see _unblurred_ink): the edges
    # are located again, halfway to the ink's level as it is without the blur.
    dark = ink
    for _ in range(ink_rounds):
        ink = _unblurred_ink(med, s, outer_s, p.frame_w, floor_side, paper, ink)
        level = ((floor + ink[:, None, None]) / 2).ravel()
        again = _crossings(flat, level, s, _nan_to(outer_s, 0.0).ravel(), rising=False).reshape(k, 4, n)
        outer_s = np.where(np.isfinite(outer_s), again, np.nan)
    # Only sides that the halfway level fails on (too few crossings) take the ramp.
    min_points = _min_points(cfg)
    sparse = np.isfinite(outer_s).sum(axis=2) < min_points
    shallow = ((ratio < cfg.shallow_ratio) | (sparse & (ratio < cfg.shallow_ratio_sparse))) & ok[:, None]
    if shallow.any():
        r = ratio[shallow, None]
        paper_side = np.broadcast_to(paper[:, None], shallow.shape)[shallow, None]
        ink_side = np.broadcast_to(ink_col, shallow.shape)[shallow, None]
        rise = 0.5 * ((floor[shallow] + paper_side) * (1.0 - r) + (2.0 * ink_side) * r)
        half_w = 0.5 * p.frame_w[shallow]
        mid = _crossings(prof[shallow].reshape(-1, len(s)), rise.ravel(), s, half_w.ravel(), rising=True)
        outer_s[shallow] = mid.reshape(half_w.shape) - half_w
    ok &= np.isfinite(outer_s).sum(axis=2).min(axis=1) >= min_points
    return outer_s, ink, dark, paper, floor_med, ok


def _unblurred_ink(
    med: np.ndarray,
    s: np.ndarray,
    outer_s: np.ndarray,
    frame_w: np.ndarray,
    floor: np.ndarray,
    paper: np.ndarray,
    ink: np.ndarray,
) -> np.ndarray:
    """The quads' ink level (K,) as it would be without blur, from each side's typical profile
    ``med`` (K, 4, S) at positions ``s`` (S,), the outer edge offsets ``outer_s`` (K, 4, n), the
    frame widths ``frame_w`` (K, 4, n), the sides' floor levels ``floor`` (K, 4), and the quads'
    paper levels and current ink levels ``paper``, ``ink`` (K,) (kept where no side gives one).

    Blur lifts the middle of the narrow frame above the ink's level with light from the floor on
    one side and the paper on the other, so the halfway level from the frame's darkest point sits
    too high and the outer edge is found too far out: the sticker is seen larger, hence nearer (on
    ideal renders under a 1 px Gaussian blur, every corner 0.19 px outward on a 50 px sticker and
    0.41 px at 40 px, where the frame is 3.2 px wide). For any symmetric blur, the light the outer
    edge carries from the floor into the frame's middle, w/2 inside it, is the light it takes from
    the floor w/2 outside it, ``(F - I) b``; the inner edge blurs alike, so it carries
    ``(P - I) b`` from the paper. The middle reads ``I + (F + P - 2 I) b`` and the floor w/2 out
    ``F - (F - I) b``, which give ``I`` (a few fixed-point steps: ``b`` is small). Each side gives
    one estimate (motion blur differs between sides); their median is the quad's. The paper level
    is read in a quiet zone only 0.44 frame widths wide, which blur darkens too, so the correction
    falls somewhat short on the smallest stickers (see ``DetectConfig.ink_rounds``)."""
    edge, count = masked_median_last(outer_s, np.isfinite(outer_s))
    found = count > 0
    edge = np.where(found, edge, 0.0)  # (K, 4): each side's median outer offset
    half = 0.5 * median_last(frame_w)  # (K, 4)
    step, last = float(s[1] - s[0]), len(s) - 1
    # ``med`` interpolated w/2 inside and w/2 outside each side's edge, (K, 4, 2).
    x = np.clip((np.stack([edge + half, edge - half], axis=2) - s[0]) / step, 0.0, last - 1e-6)
    i = x.astype(np.int64)
    # Picked by index, a row per side (np.take_along_axis's set-up cost more than the reading).
    rows, cols = np.arange(i.shape[0] * 4)[:, None], i.reshape(-1, 2)
    by_side = med.reshape(-1, med.shape[-1])
    a = by_side[rows, cols].reshape(i.shape)
    read = a + (x - i) * (by_side[rows, cols + 1].reshape(i.shape) - a)
    middle = read[..., 0].astype(float)
    lost = np.maximum(floor - read[..., 1], 0.0)  # (F - I) b
    light = floor + paper[:, None]
    est = middle
    for _ in range(3):
        est = middle - lost * (light - 2.0 * est) / np.maximum(floor - est, 1e-6)
    good = found & np.isfinite(est) & (floor - middle > 0)
    est = np.where(good, np.clip(est, 0.0, middle), np.nan)
    quad, n_good = masked_median_last(est, good)  # the median of the sides that give one
    return np.where(n_good > 0, quad, ink).astype(np.float32)


def _min_points(cfg: DetectConfig) -> int:
    """Fewest edge points a side's line may rest on."""
    return max(4, int(cfg.min_points_fraction * cfg.profiles_per_side))


def _inner_offsets(p: _Profiles, outer_s: np.ndarray, ink: np.ndarray, paper: np.ndarray) -> np.ndarray:
    """Inner edge offsets (K, 4, n) along ``inward``: the rise from ink to paper, beyond the outer edge."""
    k, _, n = p.frame_w.shape
    outer0 = _nan_to(outer_s, 0.0)
    level = np.repeat((paper.astype(float) + ink.astype(float)) / 2, 4 * n)
    inner_s = _crossings(p.prof.reshape(k * 4 * n, len(p.s)), level, p.s, (p.frame_w + outer0).ravel(), True).reshape(
        k, 4, n
    )
    inner_s[~(inner_s > _nan_to(outer_s, -1e9) + 0.5)] = np.nan
    return inner_s


def _refine(
    gray: np.ndarray,
    camera: Camera,
    quads: list[np.ndarray],
    cfg: DetectConfig,
    lin: _Linearise | None,
    search_px: float,
    inner: bool = True,
) -> list[_Refined | None]:
    """One pass of edge-profile refinement around each distorted quad (4, 2), all quads at once
    (numpy's per-call overhead, not the arithmetic, is the cost: one call per step for all the
    stickers in view); None for a quad that does not refine. ``inner`` False skips the inner
    corners (the first pass only re-aims the second, which uses its outer square alone)."""
    out: list[_Refined | None] = [None] * len(quads)
    if not quads:
        return out
    p, idx = _sample_profiles(gray, np.stack(quads), cfg, search_px, lin)
    if p is None:
        return out
    outer_s, ink, dark, paper, floor_med, ok = _outer_offsets(p, cfg, search_px, cfg.ink_rounds if inner else 0)
    inner_s = _inner_offsets(p, outer_s, ink, paper) if inner else None
    n = cfg.profiles_per_side
    # Lines are straight only without distortion: undistort every edge point (one call), then fit.
    offsets = _nan_to(np.stack([outer_s] if inner_s is None else [outer_s, inner_s], axis=1), 0.0)  # (K, 1|2, 4, n)
    pts = p.base[:, None] + offsets[..., None] * p.inward[:, None, :, None, :]
    edge = camera.undistort_pixels(pts.reshape(-1, 2)).reshape(*offsets.shape, 2)
    min_points = _min_points(cfg)
    outer_mask = np.isfinite(outer_s) & ok[:, None, None]  # a refused quad's fit is not used
    lines, rms_sides, keep, fitted = _robust_lines(
        edge[:, 0].reshape(-1, n, 2),
        outer_mask.reshape(-1, n),
        min_points,
        cfg.outlier_sigmas,
        cfg.outlier_floor_px,
        group=4,
    )
    lines, rms_sides, keep = lines.reshape(-1, 4, 3), rms_sides.reshape(-1, 4), keep.reshape(-1, 4, n)
    outer_ideal = _intersect(lines)  # (K, 4, 2)
    rms = rms_sides.max(axis=1)
    ok &= fitted & ~(rms > cfg.max_rms_px) & np.isfinite(outer_ideal).all(axis=(1, 2))
    inner_ideal: dict[int, np.ndarray] = {}
    if inner_s is not None:
        has = ok & (np.isfinite(inner_s).sum(axis=2).min(axis=1) >= min_points)
        if has.any():
            fits = huber_lines(edge[has, 1].reshape(-1, n, 2), np.isfinite(inner_s[has]).reshape(-1, n), group=4)
            for j, corners in zip(np.flatnonzero(has), _intersect(fits.reshape(-1, 4, 3))):
                dev = np.linalg.norm(corners - _implied_inner(outer_ideal[j]), axis=1)
                if np.all(np.isfinite(dev)) and dev.max() <= cfg.inner_max_dev_px:
                    inner_ideal[j] = corners
    # One projection back to distorted pixels for every corner of every quad.
    kept = np.flatnonzero(ok)
    ideal = [np.r_[outer_ideal[j], inner_ideal[j]] if j in inner_ideal else outer_ideal[j] for j in kept]
    if not ideal:
        return out
    distorted = distort_ideal(camera, np.concatenate(ideal))
    at = 0
    for j, corners in zip(kept, ideal):
        both = distorted[at : at + len(corners)]
        at += len(corners)
        valid = float(keep[j].sum()) / (4.0 * n)
        score = (
            valid
            * min(1.0, (float(floor_med[j]) - float(dark[j])) / cfg.full_score_contrast)
            * math.exp(-float(rms[j]))
        )
        out[int(idx[j])] = _Refined(both[:4], both[4:] if len(corners) == 8 else None, outer_ideal[j], score)
    return out


def _inside(point: np.ndarray, quad: np.ndarray) -> bool:
    return (
        cv2.pointPolygonTest(quad.astype(np.float32).reshape(-1, 1, 2), (float(point[0]), float(point[1])), False) >= 0
    )


def detect_stickers(
    gray: np.ndarray,
    camera: Camera,
    config: DetectConfig | None = None,
    regions: list[tuple[int, int, int, int]] | None = None,
) -> list[Detection]:
    """Find stickers in one frame.

    Args:
        gray: (H, W) image matching ``camera``'s size; colour or non-uint8 input is converted
            (see :func:`as_gray`).
        camera: intrinsics of the frame, used to fit edges as straight lines in undistorted space.
        config: tuning; by default :meth:`DetectConfig.for_camera` (sizes scaled to the focal length;
            unchanged for 1296x972 frames with stickers 40-110 px wide).
        regions: None searches the whole image; else only boxes (x0, y0, x1, y1) of full-resolution
            pixels (end exclusive) are searched for candidates, each on a cut-out wide enough that a
            sticker inside the box is found exactly as in a whole-image search (a sticker reaching
            out of every box may be missed); [] finds nothing.

    Returns:
        One Detection per sticker, largest first: outer (4, 2) and inner (4, 2) or None, distorted
        pixels, clockwise on screen, inner[i] matching outer[i]; score 0-1.
    """
    cfg = config or DetectConfig.for_camera(camera)
    img = as_gray(gray)
    if img.shape != (camera.height, camera.width):
        raise InputError(
            f"image is {img.shape[1]}x{img.shape[0]} px but the camera calibration is {camera.width}x{camera.height}"
        )
    if min(img.shape) < cfg.min_side_px + 2 * cfg.border_px:
        return []
    lin = _lineariser(float(cfg.response_gamma))
    coarse_cfg = dataclasses.replace(cfg, profiles_per_side=cfg.coarse_profiles_per_side)
    h, w = img.shape
    out: list[Detection] = []
    quads = _candidates(img, cfg, regions)
    # Both refinement passes run on every candidate at once (see _refine); the candidates are then
    # taken in order, as each would be alone.
    firsts = _refine(
        img, camera, quads, coarse_cfg, lin, search_px=cfg.coarse_search_px * cfg.downscale + 1.0, inner=False
    )
    seconds = iter(_refine(img, camera, [f.outer for f in firsts if f is not None], cfg, lin, cfg.refine_search_px))
    for quad, first in zip(quads, firsts):
        ref = next(seconds) if first is not None else None
        area = _polygon_area(quad)
        if any(_inside(quad.mean(axis=0), d.outer) and area < 0.5 * _polygon_area(d.outer) for d in out):
            continue  # a symbol inside an accepted sticker
        if first is None or ref is None or np.max(np.abs(ref.outer - first.outer)) > cfg.max_refine_shift_px:
            continue
        o = ref.outer
        if (
            np.any(o < cfg.border_px)
            or np.any(o[:, 0] > w - 1 - cfg.border_px)
            or np.any(o[:, 1] > h - 1 - cfg.border_px)
        ):
            continue
        sides = _side_lengths(o)
        if sides.max() < cfg.min_side_px or sides.max() > cfg.max_side_px or sides.max() > cfg.max_aspect * sides.min():
            continue
        if not cv2.isContourConvex(o.astype(np.float32)):
            continue
        det = Detection(outer=o, inner=ref.inner, score=float(np.clip(ref.score, 0.0, 1.0)))
        # A candidate that covers only part of a blurred sticker can refine to a wrong quad over it;
        # of two overlapping detections the better scored one stays.
        rivals = [k for k, d in enumerate(out) if _inside(o.mean(axis=0), d.outer) or _inside(d.outer.mean(axis=0), o)]
        if any(out[k].score >= det.score for k in rivals):
            continue
        out = [d for k, d in enumerate(out) if k not in rivals] + [det]
    return sorted(out, key=lambda d: -_polygon_area(d.outer))


def detect(
    gray: np.ndarray,
    camera: Camera,
    method: str = "contour",
    config: object | None = None,
    regions: list[tuple[int, int, int, int]] | None = None,
) -> list[Detection]:
    """Detect stickers with the named method: "contour" (ours) or "paper" (ORB + k-means, for
    comparison). ``regions`` (contour only; the paper's detector searches the whole image): see
    :func:`detect_stickers`."""
    if method == "contour":
        return detect_stickers(gray, camera, config, regions)  # type: ignore[arg-type]
    if method == "paper":
        from tagloc.vision.paper_detector import detect_stickers_paper

        return detect_stickers_paper(gray, camera, config)  # type: ignore[arg-type]
    raise InputError(f"unknown detection method {method!r} (want 'contour' or 'paper')")
