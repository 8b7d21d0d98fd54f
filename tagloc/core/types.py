"""Data passed along the per-frame path: frames, detections, fixes, observations, tracker output.

Units: metres and radians; pixels for image coordinates. Covariances are over (x, y, yaw) of the
body frame in the world unless stated.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np


@dataclass
class Frame:
    """One frame of one camera.

    Attributes:
        index: frame number in the session.
        timestamp: seconds (the session's clock, not wall time).
        image: (H, W) uint8 greyscale, or None when the frame could not be read.
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


@dataclass
class Observation:
    """Everything the per-frame stage knows about one sticker in one frame.

    ``rotation`` r (0-3) means the canonical top-left corner is ``detection.outer[r]``.
    ``poses`` holds one solution, or two when IPPE's two solutions are close in error
    (``ambiguous``), best first; it is empty until the sticker is identified.
    """

    detection: Detection
    camera: int = 0
    sticker_id: int | None = None
    source: IdSource = IdSource.NONE
    rotation: int | None = None
    score: float = 0.0
    margin: float = 0.0
    poses: list[PoseFix] = field(default_factory=list)
    ambiguous: bool = False
    times_ms: dict[str, float] = field(default_factory=dict)
    rejected_read: str | None = None
    accepted: bool | None = None  # did the tracker take this fix (None: no fix offered)
    gate_reason: str | None = None  # the tracker's reason when it refused

    def to_json(self) -> dict:
        """Plain-data form for the JSON-lines log."""
        return {
            "camera": self.camera,
            "corners": np.round(self.detection.outer, 3).tolist(),
            "sticker_id": self.sticker_id,
            "source": self.source.value,
            "rotation": self.rotation,
            "score": round(float(self.score), 4),
            "margin": round(float(self.margin), 4),
            "ambiguous": self.ambiguous,
            "poses": [
                {
                    "body": np.round(p.body, 5).tolist(),
                    "cov": np.round(p.cov, 8).tolist(),
                    "reprojection_px": round(p.reprojection_px, 4),
                }
                for p in self.poses
            ],
            "times_ms": {k: round(v, 3) for k, v in self.times_ms.items()},
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
    """What the localiser made of one frame: its observations and the tracker's output after it."""

    index: int
    timestamp: float
    observations: list[Observation]
    output: TrackerOutput
    times_ms: dict[str, float] = field(default_factory=dict)
    skipped: str | None = None  # why the frame was skipped (corrupt image), else None
