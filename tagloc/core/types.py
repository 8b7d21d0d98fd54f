"""Data passed along the per-frame path: frames, detections, fixes, observations, tracker output.

Units: metres and radians; pixels for image coordinates. Covariances are over (x, y, yaw) of the
body frame in the world unless stated.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from enum import Enum

import numpy as np


def frame_seconds(t: object) -> float:
    """A frame's timestamp as a float: NaN for one that is no number (a library caller's None or
    text), which the localiser refuses as it refuses a NaN, and which every output takes."""
    return math.nan if isinstance(t, bool) or not isinstance(t, numbers.Real) else float(t)


def seconds_text(t: float) -> str:
    """A time (s) for a message: to the microsecond (frames.csv's resolution), or in exponent form
    past 1e12 s, where the microseconds would print hundreds of digits of a corrupt stamp."""
    return f"{t:.6f}" if abs(t) < 1e12 else f"{t:.6g}"


@dataclass
class Frame:
    """One frame of one camera.

    Attributes:
        index: frame number in the session.
        timestamp: seconds (the session's clock, not wall time).
        image: (H, W) uint8 greyscale, or None when the frame could not be read. Each frame its own
            array, left unchanged once handed over: the localiser keeps the last ones (the floor
            odometry's previous frame) and skips an array it was given before.
        camera: index of the rig camera that took it.
        error: why ``image`` is None.
    """

    index: int
    timestamp: float
    image: np.ndarray | None
    camera: int = 0
    error: str | None = None


class IdSource(str, Enum):
    """How a sticker's identity was obtained."""

    DECODED = "decoded"  # Data Matrix symbols read and agreeing
    CHECKED = "checked"  # no symbol read; the tracker's expected ID's data modules matched (decode's check)
    ORB = "orb"  # ORB matching against tracker-chosen candidates
    APPEARANCE = "appearance"  # template correlation against tracker-chosen candidates
    NONE = "none"  # unidentified


@dataclass
class Detection:
    """A sticker's outline found in one image.

    Attributes:
        outer: (4, 2) outer-square corners, distorted pixels, in image order (clockwise on screen).
        inner: (4, 2) inner black-frame corners matching ``outer`` one for one, or None.
        score: detector confidence, 0-1.
        corner_sigma_px: the detector's own corner noise (px) when it knows it better than the pose
            solver's residual can (a method with coarse corners); None: estimate from the residual.
    """

    outer: np.ndarray
    inner: np.ndarray | None = None
    score: float = 1.0
    corner_sigma_px: float | None = None

    @property
    def points(self) -> np.ndarray:
        """All available corners (4 or 8, 2): outer then inner."""
        return self.outer if self.inner is None else np.vstack([self.outer, self.inner])


@dataclass
class PoseFix:
    """One solution of the sticker's pose.

    Attributes:
        T_world_camera: (4, 4) camera pose in the world.
        body: (3,) body (x, y, yaw) in the world through the rig.
        cov: (3, 3) covariance of ``body`` from corner noise through the reprojection Jacobian.
        reprojection_px: RMS reprojection error over the points used.
    """

    T_world_camera: np.ndarray
    body: np.ndarray
    cov: np.ndarray
    reprojection_px: float


@dataclass(frozen=True)
class SurveyPrior:
    """What the map says about how well one sticker was surveyed: the sticker's map position and the
    standard deviations of its survey error (metres per axis, radians of yaw).

    A fix inherits its sticker's survey error unchanged in every frame that sees it, so the tracker
    estimates that error as a state instead of treating it as fresh noise (see :mod:`tracker.ekf`).
    """

    sticker_xy: np.ndarray  # (2,) map position of the sticker's centre, m
    sigma_m: float
    sigma_yaw: float


@dataclass(frozen=True)
class Identity:
    """Which sticker a detection is, known by decoding or by identification among candidates.

    ``rotation`` r (0-3) means the canonical top-left corner is ``detection.outer[r]``. ``score``
    and ``margin`` are the identification's (1 and 0 for a decoded sticker).
    """

    sticker_id: int
    rotation: int
    source: IdSource
    score: float = 1.0
    margin: float = 0.0


@dataclass(frozen=True)
class Fix:
    """The pose one identified sticker gives, and what the tracker did with it.

    ``poses`` holds one solution, or two when IPPE's two solutions are close in error
    (``ambiguous``), best first; empty when the pose solver found none.
    """

    poses: list[PoseFix]
    ambiguous: bool = False
    accepted: bool | None = None  # did the tracker take this fix (None: not offered)
    gate_reason: str | None = None  # the tracker's reason, "fused", "initialised" or why it refused
    # When the poses hold, s after the frame's time (a rolling shutter's sticker rows; see
    # tagloc.vision.pose.PoseSolution.row_time_s).
    row_time_s: float = 0.0


@dataclass(frozen=True)
class Observation:
    """One sticker in one frame, built once the per-frame stages are done with it.

    The stages run detection -> identity (decoded, or identified among the tracker's candidates;
    None if neither) -> fix (only with an identity). ``rejected_read`` says why symbols that were
    read gave no identity; ``unmapped_id`` is a decoded ID that is not in the map (never a fix).
    """

    detection: Detection
    camera: int = 0
    identity: Identity | None = None
    fix: Fix | None = None
    rejected_read: str | None = None
    unmapped_id: int | None = None
    unmapped_rotation: int | None = None  # the unmapped sticker's rotation (0-3), for map audits

    @property
    def sticker_id(self) -> int | None:
        """The identity's sticker ID, else the unmapped decoded ID, else None."""
        return self.identity.sticker_id if self.identity is not None else self.unmapped_id

    @property
    def source(self) -> IdSource:
        """How the sticker was named (NONE: not named)."""
        return self.identity.source if self.identity is not None else IdSource.NONE

    @property
    def poses(self) -> list[PoseFix]:
        """The fix's pose solutions (none without a fix)."""
        return self.fix.poses if self.fix is not None else []

    @property
    def accepted(self) -> bool | None:
        """Whether the tracker took the fix (None: no fix was offered)."""
        return self.fix.accepted if self.fix is not None else None

    @property
    def gate_reason(self) -> str | None:
        """The tracker's one-line reason for taking or refusing the fix (None: no fix)."""
        return self.fix.gate_reason if self.fix is not None else None

    def to_json(self) -> dict:
        """Plain-data form for the JSON-lines log."""
        ident, fix = self.identity, self.fix
        return {
            "camera": self.camera,
            "corners": np.round(self.detection.outer, 3).tolist(),
            "sticker_id": self.sticker_id,
            "source": self.source.value,
            "rotation": ident.rotation if ident is not None else None,
            "score": round(float(ident.score), 4) if ident is not None else 0.0,
            "margin": round(float(ident.margin), 4) if ident is not None else 0.0,
            "ambiguous": fix.ambiguous if fix is not None else False,
            "poses": [
                {
                    "body": np.round(p.body, 5).tolist(),
                    "cov": np.round(p.cov, 8).tolist(),
                    "reprojection_px": round(p.reprojection_px, 4),
                }
                for p in self.poses
            ],
            "rejected_read": self.rejected_read,
            "accepted": self.accepted,
            "gate_reason": self.gate_reason,
        }


class TrackState(str, Enum):
    """Tracker life cycle."""

    INITIALISING = "initialising"  # no pose yet; only decoded fixes may start it
    TRACKING = "tracking"
    LOST = "lost"  # too uncertain to choose candidates; decoded fixes only until re-initialised


@dataclass
class TrackerOutput:
    """The pose tagloc publishes, at one instant.

    Attributes:
        t: timestamp, seconds (the frame clock).
        pose: (3,) body (x, y, yaw) in the world; meaningless while initialising (zeros).
        cov: (3, 3) covariance of ``pose``, symmetric positive definite.
        state: tracker state.
        since_fix: seconds since the last accepted fix (inf before the first).
        last_id, last_source: sticker and identification source of the last accepted fix.
    """

    t: float
    pose: np.ndarray
    cov: np.ndarray
    state: TrackState
    since_fix: float
    last_id: int | None = None
    last_source: IdSource | None = None

    def to_json(self) -> dict:
        """Plain-data form for the JSON-lines log and the sinks (SI units, yaw in rad)."""
        return {
            "t": round(self.t, 6),
            "x": round(float(self.pose[0]), 5),
            "y": round(float(self.pose[1]), 5),
            "yaw": round(float(self.pose[2]), 6),
            "cov": np.round(self.cov, 9).tolist(),
            "state": self.state.value,
            "since_fix": None if not np.isfinite(self.since_fix) else round(self.since_fix, 4),
            "last_id": self.last_id,
            "last_source": None if self.last_source is None else self.last_source.value,
        }


@dataclass
class FrameResult:
    """What the localiser made of one frame: its observations and the tracker's output after it.

    ``times_ms`` is the wall time of each stage over the whole frame (see
    :class:`tagloc.pipeline.localiser.StageTimer`), with ``total`` for the frame.
    """

    index: int
    timestamp: float
    observations: list[Observation]
    output: TrackerOutput
    times_ms: dict[str, float] = field(default_factory=dict)
    skipped: str | None = None  # why the frame was skipped (corrupt image), else None
    frame: Frame | None = None  # the frame itself, for a viewer (so it is read and decoded once)
    # Observations of earlier frames finished after those frames were published (live's deferred
    # decodes), as (frame index, observation): their fixes are fused at their own frames' times.
    late: list[tuple[int, Observation]] = field(default_factory=list)
