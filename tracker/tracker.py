"""The tracker: walking-motion EKF, gating, life cycle (INITIALISING / TRACKING / LOST), counters.

Rules, in one place:

- Time is the frames' clock. :meth:`Tracker.predict` moves the filter to a frame's timestamp; a
  frame older than the filter does not move it (counted ``out_of_order_frames``). A fix up to
  ``max_lag_s`` older than the filter is fused against the state retrodicted to its time (CTRV run
  backwards, plus the process noise over the lag); an older fix is rejected
  (``out_of_order_fixes``). A rolling-shutter camera's fix holds when its sticker's rows were read,
  ``row_time_s`` after its frame's time (up to half the read-out, either way): it is fused against
  the state carried to that instant (back, or ahead by the same motion model).
- A fix measures the vest's pose: the body's plus the vest offset, a state of the filter (see
  :mod:`tracker.ekf`): the torso's sway on the smooth walk (see :class:`TrackerConfig`); the tracker
  reports body + offset, the vest point on the floor.
  Fixes of one frame share it exactly, so three stickers in one frame do not count as three
  independent vest poses, and consecutive frames share most of it.
- Two IPPE alternatives (ambiguous pose): while tracking, the one with the smaller Mahalanobis
  distance to the prediction is used; when (re)initialising, the first (best reprojection).
- INITIALISING: only a DECODED fix starts the track. TRACKING: fixes must pass the chi-square gate
  (stricter for ORB/appearance; a CHECKED fix, the tracker's expected ID whose data modules matched
  as a decode's final check does, is gated as decoded: a wrong pick fails that check, so agreeing
  with this prior is not all its evidence). LOST (position sigma > ``lost_sigma_m`` or no fix for
  ``lost_after_s``; after ``lost_after_s`` speed and yaw rate are also forgotten): only decoded
  fixes are taken; one that passes the gate is fused, one that does not re-initialises the track,
  and so does any while the heading is at its cap (unknown: nothing to linearise a late fix at).
  An accepted fix makes the track TRACKING only if it leaves the position sigma within
  ``lost_sigma_m``: a vaguer one (a far sticker's) starts or keeps it LOST.
- ``reinit_fixes`` gated-out DECODED (or CHECKED, ``reinit_checked``) fixes that agree with each
  other re-initialise the track.
- Floor odometry (:meth:`Tracker.update_odometry`): each step is the vest's relative pose between
  two consecutive frames of one camera. When :meth:`Tracker.predict` advances from a frame of
  camera A, it keeps a clone of the (odometry) pose there, keyed by A, with its cross-covariance to
  the state (stochastic cloning); A's next step is fused as a measurement of
  ``vest(t1) (-) clone_A(t0)`` (the camera moves with the vest). That is exact for one step
  (forward, lateral and turn alike, so sidesteps and stops are followed), and consecutive steps of
  a camera share no clone, so fusing every frame never counts a frame twice. The vest's wobble,
  which the steps follow, lands in the offset state and is bounded there instead of accumulating
  in the body's pose. With several cameras their frames interleave: a clone is carried, with its
  cross-covariance kept exact, through every prediction (``cross <- F cross``) and every update
  (fixes and the other cameras' steps: a joint update over the state and the clones), so camera
  A's step is fused against A's clone even when camera B's frame came in between. A clone older
  than ``odometry_max_dt`` is dropped (no step can use it); a restart drops them all. Used while
  TRACKING or LOST (it slows the growth of the uncertainty either way), gated, and only for a step
  that ends at the filter's time and starts at the camera's clone (call it after the frame's
  :meth:`Tracker.predict`); otherwise it is counted as ``odometry_unmatched``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Protocol, TypeVar

import numpy as np

from tagloc.core.geometry import map_error_jacobian, wrap_angle
from tagloc.core.rig import RigCamera
from tagloc.core.stickermap import StickerMap
from tagloc.core.types import IdSource, PoseFix, SurveyPrior, TrackerOutput, TrackState
from tracker import motion
from tracker.candidates import centre_pixels, gate_candidates, predicted_rows
from tracker.clones import CloneSet
from tracker.config import TrackerConfig
from tracker.ekf import (
    DIM,
    M_ODO,
    OFF,
    MapTerm,
    WalkingEKF,
    heading_widened,
    largest_eig_2x2,
    map_slot,
    odometry_model,
    odometry_pose,
    pose_residual,
    sym_spd,
    vest_cov,
    vest_pose,
)
from tracker.filterpy_kalman import update as kf_update

__all__ = ["Tracker", "TrackerConfig", "UpdateResult"]


@dataclass
class UpdateResult:
    """What the tracker did with one sticker's fix.

    Attributes:
        accepted: the fix changed the estimate (fused, started or restarted the track).
        reason: one line: "fused", "initialised", "reinitialised ...", or why it was refused.
        nis: squared Mahalanobis distance of the chosen alternative (nan when not gated).
        chosen: index into the offered fixes of the alternative used, or None.
    """

    accepted: bool
    reason: str
    nis: float = math.nan
    chosen: int | None = None


@dataclass
class _Hypothesis:
    """A fresh filter fed with decoded (or checked) fixes the track rejected."""

    ekf: WalkingEKF
    t0: float
    t: float
    ids: set[int]
    count: int
    own: bool = False  # its first fix came from the track's own anchor (see reinit_own_sticker_s)
    last: int = 0  # which of the last offered alternatives it fused
    checked: bool = False  # some of its fixes were CHECKED (see reinit_checked)


#: One usable fix as the filter takes it: vest pose (3,) (m, m, rad), its covariance (3, 3) SPD, and
#: its sticker's survey error term (None: an exact map).
Alt = tuple[np.ndarray, np.ndarray, MapTerm | None]


class OdometryStepLike(Protocol):
    """A floor-odometry step as the tracker reads it (:class:`tagloc.vision.odometry.OdometryStep`,
    which the tracker's layer cannot import): the vest's pose at ``t1`` (s) in its body frame at
    ``t0`` (s), ``delta`` (3,) (m, m, rad), with covariance ``cov`` (3, 3)."""

    t0: float
    t1: float
    delta: np.ndarray
    cov: np.ndarray


_SOURCES = (IdSource.DECODED, IdSource.CHECKED, IdSource.ORB, IdSource.APPEARANCE)
_ANGLES = (motion.YAW, OFF.stop - 1)  # the state's angles: body yaw, the vest offset's yaw

R = TypeVar("R")


def _checked(step: Callable[[], R]) -> tuple[bool, R | None]:
    """Run a filter step with overflow and invalid results raised: (True, its result), or (False,
    None) when it failed numerically (the one numeric guard; callers decide what failure undoes)."""
    try:
        with np.errstate(over="raise", invalid="raise"):
            return True, step()
    except (FloatingPointError, OverflowError, np.linalg.LinAlgError):
        # OverflowError: Python float arithmetic (a power of a gap of 1e300 s) raises it, not numpy.
        return False, None


# A walker of unknown velocity (init_v_sigma 1 m/s) passes the position cap (pos_var_cap, 1 km sd)
# within 20 minutes: a longer spread changes no variance, and its powers of the interval overflow.
MAX_SPREAD_S = 3600.0


def _nis(y: np.ndarray, S: np.ndarray) -> float:
    """Squared Mahalanobis distance of the residual ``y`` (m,) under the innovation covariance ``S``
    (m, m), symmetrised (raises LinAlgError when singular). A residual too large for floats gives
    inf or NaN, without numpy's overflow warning: every gate accepts only where ``nis <= gate``, which
    refuses it."""
    with np.errstate(over="ignore", invalid="ignore"):
        return float(y @ np.linalg.solve(0.5 * (S + S.T), y))


def _advance_forgetting(
    ekf: WalkingEKF, h_walk: float, h_spread: float | None, h_turn: float | None = None, extra_yaw_psd: float = 0.0
) -> None:
    """Predict ``ekf`` ``h_walk`` s with the walk's own speed and turn rate (and ``extra_yaw_psd``, see
    :meth:`WalkingEKF.advance`), forgetting the turn rate alone after ``h_turn`` s of it (when
    inside, see ``forget_turn_heading_lost``); then, unless ``h_spread`` is None, forget the speed
    and turn rate and let a walker of unknown velocity spread for ``h_spread`` s (at most
    :data:`MAX_SPREAD_S`)."""
    if h_turn is not None and 0.0 < h_turn < h_walk:
        ekf.advance(h_turn, extra_yaw_psd)
        ekf.forget_turn()
        h_walk -= h_turn
    if h_walk > 0.0:
        ekf.advance(h_walk, extra_yaw_psd)
    if h_spread is not None:
        ekf.forget_motion()
        ekf.advance(min(h_spread, MAX_SPREAD_S))


def _pose_unknown(P: np.ndarray, cfg: TrackerConfig) -> np.ndarray:
    """``P`` (DIM, DIM) with the walking body's pose (x, y, yaw) at its caps and uncorrelated: what a
    prediction that failed numerically knows of it (never the covariance from before the gap)."""
    P = P.copy()
    P[:3, :] = 0.0
    P[:, :3] = 0.0
    P[:3, :3] = np.diag([cfg.pos_var_cap, cfg.pos_var_cap, cfg.yaw_var_cap])
    return P


def _time_tol(t: float) -> float:
    """How far apart (s) two frame times near ``t`` may be and still be the same frame's: a
    microsecond (frame times are held to it), and the float rounding of two ways of reaching one
    time there. The rounding was taken as 1e-9 of ``t``, which on an epoch clock (1.8e9 s) is 1.8 s:
    a live run's odometry step from a camera's earlier frame matched its clone of the last frame, and
    was fused over the wrong interval."""
    return 1e-6 + 4.0 * math.ulp(t)


class Tracker:
    """Walking-motion EKF over the body pose (x, y, yaw) fed with sticker pose fixes."""

    def __init__(self, config: TrackerConfig | None = None) -> None:
        self.config = config or TrackerConfig()
        cfg = self.config
        self._gate = {
            IdSource.DECODED: cfg.gate,
            IdSource.CHECKED: cfg.gate,
            IdSource.ORB: cfg.gate_identified,
            IdSource.APPEARANCE: cfg.gate_identified,
        }
        self._ekf = WalkingEKF(cfg)
        self._state = TrackState.INITIALISING
        self._t: float | None = None
        self._last_fix_t = -math.inf
        self._last_id: int | None = None
        self._last_source: IdSource | None = None
        self._track_ids: set[int] = set()  # stickers whose fixes the track took since it (re)started
        self._forgot = False  # speed and yaw rate dropped after a long time without fixes
        self._turn_forgot = False  # yaw rate dropped once the heading was lost
        self._hyp: _Hypothesis | None = None
        # Per camera (key given to predict/update_odometry; None when the caller names none): the
        # odometry pose at that camera's last frame, for its next step.
        self._clones = CloneSet(DIM)
        self._here: set[Hashable] = set()  # cameras whose frames are at the filter's time
        self._clones_dropped_t = -math.inf  # when the clones were last dropped (restart, forgetting)
        self._last_odo_t = -math.inf  # end of the last odometry step fused
        self._blind_widened_t = -math.inf  # end of the last blind span widened (see blind_turn_max_rad)
        # (camera, end time, yaw innovation, gated steps in a row that disagree the same way) of the
        # last odometry step gated, while no step has been fused since (see disagreement_noise).
        self._gated: tuple[Hashable, float, float, int] | None = None
        # (end time, covariance (DIM, DIM) with the gap's yaw noise, the covariance without it) of
        # the last frame gap (see gate_bridge_narrow); the first is the filter's own array, so an
        # update since (the filter replaces its arrays) shows as a different one.
        self._gap: tuple[float, np.ndarray, np.ndarray | None] | None = None
        # The filter (mean, covariance, clones, _last_odo_t) just before the odometry step fused at
        # the filter's current time, while no fix has been fused after it (see overrule_odometry).
        self._before_step: tuple[float, Hashable, np.ndarray, np.ndarray, CloneSet, float] | None = None
        self._last_hyp_choice = 0  # which offered alternative the hypothesis fused last
        # The state covariance (DIM, DIM) as it stood at the filter's previous time, while nothing
        # has been fused at the current one (see search_prior); None otherwise. The filter replaces
        # its arrays rather than writing into them, so keeping the reference keeps the values.
        self._P_before_predict: np.ndarray | None = None
        # (time, odometry pose (3,), clone keys, clone poses (3k,)) as predicted for the filter's
        # current time, before any fix of that frame: where a step's scale column is linearised
        # (see _predicted_step).
        self._step_prediction: tuple[float, np.ndarray, list[Hashable], np.ndarray] | None = None
        self._odo_scale = np.sqrt(np.asarray(cfg.odometry_inflation, float))
        # The last leaned camera made, with its rig camera and roll: the candidates of each
        # detection of a frame, and the region search, ask for the same one.
        self._leaned: tuple[RigCamera, float, RigCamera] | None = None
        # (map, camera, prior bytes, predicted rows) of the last candidates call (see candidates)
        self._predicted: tuple[StickerMap, RigCamera, bytes, tuple[np.ndarray, ...]] | None = None
        self._stats: dict[str, int] = {f"{v}_{s.value}": 0 for s in _SOURCES for v in ("accepted", "rejected")}
        self._stats.update(
            dict.fromkeys(
                (
                    "initialisations",
                    "reinitialisations",
                    "reinit_consistent",
                    "reinit_checked",
                    "reinit_lost",
                    "lost",
                    "ignored_initialising",
                    "ignored_lost",
                    "out_of_order_frames",
                    "out_of_order_fixes",
                    "late_fixes_fused",
                    "invalid_fixes",
                    "invalid_times",
                    "numeric_errors",
                    "odometry_accepted",
                    "odometry_rejected",
                    "odometry_unmatched",
                    "odometry_ignored",
                    "odometry_overruled",
                    "frame_gaps",
                    "missed_steps",
                    "odometry_disagreements",
                    "blind_turn_noise",
                    "odometry_heading_unknown",
                    "odometry_bridge_rejected",
                ),
                0,
            )
        )

    # -- read-only views --------------------------------------------------------------------------
    @property
    def state(self) -> TrackState:
        """Current life-cycle state."""
        return self._state

    @property
    def filter(self) -> WalkingEKF:
        """The underlying filter (state ``x`` (DIM, 1), covariance ``P`` (DIM, DIM)), for inspection."""
        return self._ekf

    @property
    def time(self) -> float | None:
        """Timestamp (s) the filter stands at, None before the first frame."""
        return self._t

    @property
    def odometry_cameras(self) -> tuple[Hashable, ...]:
        """The cameras whose next odometry step the tracker can fuse (each has a clone of the pose at
        its last frame, at most ``odometry_max_dt`` old)."""
        return tuple(self._clones.keys)

    @property
    def stats(self) -> dict[str, int]:
        """Counters: accepted/rejected fixes per source, (re)initialisations, out-of-order, ..."""
        return dict(self._stats)

    def prior(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(mean (3,), cov (3, 3)) of the vest pose (where the rig's cameras are) for choosing
        candidates; None unless TRACKING."""
        if self._state is not TrackState.TRACKING:
            return None
        return vest_pose(self._ekf.x[:, 0]), vest_cov(self._ekf.P)

    def search_prior(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(mean (3,), cov (3, 3)) of the vest pose for where to look for stickers in this frame; None
        unless TRACKING.

        The mean is :meth:`prior`'s, predicted to the filter's time. While nothing has been fused at
        that time (no odometry step ended there yet: ``tagloc live`` fuses a frame's step after
        publishing it), the covariance is the one the filter had at its previous time, without the
        walking model's noise for the frame interval since. That noise is the model's catch-all
        for a walker's changes of speed and heading (a sidestep's white sideways speed alone is
        41 mm over 1/30 s); the region search bounds the image's motion over the interval
        physically instead (``TrackingConfig.search_rate_rad_s``), so counting both gave live's
        search a prior three times as wide as a replay's, whose frame's step is fused first (median
        position sigma 43 against 14 mm on the Speed walk; 13 mm with this one)."""
        if self._state is not TrackState.TRACKING:
            return None
        P = self._ekf.P if self._P_before_predict is None else self._P_before_predict
        return vest_pose(self._ekf.x[:, 0]), vest_cov(P)

    def velocity(self) -> np.ndarray | None:
        """(3,) the body's predicted motion (forward m/s, sideways m/s (0: the model has no sideways
        speed), yaw rate rad/s) in the body frame; None unless TRACKING."""
        if self._state is not TrackState.TRACKING:
            return None
        x = self._ekf.x[:, 0]
        return np.array([float(x[3]), 0.0, float(x[4])])

    def velocity_sigma(self) -> np.ndarray | None:
        """(3,) standard deviations of :meth:`velocity`'s forward speed (m/s), sideways speed (0: the
        model has none) and yaw rate (rad/s); None unless TRACKING. Seconds after the last fix they
        are those of an extrapolation (blind 1 s: 0.6 m/s and 1.2 rad/s)."""
        if self._state is not TrackState.TRACKING:
            return None
        P = self._ekf.P
        return np.sqrt(np.maximum([P[motion.V, motion.V], 0.0, P[motion.W, motion.W]], 0.0))

    def candidates(self, smap: StickerMap, rig_camera: RigCamera, observed_px: np.ndarray, k: int = 5) -> list[int]:
        """Sticker IDs that may be the one seen at ``observed_px``, most likely first ([] unless TRACKING).

        The stickers are projected through the camera as the torso's lean into the turn under way
        tilts it (:meth:`leaned_camera`)."""
        prior = self.prior()
        if prior is None:
            return []
        camera = self.leaned_camera(rig_camera)
        # Every sticker detected under one prior shares the map's projection (on a walk with three
        # stickers in view, 60 % of the calls): kept for the last prior, camera and map, which the
        # entry holds, so neither can be a new object at an old address.
        key = prior[0].tobytes() + prior[1].tobytes()
        hit = self._predicted
        if hit is not None and hit[0] is smap and hit[1] is camera and hit[2] == key:
            predicted = hit[3]
        else:
            predicted = predicted_rows(prior[0], prior[1], smap, camera)
            self._predicted = (smap, camera, key, predicted)
        return gate_candidates(smap, predicted, observed_px, k=k)

    def sticker_pixels(self, smap: StickerMap, rig_camera: RigCamera, sticker_ids: list[int]) -> dict[int, np.ndarray]:
        """Where the centres of the mapped stickers ``sticker_ids`` are predicted in ``rig_camera``'s
        image (distorted px (2,)) from the mean pose, through the leaned camera; {} unless TRACKING.
        Stickers behind the camera or far outside the image, or not in the map, are left out."""
        ids = [i for i in sticker_ids if i in smap]
        if self._state is not TrackState.TRACKING or not ids:
            return {}
        rows = np.array([smap.row(i) for i in ids], np.int64)
        # The mean alone (prior() would also work out the covariance, which a projection does not use).
        kept, pix = centre_pixels(vest_pose(self._ekf.x[:, 0]), smap, self.leaned_camera(rig_camera), rows)
        return {int(smap.ids[r]): p for r, p in zip(kept, pix)}

    def leaned_camera(self, rig_camera: RigCamera) -> RigCamera:
        """``rig_camera`` rolled by the lean the walk's state predicts, atan(v omega / g) into the turn,
        about the vest point (the pose is the vest point's, which the lean does not move). The lean
        with speed changes is not predicted (the state has no acceleration):
        :class:`tracker.candidates.CandidateConfig`'s ``tilt_sigma`` covers it."""
        x = self._ekf.x[:, 0]
        roll = -math.atan(float(x[motion.V] * x[motion.W]) / self.config.gravity)
        if abs(roll) < self.config.lean_min_rad:
            return rig_camera
        last = self._leaned
        if last is not None and last[0] is rig_camera and last[1] == roll:
            return last[2]
        c, s = math.cos(roll), math.sin(roll)
        # The leaned body in the upright one: a roll about the body's x axis through the vest point.
        T_body_leaned = np.eye(4)
        T_body_leaned[1:3, 1:3] = [[c, -s], [s, c]]
        p = rig_camera.vest_point
        T_body_leaned[:3, 3] = p - T_body_leaned[:3, :3] @ p
        leaned = dataclasses.replace(rig_camera, T_body_camera=T_body_leaned @ rig_camera.T_body_camera)
        self._leaned = (rig_camera, roll, leaned)
        return leaned

    # -- time ---------------------------------------------------------------------------------------
    def predict(self, t: float, camera: Hashable = None, odometry: bool = True) -> None:
        """Move the filter to frame time ``t`` (s) of a frame of ``camera`` (a key naming the camera, for
        its odometry, e.g. the rig camera's index; None will do for one camera); an older or non-finite
        ``t`` leaves it unchanged. ``odometry``: the camera's next odometry step starts at this frame
        (its clone is taken here); False for a frame its odometry skips or cannot read, so the next
        step, from the frame before, still finds its clone."""
        t = float(t)
        if not math.isfinite(t):
            self._stats["invalid_times"] += 1
            return
        if self._t is not None and t < self._t:
            self._stats["out_of_order_frames"] += 1
            return
        if self._t is not None and t > self._t:
            if self._state is TrackState.INITIALISING:
                self._drop_clones()
            else:
                # The filter replaces its arrays rather than writing into them: x0, P0 stay as they were.
                t0, x0, P0 = self._t, self._ekf.x[:, 0], self._ekf.P
                self._P_before_predict = P0
                jac: list[np.ndarray] = []
                # A frame gap nothing measured (see gap_yaw_accel_psd): its yaw noise is in the whole
                # prediction, so that it spreads the position through the heading as the gap goes on.
                gap = t - t0 > self.config.gap_s and t0 - self._last_odo_t <= self.config.gap_s
                extra = self.config.gap_yaw_accel_psd if gap else 0.0
                self._stats["frame_gaps"] += gap
                forget_at = self._forget_motion_at(t0, t)
                turn_at = self._forget_turn_at(t0, t if forget_at is None else forget_at, extra)
                if forget_at is not None or turn_at is not None:
                    # The walk is extrapolated until the track goes stale, not across the whole gap
                    # (a clock that jumped hours, or 1e300 s, ahead): then, as _check_lost does,
                    # its speed and turn rate are forgotten and no step from before can be fused.
                    # The turn rate alone is forgotten where the heading is lost within the gap,
                    # and no step is placed through a lost heading either.
                    h_walk = (t if forget_at is None else forget_at) - t0
                    h_spread = None if forget_at is None else t - forget_at
                    h_turn = None if turn_at is None else turn_at - t0
                    if not self._guarded(lambda: _advance_forgetting(self._ekf, h_walk, h_spread, h_turn, extra)):
                        self._ekf.set(self._ekf.mean, _pose_unknown(self._ekf.cov, self.config))
                    self._forgot = self._forgot or forget_at is not None
                    self._turn_forgot = self._turn_forgot or turn_at is not None
                    self._drop_clones()
                elif self._guarded(lambda: jac.append(self._ekf.advance(t - t0, extra))):
                    # The cameras of the frames just left start their next steps here; a clone older
                    # than any step can span is of no more use.
                    self._clones.advance(jac[0], x0, P0, M_ODO, t0, t, self._here, self.config.odometry_max_dt)
                    self._gap = (t, self._ekf.P, self._narrow(x0, P0, t - t0)) if gap else None
                    self._step_prediction = (
                        t,
                        odometry_pose(self._ekf.x[:, 0]),
                        list(self._clones.keys),
                        self._clones.x.copy(),
                    )
                else:
                    self._drop_clones()
                if (
                    not gap
                    and self.config.missed_step_noise
                    and self._here
                    and 0.0 < t0 - self._last_odo_t <= self.config.odometry_max_dt
                ):
                    # The last frame's step was wanted and none ended there (see missed_step_noise).
                    self._missed_step_noise(t - t0)
            self._here = set()
            self._before_step = None
        if odometry:
            self._here.add(camera)
        self._t = t
        self._check_lost()

    def _forget_motion_at(self, t0: float, t: float) -> float | None:
        """When, within a prediction from ``t0`` to ``t``, the speed and turn rate are to be forgotten
        (``lost_after_s`` after the last fix), or None: not in this interval. A track that forgot them
        already forgets them again from ``t0`` when the gap alone outlasts ``lost_after_s``."""
        stale_at = self._last_fix_t + self.config.lost_after_s
        if not self._forgot and math.isfinite(stale_at) and t > stale_at:
            return max(t0, stale_at)
        if self._forgot and t - t0 > self.config.lost_after_s:
            return t0
        return None

    def _forget_turn_at(self, t0: float, t: float, extra_yaw_psd: float = 0.0) -> float | None:
        """When, strictly within a prediction from ``t0`` to ``t``, a lost track's heading sigma passes
        ``odometry_max_yaw_sd`` (at the end of one of the filter's ``max_step_s`` steps), or None:
        not in this interval (the end of an interval is :meth:`_check_lost`'s). One long prediction
        (a camera that stalled, an output asked for ahead) otherwise carried the turn on to its end
        (see ``forget_turn_heading_lost``)."""
        cfg = self.config
        if not cfg.forget_turn_heading_lost or self._turn_forgot or t - t0 <= cfg.max_step_s:
            return None
        ekf = WalkingEKF(cfg)
        ekf.set(self._ekf.mean, self._ekf.cov)
        tk = t0
        # The filter's own steps (WalkingEKF.advance), so the real prediction passes the same points.
        for _ in range(cfg.max_steps - 1):
            tk += cfg.max_step_s
            if tk >= t or not _checked(lambda: ekf.advance(cfg.max_step_s, extra_yaw_psd))[0]:
                return None
            P = ekf.cov
            if (self._state is TrackState.LOST or self._is_lost(P, tk)) and self._heading_lost(P):
                return tk
        return None

    def _drop_clones(self) -> None:
        """Forget every camera's clone: the track restarted or forgot its past, so no step from before
        now can be fused (such steps are counted as ``odometry_ignored``, not unmatched)."""
        self._clones.clear()
        if self._t is not None:
            self._clones_dropped_t = self._t
        # Nor can a fix overrule a step of the track that was: its state before the step is history.
        self._before_step = None

    def _narrow(self, x0: np.ndarray, P0: np.ndarray, dt: float) -> np.ndarray | None:
        """The covariance (DIM, DIM) of the walk predicted ``dt`` s from (``x0``, ``P0``) by the walking
        model alone, without a gap's yaw noise (see ``gate_bridge_narrow``); None when off or it
        failed numerically."""
        if not self.config.gate_bridge_narrow:
            return None
        ekf = WalkingEKF(self.config)
        ekf.set(x0, P0)
        ok, _ = _checked(lambda: ekf.advance(dt))
        return ekf.cov if ok else None

    def _missed_step_noise(self, dt: float) -> bool:
        """Widen yaw and yaw rate after a frame interval of ``dt`` s whose odometry step was wanted and
        none came (see ``missed_step_noise``); False when the filter refused it.

        The noise is independent of the state before the interval, so a clone's cross-covariance
        stands."""
        q = self.config.gap_yaw_accel_psd
        # Beyond lost_after_s the track is lost and its motion forgotten (_check_lost), and the
        # variances are capped anyway: a longer gap (a clock that jumped) adds nothing but overflow.
        dt = min(dt, self.config.lost_after_s)
        self._stats["missed_steps"] += 1
        return self._add_yaw_noise(q, dt)

    def _add_yaw_noise(self, q: float, dt: float) -> bool:
        """Add ``dt`` s of white yaw acceleration of PSD ``q`` (rad^2/s^3) to the yaw and yaw rate (the
        walking model's blocks, :func:`tracker.motion.process_noise`); False when the filter refused
        it."""
        P = self._ekf.P.copy()
        yaw, w = motion.YAW, motion.W
        # The blocks of motion.process_noise, written out: the same sums in another order round
        # differently in the last bit, and that alone moved f01 at 15 fps from 5.5 to 12.9 cm.
        P[yaw, yaw] += q * dt**3 / 3.0
        P[yaw, w] += q * dt**2 / 2.0
        P[w, yaw] += q * dt**2 / 2.0
        P[w, w] += q * dt
        return self._guarded(lambda: self._ekf.set(self._ekf.x[:, 0], P))

    def _blind_turn_noise(self, camera: Hashable, t0: float) -> None:
        """Before the first step after a span nothing measured (no step, no fix, longer than
        ``gap_s``), widen the heading of the state and of ``camera``'s clone at ``t0`` together by
        the turn a person can make in the span beyond the walking model's (see
        ``blind_turn_max_rad``)."""
        cfg = self.config
        # A gated step leaves _last_odo_t where it was: the span it widened must not be widened again.
        span = t0 - max(self._last_odo_t, self._last_fix_t, self._blind_widened_t)
        if cfg.blind_turn_max_rad <= 0.0 or not span > cfg.gap_s or not math.isfinite(span):
            return
        q = (cfg.turn_peak_accel / cfg.turn_peak_sigmas) ** 2 * span
        var = min(q * span**3 / 12.0, cfg.blind_turn_max_rad**2)
        x8 = self._ekf.x[:, 0]
        xj, Pj = self._clones.joint(x8, self._ekf.P)
        u = np.zeros(len(xj))
        u[motion.YAW] = 1.0
        u[DIM + 3 * self._clones.keys.index(camera) + 2] = 1.0
        Pj = Pj + var * np.outer(u, u)
        if self._guarded(lambda: self._ekf.set(x8, Pj[:DIM, :DIM])):
            self._clones.absorb(xj, Pj)
            self._stats["blind_turn_noise"] += 1
            self._blind_widened_t = t0

    def _turn_noise(self, dt: float) -> None:
        """Widen yaw and yaw rate for an interval of ``dt`` s that an odometry step measures, by the yaw
        acceleration the walking model leaves out there (see ``turn_peak_accel``). The noise is
        independent of the state at the interval's start, so the step's clone keeps its
        cross-covariance."""
        cfg = self.config
        q = (cfg.turn_peak_accel / cfg.turn_peak_sigmas) ** 2 * dt - cfg.yaw_accel_psd
        if q > 0.0:
            self._add_yaw_noise(q, dt)

    def _disagreement(self, camera: Hashable, t0: float, t1: float, e_yaw: float) -> None:
        """A gated odometry step of ``camera`` over ``t0``-``t1`` whose turn differs by ``e_yaw`` (rad)
        from the filter's (see ``disagreement_noise``)."""
        prev = self._gated
        if prev is None or prev[0] != camera or abs(prev[1] - t0) > _time_tol(t0) or prev[2] * e_yaw <= 0.0:
            self._gated = (camera, t1, e_yaw, 1)
            return
        self._gated = (camera, t1, e_yaw, prev[3] + 1)
        if not self.config.disagreement_noise:
            return
        # The second step of a run vouches for the first: the turn of both went missing.
        m = abs(e_yaw) + (abs(prev[2]) if prev[3] == 1 else 0.0)
        P = self._ekf.P.copy()
        # The missed turn adds up step by step (it is one error, not independent ones): the yaw
        # sigma grows by it, and the yaw rate is uncertain by this step's disagreement over its interval.
        P[motion.YAW, motion.YAW] = (math.sqrt(P[motion.YAW, motion.YAW]) + m) ** 2
        P[motion.W, motion.W] += (abs(e_yaw) / (t1 - t0)) ** 2
        self._guarded(lambda: self._ekf.set(self._ekf.x[:, 0], P))
        self._stats["odometry_disagreements"] += 1

    def _check_lost(self) -> None:
        if self._state is TrackState.TRACKING and self._is_lost(self._ekf.cov, self._t):
            self._state = TrackState.LOST
            self._stats["lost"] += 1
        if (
            self._state is TrackState.LOST
            and self.config.forget_turn_heading_lost
            and not self._turn_forgot
            and self._heading_lost()
        ):
            # See TrackerConfig.forget_turn_heading_lost.
            self._turn_forgot = True
            if self._guarded(self._ekf.forget_turn):
                # The new yaw rate is independent of the past, so of the clones too: their kept
                # cross-covariance with the old one would make the joint covariance indefinite.
                self._clones.decorrelate(slice(motion.W, motion.W + 1))
        stale = self._t - self._last_fix_t > self.config.lost_after_s
        if self._state is TrackState.LOST and stale and not self._forgot:
            # Long without a fix, the speed and turn rate are stale: keep the pose mean and let a
            # walker of unknown velocity spread from there instead of extrapolating for hours.
            self._forgot = True
            self._drop_clones()
            self._guarded(self._ekf.forget_motion)

    def _heading_lost(self, P: np.ndarray | None = None) -> bool:
        """The heading's sigma (in ``P`` (DIM, DIM), default the filter's) is past
        ``odometry_max_yaw_sd``: nothing placed through it means much."""
        P = self._ekf.P if P is None else P
        return P[motion.YAW, motion.YAW] > self.config.odometry_max_yaw_sd**2

    def _is_lost(self, P: np.ndarray, t: float) -> bool:
        sigma = math.sqrt(max(largest_eig_2x2(P), 0.0))
        return sigma > self.config.lost_sigma_m or t - self._last_fix_t > self.config.lost_after_s

    def _guarded(self, step: Callable[[], object]) -> bool:
        """Run a filter step; on a numerical failure restore the state before it, count it, return False."""
        x, P = self._ekf.x[:, 0].copy(), self._ekf.P
        ok, _ = _checked(step)
        if not ok:
            self._stats["numeric_errors"] += 1
            self._ekf.set(x, P)
        return ok

    # -- fixes --------------------------------------------------------------------------------------
    def _clean(self, fixes: list[PoseFix], sticker_id: int, survey: SurveyPrior | None) -> tuple[list[Alt], list[int]]:
        """(body (3,), cov (3, 3) SPD, map term or None) of the usable fixes, in the order given, and
        each one's index among ``fixes`` (what :attr:`UpdateResult.chosen` reports)."""
        out, where = [], []
        for i, f in enumerate(fixes):
            z = np.asarray(f.body, float).ravel()
            C = np.asarray(f.cov, float)
            if z.shape != (3,) or C.shape != (3, 3) or not (np.all(np.isfinite(z)) and np.all(np.isfinite(C))):
                continue
            # Absurd magnitudes come from a solver blow-up, not from a sticker: refuse them.
            if np.abs(C).max() > self.config.fix_max_cov or np.abs(z[:2]).max() > self.config.fix_max_xy_m:
                continue
            z = z.copy()
            z[2] = wrap_angle(float(z[2]))
            term = None
            if survey is not None and (survey.sigma_m > 0 or survey.sigma_yaw > 0):
                prior = np.diag([survey.sigma_m**2, survey.sigma_m**2, survey.sigma_yaw**2])
                term = MapTerm(int(sticker_id), map_error_jacobian(z[:2], survey.sticker_xy), prior)
            out.append((z, sym_spd(C, self.config.min_eig), term))
            where.append(i)
        return out, where

    def update(
        self,
        fixes: list[PoseFix],
        sticker_id: int,
        source: IdSource,
        t: float,
        survey: SurveyPrior | None = None,
        row_time_s: float = 0.0,
    ) -> UpdateResult:
        """Offer one sticker's pose fix(es) (1, or 2 IPPE alternatives best first) seen at frame time ``t``.

        ``survey``: the sticker's map position and survey sigmas; its survey error then becomes a
        state while the sticker is being fixed (see :mod:`tracker.ekf`). None: the map is exact (or
        the fixes' covariances already carry it). ``row_time_s``: the fixes hold this long after
        ``t`` (a rolling shutter's sticker rows, :attr:`tagloc.vision.pose.PoseSolution.row_time_s`);
        the filter itself stays at the frame's time.
        """
        source = IdSource(source)
        t = float(t)
        if not math.isfinite(t):
            self._stats["invalid_times"] += 1
            return UpdateResult(False, "invalid timestamp")
        if source is IdSource.NONE:
            return UpdateResult(False, "unidentified sticker")
        alts, where = self._clean(fixes, sticker_id, survey)
        if not alts:
            self._stats["invalid_fixes"] += 1
            return UpdateResult(False, "no usable fix (empty, NaN or malformed)")
        if self._t is None or t > self._t:
            self.predict(t)
        late = self._t - t
        if late > self.config.max_lag_s:
            self._stats["out_of_order_fixes"] += 1
            return UpdateResult(False, f"out of order: frame {late:.3f} s older than the filter")
        row_time_s = float(row_time_s) if math.isfinite(row_time_s) else 0.0
        lag = late - row_time_s  # negative: the sticker's rows were read after the filter's time

        early = self._without_track(alts, sticker_id, source, t, lag)
        if early is not None:
            return dataclasses.replace(early, chosen=where[early.chosen]) if early.chosen is not None else early

        k, nis = self._best(alts, lag)
        k, nis, how = self._overrule_step(alts, lag, source, k, nis)
        if nis <= self._gate[source]:
            self._before_step = None
            self._fuse(alts[k], lag)
            if late > 0.0:
                self._stats["late_fixes_fused"] += 1
            self._accept(sticker_id, source, t)
            if source is IdSource.DECODED:
                self._hyp = None
            return UpdateResult(True, how, nis, where[k])

        reason = f"gated: NIS {nis:.1f} > {self._gate[source]:.1f}"
        if source is IdSource.DECODED and self._state is TrackState.LOST:
            self._start(alts[0], sticker_id, source, t, lag)
            self._stats["reinitialisations"] += 1
            self._stats["reinit_lost"] += 1
            return UpdateResult(True, f"reinitialised (lost, {reason})", nis, where[0])
        if self._feeds_hypothesis(source) and self._feed_hypothesis(alts, sticker_id, source, t):
            return UpdateResult(
                True,
                f"reinitialised: {self.config.reinit_fixes} consistent decoded or checked fixes "
                f"disagreed with the track ({reason})",
                nis,
                where[self._last_hyp_choice],
            )
        self._stats[f"rejected_{source.value}"] += 1
        return UpdateResult(False, reason, nis, where[k])

    def _without_track(
        self, alts: list[Alt], sticker_id: int, source: IdSource, t: float, lag: float
    ) -> UpdateResult | None:
        """What becomes of a fix while there is no track to gate it against (initialising: a decoded
        one starts it; lost: only decoded ones are taken, and one starts it afresh while the heading is
        unknown), or None when there is a track."""
        if self._state is TrackState.INITIALISING:
            if source is not IdSource.DECODED:
                self._stats["ignored_initialising"] += 1
                return UpdateResult(False, "initialising: only a decoded sticker starts the track")
            self._start(alts[0], sticker_id, source, t, lag)
            self._stats["initialisations"] += 1
            return UpdateResult(True, "initialised", chosen=0)
        if self._state is TrackState.LOST and source is not IdSource.DECODED:
            self._stats["ignored_lost"] += 1
            return UpdateResult(False, "lost: only decoded stickers are taken")
        if self._state is TrackState.LOST and self._ekf.P[motion.YAW, motion.YAW] >= self.config.yaw_var_cap:
            # The heading is at its cap (uniform): a late fix's retrodiction, linearised at that
            # meaningless mean, would put the walk since the fix along the wrong direction (a fix
            # 0.2 s late, 2 rad off the old mean: the next frame's stated sigma shrank, 20 -> 18 cm,
            # against 40 cm of error). Started from the fix, the lag is walked at its own heading.
            self._start(alts[0], sticker_id, source, t, lag)
            self._stats["reinitialisations"] += 1
            self._stats["reinit_lost"] += 1
            return UpdateResult(True, "reinitialised (lost, heading unknown)", chosen=0)
        return None

    def _overrule_step(
        self, alts: list[Alt], lag: float, source: IdSource, k: int, nis: float
    ) -> tuple[int, float, str]:
        """A decoded (or checked) fix that the gate refuses right after this frame's odometry step, but
        that passes against the filter before that step, overrules the step: the filter goes back to
        before it.
        Returns (best alternative, its NIS, how it is fused if it passes) (see ``overrule_odometry``)."""
        b = self._before_step
        if nis <= self._gate[source] or source not in (IdSource.DECODED, IdSource.CHECKED):
            return k, nis, "fused"
        if not self.config.overrule_odometry or b is None or b[0] != self._t:
            return k, nis, "fused"
        _, camera, mean, cov, clones, last_odo_t = b
        after = (self._ekf.x, self._ekf.P)
        self._ekf.x, self._ekf.P = mean.reshape(-1, 1), cov
        k0, nis0 = self._best(alts, lag)
        if not nis0 <= self._gate[IdSource.DECODED]:
            self._ekf.x, self._ekf.P = after
            return k, nis, "fused"
        # The step's interval is spent either way: its camera's next step starts at this frame.
        self._clones = clones
        self._clones.drop(camera)
        self._last_odo_t = last_odo_t
        self._before_step = None
        self._stats["odometry_overruled"] += 1
        return k0, nis0, f"fused (NIS {nis:.1f} after this frame's odometry step, which it overruled)"

    def _best(self, alts: list[Alt], lag: float) -> tuple[int, float]:
        """Index and NIS of the alternative closest to the prediction."""
        best = (0, math.inf)
        for i, (z, C, term) in enumerate(alts):
            try:
                nis = self._ekf.innovation(z, C, lag, term).nis
            except np.linalg.LinAlgError:
                self._stats["numeric_errors"] += 1
                continue
            if nis < best[1]:
                best = (i, nis)
        return best

    def _fuse(self, alt: Alt, lag: float) -> None:
        """Fuse an accepted fix (vest pose, own covariance, map term); a late one through retrodiction."""
        z, C, term = alt
        if term is not None:
            # The sticker's survey error takes its slot first: a new sticker's is a fresh state,
            # independent of everything, clones included; then the fix is a pure conditioning,
            # which the clones follow exactly.
            k, fresh = self._ekf.claim_slot(term)
            if fresh:
                self._clones.decorrelate(map_slot(k))
        x0, P0 = self._ekf.x[:, 0], self._ekf.P
        self._P_before_predict = None
        if self._guarded(lambda: self._ekf.fuse(z, C, lag, term)):
            # The odometry clones follow the fix (see tracker.clones).
            if not self._clones.carry(x0, P0, self._ekf.x[:, 0], self._ekf.P, _ANGLES, self.config.min_eig):
                self._stats["numeric_errors"] += 1

    def _accept(self, sticker_id: int, source: IdSource, t: float) -> None:
        self._stats[f"accepted_{source.value}"] += 1
        self._track_ids.add(int(sticker_id))
        self._last_fix_t = max(self._last_fix_t, t)
        self._last_id, self._last_source = int(sticker_id), source
        # A fix vaguer than lost_sigma_m (a far sticker's, or one fused into a track hours lost)
        # leaves the pose as uncertain as LOST means: TRACKING would hand its prior to candidate
        # selection and take ORB/appearance picks (a neighbour one spacing away) through their gate.
        lost = self._is_lost(self._ekf.P, self._t if self._t is not None else t)
        if lost and self._state is not TrackState.LOST:
            self._stats["lost"] += 1
        self._state = TrackState.LOST if lost else TrackState.TRACKING
        self._forgot = False
        self._turn_forgot = False

    def _start(
        self,
        alt: Alt,
        sticker_id: int,
        source: IdSource,
        t: float,
        lag: float = 0.0,
    ) -> None:
        """(Re)start the track from one fix, ``lag`` s older than the filter's time: pose from it, speed
        and yaw rate unknown, predicted over the lag (a late fix's pose is where the operator was)."""
        self._hyp = None
        self._drop_clones()
        ekf = self._new_filter(alt)
        if lag > 0.0 and not _checked(lambda: ekf.advance(lag))[0]:
            self._stats["numeric_errors"] += 1
        self._ekf = ekf
        self._P_before_predict = None
        # A fresh track: its sticker set and last-fix time start from this fix alone.
        self._track_ids = set()
        self._last_fix_t = -math.inf
        self._accept(sticker_id, source, t)

    def _new_filter(self, alt: Alt) -> WalkingEKF:
        """A filter started from one fix; its odometry scale error is the current track's (the same
        vest on the same operator), 0 before the first track."""
        scale = 0.0 if self._state is TrackState.INITIALISING else self._ekf.odometry_scale()
        ekf = WalkingEKF(self.config)
        ekf.reset_from_fix(*alt, scale=scale)
        return ekf

    def _feeds_hypothesis(self, source: IdSource) -> bool:
        """Whether a gated-out fix of ``source`` joins the competing hypothesis (see ``reinit_checked``)."""
        return source is IdSource.DECODED or (source is IdSource.CHECKED and self.config.reinit_checked)

    def _feed_hypothesis(self, alts: list[Alt], sticker_id: int, source: IdSource, t: float) -> bool:
        """Add a rejected decoded (or checked) fix to the competing hypothesis; True when it replaced
        the track."""
        cfg = self.config
        h = self._hyp
        # A fix a little older than the hypothesis (another camera's frame, within max_lag_s) extends it.
        if h is not None and (t < h.t - cfg.max_lag_s or t - h.t0 > cfg.reinit_window_s):
            h = None
        if h is not None:
            ok, fused = _checked(lambda: self._extend_hypothesis(h, alts, sticker_id, t))
            self._stats["numeric_errors"] += not ok
            if not fused:
                h = None
        if h is None:
            own = self._last_id == int(sticker_id) and t - self._last_fix_t <= cfg.reinit_own_sticker_s
            h = _Hypothesis(self._new_filter(alts[0]), t, t, {int(sticker_id)}, 1, own)
        h.checked |= source is IdSource.CHECKED
        self._hyp = h
        # Several stickers are needed to overrule a track that other stickers support; a track that
        # rests only on stickers now disagreeing with it (one just after it started, say, when a
        # bad odometry step moved it), or whose own anchor of a moment ago now disagrees with it
        # while nothing else supports it, has nothing else to defend.
        unsupported = self._track_ids <= h.ids or (h.own and self._last_fix_t < h.t0)
        self._last_hyp_choice = h.last
        if h.count < cfg.reinit_fixes or (len(h.ids) < cfg.reinit_min_ids and not unsupported):
            return False
        # The hypothesis stands at its last fix's time; the track it replaces, at the filter's.
        if self._t is not None and self._t > h.t and not _checked(lambda: h.ekf.advance(self._t - h.t))[0]:
            self._stats["numeric_errors"] += 1
        self._ekf = h.ekf
        self._hyp = None
        self._P_before_predict = None
        self._drop_clones()
        self._track_ids = set(h.ids)
        self._accept(sticker_id, source, t)
        self._stats["reinitialisations"] += 1
        self._stats["reinit_consistent"] += 1
        self._stats["reinit_checked"] += h.checked
        return True

    def _extend_hypothesis(self, h: _Hypothesis, alts: list[Alt], sticker_id: int, t: float) -> bool:
        """Fuse the best of ``alts`` into the hypothesis if it passes its gate; False if none does. A fix
        older than the hypothesis (within ``max_lag_s``) is fused through retrodiction."""
        lag = 0.0
        if t >= h.t:
            h.ekf.advance(t - h.t)
            h.t = t
        else:
            lag = h.t - t
        nis, i = min((h.ekf.innovation(z, C, lag, term).nis, i) for i, (z, C, term) in enumerate(alts))
        if not nis <= self.config.gate:  # NaN included
            return False
        z, C, term = alts[i]
        h.ekf.fuse(z, C, lag, term)
        h.ids.add(int(sticker_id))
        h.count += 1
        h.last = i
        return True

    # -- odometry ---------------------------------------------------------------------------------
    def update_odometry(self, step: OdometryStepLike, camera: Hashable = None) -> UpdateResult:
        """Fuse one floor-odometry step (:class:`tagloc.vision.odometry.OdometryStep`) of ``camera`` (the
        key given to :meth:`predict`): the body pose at ``step.t1`` relative to ``step.t0`` (``delta``
        (3,) in the body frame at ``t0``, ``cov`` (3, 3)).

        The filter is moved to ``t1`` if it is behind. The step must start at the camera's previous
        frame (its clone) and end at the filter's time; fixes fused in between do not matter (the
        scale is linearised at the filter's prediction for ``t1``, see :meth:`_predicted_step`).
        """
        cfg = self.config
        z = np.asarray(step.delta, float).ravel()
        C = np.asarray(step.cov, float)
        t0, t1 = float(step.t0), float(step.t1)
        if (
            z.shape != (3,)
            or C.shape != (3, 3)
            or not (np.all(np.isfinite(z)) and np.all(np.isfinite(C)))
            or not (math.isfinite(t0) and math.isfinite(t1))
            or not 0.0 < t1 - t0 <= cfg.odometry_max_dt
        ):
            self._stats["invalid_fixes"] += 1
            return UpdateResult(False, "unusable odometry step (malformed, NaN, or bad interval)")
        if self._state is TrackState.INITIALISING:
            self._stats["odometry_ignored"] += 1
            return UpdateResult(False, "initialising: odometry needs a pose to move")
        if self._t is None or t1 > self._t:
            self.predict(t1, camera)
        if self._heading_lost():
            # Its direction on the map is unknown (see TrackerConfig.odometry_max_yaw_sd).
            self._stats["odometry_heading_unknown"] += 1
            return UpdateResult(False, "heading too uncertain to place the step on the map")
        t_clone = self._clones.time(camera)
        tol = _time_tol(t1)
        if t_clone is None and t0 <= self._clones_dropped_t + tol:
            self._stats["odometry_ignored"] += 1
            return UpdateResult(False, "the track restarted after the step's first frame")
        if t_clone is None or abs(t_clone - t0) > tol or abs(self._t - t1) > tol:
            self._stats["odometry_unmatched"] += 1
            return UpdateResult(False, "odometry interval does not match the camera's last frame")
        self._blind_turn_noise(camera, t0)
        if t1 - t0 <= cfg.gap_s:
            self._turn_noise(t1 - t0)
        x8 = self._ekf.x[:, 0]
        n = DIM
        # Joint state [x (DIM), clones (3 each)]; the measurement is the odometry pose (the vest's,
        # plus the tilt offset that the odometry's fixed homography adds) at t1 seen from this
        # camera's clone. The other cameras' clones ride along, so their covariances stay exact.
        x, P = self._clones.joint(x8, self._ekf.P)
        P = sym_spd(P, cfg.min_eig)  # the caps applied while advancing may have bent it slightly
        a = n + 3 * self._clones.keys.index(camera)
        hx, H3 = odometry_model(x8, x[a : a + 3], self._predicted_step(camera, t1))
        H = np.zeros((3, len(x)))
        H[:, :n] = H3[:, :n]
        H[:, a : a + 3] = H3[:, n:]
        R = sym_spd(C * np.outer(self._odo_scale, self._odo_scale), cfg.min_eig)
        y = pose_residual(z, hx)
        S = H @ P @ H.T + R
        try:
            nis = _nis(y, S)
        except np.linalg.LinAlgError:
            self._stats["numeric_errors"] += 1
            return UpdateResult(False, "singular odometry innovation")
        if not nis <= cfg.gate_odometry:
            self._stats["odometry_rejected"] += 1
            self._disagreement(camera, t0, t1, float(y[2]))
            return UpdateResult(False, f"odometry gated: NIS {nis:.1f} > {cfg.gate_odometry:.1f}", nis)
        narrow = self._bridge_nis(x8, y, H, R, t1)
        if narrow is not None and not narrow <= cfg.gate_odometry:
            # See TrackerConfig.gate_bridge_narrow.
            self._stats["odometry_bridge_rejected"] += 1
            return UpdateResult(
                False, f"bridged step gated by the walk: NIS {narrow:.1f} > {cfg.gate_odometry:.1f}", nis
            )

        def fuse() -> None:
            # filterpy's functional update is the linear one (residual z - H x): hand it the
            # measurement whose linear residual is our (wrapped) nonlinear one.
            xa, Pa = kf_update(x, P, H @ x + y, R, H)
            xa = np.asarray(xa, float).ravel()
            self._ekf.set(xa[:n], 0.5 * (Pa[:n, :n] + Pa[:n, :n].T))
            self._clones.absorb(xa, Pa)

        # The filter before the step: restored if the fusion fails, and kept for a fix of this frame
        # that may overrule the step (see overrule_odometry).
        before = (self._t, camera, self._ekf.mean, self._ekf.cov, self._clones.copy(), self._last_odo_t)
        if not self._guarded(fuse):
            self._clones = before[4]
            return UpdateResult(False, "numerical failure fusing odometry", nis)
        # One step per interval: a second one would reuse the same frames.
        self._clones.drop(camera)
        self._stats["odometry_accepted"] += 1
        self._P_before_predict = None
        self._last_odo_t = t1
        self._gated = None
        self._before_step = before
        return UpdateResult(True, "fused", nis)

    def _bridge_nis(self, x8: np.ndarray, y: np.ndarray, H: np.ndarray, R: np.ndarray, t1: float) -> float | None:
        """The NIS of a step ending at ``t1`` (residual ``y`` (3,), Jacobian ``H``, noise ``R``) against
        the filter without the yaw noise of the frame gap it bridges (see ``gate_bridge_narrow``);
        None when it bridges no gap, or the covariance changed since the gap's noise was added."""
        gap = self._gap
        if gap is None or gap[2] is None or abs(gap[0] - t1) > _time_tol(t1):
            return None
        if gap[1] is not self._ekf.P:
            return None
        P = sym_spd(self._clones.joint(x8, gap[2])[1], self.config.min_eig)
        try:
            return _nis(y, H @ P @ H.T + R)
        except np.linalg.LinAlgError:
            return None

    def _predicted_step(self, camera: Hashable, t1: float) -> np.ndarray | None:
        """The odometry step (dx, dy) (2,) m of ``camera`` from its clone to ``t1`` as the filter
        predicted it for ``t1``, before any fix of that frame was fused; None without a prediction
        for ``t1`` or a clone of ``camera`` in it.

        The scale error's column of the step's Jacobian is the true step, and the step the state
        implies is its estimate. A fix of the same frame fused before the step (live's order:
        ``LocaliserConfig.defer_odometry``) moves that estimate with part of its own noise, by
        millimetres against steps of 5-40 mm, and the step's residual then moves the opposite way
        by the same noise: their product pulls the scale low on every step (errors in variables; on the
        standard walk s01 it learnt -0.6 % against +0.4 % in a replay's order, and drifted 5 cm
        between stickers). The prediction holds no noise of that frame, so the scale is
        linearised there, in either order (a first-estimate Jacobian); the residual is still the
        state's own."""
        pred = self._step_prediction
        if pred is None or abs(pred[0] - t1) > _time_tol(t1) or camera not in pred[2]:
            return None
        _, v1, keys, clones = pred
        c = clones[3 * keys.index(camera) :][:3]
        co, si = math.cos(c[2]), math.sin(c[2])
        d = v1[:2] - c[:2]
        return np.array([co * d[0] + si * d[1], -si * d[0] + co * d[1]])

    # -- output -------------------------------------------------------------------------------------
    def output(self, t: float | None = None) -> TrackerOutput:
        """The operator's pose at ``t`` (default: the filter's time) without changing the filter.

        The pose is the vest's (body + offset): the vest point on the floor, where the operator is,
        moving with the torso's sway (see :mod:`tracker.config`).

        ``t`` earlier than the filter's time (or non-finite) gives the latest estimate, stamped with
        the filter's time. Pose zeros and a huge covariance while initialising. Never NaN.
        """
        cfg = self.config
        now = self._t if self._t is not None else 0.0
        if t is not None and math.isfinite(float(t)) and float(t) > now:
            target = float(t)
        else:
            target = now
        since = target - self._last_fix_t if math.isfinite(self._last_fix_t) else math.inf
        if self._state is TrackState.INITIALISING:
            cov = np.diag([cfg.pos_var_cap, cfg.pos_var_cap, cfg.yaw_var_cap])
            return TrackerOutput(target, np.zeros(3), cov, TrackState.INITIALISING, since)
        state = self._state
        if target > now:
            ekf = WalkingEKF(cfg)
            ekf.set(self._ekf.mean, self._ekf.cov)
            forget_at = self._forget_motion_at(now, target)
            end = target if forget_at is None else forget_at
            turn_at = self._forget_turn_at(now, end)
            h_spread = None if forget_at is None else target - forget_at
            h_turn = None if turn_at is None else turn_at - now
            ok = _checked(lambda: _advance_forgetting(ekf, end - now, h_spread, h_turn))[0]
            if not ok:
                # Never the pose of ``now`` stamped ``target`` as if known as well: nothing is known.
                ekf.set(self._ekf.mean, _pose_unknown(self._ekf.cov, cfg))
            x, P = ekf.mean, ekf.cov
            if state is TrackState.TRACKING and self._is_lost(P, target):
                state = TrackState.LOST
        else:
            x, P = self._ekf.x[:, 0], self._ekf.P
        # The operator is where the vest is: the smooth walk plus the torso's sway on it (the offset).
        pose = vest_pose(x)
        pose[2] = wrap_angle(float(pose[2]))
        cov = sym_spd(vest_cov(P), cfg.min_eig)
        if cfg.heading_widening:
            cov = heading_widened(cov)
        # The body's caps hold for the sum too (scaling rows and columns alike keeps it SPD).
        caps = np.array([cfg.pos_var_cap, cfg.pos_var_cap, cfg.yaw_var_cap])
        if (cov.diagonal() > caps).any():
            d = np.sqrt(np.minimum(1.0, caps / cov.diagonal()))
            cov = cov * np.outer(d, d)
        return TrackerOutput(target, pose, cov, state, since, self._last_id, self._last_source)
