"""What recorded walks saw of the map: every sticker sighting with its geometry, for map audits and refinement.

:func:`collect_walk` runs the localiser over one session with a given map and keeps, per frame, the
tracked pose and, per detection, the identity (decoded, identified or none), the corners in the
sticker's canonical order and the sticker's pose in the camera from the pose solver (also for
decoded stickers that are not in the map: solved against the identity, so they can be placed),
and the floor odometry's step from the camera's previous frame (its own :class:`FloorOdometry`, the
same measurement the localiser fuses), which links frames for the map refinement. The localiser's
run log (:class:`tagloc.pipeline.run.RunLog`) is kept too, so one pass scores the walk as
``tagloc eval`` would.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tagloc.core.errors import CalibrationError
from tagloc.core.geometry import invert
from tagloc.core.rig import Rig
from tagloc.core.sticker import rotate_corners
from tagloc.core.stickermap import StickerMap, load_map
from tagloc.core.types import FrameResult, IdSource, Observation
from tagloc.io.session import SessionReader
from tagloc.pipeline.localiser import Localiser, LocaliserConfig
from tagloc.pipeline.run import RunLog, run_session
from tagloc.vision.image import as_gray
from tagloc.vision.odometry import FloorOdometry, OdometryConfig, OdometryStep
from tagloc.vision.pose import solve_pose


@dataclass
class Sighting:
    """One detection in one frame, as the map audit needs it.

    Attributes:
        camera: rig camera index.
        centre_px: (2,) mean of the outer corners, distorted pixels.
        sticker_id: decoded or identified ID (also for decoded IDs not in the map), else None.
        source: how the ID was obtained (``IdSource`` value).
        in_map: the ID is in the audited map.
        accepted: the tracker took its fix (None: none offered); ``gate_reason`` when refused.
        corners: (4, 2) or (8, 2) outer (then inner) corners in the sticker's canonical order,
            distorted px; None without an ID and rotation.
        T_camera_sticker: (4, 4) the sticker's pose in the camera from the pose solver, or None.
        reprojection_px: RMS reprojection error of that pose (px).
    """

    camera: int
    centre_px: np.ndarray
    sticker_id: int | None = None
    source: str = IdSource.NONE.value
    in_map: bool = False
    accepted: bool | None = None
    gate_reason: str | None = None
    corners: np.ndarray | None = None
    T_camera_sticker: np.ndarray | None = None
    reprojection_px: float = float("nan")

    @property
    def decoded(self) -> bool:
        return self.source == IdSource.DECODED.value


@dataclass
class FrameRecord:
    """One frame: the tracker's output after it and what was seen.

    Attributes:
        index, t: frame index and timestamp (s).
        pose: (3,) body (x, y, yaw) in the world after the frame; cov: (3, 3) its covariance.
        state: tracker state value ("initialising", "tracking", "lost").
        sightings: the frame's detections.
        skipped: why the frame could not be read, else None.
        camera: rig camera of the frame.
        step: floor odometry from this camera's previous frame to this one (None: no step).
    """

    index: int
    t: float
    pose: np.ndarray
    cov: np.ndarray
    state: str
    sightings: list[Sighting] = field(default_factory=list)
    skipped: str | None = None
    camera: int = 0
    step: OdometryStep | None = None


@dataclass
class WalkLog:
    """One session seen through one map: its rig, per-frame records and the localiser's run log."""

    path: Path
    rig: Rig
    frames: list[FrameRecord]
    counts: dict = field(default_factory=dict)
    log: RunLog | None = None

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def skipped(self) -> list[str]:
        """Why each frame the localiser skipped was (unreadable, the wrong size, a bad time), in order."""
        return [fr.skipped for fr in self.frames if fr.skipped]


#: What the localiser skips a frame for, as :func:`frames_text` says it.
SKIP_REASONS = "unreadable, the wrong size or a bad time"


def walks_skipped(walks: list[WalkLog]) -> tuple[int, list[str]]:
    """(frames, why each skipped one was) over ``walks``; each reason names its walk ("walk: frame N: ...")."""
    return sum(len(w.frames) for w in walks), [f"{w.name}: {why}" for w in walks for why in w.skipped]


def frames_text(frames: int, skipped: list[str], reasons: str = SKIP_REASONS) -> str:
    """How many frames there were and how many were skipped, the first one's reason included:
    "20 frames (10 skipped: unreadable, ...; the first: walk: frame 3: ...)"; "20 frames" without."""
    if not skipped:
        return f"{frames} frames"
    return f"{frames} frames ({len(skipped)} skipped: {reasons}; the first: {skipped[0]})"


def _sighting(obs: Observation, smap: StickerMap, rig: Rig) -> Sighting:
    det = obs.detection
    source = obs.source.value
    if obs.sticker_id is not None and obs.source == IdSource.NONE:
        source = IdSource.DECODED.value  # the localiser names a sticker without a source only for unmapped reads
    s = Sighting(obs.camera, det.outer.mean(axis=0), obs.sticker_id, source)
    s.accepted, s.gate_reason = obs.accepted, obs.gate_reason
    rotation = obs.identity.rotation if obs.identity is not None else obs.unmapped_rotation
    if obs.sticker_id is None or rotation is None:
        return s
    s.in_map = obs.identity is not None and obs.sticker_id in smap
    s.corners = rotate_corners(np.asarray(det.points, float), rotation)
    if s.in_map and obs.poses:
        fix = obs.poses[0]
        s.T_camera_sticker = invert(fix.T_world_camera) @ smap.T_world_sticker(obs.sticker_id)
        s.reprojection_px = fix.reprojection_px
    elif not s.in_map:
        # Solved against the sticker's own frame: the "world" pose returned is T_sticker_camera.
        sol = solve_pose(det, rotation, np.eye(4), rig[obs.camera])
        if sol.poses:
            s.T_camera_sticker = invert(sol.poses[0].T_world_camera)
            s.reprojection_px = sol.poses[0].reprojection_px
    return s


def frame_record(res: FrameResult, smap: StickerMap, rig: Rig, step: OdometryStep | None = None) -> FrameRecord:
    """The audit's record of one localiser result (``step``: the odometry into this frame)."""
    out = res.output
    return FrameRecord(
        res.index,
        res.timestamp,
        np.array(out.pose, float),
        np.array(out.cov, float),
        out.state.value,
        [_sighting(o, smap, rig) for o in res.observations],
        res.skipped,
        res.frame.camera if res.frame is not None else 0,
        step,
    )


class _Odometry:
    """Floor odometry per rig camera over a walk's frames (None where a camera sees too little floor)."""

    def __init__(self, rig: Rig, config: OdometryConfig | None):
        self.rig, self.config = rig, config or OdometryConfig()
        self.per_camera: dict[int, FloorOdometry | None] = {}

    def step(self, res: FrameResult) -> OdometryStep | None:
        frame = res.frame
        if frame is None or frame.image is None or res.skipped:
            return None
        if frame.camera not in self.per_camera:
            try:
                self.per_camera[frame.camera] = FloorOdometry(self.rig[frame.camera], self.config)
            except CalibrationError:
                self.per_camera[frame.camera] = None
        odo = self.per_camera[frame.camera]
        return odo.measure(as_gray(frame.image), res.timestamp) if odo is not None else None


def collect_walk(
    session_dir: str | Path,
    smap: StickerMap,
    config: LocaliserConfig | None = None,
    map_path: str | Path | None = None,
    progress: bool = False,
) -> WalkLog:
    """Localise session ``session_dir`` with ``smap`` (not the session's own map) and record every sighting.

    ``map_path``: the file ``smap`` came from, so the identification's reference cache is kept beside it.
    ``config`` defaults to the localiser's without the expected-ID check
    (``LocaliserConfig.check_expected``): what the map is audited and refined with are decoded
    sightings, whose identity does not come from the map's word on where a sticker is, and that
    check would name some stickers by it instead of reading them.
    """
    session = SessionReader(session_dir)
    config = config or LocaliserConfig(check_expected=False)
    loc = Localiser(smap, session.rig, config, map_path=map_path)
    odometry = _Odometry(session.rig, config.odometry_config)
    frames: list[FrameRecord] = []

    def record(res: FrameResult) -> None:
        frames.append(frame_record(res, smap, session.rig, odometry.step(res)))

    log = run_session(session, localiser=loc, progress=progress, on_result=record)
    log.require_frames(session.path)  # a walk that saw nothing must not find every sticker missing
    return WalkLog(session.path, session.rig, frames, dict(log.counts), log)


def collect_walks(
    sessions: list[str | Path],
    map_path: str | Path | None = None,
    localiser: LocaliserConfig | None = None,
    progress: bool = False,
) -> tuple[StickerMap, Path, list[WalkLog]]:
    """Load the map (default: the first session's ``map.csv``) and localise every session with it."""
    map_path = Path(map_path) if map_path is not None else Path(sessions[0]) / "map.csv"
    smap = load_map(map_path)
    walks = [collect_walk(s, smap, localiser, map_path=map_path, progress=progress) for s in sessions]
    return smap, map_path, walks
