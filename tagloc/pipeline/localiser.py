"""The localiser: one frame in, observations and a tracked pose out.

The frame flows one way: detect -> decode, or identify against the tracker's candidates ->
pose -> tracker. Sources and sinks live elsewhere (:mod:`tagloc.io.capture`, :mod:`tagloc.io.sinks`);
the paper's baselines, which share the stages but not the tracker, in :mod:`tagloc.eval.baselines`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from tagloc.core.camera import Camera, load_calibration
from tagloc.core.errors import CalibrationError, InputError
from tagloc.core.rig import Rig, RigCamera, default_rig, load_rig, torso_tilt
from tagloc.core.sticker import SIZE_M, rotate_corners
from tagloc.core.stickermap import StickerMap, load_map
from tagloc.core.types import (
    Detection,
    Fix,
    Frame,
    FrameResult,
    Identity,
    IdSource,
    Observation,
    PoseFix,
    SurveyPrior,
    TrackState,
    frame_seconds,
    seconds_text,
)
from tagloc.io.session import CAMERA_FILE, MAP_FILE, RIG_FILE, STAMP_RESOLUTION_S
from tagloc.vision.decode import DecodeConfig, decode, verify_detection
from tagloc.vision.deflicker import Deflicker, DeflickerConfig
from tagloc.vision.detect import detect, merge_boxes
from tagloc.vision.image import as_gray, unusable
from tagloc.vision.odometry import FloorOdometry, OdometryConfig, OdometryStep
from tagloc.vision.pose import PoseConfig, PoseSolution, solve_pose
from tracker.candidates import project_map
from tracker.ekf import largest_eig_2x2
from tracker.tracker import Tracker, TrackerConfig

if TYPE_CHECKING:  # both are imported on first use: their modules' start-up is not every run's
    from tagloc.vision.decode.lookalike import LookAlikes
    from tagloc.vision.refs import ReferenceBank

#: The stages whose time is the tracker's: its prediction, candidate choice, updates and output.
TRACKER_STAGES = ("predict", "candidates", "update", "output")


class StageTimer:
    """Wall time per stage of one frame, ms: each stage is timed once, where the localiser runs it.

    ``with timer("decode"): ...`` adds the block's time to ``timer.ms["decode"]`` (stages that run
    once per sticker add up over the frame).
    """

    def __init__(self) -> None:
        self.ms: dict[str, float] = {}
        self._t0 = time.perf_counter()

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        """Time the block as (a part of) ``stage``."""
        ts = time.perf_counter()
        try:
            yield
        finally:
            self.ms[stage] = self.ms.get(stage, 0.0) + (time.perf_counter() - ts) * 1e3

    def finish(self) -> dict[str, float]:
        """The stage times with ``total``, the time since the timer was made."""
        self.ms["total"] = (time.perf_counter() - self._t0) * 1e3
        return self.ms


# Fix.gate_reason of a fix held for its frame's deferred odometry step (tilt_gate_hold_chi2,
# rs_hold_for_step); the frame's deferred work judges it and reports it in Localiser.late.
HELD_REASON = "held for the frame's odometry step"

# Stickers whose last sights are kept for their corners' image velocity before old ones are dropped
# (LocaliserConfig.rs_corner_forget_s), and the sights kept per sticker: only the latest before a
# frame is used; two more cover the same sticker detected twice in one frame.
_CORNER_MEMORY = 64
_CORNER_SIGHTS = 3


def within_gap(dt: float, limit: float) -> bool:
    """Whether a frame ``dt`` s after another is after it and no more than ``limit`` s after, to the
    stamps' microsecond (``STAMP_RESOLUTION_S``). Frame times are differences of large numbers on an
    epoch clock: one frame period later reads 0.1000000001 s or 0.0999999 s depending on where the
    clock started (1.8e9 s, 1e6 s, 0), and a limit equal to the period (``max_gap_s`` at 10 fps) had
    carried sticker tracks on one clock and dropped them on another."""
    return 0.0 < dt <= limit + STAMP_RESOLUTION_S


@dataclass
class LocaliserConfig:
    """Choices of the per-frame stage and the tracker.

    Attributes:
        detector: "contour" (ours) or "paper" (ORB + k-means, for comparison).
        decoder: Data Matrix backend: "zxing", "libdmtx" or "both".
        identify: identification when decoding fails: "auto", "orb", "appearance" or "off".
        candidates: K, the most candidates handed to identification.
        tracker: the EKF's configuration.
        odometry: measure the body's motion between frames from the floor texture and feed it to
            the tracker; ``odometry_config`` tunes it. ``odometry_stride``: let the odometry skip
            every other frame while the operator walks straight (see ``OdometryConfig.max_stride``:
            load shedding, at some cost in accuracy); False: only while :attr:`Localiser.behind`
            (set by ``tagloc live`` when frames wait for the localiser). ``odometry_cameras``: the
            rig cameras (indices) that measure it, None: all (each camera's steps run from its own
            previous frame).
        sticker_tracking: carry a decoded sticker's identity to the next frame instead of decoding
            it again; ``tracking`` tunes it (see :func:`match_tracked`).
        clock_reset_frames: a frame whose timestamp is not after the previous frame's is refused
            (skipped, counted); this many refused in a row mean the source's clock was reset, and
            the track restarts on the new clock. 5 frames (1/6 s at 30 fps): one stray stamp is
            refused without losing the track, a reset clock costs a fraction of a second.
        pose: the pose solver's options (corner noise, the map's default survey sigmas).
        rolling_shutter: for a rig camera with a rolling shutter (``readout_s`` in rig.json),
            straighten each sticker's corners to the time its rows were read (see
            :mod:`tagloc.vision.pose`) before solving its pose: each corner moved by its own image
            velocity, that corner's motion since the previous frame's sight of the same sticker
            (within ``rs_image_velocity_max_dt``), else by the body's motion (this frame's odometry
            step, else the tracker's prediction). The odometry's own correction is
            ``odometry_config.rolling_shutter``.
        rs_image_velocity_max_dt: the longest gap (s) over which a sticker's corners' motion
            stands for their velocity (and only if the two sights pass sticker tracking's
            same-place test, ``tracking.max_centre_shift`` and ``max_shape_change``): 50 ms, one
            frame interval at 30 fps and its jitter, not two (over a dropped frame the gait's bob
            and nod change the motion too much). Why the image
            velocity: it holds the whole motion of the camera that the rows see (the gait's bob
            and nod, not only the walk on the floor). On the simulator's true corners of the field
            walk f02 (30 ms read-out, 0.11 px corner noise), camera position RMS 7.8 cm
            uncorrected, 1.4 cm with the true planar body motion, 0.65 cm with the corners' motion
            since the previous frame, 0.51 cm with the camera's true instantaneous motion.
        rs_corner_forget_s: once more than 64 stickers' sights are kept for that velocity, those of
            stickers not seen for this long (s) are dropped. Any time above
            ``rs_image_velocity_max_dt`` gives the same corrections (an older sight is never
            used); 1 s keeps the sights of every sticker in view and of those just out of it.
        defer_lsq: (``tagloc live``) a detection that the quick decoding stages (zxing, grid
            sampling) leave unread is not sent through the least-squares stage (~6-11 ms), nor
            identified, within the frame: that work is done after the frame's result is published
            (:meth:`Localiser.deferred_work`, in the wait for the next frame), exactly as the frame
            would have done it, and its fix goes to the tracker at the frame's time, before the
            next frame. Only the published pose of that one frame lacks the fix; the slowest stage
            leaves the frame's latency. Off for a replay (no wait between frames): results as
            before. Only with the "zxing" decoder (the stage belongs to it).
        finish_lsq_untracked: with ``defer_lsq``, while the tracker has no track (initialising, or
            lost) the frame's deferred least-squares decodes all run after it even when the next
            frame is already waiting (:meth:`Localiser.deferred_work`), until one places the
            operator: a read is then the only way to a pose, and on a core too slow for the
            camera a frame always waits, so they never ran. On the dim walks f01 (60 lux) and s01
            (56 lux) with the camera five times faster than the core
            (``benchmarks/load_shedding.py``), ``tagloc live`` stayed initialising for 2.5-7.1 s
            on f01 and all the walk on s01 in three of four runs; with this, a pose from the first
            read, and 52-83 % of all frames within 10 cm instead of 0-44 %. The published frame
            keeps its latency (the work runs after it); the camera's next frames wait.
        defer_odometry: (``tagloc live``) the frame's floor-odometry step (2-4 ms) is measured and
            fused after its pose is published (first thing in :meth:`Localiser.deferred_work`, or
            at the start of the next frame if none ran), at its own frame's time, and the tilt
            anchors of that frame's fixes after it, in a replay's order; the published pose of
            the frame is the filter's prediction plus its fixes, without its own step. Off for a
            replay.
        tilt_gate_chi2: a pose solution whose camera tilts the torso further from the odometry's
            filtered tilt than this squared Mahalanobis distance (2 DoF) is dropped before the
            tracker sees it, and a fix with no solution left is refused (counted as
            ``tilt_gated``); 0 turns the gate off. The sticker's plane gives the camera's pitch
            and roll whatever the map says of the sticker, and a torso's tilt is known to a degree
            or two between fixes (see :mod:`tagloc.vision.torso_tilt`), so a solution that
            disagrees is the planar pose's other branch, a rolling-shutter shear or a corner
            pulled by blur or the image edge. On four simulated field walks, fixes whose tilt was
            2.5-5 deg off were 8.3 cm off in position (median; 3 cm for the rest, mostly survey
            error), and 30 of them had been accepted. 13.8: chi^2 with 2 DoF at 99.9 %, the
            tracker's own gate level. A tilt filter that refuses ``odometry_config.tilt_gate_reset``
            fixes in a row is forgotten (it may itself have been anchored by a bad fix), and the
            fix is judged against the upright prior alone.
        tilt_gate_hold, tilt_gate_hold_chi2: (``defer_odometry``) the tilt filter the gate judges
            against lacks the frame's own odometry step, so its prediction is wider than a
            replay's (0.5-0.8 deg against 0.2 deg on simulated field walks) and the gate lets
            through fixes a replay refuses. With ``tilt_gate_hold``, a fix no solution of which
            lies within ``tilt_gate_hold_chi2`` of that wider prediction is held: judged once the
            step is fused (:meth:`Localiser.deferred_work`), as a replay judges it, and fused at
            its frame's time then; only that frame's published pose lacks it (4.61: chi^2 with 2
            DoF at 90 %, the wider prediction's own 90 % region; 0 holds every fix, and live's
            filter is then the replay's). Off: its effect is mixed, and it costs the walker with
            twice the default gait (``--gait-scale 2``). In live's order
            (``benchmarks/eval_variants.py``), on the field preset / held-out field / gait x2
            field / gait x2 standard walks: 2.40 / 2.72 and 2.59 / 2.82 / 2.25 cm without it,
            2.34 / 2.65 and 2.57 / 2.92 / 2.32 at 4.61, 2.37 / 2.52 and 2.59 / 2.87 / 2.36 at 0
            (2026-11-30, when the gate was too strict: a twentieth of the fixes within 1 deg of
            the true tilt refused with that walker). With the gate judging by the tilt's actual
            error variance (``TiltAxis.var_true``; a hundredth refused), 2.44 / 2.72 and 2.58 /
            2.81 / 2.24 without it and 2.34 / 2.67 and 2.60 / 2.85 / 2.31 at 4.61; with that
            variance grown a frame ahead by the tilt's rate (``OdometryConfig.tilt_rate_sigma``),
            2.31 / 2.66 and 2.56 / 2.79 / 2.24 without it and 2.37 / 2.47 and 2.58 / 2.84 / 2.32
            at 4.61.
        rs_hold_for_step: (``defer_odometry``) a fix from a rolling-shutter camera whose corners'
            image velocity is not known (the sticker not solved in the camera's previous frame) is
            corrected with the body's motion over the frame interval. A replay takes that from the
            frame's own odometry step, which holds the torso's wobble; without the step there is
            only the tracker's smooth velocity. Such a fix is held and solved once the step is
            fused, then judged and fused at its frame's time (as ``tilt_gate_hold_chi2``'s).
        check_expected: a detection that the quick decoding stages (zxing, grid sampling) leave
            unread is first checked against the tracker's most likely sticker there: its data
            modules, already sampled, correlated in each rotation (``DecodeConfig``'s
            ``expected_min_score``, ``expected_min_margin``). A match names it as a CHECKED
            identity (the tracker gates its fix as a decoded one's, as the check that refuses a
            wrong pick is a decode's own final one, but never starts a track with it; refused,
            it can join a re-initialisation, ``TrackerConfig.reinit_checked``) and saves
            the least-squares stage (3-5 ms): the first sight of a sticker the track predicts no
            longer costs a frame's budget. Such a sticker is carried to the next frames as a
            decoded one is (sticker tracking, re-checked when due). Only with a track (the
            tracker's candidates) and the "zxing" or "both" decoder. The expected sticker must
            also lead its rivals by the same margin: the tracker's other candidates there and
            its look-alikes in the map (:mod:`tagloc.vision.decode.lookalike`).
        lookalike_min_corr: a mapped sticker whose data modules correlate with the expected one's
            at or above this, in some rotation, on the modules the check compares, is its rival.
            A sticker scores against another's modules about their correlation times its own
            raster's quality (the true sticker's best rotation: 0.62 median under the blur that
            defeats the symbol readers), so one below 0.3 cannot reach the check's 0.5; on
            ``maps/demo.csv`` each sticker's closest look-alike correlates 0.26-0.65 (median 0.39),
            and 206 of its 214 stickers have at least one rival at 0.3 (four on average: about
            0.05 ms of module scoring each, only when the quick stages read nothing).
        forget_refused_bridge: a step bridging dropped frames that the tracker refuses (see
            ``TrackerConfig.gate_bridge_narrow``) also takes back what the odometry learnt from it
            (:meth:`tagloc.vision.odometry.FloorOdometry.forget_motion`: the turn guess, the lean,
            the torso's filtered tilt), which is as doubtful as the step: kept, a refused wrong
            bridge's lean had the tilt gate refuse a right fix after it (``benchmarks/bridges.py``).
            Counted as ``odometry_bridge_forgotten``.
        skip_flow_after_fix: when the camera's last frame was placed by a read fix (a sticker
            decoded, checked or carried, its fix accepted) and the tracker predicts that sticker at
            least ``skip_flow_margin_px`` inside this frame, the frame will very likely be placed
            by its fixes too, and its odometry step is the patch's alone (``refine`` of
            :meth:`FloorOdometry.measure`: no floor flow, no homography tilt fit; about 2 of the
            odometry's ~4 ms). Such a step is fused only if the frame's own read fixes do not
            place it after all (``odometry_unfused`` counts the others): a placed frame needs no
            step (leaving out the refined steps of placed frames moved walk300's RMSE by 0.01
            cm), and the patch's cruder step fused next to the fixes pulled them (0.96 -> 1.18
            cm). It is still measured because the odometry's memory of the turn and the lean
            must follow every frame into the next gap: taking the frame without any step, that
            memory set from the tracker's motion instead, the next gaps drifted 2.7 -> 4.5 cm at
            0.5-1 s after the last fix on walk300. 80 px: half a 10 cm sticker's diagonal at
            1.3-1.6 m (57-70 px at the Pi camera's 1286 px focal length) and a little for the
            prediction's error, so that the sticker stays readable. Off by default: it takes
            about 2 ms off a frame's mean (walk300 6.6 -> 4.6 ms), but over the eval presets its
            accuracy is mixed (field 3.05 -> 3.12 cm in a replay, 98.9 % of the frames within 10
            cm instead of 99.2; standard 1.79 -> 1.88 cm in live's order, s01 2.76 -> 3.08), so
            it is load shedding: ``tagloc live`` turns it on while it falls behind the camera
            (:attr:`Localiser.behind`, with the odometry's stride). See the README's Speed
            section.
        skip_flow_min_fixes: the same, on by default, where it costs nothing: after a frame that
            at least this many read fixes placed, with at least as many of the tracked stickers
            predicted ``skip_flow_margin_px`` inside this frame (0: never). Two stickers placing
            every frame pin the pose, heading included, far better than a step between frames
            does, and the busiest frames are where the time is short: on the dense walk (2-5
            stickers in view) the flow was left out of 470 of 600 frames, its 3-sticker frames
            went 10.7 -> 9.3 ms and its RMSE 0.675 -> 0.694 cm; replays of the 33 preset and
            held-out walks (2026-11-30) moved by 0.01 cm at most (standard 1.51 -> 1.52 cm, the
            rest unchanged), 0 wrong IDs either way. 1 would be ``skip_flow_after_fix``.
        deflicker: lamp flicker is divided out of the frames before every stage: the bands of a
            rolling-shutter camera, the brightness swings of a global-shutter one
            (:mod:`tagloc.vision.deflicker`; counter ``deflickered``); None: frames are taken as
            they come.
    """

    detector: str = "contour"
    decoder: str = "zxing"
    identify: str = "auto"
    candidates: int = 5
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    odometry: bool = True
    odometry_stride: bool = False
    odometry_config: OdometryConfig = field(default_factory=OdometryConfig)
    odometry_cameras: tuple[int, ...] | None = None
    clock_reset_frames: int = 5
    sticker_tracking: bool = True
    tracking: TrackingConfig = field(default_factory=lambda: TrackingConfig())
    pose: PoseConfig = field(default_factory=PoseConfig)
    rolling_shutter: bool = True
    rs_image_velocity_max_dt: float = 0.05
    rs_corner_forget_s: float = 1.0
    defer_lsq: bool = False
    finish_lsq_untracked: bool = True
    defer_odometry: bool = False
    tilt_gate_chi2: float = 13.8
    tilt_gate_hold: bool = False
    tilt_gate_hold_chi2: float = 4.61
    rs_hold_for_step: bool = True
    check_expected: bool = True
    lookalike_min_corr: float = 0.3
    forget_refused_bridge: bool = True
    skip_flow_after_fix: bool = False
    skip_flow_min_fixes: int = 2
    skip_flow_margin_px: float = 80.0
    deflicker: DeflickerConfig | None = field(default_factory=DeflickerConfig)


@dataclass
class TrackingConfig:
    """When a sticker decoded in the previous frame keeps its identity without decoding.

    Attributes:
        redecode_every: a tracked identity is carried at most this many frames in a row minus one;
            then the sticker is decoded again (and a failed or different read ends the track).
            Decoding is the most expensive stage after detection; 4 keeps three of four decodes
            off a steadily seen sticker while every identity is re-read within 0.13 s at 30 fps.
        max_centre_shift: the detection's centre must be within this many sticker sides of the
            tracked sticker's centre in the previous frame, moved by the image motion the tracker
            predicts for it (:func:`match_tracks`). Walking at 1.5 m/s moves a floor point 5 cm
            (half a sticker side) per frame at 30 fps; turning sweeps the image by up to ~60 px
            a frame, more than a far sticker's side, which the prediction takes out.
        max_shape_change: with both centred, every corner must be within this share of a side of
            its previous place (the sticker's image turns ~3 deg and scales a few % per frame).
        max_gap_s: the previous frame must be this recent (no carrying over a dropped frame run).
        reverify: a sticker due for re-decoding that still matches its track is first re-checked
            by correlating its data modules with its tracked ID and rotation
            (:func:`tagloc.vision.decode.verify_detection`, a quarter to a twentieth of a decode's
            cost); only when that fails is it decoded (and a failed or different read ends the track).
        reverify_min_score: the correlation that re-check needs. A decode's own final check accepts
            from 0.5; any other ID or rotation scores <= 0.45 and the true one >= 0.9 up to 2 px of
            blur, so 0.7 keeps a wide margin, and a sticker scoring less is simply decoded again.
        lsq_retry_every: a detection where and what one of the previous frame was that neither
            decoding (every stage) nor identification named (a blank framed square, a worn sticker
            off the track) runs the costly least-squares stage (~10-20 ms) only every this many
            frames in a row; the cheap stages (zxing, grid sampling, ~2 ms) and identification
            still run every frame. 1 = always.
        lsq_while_initialising: while the tracker is initialising (no fix yet) the least-squares
            stage runs on every detection every frame, whatever ``lsq_retry_every`` says: nothing
            else can place the operator then, and the frame has no tracking work.
        search_every: the whole image is searched for stickers every this many frames of a camera;
            in the frames between, while the tracker is TRACKING and the camera's previous frame is
            recent (``max_gap_s``), only around that frame's detections and the mapped stickers the
            tracker predicts in view (:func:`tagloc.vision.detect.detect_stickers`' ``regions``: a
            sticker inside them is found exactly as in a whole-image search). Half the detection
            stage's cost is that search; what the regions can miss (an unmapped sticker or a stray
            square coming into view, a sticker the prediction puts far off) is found at most
            ``search_every - 1`` frames late. 1 = always the whole image.
        search_rate_rad_s: how fast a sticker's image may move between frames, as a view angle: a
            region reaches this times the time since the camera's previous frame times the focal
            length beyond the sticker. Turning at up to 1.5 rad/s sweeps the image by 64 px per frame
            at 30 fps and a 1286 px focal length, walking at 1.5 m/s moves a floor point 1.5 m away
            by another ~40 px: 2.8 rad/s (120 px a frame) leaves a margin.
        search_sigmas: a predicted sticker's region also covers this many standard deviations of the
            tracker's position and heading uncertainty.
        search_sticker_reach: a predicted sticker's region reaches this many sticker sides (at the
            sticker's depth) from its predicted centre, before the motion and uncertainty above:
            half its diagonal (0.71) and a little more, so the whole outline is inside it.
        search_max_area: regions covering more than this share of the image (merged where they
            overlap) are not worth cutting out: the whole image is searched. The search's cost
            grows with the area searched plus a cut-out margin and set-up per region; on a walk
            with 3-4 stickers in view (regions over 70 % of the image) cut-outs cost more than the
            whole image, on one with 1-2 (20 % on average) they save 0.5 ms a frame. Regions
            found crowded are not worked out again before the next scheduled whole-image search.
        search_max_stickers: after a frame with more detections than this the whole image is
            searched without working out the regions (their margins would cover most of it, and
            predicting the mapped stickers in view costs ~0.2 ms).
    """

    redecode_every: int = 4
    max_centre_shift: float = 1.0
    max_shape_change: float = 0.25
    max_gap_s: float = 0.1
    reverify: bool = True
    reverify_min_score: float = 0.7
    lsq_retry_every: int = 4
    lsq_while_initialising: bool = True
    search_every: int = 3
    search_rate_rad_s: float = 2.8
    search_sigmas: float = 3.0
    search_sticker_reach: float = 0.75
    search_max_area: float = 0.4
    search_max_stickers: int = 2


@dataclass(frozen=True)
class Tracked:
    """A sticker named by decoding (or the expected-ID check) whose fix the tracker accepted, as seen
    in one frame.

    ``outer`` (4, 2) distorted px as detected; ``age``: frames since it was last decoded;
    ``predicted_px`` (2,): where the tracker put the sticker's centre in that frame, after its fixes
    (None: not known), from which the next frame's prediction tells how far its image moved."""

    outer: np.ndarray
    identity: Identity
    camera: int
    t: float
    age: int
    predicted_px: np.ndarray | None = None


@dataclass
class HeldFix:
    """A fix that waits for its frame's deferred odometry step (``tilt_gate_hold_chi2``,
    ``rs_hold_for_step``): the detection, its identity, the camera, the frame's time ``t`` (s) and
    index, the pose solution ``sol`` (None: not solved yet); ``track_age``: set when the frame named it by reading (decode, expected-ID check or a carried
    track), the age its track takes if the fix is accepted (see :meth:`Localiser._track`)."""

    det: Detection
    identity: Identity
    rig_cam: RigCamera
    camera: int
    t: float
    index: int
    sol: PoseSolution | None = None  # None: solved once the step is fused (rs_hold_for_step)
    track_age: int | None = None


@dataclass(frozen=True)
class FailedRead:
    """A detection that neither decoding nor identification named, as seen in one frame: ``outer``
    (4, 2) distorted px; ``age``: frames since the least-squares stage last ran on it."""

    outer: np.ndarray
    camera: int
    t: float
    age: int


def _same_place(det: Detection, outer: np.ndarray, config: TrackingConfig) -> bool:
    """Whether ``det`` is where and what the quad ``outer`` (4, 2) of the previous frame was."""
    side = min(_shortest_side(det.outer), _shortest_side(outer))
    _, moved, change = _shape_match(det.outer, outer)
    return moved <= config.max_centre_shift * side and change <= config.max_shape_change * side


# Row ``sh`` lists the corners of a quad cyclically shifted by ``sh``: (j + sh) % 4.
_CYCLIC_SHIFTS = (np.arange(4)[None, :] + np.arange(4)[:, None]) % 4


def _shortest_side(quad: np.ndarray) -> float:
    d = quad - quad[_CYCLIC_SHIFTS[1]]
    return float(np.sqrt(np.min(np.sum(d * d, axis=1))))


def _shape_match(cur: np.ndarray, prev: np.ndarray) -> tuple[int, float, float]:
    """(shift, centre distance, largest corner change after centring) of quad ``cur`` (4, 2) against
    ``prev``, for the cyclic shift with ``cur[(j + shift) % 4]`` at ``prev[j]``."""
    cc, pc = cur.mean(axis=0), prev.mean(axis=0)
    a, b = cur - cc, prev - pc
    d = a[_CYCLIC_SHIFTS] - b[None]  # (shift, corner, 2), all four shifts at once
    dev = np.sqrt(np.sum(d * d, axis=2)).max(axis=1)
    shift = int(np.argmin(dev))
    c = cc - pc
    return shift, float(np.sqrt(np.sum(c * c))), float(dev[shift])


def match_tracked(
    detections: list[Detection],
    tracked: list[Tracked],
    camera: int,
    t: float,
    config: TrackingConfig,
    candidates: Callable[[Detection], list[int]],
    image_motion: Callable[[Tracked], np.ndarray | None] | None = None,
) -> list[Identity | None]:
    """The carried identity of each detection (None: decode it).

    A detection takes a tracked sticker's identity only when (1) that sticker was decoded, or
    carried, in the previous frame of this camera (``max_gap_s``) and is due no re-decode
    (``redecode_every``); (2) the detection is where and what that sticker was (``max_centre_shift``,
    ``max_shape_change``; moved by the image motion the tracker predicts, see :func:`match_tracks`),
    and the pairing is one to one; (3) the tracker's prediction, through ``candidates(detection)``
    (gated map stickers, most likely first), finds that sticker the most likely one here. The
    rotation follows the canonical corner through the corners' cyclic shift.
    """
    matches = match_tracks(detections, tracked, camera, t, config, candidates, image_motion)
    return [m.identity if m is not None and not m.due else None for m in matches]


@dataclass(frozen=True)
class TrackMatch:
    """A detection matched to a tracked sticker: its identity (rotation carried over), and whether
    that sticker is due for re-decoding (``TrackingConfig.redecode_every``)."""

    identity: Identity
    due: bool


def match_tracks(
    detections: list[Detection],
    tracked: list[Tracked],
    camera: int,
    t: float,
    config: TrackingConfig,
    candidates: Callable[[Detection], list[int]],
    image_motion: Callable[[Tracked], np.ndarray | None] | None = None,
    others: list[np.ndarray] | None = None,
) -> list[TrackMatch | None]:
    """:func:`match_tracked`, with the stickers due for re-decoding matched too (``due`` True), so
    that they can be re-checked against their tracked identity instead of decoded from scratch.
    Every track of the previous frame takes part in the one-to-one pairing, due or not, and so do
    ``others``: the outlines (4, 2) of that frame's other detections in this camera (not named by a
    read), each moved as the nearest track moved. A detection that could be one of them as well as
    a tracked sticker is not carried: when the tracked sticker is missed, the sticker next to it
    must not take its name (found by a review: an unmapped sticker laid 11 cm from a mapped one
    carried the mapped one's ID for three frames).

    ``image_motion(track)``: how far (px (2,)) the tracker predicts the track's sticker moved in
    the image since its frame, or None; the detection is then compared with the tracked outline
    moved by it. Turning at 1.5 rad/s sweeps the image by ~60 px a frame, more than the side of a
    sticker a few metres away, while the relative prediction is good to a few pixels."""
    if not detections:
        return []
    live = [k for k, tr in enumerate(tracked) if tr.camera == camera and within_gap(t - tr.t, config.max_gap_s)]
    expected = {}
    for k in live:
        moved_px = image_motion(tracked[k]) if image_motion is not None else None
        expected[k] = tracked[k].outer if moved_px is None else tracked[k].outer + moved_px
    # The other detections, as competitors only (index -1 - j), moved as the nearest track moved.
    previous = {k: tracked[k].outer for k in live}
    if live:
        centres = np.array([tracked[k].outer.mean(axis=0) for k in live])
        for j, outline in enumerate(others or []):
            near = live[int(np.argmin(np.linalg.norm(centres - outline.mean(axis=0), axis=1)))]
            previous[-1 - j] = outline
            expected[-1 - j] = outline + (expected[near] - tracked[near].outer)
    pairs: list[tuple[int, int, int]] = []  # (detection, tracked or -1 - other, shift)
    for i, det in enumerate(detections):
        for k in expected:
            side = min(_shortest_side(det.outer), _shortest_side(previous[k]))
            shift, moved, change = _shape_match(det.outer, expected[k])
            if moved <= config.max_centre_shift * side and change <= config.max_shape_change * side:
                pairs.append((i, k, shift))
    out: list[TrackMatch | None] = [None] * len(detections)
    for i, k, shift in pairs:
        if k < 0 or sum(p[0] == i for p in pairs) != 1 or sum(p[1] == k for p in pairs) != 1:
            continue
        ident = tracked[k].identity
        # The tracker's most likely sticker here must be the tracked one. Its gate may admit
        # neighbours too (0.7 m apart on a dense floor, under a conservative covariance): the
        # detection's continuity from the previous frame already tells them apart.
        cands = candidates(detections[i])
        if cands and cands[0] == ident.sticker_id:
            carried = Identity(ident.sticker_id, (ident.rotation + shift) % 4, ident.source)
            out[i] = TrackMatch(carried, tracked[k].age + 1 >= config.redecode_every)
    return out


@dataclass(frozen=True)
class Read:
    """What decoding made of one detection: an identity, or why not.

    Attributes:
        identity: the decoded sticker (in the map), or None.
        rejected: why symbols that were read gave no identity (None: accepted or nothing read).
        unmapped_id: a decoded ID that is not in the map (never a fix, not worth identifying).
        unmapped_rotation: its rotation (0-3), so that a map audit can place it.
    """

    identity: Identity | None = None
    rejected: str | None = None
    unmapped_id: int | None = None
    unmapped_rotation: int | None = None


def read_sticker(
    gray: np.ndarray,
    detection: Detection,
    camera: Camera,
    smap: StickerMap,
    backend: str,
    candidates: list[int] | None = None,
    config: DecodeConfig | None = None,
    expected: Callable[[], list[int]] | None = None,
) -> Read:
    """Decode one detection against the map (``candidates``: the tracker's, which may confirm a lone
    libdmtx read; ``expected``: gives the tracker's most likely one and its rivals, whose module
    check may name an unread sticker, as a CHECKED identity; see :func:`tagloc.vision.decode.decode`)."""
    res = decode(gray, detection, camera, backend=backend, candidates=candidates, config=config, expected=expected)
    if res.sticker_id is None:
        return Read(rejected=res.rejected)
    if res.stage == "expected":
        # Named by matching the tracker's expectation, not read from its symbols.
        return Read(Identity(res.sticker_id, res.rotation, IdSource.CHECKED, res.verify_score or 0.0))
    if res.sticker_id not in smap:
        return Read(
            rejected=f"decoded {res.sticker_id}, not in the map",
            unmapped_id=res.sticker_id,
            unmapped_rotation=res.rotation,
        )
    return Read(Identity(res.sticker_id, res.rotation, IdSource.DECODED))


def new_counts() -> dict[str, int]:
    """The per-run counters a localiser keeps (the baselines keep the same ones)."""
    keys = ("frames", "skipped", "detections", "decoded", "checked", "identified", "rejected_reads", "unmapped_reads")
    return dict.fromkeys(
        (
            *keys,
            "odometry_steps",
            "odometry_bridged",
            "odometry_bridge_forgotten",
            "odometry_bridge_unverified",
            "odometry_flow_only",
            "odometry_unverified",
            "odometry_strided",
            "odometry_unavailable",
            "flow_skipped",
            "odometry_unfused",
            "tilt_gated",
            "tilt_held",
            "rs_held",
            "held_fixes",
            "deflickered",
        ),
        0,
    )


def count_read(counts: dict[str, int], read: Read) -> None:
    """Add one decode outcome to ``counts`` ("checked": named by the expected ID's module check)."""
    counts["decoded"] += read.identity is not None and read.identity.source is IdSource.DECODED
    counts["checked"] += read.identity is not None and read.identity.source is IdSource.CHECKED
    counts["unmapped_reads"] += read.unmapped_id is not None
    counts["rejected_reads"] += read.rejected is not None and read.unmapped_id is None


def reference_bank(smap: StickerMap, map_path: str | Path | None = None) -> ReferenceBank:
    """The ORB/appearance references of ``smap``: cached beside ``map_path`` when given, else built."""
    from tagloc.vision.refs import build_refs, load_or_build_refs

    if map_path is not None:
        return load_or_build_refs(map_path, progress=False)
    return build_refs(smap, progress=False)


class FrameProcessor(Protocol):
    """Anything that turns frames into results: the :class:`Localiser`, or a paper baseline."""

    map: StickerMap
    rig: Rig
    counts: dict[str, int]

    def process(self, frame: Frame) -> FrameResult:
        """One frame in, what was seen and the pose after it out."""
        ...

    def stats(self) -> dict[str, int]:
        """The run's counters."""
        ...


def load_setup(
    map_path: str | Path | None = None,
    calibration: str | Path | None = None,
    rig_path: str | Path | None = None,
    config_dir: str | Path | None = None,
) -> tuple[StickerMap, Rig]:
    """Load the map and rig from explicit files, or all from a session-like ``config_dir``.

    Explicit files override the directory's. Without a rig, the default rig is used with the given
    calibration. The map is validated before anything else happens.
    """
    cdir = Path(config_dir) if config_dir is not None else None
    if cdir is not None and not cdir.is_dir():
        raise InputError(f"{cdir}: --config must be a directory holding camera.yaml, rig.json, map.csv")
    map_path = map_path or (cdir / MAP_FILE if cdir else None)
    if map_path is None:
        raise InputError("no map: give --map FILE or --config DIR")
    smap = load_map(map_path)
    camera = load_calibration(calibration) if calibration else None
    rig_path = rig_path or (cdir / RIG_FILE if cdir and (cdir / RIG_FILE).exists() else None)
    if rig_path is not None:
        rig = load_rig(rig_path, camera)
        names = list(dict.fromkeys(c.calibration_file for c in rig.cameras))
        if camera is not None and len(names) > 1 and not _same_calibrations(Path(rig_path).parent, names):
            # One calibration for cameras that have their own: a rear camera of another resolution
            # would have every frame refused as the wrong size, one of the same size be solved
            # through the wrong lens.
            raise InputError(
                f"{calibration}: --calibration would replace the calibration of every camera of {rig_path}, "
                f"whose {len(rig)} cameras have their own ({', '.join(names)}); leave --calibration out"
            )
    else:
        if camera is None and cdir is not None and (cdir / CAMERA_FILE).exists():
            camera = load_calibration(cdir / CAMERA_FILE)
        rig = default_rig(camera=camera)
    return smap, rig


def _same_calibrations(directory: Path, names: list[str]) -> bool:
    """Whether the calibration files ``names`` (relative to ``directory``) all hold one calibration: a
    recording names its cameras' calibrations ``camera<k>.yaml`` apart even when one served them all."""
    try:
        cams = [load_calibration(directory / name) for name in names]
    except (CalibrationError, InputError, OSError):
        return False
    return all(
        c.size == cams[0].size and np.array_equal(c.K, cams[0].K) and np.array_equal(c.dist, cams[0].dist)
        for c in cams[1:]
    )


class Localiser:
    """Per-frame vision plus the tracker, for one operator.

    One frame runs: predict -> floor odometry -> detect -> for each detection, decode and fuse its
    fix -> for each detection still unknown, identify among the tracker's candidates and fuse its fix
    -> output. Decoded stickers go first: their fixes sharpen the prediction the candidates come from.
    """

    def __init__(
        self,
        smap: StickerMap,
        rig: Rig,
        config: LocaliserConfig | None = None,
        refs: ReferenceBank | None = None,
        map_path: str | Path | None = None,
    ) -> None:
        self.map = smap
        self.rig = rig
        self.config = config or LocaliserConfig()
        self.tracker = Tracker(self.config.tracker)
        self._refs = refs
        self._map_path = map_path
        self._lookalikes = None  # the map's look-alikes (the expected-ID check's rivals), made on first use
        self._deflickers: dict[int, Deflicker] = {}  # per rig camera
        self._odometry: dict[int, FloorOdometry | None] = {}  # per rig camera; None: camera sees too little floor
        self._step = None  # this frame's odometry step, for the rolling-shutter correction
        # Set by a live loop while frames wait for the localiser (it is falling behind the camera):
        # the odometry may then skip frames as with odometry_stride, and the floor flow after
        # frames that read fixes placed as with skip_flow_after_fix.
        self.behind = False
        self.counts = new_counts()
        self.counts["tracked"] = 0  # detections whose identity came from sticker tracking, not a decode
        self.counts["reverified"] = 0  # of those, re-checked by module correlation when due a re-decode
        self.counts["lsq_skipped"] = 0  # decodes without the least-squares stage (failed there just before)
        self.counts["lsq_deferred"] = 0  # least-squares decodes run after their frame (defer_lsq)
        self.counts["deferred_named"] = 0  # of those detections, named then (decoded or identified)
        self.counts["deferred_fixes"] = 0  # and of those, fixes the tracker accepted
        self._pending: list[tuple] = []  # this frame's deferred least-squares decodes (defer_lsq)
        # Observations that deferred work finished since the last frame began: (frame index, observation).
        self.late: list[tuple[int, Observation]] = []
        self._index = -1  # the index of the frame being processed
        # (gray, camera, t, refine) (defer_odometry)
        self._pending_odo: tuple[np.ndarray, int, float, bool] | None = None
        # A step without the flow's refinement, held until the frame's fixes say whether to fuse it
        # (see skip_flow_after_fix): (step, camera).
        self._unrefined: tuple[OdometryStep, int] | None = None
        self._pending_anchors: list[tuple[float, float, float]] = []  # fixes' (t, pitch, roll) held for it
        self._held: list[HeldFix] = []  # fixes held for that step (tilt_gate_hold_chi2, rs_hold_for_step)
        self._failed: list[FailedRead] = []  # detections of the previous frame nothing named
        self._tracked: list[Tracked] = []  # decoded stickers of the previous frame whose fixes were accepted
        # Per camera: (time of its previous frame, that frame's detected quads, frames since the
        # last scheduled whole-image search, whether the regions were crowded) for the region
        # search (TrackingConfig.search_every).
        self._searched: dict[int, tuple[float, list[np.ndarray], int, bool]] = {}
        # Per camera: how many stickers its last frame read (decoded, checked or carried) whose
        # fixes the tracker accepted in the frame (see skip_flow_after_fix, skip_flow_min_fixes).
        self._read_fixed: dict[int, int] = {}
        self.counts["region_searches"] = 0  # frames searched only around expected stickers
        self.counts.update(
            refused_timestamps=0, clock_resets=0, wrong_size_frames=0, unusable_frames=0, repeated_frames=0
        )
        # Each camera's last image (index, array): a driver that hands the same buffer over again is
        # caught (see _check_repeat).
        self._last_image: dict[int, tuple[int, np.ndarray]] = {}
        self._last_t: float | None = None  # timestamp of the last frame accepted
        # Per (camera, sticker): the last few (frame time, canonical corners (N, 2) px) it was solved
        # at, for its corners' image velocity (rolling shutter, see rs_image_velocity_max_dt).
        self._sticker_corners: dict[tuple[int, int], list[tuple[float, np.ndarray]]] = {}
        self._refused_run = 0
        self._step = None  # this frame's odometry step, for the rolling-shutter correction

    @property
    def refs(self) -> ReferenceBank:
        """The ORB/appearance reference bank, built or loaded on first need."""
        if self._refs is None:
            self._refs = reference_bank(self.map, self._map_path)
        return self._refs

    def stats(self) -> dict[str, int]:
        """The localiser's counters with the tracker's (prefixed ``tracker_``)."""
        return {**self.counts, **{f"tracker_{k}": v for k, v in self.tracker.stats.items()}}

    def process(self, frame: Frame) -> FrameResult:
        """Run one frame through the pipeline and return what was seen and the pose after it.

        A frame that cannot be this camera's (wrong size) or is not after the last frame in time is
        refused: ``FrameResult.skipped`` says why and the pose is the filter's latest. One whose
        image is unreadable or repeats its camera's previous image is skipped as lost: the filter
        is carried to its time. ``frame.image`` is kept until the camera's next frames (see
        :class:`~tagloc.core.types.Frame`)."""
        timer = StageTimer()
        t = frame_seconds(frame.timestamp)
        self.counts["frames"] += 1
        self._index, self.late = frame.index, []
        if self._pending_odo is not None:
            # The last frame's deferred odometry step, not run in the wait (defer_odometry): it ends
            # at the filter's time, so it is fused before the filter moves on. The fixes that frame
            # held for it are fused now too: they go out as this frame's late ones (a copy, as
            # deferred work after this frame adds to :attr:`late`), or no run log records them.
            with timer("odometry"):
                self._run_pending_odometry()
        refused = self._check_size(frame) or self._check_time(frame)
        if refused:
            # The filter stays where it was: the output is its latest estimate, stamped with its own time.
            self.counts["skipped"] += 1
            with timer("output"):
                out = self.tracker.output()
            return FrameResult(frame.index, t, [], out, timer.finish(), refused, frame, list(self.late))
        # Whether this camera's odometry measures this frame (it may skip one while walking
        # straight, see OdometryConfig.max_stride; it cannot read an unreadable one): its next step
        # then starts from its frame before, and the tracker keeps its clone there.
        # A repeated image is a frame lost as an unreadable one is: the filter is carried to its time
        # (its uncertainty grows, and a frozen camera ends as a lost track), nothing is measured.
        repeated = self._check_repeat(frame)
        readable = frame.image is not None and repeated is None
        odo = self.floor_odometry(frame.camera) if self.config.odometry and readable else None
        measure = odo is not None and odo.wants(t, self.config.odometry_stride or self.behind)
        if odo is not None and not measure:
            self.counts["odometry_strided"] += 1
        with timer("predict"):
            self.tracker.predict(t, frame.camera, odometry=measure)
        refine = self._flow_needed(frame.camera) if measure else True
        if not readable:
            self.counts["skipped"] += 1
            with timer("output"):
                out = self.tracker.output(t)
            why = repeated or frame.error or "unreadable"
            return FrameResult(frame.index, t, [], out, timer.finish(), why, frame, list(self.late))
        gray = as_gray(frame.image)
        rig_cam = self.rig[frame.camera]
        if self.config.deflicker is not None:
            with timer("deflicker"):
                gray = self._deflicker(gray, frame.camera, rig_cam.readout_s)
        # Deferred decodes not run before this frame are dropped (the detection, still unread here,
        # queues its decode again).
        self._pending = []
        if measure and self.config.defer_odometry:
            self._pending_odo = (gray, frame.camera, t, refine)
        elif measure:
            # This camera's step since its previous frame: the tracker fuses it against its clone of
            # the pose there (tracker.clones), whatever other cameras' frames came in between.
            with timer("odometry"):
                self._odometry_step(gray, frame.camera, t, refine)
        elif odo is not None:
            odo.hold(gray, t)
        with timer("detect"):
            regions, since, crowded = self._search_plan(frame.camera, rig_cam, t)
            detections = detect(gray, rig_cam.camera, method=self.config.detector, regions=regions)
        previous = self._searched.get(frame.camera)
        self._searched[frame.camera] = (t, [d.outer.copy() for d in detections], since, crowded)
        self.counts["region_searches"] += regions is not None
        self.counts["detections"] += len(detections)

        matches = (
            match_tracks(
                detections,
                self._tracked,
                frame.camera,
                t,
                self.config.tracking,
                lambda det: self._candidates(det, rig_cam, timer),
                lambda tr: self._image_motion(tr, rig_cam),
                self._untracked(previous, frame.camera, t),
            )
            if self.config.sticker_tracking
            else [None] * len(detections)
        )
        reads, fixes, carried = [], [], []
        lsq_ages: list[int | None] = []  # per decoded detection: its least-squares age if it stays unknown
        for det, m in zip(detections, matches):
            carried.append(m.identity if m is not None and not m.due else None)
            if m is not None and (not m.due or self._reverify(gray, det, m.identity, rig_cam, timer)):
                read = Read(m.identity)
                self.counts["tracked"] += 1
                lsq_ages.append(None)
            else:
                read, age = self._decode_gated(gray, det, rig_cam, frame.camera, t, timer)
                lsq_ages.append(age)
            reads.append(read)
            fixes.append(
                self._fix(det, read.identity, rig_cam, frame.camera, t, timer) if read.identity is not None else None
            )

        observations = []
        failed: list[FailedRead] = []  # detections neither decoded nor identified, for the next frame
        for det, read, fix, age in zip(detections, reads, fixes, lsq_ages):
            identity = read.identity
            # A detection whose decode was deferred is identified after the frame too, if that decode
            # fails (as in the frame): here it would put back the cost the deferral took out.
            deferred = self.config.defer_lsq and any(job[1] is det for job in self._pending)
            if identity is None and read.unmapped_id is None and self.config.identify != "off" and not deferred:
                identity = self._identify(gray, det, rig_cam, timer)
                if identity is not None:
                    fix = self._fix(det, identity, rig_cam, frame.camera, t, timer)
            if identity is None and read.unmapped_id is None and age is not None:
                failed.append(FailedRead(det.outer.copy(), frame.camera, t, age))
            observations.append(
                Observation(det, frame.camera, identity, fix, read.rejected, read.unmapped_id, read.unmapped_rotation)
            )
        read_flags = [r.identity is not None for r in reads]
        self._track(observations, carried, read_flags, frame.camera, t)
        # Per camera, as the tracks are: another camera's frame in between must not wipe them.
        self._failed = [f for f in self._failed if f.camera != frame.camera] + failed
        self._read_fixed[frame.camera] = len(
            {
                o.sticker_id
                for o, r in zip(observations, read_flags)
                if r and o.fix is not None and o.fix.accepted is True
            }
        )
        self._fuse_unrefined()

        with timer("output"):
            out = self.tracker.output(t)
        return FrameResult(frame.index, t, observations, out, timer.finish(), None, frame, list(self.late))

    def _search_plan(
        self, camera: int, rig_cam: RigCamera, t: float
    ) -> tuple[list[tuple[int, int, int, int]] | None, int, bool]:
        """Where to search this frame for stickers (``TrackingConfig.search_every``): boxes (x0, y0,
        x1, y1) around the camera's previous detections and the mapped stickers the tracker predicts
        in view, or None for the whole image; with the frames since the last scheduled whole-image
        search (0: this one) and whether the regions are crowded (they covered too much of the image:
        none are worked out again before the next scheduled whole-image search)."""
        cfg = self.config.tracking
        prev = self._searched.get(camera)
        if cfg.search_every <= 1 or not self.config.sticker_tracking or self.config.detector != "contour":
            return None, 0, False
        if prev is None or prev[2] + 1 >= cfg.search_every or not within_gap(t - prev[0], cfg.max_gap_s):
            return None, 0, False
        since, crowded = prev[2] + 1, prev[3]
        # The prior without the walking model's noise for the frame interval: ``reach`` bounds the
        # image's motion over it (see Tracker.search_prior).
        prior = self.tracker.search_prior()
        if crowded or len(prev[1]) > cfg.search_max_stickers or prior is None:
            return None, since, crowded  # (not tracking: nothing says where stickers are)
        cam = rig_cam.camera
        reach = cfg.search_rate_rad_s * (t - prev[0]) * cam.fx
        boxes = [(*(q.min(axis=0) - reach), *(q.max(axis=0) + reach)) for q in prev[1]]
        mean, cov = prior
        proj = project_map(mean, self.map, self.tracker.leaned_camera(rig_cam))
        if len(proj.rows):
            # Half a sticker's diagonal at its depth, the motion since the previous frame, and the
            # prior's position and heading uncertainty (as pixels at that depth).
            pos_sigma = math.sqrt(max(largest_eig_2x2(cov), 0.0))
            yaw_sigma = math.sqrt(max(float(cov[2, 2]), 0.0))
            depth = np.maximum(proj.depth, 1e-3)
            r = (cfg.search_sticker_reach * SIZE_M + cfg.search_sigmas * pos_sigma) * cam.fx / depth
            r = r + reach + cfg.search_sigmas * yaw_sigma * cam.fx
            boxes += [(u - ri, v - ri, u + ri, v + ri) for (u, v), ri in zip(proj.pixels, r)]
        out = []
        for x0, y0, x1, y1 in boxes:
            x0, y0 = max(0, math.floor(x0)), max(0, math.floor(y0))
            x1, y1 = min(cam.width, math.ceil(x1) + 1), min(cam.height, math.ceil(y1) + 1)
            if x1 > x0 and y1 > y0:
                out.append((x0, y0, x1, y1))
        out = merge_boxes(out)
        if sum((x1 - x0) * (y1 - y0) for x0, y0, x1, y1 in out) > cfg.search_max_area * cam.width * cam.height:
            return None, since, True
        return out, since, False

    def _track(
        self,
        observations: list[Observation],
        carried: list[Identity | None],
        read: list[bool],
        camera: int,
        t: float,
    ) -> None:
        """Keep this frame's stickers named by reading them (decoded, matched by the expected-ID
        check, or carried; ``read``: per observation) whose fixes the tracker accepted: only they
        may carry their identity into the next frame of this camera. Identification among candidates
        does not. The other cameras' tracks are kept: with two cameras their frames alternate, and
        each camera's tracks must reach its own next frame (match_tracks pairs within a camera)."""
        ages = {tr.identity.sticker_id: tr.age for tr in self._tracked if tr.camera == camera}
        self._tracked = [tr for tr in self._tracked if tr.camera != camera]
        held = {id(h.det): h for h in self._held if h.camera == camera and h.t == t}
        for obs, c, r in zip(observations, carried, read):
            ident = obs.identity
            h = held.get(id(obs.detection))
            if ident is not None and r and h is not None:
                # Its fix is judged after the frame: tracked then if accepted (see _resolve_held).
                h.track_age = ages.get(ident.sticker_id, 0) + 1 if c is not None else 0
            if ident is None or not r or obs.fix is None or obs.fix.accepted is not True:
                continue
            age = ages.get(ident.sticker_id, 0) + 1 if c is not None else 0
            self._tracked.append(Tracked(obs.detection.outer.copy(), ident, camera, t, age))
        self._predict_tracked(camera)

    def _untracked(
        self, previous: tuple[float, list[np.ndarray], int, bool] | None, camera: int, t: float
    ) -> list[np.ndarray]:
        """The outlines of ``camera``'s previous frame's detections (``previous``: its entry of the
        region search's memory) that no track holds (see :func:`match_tracks`'s ``others``; a
        deferred decode that named one after its frame made it a track), if that frame is recent
        enough to match against."""
        if previous is None or not within_gap(t - previous[0], self.config.tracking.max_gap_s):
            return []
        held = [tr.outer for tr in self._tracked if tr.camera == camera and tr.t == previous[0]]
        return [o for o in previous[1] if not any(np.array_equal(o, h) for h in held)]

    def _predict_tracked(self, camera: int) -> None:
        """Note where the tracker now puts each of ``camera``'s tracked stickers
        (:attr:`Tracked.predicted_px`). Only that camera's, just fused: another camera's tracks
        keep the place predicted at their own frame's time, from which their image motion runs."""
        ids = [tr.identity.sticker_id for tr in self._tracked if tr.camera == camera]
        if not ids:
            return
        pix = self.tracker.sticker_pixels(self.map, self.rig[camera], ids)
        self._tracked = [
            dataclasses.replace(tr, predicted_px=pix.get(tr.identity.sticker_id)) if tr.camera == camera else tr
            for tr in self._tracked
        ]

    def _image_motion(self, tr: Tracked, rig_cam: RigCamera) -> np.ndarray | None:
        """How far the tracker predicts ``tr``'s sticker moved in the image since its frame (px (2,)),
        or None (not known then or now)."""
        if tr.predicted_px is None:
            return None
        now = self.tracker.sticker_pixels(self.map, rig_cam, [tr.identity.sticker_id]).get(tr.identity.sticker_id)
        return None if now is None else now - tr.predicted_px

    def _check_repeat(self, frame: Frame) -> str | None:
        """Why the frame is skipped as its camera's previous image over again, or None.

        A sensor's noise never gives two equal frames; a driver that re-delivers a buffer (or a
        caller that fills one array in place) does. Measured as a step, such a frame says the
        camera did not move, confidently (one in five frames repeated on a 4 s walk took it from
        2.3 to 8.3 cm RMSE), so it is not measured. A few rows are compared first:
        real frames differ there, and the whole image is compared only when they agree. Such a
        frame is then skipped as a lost one (see :meth:`process`)."""
        if frame.image is None:
            return None
        last = self._last_image.get(frame.camera)
        self._last_image[frame.camera] = (frame.index, frame.image)
        if last is None:
            return None
        prev = last[1]
        if prev is not frame.image and (
            prev.shape != frame.image.shape
            or not np.array_equal(prev[::61], frame.image[::61])
            or not np.array_equal(prev, frame.image)
        ):
            return None
        self.counts["repeated_frames"] += 1
        return (
            f"frame {frame.index}: the same image as camera {frame.camera}'s frame {last[0]} "
            "(a re-delivered buffer, or one array filled in place: each frame needs its own)"
        )

    def _check_time(self, frame: Frame) -> str | None:
        """Why the frame's timestamp is refused, or None (then it becomes the last accepted time)."""
        t = frame_seconds(frame.timestamp)  # a library caller's None or text is refused as a NaN is
        if not math.isfinite(t):
            self.counts["refused_timestamps"] += 1
            return f"frame {frame.index}: timestamp {str(frame.timestamp)[:40]!r} is not a finite number"
        last = self._last_t
        if last is not None and t <= last:
            self._refused_run += 1
            if self._refused_run < self.config.clock_reset_frames:
                self.counts["refused_timestamps"] += 1
                return (
                    f"frame {frame.index}: timestamp {seconds_text(t)} s is not after the previous frame's"
                    f" {seconds_text(last)} s"
                )
            self._restart()
        self._refused_run = 0
        self._last_t = t
        return None

    def _restart(self) -> None:
        """Start the track afresh on a source clock that was reset (nothing of the old track holds)."""
        self.counts["clock_resets"] += 1
        self.tracker = Tracker(self.config.tracker)
        self._odometry.clear()
        self._tracked = []
        self._failed = []
        self._pending = []
        self._held, self._pending_anchors = [], []  # (resolved at the frame's start already: kept empty)
        self._searched = {}
        self._read_fixed = {}
        self._sticker_corners = {}

    def _deflicker(self, gray: np.ndarray, camera: int, readout_s: float) -> np.ndarray:
        """``gray`` with the camera's lamp flicker bands divided out, or as it is while it has none."""
        d = self._deflickers.get(camera)
        if d is None:
            d = self._deflickers[camera] = Deflicker(readout_s, self.config.deflicker)
        out = d(gray)
        self.counts["deflickered"] += out is not gray
        return out

    def _check_size(self, frame: Frame) -> str | None:
        """Why the frame's image cannot be this camera's, or None."""
        if frame.image is None:
            return None
        if not 0 <= frame.camera < len(self.rig.cameras):
            return f"frame {frame.index}: camera {frame.camera} is not in the rig ({len(self.rig.cameras)} cameras)"
        why = unusable(frame.image)
        if why is not None:
            # Not an image any stage takes (a 1-D buffer, two channels, complex numbers): refused as
            # a frame of the wrong size is, before the filter moves, rather than raised mid-frame.
            self.counts["unusable_frames"] += 1
            return f"frame {frame.index}: {why}"
        cam = self.rig[frame.camera].camera
        h, w = frame.image.shape[:2]
        if (w, h) != (cam.width, cam.height):
            self.counts["wrong_size_frames"] += 1
            return f"frame {frame.index}: image is {w}x{h}, the calibration is for {cam.width}x{cam.height}"
        return None

    def warm_up(self) -> None:
        """Do now the set-up the first frames would otherwise pay (a live loop, before its first
        frame: 0.1 s of it landed on the first frame's latency): each camera's odometry (patch
        search, remap tables), the least-squares decoder's blur models, the expected-ID check's
        module masks and, with a reference bank, identification's tables."""
        if self.config.decoder in ("zxing", "both"):
            from tagloc.vision.decode import blur, verify

            blur.prepare()
            if self.config.check_expected:
                verify.prepare()
                self.lookalikes.prepare()
        if self.config.odometry:
            for c in range(len(self.rig)):
                self.floor_odometry(c)
        if self.config.identify != "off" and self._refs is not None:
            from tagloc.vision.identify import prepare

            prepare(self._refs)

    @property
    def lookalikes(self) -> LookAlikes:
        """The map's look-alikes (:class:`tagloc.vision.decode.lookalike.LookAlikes`), made on first use."""
        if self._lookalikes is None:
            from tagloc.vision.decode.lookalike import LookAlikes

            self._lookalikes = LookAlikes(self.map.ids, self.config.lookalike_min_corr)
        return self._lookalikes

    def floor_odometry(self, camera: int) -> FloorOdometry | None:
        """The floor odometry of rig camera ``camera`` (made on first use), or None if that camera
        sees too little floor for it or is not one of ``odometry_cameras``."""
        chosen = self.config.odometry_cameras
        if camera not in self._odometry and chosen is not None and camera not in chosen:
            self._odometry[camera] = None
        if camera not in self._odometry:
            try:
                self._odometry[camera] = FloorOdometry(self.rig[camera], self.config.odometry_config)
            except CalibrationError:
                self._odometry[camera] = None
                self.counts["odometry_unavailable"] += 1
        return self._odometry[camera]

    def _odometry_step(self, gray: np.ndarray, camera: int, t: float, refine: bool = True) -> None:
        """Measure this camera's step to the frame at ``t`` and fuse it; a step without the flow's
        refinement (``refine`` False) is held (:attr:`_unrefined`) until the frame's fixes are
        known, then fused only if none of them placed the frame (:meth:`_fuse_unrefined`; see
        ``skip_flow_after_fix``)."""
        odo = self.floor_odometry(camera)
        velocity = self.tracker.velocity()
        # The walk's predicted motion: a rolling-shutter patch's remap, and where the patch finds no
        # match, the floor flow's start (OdometryConfig.flow_without_patch).
        wants_twist = self.rig[camera].readout_s > 0 or (odo is not None and odo.flow_without_patch)
        twist = velocity if wants_twist else None
        speed = None if velocity is None else float(velocity[0])
        self.counts["flow_skipped"] += odo is not None and not refine
        before = (odo.bridges_unverified, odo.steps_unverified, odo.flow_only_steps) if odo is not None else None
        step = odo.measure(gray, t, twist, speed, refine) if odo is not None else None
        self._step = step
        if odo is not None:
            self.counts["odometry_bridge_unverified"] += odo.bridges_unverified - before[0]
            self.counts["odometry_unverified"] += odo.steps_unverified - before[1]
            self.counts["odometry_flow_only"] += odo.flow_only_steps - before[2]
        if step is not None:
            # Only a step over dropped frames spans more than max_dt (see OdometryConfig.bridge_max_dt).
            self.counts["odometry_bridged"] += int(step.t1 - step.t0 > odo.config.max_dt)
            if refine:
                self._fuse_step(step, camera)
            else:
                self._unrefined = (step, camera)

    def _fuse_step(self, step: OdometryStep, camera: int) -> None:
        """Fuse a camera's odometry step; a bridged step the tracker refuses also takes back what the
        odometry learnt from it (``LocaliserConfig.forget_refused_bridge``)."""
        self.counts["odometry_steps"] += 1
        res = self.tracker.update_odometry(step, camera)
        odo = self.floor_odometry(camera)
        # Refused by a gate (its NIS known), not for want of a track or a clone to move.
        gated = not res.accepted and math.isfinite(res.nis)
        if self.config.forget_refused_bridge and gated and step.t1 - step.t0 > odo.config.max_dt:
            odo.forget_motion()
            self.counts["odometry_bridge_forgotten"] += 1

    def _flow_needed(self, camera: int) -> bool:
        """Whether this frame's odometry step needs the floor flow's refinement: False only when the
        camera's last frame was placed by at least ``need`` read fixes and the tracker now predicts
        at least ``need`` of its tracked stickers ``skip_flow_margin_px`` inside the image (so that
        this frame will very likely be placed by them too); ``need`` is 1 with
        ``skip_flow_after_fix`` (or :attr:`behind`), else ``skip_flow_min_fixes`` (0: never)."""
        cfg = self.config
        need = 1 if (cfg.skip_flow_after_fix or self.behind) else cfg.skip_flow_min_fixes
        if need <= 0 or self._read_fixed.get(camera, 0) < need:
            return True
        rig_cam = self.rig[camera]
        ids = [tr.identity.sticker_id for tr in self._tracked if tr.camera == camera]
        m, w, h = cfg.skip_flow_margin_px, rig_cam.camera.width, rig_cam.camera.height
        pix = self.tracker.sticker_pixels(self.map, rig_cam, ids).values()
        return sum(m <= u <= w - 1 - m and m <= v <= h - 1 - m for u, v in pix) < need

    def _fuse_unrefined(self) -> None:
        """Fuse the held unrefined step unless its frame was placed by a read fix."""
        held, self._unrefined = self._unrefined, None
        if held is None:
            return
        step, camera = held
        if self._read_fixed.get(camera, False):
            self.counts["odometry_unfused"] += 1
        else:
            self._fuse_step(step, camera)

    def _body_twist(self, rig_cam: RigCamera, t: float) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The body's motion (vx, vy, yaw rate; body frame) for the rolling-shutter correction, or
        None, and its standard deviations when it is the tracker's estimate (None: measured)."""
        if not self._rolling_shutter(rig_cam):
            return None, None
        s = self._step
        if s is not None and s.t1 == t and s.t1 > s.t0:
            # The vest's own motion over the last frame interval, wobble included.
            return np.asarray(s.delta, float) / (s.t1 - s.t0), None
        # The prediction is only as good as its sigmas: after a second blind, 0.6 m/s and 1.2 rad/s.
        return self.tracker.velocity(), self.tracker.velocity_sigma()

    def survey_prior(self, sticker_id: int) -> SurveyPrior:
        """The sticker's map position and survey sigmas: the map's ``sigma_m``/``sigma_deg`` where
        stated, else the pose config's defaults (``map_sigma_m``, ``map_sigma_yaw``)."""
        row = self.map.row(sticker_id)
        sig_m, sig_yaw = self.config.pose.survey_sigmas(float(self.map.sigma_xy[row]), float(self.map.sigma_yaw[row]))
        return SurveyPrior(np.asarray(self.map.T_world_sticker(sticker_id)[:2, 3], float), sig_m, sig_yaw)

    def _candidates(self, det: Detection, rig_cam: RigCamera, timer: StageTimer) -> list[int]:
        with timer("candidates"):
            return self.tracker.candidates(self.map, rig_cam, det.outer.mean(axis=0), k=self.config.candidates)

    def _reverify(
        self, gray: np.ndarray, det: Detection, identity: Identity, rig_cam: RigCamera, timer: StageTimer
    ) -> bool:
        """Whether a tracked sticker due for re-decoding still shows its tracked ID and rotation
        (``TrackingConfig.reverify``); timed as decoding, which it stands in for."""
        cfg = self.config.tracking
        if not cfg.reverify:
            return False
        with timer("decode"):
            score = verify_detection(gray, det, rig_cam.camera, identity.sticker_id, identity.rotation)
        ok = score >= cfg.reverify_min_score
        self.counts["reverified"] += ok
        return ok

    def _decode_gated(
        self,
        gray: np.ndarray,
        det: Detection,
        rig_cam: RigCamera,
        camera: int,
        t: float,
        timer: StageTimer,
    ) -> tuple[Read, int]:
        """Decode, leaving out the least-squares stage on a detection that neither decoding nor
        identification named in the previous frame until its retry is due
        (``TrackingConfig.lsq_retry_every``). Returns the read and the frames since the
        least-squares stage last ran on this detection (0: now)."""
        cfg = self.config.tracking
        prev = next(
            (
                f
                for f in self._failed
                if f.camera == camera and within_gap(t - f.t, cfg.max_gap_s) and _same_place(det, f.outer, cfg)
            ),
            None,
        )
        # Before the first fix nothing else can place the operator, and the frame has no tracking
        # work: every detection gets every stage.
        skip_lsq = (
            self.config.sticker_tracking
            and prev is not None
            and prev.age + 1 < cfg.lsq_retry_every
            and not (cfg.lsq_while_initialising and self.tracker.state is TrackState.INITIALISING)
        )
        self.counts["lsq_skipped"] += skip_lsq
        defer = self.config.defer_lsq and self.config.decoder == "zxing" and not skip_lsq
        read = self._decode(gray, det, rig_cam, timer, DecodeConfig(lsq=False) if skip_lsq or defer else None)
        if defer and read.identity is None and read.unmapped_id is None:
            self._pending.append((gray, det, rig_cam, camera, t, self._index))
        return read, prev.age + 1 if skip_lsq else 0

    def deferred_work(self, go_on: Callable[[], bool] | None = None) -> int:
        """Finish what the last frame deferred. First its odometry step (``defer_odometry``) and its
        fixes' tilt anchors, always (the step must reach the filter before it moves on). Then the
        detections it deferred (``defer_lsq``), each while ``go_on()`` (default: always) says there
        is time (a live loop: no frame waiting) or the tracker has no track
        (``finish_lsq_untracked``): the whole decode, identification if it fails, and
        the fix, fused at the frame's time as the frame would have fused it (the filter is still
        there); a decoded sticker whose fix the tracker accepted is tracked into the next frame.
        Each named detection is added to :attr:`late` with its frame's index (cleared when the next
        frame starts), so that a caller can count its fix with that frame's, as is each fix the
        frame held for its step (``tilt_gate_hold_chi2``, ``rs_hold_for_step``), judged and fused
        right after the step. Returns how many detections ran; the rest are dropped."""
        self._run_pending_odometry()
        jobs, self._pending = self._pending, []
        ran = 0
        for gray, det, rig_cam, camera, t, index in jobs:
            # Without a track a read is the only way to a pose: not left for want of time.
            untracked = self.config.finish_lsq_untracked and self.tracker.state is not TrackState.TRACKING
            if go_on is not None and not untracked and not go_on():
                break
            ran += 1
            timer = StageTimer()  # not reported: the frame's result is already out
            read = read_sticker(gray, det, rig_cam.camera, self.map, self.config.decoder)
            identity = read.identity
            if identity is not None or read.unmapped_id is not None:
                count_read(self.counts, read)
            if identity is None and read.unmapped_id is None and self.config.identify != "off":
                identity = self._identify(gray, det, rig_cam, timer)
            if identity is None and read.unmapped_id is None:
                continue
            # Named after all (or read as an unmapped sticker): not a failed read (see process).
            self._failed = [f for f in self._failed if not (f.t == t and np.array_equal(f.outer, det.outer))]
            if identity is None:
                continue
            self.counts["deferred_named"] += 1
            fix = self._fix(det, identity, rig_cam, camera, t, timer)
            self.counts["deferred_fixes"] += fix.accepted is True
            self.late.append((index, Observation(det, camera, identity, fix)))
            # Decoded and accepted: carried into the next frame (see _track).
            if identity.source == IdSource.DECODED and fix.accepted is True:
                self._tracked.append(Tracked(det.outer.copy(), identity, camera, t, 0))
                self._predict_tracked(camera)
        self.counts["lsq_deferred"] += ran
        return ran

    def finish(self) -> list[tuple[int, Observation]]:
        """At the end of a run: the last frame's deferred work (:meth:`deferred_work`, all of it),
        which no next frame would run, and the observations it finished, each with its frame's
        index (:attr:`late`). Nothing when nothing was deferred (a replay)."""
        self.late = []  # (what the last frame began with went out in its result)
        self.deferred_work()
        return list(self.late)

    def _decode(
        self,
        gray: np.ndarray,
        det: Detection,
        rig_cam: RigCamera,
        timer: StageTimer,
        config: DecodeConfig | None = None,
    ) -> Read:
        # Only libdmtx can need the tracker's word: zxing reads stand or fall on their own.
        cands = self._candidates(det, rig_cam, timer) if self.config.decoder != "zxing" else None
        expected = None
        if self.config.check_expected:

            def expected() -> list[int]:
                # Asked only when the quick stages read nothing; timed as decoding, which it is part
                # of. With libdmtx the candidates are already there, most likely first. The most
                # likely one, then its rivals: the other candidates and its look-alikes in the map.
                ranked = (
                    cands
                    if cands is not None
                    else self.tracker.candidates(self.map, rig_cam, det.outer.mean(axis=0), k=self.config.candidates)
                )
                return [*ranked, *self.lookalikes.rivals(ranked[0])] if ranked else []

        with timer("decode"):
            read = read_sticker(gray, det, rig_cam.camera, self.map, self.config.decoder, cands, config, expected)
        count_read(self.counts, read)
        return read

    def _identify(self, gray: np.ndarray, det: Detection, rig_cam: RigCamera, timer: StageTimer) -> Identity | None:
        from tagloc.vision.identify import identify

        cands = self._candidates(det, rig_cam, timer)
        if not cands:
            return None
        with timer("identify"):
            res = identify(gray, det, rig_cam.camera, cands, self.refs, method=self.config.identify)
        if res.sticker_id is None:
            return None
        self.counts["identified"] += 1
        return Identity(res.sticker_id, res.rotation, res.source, res.score, res.margin)

    def _fix(
        self, det: Detection, identity: Identity, rig_cam: RigCamera, camera: int, t: float, timer: StageTimer
    ) -> Fix:
        with timer("pose"):
            velocity = self._corner_velocity(det, identity, rig_cam, camera, t)
            if (
                self._pending_odo is not None
                and velocity is None
                and self.config.rs_hold_for_step
                and self._rolling_shutter(rig_cam)
            ):
                # Corrected with the body's motion, which the frame's own step measures (see
                # rs_hold_for_step): solved once that step is fused.
                self._held.append(HeldFix(det, identity, rig_cam, camera, t, self._index))
                self.counts["rs_held"] += 1
                return Fix([], False, None, HELD_REASON)
            sol = self._solve(det, identity, rig_cam, t, velocity)
        if not sol.poses:
            return Fix([], sol.ambiguous, row_time_s=sol.row_time_s)
        if self._pending_odo is not None and self._hold(sol.poses, rig_cam, t):
            self._held.append(HeldFix(det, identity, rig_cam, camera, t, self._index, sol))
            self.counts["tilt_held"] += 1
            return Fix(sol.poses, sol.ambiguous, None, HELD_REASON, row_time_s=sol.row_time_s)
        return self._gate_and_fuse(sol, identity, rig_cam, t, timer)

    def _solve(
        self, det: Detection, identity: Identity, rig_cam: RigCamera, t: float, velocity: np.ndarray | None
    ) -> PoseSolution:
        """The camera and body poses the sticker gives, corrected for a rolling shutter by its corners'
        image ``velocity`` (N, 2) px/s, or else by the body's motion (see :meth:`_body_twist`)."""
        twist, twist_sigma = self._body_twist(rig_cam, t) if velocity is None else (None, None)
        # The fix itself is solved against the map as if exact: the tracker carries the sticker's
        # survey error as a state, shared by all of that sticker's fixes.
        return solve_pose(
            det,
            identity.rotation,
            self.map.T_world_sticker(identity.sticker_id),
            rig_cam,
            config=self.config.pose,
            body_twist=twist,
            corner_velocity=velocity,
            body_twist_sigma=twist_sigma,
        )

    def _rolling_shutter(self, rig_cam: RigCamera) -> bool:
        """Whether fixes of ``rig_cam`` are corrected for its rolling shutter (by their corners'
        image velocity, or else the body's motion)."""
        return self.config.rolling_shutter and rig_cam.readout_s > 0

    def _gate_and_fuse(
        self, sol: PoseSolution, identity: Identity, rig_cam: RigCamera, t: float, timer: StageTimer
    ) -> Fix:
        """A sticker's pose solution (at least one pose) through the tilt gate and the tracker; an
        accepted fix anchors the odometry's tilt (after the frame's step when that is deferred)."""
        poses = self._tilt_gate(sol.poses, rig_cam, t)
        if not poses:
            self.counts["tilt_gated"] += 1
            return Fix(
                sol.poses,
                sol.ambiguous,
                False,
                "tilt gated: the camera's tilt disagrees with the torso's",
                row_time_s=sol.row_time_s,
            )
        with timer("update"):
            res = self.tracker.update(
                poses,
                identity.sticker_id,
                identity.source,
                t,
                self.survey_prior(identity.sticker_id),
                row_time_s=sol.row_time_s,
            )
        if res.accepted and res.chosen is not None:
            # The sticker's plane gives the torso's tilt whatever the map says of the sticker's
            # place: it anchors every camera's odometry tilt (see tagloc.vision.torso_tilt).
            tilt = torso_tilt(poses[res.chosen].T_world_camera, rig_cam.T_body_camera)
            if self._pending_odo is not None:
                # The frame's odometry step (deferred) comes first: it carries the tilt up to t.
                self._pending_anchors.append((t, *tilt))
            else:
                self._anchor_tilt(t, *tilt)
        return Fix(poses, len(poses) > 1, res.accepted, res.reason, row_time_s=sol.row_time_s)

    def _hold(self, poses: list[PoseFix], rig_cam: RigCamera, t: float) -> bool:
        """Whether a fix waits for its frame's deferred odometry step before the tilt gate judges it:
        with ``tilt_gate_hold``, none of its solutions is within ``tilt_gate_hold_chi2`` of the
        tilt filter as it stands without that step (see the config)."""
        chi2, hold = self.config.tilt_gate_chi2, self.config.tilt_gate_hold_chi2
        odo = self._tilt_odometry(rig_cam)
        if not self.config.tilt_gate_hold or chi2 <= 0 or hold >= chi2 or odo is None:
            return False
        return not any(odo.tilt_consistent(t, p.T_world_camera, hold)[0] for p in poses)

    def _resolve_held(self) -> None:
        """The held fixes, now that their frame's step is fused: solved if they were held unsolved
        (``rs_hold_for_step``), gated and fused at their frame's time, each added to :attr:`late`
        with its frame's index; one named by reading and accepted is tracked into the next frame,
        as the frame would have tracked it."""
        held, self._held = self._held, []
        for h in held:
            sol = h.sol if h.sol is not None else self._solve(h.det, h.identity, h.rig_cam, h.t, None)
            if sol.poses:
                fix = self._gate_and_fuse(sol, h.identity, h.rig_cam, h.t, StageTimer())
            else:
                fix = Fix([], sol.ambiguous, row_time_s=sol.row_time_s)
            self.counts["held_fixes"] += fix.accepted is True
            self.late.append((h.index, Observation(h.det, h.camera, h.identity, fix)))
            if fix.accepted is not True or h.track_age is None:
                continue
            sid = h.identity.sticker_id
            if not any(tr.camera == h.camera and tr.identity.sticker_id == sid for tr in self._tracked):
                self._read_fixed[h.camera] = self._read_fixed.get(h.camera, 0) + 1
            self._tracked.append(Tracked(h.det.outer.copy(), h.identity, h.camera, h.t, h.track_age))
            self._predict_tracked(h.camera)

    def _corner_velocity(
        self, det: Detection, identity: Identity, rig_cam: RigCamera, camera: int, t: float
    ) -> np.ndarray | None:
        """The sticker's corners' image velocity (N, 2) px/s, canonical order, from its sight in this
        camera's previous frame (``rs_image_velocity_max_dt``); None without a rolling shutter or
        such a sight. Records this sight for the next frame."""
        if not self._rolling_shutter(rig_cam):
            return None
        pts = rotate_corners(np.asarray(det.points, float), identity.rotation)
        key = (camera, identity.sticker_id)
        seen = self._sticker_corners.setdefault(key, [])
        prev = max((s for s in seen if s[0] < t), key=lambda s: s[0], default=None)
        seen.append((t, pts))
        del seen[:-_CORNER_SIGHTS]
        if len(self._sticker_corners) > _CORNER_MEMORY:
            forget = t - self.config.rs_corner_forget_s
            self._sticker_corners = {k: v for k, v in self._sticker_corners.items() if v[-1][0] > forget}
        if prev is None or not within_gap(t - prev[0], self.config.rs_image_velocity_max_dt):
            return None
        if not _same_place(det, prev[1][:4], self.config.tracking):
            # Not where and what the sticker was (a wrong name in either frame): no motion to take.
            return None
        a, b = prev[1], pts
        if len(a) != len(b):
            # One sight had the inner corners, the other not: the outer corners' mean motion for all.
            v = (b[:4] - a[:4]).mean(axis=0) / (t - prev[0])
            return np.tile(v, (len(b), 1))
        return (b - a) / (t - prev[0])

    def _anchor_tilt(self, t: float, pitch: float, roll: float) -> None:
        for odo in self._odometry.values():
            if odo is not None:
                odo.anchor_tilt_angles(t, pitch, roll)

    def _run_pending_odometry(self) -> None:
        """The deferred odometry step of the last frame (``defer_odometry``), the tilt anchors of that
        frame's fixes, then its held fixes (:meth:`_resolve_held`), in the order a replay runs them
        (a replay anchors each fix before judging the next)."""
        job, self._pending_odo = self._pending_odo, None
        if job is not None:
            self._odometry_step(*job)
        anchors, self._pending_anchors = self._pending_anchors, []
        for anchor in anchors:
            self._anchor_tilt(*anchor)
        self._resolve_held()
        if job is not None:
            self._fuse_unrefined()  # (its frame's fixes, held ones too, are known by now)

    def _tilt_odometry(self, rig_cam: RigCamera) -> FloorOdometry | None:
        """The floor odometry of ``rig_cam`` (whose tilt filter the gate asks), or None."""
        return next((o for o in self._odometry.values() if o is not None and o.rig_camera is rig_cam), None)

    def _tilt_gate(self, poses: list[PoseFix], rig_cam: RigCamera, t: float) -> list[PoseFix]:
        """The pose solutions whose camera tilt agrees with this camera's odometry tilt (all of them
        when the gate is off or the camera runs no tilt filter)."""
        chi2 = self.config.tilt_gate_chi2
        odo = self._tilt_odometry(rig_cam)
        if chi2 <= 0 or odo is None:
            return poses
        kept = [p for p in poses if odo.tilt_consistent(t, p.T_world_camera, chi2)[0]]
        odo.tilt_gate_result(bool(kept))
        if not kept and odo.tilt_gated_in_row == 0:
            # The filter had been refusing fixes in a row and was reset: judge these against the prior.
            kept = [p for p in poses if odo.tilt_consistent(t, p.T_world_camera, chi2)[0]]
        return kept
