"""Which of a few candidate stickers is this undecodable detection? Or none of them.

Used when motion blur stops Data Matrix decoding: the tracker proposes candidate IDs and this
module says which one is seen, with its in-plane rotation, or refuses. Accepting a wrong ID is the
worst failure of the system, so both tests refuse unless the best (candidate, rotation) pair beats
an absolute score *and* every other pair (other candidates and the same candidate's other
rotations, since a wrong rotation is as harmful as a wrong ID) by a margin.

Both tests work on the rectified sticker (:func:`tagloc.vision.rectify.rectify`), whose top-left is
``detection.outer[0]``; a sticker seen with rotation r appears as the canonical raster rotated
clockwise by r quarter turns, so geometry is known and no RANSAC is needed.

- Appearance: the motion-blur kernel is fitted once on the structure every sticker shares (mean
  sticker, four-fold symmetrised). Each candidate's rendered template is rotated, blurred with that
  kernel (and its mirror image, which the symmetric fit cannot tell apart) and correlated with the
  observed inner code area, after taking out of both what every sticker shares (frame, finder
  patterns) and, per candidate, what it shares with the other IDs of its decade (the same first
  two of its three data codewords): a missing neighbour sticker matches those parts as well as
  the candidate does. Score = that (partial) NCC.
- ORB: features of the rectified sticker are matched to each candidate's reference features
  (Hamming, ratio test); a match counts only if it lands where the square's known geometry puts it
  for that rotation. Score = number of such matches.

Thresholds come from :mod:`tagloc.eval.bench_identify` (see ``IdentifyConfig``); ``tagloc
bench-identify`` re-measures the rates and shows where the thresholds sit in the score distributions.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from tagloc.core.camera import Camera
from tagloc.core.errors import InputError
from tagloc.core.types import Detection, IdSource
from tagloc.vision.image import require_gray
from tagloc.vision.psf import motion_kernel
from tagloc.vision.rectify import rectify
from tagloc.vision.refs import ReferenceBank, inner_box, make_orb, orb_features

METHODS = ("auto", "orb", "appearance")


@dataclass
class IdentifyConfig:
    """Thresholds and options of :func:`identify` (values measured by :mod:`tagloc.eval.bench_identify`).

    Attributes:
        min_ncc, min_ncc_margin: appearance acceptance: best NCC and its lead over every other
            (candidate, rotation) pair.
        min_inliers, min_inlier_margin: ORB acceptance: geometric inliers and their lead.
        ratio: Lowe ratio test for ORB matches.
        inlier_px: largest distance (ORB raster px) between a match and where the square's
            geometry puts it.
        orb_global_above: with more candidates than this, ORB matches once against all their
            references (ratio test across stickers) instead of once per candidate.
        blur_lengths_px, blur_angles_deg: the linear motion-blur kernels tried when estimating
            the blur (appearance raster px; angle of the blur direction from raster +x).
        contrast: what is correlated: "none" (plain NCC of the templates), "generic" (the
            structure all stickers share is regressed out of the view and subtracted from the
            templates), "decade" (generic, and per candidate also what it shares with the other
            IDs of its decade -- same first four digits, hence the same first two of its three
            data codewords -- taken out by partial correlation).
    """

    min_ncc: float = 0.55
    min_ncc_margin: float = 0.20
    min_inliers: int = 20
    min_inlier_margin: int = 12
    ratio: float = 0.8
    inlier_px: float = 4.0
    orb_global_above: int = 16
    blur_lengths_px: tuple[float, ...] = (0.0, 1.5, 3.0, 4.5, 6.0, 8.0, 10.0, 13.0)
    blur_angles_deg: tuple[float, ...] = tuple(range(0, 180, 15))
    contrast: str = "decade"


@dataclass
class IdResult:
    """Outcome of :func:`identify`.

    Attributes:
        sticker_id: the identified candidate, or None (refused).
        rotation: 0-3, canonical top-left is ``detection.outer[rotation]``; None if refused.
        score: best pair's score (NCC for appearance, inlier count for ORB), even when refused.
        margin: best score minus the best other (candidate, rotation) pair's score.
        source: ``IdSource.APPEARANCE`` / ``IdSource.ORB``; ``IdSource.NONE`` if refused.
        runner_up: best other candidate's ID (None with a single candidate).
        blur_px: (2,) blur vector estimated in the appearance raster (px), or None.
    """

    sticker_id: int | None
    rotation: int | None
    score: float
    margin: float
    source: IdSource
    runner_up: int | None = None
    blur_px: np.ndarray | None = None


@dataclass
class _Scores:
    """Score of every (candidate, rotation) pair: (C, 4)."""

    table: np.ndarray
    blur: np.ndarray | None = None
    best: tuple[int, int] = field(init=False)
    score: float = field(init=False)
    margin: float = field(init=False)
    runner_up: int | None = field(init=False)

    def __post_init__(self) -> None:
        t = self.table
        c, r = np.unravel_index(int(np.argmax(t)), t.shape)
        self.best = (int(c), int(r))
        self.score = float(t[c, r])
        others = t.copy()
        others[c, r] = -np.inf
        second = float(others.max()) if others.size > 1 else -np.inf
        self.margin = self.score - second if np.isfinite(second) else self.score
        per_cand = t.max(axis=1)
        per_cand[c] = -np.inf
        self.runner_up = int(np.argmax(per_cand)) if len(per_cand) > 1 else None


# ---------------------------------------------------------------- appearance


def _blur(img: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    if kernel.size == 1:
        return img
    return cv2.filter2D(img, cv2.CV_32F, kernel, borderType=cv2.BORDER_REPLICATE)


def _rot(img: np.ndarray, r: int) -> np.ndarray:
    """Canonical raster as seen with rotation r: turned clockwise by r quarter turns."""
    return np.ascontiguousarray(np.rot90(img, -r))


def _unrotate_vector(v: np.ndarray, r: int) -> np.ndarray:
    """A raster vector (x right, y down) expressed in the canonical frame of a rotation-r view.

    Blurring the turned template with kernel ``v`` equals turning the template blurred with this
    vector, so candidates are filtered once, in canonical orientation, per rotation.
    """
    x, y = float(v[0]), float(v[1])
    for _ in range(r % 4):
        x, y = y, -x  # one counter-clockwise quarter turn (image axes, row down)
    return np.array([x, y])


def _ambiguous_blurs(blur: np.ndarray) -> list[np.ndarray]:
    """``blur`` and its mirror about the raster axes, which a fit on the square frame cannot tell apart.

    (Sign never matters: the kernel is centred. The diagonal mirrors are symmetries of the frame
    too, but trying them as well changed no decision in 900 measured views, so they are left out.)
    """
    v, m = np.asarray(blur, float), np.array([blur[0], -blur[1]], float)
    return [v] if np.allclose(v, m, atol=0.25) or np.allclose(v, -m, atol=0.25) else [v, m]


def _centred_unit(rows: np.ndarray) -> np.ndarray:
    """Rows made zero-mean and unit-norm (all-constant rows stay zero)."""
    rows = rows - rows.mean(axis=-1, keepdims=True)
    n = np.linalg.norm(rows, axis=-1, keepdims=True)
    return np.divide(rows, n, out=np.zeros_like(rows), where=n > 1e-6)


class _Appearance:
    """Per-bank precomputation of the appearance test (mean sticker, blur basis)."""

    def __init__(self, bank: ReferenceBank, cfg: IdentifyConfig):
        s = bank.params.template_size_px
        self.size = s
        self.mean = bank.mean_template
        mean_sym = sum(_rot(self.mean, r) for r in range(4)) / 4.0
        lo, hi = inner_box(s, margin_px=0.5)
        a, b = int(np.ceil(lo)), int(np.floor(hi)) + 1
        self.inner = (slice(a, b), slice(a, b))
        # The outer band sees the unknown floor through the blur: fit the kernel inside it.
        m = max(2, int(round(0.03 * s)))
        self.fit = (slice(m, s - m), slice(m, s - m))
        vecs = [np.zeros(2)]
        for length in cfg.blur_lengths_px:
            if length > 0:
                vecs += [
                    length * np.array([np.cos(np.radians(ang)), np.sin(np.radians(ang))]) for ang in cfg.blur_angles_deg
                ]
        self.blur_vectors = np.array(vecs)
        self.basis = _centred_unit(np.stack([_blur(mean_sym, motion_kernel(v))[self.fit].ravel() for v in vecs]))
        # Room around each template so the blur sees the sticker's own border, never a neighbour.
        self.pad = int(np.ceil(max(cfg.blur_lengths_px, default=0) / 2)) + 2

    def estimate_blur(self, obs: np.ndarray) -> np.ndarray:
        """Blur vector (2,) raster px that best explains the shared structure of ``obs`` (up to sign).

        With a least-squares gain per kernel, the residual is smallest for the kernel whose
        centred, normalised prediction has the largest squared correlation with the observation.
        """
        o = obs[self.fit].ravel()
        corr = self.basis @ (o - o.mean())
        return self.blur_vectors[int(np.argmax(corr**2))]

    def scores(
        self, obs: np.ndarray, cands: Sequence[int], bank: ReferenceBank, contrast: str, blur: np.ndarray
    ) -> np.ndarray:
        """NCC table (C, 4) over candidates and rotations."""
        vectors = _ambiguous_blurs(blur)
        p, s, n_c = self.pad, self.size, len(cands)
        if contrast == "none":
            tiles = [bank.template(c) for c in cands]
        elif contrast == "generic":
            tiles = [bank.template(c) - self.mean for c in cands]
        else:  # "decade": what sets c apart from its decade-mates, and what it shares with them
            tiles = [bank.template(c) - bank.decade_mean(c) for c in cands]
            tiles += [bank.decade_mean(c) - self.mean for c in cands]
        tiles.append(self.mean)
        stack = np.vstack([cv2.copyMakeBorder(t, p, p, p, p, cv2.BORDER_REPLICATE) for t in tiles])
        n_t, step = len(tiles), s + 2 * p
        inner = self.inner
        table = np.full((n_c, 4), -1.0)
        for v in vectors:
            for r in range(4):
                blurred = _blur(stack, motion_kernel(_unrotate_vector(v, r)))
                crops = blurred.reshape(n_t, step, step)[:, p : p + s, p : p + s][:, inner[0], inner[1]]
                crops = crops.reshape(n_t, -1)
                o = _rot(obs, -r)[inner].ravel()  # the observation in the candidates' frame
                if contrast != "none":
                    shared = crops[-1]
                    A = np.stack([shared, np.ones_like(shared)], 1)
                    coef, *_ = np.linalg.lstsq(A, o, rcond=None)
                    o = o - A @ coef
                o = _centred_unit(o)
                d = _centred_unit(crops[:n_c])
                if contrast == "decade":
                    # Partial correlation: take out, per candidate, the codewords it shares with its
                    # decade, which a missing neighbour sticker would match just as well.
                    sh = _centred_unit(crops[n_c : 2 * n_c])
                    o_c = o[None, :] - (sh @ o)[:, None] * sh
                    d = d - np.sum(d * sh, axis=1, keepdims=True) * sh
                    ncc = np.sum(_centred_unit(d) * _centred_unit(o_c), axis=1)
                else:
                    ncc = d @ o
                table[:, r] = np.maximum(table[:, r], ncc)
        return table


def _appearance_of(bank: ReferenceBank, cfg: IdentifyConfig) -> _Appearance:
    key = ("appearance", cfg.blur_lengths_px, cfg.blur_angles_deg)
    ap = bank.derived.get(key)
    if ap is None:
        ap = bank.derived[key] = _Appearance(bank, cfg)
    return ap


def prepare(bank: ReferenceBank, config: IdentifyConfig | None = None) -> None:
    """Make the appearance test's per-bank tables now (the first :func:`identify` call would: ~10 ms)."""
    _appearance_of(bank, config or IdentifyConfig())


def appearance_scores(
    gray: np.ndarray,
    detection: Detection,
    camera: Camera,
    cands: Sequence[int],
    bank: ReferenceBank,
    cfg: IdentifyConfig,
    motion_hint: np.ndarray | None = None,
) -> _Scores:
    """Appearance score table (C, 4) for the candidates, with the blur used."""
    ap = _appearance_of(bank, cfg)
    obs = rectify(gray, detection, camera, ap.size).astype(np.float32)
    blur = np.asarray(motion_hint, float).reshape(2) if motion_hint is not None else ap.estimate_blur(obs)
    return _Scores(ap.scores(obs, cands, bank, cfg.contrast, blur), blur)


# ---------------------------------------------------------------- ORB


_ORB: dict[tuple, cv2.ORB] = {}
_MATCHER = cv2.BFMatcher(cv2.NORM_HAMMING)


def orb_scores(
    gray: np.ndarray,
    detection: Detection,
    camera: Camera,
    cands: Sequence[int],
    bank: ReferenceBank,
    cfg: IdentifyConfig,
) -> _Scores:
    """ORB geometric-inlier table (C, 4) for the candidates."""
    p = bank.params
    key = (p.orb_features, p.orb_levels)
    orb = _ORB.get(key) or _ORB.setdefault(key, make_orb(p))
    raster = rectify(gray, detection, camera, p.orb_size_px)
    xy, des = orb_features(raster, p, bank.orb_mask, orb)
    table = np.zeros((len(cands), 4))
    if len(des) < 2:
        return _Scores(table)
    c = (p.orb_size_px - 1) / 2.0
    if len(cands) > cfg.orb_global_above:
        # Many candidates (the paper's match-everything baseline): one match against all their
        # references, the ratio test then runs across stickers -- stricter, and ~50x faster
        # than one matcher call per sticker.
        feats = [bank.features(sid) for sid in cands]
        owner = np.repeat(np.arange(len(cands)), [len(f[1]) for f in feats])
        rxy = np.concatenate([f[0] for f in feats])
        rdes = np.concatenate([f[1] for f in feats])
        q, t = _ratio_matches(des, rdes, cfg.ratio)
        _count_inliers(table, owner[t], q, xy[q] - c, rxy[t] - c, cfg.inlier_px)
        return _Scores(table)
    for ci, sid in enumerate(cands):
        rxy, rdes = bank.features(sid)
        q, t = _ratio_matches(des, rdes, cfg.ratio)
        _count_inliers(table, np.full(len(q), ci), q, xy[q] - c, rxy[t] - c, cfg.inlier_px)
    return _Scores(table)


def _ratio_matches(des: np.ndarray, ref: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """(query, train) index arrays of the matches passing Lowe's ratio test."""
    if len(des) < 1 or len(ref) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    good = [
        (m.queryIdx, m.trainIdx)
        for m, n in (pr for pr in _MATCHER.knnMatch(des, ref, k=2) if len(pr) == 2)
        if m.distance < ratio * n.distance
    ]
    if not good:
        return np.zeros(0, int), np.zeros(0, int)
    q, t = np.array(good).T
    return q, t


def _count_inliers(
    table: np.ndarray, owner: np.ndarray, q: np.ndarray, sxy: np.ndarray, ref: np.ndarray, inlier_px: float
) -> None:
    """Add to ``table[owner, r]`` the scene keypoints whose match lands where rotation r puts it.

    ``sxy``/``ref`` are scene/reference positions relative to the raster centre; one scene
    keypoint counts once per (candidate, rotation) even if several of its matches agree.
    """
    rr = ref
    for r in range(4):
        ok = np.linalg.norm(sxy - rr, axis=1) <= inlier_px
        if np.any(ok):
            pairs = np.unique(np.stack([owner[ok], q[ok]], 1), axis=0)
            np.add.at(table[:, r], pairs[:, 0], 1)
        rr = np.stack([-rr[:, 1], rr[:, 0]], 1)  # one more clockwise quarter turn (row-down axes)


# ---------------------------------------------------------------- entry point


def _usable(detection: Detection) -> bool:
    """A convex, finite, non-degenerate outline (a detector's degenerate quad is refused, not an error)."""
    q = np.asarray(detection.outer, float)
    if q.shape != (4, 2) or not np.all(np.isfinite(q)):
        return False
    if detection.inner is not None and not np.all(np.isfinite(detection.inner)):
        return False
    return (
        bool(cv2.isContourConvex(q.astype(np.float32).reshape(-1, 1, 2)))
        and cv2.contourArea(q.astype(np.float32)) >= 16.0
    )


def identify(
    gray: np.ndarray,
    detection: Detection,
    camera: Camera,
    candidate_ids: Sequence[int],
    bank: ReferenceBank,
    method: str = "auto",
    motion_hint: np.ndarray | None = None,
    config: IdentifyConfig | None = None,
) -> IdResult:
    """Say which candidate sticker ``detection`` shows, with its rotation, or refuse.

    Args:
        gray: (H, W) uint8 distorted frame.
        detection: the undecoded sticker's corners (distorted px, clockwise on screen).
        camera: intrinsics of ``gray``.
        candidate_ids: the tracker's candidates, most likely first (order does not bias the answer).
        bank: references (:func:`tagloc.vision.refs.load_or_build_refs`); candidates missing from it
            are rendered on the fly.
        method: "appearance", "orb", or "auto" (appearance: measured better and faster, see the
            module docs of :mod:`tagloc.eval.bench_identify`).
        motion_hint: optional (2,) blur vector in appearance-raster px (skips blur estimation).
        config: thresholds; defaults are the measured ones.
    Returns:
        :class:`IdResult`; ``sticker_id`` is None when no candidate is clearly the one seen.
    """
    cfg = config or IdentifyConfig()
    if method not in METHODS:
        raise InputError(f"identify: unknown method {method!r} (want one of {', '.join(METHODS)})")
    require_gray(gray, "identify")
    cands = list(dict.fromkeys(int(c) for c in candidate_ids))  # unique, order kept
    if not cands or not _usable(detection):
        return IdResult(None, None, 0.0, 0.0, IdSource.NONE)
    if method == "orb":
        s = orb_scores(gray, detection, camera, cands, bank, cfg)
        ok = s.score >= cfg.min_inliers and s.margin >= cfg.min_inlier_margin
        source = IdSource.ORB
    else:
        s = appearance_scores(gray, detection, camera, cands, bank, cfg, motion_hint)
        ok = s.score >= cfg.min_ncc and s.margin >= cfg.min_ncc_margin
        source = IdSource.APPEARANCE
    c, r = s.best
    runner = cands[s.runner_up] if s.runner_up is not None else None
    if not ok:
        return IdResult(None, None, s.score, s.margin, IdSource.NONE, runner, s.blur)
    return IdResult(cands[c], r, s.score, s.margin, source, runner, s.blur)
