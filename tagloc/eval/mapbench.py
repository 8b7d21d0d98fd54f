"""Measure map refinement on simulated walks: survey-error map in, refined map out, both against the truth.

The simulator renders the floor from the true map; the localiser is handed a copy with survey
errors (:func:`survey_error_map`), as a site would have. Refining from some walks and localising the
same and fresh walks with each map shows what the refinement is worth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tagloc.core.geometry import wrap_angle
from tagloc.core.stickermap import StickerMap
from tagloc.eval.mapobs import WalkLog, collect_walk
from tagloc.eval.maprefine import RefineConfig, RefineResult, refine_map
from tagloc.eval.metrics import error_metrics, trajectory_errors
from tagloc.io.session import SessionReader


def survey_error_map(
    smap: StickerMap,
    sigma_m: float = 0.02,
    sigma_deg: float = 2.0,
    seed: int = 0,
    moved: dict[int, tuple[float, float]] | None = None,
) -> StickerMap:
    """A copy of ``smap`` as a survey with errors would give it.

    Each centre moves by a 2-D Gaussian whose radial RMS is ``sigma_m`` (``sigma_m / sqrt 2`` per
    axis) and each yaw by a Gaussian of ``sigma_deg``; ``moved`` adds known offsets (dx, dy, m) to
    chosen IDs (a sticker replaced elsewhere). The map states the per-axis sigma and the yaw sigma
    in its sigma columns, as an honest survey would.
    """
    rng = np.random.default_rng([seed, 18])
    per_axis = sigma_m / math.sqrt(2)
    xy = smap.xy + rng.normal(0.0, per_axis, smap.xy.shape)
    yaw = wrap_angle(smap.yaw + np.radians(rng.normal(0.0, sigma_deg, len(smap))))
    for sid, (dx, dy) in (moved or {}).items():
        xy[smap.row(sid)] += (dx, dy)
    n = len(smap)
    return StickerMap(
        smap.ids.copy(),
        xy,
        yaw,
        f"{smap.source} (survey error)",
        np.full(n, per_axis),
        np.full(n, math.radians(sigma_deg)),
    )


def map_errors(est: StickerMap, truth: StickerMap, ids: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """(K,) position errors (m) and (K,) signed yaw errors (rad) of ``est`` against ``truth`` for ``ids``."""
    if not ids:
        return np.zeros(0), np.zeros(0)
    rows_e = [est.row(i) for i in ids]
    rows_t = [truth.row(i) for i in ids]
    pos = np.hypot(*(est.xy[rows_e] - truth.xy[rows_t]).T)
    return pos, wrap_angle(est.yaw[rows_e] - truth.yaw[rows_t])


def walk_metrics(walk: WalkLog) -> dict:
    """Localisation figures of a collected walk against its session's ground truth (tracked frames only)."""
    gt = SessionReader(walk.path).groundtruth()
    frames = [fr for fr in walk.frames if fr.state != "initialising"]
    if gt is None or not frames:
        return {"frames": 0}
    e = trajectory_errors(
        np.array([fr.t for fr in frames]),
        np.array([fr.pose for fr in frames]),
        np.array([fr.cov for fr in frames]),
        *gt,
    )
    m = error_metrics(e)
    m["gated_fixes"] = sum(s.accepted is False for fr in walk.frames for s in fr.sightings)
    return m


@dataclass
class MapBenchResult:
    """Figures of one refinement trial.

    Attributes:
        refine: the refinement.
        seen: IDs refined (seen two or more to a frame); moved_ids: IDs moved on purpose.
        before_m, after_m: position errors (m) of the seen stickers not moved on purpose, survey-error
            map and refined map; before_yaw, after_yaw: yaw errors (rad).
        moved_after_m: residual error of each sticker moved on purpose, after.
        unseen_unchanged: every sticker not refined is bit-identical to the survey-error map.
        metrics: {"survey"|"refined"|"true": {walk name: metrics}} localising the walks with each map.
    """

    refine: RefineResult
    seen: list[int]
    moved_ids: list[int]
    before_m: np.ndarray
    after_m: np.ndarray
    before_yaw: np.ndarray
    after_yaw: np.ndarray
    moved_after_m: np.ndarray
    unseen_unchanged: bool
    metrics: dict[str, dict[str, dict]] = field(default_factory=dict)


def map_bench(
    truth: StickerMap,
    survey: StickerMap,
    refine_sessions: list[str | Path],
    eval_sessions: list[str | Path] | None = None,
    moved_ids: list[int] | None = None,
    config: RefineConfig | None = None,
    progress: bool = False,
) -> MapBenchResult:
    """Refine ``survey`` from ``refine_sessions`` (rendered from ``truth``) and score both maps.

    Localises ``refine_sessions`` (and ``eval_sessions``, fresh walks) with the survey-error map,
    the refined map and the true map, and compares the maps' stickers with the truth.
    """
    moved_ids = list(moved_ids or [])
    walks = [collect_walk(s, survey, progress=progress) for s in refine_sessions]
    res = refine_map(walks, survey, config)
    seen = [c.sticker_id for c in res.changes]
    plain = [i for i in seen if i not in moved_ids]
    before, before_yaw = map_errors(survey, truth, plain)
    after, after_yaw = map_errors(res.refined, truth, plain)
    moved_after, _ = map_errors(res.refined, truth, [i for i in moved_ids if i in seen])
    unseen = [int(i) for i in survey.ids if int(i) not in set(seen)]
    rows = [survey.row(i) for i in unseen]
    unchanged = bool(
        np.array_equal(res.refined.xy[rows], survey.xy[rows])
        and np.array_equal(res.refined.yaw[rows], survey.yaw[rows])
    )
    out = MapBenchResult(res, seen, moved_ids, before, after, before_yaw, after_yaw, moved_after, unchanged)
    sessions = list(refine_sessions) + list(eval_sessions or [])
    for name, smap in (("survey", survey), ("refined", res.refined), ("true", truth)):
        logs = walks if name == "survey" else [collect_walk(s, smap, progress=progress) for s in refine_sessions]
        logs = logs + [collect_walk(s, smap, progress=progress) for s in sessions[len(refine_sessions) :]]
        out.metrics[name] = {w.name: walk_metrics(w) for w in logs}
    return out
