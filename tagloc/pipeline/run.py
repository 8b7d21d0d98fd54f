"""Run a localiser (or a baseline) over a whole session and collect what the evaluation needs.

Shared by ``tagloc replay``, ``tagloc eval`` and ``tagloc demo`` so that they measure the same
thing. Any :class:`tagloc.pipeline.localiser.FrameProcessor` runs: tagloc's
:class:`~tagloc.pipeline.localiser.Localiser` (the default) or one of the paper's baselines
(:mod:`tagloc.eval.baselines`, chosen by ``tagloc replay --mode`` and ``tagloc eval --modes``).
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from tagloc.core.errors import SessionError
from tagloc.core.types import FrameResult, Observation
from tagloc.io.session import CLOCK_JUMP_S, SessionReader
from tagloc.pipeline.localiser import HELD_REASON, TRACKER_STAGES, FrameProcessor, Localiser, LocaliserConfig

if TYPE_CHECKING:
    from tagloc.vision.refs import ReferenceBank


@dataclass
class RunLog:
    """Per-frame outputs of one run over a session.

    Attributes:
        stamps: (N,) frame timestamps, s.
        poses: (N, 3) (x, y, yaw) estimates; rows before the first pose are NaN-free but flagged
            by ``valid``.
        covs: (N, 3, 3) covariances.
        valid: (N,) bool, False while the localiser had no pose yet and for the frames it skipped
            (nothing is published for them).
        fixes: list of dicts, one per accepted fix (one a frame's deferred work made too, with that
            frame's index and time): frame index, time, sticker id, source, corners centre, the
            fix's body poses (x, y, yaw; one, or IPPE's two) and the tracker's reason.
        rejected: the same for each fix the tracker refused.
        counts: counters from the localiser and tracker.
        frame_ms: (N,) wall time per frame, ms; tracker_ms, odometry_ms: (N,) of which in the
            tracker (``TRACKER_STAGES``: predict, candidates, update, output) and in the floor odometry.
        skipped: frames the localiser skipped (unreadable, the wrong size, a refused time);
            first_skipped: why the first of them was, else None.
    """

    stamps: np.ndarray
    poses: np.ndarray
    covs: np.ndarray
    valid: np.ndarray
    fixes: list[dict] = field(default_factory=list)
    rejected: list[dict] = field(default_factory=list)
    counts: dict = field(default_factory=dict)
    frame_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tracker_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    odometry_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    skipped: int = 0
    first_skipped: str | None = None

    def require_frames(self, source: object) -> None:
        """Refuse a run of ``source`` (a session, named in the message) none of whose frames could be
        used: nothing was localised, and no result may be reported as if something had been."""
        if len(self.stamps) and self.skipped == len(self.stamps):
            raise SessionError(f"{source}: none of its {self.skipped} frames could be used ({self.first_skipped})")


@contextlib.contextmanager
def single_threaded() -> Iterator[None]:
    """A context in which BLAS (numpy's and scipy's linear algebra) and OpenCV run on one thread
    each, as the localiser processes its frames; the process's own settings come back after.

    Real time means one core (the vest's budget; the benchmarks measure it so), and the frame's
    work is small: the tracker's 25 x 25 state, the fits' few dozen points, images of 1296 x 972.
    OpenBLAS's threads spin while they wait, so on a busy computer they take the time the frame
    needs: with both cores of this machine kept busy by other processes, the Speed walk's frames
    cost 7.9-8.2 ms of CPU with OpenBLAS's default two threads and 5.9-6.0 with one (p99 15.2-15.8
    -> 8.7 ms), alike on a quiet machine. OpenCV's thread pool, on a quiet machine, took 8.1 ms of
    CPU a frame against 5.6-5.8 on one thread, for 0.2-0.4 ms less wall time. See the README's
    Speed section."""
    import cv2
    from threadpoolctl import threadpool_limits

    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(limits=1, user_api="blas"):
            yield
    finally:
        cv2.setNumThreads(before)


def iterate_results(
    session: SessionReader, localiser: FrameProcessor, progress: bool = False, realtime: bool = False
) -> Iterator[FrameResult]:
    """Yield the localiser's result for each frame of ``session``, in order (BLAS and OpenCV on one
    thread each meanwhile, :func:`single_threaded`)."""
    with single_threaded():
        yield from _results(session, localiser, progress, realtime)


def _results(
    session: SessionReader, localiser: FrameProcessor, progress: bool, realtime: bool
) -> Iterator[FrameResult]:
    it = session.frames()
    if progress:  # tqdm only when shown: its import is 10-20 ms of a quiet replay's start-up
        from tqdm import tqdm

        it = tqdm(it, total=len(session), unit="frame", desc="replay", leave=False)
    start_wall, start_t = None, None
    last_t = -math.inf
    for frame in it:
        if realtime:
            now = time.monotonic()
            if start_wall is None or frame.timestamp - last_t > CLOCK_JUMP_S:
                # A gap in the recording is not waited out, as live's pacing does not: a session whose
                # clock jumped an hour had the replay sleep an hour, one of 1e300 s stopped with an
                # OverflowError from time.sleep.
                start_wall, start_t = now, frame.timestamp
            last_t = frame.timestamp
            delay = (frame.timestamp - start_t) - (now - start_wall)
            if delay > 0:
                time.sleep(delay)
        yield localiser.process(frame)


def _record_fix(index: int, obs: Observation, t: float, fixes: list[dict], rejected: list[dict]) -> None:
    """Add an observation's fix, if it has one, to the run log's accepted or refused fixes; a held
    fix (live's order) is recorded with its outcome, when its frame's late observations come."""
    if not obs.poses or obs.sticker_id is None or obs.gate_reason == HELD_REASON:
        return
    rec = {
        "frame": index,
        "t": t,
        "id": obs.sticker_id,
        "source": obs.source.value,
        "centre": obs.detection.outer.mean(axis=0).tolist(),
        "bodies": [p.body.tolist() for p in obs.poses],
        "reason": obs.gate_reason,
    }
    (fixes if obs.accepted else rejected).append(rec)


def run_session(
    session: SessionReader,
    config: LocaliserConfig | None = None,
    refs: ReferenceBank | None = None,
    progress: bool = False,
    on_result: Callable[[FrameResult], None] | None = None,
    realtime: bool = False,
    localiser: FrameProcessor | None = None,
) -> RunLog:
    """Run ``localiser`` over every frame of a session.

    ``localiser`` defaults to a :class:`Localiser` on the session's map and rig with ``config`` and
    ``refs``. ``realtime`` paces frames at their timestamps; otherwise they go as fast as they can.
    """
    loc = localiser or Localiser(
        session.map, session.rig, config or LocaliserConfig(), refs=refs, map_path=session.map_path
    )
    stamps, poses, covs, valid, frame_ms, tracker_ms, odometry_ms = [], [], [], [], [], [], []
    fixes, rejected = [], []
    frame_t: dict[int, float] = {}  # frame index -> timestamp, for observations finished late
    skipped: list[str] = []
    for res in iterate_results(session, loc, progress=progress, realtime=realtime):
        frame_t[res.index] = res.timestamp
        if res.skipped is not None:
            skipped.append(res.skipped)
        out = res.output
        stamps.append(res.timestamp)
        poses.append(out.pose)
        covs.append(out.cov)
        # A skipped frame publishes nothing (the filter's prediction is no pose of it): it has none
        # here either, so scores count what a receiver got.
        valid.append(res.skipped is None and out.state.value != "initialising")
        frame_ms.append(res.times_ms.get("total", 0.0))
        tracker_ms.append(sum(res.times_ms.get(k, 0.0) for k in TRACKER_STAGES))
        odometry_ms.append(res.times_ms.get("odometry", 0.0))
        # A frame's own observations, then those of earlier frames finished since (live's order).
        for index, obs in [(res.index, o) for o in res.observations] + res.late:
            _record_fix(index, obs, frame_t.get(index, res.timestamp), fixes, rejected)
        if on_result is not None:
            on_result(res)
    finish = getattr(loc, "finish", None)
    if callable(finish):
        # The last frame's deferred work (live's order): nothing after it would run it.
        for index, obs in finish():
            _record_fix(index, obs, frame_t.get(index, math.nan), fixes, rejected)
    counts = loc.stats()
    counts["skipped_frames"] = len(session.skipped)
    return RunLog(
        np.array(stamps),
        np.array(poses, float).reshape(-1, 3),
        np.array(covs, float).reshape(-1, 3, 3),
        np.array(valid, bool),
        fixes,
        rejected,
        counts,
        np.array(frame_ms),
        np.array(tracker_ms),
        np.array(odometry_ms),
        skipped=len(skipped),
        first_skipped=skipped[0] if skipped else None,
    )
