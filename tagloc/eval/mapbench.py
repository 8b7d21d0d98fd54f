"""Measure map refinement on simulated walks over a site whose map has known survey errors.

The site (:func:`strip_site`) is rendered by the simulator at the stickers' true poses; each
session's ``map.csv`` carries the survey error of :mod:`tagloc.sim.survey` (one survey of the site,
stated in the sigma columns, with a sticker moved since the survey on top), and the audited map is
that survey of the mapped stickers (:func:`site_map`). Refining from some walks and localising the
same and fresh walks with the survey-error map, the refined map and the true map shows what the
refinement is worth, scored as ``tagloc eval`` scores a walk (RMSE, NEES and its verdict, wrong IDs).

What the walks can determine, and so what the refined map is compared with (:func:`anchoring_bound`):
the walks fix the stickers relative to one another, but where the whole group sits (two offsets and a
rotation) is known only from the survey priors. With N stickers surveyed at sigma per axis, the best
any estimator can do, even knowing the group's shape exactly, leaves an error of the rigid transform
with covariance (J^T W J)^-1: the survey's errors projected onto three degrees of freedom, a position
error of about sigma * sqrt(3 / N) RMS over the stickers (the yaw priors take a little off). The
refined map is scored against the truth directly, never after an alignment a real site would not have.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from tagloc.core.geometry import wrap_angle
from tagloc.core.stickermap import StickerMap
from tagloc.eval.consistency import nees_blocks, nees_test
from tagloc.eval.evaluate import wrong_id_fixes
from tagloc.eval.mapobs import WalkLog, collect_walk
from tagloc.eval.maprefine import RefineConfig, RefineResult, refine_map
from tagloc.eval.metrics import error_metrics, trajectory_errors
from tagloc.io.session import SessionReader
from tagloc.sim.survey import SurveyConfig, surveyed_map

#: The benchmark's and test's site (see :func:`strip_site`): a sticker moved since the survey, one
#: mapped but no longer on the floor (missing) and one on the floor but not mapped (unmapped).
MOVED, MISSING, UNMAPPED = 1029, 1047, 1066
MOVE_M = (0.09, 0.12)  # 15 cm
#: The issue's survey: 2 cm RMS in position (radial, 1.41 cm per axis) and 2 degrees, stated in the map.
SITE_SURVEY = SurveyConfig(0.02 / math.sqrt(2), 2.0, stated=True, seed=5, moved=((MOVED, *MOVE_M),))


def strip_site(rows: int = 4, cols: int = 20, spacing_m: float = 0.4, first_id: int = 1000) -> StickerMap:
    """A strip of ``rows`` x ``cols`` stickers ``spacing_m`` apart along x (rows across y), IDs from
    ``first_id`` row by row, at yaws cycling through six directions.

    The default (4 x 20 at 0.4 m: 7.6 m x 1.2 m) is about as wide as the camera's footprint (about
    1.5 m across, 0.3-2 m ahead), so three 8 s walks along it see some 70 of the 80 stickers, many
    to a frame: enough stickers for the survey priors to place the group within the issue's 0.5 cm
    (:func:`anchoring_bound`; 11 stickers could not: about 0.74 cm).
    """
    x, y = np.meshgrid(np.arange(cols) * spacing_m, (np.arange(rows) - (rows - 1) / 2) * spacing_m)
    ids = first_id + np.arange(rows * cols)
    yaw = np.radians(np.resize([0.0, 90.0, 35.0, 180.0, -60.0, 120.0, -150.0], len(ids)))
    return StickerMap(ids, np.column_stack([x.ravel(), y.ravel()]), yaw, f"strip {rows}x{cols}")


def without(smap: StickerMap, *drop: int) -> StickerMap:
    """``smap`` without the stickers ``drop``."""
    keep = ~np.isin(smap.ids, drop)
    return StickerMap(
        smap.ids[keep], smap.xy[keep], smap.yaw[keep], smap.source, smap.sigma_xy[keep], smap.sigma_yaw[keep]
    )


def site_map(
    truth: StickerMap, survey: SurveyConfig = SITE_SURVEY, unmapped: tuple[int, ...] = (UNMAPPED,)
) -> StickerMap:
    """The site's map as surveyed: every true sticker but the ``unmapped`` ones, with the survey's
    errors (the same per sticker as in every session's ``map.csv``, see :mod:`tagloc.sim.survey`)."""
    return surveyed_map(without(truth, *unmapped), survey, seed=0)


def map_errors(est: StickerMap, truth: StickerMap, ids: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """(K,) position errors (m) and (K,) signed yaw errors (rad) of ``est`` against ``truth`` for ``ids``."""
    if not ids:
        return np.zeros(0), np.zeros(0)
    rows_e = [est.row(i) for i in ids]
    rows_t = [truth.row(i) for i in ids]
    pos = np.hypot(*(est.xy[rows_e] - truth.xy[rows_t]).T)
    return pos, wrap_angle(est.yaw[rows_e] - truth.yaw[rows_t])


def stated_exact(smap: StickerMap) -> StickerMap:
    """``smap`` stating a survey sigma of 0 for every sticker: the true map as a reference must not be
    taken for a survey (without sigma columns the localiser assumes its default survey error)."""
    n = len(smap)
    return StickerMap(smap.ids, smap.xy, smap.yaw, smap.source, np.zeros(n), np.zeros(n))


def rms(a: np.ndarray) -> float:
    """Root mean square of ``a`` (NaN when empty)."""
    a = np.asarray(a, float)
    return float(np.sqrt(np.mean(a**2))) if a.size else math.nan


@dataclass
class AnchoringBound:
    """What the survey priors of ``ids`` can place, given the group's exact shape.

    Attributes:
        oracle_m: (K,) position errors of the best estimate knowing the true shape: the true group
            moved by the rigid transform that best fits the survey priors (weighted by their sigmas).
            The refined map cannot beat this on average; a solver reaching the bound matches it.
        expected_rms_m: the RMS position error that estimate has on average over survey draws,
            sqrt(trace of the transform's covariance mapped onto the stickers / K).
        shape_rms_m: RMS position error of the refined map after its best rigid fit to the truth
            (a diagnostic of the shape alone; the map is never scored after such a fit).
    """

    oracle_m: np.ndarray
    expected_rms_m: float
    shape_rms_m: float


def _rigid(xy: np.ndarray, centre: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(K, 2) points ``xy`` turned by ``p[2]`` about ``centre`` and shifted by ``p[:2]``."""
    c, s = math.cos(p[2]), math.sin(p[2])
    d = xy - centre
    return centre + p[:2] + np.column_stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]])


def anchoring_bound(truth: StickerMap, prior: StickerMap, refined: StickerMap, ids: list[int]) -> AnchoringBound:
    """The anchoring bound of the stickers ``ids`` (see :class:`AnchoringBound`); ``prior`` must state sigmas."""
    if not ids:
        return AnchoringBound(np.zeros(0), math.nan, math.nan)
    rt = [truth.row(i) for i in ids]
    rp = [prior.row(i) for i in ids]
    p_true, yaw_true = truth.xy[rt], truth.yaw[rt]
    s_xy, s_yaw = prior.sigma_xy[rp], prior.sigma_yaw[rp]
    centre = p_true.mean(axis=0)

    def residuals(p: np.ndarray) -> np.ndarray:
        dxy = (_rigid(p_true, centre, p) - prior.xy[rp]) / s_xy[:, None]
        dyaw = wrap_angle(yaw_true + p[2] - prior.yaw[rp]) / s_yaw
        return np.concatenate([dxy.ravel(), dyaw])

    fit = least_squares(residuals, np.zeros(3))
    oracle = np.hypot(*(_rigid(p_true, centre, fit.x) - p_true).T)
    # Covariance of the transform from the priors alone, mapped onto each sticker's position.
    d = p_true - centre
    J = np.zeros((len(ids), 2, 3))
    J[:, 0, 0] = J[:, 1, 1] = 1.0
    J[:, 0, 2], J[:, 1, 2] = -d[:, 1], d[:, 0]
    info = np.einsum("kai,kaj->ij", J / s_xy[:, None, None], J / s_xy[:, None, None])
    info[2, 2] += float(np.sum(1.0 / s_yaw**2))
    cov = np.linalg.inv(info)
    expected = math.sqrt(float(np.einsum("kai,ij,kaj->", J, cov, J)) / len(ids))
    # Shape only: the refined positions after their best (unweighted) rigid fit to the truth.
    est = refined.xy[[refined.row(i) for i in ids]]
    shape = least_squares(lambda p: (_rigid(est, est.mean(axis=0), p) - p_true).ravel(), np.zeros(3))
    return AnchoringBound(oracle, expected, rms(np.hypot(*shape.fun.reshape(-1, 2).T)))


def walk_metrics(walk: WalkLog) -> dict:
    """A walk scored as ``tagloc eval`` scores one: its error metrics against the session's ground
    truth (frames with a pose), NEES blocks, accepted and gated fixes, and wrong-ID fixes."""
    log, path = walk.log, walk.path
    gt = SessionReader(path).groundtruth()
    if log is None or gt is None or not log.valid.any():
        return {"frames": 0}
    v = log.valid
    e = trajectory_errors(log.stamps[v], log.poses[v], log.covs[v], *gt)
    m = error_metrics(e)
    wrong, checked = wrong_id_fixes(path, log)
    m.update(
        wrong_id_fixes=wrong,
        fixes=checked,
        gated_fixes=len(log.rejected),
        nees_blocks=nees_blocks(e.stamps, e.nees).tolist(),
    )
    return m


def pooled(metrics: dict[str, dict]) -> dict:
    """Walks' metrics pooled by frame: RMSE, heading RMSE, mean NEES with its verdict, fixes, wrong IDs."""
    rows = [m for m in metrics.values() if m.get("frames")]
    if not rows:
        return {"frames": 0}
    n = np.array([m["frames"] for m in rows], float)
    w = n / n.sum()
    test = nees_test(np.array([b for m in rows for b in m["nees_blocks"]], float).reshape(-1, 3))
    return {
        "frames": int(n.sum()),
        "rmse_m": float(np.sqrt(np.sum(w * np.array([m["rmse_m"] for m in rows]) ** 2))),
        "heading_rmse_deg": float(np.sqrt(np.sum(w * np.array([m["heading_rmse_deg"] for m in rows]) ** 2))),
        "nees_mean": test.mean,
        "nees_bounds_95_effective": list(test.bounds_effective),
        "nees_verdict": test.verdict,
        "fixes": int(sum(m["fixes"] for m in rows)),
        "gated_fixes": int(sum(m["gated_fixes"] for m in rows)),
        "wrong_id_fixes": int(sum(m["wrong_id_fixes"] for m in rows)),
    }


@dataclass
class MapBenchResult:
    """Figures of one refinement trial.

    Attributes:
        refine: the refinement.
        seen: IDs refined; moved_ids: IDs moved on purpose.
        before_m, after_m: position errors (m) of the refined stickers not moved on purpose, survey-error
            map and refined map, against the truth; before_yaw, after_yaw: yaw errors (rad).
        moved_after_m: residual error of each sticker moved on purpose, after.
        unseen_unchanged: every sticker not refined is bit-identical to the survey-error map.
        bound: what the survey priors allow (:func:`anchoring_bound`).
        metrics: {"survey"|"refined"|"true": {walk name: walk_metrics}} localising the walks with each map.
        walks: the refining walks as collected with the survey-error map.
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
    bound: AnchoringBound
    metrics: dict[str, dict[str, dict]] = field(default_factory=dict)
    walks: list[WalkLog] = field(default_factory=list)

    def pooled(self, name: str) -> dict:
        """The walks localised with map ``name`` ("survey", "refined", "true"), pooled (:func:`pooled`)."""
        return pooled(self.metrics[name])


def score_refinement(res: RefineResult, truth: StickerMap, survey: StickerMap, moved_ids: list[int]) -> MapBenchResult:
    """The map figures of a refinement of ``survey`` against ``truth`` (no localisation)."""
    seen = [c.sticker_id for c in res.changes]
    plain = [i for i in seen if i not in moved_ids]
    before, before_yaw = map_errors(survey, truth, plain)
    after, after_yaw = map_errors(res.refined, truth, plain)
    moved_after, _ = map_errors(res.refined, truth, [i for i in moved_ids if i in seen])
    rows = [survey.row(int(i)) for i in survey.ids if int(i) not in set(seen)]
    unchanged = bool(
        np.array_equal(res.refined.xy[rows], survey.xy[rows])
        and np.array_equal(res.refined.yaw[rows], survey.yaw[rows])
    )
    bound = anchoring_bound(truth, survey, res.refined, plain)
    return MapBenchResult(res, seen, moved_ids, before, after, before_yaw, after_yaw, moved_after, unchanged, bound)


def map_bench(
    truth: StickerMap,
    survey: StickerMap,
    refine_sessions: list[str | Path],
    eval_sessions: list[str | Path] | None = None,
    moved_ids: list[int] | None = None,
    config: RefineConfig | None = None,
    progress: bool = False,
    survey_path: str | Path | None = None,
) -> MapBenchResult:
    """Refine ``survey`` from ``refine_sessions`` (rendered from ``truth``) and score both maps.

    Localises ``refine_sessions`` (and ``eval_sessions``, fresh walks) with the survey-error map,
    the refined map and the true map (stated exact), and compares the maps' stickers with the truth.
    ``survey_path``: the file ``survey`` came from (the identification's reference cache sits beside it).
    """
    moved_ids = list(moved_ids or [])
    fresh = list(eval_sessions or [])
    walks = [collect_walk(s, survey, map_path=survey_path, progress=progress) for s in refine_sessions]
    res = refine_map(walks, survey, config)
    out = score_refinement(res, truth, survey, moved_ids)
    out.walks = walks
    for name, smap in (("survey", survey), ("refined", res.refined), ("true", stated_exact(truth))):
        logs = walks if name == "survey" else [collect_walk(s, smap, progress=progress) for s in refine_sessions]
        logs = logs + [collect_walk(s, smap, progress=progress) for s in fresh]
        out.metrics[name] = {w.name: walk_metrics(w) for w in logs}
    return out
