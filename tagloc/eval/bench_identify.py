"""Measuring identification: synthetic blurred views, score distributions, rates vs blur.

:func:`synth_view` renders one sticker into a camera frame by ray-casting every (2x supersampled)
pixel of the region onto the floor plane through the real lens distortion, then applies linear
motion blur, photometric gain/offset, sensor noise and corner noise on the detection.
:func:`bench_identification` runs :func:`tagloc.vision.identify.identify` on many such views with K
candidates (the true one plus K-1 others, or K others when ``absent``) and reports rates.
:func:`score_samples` returns the raw (score, margin, correct) samples the thresholds of
:class:`tagloc.vision.identify.IdentifyConfig` were chosen from.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from tagloc.core.camera import Camera, default_camera
from tagloc.core.sticker import INNER_CORNERS, OUTER_CORNERS, render_sticker
from tagloc.core.types import Detection
from tagloc.vision.identify import IdentifyConfig, appearance_scores, identify, orb_scores
from tagloc.vision.psf import motion_kernel
from tagloc.vision.refs import ReferenceBank, build_refs


@dataclass
class View:
    """One synthetic view: the frame, the detection handed to identification, and the truth."""

    gray: np.ndarray
    detection: Detection
    sticker_id: int
    rotation: int
    size_px: float  # apparent sticker side in the image (px)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def synth_view(
    sticker_id: int,
    rng: np.random.Generator,
    camera: Camera | None = None,
    blur_px: float = 0.0,
    view_deg: float | None = None,
    rotation: int | None = None,
    size_px: float | None = None,
    corner_noise_px: float | None = None,
    noise: float = 3.0,
    with_inner: bool = True,
    jpeg: bool = True,
) -> View:
    """Render one sticker seen at ``view_deg`` from its normal, ~``size_px`` across, blurred.

    Args:
        sticker_id: sticker to show.
        rng: randomness (position in the image, in-plane yaw, blur direction, photometry, noise).
        camera: camera model (default :func:`tagloc.core.camera.default_camera`, distorted).
        blur_px: length of the linear motion blur in image px, random direction.
        view_deg: angle between the line of sight and the floor normal (default U(20, 70)).
        rotation: which detection corner is the canonical top-left (default random 0-3).
        size_px: apparent side (default U(60, 110)).
        corner_noise_px: std of the Gaussian noise on the detection corners (default
            0.5 + 0.1 * blur_px: blurred edges are located less well).
        noise: std of the sensor noise (grey levels).
        with_inner: give the inner corners in the detection too.
        jpeg: pass the region through JPEG at a random quality 70-95 (sessions store JPEG frames).

    The photometry varies too: ink and paper levels, floor level and texture, a brightness
    gradient of up to +-25 % across the region and a gamma of 0.8-1.25.
    """
    cam = camera or default_camera()
    view = np.radians(rng.uniform(20, 70) if view_deg is None else view_deg)
    r_true = int(rng.integers(4)) if rotation is None else int(rotation)
    side = rng.uniform(60, 110) if size_px is None else float(size_px)
    plane, outer, inner = _place_sticker(cam, rng, view, side)

    # Region to render: the sticker's box plus room for the blur and the floor around it.
    pad = int(blur_px) + 12
    x0, y0 = np.floor(outer.min(0)).astype(int) - pad
    x1, y1 = np.ceil(outer.max(0)).astype(int) + pad
    box = (max(x0, 0), max(y0, 0), min(x1, cam.width), min(y1, cam.height))
    img, floor_level = _render_region(cam, sticker_id, plane, box, rng)
    img = _sensor(img, blur_px, noise, jpeg, rng)
    x0, y0, x1, y1 = box
    gray = np.full((cam.height, cam.width), int(floor_level), np.uint8)
    gray[y0:y1, x0:x1] = img

    # Canonical corners project clockwise on screen; the detector may start at any of them.
    if corner_noise_px is None:
        corner_noise_px = 0.5 + 0.1 * blur_px
    outer_d = np.roll(outer, r_true, 0) + rng.normal(0, corner_noise_px, (4, 2))
    inner_d = np.roll(inner, r_true, 0) + rng.normal(0, corner_noise_px, (4, 2)) if with_inner else None
    return View(gray, Detection(outer_d, inner_d), int(sticker_id), r_true, side)


def _place_sticker(
    cam: Camera, rng: np.random.Generator, view: float, side: float
) -> tuple[tuple[np.ndarray, ...], np.ndarray, np.ndarray]:
    """A sticker plane seen at ``view`` rad from its normal, ~``side`` px across, somewhere in the
    middle of the image: ((centre, normal, ex, ey) in camera coordinates (m), outer (4, 2) and
    inner (4, 2) corners in distorted pixels)."""
    u = np.array([rng.uniform(0.2, 0.8) * cam.width, rng.uniform(0.2, 0.8) * cam.height])
    ray = cv2.undistortPoints(u.reshape(1, 1, 2), cam.K, cam.dist).reshape(2)
    v = _unit(np.array([ray[0], ray[1], 1.0]))
    dist = cam.fx * 0.1 / side * np.sqrt(np.cos(view))  # geometric mean of the two foreshortenings
    centre = dist * v
    axis = _unit(np.cross(v, rng.normal(size=3)))
    # Floor normal: the reversed line of sight turned by the viewing angle about ``axis``.
    n = -v * np.cos(view) + np.cross(axis, -v) * np.sin(view)
    ex = _unit(np.cross(n, rng.normal(size=3)))
    ey = np.cross(n, ex)
    corners3 = centre + OUTER_CORNERS[:, :1] * ex + OUTER_CORNERS[:, 1:2] * ey
    inner3 = centre + INNER_CORNERS[:, :1] * ex + INNER_CORNERS[:, 1:2] * ey
    return (centre, n, ex, ey), cam.project(corners3), cam.project(inner3)


def _render_region(
    cam: Camera, sticker_id: int, plane: tuple[np.ndarray, ...], box: tuple[int, int, int, int], rng
) -> tuple[np.ndarray, float]:
    """The image region ``box`` (x0, y0, x1, y1) px, float32: every pixel ray-cast (2x supersampled)
    onto the sticker plane through the lens distortion, sticker or textured floor, with random
    ink/paper/floor levels, a brightness gradient and a gamma; and the floor level."""
    centre, n, ex, ey = plane
    x0, y0, x1, y1 = box
    ss = 2
    xs = x0 - 0.5 + (np.arange((x1 - x0) * ss) + 0.5) / ss
    ys = y0 - 0.5 + (np.arange((y1 - y0) * ss) + 0.5) / ss
    grid = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 1, 2)
    rays = cv2.undistortPoints(grid, cam.K, cam.dist).reshape(-1, 2)
    rays3 = np.hstack([rays, np.ones((len(rays), 1))])
    s = (n @ centre) / (rays3 @ n)
    pts = rays3 * s[:, None] - centre
    px, py = pts @ ex, pts @ ey
    res = 200
    col = (px + 0.05) / 0.1 * res - 0.5
    row = (0.05 - py) / 0.1 * res - 0.5
    tex = render_sticker(sticker_id, res).astype(np.float32)
    shape = (len(ys), len(xs))
    floor_level = rng.uniform(90, 200)
    sampled = cv2.remap(
        tex,
        col.reshape(shape).astype(np.float32),
        row.reshape(shape).astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=-1.0,
    )
    floor = floor_level + cv2.GaussianBlur(rng.normal(0, 25, shape).astype(np.float32), (0, 0), 3)
    black, white = rng.uniform(15, 60), rng.uniform(150, 235)
    img = np.where(sampled < 0, floor, black + (white - black) * np.clip(sampled, 0, 255) / 255.0)
    ramp = np.linspace(-1, 1, shape[1])[None, :] * np.cos(g := rng.uniform(0, 2 * np.pi)) + np.linspace(
        -1, 1, shape[0]
    )[:, None] * np.sin(g)
    img = img * (1 + rng.uniform(-0.25, 0.25) * ramp)
    img = 255.0 * (np.clip(img, 0, 255) / 255.0) ** rng.uniform(0.8, 1.25)
    return cv2.resize(img.astype(np.float32), (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA), floor_level


def _sensor(img: np.ndarray, blur_px: float, noise: float, jpeg: bool, rng: np.random.Generator) -> np.ndarray:
    """Motion blur of ``blur_px`` in a random direction, sensor noise, 8 bits and optionally JPEG."""
    if blur_px > 0:
        a = rng.uniform(0, np.pi)
        img = cv2.filter2D(
            img, -1, motion_kernel(blur_px * np.array([np.cos(a), np.sin(a)])), borderType=cv2.BORDER_REPLICATE
        )
    img = np.clip(np.round(img + rng.normal(0, noise, img.shape)), 0, 255).astype(np.uint8)
    if jpeg:
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(70, 96))])
        img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return img


def candidate_ids(pool: np.ndarray, true_id: int, k: int, absent: bool, rng: np.random.Generator) -> list[int]:
    """``k`` candidate IDs from ``pool`` as the tracker would hand them over: the true ID at a random
    place among its nearest IDs, or (``absent``) only its neighbours."""
    # Maps number stickers consecutively and the tracker's candidates are neighbours, so the
    # others are drawn among the closest IDs: they share leading digits, hence Data Matrix
    # codewords, with the true one -- the hard case.
    near = pool[(pool != true_id) & (np.abs(pool - true_id) <= 2 * k)]
    others = rng.choice(near, size=k if absent else k - 1, replace=False)
    cands = [int(c) for c in others]
    if not absent:
        cands.insert(int(rng.integers(k)), true_id)
    return cands


def _bank(n_ids: int, seed: int) -> tuple[ReferenceBank, np.ndarray]:
    """A bank over ``n_ids`` consecutive IDs from a random start."""
    start = int(np.random.default_rng(seed).integers(0, 100000 - n_ids))
    ids = np.arange(start, start + n_ids)
    return build_refs(ids.tolist(), progress=False), ids


def score_samples(
    method: str,
    blur_px: float,
    trials: int = 100,
    k: int = 5,
    absent: bool = False,
    seed: int = 0,
    bank: ReferenceBank | None = None,
    pool: np.ndarray | None = None,
    config: IdentifyConfig | None = None,
) -> np.ndarray:
    """Raw decisions before thresholds: (trials, 4) rows (score, margin, id_right, rotation_right)."""
    cfg = config or IdentifyConfig()
    if bank is None:
        bank, pool = _bank(200, seed + 1000)
    rng = np.random.default_rng(seed)
    cam = default_camera()
    out = np.zeros((trials, 4))
    for i in range(trials):
        true_id = int(rng.choice(pool))
        v = synth_view(true_id, rng, cam, blur_px=blur_px)
        cands = candidate_ids(pool, true_id, k, absent, rng)
        score_fn = orb_scores if method == "orb" else appearance_scores
        s = score_fn(v.gray, v.detection, cam, cands, bank, cfg)
        c, r = s.best
        out[i] = (s.score, s.margin, cands[c] == true_id, cands[c] == true_id and r == v.rotation)
    return out


def bench_identification(
    methods: tuple[str, ...] = ("appearance", "orb"),
    blurs_px: tuple[float, ...] = (0, 1, 2, 4, 6, 8),
    trials: int = 100,
    k: int = 5,
    seed: int = 0,
    config: IdentifyConfig | None = None,
    bank_size: int = 200,
) -> dict:
    """Identification rate, wrong-ID count and time per call vs blur, true sticker present or absent.

    Returns ``{"rows": [{method, blur_px, case ("present"/"absent"), trials, right, wrong,
    refused, rate, wrong_rate, ms_median, ms_p95}], "config": {...}}``. "wrong" counts any accepted
    answer that is not the true (ID, rotation); in the "absent" case every answer is wrong.
    """
    cfg = config or IdentifyConfig()
    bank, pool = _bank(bank_size, seed + 1000)
    cam = default_camera()
    rows = []
    for method in methods:
        for blur in blurs_px:
            for absent in (False, True):
                rng = np.random.default_rng([seed, int(blur * 10), int(absent)])
                right = wrong = 0
                times = []
                for _ in range(trials):
                    true_id = int(rng.choice(pool))
                    v = synth_view(true_id, rng, cam, blur_px=blur)
                    cands = candidate_ids(pool, true_id, k, absent, rng)
                    t0 = time.perf_counter()
                    res = identify(v.gray, v.detection, cam, cands, bank, method=method, config=cfg)
                    times.append((time.perf_counter() - t0) * 1e3)
                    if res.sticker_id is None:
                        continue
                    if res.sticker_id == true_id and res.rotation == v.rotation:
                        right += 1
                    else:
                        wrong += 1
                rows.append(
                    {
                        "method": method,
                        "blur_px": blur,
                        "case": "absent" if absent else "present",
                        "trials": trials,
                        "right": right,
                        "wrong": wrong,
                        "refused": trials - right - wrong,
                        "rate": right / trials,
                        "wrong_rate": wrong / trials,
                        "ms_median": float(np.median(times)),
                        "ms_p95": float(np.percentile(times, 95)),
                    }
                )
    return {
        "rows": rows,
        "config": {
            "k": k,
            "trials": trials,
            "seed": seed,
            "bank_size": bank_size,
            "min_ncc": cfg.min_ncc,
            "min_ncc_margin": cfg.min_ncc_margin,
            "min_inliers": cfg.min_inliers,
            "min_inlier_margin": cfg.min_inlier_margin,
        },
    }


def format_rows(rows: list[dict]) -> str:
    """Markdown table of :func:`bench_identification` rows."""
    lines = [
        "| method | blur px | case | right | wrong | refused | ms median | ms p95 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['method']} | {r['blur_px']:g} | {r['case']} | {r['right']}/{r['trials']} | {r['wrong']} | "
            f"{r['refused']} | {r['ms_median']:.2f} | {r['ms_p95']:.2f} |"
        )
    return "\n".join(lines)


def format_thresholds(samples: dict[tuple[str, float], tuple[np.ndarray, np.ndarray]], cfg: IdentifyConfig) -> str:
    """Markdown table of where :class:`IdentifyConfig`'s thresholds sit in the score distributions.

    ``samples`` maps (method, blur px) to :func:`score_samples` of the true sticker present and
    absent. Right answers (ID and rotation) should clear both thresholds; wrong ones (any answer
    with the true sticker absent, or a wrong ID or rotation) should fail at least one.
    """
    lines = [
        "| method | blur px | right: score p5 / margin p5 | wrong: score p95 / margin p95 | thresholds "
        "| right passing | wrong passing |",
        "|---|---|---|---|---|---|---|",
    ]
    for (method, blur), (present, absent) in samples.items():
        lo = (cfg.min_inliers, cfg.min_inlier_margin) if method == "orb" else (cfg.min_ncc, cfg.min_ncc_margin)
        right = present[present[:, 3] == 1]
        wrong = np.vstack([present[present[:, 3] == 0], absent])

        def passing(rows: np.ndarray, lo=lo) -> str:
            return f"{int(np.sum((rows[:, 0] >= lo[0]) & (rows[:, 1] >= lo[1])))}/{len(rows)}"

        def pct(rows: np.ndarray, q: float) -> str:
            return " / ".join(f"{np.percentile(rows[:, j], q):.2f}" for j in (0, 1)) if len(rows) else "-"

        lines.append(
            f"| {method} | {blur:g} | {pct(right, 5)} | {pct(wrong, 95)} | {lo[0]:g} / {lo[1]:g} "
            f"| {passing(right)} | {passing(wrong)} |"
        )
    return "\n".join(lines)


def identify_bench_command(
    methods: tuple[str, ...] = ("appearance", "orb"),
    blurs_px: tuple[float, ...] = (0, 2, 4, 8),
    trials: int = 100,
    k: int = 5,
    seed: int = 0,
    progress: bool = True,
) -> str:
    """The identification bench as ``tagloc bench-identify`` prints it: rates and wrong IDs vs blur
    (:func:`bench_identification`), and where the thresholds of :class:`IdentifyConfig` sit in the
    raw score distributions they were chosen from (:func:`format_thresholds`)."""
    from tqdm import tqdm

    cfg = IdentifyConfig()
    bank, pool = _bank(200, seed + 1000)
    samples = {}
    cells = [(m, b) for m in methods for b in blurs_px]
    for method, blur in tqdm(cells, desc="score samples", unit="cell", disable=not progress, leave=False):
        present, absent = (
            score_samples(method, blur, trials, k, absent, seed, bank, pool, cfg) for absent in (False, True)
        )
        samples[(method, blur)] = (present, absent)
    rates = bench_identification(methods, blurs_px, trials, k, seed, cfg)
    return (
        f"Identification, {trials} views per cell, {k} candidates (seed {seed})\n\n"
        + format_rows(rates["rows"])
        + "\n\nThresholds against the raw scores (before thresholds)\n\n"
        + format_thresholds(samples, cfg)
    )
