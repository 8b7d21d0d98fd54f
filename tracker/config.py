"""The tracker's configuration: walking-motion noise, vest offset, gates and life-cycle limits.

Every number below is chosen by reasoning about a person walking in a warehouse with a camera on a
vest, not by fitting a test. Units: metres, seconds, radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from functools import lru_cache

import numpy as np

from tagloc.core.errors import InputError


@lru_cache(maxsize=64)
def chi2_bound(prob: float, dof: int) -> float:
    """The chi-square quantile ``prob`` for ``dof`` degrees of freedom (cached: scipy takes ~0.2 ms).

    scipy.special's inverse of the complemented chi-square CDF gives what scipy.stats.chi2.ppf does,
    without importing scipy.stats (0.8 s of start-up)."""
    from scipy.special import chdtri

    return float(chdtri(dof, 1.0 - prob))


#: Fields of :class:`TrackerConfig` that may be negative (every other number must be >= 0).
_MAY_BE_NEGATIVE = frozenset({"v_min"})


@dataclass
class TrackerConfig:
    """Choices of the walking-motion EKF (:class:`tracker.tracker.Tracker`).

    Motion noise (continuous-time white-noise power spectral densities of the CTRV model in
    :mod:`tracker.motion`):

    - ``accel_psd`` (m^2/s^3), longitudinal acceleration. Over 1 s the speed spreads by
      sqrt(0.3) = 0.55 m/s and the position by sqrt(0.3/3) = 0.32 m. A hard stop from 1.4 m/s at
      1.4 m/s^2 (the 1-2 m/s^2 people stop and start with) leaves the walker 0.7 m behind the
      constant-velocity prediction after 1 s: 2.2 sigma, well inside the gate, so fixes after a stop
      are not thrown away, while steady walking (speed changes of ~0.1 m/s per step) stays sharp.
    - ``yaw_accel_psd`` (rad^2/s^3), yaw acceleration. 0.5 spreads the yaw rate by 0.7 rad/s per
      second, so a corner taken while walking (~1.5 rad/s built up over ~1 s) is a 2-sigma event.
      Spinning on the spot (3 rad/s within 0.5 s, 0.75 rad off after 0.5 s) is beyond it on
      purpose: a model wide enough for spins would leave the heading +-0.5 rad half a second after
      every fix (position +-0.5 m at walking speed) and the prior useless for candidates. Fixes
      after such a spin fail the gate and the track recovers by re-initialisation (below).
    - ``turn_peak_accel``, ``turn_peak_sigmas``: over the interval of an odometry step (up to
      ``gap_s``), the yaw acceleration noise is raised so that the peak yaw acceleration of a brisk
      walking turn is a ``turn_peak_sigmas`` change of the yaw rate across the step: PSD
      ``(turn_peak_accel / turn_peak_sigmas)^2 dt`` where that exceeds ``yaw_accel_psd``. A 90 deg
      turn made in 1 s along a minimum-jerk profile peaks at 5.77 (pi/2) / 1^2 = 9.06 rad/s^2; over
      a step of ``dt`` s the yaw rate then changes by 9.06 ``dt``, and white noise of PSD q spreads
      it by sqrt(q ``dt``), so 2 sigma needs q = 20.5 ``dt``: 0.68 rad^2/s^3 over a 30 Hz interval
      (about the walking model's 0.5: little changes there), 1.4 over two intervals, 2.0 over
      three (a core too slow for its camera, whose steps span two or three intervals). The turn is
      the model's blind spot exactly there: at the camera's rate the steps follow a turn's onset
      closely enough, but over two intervals the walking model's yaw rate lagged a 140 deg/s turn
      at 60 lux so far that two wrong steps (2.8 and 3.4 deg read for 9.7 and 9.5, the smeared
      patches' best correlation) passed the gate, the right one after them did not, and the
      heading went 25-28 deg off at a stated 4 (field walk f01 at every other frame, README
      "Speed"). The walking model stays as it is where no step measures the walk (the candidates'
      prior, blind spans), and the noise is added when a step arrives, for its interval, so a blind
      second does not spread the heading past ``odometry_max_yaw_sd`` (a constant 2 everywhere did,
      at half resolution). Replays of 43 walks at every other frame: field 5.61 -> 3.46 cm,
      g2field 7.00 -> 5.31, standard 2.02 -> 1.79 (mostly the f01 walks, which are chaotic there;
      walk by walk 13 better and 9 worse by over 0.15 cm); at the camera's rate the 28 walks within 0.15
      cm each and the 15 held-out field walks 2.72 / 2.39 / 2.47 -> 2.63 / 2.39 / 2.45 cm (README,
      "Speed"). 0: off.
    - ``blind_turn_max_rad``: the first odometry step after a span of frames that neither a step
      nor a fix measured (longer than ``gap_s``: the patch found no match, as in a fast turn in dim
      light) widens the heading of the state and of the step's clone together (one error) by the
      turn a person can make there beyond what the walking model carried: the yaw acceleration of
      a brisk turn (PSD ``(turn_peak_accel / turn_peak_sigmas)^2 T`` over a span of T s, as above)
      taken as a bridge between the yaw rates at the span's two ends (the step measures the later
      one), variance ``q T^3 / 12``, at most this squared (45 deg: a 90 deg corner turned wholly
      inside the span is 2 sigma). Without it the step's measured rate, through its correlation
      with the heading, cut the heading's stated spread as if the rate had been steady through the
      span: at 648 x 486 the held-out field walk f01 (seed 2; 60 lux, 1.6 m/s) found no patch match
      for 0.63 s in the onset of a 90 deg turn, the heading came out 43 deg short at a stated 10.6
      deg, and the track ran 3.1 m off at NEES 4.3 (10 % of its frames beyond the 99.9 % point);
      with it, 20.6 cm RMS at NEES 1.5 (none beyond). Added when the step arrives and not during
      the span, the heading does not pass ``odometry_max_yaw_sd`` in a blind second (README,
      "Other cameras"). 0: off.
    - ``lateral_psd`` (m^2/s), white lateral velocity: people sidestep without turning. 0.05 gives
      0.16 m of sideways spread in 0.5 s, the size of one sidestep.

    Physical limits (the state is clipped to them after every step): speed ``v_min``..``v_max``
    (walking backwards slowly .. running 2.5 m/s), yaw rate +-``w_max``.

    Vest offset: where the vest is, relative to the smooth walk the motion model follows. A fix
    measures the vest point projected onto the floor (see :mod:`tagloc.core.rig`), which does not
    move when the torso tilts about it, so tilt is not in the offset; what remains is the torso's
    real motion on the walk, which is where the operator is (the tracker reports body + offset).
    As standard deviations (RMS, not peak), along and across the walk, since the gait moves the
    chest differently in the two directions. The torso's rotations pivot about the centre of mass
    (~0.95 m up), 0.35 m below the vest point (1.3 m), so a tilt moves the vest point by 0.35 m
    times its angle (1 deg: 6 mm). Two parts:

    - Posture, walking or not (``floor_still_sigma_xy`` 5 mm, ``floor_still_sigma_yaw`` 0.5 deg,
      correlation ``floor_still_corr_s`` 2 s): quiet standing sways the body as an inverted pendulum
      about the ankles by a few millimetres RMS, and weight shifts tilt it ~0.5 deg (3 mm on the
      0.35 m arm); together about 5 mm.
    - Gait, on top of it, scaled by ``min(1, |v| / floor_walk_speed)^2`` (``v`` is the filter's own
      speed estimate): the wobble builds up over the first steps and is all there from a slow walk,
      0.6 m/s, on (sideways sway does not grow with speed; the nod and the surge grow a little with
      step length, so this is conservative for them between a slow and a brisk pace), with
      correlation ``floor_corr_s``:

      - forward (``floor_sigma_forward``): the trunk's forward speed rises and falls by ~0.1 m/s
        with each step (at ~1.9 Hz: 0.1 / (2 pi 1.9) = 8 mm semi-amplitude, 6 mm RMS), and the
        chest's ~0.6 deg nod moves the vest point 3 mm RMS on the 0.35 m arm: 6.5 mm in quadrature;
      - sideways (``floor_sigma_lateral``): the torso sways ~2 cm over the stance foot and rolls
        ~0.7 deg with it (4 mm on the arm); both follow the stance at half the step frequency, so
        they add in amplitude, not in quadrature: 2.4 cm semi-amplitude, 1.7 cm RMS;
      - heading (``floor_sigma_yaw``): the torso twists by ~2.5 deg semi-amplitude, 1.8 deg RMS (the
        reported heading is the torso's, so the twist is real heading).

    The lean into turns and with speed changes (up to ~10 deg) moves the vest point by up to 6 cm
    on the arm, but smoothly, over as long as the turn or the braking lasts: a bend of the walk's
    path that the motion model's noise (below) follows, not a ~1 Hz wobble. Vertical bobbing does
    not count (the vest point is projected onto the floor). The offset's correlation time is the
    two parts' times weighted by their variances. The offset is a state of the filter (see
    :mod:`tracker.ekf`): first-order Gauss-Markov with these as its stationary covariance. The
    gait's sway and twist swing at half the step frequency (~1 Hz) and keep their sign for about
    half a period, 0.5 s. So fixes of one frame share the offset, consecutive frames share most of
    it, and the offset decays back onto the walk between fixes.

    Tilt offset, seen by floor odometry only: an odometry that maps the image to the floor through
    the rig's nominal pose sees a change of the torso's tilt between two frames as floor motion: for
    the patch centre ~0.9 m ahead of a camera 1.3 m up, (h^2 + d^2) / h = 1.9 m per radian of pitch
    (forward) and h = 1.3 m per radian of roll (sideways). A second Gauss-Markov state (x, y) can
    carry that apparent motion (``tilt_sigma_forward``, ``tilt_sigma_lateral`` stationary, body
    axes, correlation ``tilt_corr_s``, scaled by ``min(1, |v| / floor_walk_speed)``): fixes do not
    see it, odometry steps measure vest + tilt offset, so the lean's apparent motion is bounded
    instead of integrated. tagloc's floor odometry takes the tilt out itself (it fits the tilt's
    change between frames from the patch's perspective and follows the lean into turns: see
    :class:`tagloc.vision.odometry.OdometryConfig`), so the defaults are 0 (no such state: on the
    eleven eval walks the state only let the filter explain real motion away as tilt, since a 2 cm
    per-frame tilt freedom is cheaper than any change of speed). Set them (e.g. 7.7 and 6.0 cm,
    1 s: the lean of atan(a / g) and atan(v omega / g) at 2.3-2.6 deg RMS on the arms above) for an
    odometry source that does not. ``gravity`` (m/s^2) gives the lean into a turn that candidate
    selection expects, atan(v omega / g) (:meth:`tracker.tracker.Tracker.leaned_camera`).

    Odometry scale: floor odometry measures the floor's motion through the camera's height, so a
    camera worn higher or lower than the rig states scales every step (an operator's stature moves
    a chest-worn camera by +-5 cm about the 1.3 m a rig was fitted at: +-4 %), and the full-frame
    flow's fit reads motion long under sensor noise (rendered pure forward steps at 165-200 lux:
    +0.7-1.1 %, none at 5x the light; the gait's noise-driven fits in the walks, 1.5-2 %). The state
    carries the relative error ``e`` of the odometry's translation (a step measures ``1 + e`` times
    the vest's), zero mean with ``odometry_scale_sigma`` (3 %: the stature spread and the flow's
    bias in quadrature) and a random walk of ``odometry_scale_rw`` per sqrt(s) (0.2 %: the light,
    and with it the noise, changes along aisles; 1 % over 25 s). Fixes at both ends of a gap
    between stickers tell it apart from the walk: one 1.5 m gap with fixes good to 1-2 cm pins it to
    about 1 %. A restarted track starts from the scale learnt so far (with the prior's variance). 0
    for both: no such state. ``odometry_scale_max`` bounds its mean (10 %: a camera
    13 cm off the height its rig was fitted at is a wrong rig, for ``tagloc rig fit`` to correct).

    Gates (squared Mahalanobis distance of the innovation over x, y, yaw, 3 DoF):

    - ``gate_prob`` 0.999 for decoded fixes (the brief's bound, 16.27), and checked ones (the
      prior's most likely sticker, its data modules matched as a decode's own final check matches
      them: another ID scores <= 0.22 against the 0.5 needed, so a wrong pick is refused there).
    - ``gate_prob_identified`` 0.99 (11.34) for ORB/appearance fixes: their identity was picked among
      candidates chosen from this very prior, so agreement with it is weaker evidence, and a wrong
      pick (a neighbouring sticker, one spacing away) must not pull the track; losing 1% of good
      identified fixes costs little.

    Life cycle:

    - ``lost_sigma_m``: TRACKING becomes LOST when the position standard deviation (square root of
      the largest eigenvalue of the x, y covariance) exceeds it. Candidates for the sticker seen at
      a pixel are the map stickers within the gate (~3.7 sigma) of the floor point under that pixel:
      pi (3.7 sigma)^2 / spacing^2 stickers, about K = 5 at sigma = 0.5 m and 1.5 m spacing. Beyond
      that the true sticker often falls outside the top K, and a wrong pick (one spacing away)
      would pass the identified gate. With the noise above this happens ~1.1 s into a gap while
      walking (an honest limit without odometry): decoded fixes still resume tracking.
    - ``lost_after_s``: or when no fix was accepted for this long; after it the speed and yaw rate
      are forgotten (zero mean, initial variance), so the mean stops extrapolating.
    - ``heading_widening``: the published (x, y) covariance is widened for the heading's own
      uncertainty (:func:`tracker.ekf.heading_widened`): its ellipse's orientation comes from the
      heading, so a heading uncertain by a radian (seconds blind in a turn) leaves the ellipse's
      orientation unknown too. Blind 2 s into a turn, the thin ellipse had the walker 1.7 m off
      across it at NEES 5 for 1.5 s (``benchmarks/blind_spans.py``). Below a degree of heading
      sigma it changes nothing measurable. Off: the filter's ellipse as it is.
    - ``max_lag_s``: a fix from a frame up to this much older than the filter is fused against the
      state retrodicted to its time (multi-camera rigs interleave frames); older ones are rejected
      and counted, and so are frames older than the filter (they do not move it).
    - Re-initialisation: ``reinit_fixes`` decoded fixes rejected by the gate but consistent with
      each other (each passing the decoded gate of a fresh filter started from the first), from at
      least ``reinit_min_ids`` different stickers, within ``reinit_window_s``, replace the track:
      the filter was wrong, not the stickers (a "kidnapped" operator, a missed turn). One sticker is
      enough when every sticker the track took fixes from since it (re)started is among them: such
      a track has no other support (seen just after a start from that sticker, when one bad
      odometry step had moved the young track and its own sticker's fixes were gated for 0.6 s).
      One sticker is also enough when it was the track's own anchor: the last fix the track took,
      at most ``reinit_own_sticker_s`` before the first refused one, was that sticker's, and no
      fix has been taken since. Its map position is then the one the track itself agreed with
      moments before, so what changed is the track (a wrong odometry step: after 0.3 s of dropped
      frames with the operator standing at a sticker, a bridging match 5.9 deg off its true turn
      left the track 10 cm and 4.8 deg off, and the sticker's next 18 decoded fixes, 1 s of them,
      were refused). A sticker that is wrong in the map cannot take a track over this way: its
      first fixes are refused against a track anchored elsewhere, and a sticker the track did
      take is still refused in favour of another sticker fused since. 1 s: the gap a standing or
      slowly turning operator bridges on odometry alone, which is where one sticker is in view;
      0 turns it off.
    - ``reinit_checked``: CHECKED fixes (the track's expected sticker, named by its data modules
      matching by a margin over its rivals, no symbol read) that the gate refuses join the
      competing hypothesis as decoded ones do, under the same rules (consistent with each other,
      two stickers or the track's own anchor). Their identity comes from the modules, not from
      agreeing with the track, so a refusal says the track is off as a decoded one's does. Without
      them a wrong odometry step that passed the gate (one fast-turn step 6 deg off, then steps
      that follow the walk well) held the track for as long as no symbol was read: every checked
      fix of the sticker in view refused, its error and NEES growing (a synthetic second of it,
      ``tests/test_tracker.py``: 5.6 cm at NEES 3.9 and rising; a replay with a variant of
      ``blind_turn_max_rad`` that was not kept refused checked and appearance fixes for 2.5 s
      after such a step, 138 cm off at NEES 17 by the walk's end). A hypothesis with checked
      fixes in it replaces the track as ``reinit_consistent`` and also counts ``reinit_checked``.
      Off: only decoded fixes form a hypothesis.
    - ``overrule_odometry``: a decoded fix that the gate refuses just after its frame's odometry
      step was fused, but that passes against the filter as it was before that step, overrules the
      step: the filter goes back to before it and takes the fix instead (counted as
      ``odometry_overruled``). A decoded fix names its sticker for sure; a step that turned the
      track off its own frame's sticker is the suspect (the first step of a fast turn, 2.7 degrees
      off, within the odometry gate because the walking model cannot foresee a turn starting: on
      the two-camera preset's walk s1 with the front camera alone, it made the next 13 fixes fail
      the gate and the track drift 28 cm). Identified fixes cannot overrule (their name is a guess).

    Floor odometry (:meth:`tracker.tracker.Tracker.update_odometry`), fused as a relative-pose
    measurement between consecutive frames (the pose at the earlier frame is cloned into the state):

    - ``odometry_inflation``: factors on the variances (dx, dy, dyaw) of each step (the covariance's
      rows and columns scaled by their square roots, which keeps it positive definite), for an
      odometry source whose covariance is not stated against the vest's motion. A step measures the
      vest's motion (the camera's) and the vest's wobble on the body goes to the offset state, and
      tagloc's floor odometry states its covariance against exactly that motion (see
      :class:`tagloc.vision.odometry.OdometryConfig`), so the factors are 1.
    - ``odometry_gate_prob``: chi-square bound (3 DoF) on the relative-pose innovation.
    - ``odometry_max_dt``: the longest interval between the two frames of a step (so also how long
      a camera's clone of its last frame is kept, see :mod:`tracker.clones`).
    - ``odometry_max_yaw_sd``: a step is fused only while the heading's standard deviation is
      within this (rad). A step is measured in the body frame and placed on the map through the
      heading; the filter places it linearly about its mean heading, whose error the linear term
      spreads across the step only. With the heading lost (seconds blind in a turn: 1-2.5 rad
      off) that places every step in the wrong direction, and the speed it learns narrows the
      ellipse along the wrong one: blind 2 s in a turn, the steps fused after it had the walker
      2-3 m off at NEES 15-21 (``benchmarks/blind_spans.py``). At 1 rad (57 deg) the placement
      is meaningless: the step's second-order displacement (1 - cos 1 = 46 % of it, along) is of
      the size of its linear spread; the track is lost by then (decoded fixes only), and refusing
      its steps lets the pose spread at the walking model's rate. 0.5 rad refused the steps after
      half-second blind spans too and cost accuracy there (RMSE 11.9 -> 16.5 cm) for nothing in
      NEES. Counted as ``odometry_heading_unknown``.
    - ``forget_turn_heading_lost``: on a lost track whose heading sigma passes
      ``odometry_max_yaw_sd``, the yaw rate is forgotten (zero mean, ``init_w_sigma``), once until
      the next fix. A walker's turn lasts about a second (90 deg at the 1-1.5 rad/s of a walking
      turn); a heading a radian uncertain has had longer than that without sight, so the rate of
      the last turn seen says nothing of the present one, and carrying it on only turns the mean
      away from a walker who has long since walked out of the turn (standard s03 blind 2 s as it
      left a turn: 2.2 rad of heading carried against 0.1, NEES 7.4 -> 2.8,
      ``benchmarks/blind_spans.py``). Within one long prediction (a camera that stalled, an
      output asked for ahead) it happens at the end of the filter's step where the sigma passes
      the limit, not at the prediction's end.

    Frame gaps (dropped frames: the driver loses single frames and bursts of 3-8): the filter
    predicts across a gap like across any interval, and what the walker did in a gap longer than
    ``gap_s`` (the 0.12 s of :class:`tagloc.vision.odometry.OdometryConfig`'s ``max_dt``) is known
    only from the one step that bridges it, if the odometry finds one (its ``bridge_max_dt``,
    0.35 s; ``odometry_max_dt`` is as long). The narrow yaw model above then
    claims too much: a spin on the spot that starts in the gap (3 rad/s within 0.5 s, about
    6 rad/s^2) leaves the heading off by several sigma, and the odometry steps after the gap,
    turning fast, are gated against a stale yaw rate. A prediction over a longer interval, when
    odometry was following the walk up to its start, therefore adds yaw-acceleration noise of
    PSD ``gap_yaw_accel_psd`` over the whole interval (without odometry the narrow model is the
    design above, and fixes after a spin re-initialise):
    2.5 rad^2/s^3 makes a spin's first 0.27 s (an 8-frame burst) a 2-sigma event in yaw rate
    (1.6 against 0.82 rad/s) and in yaw (12.6 against 7.3 degrees). The noise is part of the
    prediction across the gap (:meth:`tracker.ekf.WalkingEKF.advance`), so the heading's spread
    also spreads the position as the gap goes on; added at the gap's end instead, as it was, it
    could not: a camera that delivered no frame for 2 s as standard walk s03 left a turn had the
    pose at NEES 4.6-7.8 (2 DoF) for half a second after the stall, 1.7-3.3 with it
    (``benchmarks/blind_spans.py --stall``; ``tests/test_tracker.py`` has a synthetic stall).
    ``gate_bridge_narrow``: that noise is for the steps after a gap nothing measured; the step that
    bridges the gap (one match between the frames either side, with no frame between to check it)
    must also pass the gate against the walk as predicted without it, as an ordinary interval's
    step must. A bridged match that goes wrong does so grossly (in a fast turn across a painted
    line it slid 10-35 cm along the line and turned up to 15 deg too far, at a correlation as high
    as a right match's), and the gap's widened yaw let such steps in, stated at a few centimetres
    and 2 deg. A true spin within the gap then loses its bridge and is carried by the widened
    yaw and the steps after it, which is honest; counted as ``odometry_bridge_rejected``.
    Measured with ``benchmarks/bridges.py`` (3, 6 and 9 frames dropped after every frame of
    three 4 s walks, ``tagloc simulate --map maps/demo.csv --seconds 4 --seed 1..3``, with the
    odometry's ``bridge_overlap_mask``): of the 16 wrong bridges of seed 1, 14 were fused without
    this gate and 9 with it, and the published pose after the gap was beyond the 99.9 % bound
    after 8 of the bridges and after 5; it refused 2 of the 212 right bridges there and none of
    the 574 of seeds 2 and 3.
    ``missed_step_noise``: the same, frame interval by frame interval, when frames arrive but their
    odometry steps are refused (the camera's last frame was to be measured and no step ended
    there), for as long as the odometry had followed the walk until ``odometry_max_dt`` before:
    the odometry mostly fails where a turn is fast (its smeared frames, see
    :class:`tagloc.vision.odometry.OdometryConfig`), which is also where the narrow model fails.
    Measured (2026-11-25, replays): twelve 20 s walks at 648 x 486 (``tagloc simulate --scale
    0.5``, 60-300 lux, field timing and survey error) had runs of 8-10 refused steps in turns at
    100-120 deg/s, after which the heading was 10-28 deg off against a stated 2-6 deg, the fixes
    were gated and, with no sticker decodable at that resolution, nothing recovered for up to 6
    s (48 and 22 cm RMSE on the two worst walks). With the noise, 7.2 and 4.4 cm; 8 of the 12
    walks better, median 5.7 -> 5.5 cm. On the eval presets (1296 x 972): standard 1.81 -> 1.78
    cm, field 2.89 -> 2.93 cm (f01 4.10 -> 4.30 in a replay, 3.82 -> 3.81 in live's order).
    Starting the noise only once the run is longer than ``gap_s``, as for a frame gap, left the
    presets as they were but the worst walk at 17.6 cm.
    ``disagreement_noise``: the other way a turn goes missing. The first step after such a run can
    be a mistracking that passes the gate, because the filter no longer knows the turn
    rate. On the field walk f01 at 648 x 486 (60 lux, a 145 deg/s turn), that step read -0.4 deg
    for a true +4.5. The filter then held a yaw rate near zero and gated the right steps that
    followed, each reporting the 4-5 deg turn the filter missed: the heading ended 45 deg off
    against a stated 9. One gated step may be a mistracking of its own, so the first is only
    noted. When the next step of the same camera is gated too, with the same sign, the turn of
    both went missing. The yaw sigma grows by the sum of their disagreements: the missing turn is
    one error that adds up, not independent ones. Every further gated step with the same sign adds
    its own disagreement. The yaw rate's variance grows by (disagreement / interval)^2, so the
    right steps pass the gate again. Measured (2026-11-25) on that walk: heading 30 deg off against
    a stated 18 after the turn, 91.5 -> 61.4 cm RMSE, NEES 7.5 -> 1.9. It fired on no other walk
    of the presets at either resolution, nor on twelve other walks at 648 x 486; at 1296 x 972 the
    tracker gates 0-1 steps a walk, and the presets' figures are unchanged.

    Input guards (what no sticker gives, only a solver's blow-up, is refused before the gate):
    a fix whose covariance has an entry beyond ``fix_max_cov`` (1e12 m^2 or rad^2: a 1000 km
    sigma), or whose position is beyond ``fix_max_xy_m`` (1e9 m: ten thousand times the largest
    map coordinate, :data:`tagloc.core.stickermap.MAX_COORD_M`) on either axis. The lean of
    :meth:`tracker.tracker.Tracker.leaned_camera` is left out below ``lean_min_rad`` (1e-4 rad moves
    a sticker's image by 0.13 px at the reference camera's 1286 px focal length, against the
    candidates' 3 px ``pixel_sigma``), so that walking straight keeps the rig's own camera and the
    projections cached for it.

    Covariance guards: eigenvalues are kept >= ``min_eig``; variances are capped (position
    ``pos_var_cap`` m^2, i.e. 1 km sigma; yaw pi^2/3, the variance of a uniform heading, whose
    covariances with the rest are then dropped (nothing follows from a uniform heading); speed
    ``v_var_cap``; yaw rate ``w_var_cap``) so hours without a fix give a huge but finite covariance.
    The vest and tilt offsets' variances are capped at ``offset_var_cap_factor`` (4: twice the
    sigma) times their largest stationary variance (full gait): a Gauss-Markov state predicted
    from at most its stationary covariance stays at most there, so the cap only catches numerical
    growth and leaves the model's own values alone. A map-error slot's variance is capped at
    ``map_var_cap`` (100 m^2 or rad^2: at least what a map may state, 10 m and 180 deg =
    pi rad (:data:`tagloc.core.stickermap.MAX_SIGMA`), so a stated survey enters the state whole,
    never clipped to a sharper one; survey errors have no process noise, so the cap only guards
    against numerical growth).
    ``max_step_s`` splits long predictions into steps (at most ``max_steps``).
    """

    accel_psd: float = 0.3
    yaw_accel_psd: float = 0.5
    lateral_psd: float = 0.05
    v_min: float = -1.0
    v_max: float = 2.5
    w_max: float = 4.0
    init_v_sigma: float = 1.0
    init_w_sigma: float = 1.0
    floor_sigma_forward: float = 0.0065
    floor_sigma_lateral: float = 0.017
    floor_sigma_yaw: float = math.radians(1.8)
    floor_walk_speed: float = 0.6
    floor_still_sigma_xy: float = 0.005
    floor_still_sigma_yaw: float = math.radians(0.5)
    floor_still_corr_s: float = 2.0
    floor_corr_s: float = 0.5
    tilt_sigma_forward: float = 0.0
    tilt_sigma_lateral: float = 0.0
    tilt_corr_s: float = 1.0
    odometry_scale_sigma: float = 0.03
    odometry_scale_rw: float = 0.002
    odometry_scale_max: float = 0.1
    gravity: float = 9.81
    gate_prob: float = 0.999
    gate_prob_identified: float = 0.99
    lost_sigma_m: float = 0.5
    lost_after_s: float = 10.0
    heading_widening: bool = True
    max_lag_s: float = 0.25
    reinit_fixes: int = 3
    reinit_min_ids: int = 2
    reinit_window_s: float = 5.0
    reinit_own_sticker_s: float = 1.0
    reinit_checked: bool = True
    overrule_odometry: bool = True
    fix_max_cov: float = 1e12
    fix_max_xy_m: float = 1e9
    lean_min_rad: float = 1e-4
    min_eig: float = 1e-10
    pos_var_cap: float = 1e6
    yaw_var_cap: float = math.pi**2 / 3
    v_var_cap: float = 4.0
    w_var_cap: float = 9.0
    offset_var_cap_factor: float = 4.0
    map_var_cap: float = 100.0
    max_step_s: float = 0.2
    max_steps: int = 50
    odometry_inflation: tuple[float, float, float] = (1.0, 1.0, 1.0)
    odometry_gate_prob: float = 0.999
    odometry_max_dt: float = 0.35
    odometry_max_yaw_sd: float = 1.0
    forget_turn_heading_lost: bool = True
    gap_s: float = 0.12
    gap_yaw_accel_psd: float = 2.5
    turn_peak_accel: float = 9.06
    turn_peak_sigmas: float = 2.0
    blind_turn_max_rad: float = math.pi / 4
    gate_bridge_narrow: bool = True
    missed_step_noise: bool = True
    disagreement_noise: bool = True

    def __post_init__(self) -> None:
        """Refuse values the filter cannot run with (a config is set in code: a typo there must
        fail at once, naming the field, not as a NaN pose or a silent gate later)."""
        bad: list[str] = []
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool):
                continue
            values = v if isinstance(v, tuple) else (v,)
            if not all(isinstance(x, (int, float)) and math.isfinite(x) for x in values):
                bad.append(f"{f.name}={v!r} is not a finite number")
            elif f.name not in _MAY_BE_NEGATIVE and min(values) < 0:
                bad.append(f"{f.name}={v!r} is negative")
        if bad:
            raise InputError("TrackerConfig: " + "; ".join(bad))
        checks = (
            (self.v_min < self.v_max, f"v_min {self.v_min} must be below v_max {self.v_max}"),
            (
                all(0.0 < p < 1.0 for p in (self.gate_prob, self.gate_prob_identified, self.odometry_gate_prob)),
                "gate_prob, gate_prob_identified and odometry_gate_prob must be probabilities in (0, 1)",
            ),
            (
                all(
                    x > 0
                    for x in (
                        self.min_eig,
                        self.pos_var_cap,
                        self.yaw_var_cap,
                        self.v_var_cap,
                        self.w_var_cap,
                        self.offset_var_cap_factor,
                        self.map_var_cap,
                    )
                ),
                "min_eig and the variance caps must be > 0",
            ),
            (self.odometry_scale_max < 1.0, f"odometry_scale_max {self.odometry_scale_max} must be < 1"),
            (
                len(self.odometry_inflation) == 3 and min(self.odometry_inflation) > 0,
                "odometry_inflation: 3 values > 0",
            ),
            (
                all(x > 0 for x in (self.gravity, self.max_step_s, self.odometry_max_dt, self.floor_walk_speed)),
                "gravity, max_step_s, odometry_max_dt and floor_walk_speed must be > 0",
            ),
            (
                self.max_steps >= 1 and self.reinit_fixes >= 1 and self.reinit_min_ids >= 1,
                "max_steps, reinit_fixes and reinit_min_ids must be >= 1",
            ),
            (self.turn_peak_sigmas > 0, "turn_peak_sigmas must be > 0"),
        )
        bad = [why for ok, why in checks if not ok]
        if bad:
            raise InputError("TrackerConfig: " + "; ".join(bad))

    def _gait(self, speed: float | None) -> float:
        """Share of the gait wobble at ``speed`` (m/s; None: unknown, taken as walking)."""
        return 1.0 if speed is None else min(1.0, abs(speed) / self.floor_walk_speed) ** 2

    def floor_corr(self, speed: float | None = None) -> float:
        """Correlation time (s) of the vest offset: the gait's and the posture's, weighted by their
        variances; 0 (white) if either is set to 0."""
        if self.floor_corr_s <= 0.0 or self.floor_still_corr_s <= 0.0:
            return 0.0
        still = self.floor_still_sigma_xy**2
        gait = self._gait(speed) * 0.5 * (self.floor_sigma_forward**2 + self.floor_sigma_lateral**2)
        return (still * self.floor_still_corr_s + gait * self.floor_corr_s) / max(still + gait, 1e-12)

    def floor_cov(self, yaw: float, speed: float | None = None) -> np.ndarray:
        """(3, 3) stationary covariance of the vest offset in world axes (x, y, yaw).

        ``yaw`` (rad) is the walker's heading; ``speed`` (m/s) scales the gait part (None: full
        gait, for when the speed is not known yet).
        """
        g = self._gait(speed)
        c, s = math.cos(yaw), math.sin(yaw)
        st2 = self.floor_still_sigma_xy**2
        f2 = st2 + g * self.floor_sigma_forward**2
        l2 = st2 + g * self.floor_sigma_lateral**2
        # R diag(f2, l2) R^T with R the heading rotation.
        xy = (f2 - l2) * c * s
        return np.array(
            [
                [f2 * c * c + l2 * s * s, xy, 0.0],
                [xy, f2 * s * s + l2 * c * c, 0.0],
                [0.0, 0.0, self.floor_still_sigma_yaw**2 + g * self.floor_sigma_yaw**2],
            ]
        )

    def tilt_cov(self, yaw: float, speed: float | None = None) -> np.ndarray:
        """(2, 2) stationary covariance of the odometry's tilt offset in world axes (x, y).

        ``yaw`` (rad) is the walker's heading; ``speed`` (m/s) scales it (None: walking).
        """
        g = 1.0 if speed is None else min(1.0, abs(speed) / self.floor_walk_speed)
        c, s = math.cos(yaw), math.sin(yaw)
        R = np.array([[c, -s], [s, c]])
        return g * (R @ np.diag([self.tilt_sigma_forward**2, self.tilt_sigma_lateral**2]) @ R.T)

    @property
    def gate(self) -> float:
        """Squared-Mahalanobis bound for decoded fixes (chi-square, 3 DoF)."""
        return chi2_bound(self.gate_prob, 3)

    @property
    def gate_odometry(self) -> float:
        """Squared-Mahalanobis bound for odometry steps (chi-square, 3 DoF)."""
        return chi2_bound(self.odometry_gate_prob, 3)

    @property
    def gate_identified(self) -> float:
        """Squared-Mahalanobis bound for ORB/appearance fixes (chi-square, 3 DoF)."""
        return chi2_bound(self.gate_prob_identified, 3)
