"""Floor visual odometry: the body's planar motion between consecutive frames, from the floor texture.

The camera looks at a flat floor, so a fixed homography (from the rig's nominal pose and the
calibration, undistortion included) turns a floor patch in front of the operator into a metric
bird's-eye image: :func:`cv2.remap` with maps built once. Consecutive bird's-eye images of a static
floor differ by a 2-D rigid motion (the body's planar motion, seen from the patch):

1. translation by :func:`cv2.phaseCorrelate` on high-passed, Hann-windowed images (robust to large
   shifts, to lighting gradients and to heavy noise; its peak ``response`` is the quality).
   Phase correlation sees translation only, so the earlier image is first pre-rotated by the turn
   under way (the last measured turn rate), and if that fails by a grid of turn guesses, keeping
   the one that correlates best: a corner taken at 90-180 deg/s turns the body 3-6 degrees
   between frames, beyond what a translation-only match or ECC from no turn can follow;
2. rotation and a sub-pixel refinement by :func:`cv2.findTransformECC` (``MOTION_EUCLIDEAN``),
   started from that translation (its correlation is a second quality).

The image motion is converted into the body frame at the earlier frame (``T_body0_body1``), which
accounts for the patch lying ~1 m ahead of the body origin: a turn about the body origin also
shifts the patch sideways.

With a rolling shutter (``RigCamera.readout_s`` > 0) each image row is exposed at its own time, so
a floor point under the patch is seen where the camera was at its row's time; when the motion
changes between frames (the vest's wobble turns it one way, then the other) the two patches are
warped differently and the match picks up a spurious shift and turn (on simulated walks at 30 ms
read-out: 45 % more sideways error, 60 % more turn error). Each frame's patch is therefore sampled
where each floor point was at its row's time, given the body's motion (the tracker's prediction
for the frame, else the odometry's own last step; see ``rs_twist_from_tracker``): the remap moves
by ``-d (dp/dq) (v + w x q)`` for row delay
``d``, floor point ``q`` and body twist ``(v, w)`` (first order; computed on the 80 x 80 patch
grid and interpolated).

A torso leaning into a turn (roll atan(v omega / g): 8 degrees at 1.3 m/s and 60 deg/s, 15 at 1.5 m/s
and 100 deg/s) sees the floor through the tilted camera, so the nominal patch is a perspective-
distorted square displaced sideways: the best rigid match of two such patches turns less than the
body (6.3 % of every turn on the standard eval's s02, 10 degrees summed over its 20 s; 0.4 degrees
per metre walked per degree of roll), and the turn's lever to the displaced patch lengthens or
shortens the step. The odometry therefore follows the lean from its own speed and turn rate (see
``lean_correction``) and computes the step from where the matched patch points really are on the
floor (:meth:`FloorOdometry.level_motion`). With the true per-frame tilt instead of the predicted
lean, the step errors on s02 would fall from 10.4 / 6.1 mm (forward / sideways RMS) to 3.8 / 1.8 mm
and the turn bias to -0.7 %: the remaining step error is mostly the tilt's change from frame to
frame (gait nod, lean building up and easing), which a planar match cannot tell from motion.

What it measures is the camera's motion carried through the nominal rig: the vest's. The vest
moving on the body (sway, torso yaw, tilt) is not the body's motion; the tracker's vest-offset
state takes that part (see :mod:`tracker.config`), so the step covariance (see
:class:`OdometryConfig`) states the errors against the vest's motion.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np

from tagloc.core.camera import pixel_scale
from tagloc.core.errors import CalibrationError, InputError
from tagloc.core.rig import RigCamera, floor_under_pixels, row_delay_s, torso_tilt
from tagloc.vision.floor_flow import FloorFlow, FloorFlowConfig, FlowStep
from tagloc.vision.image import require_gray
from tagloc.vision.torso_tilt import TRUNK_TILT_RATE_SIGMA, TorsoTilt

__all__ = ["OdometryConfig", "OdometryStep", "FloorOdometry", "floor_patch"]

# Search resolution of the floor square (:func:`floor_patch`); finer changes the square by
# under a millimetre.
_BORDER_SAMPLES = 41  # points per image side traced onto the floor for the footprint polygon
_MIN_FLOOR_POINTS = 8  # fewer border points on the floor: no footprint to speak of
_EDGE_SAMPLES = 5  # points per square side tested inside the footprint (it is convex)
_NEAR_EDGE_STEPS = 60  # near-edge positions tried across the footprint's depth
_BISECTIONS = 20  # bisection steps of the side: max_side_m / 2**20, about a micrometre
_SIDE_TOL_M = 1e-4  # a farther square must be larger by this to win
_ZNCC_INSET = 6  # the turn guesses are compared on the patch less 1/6 at each border (warped in)
_SAME_TURN_RAD = 1e-9  # a grid guess this close to the one already tried is skipped
# A frame later than this many of the last step's frame intervals after the last frame measured
# follows a dropped frame (the timestamps' jitter is a few percent of an interval).
_STRIDE_DT_SLACK = 1.5
_STRIDE_INTERVALS = 8  # the frame interval is the shortest of this many recent steps' (a drop lengthens one)
_G = 9.81  # gravity, m/s^2
# ECC's stop for a bridged gap (rare, so it may iterate longer than ecc_iterations): on the rendered
# 6-degree burst of tests/test_odometry.py, 5 iterations to 1e-2 left 1.5 cm and 0.36 deg, 30 to
# 1e-3 1.1 cm and 0.25 deg.
_BRIDGE_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-3)
_TILT_GRID = 5  # cells per patch side of the lean's weighted fit (a smooth map; each cell 16 px)
# Corrections of the level motion. A second one moved the steps of the Speed walk's first 300
# frames by 0.08 mm and 0.001 deg at most (steps of 41 mm median, each ~4 mm off on its own).
_LEVEL_ITERATIONS = 1


@dataclass
class OdometryConfig:
    """Choices of the floor odometry. Lengths in metres, angles in radians, times in seconds.

    Bird's-eye patch:

    - ``patch_px``: side of the bird's-eye image, the resolution the frames are matched at (80 px
      over a 1 m square: 12.5 mm pixels; rotation and sub-pixel shift converge there, and finer
      patches cost more without better steps). ``max_side_m`` caps the floor square it covers; the
      square is the largest one, centred in front of the camera, whose corners stay
      ``image_margin`` (fraction of the image size) inside the image and whose rays dip at least
      ``min_depression`` below the horizon. ``supersample`` (a power of 2): the patch is remapped
      at this factor and reduced with :func:`cv2.pyrDown` (anti-aliasing: the camera resolves
      1-4 mm of floor; at 2 instead of 4, aliased texture made 47 % of the steps on six simulated
      walks fail to match, at 0.17 ms less per frame). ``supersample`` counts samples on the
      full-resolution frame.
    - ``patch_from_half``: the patch is sampled from the frame's half-resolution level
      (:func:`cv2.pyrDown`, the floor flow's own, see :mod:`tagloc.vision.floor_flow`) at half
      ``supersample`` per side: as many samples per source pixel, from an image already low-passed
      by the reduction. Only for cameras whose pixels are at most the reference camera's
      (:func:`tagloc.core.camera.pixel_scale`); a coarser camera samples its full resolution.
      Through the localiser on the eleven cached eval walks (replays, 2026-11-25, from the half
      level -> from the frame): standard 1.45 / 1.46 cm pooled (s01 2.14 / 2.31, s03 1.43 / 1.19),
      field 2.61 / 2.74 (f01 3.38 / 4.10, f03-long 2.49 / 2.58, f00 2.17 / 2.09, f04-dim 2.98 /
      2.86), 0 wrong IDs; 0.1-0.3 ms a frame less (a quarter of the remap's samples, one
      reduction fewer). The same sampling from the frame itself (``supersample`` 2) aliased the
      floor's grain and lost the walks (tens of centimetres).
    - ``highpass_sigma_px``: the local mean (Gaussian of this sigma) is subtracted, so lighting
      gradients and vignetting do not correlate.
    - ``grain_clip_sigmas``: the high-passed patch is clipped at this many robust standard
      deviations of itself (:func:`clip_to_grain`: the median absolute value / 0.6745, which the
      floor's grain and the noise set, as they fill most of the patch); 0: not clipped. A painted
      lane line (reflectance 0.6-0.75 on 0.38 concrete) or a sticker's ink on paper is many times
      the grain's contrast, so unclipped it outweighs the whole patch's grain in ECC's correlation
      and in the choice of its start. Cut by the patch's border, or smeared along itself in a fast
      turn, such a line says nothing about the motion along it, and the match slid there: on the
      field walk f01 replayed at 15 fps a step read 25 cm sideways where the walker moved 2 cm,
      stated to 3.5 cm (rho 0.68 for the line's alignment against 0.26 for the right one, clipped),
      and the track went 35 cm off at a stated 12. Clipped at 3 sigma (0.3 % of a Gaussian grain's
      samples), a line or a sticker weighs as much as grain of the same area. The floor odometry
      alone (``benchmarks/odometry_accuracy.py`` on the 28 validation and 15 held-out walks,
      2026-12-01) came out better per step sideways on 28 of the 43 walks (worse on 1), in the
      turn on 33 (worse on 2), forward on 15 (worse on 2; and on the flicker walk, whose frames
      the localiser deflickers first), RMS over the walks 3.31 -> 2.77 mm sideways and 0.129 ->
      0.075 deg of turn a step; f01 5.30 -> 3.07 mm and 0.148 -> 0.069 deg. Its cost: 9 us a
      patch (a median by partition); the replay's odometry stage within the machine's noise. At 2
      sigma the gait x2 walk f01 replayed at 15 fps was lost (82 cm RMS): grain clipped too. At
      648 x 486 fewer steps were measured (f01 74.7 -> 71.5 %): where a line or a sticker carried
      a coarse camera's match, the clipped correlation fell under ``weak_ecc`` at 0.25, now 0.2.
    - ``dark_level``, ``min_lit_fraction``: patch pixels at or below ``dark_level`` grey levels (the
      patch's pixels average many of the frame's, so it is the mean of a dark area, not a noisy
      pixel) see no lit floor: a lens cap or a flap partly over the lens, an unlit corner. Such a
      part is fixed in the image, and its edge, high-passed, matched itself: with the left tenth
      of the patch's footprint black, steps of a 4 s walk (``tagloc simulate --seed 1``) came out
      near zero with NEES in the hundreds, and the track 1.6-2.3 m off with its covariance at a
      few centimetres. It is cut out of the patch (with the 3-sigma band over which the high-pass
      spreads its edge). A patch with less than ``min_lit_fraction`` left is no step: on that
      walk, with 53 % of the patch lit 1 of 39 steps was beyond the 99 % chi-square bound, with
      40 % lit 5. Simulated floors at 25 lux give patches no darker than 58 grey levels.
    - ``legs_reach_m``, ``legs_half_width_m``: for a rig camera that sees the wearer's own feet
      and legs (``legs_in_view`` in ``rig.json``, :mod:`tagloc.core.rig`; not stated there: a
      forward camera that sees the floor within ``legs_reach_m`` of the vest point), the floor they
      can cover, from the vest point up to ``legs_reach_m`` ahead of it and ``legs_half_width_m``
      either side, is left out: the patch's near edge starts beyond it, and the floor flow tracks
      no point that sees it. They move with the body, not with the floor, and
      a camera pitched 55-65 degrees sees them once per step (:mod:`tagloc.sim.legs`): a heel lands
      half a step (0.3-0.4 m) ahead of the hips, which are ~0.12 m behind a chest-mounted vest
      point, and the shoe reaches 0.2 m beyond the ankle; a shin or knee 0.3-0.5 m up hides floor
      further out still (seen from 1.3 m, a knee 0.3 m ahead covers the floor 0.5 m ahead). Hence
      0.7 m and 0.3 m (the feet 0.05 m either side of the walking line, the hips and thighs 0.17 m,
      spread by the view from above). The legs of :mod:`tagloc.sim.legs` reach 0.46 / 0.58 / 0.68 m
      ahead of the vest point (99th percentile of their floor-projected outline) at 0.9 / 1.3 /
      1.6 m/s. The patch further out sees the floor coarser, so this costs where no legs are in
      view (see the README's "The wearer's legs"), and a rig can say ``"legs_in_view": false``.
    - ``min_camera_height``: a camera lower than this (m) sees no floor patch worth matching;
      ``min_side_m``: a floor square smaller than this (20 cm: 2.5 mm pixels at 80 px, finer
      than the camera resolves at 1-2 m) is refused.

    Acceptance (otherwise :meth:`FloorOdometry.measure` returns None):

    - ``max_dt``: a longer gap between frames (dropped frames) is not measured as an ordinary step:
      the patch moves too far for phase correlation from no prior, and the turn in it is unknown.
    - ``bridge_max_dt``, ``bridge_yaw_accel``: a gap up to ``bridge_max_dt`` (a burst of 8 frames
      dropped at 30 Hz is 0.3 s between the frames either side; the driver loses bursts of 3-8) is
      bridged instead: the step is predicted from the walk just before (this odometry's last step,
      else the tracker's velocity: a constant-rate arc), the earlier patch is warped by it, and
      turns either side of the predicted one, up to half ``bridge_yaw_accel`` times the gap
      squared (8 rad/s^2: trunk yaw rate builds up to ~150-200 deg/s within 0.3-0.5 s in a brisk
      turn), compete as starts for ECC (:meth:`FloorOdometry._bridge`). A bridged match must reach
      ``min_ecc``; its covariance is generous (see :meth:`FloorOdometry._bridge`).
      ``bridge_overlap_mask``: the bridged match correlates a part of the overlap only. ECC by
      itself already correlates just the pixels its map brings inside the earlier patch (the
      overlap); the mask (:func:`overlap_mask` of the start) is read by ECC in the earlier
      patch's pixels, so it leaves out a further band as wide as the start's motion: what is
      correlated is the overlap shrunk by that motion once more. Over a gap the patch moves by a
      third to a half of its side, and the whole overlap let the match follow whatever its
      strongest edge allows: in a fast turn across a painted lane line, the match slid along the
      line. (A mask of the overlap itself, in the earlier patch's pixels, changes nothing: 23
      wrong of 245 on the walk below.) (``benchmarks/bridges.py`` on a 4 s walk, ``tagloc simulate --seconds 4 --seed 1``, with 3,
      6 and 9 frames dropped after every frame: 24 of 243 bridged steps beyond the 99 % bound,
      10-35 cm off, against 16 of 228 with the mask; the same walk's seeds 2 and 3 bridged 293 and
      301 gaps without the mask, 285 and 289 with it, none wrong either way). Measured on
      the three field_sensor ``timing`` walks and the field walks f00, f02, f03-long, f04-dim
      (odometry alone): 10 of 15 gaps bridged, 1.2 / 1.1 cm (forward / sideways) and 0.4 deg RMS,
      none wrong; of the five refused, two were in 25-33 degree turns (the patch ahead swings
      away, a third of it overlaps, and the lean into the turn changes its perspective: no
      correlation is left even at the true motion), two were standing turns of 6-12 degrees and
      one reached 0.27 (below ``min_ecc``).
      ``bridge_max_flow_residual_px``: a bridged match is verified by the floor flow (run for a
      bridge even where the localiser skips it, ``refine``): tracked from the match's step, the
      floor's points must fit one rigid motion to this median reprojection error (px), else the
      bridge is refused (counted in ``bridges_unverified``) and the gap left to the walking model
      (with ``flow`` off, nothing verifies a bridge). ECC correlates one patch; the flow's points
      cover the whole floor in view, so a match slid along a painted line leaves them
      unexplained. Measured with ``benchmarks/bridges.py`` (4 s
      walks, ``tagloc simulate --seconds 4 --seed S``, 3, 6 and 9 frames dropped after every
      frame): on seed 1, whose fast turn crosses a lane line, the 60 bridges whose match was more
      than 8 cm off all left 3.9 px or more; on seed 2, where none was wrong, 55 % of the bridges
      left under 2.5 px (the ordinary step's ``FloorFlowConfig.max_residual_px``) and 17 % over 5
      (up to 8.7, in its fast turns). Over seeds 1-18 at 5 px, 2 of 3,178 bridges kept were wrong
      against 44 of 4,613 without the check, and no published pose after a gap was beyond the
      99.9 % bound (8 before), for 22.5 mm RMS after every gap against 21.7. At 4 px the same
      walks kept 1 wrong, but the held-out field walk f03-long (seed 3) lost right bridges in its
      turns, 2.66 -> 3.02 cm; at 5 px every field walk (presets, held-out, gait x2) is within
      0.1 cm of before.
    - ``max_flow_residual_px``, ``plain_floor_residual_px``, ``forget_unverified``: the same check
      on an ordinary step, on a plain floor. Where the floor's right fits already leave
      ``plain_floor_residual_px`` or more (the median of the flow's recent fits,
      :meth:`tagloc.vision.floor_flow.FloorFlow.residual_floor`: ~0.9-1.3 px on the reference
      floor, 2.2-2.5 at half its texture contrast, 4.3-5 at a quarter) and the floor flow, tracked
      from the patch's step, leaves more than ``max_flow_residual_px`` (median), the patch is as
      noise-bound as the flow and neither is trusted: the step is refused (counted in
      ``steps_unverified``). On a textured floor such a residual comes from a frame smeared in a
      fast turn, where the patch's coarse pixels are the better measurement, and its step stands
      (refused there too, the held-out field walk f00 of seed 3 went 2.25 -> 2.57 cm). On the
      tenth-contrast floor (``tagloc simulate --floor-contrast 0.1``) these patch steps put a walk's
      heading 20-40 deg off in its turns at NEES 14-72 (the walk's 5.2); refused, that walk is
      4.2 cm off at NEES 0.58 instead of 13.6. At 6 px it was overconfident again. What a refused
      step taught the odometry (turn guess, lean, torso tilt) is kept unless ``forget_unverified``:
      forgetting it, as for a refused bridge, cost the field walks f04-dim and f00 of seed 3
      2.6 -> 9.7 and 2.2 -> 8.1 cm (every refusal restarted the torso's tilt filter mid-turn).
    - ``flow_without_patch``: where ECC finds no match (below ``weak_ecc`` or no phase-correlation
      peak: a plain floor, heavy blur), the floor flow is tracked from the walk's predicted step
      instead (the odometry's last step while recent, else ``measure``'s ``body_twist``, the
      tracker's prediction), and its fit, judged by the same residual limits and within
      ``FloorFlowConfig.max_disagreement_m`` / ``_rad`` of that prediction, is the step
      (counted in ``flow_only_steps``). On the reference floor the patch almost always matches;
      on concrete of half the texture contrast it failed in a third of the frames, and with this
      (and the flow's limits that follow the floor) the three walks came out 3.4 cm RMS against
      10.0 (``benchmarks/eval_variants.py``, 2026-11-30).
      ``flow_without_patch_max_scale``: only cameras whose pixels are at most this many times the
      reference camera's (:func:`tagloc.core.camera.pixel_scale`) do so. Without the patch's
      match, nothing independent starts the fit or checks it: each flow-only step is fitted from
      the last one (or the tracker's prediction, which those steps feed), so where the fit cannot
      pull away from its start, it measures its start and the error is carried on from step to
      step. At 648 x 486 (pixels twice the reference's), on the field walk f01 (60 lux, 1.6 m/s,
      the floor 1.8 m away and smeared along the walk), 21 flow-only steps in 0.74 s each
      ended within a few millimetres of its start while the truth stayed at 61 mm a step: the
      fitted forward step shrank from 60 to 16 mm and the sideways one grew to 55 mm, each step
      2-6 sigmas off, and the track ran 88 cm off at a NEES of 107 (the walk's NEES 10.2,
      overconfident; ``tagloc eval --preset all --scale 0.5``, 2026-11-30). Without flow-only
      steps there, no half-resolution preset walk is overconfident (field 21.3 cm RMS, NEES 0.95;
      standard 266 cm, 0.75, s01 lost either way and s03 for seconds) against 16.7 cm at NEES
      2.80 with them (standard 190 cm). Guessing the steps from the tracker, not letting them teach
      the odometry the walk, fitting each a second time from a start 5 mm / 0.2 deg away and
      refusing those that did not come back, or keeping their residuals out of the floor's took
      that walk to 7-21 cm, but each made a half-contrast floor group of the reference camera
      (the floors ``flow_without_patch`` is for) 2.5-4.6 cm worse (``benchmarks/eval_variants.py``,
      2026-11-30). So it stays off there, as flattening does (``FloorFlowConfig.flatten_max_scale``),
      until the fit can say how well it measured.
    - ``min_response``: phase-correlation peak. Independent sensor noise on a blank floor gives
      0.04 (median; up to 0.1 in 40 trials); consecutive frames of simulated concrete 0.3-0.6
      (median per session, lux 50-300), down to ~0.05 only under the heaviest blur.
    - ``min_ecc``: ECC correlation after alignment: < 0.1 on noise, >= 0.3 on matching frames.
    - ``weak_ecc``: a match between this and ``min_ecc`` (heavy blur: a fast turn in dim light
      smears the two patches differently; a coarse camera's patch with little grain left after the
      clip, ``grain_clip_sigmas``) is kept with its covariance times ``weak_ecc_cov_scale`` (twice
      the sigma). Noise alone correlates under 0.1 (``min_ecc``), so 0.2 is still twice noise's
      worst. Measured against the true motion (odometry alone, every step, the patch clipped;
      ``benchmarks/odometry_accuracy.py --by-rho``, 2026-12-02): at 648 x 486 the six standard
      walks' 479 steps at 0.2-0.25 were 4.5 / 3.9 mm / 0.11 deg off (forward, sideways, turn RMS)
      against 3.4 / 3.0 / 0.062 at 0.3-0.4, which is 0.24 / 0.21 / 0.37 of their stated (scaled)
      sigmas, the largest 2.0; the five field walks' 555 (rolling shutter) 5.1 / 5.2 / 0.15 against
      4.2 / 3.4 / 0.081, 0.26 / 0.25 / 0.41 of their sigmas. At 1296 x 972 no step of the eleven
      eval walks fell there. At 0.25 (derived before the clip, on unclipped correlations) the
      half-resolution walks f01 and s01 lost most such steps and with them the walk (field 277 ->
      4.5 cm RMS at 0.2, standard 281 -> 5.7; held out, seed 2: 35.8 -> 25.2 and 35.2 -> 3.7, its
      f01 lost either way; ``benchmarks/eval_variants.py``). On the standard walk s01 (56 lux), six
      weak frames in one fast turn had been refused and the turn's 19 degrees left to the walking
      model: heading RMSE 3.1 -> 1.0 deg.
    - ``flow_cov_ref_px``, ``flow_cov_power``, ``flow_cov_min_scale``: a step the floor flow
      measured has its covariance (the sigmas above, fitted to the patch's steps) times
      ``clip((r / flow_cov_ref_px) ** flow_cov_power, flow_cov_min_scale, 1)`` for the flow's
      median reprojection error ``r`` (px). The residual is the tracking noise the fit saw (sensor
      noise in dim light, blur, the floor's texture), and the flow's steps' error grows with it.
      Measured on the steps the localiser fuses (``benchmarks/odometry_accuracy.py --in-localiser
      --by-residual --windows`` on today's eval walks, 2026-11-28): per step ~1 mm under 0.75 px,
      1-2 mm at 0.75-1 px, 2-5 mm at 1-1.5 px and 4-9 mm at 1.5-2.5 px, against ~10 mm stated;
      summed over 15-60 steps (the gaps between stickers), the mean 3-DoF NEES against the stated
      sums was 0.08-0.12 on s00 (median residual 0.77 px), 0.24-0.33 on s02 (0.83), 0.14-0.54 on
      f00 (0.82), 0.29-0.94 on f04-dim (1.10) and 0.74-1.50 on f01 (1.25; 3 if honest): the
      gap's variance grows about as r^4 (the per-step sigma as r^2). 1.33 px and the 4th power
      divide those NEES by about 9 at s00's residual, 7 at s02's and f00's, 2 at f04-dim's and 1.3
      at f01's, towards the 1-2 of a covariance still on the safe side (measured after the change
      with the same command: see "Floor odometry" in the README); a step with a poor fit
      (r >= 1.33 px) keeps the patch-fitted covariance. The floor 0.1 (a sigma a third of the
      patch's) keeps one very clean step from being taken as exact. 0: the sigmas above for every
      step, as before 2026-11-28 (see "Field physics" in the README for what the scaling does
      through the localiser).
    - ``refused_flow_cov_power``: where the floor flow refused its fit of a step and the patch's
      step stands (a frame smeared in a fast turn, see ``max_flow_residual_px``), the fit's median
      reprojection error ``r`` (px) still says how far the frames are from any rigid floor motion,
      and the patch was matched in the same frames. Beyond the flow's limit for a fit on this
      floor (:meth:`tagloc.vision.floor_flow.FloorFlow.residual_limits`: 2.5 px on a textured
      floor, rising on a plainer one whose right fits leave more) the step's covariance is
      multiplied by ``(r / limit) ** refused_flow_cov_power``: power 2, an error proportional to
      the motion no rigid fit explains (against the fixed 2.5 px, a half-contrast floor's ordinary
      refused steps were inflated too). Measured against the true vest motion (every step the
      localiser fuses, 2026-12-01; README, "Combined conditions"): such steps' mean 3-DoF NEES,
      3 if honest, was 0.6-2.2 at any residual under 2.5 px, and above it 7.9 on the field
      preset's walks (54 steps, median 1.7), 2.0 on the standard preset's (13) and 7.3 on ten
      walks outside both presets (199; 4.6 at 3-4 px, 10.6 at 4-5 px, 10.9 at 5-7 px); with the
      factor 2.6, 0.8 and 2.5 (``benchmarks/odometry_accuracy.py --in-localiser --by-residual``,
      its ``patch`` rows). Whole walks move by 0.1 cm or less (mostly down) against a control
      at power 0.01 (README, "Combined conditions"). 0: the patch's covariance as it is.
    - ``max_shift_frac``: shifts beyond this fraction of the patch leave too little overlap.
    - ``rotation_step``, ``max_rotation``, ``max_turn_rate``: the grid of turn guesses tried when
      the match from the turn under way fails, up to ``max_rotation`` either way or, for a step
      over a longer interval (dropped or skipped frames, a slower camera or core), as far as a
      person turns at ``max_turn_rate`` (up to ~4 rad/s: 7.6 deg between frames at 30 Hz, 23 deg
      at 10 Hz, which a fixed 9 deg bound could not find); 0 ``max_rotation`` turns the search
      off.
    - ``turn_memory``: the last step's turn rate is the first guess while that step is at most
      this many ``max_dt`` old (two frame gaps: a person's yaw acceleration keeps it close).
    - ``ecc_turn_tolerance``: ECC ending further than this fraction of ``rotation_step`` from the
      guessed turn may have found a wrong optimum, so the grid of guesses is tried too (half a
      step: beyond it another grid guess is nearer).
    - ``turn_check_rate``: while the turn under way is faster than this (rad/s), ECC also starts a
      ``rotation_step`` either side of it and the best correlation wins. A fast turn smears the
      patch along the turn, its correlation is then nearly flat in the turn, and ECC's few
      iterations stop near wherever they started: on the field walk f01 (60 lux), from a guess of
      7 deg a frame ECC ended at 6.7 deg while the true turn had slowed to 3.8 (rho 0.852, against
      0.880 at 3.0 deg from a start at 3), each locked step became the next guess, and in live's
      order (``LocaliserConfig.defer_odometry``) the track ran 6 m off with its heading 70 deg
      wrong. 45 deg/s is where the floor flow stops trusting blurred frames too
      (``FloorFlowConfig.max_turn_rate``); below it the whole turn under way is under 1.5 deg a
      frame, half a grid step.
    - ``ecc_shift_allowance``: ECC may move the alignment this many times further than
      ``max_shift_frac`` before the step is refused (its sub-pixel refinement and the turn's
      lever arm add to phase correlation's shift).
    - ``ecc_iterations``, ``ecc_eps``: ECC stops after this many iterations or once its update is
      below ``ecc_eps`` pixels of the matched patch (0.01 px: under 0.1 mm on the floor, far below
      the per-frame noise; 1e-4 gave the same step errors on the six eval walks, to 0.02 mm RMS,
      at 0.15-0.2 ms more per frame).

    Noise per frame, as standard deviations that add in quadrature, of the motion of the patch
    centre (forward, lateral, in the body frame at the earlier frame) and of the turn, against the
    camera's true motion carried to the body origin through the nominal rig (the vest's motion; the
    vest's wobble on the body is the tracker's to model, see :mod:`tracker.config`):

    - ``sigma_forward``, ``sigma_lateral``, ``sigma_yaw``: standing still (image-matching noise,
      slow pitch drift of the vest);
    - ``sigma_forward_per_m``, ``sigma_lateral_per_m`` (metres per metre) and ``sigma_yaw_per_m``
      (radians per metre), per metre the patch centre moved in the step (on a turn on the spot the
      patch moves and the body origin does not; blur and perspective follow the image's motion):
      walking jolts the camera in roll and pitch, which the nominal homography turns into apparent
      floor motion, and the vest's height and pitch off nominal scale the measured displacement.

    The patch lies ``c`` ~0.6-1.1 m ahead of the body origin: what the images fix is where the patch
    centre went, and the turn about the body origin is the less certain part. An error ``e`` in the
    turn therefore comes with a sideways error ``-c e`` of the body origin (measured correlation of
    the two: -0.6 to -0.9 on six simulated walks), which the step's covariance carries (see
    :meth:`FloorOdometry.covariance`): over a gap, the heading error then swings the estimated path
    about the patch ahead, and its sideways drift stays small until the walker passes that patch.

    Tilt (``tilt_correction``): the bird's-eye patch is made through the rig's nominal pose, so a
    change of the vest's pitch or roll between two frames (the gait's nod and sway, the lean into a
    turn or with braking) shifts and keystones the patch as if the floor had moved: 1.9 m per radian
    of pitch and 1.3 m per radian of roll at the patch centre, ~1 cm per frame of walking (measured
    against the true camera poses of simulated walks). Seen through a homography instead of a
    rigid motion, the two differ: a shift is uniform, a tilt stretches the near and far edges of
    the patch differently. So after the rigid alignment, ECC is run again with
    ``MOTION_HOMOGRAPHY`` (``homography_iterations``: 5, like the rigid match; 10 fitted the noise
    more and cost 0.3 ms more a frame, for equal or worse steps on the eval walks;
    ``homography_eps``), and the step is fitted (``tilt_iterations`` Gauss-Newton steps, each solved
    by :func:`numpy.linalg.lstsq`: the problem is nearly linear for a small tilt and step, and
    scipy's general solver cost 2.5 ms a frame for the same answers) as the rigid motion of the floor
    seen by a camera whose
    pitch and roll changed by (rx, ry) about its centre, on a ``tilt_grid`` x ``tilt_grid`` grid of
    patch points (each fitted to ``homography_point_sigma_m``, the homography's precision on the
    floor: ~0.1 of a 12.5 mm patch pixel, at a few points' spread). The tilt change has a prior of
    ``tilt_prior_sigma`` per frame: the gait's ~0.6 deg nod at 1.9 Hz changes by at most 0.24 deg in
    1/30 s and its ~0.7 deg sway at 0.95 Hz by 0.14 deg; a 10 deg lean into a turn takes ~0.3 s or
    more to build up (1 deg per frame at the most, rare, and followed by ``lean_correction``). So 0.3
    deg keeps the fit in the physical range where the patch's perspective alone cannot pin it down
    (with 1 deg, roll traded against sideways motion on simulated walks: 11 mm per step sideways on
    one). ``tilt_fit_max``: a fitted change of pitch or roll beyond this (5 deg, five times the
    most a walking torso's tilt changes in a frame) is a fit that broke down, not a measurement, and
    is dropped (counter ``tilt_fits_refused``; the flow's own fit is judged by its residual): a homography fit on a flickering global-shutter walk
    once returned -73 and -273 deg, the tilt filter took it, and the steps of the next 0.7 s were
    corrected 20-30 mm sideways, the track 65 cm off and overconfident
    (``benchmarks/flicker.py``, 30 %, 50 Hz, global shutter, seed 4). ``tilt_fit_roll``: fit the roll too, not only the pitch (on four simulated walks it took
    the sideways error summed over 0.5 s from 5 to 2.4-3.5 cm on three and raised it from 2.4 to
    4.4 cm on the fourth, a slow walk under a steep camera).
    The tilt change is used to correct the rigid match's step (the rigid map that the tilt
    change alone makes the nominal patch see is taken out of it), not to replace the step by the
    fit's own rigid part: on a simulated 8 s stop in front of a sticker the homography's rigid
    part drifted by 0.04 deg and 2-3 mm per frame the same way, the rigid match's did not. Below ``tilt_min_speed`` of the patch (0.15 m/s: a standing body sways by a
    few tenths of a degree over seconds, below the fit's noise, which there became a forward creep
    of 1.4 mm per frame) the rigid step stands; above it, the pitch of starting and braking
    (atan(a / g), 5-8 deg over a second) is caught from the first steps (on a simulated start from
    a stop: 7 cm of forward error over 1 s instead of 11). ``tilt_pitch_when_slow`` fits the pitch
    below that speed too: summed raw, those fits became the creep above, but through
    ``tilt_filter`` they only inform a bounded estimate, and the pitch easing back after braking is
    then followed while standing (standard eval preset, tagloc's simulator revision 3: 4.50 cm RMSE
    with it and a 3 deg pitch prior against 4.93 cm without it and 2 deg; see ``tilt_filter``).
    Only the change between the two frames matters to first order (a constant tilt off the nominal
    changes the step's scale by its cosine). On simulated walks this halves to quarters the error
    of steps summed over 0.5-1 s (the time between sticker passes) in the forward and sideways
    directions; per single step it is no better, because the nod it removes telescopes anyway
    over consecutive steps.

    ``tilt_filter``: correct each step by the change of a filtered *absolute* tilt instead of the
    frame's raw fit (:mod:`tagloc.vision.torso_tilt`): the raw fits, ~0.3 deg off each
    (``tilt_fit_sigma``: 0.25-0.36 deg pitch and 0.22-0.26 deg roll RMS against the true vest
    tilt on two simulated walks), random-walk when summed over a gap (on the standard eval's s04,
    6.7 deg after 5 s, 15 cm of forward error), while a torso's tilt stays near upright. The
    filter's prior (``tilt_sigma_pitch``, ``tilt_sigma_roll`` about the upright and the lean into
    the turn, correlation time ``tilt_tau_s``): a walking trunk nods by about +-1 deg with each
    step and leans atan(a / g) with starting and braking (3-8 deg at 0.5-1.4 m/s^2, for about a
    second), 2-3 deg RMS over a walk with stops (3 deg: the braking peaks are what the filter must
    not clip; measured as the simulated vest's pitch through the localiser, 2.0-2.6 deg RMS on the
    walks named below for the roll and 2.1-2.9 deg with the walker swinging twice as much, so 3 deg
    holds for both); sideways, what stays once the turn's lean (already modelled) is taken out: the
    gait's roll and sway and the lean model's own error (it follows the odometry's speed and turn
    rate, atan(v omega / g), up to 8-12 deg in a turn). Measured as the simulated vest's roll
    about the lean model through the localiser: 0.72-1.20 deg RMS (1.4-2.3 deg at the 95th
    percentile) on the standard walks s00, s02 and the field walks f00, f01, and 1.40-2.16 deg
    RMS on the same walks with a walker swinging twice as much (``tagloc eval --gait-scale 2``);
    gait studies spread the trunk's motion by about that between people. So 2 deg: 1 deg, the
    default walker's gait alone, clipped the roll the filter must follow (the 33 preset and
    held-out walks, ``benchmarks/eval_variants.py``: 26 better, 7 worse with 2 deg; field 2.37 ->
    2.30 cm, held-out 2.76 -> 2.50 and 2.73 -> 2.55, standard 1.52 -> 1.42, held-out 1.38 ->
    1.36 and 1.64 -> 1.44; the twice-swinging walker's presets 2.98 -> 2.81 and 2.49 -> 2.26;
    0 wrong IDs; 1.5 and 3 deg came out about the same: field 2.32 and 2.30, standard 1.44 and
    1.41). Every accepted sticker fix anchors it with
    the camera's measured tilt (``tilt_anchor_sigma``: 0.15 deg RMS measured on simulated walks,
    0.45 deg at the 99th percentile), and the operator's own posture (a vest worn tipped) is
    learned as the mean of the fixes' tilts (``tilt_posture_fixes``: averaged over the first 300,
    ~30 s of fixes, then followed with that weight, and shrunk towards upright as if 30 upright
    fixes had come first, so that one odd fix cannot set it). ``tilt_gate_reset``: see
    ``LocaliserConfig.tilt_gate_chi2`` (3 fixes, a tenth of a second of a sticker in view);
    ``tilt_gate_prior_sigma``: before any fix, or after a reset, the gate judges against upright
    (the posture) with 2 deg per axis, the roll also against the lean model with half its lean as
    extra uncertainty (its first step can be far off). At 2 deg an upright start passes (on a
    simulated strip walk the true tilt at the first fixes was -1.9 / -1.9 deg while the lean model
    said -6.2 deg of roll; with 1 deg about the lean model all 26 fixes of the first frames were
    refused and the walk's error doubled) while a bad first fix on a field walk (6.5 / 5.3 deg, a
    sticker leaving the image) is refused (with 5 deg it anchored the filter: 3.8 -> 4.3 cm). Offline on s04 and s00 (anchored at the true
    tilt, as a fix does), the forward error summed over 5 s fell from 14.9 / 7.0 cm (raw fits) to
    7.1 / 7.1 cm, and over 1-2 s stayed at 4.8-6.6 / 3.5-4.7 cm.

    ``tilt_fit_sigma_rel``: where the floor flow's fit was refused (a fast turn with blur) and the
    patch's homography fit stands, its actual error grows with the change it reports, by this
    share of it in quadrature with ``tilt_fit_sigma``: measured against the true vest tilt on the
    field walks f00, f01, f02, f04-dim (2026-11-30), 0.21 / 0.39 / 0.33 deg RMS for fitted pitch
    changes below 0.2 / 0.2-0.5 / 0.5-1 deg (it followed 75 % of the true change), and 0.37 / 0.53
    / 0.72 / 1.57 deg (above 1 deg) with the walker swinging twice as much, whose fits there carried
    no information (their regression on the true change: -0.04). As for the flow's
    (``FloorFlowConfig.tilt_sigma_rel``), this sets the tilt estimate's stated variance, which the
    tilt gate judges by, not the fit's weight.

    ``tilt_rate_sigma``: the trunk's tilt rate (standard deviation), which bounds how much the tilt
    estimate's stated spread grows over a short time (:class:`tagloc.vision.torso_tilt.TorsoTilt`'s
    ``rate_sigma``): the vest's true pitch changed by 0.17-0.23 deg per frame RMS on the field
    walks f00, f01, f02, f04-dim (5-7 deg/s) and 0.26-0.32 deg with the walker swinging twice as
    much (8-10 deg/s; 0.19 and 0.28 deg on the standard walks; roll 0.24 at twice the gait), so
    10 deg/s. Without it, the spread a frame ahead (the tilt gate's in live's order, before the
    frame's odometry step) was the Ornstein-Uhlenbeck increment's, 0.78 deg for an error of 0.3
    (0.47 of the stated sigma RMS, on those four field walks in live's order); with it 0.38 deg,
    0.80 of the stated sigma with the default walker and 1.19 with the other (near-true fixes
    refused: 0.59 % and 1.25 %, against 0.34 % and 1.07 % in a replay; 2026-11-30).

    These angular sigmas (``tilt_fit_sigma``, ``tilt_anchor_sigma`` and the flow's
    ``FloorFlowConfig.tilt_sigma``) were measured with the reference camera (the Pi camera v1 at
    1296 x 972). An angle read from image positions is as sure as a pixel is small, so for a camera
    with a shorter focal length (fewer pixels over the same view) all three grow with its pixels'
    angular size (:func:`tagloc.core.camera.pixel_scale`; never shrunk for a finer camera, since they also hold errors
    that are not in pixels). At 648 x 486 (``tagloc simulate --scale 0.5``, 150 lux, rolling
    shutter, jitter, drops; replay 2026-11-25) the fixes' tilts were 0.6-1.1 deg uncertain by their
    corner noise, and the filter at the reference sigmas refused the fixes of 71 frames at its tilt
    gate (the same walk at 1296 x 972: 3 frames): 3.88 cm RMSE with 327 fixes. With the anchor's sigma scaled,
    23 refused, 375 fixes, 3.69 cm; with all three, 390 fixes, 2.84 cm.

    ``rolling_shutter``: for a rolling-shutter camera (``RigCamera.readout_s`` > 0), sample each
    frame's patch where each floor point was at its row's time (see the module docstring).
    ``rs_twist_from_tracker``: the body motion for that is the tracker's prediction for the frame
    (``measure``'s ``body_twist``) whenever it is given; False: the odometry's own last step while
    recent, the tracker's only without one. The last step carries its own error into the next
    patch, and so into the next step: in a fast turn under heavy blur (field walk f01, 150 deg/s
    at 60 lux, where the floor flow is refused and the patch's step stands), the odometry alone
    with the true body motion of the last interval instead of its own last step: the turn error
    summed over f01's two turns went 3.6 -> 0.4 and 5.3 -> 2.3 degrees, the sideways error 15 -> 8
    and 17 -> 6 cm. The tracker's prediction is filtered through the fixes and the walking model,
    and is for the frame's own time rather than the interval before. Through the localiser on the
    field walks (replays): f00 2.17 -> 2.19 cm, f01 4.42 -> 4.10, f02 2.51 -> 2.45, f03-long 2.92 ->
    2.76, f04-dim 3.14 -> 2.99; taking only the turn rate from the tracker and the rest from the last
    step instead sent f00 to 25 cm (the two disagree). Without rolling-shutter sampling at all: f00
    2.62, f01 4.30, f02 2.73, f03-long 3.08, f04-dim 3.33.

    ``flow``: refine each step at the camera's own pixel scale (:mod:`tagloc.vision.floor_flow`,
    tuned by ``flow_config``): a grid of image points tracked from where the patch's step puts
    them gives the step, the tilt change and the bobbing together. The tilt change goes to the
    tilt filter in place of the patch's homography fit (with ``flow_config.tilt_sigma``), and the
    step reported is the flow's, corrected by the filtered change less the flow's own. On the
    standard walk s00, odometry alone, the forward / sideways error summed over 1 s fell from 49.6 /
    24.1 mm to 22.6 / 19.5 mm and the turn's from 0.79 to 0.33 deg (the patch's tilt-change fit
    followed 25 % of the true change, the flow's 77-82 %). A refused fit (see the module; among
    others, a fast turn whose smeared frame the fit does not match) leaves the patch's step as
    before; so does a step through a skipped frame (stride), whose two frames' flow is not tracked.

    Stride (``max_stride``, ``stride_max_turn_rate``; :meth:`FloorOdometry.wants`, used when the
    localiser allows it: see ``LocaliserConfig.odometry_stride``): while the walker goes straight,
    a step may span two frame intervals, the frame between skipped (its patch is not even made),
    which saves the odometry's whole cost on that frame (25-46 % of the frames of the eval walks;
    the odometry's CPU per frame 2.4-4.2 -> 1.5-3.1 ms). It is load shedding, not free: a step
    over two intervals has the same image noise over twice the motion (per step 1.6-1.8 times a
    single step's error), and over 1 s of chained steps the errors are mixed, most walks within
    25 % either way, a few up to 35 % worse (``benchmarks/odometry_stride.py``). A frame is
    skipped only when the last step was a sure match (strong, and ECC ended near the turn first
    guessed), no frame was dropped since, and the turn rate is below ``stride_max_turn_rate``: 10 deg/s turns 0.67 deg over two
    intervals at 30 Hz, under half of the 1.5 deg that ECC is trusted to move from its guess
    (``ecc_turn_tolerance``), so a turn starting during the step stays within reach. (At 20-30
    deg/s a turn starting in dim light, blur 6-10 px, was matched near the old rate with ECC
    correlation 0.7 and the track lost 20-50 cm.) A two-interval match that is not sure is
    replaced by the two single steps through the skipped frame (:meth:`FloorOdometry.hold`),
    composed. The tilt fit's prior per step grows with the intervals a step spans.

    ``lean_correction``: follow the torso's lean into turns, roll atan(v omega / g) from the
    odometry's own speed and turn rate, through the inverted pendulum's lag sqrt(h_com / g)
    (``lean_com_height_m``: an adult's centre of mass, about 0.55 of 1.75 m stature), and match the
    patches as the tilted camera sees them (see :meth:`FloorOdometry.level_motion`). Below
    ``lean_min`` (0.25 degrees: a false turn of 0.004 degrees per 4.5 cm step, a twentieth of the
    step noise) the nominal geometry is kept, which saves the fit's 0.45 ms on straight walking.
    Across frames the odometry could not follow (a burst of drops), the lean's lag runs on through
    a demand taken to move linearly from the last step's to the next one's (see
    :meth:`FloorOdometry._update_lean`).

    ``pitch_lean``: follow the torso's pitch with starting and braking too, atan(a / g) forward
    for a forward acceleration ``a`` (3-8 degrees for about a second at 0.5-1.4 m/s^2; a walker
    slows into a turn, so the patch is pitched while it turns): the bird's-eye patch levelled with the
    roll only reads turns short (a rendered camera pitched 4 degrees back, turning 3 degrees per frame
    at 1.3 m/s: 2.9 %; the odometry alone on the eleven eval walks: 0.9-4.3 %). ``a`` is the lagged
    derivative of the walk's speed as the tracker predicts it for each frame (``measure``'s
    ``walk_speed``: fixes and odometry fused under the walking model), ``(v - lag(v)) / tau`` through
    the same pendulum lag as the roll, so no differentiation of a noisy speed. Not the odometry's own
    steps: their speed feeds back through the geometry it shapes (tried: on a fast turn at 60 lux the
    field walk f01 diverged by 112 cm). ``pitch_lean_max`` bounds it (3 degrees: the lower end of
    braking's lean, so a wrong speed change costs at most ~2 % of a turn). On the eleven eval walks
    (``benchmarks/eval_variants.py``, standard / field RMSE): 3 degrees 4.02 / 3.64 cm, 5 degrees
    4.23 / 3.58, 2 degrees 3.94 / 4.05; the last is all f01 (6.36 cm, NEES 3.12), which a clamp
    1.5e-9 rad off 2 degrees also gives: one identified fix at its gate's edge decides that walk.

    Calibration (tagloc's simulator, revision 3 with the leaning walker: the six 20 s walks of
    ``tagloc eval --preset standard``, 56-265 lux, 0.9-1.5 m/s, pitch 46-66 deg, tilt correction on),
    on non-overlapping windows of 15, 30 and 60 frames (the 0.5-2 s gaps between sticker passes
    that odometry bridges): the errors of the patch centre's motion and of the turn, summed over a
    window, squared, fitted (non-negative least squares, each window weighted by 1/its length) as
    the window's sum of ``sigma^2 + sigma_per_m^2 d^2``, then raised by 10 % so that the stated
    variance covers the actual one over all windows (actual/stated 1.03-1.16 before; 324 windows
    per axis). The standing values are large for a still camera because the walks' slow windows are
    braking, turning on the spot and swaying in place, not a tripod. Tilt correction trades the
    old per-frame sharpness (1.4 mm forward) for errors that no longer grow with the gait's nod.
    """

    patch_px: int = 80
    max_side_m: float = 1.0
    legs_reach_m: float = 0.7
    legs_half_width_m: float = 0.3
    image_margin: float = 0.03
    min_depression: float = math.radians(20.0)
    supersample: int = 4
    patch_from_half: bool = True
    highpass_sigma_px: float = 2.5
    grain_clip_sigmas: float = 3.0
    dark_level: float = 10.0
    min_lit_fraction: float = 0.5
    max_dt: float = 0.12
    bridge_max_dt: float = 0.35
    bridge_yaw_accel: float = 8.0
    bridge_overlap_mask: bool = True
    bridge_max_flow_residual_px: float = 5.0
    max_flow_residual_px: float = 5.0
    forget_unverified: bool = False
    plain_floor_residual_px: float = 2.0
    min_response: float = 0.1
    min_ecc: float = 0.3
    weak_ecc: float = 0.2
    weak_ecc_cov_scale: float = 4.0
    flow_cov_ref_px: float = 1.33
    flow_cov_power: float = 4.0
    flow_cov_min_scale: float = 0.1
    refused_flow_cov_power: float = 2.0
    max_shift_frac: float = 0.3
    rotation_step: float = math.radians(3.0)
    max_rotation: float = math.radians(9.0)
    max_turn_rate: float = 4.0
    turn_memory: float = 2.0
    ecc_turn_tolerance: float = 0.5
    turn_check_rate: float = math.radians(45.0)
    ecc_shift_allowance: float = 1.5
    min_camera_height: float = 0.05
    min_side_m: float = 0.2
    ecc_iterations: int = 5
    ecc_eps: float = 1e-2
    sigma_forward: float = 0.0102
    sigma_lateral: float = 0.0069
    sigma_yaw: float = math.radians(0.123)
    sigma_forward_per_m: float = 0.0
    sigma_lateral_per_m: float = 0.159
    sigma_yaw_per_m: float = math.radians(2.83)
    rolling_shutter: bool = True
    rs_twist_from_tracker: bool = True
    tilt_correction: bool = True
    tilt_prior_sigma: float = math.radians(0.3)
    tilt_min_speed: float = 0.15
    tilt_fit_roll: bool = True
    tilt_pitch_when_slow: bool = True
    tilt_filter: bool = True
    tilt_sigma_pitch: float = math.radians(3.0)
    tilt_sigma_roll: float = math.radians(2.0)
    tilt_tau_s: float = 1.0
    tilt_fit_sigma: float = math.radians(0.3)
    tilt_fit_sigma_rel: float = 1.0
    tilt_fit_max: float = math.radians(5.0)
    tilt_anchor_sigma: float = math.radians(0.3)
    tilt_posture_fixes: int = 300
    tilt_rate_sigma: float = TRUNK_TILT_RATE_SIGMA
    tilt_gate_reset: int = 3
    tilt_gate_prior_sigma: float = math.radians(2.0)
    tilt_iterations: int = 2
    tilt_grid: int = 6
    homography_point_sigma_m: float = 0.002
    homography_iterations: int = 5
    homography_eps: float = 1e-3
    lean_correction: bool = True
    pitch_lean: bool = True
    pitch_lean_max: float = math.radians(3.0)
    lean_com_height_m: float = 0.95
    lean_min: float = math.radians(0.25)
    max_stride: int = 2
    stride_max_turn_rate: float = math.radians(10.0)
    flow: bool = True
    flow_without_patch: bool = True
    flow_without_patch_max_scale: float = 1.0
    flow_config: FloorFlowConfig = field(default_factory=FloorFlowConfig)


@dataclass
class OdometryStep:
    """Body motion between two frames.

    Attributes:
        t0, t1: timestamps of the earlier and later frame, s.
        delta: (3,) ``(dx, dy, dyaw)``: the body pose at ``t1`` in the body frame at ``t0`` (m, m, rad).
        cov: (3, 3) covariance of ``delta``.
        quality: phase-correlation response (0-1, higher is better).
        rho: ECC correlation of the patch's match (0-1; below ``OdometryConfig.min_ecc`` a weak
            match, see ``weak_ecc``); NaN for a step the floor flow measured without a patch
            match. For diagnostics: the covariance already carries what it says.
    """

    t0: float
    t1: float
    delta: np.ndarray
    cov: np.ndarray
    quality: float
    rho: float = float("nan")


@dataclass
class FloorPatch:
    """The floor square seen as the bird's-eye image (body frame, metres).

    Bird's-eye pixel (col, row) is the floor point ``origin + A @ (col, row)``, with ``A`` (2, 2) =
    ``res * [[0, -1], [-1, 0]]``: rows run backwards (image up = forward), columns to the right.
    """

    x_near: float
    x_far: float
    y_left: float
    side: float
    res: float
    origin: np.ndarray
    A: np.ndarray

    @property
    def centre(self) -> np.ndarray:
        """(2,) centre of the square, body frame (m)."""
        return np.array([0.5 * (self.x_near + self.x_far), self.y_left - 0.5 * self.side])


def _lag_through_ramp(y0: float, u0: float, u1: float, T: float, tau: float) -> float:
    """The first-order lag ``y' = (u - y) / tau`` after ``T`` s from ``y0``, its input ``u`` going
    linearly from ``u0`` to ``u1`` (same units as ``y0``; ``T``, ``tau`` > 0, s)."""
    k = (u1 - u0) / T
    return u1 - k * tau + (y0 - u0 + k * tau) * math.exp(-T / tau)


def flow_cov_scale(residual_px: float, config: OdometryConfig) -> float:
    """Factor on the covariance of a step the floor flow measured with median reprojection error
    ``residual_px`` (see ``OdometryConfig.flow_cov_ref_px``; 1 when off or the residual unknown)."""
    ref = config.flow_cov_ref_px
    if not (ref > 0.0 and math.isfinite(residual_px)):
        return 1.0
    return min(1.0, max(config.flow_cov_min_scale, (residual_px / ref) ** config.flow_cov_power))


def refused_flow_cov_scale(residual_px: float | None, limit_px: float, config: OdometryConfig) -> float:
    """Factor on the covariance of a patch step whose floor-flow fit was refused with median
    reprojection error ``residual_px``, the flow's limit for a fit on this floor being ``limit_px``
    (see ``OdometryConfig.refused_flow_cov_power``; 1 when off, the residual unknown or within the
    limit)."""
    power = config.refused_flow_cov_power
    if not (power > 0.0 and limit_px > 0.0 and residual_px is not None and math.isfinite(residual_px)):
        return 1.0
    return max(1.0, (residual_px / limit_px) ** power)


def overlap_mask(W: np.ndarray, m: int) -> np.ndarray:
    """(m, m) uint8 mask of the pixels of an m x m patch that the map ``W`` (2, 3; this patch's pixels
    -> the earlier patch's) sends inside the earlier patch: 255 there, 0 elsewhere.

    ECC reads its mask in the earlier patch's pixels (its ``inputMask``), where this one keeps
    those that ``W`` sends inside the patch once more: ECC, which leaves out what falls outside the
    earlier patch by itself, then correlates the overlap less a band as wide as ``W``'s motion
    (see ``OdometryConfig.bridge_overlap_mask``)."""
    full = np.full((m, m), 255, np.uint8)
    return cv2.warpAffine(
        full,
        np.asarray(W, np.float32),
        (m, m),
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )


def _rot2(a: float) -> np.ndarray:
    """(2, 2) rotation by ``a`` rad."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s], [s, c]])


def _kabsch(p1: np.ndarray, p0: np.ndarray) -> np.ndarray:
    """(dx, dy, dyaw) of the rigid map best taking points ``p1`` (N, 2) to ``p0`` (N, 2)."""
    m1, m0 = p1.mean(axis=0), p0.mean(axis=0)
    H = (p1 - m1).T @ (p0 - m0)
    yaw = math.atan2(H[0, 1] - H[1, 0], H[0, 0] + H[1, 1])
    t = m0 - _rot2(yaw) @ m1
    return np.array([t[0], t[1], yaw])


def _arc(v: np.ndarray, turn: float, dt: float) -> np.ndarray:
    """Body step (3,) ``(dx, dy, dyaw)`` over ``dt`` s at body-frame velocity ``v`` (2,) m/s while
    turning steadily by ``turn`` rad: the velocity turns with the body, int_0^dt R(turn s/dt) v ds."""
    if abs(turn) < 1e-6:
        return np.array([v[0] * dt, v[1] * dt, turn])
    s, c = math.sin(turn), math.cos(turn)
    M = (dt / turn) * np.array([[s, c - 1.0], [1.0 - c, s]])
    return np.array([*(M @ np.asarray(v, float)), turn])


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(dx, dy, dyaw) of the planar motion ``a`` followed by ``b`` (``b`` in ``a``'s frame)."""
    return np.array([*(a[:2] + _rot2(a[2]) @ b[:2]), a[2] + b[2]])


def _compose_steps(a: OdometryStep, b: OdometryStep) -> OdometryStep:
    """The step ``a`` followed by ``b`` (from ``a.t0`` to ``b.t1``), its covariance carried through
    the composition's Jacobians (the two steps' errors are independent)."""
    c, s = math.cos(a.delta[2]), math.sin(a.delta[2])
    bx, by = b.delta[0], b.delta[1]
    Ja = np.array([[1.0, 0.0, -s * bx - c * by], [0.0, 1.0, c * bx - s * by], [0.0, 0.0, 1.0]])
    Jb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    cov = Ja @ a.cov @ Ja.T + Jb @ b.cov @ Jb.T
    return OdometryStep(
        a.t0, b.t1, _compose(a.delta, b.delta), cov, min(a.quality, b.quality), float(np.fmin(a.rho, b.rho))
    )


def _invert2(a: np.ndarray) -> np.ndarray:
    """(dx, dy, dyaw) of the inverse planar motion of ``a``."""
    return np.array([*(-(_rot2(-a[2]) @ a[:2])), -a[2]])


def _apply_h(H: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Points (N, 2) through the homography ``H`` (3, 3)."""
    x = np.column_stack([p, np.ones(len(p))]) @ H.T
    return x[:, :2] / x[:, 2:]


def _weighted_rigid_fit(q1: np.ndarray, q0: np.ndarray, S: np.ndarray) -> np.ndarray:
    """(2, 3) rigid map ``q0 ~ R q1 + t`` minimising sum (r_i^T S_i r_i) with 2x2 weights ``S`` (N, 2, 2):
    one Gauss-Newton step from the unweighted fit (the maps fitted here are near-rigid)."""
    d = _kabsch(q1, q0)
    R = _rot2(d[2])
    r = q0 - q1 @ R.T - d[:2]
    Jt = (q1 @ R.T) @ np.array([[0.0, 1.0], [-1.0, 0.0]])  # d(R q)/d(angle) = J R q, J = [[0, -1], [1, 0]]
    J = np.zeros((len(q1), 2, 3))
    J[:, :, 0] = Jt
    J[:, 0, 1] = J[:, 1, 2] = 1.0
    SJ = S @ J  # (N, 2, 3)
    N = np.tensordot(J, SJ, axes=([0, 1], [0, 1]))
    g = np.tensordot(SJ, r, axes=([0, 1], [0, 1]))
    step = np.linalg.solve(N, g)
    a = d[2] + step[0]
    return np.hstack([_rot2(a), (d[:2] + step[1:])[:, None]])


def _floor_hit(c: np.ndarray, rays: np.ndarray, rx, ry):
    """(x, y) where ``rays`` (N, 3) from the camera centre ``c`` (3,) meet the floor after a small
    rotation (``rx`` about body x, ``ry`` about body y) about the camera: d + (rx, ry, 0) x d.
    Scalars or (k, 1) columns."""
    ddx = rays[:, 0] + ry * rays[:, 2]
    ddy = rays[:, 1] - rx * rays[:, 2]
    ddz = rays[:, 2] + rx * rays[:, 1] - ry * rays[:, 0]
    k = -c[2] / ddz
    return c[0] + k * ddx, c[1] + k * ddy


def sees_legs(rig_camera: RigCamera, config: OdometryConfig | None = None) -> bool:
    """Whether the camera sees the wearer's feet and legs: as its rig entry says (``legs_in_view``),
    else (not stated) whether it looks forward and sees the floor within ``legs_reach_m`` of the
    vest point, where the feet step (:func:`nearest_floor_ahead`)."""
    if rig_camera.legs_in_view is not None:
        return bool(rig_camera.legs_in_view)
    cfg = config or OdometryConfig()
    near = nearest_floor_ahead(rig_camera, cfg)
    return near is not None and near < cfg.legs_reach_m


def legs_zone(rig_camera: RigCamera, config: OdometryConfig) -> tuple[float, float]:
    """(reach, half width) m of the floor ahead of the vest point that the odometry leaves to the
    wearer's legs: ``legs_reach_m``, ``legs_half_width_m`` for a camera that sees them
    (:func:`sees_legs`), else (0, 0)."""
    if config.legs_reach_m > 0 and config.legs_half_width_m > 0 and sees_legs(rig_camera, config):
        return float(config.legs_reach_m), float(config.legs_half_width_m)
    return 0.0, 0.0


def nearest_floor_ahead(rig_camera: RigCamera, config: OdometryConfig | None = None) -> float | None:
    """How far ahead of the vest point (m, along the body's +x) the nearest floor the camera sees
    lies (its image's bottom row, inset by 3 %, rays at least ``min_depression`` down), or None for
    a camera that sees no floor ahead (looking up, back or sideways): where the wearer's feet enter
    the view when it is within ``OdometryConfig.legs_reach_m``."""
    min_depression = (config or OdometryConfig()).min_depression
    cam = rig_camera.camera
    if float(rig_camera.T_body_camera[0, 2]) <= 0.0:
        return None  # the optical axis does not point forward
    u = np.linspace(0.03, 0.97, 33) * (cam.width - 1)
    px = np.column_stack([u, np.full_like(u, 0.97 * (cam.height - 1))])
    floor = floor_under_pixels(rig_camera, px, min_depression)
    ahead = floor[np.isfinite(floor[:, 0]), 0] - float(rig_camera.vest_point[0])
    ahead = ahead[ahead > 0.0]
    return float(ahead.min()) if len(ahead) else None


def clip_to_grain(high: np.ndarray, sigmas: float, where: np.ndarray | None = None) -> np.ndarray:
    """A copy of ``high`` (a high-passed patch (m, m) float32, about zero mean) clipped at ``sigmas``
    times its robust standard deviation (the median absolute value / 0.6745: the floor's grain and
    the noise, which fill most of it), that measured over the pixels ``where`` (m, m) bool is True
    (None: all); ``high`` itself when ``sigmas`` <= 0, nothing is beyond or nothing is measured."""
    if not sigmas > 0.0:
        return high
    a = np.abs(high)
    flat = a.ravel() if where is None else a[where]
    if not flat.size:
        return high
    limit = sigmas * float(np.partition(flat, flat.size // 2)[flat.size // 2]) / 0.6745
    if not (limit > 0.0 and float(a.max()) > limit):
        return high
    return np.clip(high, -limit, limit)


def floor_patch(rig_camera: RigCamera, config: OdometryConfig | None = None) -> FloorPatch:
    """The largest floor square (side <= ``max_side_m``) in front of the camera that the image covers.

    The square is axis-aligned in the body frame and centred on the camera's lateral position; its
    near edge is searched over the footprint. Raises CalibrationError if the camera does not see
    enough floor (looking up, or a rig far above the floor).
    """
    cfg = config or OdometryConfig()
    cam = rig_camera.camera
    if rig_camera.T_body_camera[2, 3] <= cfg.min_camera_height:
        raise CalibrationError(f"camera {rig_camera.name!r}: floor odometry needs the camera above the floor")
    m = cfg.image_margin
    # The image border (inset by the margin), densely, as the footprint polygon on the floor.
    k = np.linspace(0.0, 1.0, _BORDER_SAMPLES)
    u0, u1 = m * (cam.width - 1), (1 - m) * (cam.width - 1)
    v0, v1 = m * (cam.height - 1), (1 - m) * (cam.height - 1)
    border = np.vstack(
        [
            np.column_stack([u0 + (u1 - u0) * k, np.full_like(k, v0)]),
            np.column_stack([np.full_like(k, u1), v0 + (v1 - v0) * k]),
            np.column_stack([u1 - (u1 - u0) * k, np.full_like(k, v1)]),
            np.column_stack([np.full_like(k, u0), v1 - (v1 - v0) * k]),
        ]
    )
    floor = floor_under_pixels(rig_camera, border, cfg.min_depression)
    ok = np.all(np.isfinite(floor), axis=1)
    if ok.sum() < _MIN_FLOOR_POINTS:
        raise CalibrationError(f"camera {rig_camera.name!r}: sees too little floor for odometry")
    # Rays above the depression limit are dropped: what is left is the footprint's near part.
    poly = cv2.convexHull(floor[ok].astype(np.float32)).reshape(-1, 2).astype(float)
    yc = float(rig_camera.T_body_camera[1, 3])
    # The hull is convex: a point is inside (or on it) when it is on the same side of every edge.
    # One vectorised test per square instead of a pointPolygonTest call per edge point: the search
    # below made 24,000 of those, a visible share of a replay's start-up.
    edge_dir = np.roll(poly, -1, axis=0) - poly  # (K, 2)
    t = np.linspace(0.0, 1.0, _EDGE_SAMPLES)

    def fits(x0: np.ndarray, s: np.ndarray) -> np.ndarray:
        """(k,) whether each square (near edge ``x0`` (k,), side ``s`` (k,)) lies in the footprint."""
        x0, s = x0[:, None], s[:, None]
        along, ones = x0 + s * t, np.ones_like(t)
        across = yc - s / 2 + s * t
        ex = np.concatenate([along, along, x0 * ones, (x0 + s) * ones], axis=1)  # (k, 4 n)
        ey = np.concatenate([(yc - s / 2) * ones, (yc + s / 2) * ones, across, across], axis=1)
        side = edge_dir[:, 0] * (ey[..., None] - poly[:, 1]) - edge_dir[:, 1] * (ex[..., None] - poly[:, 0])
        return np.all(side >= 0, axis=(1, 2)) | np.all(side <= 0, axis=(1, 2))

    xs = floor[ok, 0]
    x_min = float(xs.min())
    reach, half = legs_zone(rig_camera, cfg)
    if reach > 0 and abs(yc - float(rig_camera.vest_point[1])) < half:
        # In front of the wearer's own legs (see ``legs_reach_m``).
        x_min = max(x_min, float(rig_camera.vest_point[0]) + reach)
        if x_min >= xs.max():
            raise CalibrationError(f"camera {rig_camera.name!r}: sees no floor beyond the wearer's legs")
    # Each near edge's largest square by bisection, all near edges at once (one call per step
    # instead of one per edge and step: 1,200 calls were a visible share of a replay's start-up).
    near_edges = np.linspace(x_min, xs.max(), _NEAR_EDGE_STEPS)
    lo, hi = np.zeros(len(near_edges)), np.full(len(near_edges), cfg.max_side_m)
    for _ in range(_BISECTIONS):
        mid = 0.5 * (lo + hi)
        ok_mid = fits(near_edges, mid)
        lo, hi = np.where(ok_mid, mid, lo), np.where(ok_mid, hi, mid)
    best = (0.0, 0.0)
    # Squares nearest the camera first (of equal size the first found stays): a nearer patch is seen
    # finer. A camera looking back sees its nearest floor at the footprint's largest x, not its least.
    x_cam = float(rig_camera.T_body_camera[0, 3])
    for k in sorted(range(len(near_edges)), key=lambda k: abs(near_edges[k] + 0.5 * cfg.max_side_m - x_cam)):
        if lo[k] > best[1] + _SIDE_TOL_M:
            best = (float(near_edges[k]), float(lo[k]))
    x0, side = best
    if side < cfg.min_side_m:
        raise CalibrationError(
            f"camera {rig_camera.name!r}: the floor square in view is {side:.2f} m, too small for odometry"
        )
    res = side / cfg.patch_px
    origin = np.array([x0 + side - 0.5 * res, yc + side / 2 - 0.5 * res])  # centre of pixel (0, 0)
    A = res * np.array([[0.0, -1.0], [-1.0, 0.0]])
    return FloorPatch(x0, x0 + side, yc + side / 2, side, res, origin, A)


def _grown_sigmas(floor: float, rel: float, d_pitch: float, d_roll: float) -> tuple[float, float]:
    """A fitted tilt change's actual (pitch, roll) standard deviations (rad): ``floor`` in quadrature
    with the share ``rel`` of the change (rad) itself."""
    return math.hypot(floor, rel * d_pitch), math.hypot(floor, rel * d_roll)


class FloorOdometry:
    """Planar body motion between consecutive frames of one rig camera, from the floor texture."""

    def __init__(self, rig_camera: RigCamera, config: OdometryConfig | None = None):
        self.config = cfg = config or OdometryConfig()
        self.rig_camera = rig_camera
        self.patch = p = floor_patch(rig_camera, cfg)
        n = cfg.patch_px
        ss = int(cfg.supersample)
        if ss < 1 or ss & (ss - 1):
            raise InputError(f"odometry supersample must be a power of 2 (1, 2, 4, ...), got {cfg.supersample}")
        # A zero or negative factor would state a flow step exact or its covariance indefinite.
        if not (cfg.flow_cov_ref_px >= 0.0 and cfg.flow_cov_power > 0.0 and 0.0 < cfg.flow_cov_min_scale <= 1.0):
            raise InputError(
                "odometry flow_cov_ref_px must be >= 0, flow_cov_power > 0 and flow_cov_min_scale in (0, 1], got "
                f"{cfg.flow_cov_ref_px}, {cfg.flow_cov_power}, {cfg.flow_cov_min_scale}"
            )
        if not cfg.refused_flow_cov_power >= 0.0:
            raise InputError(f"odometry refused_flow_cov_power must be >= 0, got {cfg.refused_flow_cov_power}")
        # Sampled from the half-resolution level (see ``patch_from_half``): half the samples per side.
        self._from_half = cfg.patch_from_half and pixel_scale(rig_camera.camera) <= 1.0 + 1e-6
        if self._from_half:
            ss = max(1, ss // 2)
        m = n * ss
        # pyrDown's output pixel j is centred on its input pixel 2j: supersampled pixel i is patch
        # coordinate i / ss.
        g = np.arange(m) / ss
        cols, rows = np.meshgrid(g, g)
        pts = p.origin + np.stack([cols.ravel(), rows.ravel()], axis=1) @ p.A.T
        T_cb = np.linalg.inv(rig_camera.T_body_camera)
        pc = np.column_stack([pts, np.zeros(len(pts))]) @ T_cb[:3, :3].T + T_cb[:3, 3]
        px = rig_camera.camera.project(pc).astype(np.float32)
        if self._from_half:
            px *= 0.5  # pyrDown's pixel j is centred on the frame's pixel 2j
        # Float maps: OpenCV's fixed-point (CV_16SC2) remap ran 1.6 times slower on this patch.
        self._map_x = np.ascontiguousarray(px[:, 0].reshape(m, m))
        self._map_y = np.ascontiguousarray(px[:, 1].reshape(m, m))
        self._levels = ss.bit_length() - 1
        self._window = cv2.createHanningWindow((n, n), cv2.CV_32F)
        self._A_inv = np.linalg.inv(p.A)
        self._cam_centre = np.asarray(rig_camera.T_body_camera, float)[:3, 3].copy()
        g5 = (np.arange(_TILT_GRID) + 0.5) * n / _TILT_GRID - 0.5  # cell centres
        gc, gr = np.meshgrid(g5, g5)
        self._grid = np.column_stack([gc.ravel(), gr.ravel()])  # patch pixels carried through the lean
        self._lean_state: list[float] | None = None  # see _update_lean
        self._pitch_state: list[float] | None = None  # (time, speed, lagged speed), see _update_pitch
        self._lean_tau = math.sqrt(cfg.lean_com_height_m / _G)
        self._centre = p.centre
        cx, cy = self._centre
        self._lever = np.array([[1.0, 0.0, cy], [0.0, 1.0, -cx], [0.0, 0.0, 1.0]])
        self._prev: tuple[float, np.ndarray] | None = None
        self._intervals: deque[float] = deque(maxlen=_STRIDE_INTERVALS)  # recent steps' frame intervals (s)
        self._skipped = 0  # frames skipped since the last one measured (see wants)
        self._held: tuple[float, np.ndarray] | None = None  # the frame skipped last (see hold)
        # The last frame measured made a step from a strong match near its turn guess (not a
        # composed one): only then may the next frame be skipped.
        self._last_sure = False
        self._last_turn: tuple[float, float] | None = None  # (time, yaw rate rad/s) of the last step
        self._criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, cfg.ecc_iterations, cfg.ecc_eps)
        self._last_twist: tuple[float, np.ndarray] | None = None  # (time, (vx, vy, w)) of the last step
        # The tilt fit's grid: patch pixels of the current frame, and the nominal rays to their floor
        # points from the camera (body frame).
        g = np.linspace(0.1, 0.9, cfg.tilt_grid) * (n - 1)
        q1 = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
        self._tilt_q1 = np.column_stack([q1, np.ones(len(q1))])
        c = rig_camera.T_body_camera[:3, 3]
        f1 = q1 @ p.A.T + p.origin
        self._tilt_rays = np.column_stack([f1 - c[:2], np.full(len(f1), -c[2])])
        rs = cfg.rolling_shutter and rig_camera.readout_s > 0
        self._rs = self._rolling_shutter_grid(n, ss, T_cb) if rs else None
        self.tilt_gated_in_row = 0  # sticker fixes refused by the tilt gate in a row (see tilt_gate_result)
        self._flow = (
            FloorFlow(
                rig_camera,
                cfg.flow_config,
                rolling_shutter=cfg.rolling_shutter,
                legs=legs_zone(rig_camera, cfg),
            )
            if cfg.flow
            else None
        )
        self._prev_gray: np.ndarray | None = None  # the frame of _prev, for the flow
        self.flow_steps = 0  # steps the flow refined
        self.bridged = 0  # steps that bridged dropped frames (see bridge_max_dt)
        self.bridges_unverified = 0  # bridges the floor flow did not verify (see bridge_max_flow_residual_px)
        self.flow_refused = 0  # steps whose flow fit was refused (the patch's step stands)
        self.flow_only_steps = 0  # steps the patch could not match, measured by the flow alone
        self.steps_unverified = 0  # patch steps refused: the flow left more than max_flow_residual_px
        self.tilt_fits_refused = 0  # fitted tilt changes beyond tilt_fit_max, dropped
        self.dark_frames = 0  # frames whose patch was too little lit to measure (see min_lit_fraction)
        # The flow fit's median reprojection error (px) in the last measure, kept or refused; None
        # when it made none (see FloorFlow.last_residual).
        self.last_flow_residual: float | None = None
        self._pixel_scale = pixel_scale(rig_camera.camera)
        #: Whether a step the patch cannot match is measured by the floor flow alone (see
        #: ``flow_without_patch`` and ``flow_without_patch_max_scale``).
        self.flow_without_patch = (
            cfg.flow_without_patch
            and self._flow is not None
            and self._pixel_scale <= cfg.flow_without_patch_max_scale * (1 + 1e-6)
        )
        self._torso = (
            TorsoTilt(
                cfg.tilt_sigma_pitch,
                cfg.tilt_sigma_roll,
                cfg.tilt_tau_s,
                cfg.tilt_fit_sigma * self._pixel_scale,
                cfg.tilt_anchor_sigma * self._pixel_scale,
                cfg.tilt_posture_fixes,
                rate_sigma=cfg.tilt_rate_sigma,
            )
            if cfg.tilt_correction and cfg.tilt_filter
            else None
        )

    def _rolling_shutter_grid(self, n: int, ss: int, T_cb: np.ndarray) -> tuple[np.ndarray, ...]:
        """(q (n*n, 2) floor points, row delays (n*n,), d pixel / d q (n*n, 2, 2)) on the coarse grid
        whose bilinear resize to the supersampled maps is aligned (coarse pixel j sits at fine
        coordinate (j + 0.5) ss - 0.5, i.e. patch coordinate j + 0.5 - 0.5 / ss)."""
        p, cam = self.patch, self.rig_camera.camera
        g = np.arange(n) + 0.5 - 0.5 / ss
        cols, rows = np.meshgrid(g, g)
        q = p.origin + np.stack([cols.ravel(), rows.ravel()], axis=1) @ p.A.T

        def project(pts: np.ndarray) -> np.ndarray:
            pc = np.column_stack([pts, np.zeros(len(pts))]) @ T_cb[:3, :3].T + T_cb[:3, 3]
            return cam.project(pc)

        px = project(q)
        h = 1e-3  # 1 mm: the projection is smooth over it
        J = np.stack([(project(q + (h, 0.0)) - px) / h, (project(q + (0.0, h)) - px) / h], axis=2)
        if self._from_half:
            J = 0.5 * J  # the remap's pixels are the half level's
        return q, row_delay_s(px[:, 1], cam.height, self.rig_camera.readout_s), J

    def _maps(self, body_twist: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The remap maps for one frame: the nominal ones, moved for the rolling shutter when known."""
        if self._rs is None or body_twist is None:
            return self._map_x, self._map_y
        q0, q1, d, J00, J01, J10, J11 = self._rs_columns()
        vx, vy, w = (float(a) for a in np.asarray(body_twist, float).ravel()[:3])
        # A floor point fixed in the world, seen d seconds after the frame time, sits at
        # q - d (v + w x q) in the body frame of the frame time.
        u0, u1 = vx - w * q1, vy + w * q0
        n, m = self.config.patch_px, self._map_x.shape[0]
        # x and y apart, from contiguous columns (numpy over a trailing axis of 2, and strided adds
        # of the interleaved resize, cost more than the arithmetic). One two-channel resize: resized
        # apart, OpenCV's single-channel path rounds differently in the last bit.
        shift = np.empty((n * n, 2), np.float32)
        shift[:, 0] = -(d * (J00 * u0 + J01 * u1))
        shift[:, 1] = -(d * (J10 * u0 + J11 * u1))
        fx, fy = cv2.split(cv2.resize(shift.reshape(n, n, 2), (m, m), interpolation=cv2.INTER_LINEAR))
        return self._map_x + fx, self._map_y + fy

    def _rs_columns(self) -> tuple[np.ndarray, ...]:
        """The rolling-shutter grid (see :meth:`_rolling_shutter_grid`) as contiguous columns: q_x,
        q_y, row delays, and the four entries of d pixel / d q, each (n*n,)."""
        if getattr(self, "_rs_cols", None) is None:
            q, d, J = self._rs
            cols = (q[:, 0], q[:, 1], d, J[:, 0, 0], J[:, 0, 1], J[:, 1, 0], J[:, 1, 1])
            self._rs_cols = tuple(np.ascontiguousarray(c) for c in cols)
        return self._rs_cols

    def birdseye(self, gray: np.ndarray, body_twist: np.ndarray | None = None) -> np.ndarray:
        """The bird's-eye patch (patch_px, patch_px) of a (H, W) uint8 frame, float32, high-passed.

        ``body_twist`` (vx, vy, yaw rate; body frame, m/s and rad/s): the body's motion, for a
        rolling-shutter camera (see the module docstring); None: the nominal patch. Unlit parts
        (see ``dark_level``) are zero."""
        return self._lit_patch(gray, body_twist)[0]

    def _lit_patch(self, gray: np.ndarray, body_twist: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """:meth:`birdseye`'s patch, and the fraction of it that is lit (see ``dark_level``)."""
        cam = self.rig_camera.camera
        require_gray(gray, "odometry")
        if gray.shape != (cam.height, cam.width):
            raise InputError(f"odometry wants a {cam.width}x{cam.height} greyscale frame, got shape {gray.shape}")
        map_x, map_y = self._maps(body_twist)
        src = gray
        if self._from_half:
            src = self._flow.half_level(gray) if self._flow is not None else cv2.pyrDown(gray)
        img = cv2.remap(src, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        if self._levels:
            img = cv2.pyrDown(img)
        f = img.astype(np.float32)  # float before further reduction: keeps the averaged precision
        for _ in range(self._levels - 1):
            f = cv2.pyrDown(f)
        s = self.config.highpass_sigma_px
        high = f - cv2.GaussianBlur(f, (0, 0), s) if s > 0 else f - float(f.mean())
        dark = f <= self.config.dark_level
        if not dark.any():
            return clip_to_grain(high, self.config.grain_clip_sigmas), 1.0
        # Unlit floor is fixed in the image, not on the floor: its edge, high-passed, would match
        # itself and say that the camera did not move. It is cut out with the band the high-pass
        # spreads the edge over (3 sigma), which leaves no structure fixed in the image.
        r = max(1, math.ceil(3.0 * s))
        cut = cv2.dilate(dark.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
        lit = cut == 0
        # The grain's level from the lit floor alone: the cut's zeros would lower it.
        high = clip_to_grain(high, self.config.grain_clip_sigmas, lit)
        high[~lit] = 0.0
        return high, float(np.count_nonzero(lit)) / lit.size

    def reset(self) -> None:
        """Forget the previous frame (the next :meth:`measure` returns None)."""
        self._prev = None
        self._prev_gray = None
        self._intervals.clear()
        self._skipped = 0
        self._held = None
        self._last_sure = False
        self.forget_motion()

    def _learn_motion(self, t: float, level: np.ndarray, dt: float) -> None:
        """Note what a step ``level`` (3,) (dx, dy, dyaw, level body frame) over ``dt`` s ending at
        ``t`` says of the walk for the next ones: the lean into the turn, the turn guess and the
        twist (what :meth:`forget_motion` forgets)."""
        self._update_lean(t, level, dt)
        self._last_turn = (t, float(level[2]) / dt)
        self._last_twist = (t, level / dt)

    def forget_motion(self) -> None:
        """Forget what the last steps said of the walk (the turn guess, the last twist, the lean into
        the turn, the pitch with speed changes, the torso's filtered tilt), keeping the last frame:
        the next step is matched from it as after a gap. For a step the tracker refused (see
        ``LocaliserConfig.forget_refused_bridge``)."""
        self._last_turn = None
        self._last_twist = None
        self._lean_state = None
        self._pitch_state = None
        if self._torso is not None:
            self._torso.reset()

    def _lean(self, t: float) -> float | None:
        """The lean's roll (rad) at time ``t`` as the steps up to then say (see
        :meth:`_update_lean`); None when off, or when no step that recent is known."""
        st = self._lean_state
        if (
            not self.config.lean_correction
            or st is None
            or not 0.0 <= t - st[0] <= self.config.turn_memory * self.config.max_dt
        ):
            return None
        return float(st[2])

    def _lean_roll(self, t: float) -> float:
        """The lean's roll (rad) at time ``t`` (0 when unknown or off)."""
        roll = self._lean(t)
        return 0.0 if roll is None else roll

    def tilt_consistent(self, t: float, T_world_camera: np.ndarray, chi2: float) -> tuple[bool, float]:
        """Whether a camera pose ``T_world_camera`` (4, 4) of this odometry's camera, measured at
        ``t``, tilts the torso as the filtered tilt expects (see :meth:`TorsoTilt.consistent`);
        always True without the filter."""
        if self._torso is None:
            return True, 0.0
        pitch, roll = torso_tilt(T_world_camera, self.rig_camera.T_body_camera)
        return self._torso.consistent(
            float(t), self._lean_roll(t), pitch, roll, chi2, self.config.tilt_gate_prior_sigma
        )

    def tilt_gate_result(self, passed: bool) -> None:
        """Count fixes refused by the tilt gate in a row; after ``tilt_gate_reset`` of them the tilt
        estimate is forgotten (``tilt_gated_in_row`` back to 0)."""
        self.tilt_gated_in_row = 0 if passed else self.tilt_gated_in_row + 1
        if self.tilt_gated_in_row >= self.config.tilt_gate_reset and self._torso is not None:
            self._torso.reset()
            self.tilt_gated_in_row = 0

    def anchor_tilt_angles(self, t: float, pitch: float, roll: float) -> None:
        """Fuse a measured torso (pitch, roll) (rad) at time ``t`` (see :mod:`tagloc.vision.torso_tilt`)."""
        if self._torso is not None:
            self._torso.anchor(float(t), self._lean_roll(t), float(pitch), float(roll))

    def wants(self, t: float, stride: bool = True) -> bool:
        """Whether to measure the frame at ``t`` (s), or skip it so that the next step spans two frame
        intervals (see ``max_stride``; ``stride`` False: measure every frame). Call :meth:`measure`
        for a frame this says yes to, :meth:`hold` for one it skips."""
        cfg = self.config
        prev = self._prev
        dt_frame = self._frame_interval()
        skip = (
            stride
            and cfg.max_stride > 1
            and self._skipped < cfg.max_stride - 1
            and prev is not None
            and self._last_sure
            and dt_frame is not None
            # A frame dropped since the last one measured: the step is long already.
            and 0.0 < float(t) - prev[0] <= _STRIDE_DT_SLACK * dt_frame
            and 2.0 * (float(t) - prev[0]) <= cfg.max_dt
            and self._last_turn is not None
            and abs(self._last_turn[1]) <= cfg.stride_max_turn_rate
        )
        if skip:
            self._skipped += 1
        return not skip

    def _frame_interval(self) -> float | None:
        """The camera's frame interval (s): the shortest of the recent steps' per-interval times (a
        dropped frame lengthens a step, jitter shortens one a little); None before any step."""
        return min(self._intervals) if self._intervals else None

    def hold(self, gray: np.ndarray, t: float) -> None:
        """Keep the frame (``gray`` (H, W) uint8, time ``t`` s) that :meth:`wants` just skipped: if the
        match over both intervals is in doubt, :meth:`measure` goes through it after all."""
        self._held = (float(t), gray)

    def measure(
        self,
        gray: np.ndarray,
        t: float,
        body_twist: np.ndarray | None = None,
        walk_speed: float | None = None,
        refine: bool = True,
    ) -> OdometryStep | None:
        """Body motion from the previous frame measured to this one (``gray`` (H, W) uint8, time ``t``
        s), or None.

        None for the first frame, after a gap longer than ``max_dt``, out-of-order time, or when the
        match is poor (texture-less floor, heavy blur, too large a shift). ``body_twist``: the
        body's predicted motion (see :meth:`birdseye`), for a rolling-shutter camera (see
        ``rs_twist_from_tracker``; without it, the odometry's own last step is used).
        After a skipped frame (:meth:`wants`, :meth:`hold`), a match over both intervals that is
        weak or ended far from the turn guessed (the turn changed) is replaced by the two steps
        through the skipped frame, composed. ``walk_speed``: the walk's forward speed (m/s) predicted
        for this frame by the tracker, for the pitch lean (see ``pitch_lean``); None: not tracking.
        ``refine`` False: the patch's step alone, for a frame that sticker fixes will very likely
        place (``LocaliserConfig.skip_flow_after_fix``): neither the flow's refinement (``flow``)
        nor the homography's tilt fit (``tilt_correction``) is made, and the torso's tilt filter
        only predicts through the step (the fixes' tilt anchors it at the frame).
        """
        t = float(t)
        self.last_flow_residual = None
        small, lit = self._lit_patch(gray, self._twist(t, body_twist))
        if lit < self.config.min_lit_fraction:
            # Too little floor to measure a step to or from (see ``min_lit_fraction``).
            self._prev, self._prev_gray, self._held, self._skipped, self._last_sure = None, None, None, 0, False
            self.dark_frames += 1
            return None
        prev, self._prev = self._prev, (t, small)
        # Kept by reference: frame sources hand over a new array per frame.
        prev_gray, self._prev_gray = self._prev_gray, (gray if self._flow is not None else None)
        held, self._held = self._held, None
        self._last_sure = False
        stride, self._skipped = self._skipped + 1, 0  # frame intervals this step spans
        if prev is None:
            return None
        dt = t - prev[0]
        if not (0.0 < dt <= max(self.config.max_dt, self.config.bridge_max_dt)):
            return None
        pair = (prev_gray, gray) if prev_gray is not None else None
        if dt > self.config.max_dt:
            # Frames were dropped: bridge the gap from the walk predicted through it. The floor flow
            # verifies the bridge (``bridge_max_flow_residual_px``) even where ``refine`` would
            # skip it: nothing else checks a match across a gap.
            step = self._bridge(prev, (t, small), body_twist, pair, refine)
            if step is not None:
                self.bridged += 1
                self._update_pitch(t, walk_speed)
            return step
        match = self._match(prev, (t, small))
        if held is not None and prev[0] < held[0] < t and (match is None or not match[3]):
            mid = (held[0], self.birdseye(held[1], self._twist(held[0], body_twist)))
            first = self._step(prev, mid, self._match(prev, mid), refine=refine)
            if first is None:
                return None
            second = self._step(mid, (t, small), self._match(mid, (t, small)), refine=refine)
            if second is None:
                return None
            step = _compose_steps(first, second)
        else:
            step = self._step(prev, (t, small), match, pair if refine else None, refine=refine)
            cfg, residual = self.config, self.last_flow_residual
            if (
                step is not None
                and residual is not None
                and residual > cfg.max_flow_residual_px
                and (self._flow.residual_floor() or 0.0) >= cfg.plain_floor_residual_px
            ):
                # On a floor this plain the patch is as noise-bound as the flow, so a step whose
                # floor points fit no rigid motion near it is trusted by neither (see
                # max_flow_residual_px; on a textured floor the residual means a smeared frame).
                if cfg.forget_unverified:
                    self.forget_motion()
                self.steps_unverified += 1
                return None
            if step is None:
                step = self._flow_only(prev, (t, small), pair, body_twist, refine)
                if step is None:
                    return None
            else:
                self._last_sure = match[3]
        self._intervals.append(dt / stride)
        self._update_pitch(t, walk_speed)
        return step

    def _flow_only(
        self,
        prev: tuple[float, np.ndarray],
        cur: tuple[float, np.ndarray],
        grays: tuple[np.ndarray, np.ndarray] | None,
        body_twist: np.ndarray | None,
        refine: bool,
    ) -> OdometryStep | None:
        """The step the patch could not match, measured by the floor flow alone from the walk's
        predicted step (``flow_without_patch``), or None; its ``quality`` is 0 (no phase-correlation
        peak stands behind it)."""
        cfg = self.config
        if not (self.flow_without_patch and refine and grays is not None):
            return None
        (t0, psmall), (t, small) = prev, cur
        dt = t - t0
        if self._last_twist is not None and 0.0 <= t0 - self._last_twist[0] <= cfg.turn_memory * cfg.max_dt:
            guess = self._last_twist[1] * dt
        elif body_twist is not None:
            guess = np.asarray(body_twist, float)[:3] * dt
        else:
            return None
        R_tilt = self._tilt(t0)
        lean_known = self._lean(t0) is not None
        flow = self._flow.refine(grays[0], grays[1], guess, dt, R_tilt)
        self.last_flow_residual = self._flow.last_residual
        if flow is None:
            return None
        self.flow_only_steps += 1
        self._learn_motion(t, flow.delta, dt)
        if cfg.tilt_correction:
            # (No patch match W: with the flow's fit, the tilt change is the flow's own.)
            delta = self._untilted_step(small, psmall, None, flow.delta, t0, t, R_tilt, flow, refine, lean_known)
        else:
            delta = flow.delta
        cov = self.covariance(delta) * flow_cov_scale(flow.residual_px, cfg)
        return OdometryStep(t0, t, delta, cov, 0.0)

    def _twist(self, t: float, body_twist: np.ndarray | None) -> np.ndarray | None:
        """The body twist for a rolling-shutter patch at ``t``: ``body_twist`` (the tracker's
        prediction) when given and ``rs_twist_from_tracker``, else this odometry's last step's when
        recent, else ``body_twist``."""
        cfg = self.config
        if cfg.rs_twist_from_tracker and body_twist is not None:
            return body_twist
        if (
            self._rs is not None
            and self._last_twist is not None
            and 0.0 < t - self._last_twist[0] <= cfg.turn_memory * cfg.max_dt
        ):
            return self._last_twist[1]
        return body_twist

    def _match(
        self, prev: tuple[float, np.ndarray], cur: tuple[float, np.ndarray]
    ) -> tuple[float, np.ndarray, float, bool] | None:
        """ECC's rigid match of the patch ``cur`` (time, patch) onto ``prev``: (rho, W (2, 3) current
        -> earlier patch pixels, phase-correlation response, sure), or None. ``sure``: a strong match
        that ended near the turn first guessed. Changes no state."""
        cfg = self.config
        (t0, psmall), (t, small) = prev, cur
        dt = t - t0
        # First from the turn under way (the last measured rate; people's yaw acceleration is
        # limited, so it is usually within a degree of this frame's turn); if phase correlation or
        # ECC fails from there, or ECC ends far from it, also from the best of a grid of guesses.
        if self._last_turn is not None and 0.0 <= t0 - self._last_turn[0] <= cfg.turn_memory * cfg.max_dt:
            bound = self._turn_bound(dt)
            g0 = float(np.clip(self._last_turn[1] * dt, -bound, bound))
            rounds = ([g0], self._turn_grid(g0, dt))
        else:
            # No turn under way is known (first step, or after a gap): nothing says the turn is
            # near zero, and ECC from a wrong turn can settle on a plausible wrong optimum, so the
            # whole grid competes at once.
            g0 = 0.0
            rounds = ([g0] + self._turn_grid(g0, dt),)
        best: tuple[float, np.ndarray, float, bool] | None = None
        for guesses in rounds:
            found = self._ecc_from(psmall, small, guesses)
            if found is None:
                continue
            rho, W, response, _ = found
            # ECC that had to turn far from the guess may have stopped at a wrong optimum (the
            # turn changed fast), and a weak match may have a better one elsewhere: then compare
            # with the grid's start before trusting it.
            near = abs(self._turn(W[:, :2].astype(np.float64)) - g0) <= cfg.ecc_turn_tolerance * cfg.rotation_step
            sure = near and rho >= cfg.min_ecc and len(guesses) == 1
            if sure and abs(g0) >= cfg.turn_check_rate * dt:
                # In a fast turn the patch is smeared along the turn and its correlation is nearly
                # flat there: ECC's few iterations end near wherever they started, so a turn that
                # changed is not found from the last one. Starts a grid step either side compete.
                for g in (g0 - cfg.rotation_step, g0 + cfg.rotation_step):
                    alt = self._ecc_from(psmall, small, [g])
                    if alt is not None and alt[0] > rho:
                        rho, W, response, _ = alt
                        sure = abs(self._turn(W[:, :2].astype(np.float64)) - g0) <= (
                            cfg.ecc_turn_tolerance * cfg.rotation_step
                        )
            if best is None or rho > best[0]:
                best = (float(rho), W, response, sure)
            if near and rho >= cfg.min_ecc:
                break
        return best

    def _ecc_from(
        self,
        psmall: np.ndarray,
        small: np.ndarray,
        guesses: list[float],
        steps: list[np.ndarray] | None = None,
        bridge: bool = False,
    ) -> tuple[float, np.ndarray, float, np.ndarray] | None:
        """ECC from the best of the turn ``guesses`` (``steps``: whole predicted body steps, see
        :meth:`_initial_alignment`): (rho, W (2, 3) current -> earlier patch pixels,
        phase-correlation response, the start W), or None (no start, ECC failed, or rho below
        ``weak_ecc``/``min_ecc``). ``bridge``: a gap's match (:meth:`_bridge`), which runs ECC
        longer (``_BRIDGE_CRITERIA``) and must reach ``min_ecc``."""
        cfg = self.config
        start = self._initial_alignment(psmall, small, guesses, steps)
        if start is None:
            return None
        criteria, min_rho = (
            (_BRIDGE_CRITERIA, cfg.min_ecc) if bridge else (self._criteria, min(cfg.min_ecc, cfg.weak_ecc))
        )
        mask = overlap_mask(start[0], small.shape[0]) if bridge and cfg.bridge_overlap_mask else None
        try:
            rho, W = cv2.findTransformECC(small, psmall, start[0].copy(), cv2.MOTION_EUCLIDEAN, criteria, mask, 1)
        except cv2.error:
            return None
        if not (math.isfinite(rho) and rho >= min_rho):
            return None
        return float(rho), W, start[1], start[0].astype(np.float64)

    def _step(
        self,
        prev: tuple[float, np.ndarray],
        cur: tuple[float, np.ndarray],
        match: tuple[float, np.ndarray, float, bool] | None,
        grays: tuple[np.ndarray, np.ndarray] | None = None,
        predicted_shift: np.ndarray | None = None,
        refine: bool = True,
    ) -> OdometryStep | None:
        """The step from ``prev`` to ``cur`` (time, patch) from ECC's ``match`` (see :meth:`_match`), or
        None; follows the lean, the turn and the tilt to ``cur``'s time. ``grays``: the two frames
        themselves, for the flow's refinement (``flow``); None: the patch's step alone.
        ``predicted_shift``: the patch shift (2,) (pixels) the match started from when it bridged
        a gap (:meth:`_bridge`); the shift limit then applies to the match's departure from it.
        ``refine`` False: no homography tilt fit either (see :meth:`measure`)."""
        cfg = self.config
        if match is None:
            return None
        (t0, psmall), (t, small) = prev, cur
        dt = t - t0
        rho, W, response, _ = match
        W = W.astype(np.float64)
        shift = W[:, 2] if predicted_shift is None else W[:, 2] - predicted_shift
        if np.hypot(*shift) > cfg.max_shift_frac * cfg.patch_px * cfg.ecc_shift_allowance:
            return None
        R_tilt = self._tilt(t0)
        lean_known = self._lean(t0) is not None
        if R_tilt is None:
            level = self.body_motion(W[:, :2], W[:, 2])
        else:
            level = self.level_motion(W[:, :2], W[:, 2], R_tilt, small)
        # The rigid match guides the next frame (turn guess, rolling-shutter remap); the step
        # reported also has the tilt's change between the two frames taken out.
        self._learn_motion(t, level, dt)
        flow = None
        if grays is not None and self._flow is not None:
            flow = self._flow.refine(grays[0], grays[1], level, dt, R_tilt)
            self.last_flow_residual = self._flow.last_residual
            if flow is None:
                self.flow_refused += 1
            else:
                self.flow_steps += 1
        if cfg.tilt_correction:
            delta = self._untilted_step(small, psmall, W, level, t0, t, R_tilt, flow, refine, lean_known)
        else:
            delta = level if flow is None else flow.delta
        cov = self.covariance(delta) * (1.0 if rho >= cfg.min_ecc else cfg.weak_ecc_cov_scale)
        if flow is not None:
            cov = cov * flow_cov_scale(flow.residual_px, cfg)
        elif grays is not None and self._flow is not None and self._flow.last_residual is not None:
            r = self._flow.last_residual
            cov = cov * refused_flow_cov_scale(r, self._flow.limit_for(r), cfg)
        return OdometryStep(t0, t, delta, cov, float(response), float(rho))

    def _untilted_step(
        self,
        small: np.ndarray,
        psmall: np.ndarray,
        W: np.ndarray | None,
        delta: np.ndarray,
        t0: float,
        t1: float,
        R_tilt: np.ndarray | None = None,
        flow: FlowStep | None = None,
        refine: bool = True,
        lean_known: bool = True,
    ) -> np.ndarray:
        """The step ``delta`` (3,) from ``t0`` to ``t1`` (s) with the vest's tilt change taken out
        (see ``tilt_correction`` and ``tilt_filter``), on top of the lean ``R_tilt`` (3, 3; None:
        level) both frames share. With the ``flow``'s fit, its tilt change is the measurement and
        its step (which has that change taken out) is corrected by the filtered change less it.
        ``refine`` False: no tilt fit (the frame's sticker fixes anchor the tilt instead).
        ``lean_known`` False: no lean was known at ``t0`` (the first step after a gap), so where a
        fix measured the roll at ``t0`` and no tilt change is measured, the lean this step gives is
        what the lean was all along, not a change of the torso's roll."""
        if flow is not None:
            fit: tuple[float, float | None] | None = (flow.d_pitch, flow.d_roll)
            fit_sigma = self.config.flow_config.tilt_sigma * self._pixel_scale
            fit_sigma_true = self._flow_tilt_sigmas(flow)
        elif not refine:
            fit, fit_sigma, fit_sigma_true = None, None, None
        else:
            fit = self._tilt_fit(small, psmall, W, delta, t1 - t0, R_tilt)
            fit_sigma, fit_sigma_true = None, None
            if fit is not None and max(abs(fit[0]), abs(fit[1] or 0.0)) > self.config.tilt_fit_max:
                self.tilt_fits_refused += 1
                fit = None
            if fit is not None:
                base = self.config.tilt_fit_sigma * self._pixel_scale
                fit_sigma_true = _grown_sigmas(base, self.config.tilt_fit_sigma_rel, fit[0], fit[1] or 0.0)
        torso = self._torso
        if torso is None:
            if fit is None:
                return delta
            d_pitch, d_roll = fit[0], fit[1] or 0.0
        else:
            lean = self._lean_roll(t1)
            if not lean_known and fit is None and torso.roll.t is not None and torso.roll.t >= t0:
                # A fix measured the roll at t0 about a prior mean of "no lean", for want of one: the
                # lean under way became known here, it did not change (read as a change, a 4 deg
                # lean after a 2 s stall put 12 cm of sideways motion into one step). A roll only
                # carried to t0 from before the gap follows the lean as before, and a measured
                # change (a tilt fit) is weighed against the prior as before.
                torso.roll.rebase(lean)
            if torso.pitch.t is None or torso.pitch.t < t0:
                # First step, or steps were missed: start from the prior, or carry the estimate, to t0.
                torso.step(t0, lean, None, None)
            d_pitch, d_roll = torso.step(
                t1, lean, *(fit or (None, None)), fit_sigma=fit_sigma, fit_sigma_true=fit_sigma_true
            )
        if flow is not None:
            return self._tilt_corrected(flow.delta, R_tilt, d_pitch - flow.d_pitch, d_roll - flow.d_roll)
        return self._tilt_corrected(delta, R_tilt, d_pitch, d_roll)

    def _flow_tilt_sigmas(self, flow: FlowStep) -> tuple[float, float]:
        """Actual standard deviations (rad) of the flow's fitted (pitch, roll) change: a floor that
        scales with the camera's pixels, and a share of the change itself that grows with the
        read-out (see ``FloorFlowConfig.tilt_sigma_rel``)."""
        fc = self.config.flow_config
        rel = fc.tilt_sigma_rel + fc.tilt_sigma_rel_per_readout_s * self.rig_camera.readout_s
        return _grown_sigmas(fc.tilt_sigma * self._pixel_scale, rel, flow.d_pitch, flow.d_roll)

    def _tilt_geometry(self, R_tilt: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The camera centre (3,) and the tilt grid's rays (N, 3) in the level body frame under the
        lean ``R_tilt`` (3, 3; None: level)."""
        Rt = np.eye(3) if R_tilt is None else R_tilt
        pv = self.rig_camera.vest_point
        return pv + Rt @ (self._cam_centre - pv), self._tilt_rays @ Rt.T

    def _tilt_corrected(
        self, delta: np.ndarray, R_tilt: np.ndarray | None, d_pitch: float, d_roll: float
    ) -> np.ndarray:
        """``delta`` (3,) less the rigid map that a tilt change alone (rad) makes the patch see."""
        if d_pitch == 0.0 and d_roll == 0.0:
            return delta
        c, rays = self._tilt_geometry(R_tilt)
        p_tilt = np.column_stack(_floor_hit(c, rays, d_roll, d_pitch))
        p_nom = np.column_stack(_floor_hit(c, rays, 0.0, 0.0))
        return _compose(delta, _invert2(_kabsch(p_nom, p_tilt)))

    def _tilt_fit(
        self,
        small: np.ndarray,
        psmall: np.ndarray,
        W: np.ndarray,
        delta: np.ndarray,
        dt: float,
        R_tilt: np.ndarray | None,
    ) -> tuple[float, float | None] | None:
        """The fitted change of (pitch, roll) (rad; roll None when not fitted) between the frames,
        or None when not fitted (slow, or the homography did not converge)."""
        cfg = self.config
        slow = math.sqrt(self._centre_moved2(delta)) < cfg.tilt_min_speed * dt
        if slow and not cfg.tilt_pitch_when_slow:
            return None
        roll = cfg.tilt_fit_roll and not slow
        H0 = np.eye(3, dtype=np.float32)
        H0[:2] = W
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, cfg.homography_iterations, cfg.homography_eps)
        try:
            _, H = cv2.findTransformECC(small, psmall, H0, cv2.MOTION_HOMOGRAPHY, crit, None, 1)
        except cv2.error:
            return None
        q0 = self._tilt_q1 @ H.T.astype(np.float64)
        if not np.all(np.abs(q0[:, 2]) > 1e-6):
            return None
        p0 = (q0[:, :2] / q0[:, 2:]) @ self.patch.A.T + self.patch.origin
        p0 = self._level_floor(p0, np.eye(3) if R_tilt is None else R_tilt)
        c, rays = self._tilt_geometry(R_tilt)
        sp = cfg.homography_point_sigma_m
        # The prior is per frame interval; a step over more (a skipped or dropped frame) sees the
        # tilt change for longer: the nod and sway change about linearly over a few frames.
        dt_frame = self._frame_interval()
        sig = cfg.tilt_prior_sigma * (max(1.0, dt / dt_frame) if dt_frame is not None else 1.0)

        def residuals(X: np.ndarray) -> np.ndarray:
            """Residuals (k, m) of k parameter rows X (k, 5): (dx, dy, dyaw, ry, rx)."""
            dx, dy, dyaw, ry, rx = (X[:, i, None] for i in range(5))
            p1x, p1y = _floor_hit(c, rays, rx, ry)
            co, si = np.cos(dyaw), np.sin(dyaw)
            rxy = np.concatenate([co * p1x - si * p1y + dx - p0[:, 0], si * p1x + co * p1y + dy - p0[:, 1]], axis=1)
            return np.concatenate([rxy / sp, ry / sig, rx / sig], axis=1)

        # Gauss-Newton on a near-linear problem (small tilt and step), the Jacobian by central
        # differences in one batch, each step solved by numpy's least squares; roll held at 0 when
        # not fitted.
        free = 5 if roll else 4
        x = np.r_[delta, 0.0, 0.0]
        h = np.array([1e-4, 1e-4, 1e-5, 1e-5, 1e-5])[:free]
        for _ in range(cfg.tilt_iterations):
            E = np.zeros((2 * free, 5))
            E[:free, :free] = np.diag(h)
            E[free:, :free] = -np.diag(h)
            R = residuals(np.vstack([x, x + E]))
            J = ((R[1 : free + 1] - R[free + 1 :]) / (2 * h[:, None])).T
            step = np.linalg.lstsq(J, -R[0], rcond=None)[0]
            if not np.all(np.isfinite(step)):
                return None
            x[:free] += step
        return float(x[3]), (float(x[4]) if roll else None)

    def _tilt(self, t: float) -> np.ndarray | None:
        """The torso's lean (3, 3) at time ``t``: the roll into the turn as the steps up to then say
        (see :meth:`_update_lean`), then the pitch with the walk's speed changes (see
        :meth:`_update_pitch`); None when off, or when no step that recent is known, or both are
        below ``lean_min``."""
        roll = self._lean(t)
        if roll is None:
            return None
        pitch = self._pitch(t)
        if abs(roll) < self.config.lean_min and abs(pitch) < self.config.lean_min:
            return None
        cr, sr = math.cos(roll), math.sin(roll)
        R = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
        if pitch == 0.0:
            return R
        cp, sp = math.cos(pitch), math.sin(pitch)
        # Pitch about the body's y axis after the roll (a forward lean tips the torso's top forward).
        return np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]]) @ R

    def _pitch(self, t: float) -> float:
        """The torso's pitch lean (rad, forward positive) at ``t``, atan(a / g) with the lagged
        acceleration of the walk's speed, within ``pitch_lean_max``; 0 when off or unknown."""
        ps = self._pitch_state
        cfg = self.config
        if not cfg.pitch_lean or ps is None or not 0.0 <= t - ps[0] <= cfg.turn_memory * cfg.max_dt:
            return 0.0
        pitch = math.atan((ps[1] - ps[2]) / (self._lean_tau * _G))
        return max(-cfg.pitch_lean_max, min(cfg.pitch_lean_max, pitch))

    def _update_pitch(self, t: float, speed: float | None) -> None:
        """Follow the walk's speed for the pitch lean after a step measured to the frame at ``t`` (s):
        ``speed`` (m/s), what the tracker predicted for that frame (:meth:`measure`'s ``walk_speed``),
        and its pendulum lag, whose difference over the lag's time constant is the lagged
        acceleration. A frame without a speed (or a non-finite one) forgets it."""
        if speed is None or not math.isfinite(speed):
            self._pitch_state = None
            return
        ps = self._pitch_state
        if ps is None or not 0.0 < t - ps[0] <= self.config.turn_memory * self.config.max_dt:
            self._pitch_state = [t, float(speed), float(speed)]
            return
        # The lag runs over the time since its last update: after frames the odometry could not
        # match (a burst of drops), more than this step's own interval.
        elapsed = t - ps[0]
        ps[0], ps[1] = t, float(speed)
        ps[2] += (1.0 - math.exp(-elapsed / self._lean_tau)) * (ps[1] - ps[2])

    def _update_lean(self, t: float, delta: np.ndarray, dt: float) -> None:
        """Follow the torso's lean with the step ``delta`` (3,) over ``dt`` s ending at ``t``.

        A walker in balance leans into a turn so that gravity and the centripetal force add up
        along the body: roll atan(v omega / g) (a left turn tips the top to the left, roll < 0 about
        +x), reached with the inverted pendulum's time constant sqrt(h_com / g); speed and turn rate
        are this odometry's own steps, and the lag also averages their noise. (The forward lean
        with acceleration, atan(a / g), is taken from the tracker's speed instead, see
        :meth:`_update_pitch`: differentiated from these steps it is too noisy, and its error moves
        the patch, and with it the turn's lever, by 3.7 cm per degree.)"""
        v, w = float(delta[0]) / dt, float(delta[2]) / dt
        demand = -math.atan(v * w / _G)
        st = self._lean_state
        if st is None or not 0.0 < t - st[0]:
            # (time, the roll's demand atan(v omega / g) then, roll); a walk starts in balance.
            self._lean_state = [t, demand, demand]
            return
        elapsed = t - st[0]
        if elapsed > self.config.turn_memory * self.config.max_dt:
            # Frames the odometry could not follow (a burst of drops, a blurred stretch): the lean
            # kept lagging behind a demand nobody saw. A person's yaw acceleration is bounded, so
            # the demand is taken to have moved linearly from the last known one to this step's,
            # and the lag is integrated over it. Restarting in balance instead, at the demand of a
            # turn already under way, overstated the lean: a 0.3 s burst of drops into a 145 deg/s
            # turn gave -22 degrees of roll against -10 true, and steps 3-7 cm off sideways.
            st[2] = _lag_through_ramp(st[2], st[1], demand, elapsed, self._lean_tau)
        else:
            st[2] += (1.0 - math.exp(-dt / self._lean_tau)) * (demand - st[2])
        st[0], st[1] = t, demand

    def _turn_bound(self, dt: float) -> float:
        """The largest turn (rad) a step over ``dt`` s is searched for (see ``max_turn_rate``); 0 with
        the search off (``max_rotation`` 0)."""
        cfg = self.config
        return max(cfg.max_rotation, cfg.max_turn_rate * dt) if cfg.max_rotation > 0 else 0.0

    def _turn_grid(self, skip: float, dt: float) -> list[float]:
        """Turn guesses (rad) every ``rotation_step`` up to the turn a step over ``dt`` s can hold
        (:meth:`_turn_bound`) either way, less ``skip``."""
        cfg = self.config
        if not (cfg.max_rotation > 0 and cfg.rotation_step > 0):
            return []
        k = int(round(self._turn_bound(dt) / cfg.rotation_step))
        return [j * cfg.rotation_step for j in range(-k, k + 1) if abs(j * cfg.rotation_step - skip) > _SAME_TURN_RAD]

    def _initial_alignment(
        self,
        psmall: np.ndarray,
        small: np.ndarray,
        guesses: list[float],
        steps: list[np.ndarray] | None = None,
    ) -> tuple[np.ndarray, float] | None:
        """Start for ECC: the best of the turn ``guesses`` (rad), each completed by phase correlation.

        Phase correlation sees translation only and its peak fades beyond ~3 degrees of turn, and
        ECC started from no turn can settle on a wrong local optimum when the true turn is larger
        (a corner at 150-180 deg/s turns the body 5-6 degrees between frames). So the earlier
        patch is pre-rotated by each guess, phase correlation adds the shift, and
        with several guesses the alignment that correlates best (zero-mean normalised, over the
        patch centre) wins.

        ``steps``: instead of turns about the patch centre, whole predicted body steps (3,) ``(dx,
        dy, dyaw)``, one per guess (a bridged gap, :meth:`_bridge`): phase correlation then adds
        the shift left over.

        Returns ECC's start ``W`` (2, 3) (current -> earlier patch pixels) and the
        winner's phase-correlation peak, or None when no guess has a peak of ``min_response``.
        """
        cfg = self.config
        m = small.shape[0]
        A = self.patch.A
        c = np.full(2, (m - 1) / 2.0)
        lo, hi = m // _ZNCC_INSET, m - m // _ZNCC_INSET
        best: tuple[float, float, np.ndarray] | None = None
        for k, g in enumerate(guesses):
            if steps is None:
                # Body turn g in patch pixels (the scale of A cancels), about the patch centre: the
                # rest of the turn's lever arm is a shift, which phase correlation finds.
                Wl = self._A_inv @ _rot2(g) @ A
                Wg = np.hstack([Wl, (c - Wl @ c)[:, None]])
            else:
                Wg = self.patch_map(steps[k])
                Wl = Wg[:, :2]
            warped = (
                psmall
                if g == 0.0 and steps is None
                else cv2.warpAffine(
                    psmall, Wg.astype(np.float32), (m, m), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
                )
            )
            # phaseCorrelate applies the window in place: hand it copies.
            (sx, sy), r = cv2.phaseCorrelate(warped.copy(), small.copy(), self._window)
            if not (math.isfinite(r) and r >= cfg.min_response) or max(abs(sx), abs(sy)) > cfg.max_shift_frac * m:
                continue
            # cur(q) ~ warped(q - s) = prev(Wg (q - s)).
            W = np.hstack([Wl, (Wg[:, 2] - Wl @ np.array([sx, sy]))[:, None]])
            zncc = 0.0
            if len(guesses) > 1:
                aligned = cv2.warpAffine(
                    psmall, W.astype(np.float32), (m, m), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
                )
                zncc = float(cv2.matchTemplate(aligned[lo:hi, lo:hi], small[lo:hi, lo:hi], cv2.TM_CCOEFF_NORMED)[0, 0])
            if best is None or zncc > best[0]:
                best = (zncc, float(r), W)
        if best is None:
            return None
        return best[2].astype(np.float32), best[1]

    def patch_map(self, delta: np.ndarray) -> np.ndarray:
        """The patch-pixel map ``W`` (2, 3), q0 = W [q1, 1], of a body step ``delta`` (3,) ``(dx, dy,
        dyaw)``: the inverse of :meth:`body_motion`."""
        A, b = self.patch.A, self.patch.origin
        R = _rot2(float(delta[2]))
        Wl = self._A_inv @ R @ A
        wt = self._A_inv @ (R @ b + np.asarray(delta[:2], float) - b)
        return np.hstack([Wl, wt[:, None]])

    def _bridge(
        self,
        prev: tuple[float, np.ndarray],
        cur: tuple[float, np.ndarray],
        body_twist: np.ndarray | None,
        grays: tuple[np.ndarray, np.ndarray] | None,
        refine: bool = True,
    ) -> OdometryStep | None:
        """The step across dropped frames from ``prev`` to ``cur`` (time, patch), or None (see
        ``bridge_max_dt``). The walk before the gap (this odometry's last step when it ended at
        most ``turn_memory`` frame gaps before ``prev``, else ``body_twist``) predicts a
        constant-rate arc; arcs turning by up to half ``bridge_yaw_accel`` dt^2 more or less, a
        ``rotation_step`` apart, compete as starts for ECC, which must reach ``min_ecc``. ``refine``: see
        :meth:`measure`."""
        cfg = self.config
        (t0, _), (t, _) = prev, cur
        dt = t - t0
        lt = self._last_twist
        if lt is not None and 0.0 <= t0 - lt[0] <= cfg.turn_memory * cfg.max_dt:
            twist = np.asarray(lt[1], float)
        elif body_twist is not None and np.all(np.isfinite(body_twist)):
            twist = np.asarray(body_twist, float).ravel()[:3]
        else:
            return None  # nothing predicts the gap: a search from nothing could settle anywhere
        if not (cfg.rotation_step > 0):
            return None
        v, w = twist[:2], float(twist[2])
        k = int(math.ceil(0.5 * cfg.bridge_yaw_accel * dt * dt / cfg.rotation_step))
        turns = [w * dt + j * cfg.rotation_step for j in range(-k, k + 1)]
        steps = [_arc(v, turn, dt) for turn in turns]
        found = self._ecc_from(prev[1], cur[1], turns, steps, bridge=True)
        if found is None:
            return None
        rho, W, response, start = found
        step = self._step(prev, cur, (rho, W, response, False), grays, predicted_shift=start[:, 2], refine=refine)
        if step is None:
            return None
        residual = self.last_flow_residual
        if (
            grays is not None
            and self._flow is not None
            and (residual is None or residual > cfg.bridge_max_flow_residual_px)
        ):
            # The floor's points fit no rigid motion near the match: it may have slid along a line.
            # What the step taught the odometry (turn guess, lean, tilt) goes with it.
            self.forget_motion()
            self.bridges_unverified += 1
            return None
        # Too few bursts to calibrate a bridged step's error, so its covariance is deliberately
        # generous: the ordinary one for the distance moved (as if one long step) plus that of the n
        # ordinary steps it stands for (one per frame interval; standing still, the first is tiny while
        # the torso's sway and tilt still change over the gap: 2.7 cm and 0.9 deg off over 0.3 s
        # on a field_sensor timing walk).
        n = max(1.0, dt / (self._frame_interval() or dt))
        return dataclasses.replace(step, cov=step.cov + n * self.covariance(step.delta / n))

    def _turn(self, Wl: np.ndarray) -> float:
        """Body turn (rad) of the patch-pixel linear map ``Wl`` (2, 2): the angle of A Wl A^-1."""
        M = self.patch.A @ Wl @ self._A_inv
        return math.atan2(M[1, 0] - M[0, 1], M[0, 0] + M[1, 1])

    def body_motion(self, Wl: np.ndarray, wt: np.ndarray) -> np.ndarray:
        """(dx, dy, dyaw) of body1 in body0 from the patch-pixel map q0 = Wl q1 + wt."""
        A, b = self.patch.A, self.patch.origin
        # Floor points p = A q + b; p0 = R p1 + t (T_body0_body1). Hence R = A Wl A^-1 and
        # t = A wt + b - R b: the rotation is about the body origin, not the patch centre.
        yaw = self._turn(Wl)
        R = _rot2(yaw)
        t = A @ wt + b - R @ b
        return np.array([t[0], t[1], yaw])

    def _centre_moved2(self, delta: np.ndarray) -> float:
        """Squared distance (m^2) the patch centre moved in a step ``delta`` (3,) (dx, dy, dyaw)."""
        co, si = math.cos(delta[2]), math.sin(delta[2])
        cx, cy = self._centre
        return float((delta[0] + (co - 1.0) * cx - si * cy) ** 2 + (delta[1] + si * cx + (co - 1.0) * cy) ** 2)

    def _level_floor(self, p: np.ndarray, R_tilt: np.ndarray) -> np.ndarray:
        """Where nominal floor points ``p`` (N, 2) (body frame, m) are when the torso is tilted by
        ``R_tilt`` (3, 3) about the vest point: (N, 2) in the level body frame."""
        c = self._cam_centre
        pv = self.rig_camera.vest_point
        rays = np.column_stack([p - c[:2], np.full(len(p), -c[2])]) @ R_tilt.T
        c1 = pv + R_tilt @ (c - pv)
        s = -c1[2] / rays[:, 2]
        return c1[:2] + s[:, None] * rays[:, :2]

    def level_motion(self, Wl: np.ndarray, wt: np.ndarray, R_tilt: np.ndarray, small: np.ndarray) -> np.ndarray:
        """(dx, dy, dyaw) of body1 in body0 from ECC's patch-pixel map q0 = Wl q1 + wt, the torso
        tilted by ``R_tilt`` (3, 3) in both frames; ``small``: the current (template) patch.

        The bird's-eye patch assumes the nominal rig. Seen through a tilted torso, the floor under
        the patch is a perspective-distorted square off to one side, so two patches differ by a
        non-rigid map, and ECC's best rigid match of it turns by about (tilt) x (patch motion) more
        or less than the body (per degree of roll, 0.017 degrees per 4.5 cm walked; per degree of
        pitch, 0.6 % of the turn), and the turn's lever to the displaced patch moves it forward or
        back. The body motion is therefore the one whose non-rigid map ECC would have matched as
        it did: ECC weighs each part of the patch by its image gradients (the structure tensor;
        the bird's-eye patch is blurred along the view, so sideways displacements count more), so
        the same weighted rigid fit is applied to the map a candidate motion predicts, and the
        candidate (from the unweighted fit of the matched points carried to the level floor) is
        corrected by the difference (``_LEVEL_ITERATIONS`` times). The tilt's change between the
        frames is left out: its apparent motion is the tracker's tilt offset."""
        A, b = self.patch.A, self.patch.origin
        q1 = self._grid

        def to_floor(q: np.ndarray) -> np.ndarray:
            return q @ A.T + b

        def to_px(pf: np.ndarray) -> np.ndarray:
            return (pf - b) @ self._A_inv.T

        corners = to_floor(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]) * (self.config.patch_px - 1))
        H = cv2.getPerspectiveTransform(
            corners.astype(np.float32), self._level_floor(corners, R_tilt).astype(np.float32)
        )  # nominal floor -> level floor
        H_inv = np.linalg.inv(H)
        S = self._structure(small)
        measured = self.body_motion(Wl, wt)
        p1 = self._level_floor(to_floor(q1), R_tilt)
        M = _kabsch(p1, self._level_floor(to_floor(q1 @ Wl.T + wt), R_tilt))
        for _ in range(_LEVEL_ITERATIONS):
            # The patch points q1 seen in frame 0 if the body moved by M: level floor, moved, nominal.
            pm = p1 @ _rot2(M[2]).T + M[:2]
            q0 = to_px(_apply_h(H_inv, pm))
            Wp = _weighted_rigid_fit(q1, q0, S)
            M = M + (measured - self.body_motion(Wp[:, :2], Wp[:, 2]))
        return M

    def _structure(self, small: np.ndarray) -> np.ndarray:
        """(k*k, 2, 2) image-gradient structure tensors of the patch's k x k cells (patch pixels)."""
        k = _TILT_GRID
        gx = cv2.Sobel(small, cv2.CV_32F, 1, 0)
        gy = cv2.Sobel(small, cv2.CV_32F, 0, 1)
        t = [cv2.resize(g, (k, k), interpolation=cv2.INTER_AREA) for g in (gx * gx, gx * gy, gy * gy)]
        S = np.empty((k * k, 2, 2))
        S[:, 0, 0], S[:, 0, 1], S[:, 1, 1] = (x.ravel() for x in t)
        S[:, 1, 0] = S[:, 0, 1]
        return S + 1e-9 * np.eye(2)

    def covariance(self, delta: np.ndarray) -> np.ndarray:
        """(3, 3) covariance of a step ``delta`` (3,) ``(dx, dy, dyaw)`` (see :class:`OdometryConfig`).

        Independent errors of the patch centre's motion (forward, lateral) and of the turn, carried
        to the body origin: a turn error ``e`` about the origin moves the origin by ``-e J c`` for
        the patch centre ``c`` (J: 90-degree rotation), so ``G = [[1, 0, c_y], [0, 1, -c_x], [0, 0, 1]]``
        and the covariance is ``G diag(...) G^T``.
        """
        cfg = self.config
        # The image motion drives the errors (blur, perspective), so they grow with how far the
        # patch centre moved, which on a turn on the spot is far more than the body origin.
        d2 = self._centre_moved2(delta)
        D = np.diag(
            [
                cfg.sigma_forward**2 + cfg.sigma_forward_per_m**2 * d2,
                cfg.sigma_lateral**2 + cfg.sigma_lateral_per_m**2 * d2,
                cfg.sigma_yaw**2 + cfg.sigma_yaw_per_m**2 * d2,
            ]
        )
        return self._lever @ D @ self._lever.T
