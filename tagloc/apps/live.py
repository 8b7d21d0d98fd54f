"""``tagloc live``: localise from a camera (or a file played as one) and publish every pose.

The capture thread keeps only the newest frame(s) (:mod:`tagloc.io.capture`); the main loop
records the frame (``record``), runs the localiser, publishes the pose to every sink, then
logs to Rerun. Frames dropped because processing fell behind are neither processed nor recorded,
so replaying a recording reproduces the live run frame for frame.

Latency is measured from the frame's grab (monotonic clock) to the end of publication.
"""

from __future__ import annotations

import math
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tagloc.core.errors import InputError
from tagloc.io.capture import CaptureStats, CaptureThread, open_source
from tagloc.io.session import SessionInfo, SessionWriter
from tagloc.io.sinks import FrameLog, PoseMessage, Sink, open_sink


@dataclass
class LiveConfig:
    """What ``tagloc live`` runs.

    Attributes:
        source: camera index, video file, stream URL or session directory.
        config_dir: session-like directory with camera.yaml, rig.json, map.csv; or give
            ``map``/``calibration``/``rig`` files (they override the directory's).
        publish: sink descriptions (see :func:`tagloc.io.sinks.open_sink`).
        vest: operator/vest ID put in every message.
        record: directory to record the processed frames to, as a session.
        log: per-frame JSON lines log.
        rerun_spawn, rerun_connect, rerun_save: Rerun viewer to start, viewer URL, .rrd file.
        max_seconds, max_frames: stop after this much wall time / this many processed frames.
        pace: play files and sessions at their own rate (False: every frame, as fast as possible).
        buffer: frames the capture thread keeps (the oldest is dropped when full).
        mode: localiser mode (see :class:`tagloc.pipeline.localiser.LocaliserConfig`).
    """

    source: str
    config_dir: Path | None = None
    map: Path | None = None
    calibration: Path | None = None
    rig: Path | None = None
    publish: list[str] = field(default_factory=list)
    vest: str = "vest-1"
    record: Path | None = None
    log: Path | None = None
    rerun_spawn: bool = False
    rerun_connect: str | None = None
    rerun_save: Path | None = None
    max_seconds: float | None = None
    max_frames: int | None = None
    pace: bool = True
    buffer: int = 1
    mode: str = "full"


@dataclass
class LiveSummary:
    """End-of-run figures.

    Attributes:
        frames: frames processed; fixes: fixes the tracker accepted.
        capture: capture counters (grabbed, delivered, dropped, skipped).
        seconds: wall time of the run.
        latency_ms: (frames,) grab-to-publication latency of each processed frame, ms.
        sinks: per sink description: (sent, dropped).
        final_state: tracker state after the last frame.
        recorded: frames written to the recording.
    """

    frames: int
    fixes: int
    capture: CaptureStats
    seconds: float
    latency_ms: np.ndarray
    sinks: dict[str, tuple[int, int]]
    final_state: str
    recorded: int = 0

    def latency(self, q: float) -> float:
        """Latency percentile ``q`` (0-100), ms; NaN without frames."""
        return float(np.percentile(self.latency_ms, q)) if len(self.latency_ms) else math.nan

    def format(self) -> str:
        """Human-readable summary (several lines)."""
        fps = self.frames / self.seconds if self.seconds > 0 else 0.0
        c = self.capture
        lines = [
            f"frames: {self.frames} processed in {self.seconds:.1f} s ({fps:.1f} fps); grabbed {c.grabbed}, "
            f"dropped {c.dropped} (processing behind), skipped {c.skipped} (corrupt)",
            f"fixes: {self.fixes}; final state: {self.final_state}; capture ended: {c.ended or 'stopped'}",
            f"latency: median {self.latency(50):.1f} ms, p95 {self.latency(95):.1f} ms (grab to publication)",
        ]
        lines += [f"sink {name}: sent {s}, dropped {d}" for name, (s, d) in self.sinks.items()]
        if self.recorded:
            lines.append(f"recorded: {self.recorded} frames")
        return "\n".join(lines)


def run_live(cfg: LiveConfig, localiser=None, stop: threading.Event | None = None) -> LiveSummary:
    """Run the live loop until the source ends, a limit is reached, SIGINT/SIGTERM, or ``stop`` is set.

    ``localiser`` (anything with ``process(frame) -> FrameResult``, ``map`` and ``rig``) defaults to
    :class:`tagloc.pipeline.localiser.Localiser` on the configured map and rig.
    """
    if cfg.max_frames is not None and cfg.max_frames < 1:
        raise InputError(f"--max-frames must be at least 1, not {cfg.max_frames}")
    if cfg.max_seconds is not None and not cfg.max_seconds > 0:
        raise InputError(f"--max-seconds must be positive, not {cfg.max_seconds}")
    if localiser is None:
        from tagloc.eval.baselines import make_localiser
        from tagloc.pipeline.localiser import load_setup

        smap, rig = load_setup(
            map_path=cfg.map, calibration=cfg.calibration, rig_path=cfg.rig, config_dir=cfg.config_dir
        )
        map_path = cfg.map or (Path(cfg.config_dir) / "map.csv" if cfg.config_dir else None)
        localiser = make_localiser(cfg.mode, smap, rig, map_path=map_path)
    stop = stop or threading.Event()
    source = open_source(cfg.source)
    sinks: list[Sink] = []
    writer = log = view = None
    cap = CaptureThread(source, buffer=cfg.buffer, pace=cfg.pace)
    restore = _stop_on_signals(stop)
    latencies: list[float] = []
    frames = fixes = 0
    state = "initialising"
    t_start = time.monotonic()
    try:
        sinks = [open_sink(p, cfg.vest) for p in cfg.publish]
        if cfg.record is not None:
            writer = SessionWriter(
                cfg.record,
                localiser.map,
                localiser.rig,
                SessionInfo(source=f"tagloc live {cfg.source}", fps=source.fps, notes=f"vest {cfg.vest}"),
            )
        if cfg.log is not None:
            log = FrameLog(cfg.log)
        if cfg.rerun_spawn or cfg.rerun_connect or cfg.rerun_save:
            from tagloc.io.rerun_view import RerunView

            view = RerunView(
                localiser.map,
                localiser.rig,
                save=cfg.rerun_save,
                spawn=cfg.rerun_spawn,
                connect=cfg.rerun_connect,
                clock="timestamp" if source.live else "duration",
            )
        cap.start()
        t_start = time.monotonic()
        while not stop.is_set():
            if cfg.max_frames is not None and frames >= cfg.max_frames:
                break
            wait = 0.25
            if cfg.max_seconds is not None:
                wait = min(wait, cfg.max_seconds - (time.monotonic() - t_start))
                if wait <= 0:
                    break
            item = cap.get(timeout=wait)
            if item is None:
                if cap.finished:
                    break
                continue
            frame = item.frame
            if writer is not None:
                # Before processing: a crash inside the localiser must still leave this frame recorded.
                writer.write(frame.index, frame.timestamp, frame.image)
            result = localiser.process(frame)
            msg = PoseMessage(cfg.vest, frame.index, result.output, (time.monotonic() - item.grabbed) * 1e3)
            for s in sinks:
                s.publish(msg)
            latencies.append((time.monotonic() - item.grabbed) * 1e3)
            frames += 1
            fixes += sum(o.accepted is True for o in result.observations)
            state = result.output.state.value
            if log is not None:
                log.write(result)
            if view is not None:
                view.log(frame, result)
    except KeyboardInterrupt:
        pass  # a second Ctrl-C during shutdown is the user's to give
    finally:
        seconds = time.monotonic() - t_start
        cap.stop()
        restore()
        for s in sinks:
            s.close()
        for closable in (writer, log, view):
            if closable is not None:
                closable.close()
    return LiveSummary(
        frames,
        fixes,
        cap.stats,
        seconds,
        np.array(latencies),
        {s.name: (s.sent, s.dropped) for s in sinks},
        state,
        writer.count if writer else 0,
    )


def _stop_on_signals(stop: threading.Event):
    """Make SIGTERM set ``stop`` (main thread only); returns the function restoring the old handler."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    old = signal.signal(signal.SIGTERM, lambda signum, frame: stop.set())
    return lambda: signal.signal(signal.SIGTERM, old)
