"""Detection benchmark: detection rate, corner error and time per frame, per method and per group.

``tagloc bench`` feeds :func:`bench_detection` frames with known corners (from the simulator, or
the tests' synthetic frames) and prints or stores the returned plain dict.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from tagloc.core.camera import Camera
from tagloc.core.types import Detection
from tagloc.vision.detect import detect


@dataclass
class FrameTruth:
    """A frame and its true sticker corners.

    Attributes:
        image: (H, W) uint8 frame.
        camera: the frame's camera.
        outer: per sticker (4, 2) true outer corners, distorted pixels, clockwise on screen.
        inner: per sticker (4, 2) true inner corners (or None), same order.
        group: label results are aggregated by (e.g. "blur=4").
    """

    image: np.ndarray
    camera: Camera
    outer: Sequence[np.ndarray] = field(default_factory=list)
    inner: Sequence[np.ndarray | None] = field(default_factory=list)
    group: str = ""


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


def _stats(values: list[float], prefix: str) -> dict:
    if not values:
        return {f"{prefix}_median": None, f"{prefix}_p95": None}
    a = np.asarray(values, float)
    return {f"{prefix}_median": round(float(np.median(a)), 4), f"{prefix}_p95": round(float(np.percentile(a, 95)), 4)}


def bench_detection(
    frames_with_truth: Iterable[FrameTruth],
    methods: Sequence[str] = ("contour", "paper"),
    max_px: float = 8.0,
    repeats: int = 1,
) -> dict:
    """Run each detection method on every frame, single-threaded, and summarise per group.

    Returns ``{method: {group: {...}}}`` with: frames, stickers, detected, rate, false_positives,
    outer_err_px_median/p95 (per corner), inner_rate (matched detections with inner corners),
    inner_err_px_median/p95, time_ms_median/p95 (best of ``repeats`` per frame).
    """
    frames = list(frames_with_truth)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        result: dict = {}
        for method in methods:
            acc: dict[str, dict] = {}
            for f in frames:
                g = acc.setdefault(
                    f.group,
                    {
                        "frames": 0,
                        "stickers": 0,
                        "detected": 0,
                        "false_positives": 0,
                        "with_inner": 0,
                        "outer": [],
                        "inner": [],
                        "times": [],
                    },
                )
                best = np.inf
                for _ in range(max(1, repeats)):
                    t0 = time.perf_counter()
                    dets = detect(f.image, f.camera, method=method)
                    best = min(best, time.perf_counter() - t0)
                matches = match_detections(dets, f.outer, f.inner, max_px)
                g["frames"] += 1
                g["stickers"] += len(f.outer)
                g["detected"] += len(matches)
                g["false_positives"] += len(dets) - len(matches)
                g["times"].append(best * 1e3)
                for m in matches:
                    g["outer"].extend(m.outer_err.tolist())
                    if m.inner_err is not None:
                        g["with_inner"] += 1
                        g["inner"].extend(m.inner_err.tolist())
            summary = {}
            for name, g in acc.items():
                summary[name] = {
                    "frames": g["frames"],
                    "stickers": g["stickers"],
                    "detected": g["detected"],
                    "rate": round(g["detected"] / g["stickers"], 4) if g["stickers"] else None,
                    "false_positives": g["false_positives"],
                    **_stats(g["outer"], "outer_err_px"),
                    "inner_rate": round(g["with_inner"] / g["detected"], 4) if g["detected"] else None,
                    **_stats(g["inner"], "inner_err_px"),
                    **_stats(g["times"], "time_ms"),
                }
            result[method] = summary
        return result
    finally:
        cv2.setNumThreads(threads)
