"""The paper's baselines, beside the evaluation that compares them with tagloc.

Both run tagloc's detector, decoder and pose solver on the same frames, but have no tracker: the
pose is this frame's best fix (least reprojection error), else the last one held.

- ``decoded-only``: decoded fixes only.
- ``orb-all``: decoded fixes, and ORB identification of every undecoded sticker against every
  reference in the map (no prediction narrows the choice), each scored by its own match count.

:func:`make_localiser` builds tagloc's :class:`~tagloc.pipeline.localiser.Localiser` or a baseline
from a mode name, for ``tagloc replay --mode``, ``tagloc live --mode`` and ``tagloc eval --modes``.
``tagloc eval`` also has ``full-live`` (:class:`LiveOrderLocaliser`): tagloc in ``tagloc live``'s
order, where a frame's odometry step and least-squares decodes come after its pose is published.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from tagloc.core.errors import InputError
from tagloc.core.rig import Rig
from tagloc.core.stickermap import StickerMap
from tagloc.core.types import Fix, Frame, FrameResult, Identity, Observation, TrackerOutput, TrackState
from tagloc.pipeline.localiser import (
    FrameProcessor,
    Localiser,
    LocaliserConfig,
    StageTimer,
    count_read,
    new_counts,
    read_sticker,
    reference_bank,
)
from tagloc.vision.detect import detect
from tagloc.vision.image import as_gray
from tagloc.vision.pose import solve_pose

#: tagloc ("full") and the paper's baselines.
MODES = ("full", "decoded-only", "orb-all")
#: What ``tagloc eval --modes`` accepts: the modes and tagloc in live's order (:class:`LiveOrderLocaliser`).
EVAL_MODES = (*MODES, "full-live")

#: Pose reported before the first fix: none, with a covariance that says so (1000 m, pi rad).
_NO_POSE_COV = np.diag([1e6, 1e6, np.pi**2])


class BaselineLocaliser:
    """A paper baseline with the :class:`~tagloc.pipeline.localiser.Localiser`'s ``process(frame)``.

    Uses ``config.detector`` and ``config.decoder``; the tracker, odometry and identification
    settings do not apply.
    """

    def __init__(
        self,
        mode: str,
        smap: StickerMap,
        rig: Rig,
        config: LocaliserConfig | None = None,
        refs=None,
        map_path: str | Path | None = None,
    ):
        if mode not in MODES[1:]:
            raise InputError(f"unknown baseline {mode!r} (want one of {', '.join(MODES[1:])})")
        self.mode = mode
        self.map = smap
        self.rig = rig
        self.config = config or LocaliserConfig()
        self.counts = new_counts()
        self._held: TrackerOutput | None = None  # the last fix
        self._refs = refs
        self._map_path = map_path

    @property
    def refs(self):
        """The ORB reference bank (``orb-all``), built or loaded on first need."""
        if self._refs is None:
            self._refs = reference_bank(self.map, self._map_path)
        return self._refs

    def stats(self) -> dict[str, int]:
        """The counters (a baseline has no tracker)."""
        return dict(self.counts)

    def process(self, frame: Frame) -> FrameResult:
        """One frame: detect, decode (and for ``orb-all`` identify), solve poses, report the best."""
        timer = StageTimer()
        t = frame.timestamp
        self.counts["frames"] += 1
        if frame.image is None:
            self.counts["skipped"] += 1
            return FrameResult(frame.index, t, [], self._output(t), timer.finish(), frame.error or "unreadable", frame)
        gray = as_gray(frame.image)
        rig_cam = self.rig[frame.camera]
        with timer("detect"):
            detections = detect(gray, rig_cam.camera, method=self.config.detector)
        self.counts["detections"] += len(detections)
        seen = []
        for det in detections:
            with timer("decode"):
                read = read_sticker(gray, det, rig_cam.camera, self.map, self.config.decoder)
            count_read(self.counts, read)
            identity = read.identity
            if identity is None and read.unmapped_id is None and self.mode == "orb-all":
                with timer("identify"):
                    identity = self._identify_all(gray, det, rig_cam.camera)
            fix = None
            if identity is not None:
                with timer("pose"):
                    sol = solve_pose(det, identity.rotation, self.map.T_world_sticker(identity.sticker_id), rig_cam)
                fix = Fix(sol.poses, sol.ambiguous, row_time_s=sol.row_time_s)
            seen.append((det, read, identity, fix))
        best = self._best(seen)
        observations = []
        for i, (det, read, identity, fix) in enumerate(seen):
            if i == best:
                fix = dataclasses.replace(fix, accepted=True)
                p = fix.poses[0]
                self._held = TrackerOutput(
                    t, p.body.copy(), p.cov.copy(), TrackState.TRACKING, 0.0, identity.sticker_id, identity.source
                )
            observations.append(Observation(det, frame.camera, identity, fix, read.rejected, read.unmapped_id))
        return FrameResult(frame.index, t, observations, self._output(t), timer.finish(), None, frame)

    def _identify_all(self, gray: np.ndarray, det, camera) -> Identity | None:
        from tagloc.vision.identify import IdentifyConfig, identify

        cands = [int(i) for i in self.map.ids]
        # The paper's baseline scores each reference by its own match count (no cross-sticker ratio test).
        cfg = IdentifyConfig(orb_global_above=len(cands) + 1)
        res = identify(gray, det, camera, cands, self.refs, method="orb", config=cfg)
        if res.sticker_id is None:
            return None
        self.counts["identified"] += 1
        return Identity(res.sticker_id, res.rotation, res.source, res.score, res.margin)

    @staticmethod
    def _best(seen: list) -> int | None:
        """Index of the observation whose first pose has the least reprojection error (first of equals)."""
        scored = [(fix.poses[0].reprojection_px, i) for i, (_, _, _, fix) in enumerate(seen) if fix and fix.poses]
        return min(scored)[1] if scored else None

    def _output(self, t: float) -> TrackerOutput:
        """The last fix held (its age in ``since_fix``), or no pose before the first."""
        h = self._held
        if h is None:
            return TrackerOutput(t, np.zeros(3), _NO_POSE_COV.copy(), TrackState.INITIALISING, float("inf"))
        return TrackerOutput(t, h.pose, h.cov, h.state, t - (h.t - h.since_fix), h.last_id, h.last_source)


class LiveOrderLocaliser:
    """A :class:`~tagloc.pipeline.localiser.Localiser` driven in ``tagloc live``'s order, on recorded frames.

    Live publishes a frame's pose before the work its config defers (``LocaliserConfig.defer_odometry``,
    ``defer_lsq``: the frame's floor-odometry step, its least-squares decodes) and runs that work
    while it waits for the next frame (:meth:`~tagloc.pipeline.localiser.Localiser.deferred_work`).
    Here the work always gets its time (a live loop that keeps up), so the filter sees what live's
    does, in the same order, deterministically. :func:`make_localiser` ("full-live") gives it
    live's config; a replay (mode ``full``) does each frame's work inside it.
    """

    def __init__(self, localiser: Localiser):
        self.localiser = localiser
        self.map, self.rig = localiser.map, localiser.rig

    @property
    def counts(self) -> dict[str, int]:
        """The localiser's counters."""
        return self.localiser.counts

    def process(self, frame: Frame) -> FrameResult:
        """The previous frame's deferred work, then this frame (its result as live publishes it,
        with the deferred work's observations as its ``late`` ones)."""
        self.localiser.deferred_work()
        late = self.localiser.late
        return dataclasses.replace(self.localiser.process(frame), late=late)

    def finish(self) -> list[tuple[int, Observation]]:
        """The last frame's deferred work (see :meth:`~tagloc.pipeline.localiser.Localiser.finish`)."""
        return self.localiser.finish()

    def stats(self) -> dict[str, int]:
        """The localiser's counters with the tracker's (see :meth:`~tagloc.pipeline.localiser.Localiser.stats`)."""
        return self.localiser.stats()


def make_localiser(
    mode: str,
    smap: StickerMap,
    rig: Rig,
    config: LocaliserConfig | None = None,
    refs=None,
    map_path: str | Path | None = None,
) -> FrameProcessor:
    """tagloc's Localiser for ``mode`` "full" ("full-live": in live's order, see
    :class:`LiveOrderLocaliser`), else the named baseline (see :data:`EVAL_MODES`)."""
    if mode == "full":
        return Localiser(smap, rig, config, refs=refs, map_path=map_path)
    if mode == "full-live":
        # tagloc live's defaults (tagloc.apps.live.LiveConfig): both stages after the frame.
        live = dataclasses.replace(config or LocaliserConfig(), defer_lsq=True, defer_odometry=True)
        return LiveOrderLocaliser(Localiser(smap, rig, live, refs=refs, map_path=map_path))
    if mode not in MODES:
        raise InputError(f"unknown localiser mode {mode!r} (want one of {', '.join(EVAL_MODES)})")
    return BaselineLocaliser(mode, smap, rig, config, refs=refs, map_path=map_path)
