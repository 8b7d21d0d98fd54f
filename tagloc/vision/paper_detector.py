"""The paper's sticker detector, reproduced for comparison (select it with ``detect(..., method="paper")``).

As described in the paper (Sec. "Pattern Recognition" to "Position Computation"):

1. ORB features of a reference picture (a sticker with random 10x10 codes, rendered at the size
   stickers are expected to appear) are matched to ORB features of the frame by nearest-neighbour
   search; more than 50 matches means a sticker is present.
2. The matched frame keypoints are clustered with k-means starting at 4 clusters; clusters whose
   means are too close are merged (one cluster per sticker). Only the cluster with the most points
   is kept, and an ROI is cut around it.
3. In the ROI (thresholded halfway between ink and floor) the sticker's contour is found and its corners are the contour's extreme points
   (leftmost, topmost, rightmost, bottommost).

It returns at most one detection, with no inner corners. The paper leaves the matching filter
unspecified (a bare nearest neighbour always "matches"); a Hamming distance cap stands in for it,
set so that frames without stickers give about as few matches as the paper reports (< 15).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from tagloc.core.camera import Camera
from tagloc.core.errors import InputError
from tagloc.core.sticker import MAX_ID, render_sticker
from tagloc.core.types import Detection
from tagloc.vision.image import as_gray, clockwise


@dataclass
class PaperDetectConfig:
    """Tuning of :func:`detect_stickers_paper` (pixels at full resolution).

    Attributes:
        n_features: ORB features per frame.
        reference_px: side of the rendered reference sticker (the expected on-screen size).
        reference_seed: picks the reference's random codes.
        min_matches: a sticker is present with more matches than this (the paper's 50).
        max_distance: largest Hamming distance (of 256 bits) of a nearest neighbour counted as a match.
        clusters: initial k-means clusters (the paper's 4).
        merge_px: clusters whose means are closer than this are merged.
        roi_margin: ROI grows by this fraction of the cluster's extent on each side.
        corner_sigma_px: corner noise stated with each detection for the pose covariance. The
            extreme points of a thresholded contour are off by 1.8-2.5 px (median, ``tagloc
            bench``), and the same way in every frame of a sticker's pass (the blur and the view
            change slowly), so the tracker's fusing of 20-40 such fixes must not shrink the error
            as if they were independent. 8 px is where a replay of ``logs/walk2s`` with this
            detector is about consistent (position NEES 4.9 at 2 px, 3.5 at 4 px, 2.4 at 8 px with the
            tracker of the time; 2.5 at 8 px since the vest floor follows the walk).
    """

    n_features: int = 1500
    reference_px: int = 80
    reference_seed: int = 2019
    min_matches: int = 50
    max_distance: int = 64
    clusters: int = 4
    merge_px: float = 90.0
    roi_margin: float = 0.5
    corner_sigma_px: float = 8.0


@lru_cache(maxsize=8)
def _reference(size_px: int, seed: int, n_features: int) -> tuple[tuple, np.ndarray]:
    """ORB keypoints and descriptors of the generic reference sticker on a grey margin."""
    sticker_id = int(np.random.default_rng(seed).integers(0, MAX_ID + 1))
    img = render_sticker(sticker_id, size_px)
    margin = 40  # ORB ignores a border of about its patch size
    img = cv2.copyMakeBorder(img, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=110)
    orb = cv2.ORB_create(nfeatures=n_features)
    kp, des = orb.detectAndCompute(img, None)
    return tuple(kp), des


def _merge_clusters(points: np.ndarray, labels: np.ndarray, merge_px: float) -> np.ndarray:
    """Merge clusters whose means are closer than ``merge_px`` until none are; returns new labels."""
    labels = labels.copy()
    while True:
        ids = np.unique(labels)
        means = np.array([points[labels == i].mean(axis=0) for i in ids])
        d = np.linalg.norm(means[:, None] - means[None], axis=2) + np.eye(len(ids)) * 1e9
        a, b = np.unravel_index(np.argmin(d), d.shape)
        if len(ids) < 2 or d[a, b] >= merge_px:
            return labels
        labels[labels == ids[b]] = ids[a]


def detect_stickers_paper(gray: np.ndarray, camera: Camera, config: PaperDetectConfig | None = None) -> list[Detection]:
    """The paper's detector: ORB matches -> k-means ROI -> contour extreme points (at most one sticker).

    Args:
        gray: (H, W) frame of ``camera``'s size (colour or non-uint8 input is converted).
        camera: only its image size is used; the paper's corners are raw contour pixels.
        config: tuning.

    Returns:
        Zero or one Detection (outer corners clockwise on screen, inner None, score from match count).
    """
    cfg = config or PaperDetectConfig()
    img = as_gray(gray)
    if img.shape != (camera.height, camera.width):
        raise InputError(
            f"image is {img.shape[1]}x{img.shape[0]} px but the camera calibration is {camera.width}x{camera.height}"
        )
    if min(img.shape) < 64:
        return []
    ref_kp, ref_des = _reference(cfg.reference_px, cfg.reference_seed, cfg.n_features)
    if ref_des is None:
        return []
    orb = cv2.ORB_create(nfeatures=cfg.n_features)
    kp, des = orb.detectAndCompute(img, None)
    if des is None or len(kp) < 2:
        return []
    good = [m for m in cv2.BFMatcher(cv2.NORM_HAMMING).match(des, ref_des) if m.distance <= cfg.max_distance]
    if len(good) <= cfg.min_matches:
        return []
    pts = np.array([kp[m.queryIdx].pt for m in good], np.float32)
    k = min(cfg.clusters, len(pts))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.5)
    cv2.setRNGSeed(0)  # k-means++ seeding is random; keep runs repeatable
    _, labels, _ = cv2.kmeans(pts, k, None, criteria, 3, cv2.KMEANS_PP_CENTERS)
    labels = _merge_clusters(pts, labels.ravel(), cfg.merge_px)
    ids, counts = np.unique(labels, return_counts=True)
    best = pts[labels == ids[np.argmax(counts)]]
    # Stray matches on the floor join the cluster; its central 90 % marks the sticker.
    lo, hi = np.percentile(best, 5, axis=0), np.percentile(best, 95, axis=0)
    pad = cfg.roi_margin * (hi - lo) + 5
    h, w = img.shape
    x0, y0 = np.maximum(np.floor(lo - pad).astype(int), 0)
    x1, y1 = np.minimum(np.ceil(hi + pad).astype(int), [w, h])
    roi = img[y0:y1, x0:x1]
    if roi.shape[0] < 8 or roi.shape[1] < 8:
        return []
    # The paper does not say how the contour is found. Otsu lumps grey concrete with the black ink
    # (the frame then merges into the floor), so split halfway between ink and the ROI's median.
    ink, floor = np.percentile(roi, [1, 50])
    _, dark = cv2.threshold(roi, float(ink + floor) / 2, 255, cv2.THRESH_BINARY_INV)
    contours, _ = cv2.findContours(dark, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return []
    # The floor's dark share touches the ROI's edge; the sticker's contour lies inside it.
    rh, rw = dark.shape
    inner = [
        c
        for c in contours
        if (lambda x, y, cw, ch: x > 0 and y > 0 and x + cw < rw and y + ch < rh)(*cv2.boundingRect(c))
    ]
    if not inner:
        return []
    c = max(inner, key=cv2.contourArea).reshape(-1, 2)
    extreme = np.array([c[c[:, 0].argmin()], c[c[:, 1].argmin()], c[c[:, 0].argmax()], c[c[:, 1].argmax()]], float)
    if len({tuple(p) for p in extreme}) < 4:
        return []
    quad = clockwise(extreme + [x0, y0])
    return [
        Detection(
            outer=quad,
            inner=None,
            score=float(min(1.0, len(good) / (4.0 * cfg.min_matches))),
            corner_sigma_px=cfg.corner_sigma_px,
        )
    ]
