"""Accuracy and consistency of an estimated trajectory against ground truth.

Ground truth is interpolated at the estimates' timestamps (positions linearly, rotations by scipy's
Slerp); estimates outside the ground truth's time span, or inside a gap of it longer than
:data:`GT_MAX_GAP_S` (a motion-capture dropout: a straight line across it is no truth), are not
scored. Errors are horizontal
(x, y) and heading (yaw of the body's +x axis about world +z).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tagloc.core.geometry import interpolate_groundtruth, wrap_angle
from tracker.config import chi2_bound

#: A gap between consecutive ground-truth poses is a dropout, not scored across, when longer than
#: both this and :data:`GT_GAP_INTERVALS` of the ground truth's median interval (a simulated walk's
#: longest is a burst of dropped frames: 8 frames, 0.3 s at 30 fps).
GT_MAX_GAP_S = 0.5
GT_GAP_INTERVALS = 10.0


def gt_covers(stamps: np.ndarray, gt_stamps: np.ndarray, max_gap_s: float = GT_MAX_GAP_S) -> np.ndarray:
    """(N,) bool: which ``stamps`` the ground truth can score, those within its span and not strictly
    inside a gap between consecutive ground-truth stamps longer than ``max_gap_s`` and
    :data:`GT_GAP_INTERVALS` median intervals."""
    stamps = np.asarray(stamps, float).ravel()
    g = np.unique(np.asarray(gt_stamps, float).ravel())
    if len(g) == 0:
        return np.zeros(len(stamps), bool)
    out = (stamps >= g[0]) & (stamps <= g[-1])
    if len(g) > 1:
        gap = max(max_gap_s, GT_GAP_INTERVALS * float(np.median(np.diff(g))))
        i = np.clip(np.searchsorted(g, stamps, side="right"), 1, len(g) - 1)
        lo, hi = g[i - 1], g[i]
        out &= ~((hi - lo > gap) & (stamps > lo) & (stamps < hi))
    return out


@dataclass
class TrajectoryErrors:
    """Per-estimate errors against interpolated ground truth (only estimates it covers, :func:`gt_covers`).

    Attributes:
        stamps: (K,) timestamps scored, s.
        inside: (N,) bool over the estimates given: True where scored.
        gt: (K, 3) ground-truth (x, y, yaw) at ``stamps``.
        position: (K,) horizontal error, m.
        yaw: (K,) signed heading error (estimate - truth) wrapped to [-pi, pi), rad.
        nees: (K,) normalised estimation error squared of the position (2 DoF) under the
            estimate's (x, y) covariance block.
    """

    stamps: np.ndarray
    inside: np.ndarray
    gt: np.ndarray
    position: np.ndarray
    yaw: np.ndarray
    nees: np.ndarray


def trajectory_errors(
    est_stamps: np.ndarray, est_poses: np.ndarray, est_covs: np.ndarray, gt_stamps: np.ndarray, gt_T: np.ndarray
) -> TrajectoryErrors:
    """Errors of estimates (x, y, yaw) (N, 3) with covariances (N, 3, 3) against GT poses (M, 4, 4)."""
    est_stamps = np.asarray(est_stamps, float).ravel()
    est_poses = np.asarray(est_poses, float).reshape(-1, 3)
    est_covs = np.asarray(est_covs, float).reshape(-1, 3, 3)
    if not len(est_stamps) == len(est_poses) == len(est_covs):
        raise ValueError("est_stamps, est_poses and est_covs must have the same length")
    gt, inside = interpolate_groundtruth(gt_stamps, gt_T, est_stamps)
    covered = gt_covers(est_stamps, gt_stamps)
    gt, inside = gt[covered[inside]], inside & covered
    est, cov = est_poses[inside], est_covs[inside]
    d = est[:, :2] - gt[:, :2]
    # Solve rather than invert: position blocks can be badly conditioned right after a fix.
    nees = np.einsum("ki,ki->k", d, np.linalg.solve(cov[:, :2, :2], d[:, :, None])[:, :, 0]) if len(d) else np.zeros(0)
    return TrajectoryErrors(
        est_stamps[inside],
        inside,
        gt,
        np.hypot(d[:, 0], d[:, 1]),
        np.asarray(wrap_angle(est[:, 2] - gt[:, 2]), float).reshape(-1),
        nees,
    )


def trajectory_metrics(
    est_stamps: np.ndarray, est_poses: np.ndarray, est_covs: np.ndarray, gt_stamps: np.ndarray, gt_T: np.ndarray
) -> dict:
    """Summary figures of an estimated trajectory against ground truth.

    Args:
        est_stamps: (N,) estimate timestamps, s.
        est_poses: (N, 3) estimated body (x, y, yaw), m and rad.
        est_covs: (N, 3, 3) their covariances.
        gt_stamps: (M,) ground-truth timestamps, s.
        gt_T: (M, 4, 4) ground-truth T_world_body.

    Returns:
        ``frames`` (estimates scored), ``outside_gt`` (estimates outside the GT span), ``rmse_m``,
        ``median_m``, ``p95_m``, ``max_m`` (horizontal error), ``heading_rmse_deg``,
        ``within_10cm`` and ``within_25cm`` (fractions of scored estimates), ``nees_mean`` (2-DoF
        position NEES; about 2 for a consistent filter), ``beyond_999`` (fraction of scored
        estimates whose NEES exceeds :data:`NEES_999_2DOF`; 0.001 for a consistent filter). Figures
        are NaN (fractions 0) when nothing was scored.
    """
    return error_metrics(trajectory_errors(est_stamps, est_poses, est_covs, gt_stamps, gt_T))


#: Chi-square's 99.9 % point for 2 DoF (13.8): a consistent filter's position NEES exceeds it on 0.1 %
#: of frames (Gaussian errors). A run with many more frames beyond it was stated surer than it was
#: somewhere, which its mean NEES over the whole walk can hide.
NEES_999_2DOF = chi2_bound(0.999, 2)


def error_metrics(e: TrajectoryErrors) -> dict:
    """The figures of :func:`trajectory_metrics` from errors already computed."""
    n = len(e.position)
    out = {"frames": n, "outside_gt": int(len(e.inside) - n)}
    if n == 0:
        nan = math.nan
        out.update(
            rmse_m=nan,
            median_m=nan,
            p95_m=nan,
            max_m=nan,
            heading_rmse_deg=nan,
            within_10cm=0.0,
            within_25cm=0.0,
            nees_mean=nan,
            beyond_999=nan,
        )
        return out
    p = e.position
    out.update(
        rmse_m=float(np.sqrt(np.mean(p**2))),
        median_m=float(np.median(p)),
        p95_m=float(np.percentile(p, 95)),
        max_m=float(np.max(p)),
        heading_rmse_deg=float(np.degrees(np.sqrt(np.mean(e.yaw**2)))),
        within_10cm=float(np.mean(p <= 0.10)),
        within_25cm=float(np.mean(p <= 0.25)),
        nees_mean=float(np.mean(e.nees)),
        beyond_999=float(np.mean(e.nees > NEES_999_2DOF)),
    )
    return out


def frames_in_span(stamps: np.ndarray, gt_stamps: np.ndarray) -> int:
    """How many of a run's frame ``stamps`` (N,) s lie within the ground truth's span and outside its
    gaps (:func:`gt_covers`: the frames it can score; a frame just past the span's end, by a
    jittered stamp, is neither hit nor miss)."""
    return int(np.sum(gt_covers(stamps, gt_stamps)))
