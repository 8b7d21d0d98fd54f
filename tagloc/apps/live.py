"""``tagloc live``: localise from a camera (or a file played as one) and publish every pose.

The capture thread keeps only the newest frame(s) (:mod:`tagloc.io.capture`); the main loop
records the frame (``record``), runs the localiser, publishes the pose to every sink, then
logs to Rerun. Frames dropped because processing fell behind are neither processed nor recorded,
so replaying a recording reproduces the live run frame for frame.

Latency is measured from the frame's grab (monotonic clock) to the end of publication.
"""

from __future__ import annotations

import array
import dataclasses
import math
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tagloc.core.errors import InputError, SourceFailed, TaglocError
from tagloc.io.capture import CameraSettings, CaptureStats, CaptureThread, FrameSource, MultiCapture, open_source
from tagloc.io.session import MAP_FILE, SessionInfo, SessionWriter
from tagloc.pipeline.output import OutputConfig, Outputs, OutputSummary


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
        max_age_s: network sinks never send a pose older than this, s (see OutputConfig).
        camera_settings: exposure, gain, frame rate and resolution asked of a camera; what the
            driver accepted is printed and written into the recording's session.json.
        more_cameras: further sources, rig cameras 1, 2, ... (``source`` is camera 0): one capture
            thread each, frames merged in timestamp order for the one tracker.
        record_bag: rosbag2 directory to write (poses, /tf, detections; images too with ``bag_images``).
        defer_lsq: the "full" localiser decodes a sticker that needs the least-squares stage after
            the frame's pose is published, while no next frame waits (see
            :attr:`tagloc.pipeline.localiser.LocaliserConfig.defer_lsq`): that stage (6-11 ms)
            set the latency's tail. False: every frame does all its work before publishing.
        defer_odometry: likewise the frame's floor-odometry step (see
            :attr:`tagloc.pipeline.localiser.LocaliserConfig.defer_odometry`): the published pose
            lacks only that frame's own step.
        stride_when_behind: while a frame is already waiting when the localiser finishes one (the
            computer is not keeping up with the camera, e.g. a Pi-class core), let the floor
            odometry skip every other frame while the operator walks straight (see
            :attr:`tagloc.pipeline.localiser.Localiser.behind`): it sheds a third of the
            odometry's work at a small cost in accuracy, instead of the capture dropping whole frames.
            It also leaves the floor flow out after frames that read fixes placed (see
            ``LocaliserConfig.skip_flow_after_fix``), which sheds about half of it.
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
    max_age_s: float = 0.5
    camera_settings: CameraSettings = field(default_factory=CameraSettings)
    more_cameras: list[str] = field(default_factory=list)
    record_bag: Path | None = None
    bag_images: bool = False
    defer_lsq: bool = True
    defer_odometry: bool = True
    stride_when_behind: bool = True


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
        per_camera: with several cameras, each one's grabbed / dropped / late / skipped counts.
        outputs: the output path's counts (per-sink counters, warnings, refused stamps).
    """

    frames: int
    fixes: int
    capture: CaptureStats
    seconds: float
    latency_ms: np.ndarray
    sinks: dict[str, tuple[int, int]]
    final_state: str
    recorded: int = 0
    outputs: OutputSummary = field(default_factory=OutputSummary)
    per_camera: list[dict] = field(default_factory=list)

    def failure(self, source: str) -> TaglocError | None:
        """The error the run ends with once this summary is shown (``source`` names the camera or
        file), or None for a clean end: :class:`SourceFailed` when a camera was lost mid-run
        (unplugged: every read failing), which had ended the run with exit code 0, taken by a
        supervisor for a clean stop; :class:`InputError` when the source ended by itself before
        giving one frame (a file OpenCV opens but cannot read: its failed reads count as grabbed,
        and skipped)."""
        c = self.capture
        if c.failed:
            return SourceFailed(f"{source}: capture failed during the run ({c.ended})")
        if c.grabbed - c.skipped == 0 and "stopped" not in c.ended:
            return InputError(f"{source}: no frame could be read ({c.ended})")
        return None

    def latency(self, q: float) -> float:
        """Latency percentile ``q`` (0-100), ms; NaN without frames."""
        return float(np.percentile(self.latency_ms, q)) if len(self.latency_ms) else math.nan

    def format(self) -> str:
        """Human-readable summary (several lines)."""
        fps = self.frames / self.seconds if self.seconds > 0 else 0.0
        c = self.capture
        lines = [
            f"frames: {self.frames} processed in {self.seconds:.1f} s ({fps:.1f} fps); grabbed {c.grabbed}, "
            f"dropped {c.dropped} (processing behind), skipped {c.skipped} (corrupt)"
            + (f", {c.unprocessed} still buffered at the stop" if c.unprocessed else ""),
            f"fixes: {self.fixes}; final state: {self.final_state}; capture ended: {c.ended or 'stopped'}",
            f"latency: median {self.latency(50):.1f} ms, p95 {self.latency(95):.1f} ms (grab to publication)",
        ]
        for k, pc in enumerate(self.per_camera):
            lines.append(
                f"camera {k}: grabbed {pc['grabbed']}, dropped {pc['dropped']} (processing behind), "
                f"{pc['late']} late (out of time order), skipped {pc['skipped']}"
            )
        lines += self.outputs.format()
        if self.recorded:
            lines.append(f"recorded: {self.recorded} frames")
        return "\n".join(lines)


def run_live(
    cfg: LiveConfig, localiser=None, stop: threading.Event | None = None, source: FrameSource | None = None
) -> LiveSummary:
    """Run the live loop until the source ends, a limit is reached, SIGINT/SIGTERM, or ``stop`` is set.

    ``localiser`` (anything with ``process(frame) -> FrameResult``, ``map`` and ``rig``) defaults to
    :class:`tagloc.pipeline.localiser.Localiser` on the configured map and rig; ``source`` to
    ``open_source(cfg.source)``.
    """
    _check_limits(cfg)
    # A source handed in (tests, benchmarks) is the one camera; otherwise one per --camera, opened
    # (a session's frames.csv checked, say) before the reference bank, which can take a minute.
    sources = [source] if source is not None else None
    try:
        if localiser is None:
            from tagloc.pipeline.localiser import load_setup

            smap, rig = load_setup(
                map_path=cfg.map, calibration=cfg.calibration, rig_path=cfg.rig, config_dir=cfg.config_dir
            )
            sources = sources or _open_sources(cfg, len(rig))
            localiser = _make_localiser(cfg, smap, rig)
        sources = sources or _open_sources(cfg, len(localiser.rig))
        for s, rig_cam in zip(sources, localiser.rig.cameras):
            # A camera's stamps become frame times (the middle row's exposure centre) with its
            # read-out: see tagloc.io.capture.frame_time.
            if hasattr(s, "set_timing"):
                s.set_timing(rig_cam.readout_s, rig_cam.stamp_offset_s)
        if hasattr(localiser, "warm_up"):
            localiser.warm_up()  # set-up the first frame would pay, before the clock starts
    except BaseException:
        for s in sources or []:
            if s is not source:
                s.close()
        raise
    stop = stop or threading.Event()
    source = sources[0]
    reports = [s.settings_report() if hasattr(s, "settings_report") else {} for s in sources]
    for c, (s, rep) in enumerate(zip(sources, reports)):
        if s.live:
            print(f"tagloc live: camera {c}: {format_camera_report(rep)}", file=sys.stderr)
    camera_report = reports[0] if len(reports) == 1 else reports
    cap = (
        CaptureThread(source, buffer=cfg.buffer, pace=cfg.pace)
        if len(sources) == 1
        else MultiCapture(sources, buffer=cfg.buffer, pace=cfg.pace)
    )
    run = _LiveRun(cfg, localiser, cap, stop, sources)
    restore = _stop_on_signals(stop)
    outputs = writer = None
    try:
        outputs = Outputs(localiser.map, localiser.rig, _output_config(cfg, source.live, cap.drop_oldest))
        if cfg.record_bag is not None:
            from tagloc.io.rosbag import BagWriter

            # A sink for the poses; the loop also hands it each frame's detections (and image).
            run.bag = BagWriter(cfg.record_bag, cfg.vest, localiser.rig, images=cfg.bag_images)
            outputs.add_sink(run.bag)
        if cfg.record is not None:
            info = SessionInfo(
                source=f"tagloc live {cfg.source}",
                fps=source.fps,
                notes=f"vest {cfg.vest}",
                extra={"camera": camera_report},
            )
            writer = SessionWriter(cfg.record, localiser.map, localiser.rig, info)
        run.loop(outputs, writer)
    except KeyboardInterrupt:
        pass  # a second Ctrl-C during shutdown is the user's to give
    finally:
        run.seconds = time.monotonic() - run.t_start
        cap.stop()
        restore()
        out_summary = outputs.close() if outputs is not None else OutputSummary()
        if writer is not None:
            # The clock the frames were stamped on is known only once frames came (a driver's stamps
            # are taken up at the first, abandoned if they stop rising): the report from before the
            # first frame had recorded "grab" for a camera stamped on its driver's clock.
            # (picamera2 reads exposure and gain back from each frame: none before the first.)
            final = [
                s.report_after_run(rep) if hasattr(s, "report_after_run") else rep for s, rep in zip(sources, reports)
            ]
            writer.update_info(dataclasses.replace(info, extra={"camera": final[0] if len(final) == 1 else final}))
            writer.close()
    return LiveSummary(
        run.frames,
        run.fixes,
        cap.stats,
        run.seconds,
        np.frombuffer(run.latencies, dtype=np.float64).copy(),
        {name: (c["sent"], c["dropped"]) for name, c in out_summary.sinks.items()},
        run.state,
        writer.count if writer else 0,
        out_summary,
        cap.per_camera() if isinstance(cap, MultiCapture) else [],
    )


def _open_sources(cfg: LiveConfig, rig_cameras: int) -> list:
    """One source per ``--camera``, in rig-camera order; each is closed again if a later one fails."""
    specs = [cfg.source, *cfg.more_cameras]
    if len(specs) > rig_cameras:
        raise InputError(f"{len(specs)} cameras given but the rig has {rig_cameras} (one rig camera per --camera)")
    sources = []
    try:
        for spec in specs:
            sources.append(open_source(spec, cfg.camera_settings))
    except BaseException:
        for s in sources:
            s.close()
        raise
    return sources


def format_camera_report(report: dict) -> str:
    """One line: what the camera runs at as read back, and the requested values it differs from."""
    parts = []
    if report.get("resolution"):
        parts.append("x".join(str(v) for v in report["resolution"]))
    for key, unit in (("fps", " fps"), ("exposure_ms", " ms exposure"), ("gain", " gain")):
        if report.get(key) is not None:
            parts.append(f"{report[key]:g}{unit}")
        elif key in report:  # the driver gave no value (0 fps, a negative exposure): say so
            parts.append(f"{unit.split()[-1]} not reported")
    req = report.get("requested") or {}
    asked = [f"{k} {v}" for k, v in req.items() if v is not None]
    text = ", ".join(parts) + f" (timestamps: {report.get('clock', '?')} clock)"
    return text + (f"; requested {', '.join(asked)}" if asked else "")


def _check_limits(cfg: LiveConfig) -> None:
    if cfg.max_frames is not None and cfg.max_frames < 1:
        raise InputError(f"--max-frames must be at least 1, not {cfg.max_frames}")
    if cfg.max_seconds is not None and not (cfg.max_seconds > 0 and math.isfinite(cfg.max_seconds)):
        raise InputError(f"--max-seconds must be a positive number, not {cfg.max_seconds}")
    if not (cfg.max_age_s > 0 and math.isfinite(cfg.max_age_s)):
        raise InputError(f"--max-age must be a positive number of seconds, not {cfg.max_age_s}")
    if not 1 <= cfg.buffer <= 1000:
        raise InputError(f"--buffer must be 1 to 1000 frames, not {cfg.buffer}")


def _make_localiser(cfg: LiveConfig, smap=None, rig=None):
    """The configured localiser, its reference bank prepared, on map ``smap`` and ``rig`` when the
    caller has loaded them (else they are loaded here)."""
    from tagloc.eval.baselines import make_localiser
    from tagloc.pipeline.localiser import load_setup

    if smap is None or rig is None:
        smap, rig = load_setup(
            map_path=cfg.map, calibration=cfg.calibration, rig_path=cfg.rig, config_dir=cfg.config_dir
        )
    map_path = cfg.map or (Path(cfg.config_dir) / MAP_FILE if cfg.config_dir else None)
    refs = None
    if cfg.mode != "decoded-only":
        # Before the first frame: building a large map's bank on the first identification would stall
        # the live loop for minutes. Cached beside the map, so this is quick after the first run.
        from tagloc.vision.refs import build_refs, load_or_build_refs

        print("tagloc live: preparing the sticker reference bank (cached beside the map)", file=sys.stderr)
        refs = load_or_build_refs(map_path, progress=True) if map_path else build_refs(smap, progress=True)
    from tagloc.pipeline.localiser import LocaliserConfig

    config = LocaliserConfig(defer_lsq=cfg.defer_lsq, defer_odometry=cfg.defer_odometry) if cfg.mode == "full" else None
    return make_localiser(cfg.mode, smap, rig, config=config, refs=refs, map_path=map_path)


def _output_config(cfg: LiveConfig, live_clock: bool, real_time: bool) -> OutputConfig:
    return OutputConfig(
        publish=list(cfg.publish),
        vest=cfg.vest,
        log=cfg.log,
        rerun_save=cfg.rerun_save,
        rerun_spawn=cfg.rerun_spawn,
        rerun_connect=cfg.rerun_connect,
        rerun_clock="timestamp" if live_clock else "duration",
        max_age_s=cfg.max_age_s,
        drop_stale=real_time,
    )


class _LiveRun:
    """The loop's state: counts, latencies, the tracker state after the last frame."""

    def __init__(self, cfg: LiveConfig, localiser, cap: CaptureThread, stop: threading.Event, sources: list):
        """``sources``: the frame sources behind ``cap``, one per rig camera in order."""
        self.cfg, self.localiser, self.cap, self.stop, self.sources = cfg, localiser, cap, stop, sources
        # 8 bytes a frame (a list of floats took 32: 28 MB over an 8-hour shift at 30 fps).
        self.latencies = array.array("d")
        self.frames = self.fixes = 0
        self.state = "initialising"
        self.t_start = time.monotonic()
        self.seconds = 0.0
        self.bag = None  # a tagloc.io.rosbag.BagWriter when recording a bag
        # Each camera's timestamp clock as last seen (see :meth:`_clock_changes`).
        self._clocks: list[str | None] = [getattr(s, "clock", None) for s in sources]

    def _clock_changes(self) -> list[str]:
        """A line for each camera whose timestamps left the driver's clock since the last call (a
        driver clock that stopped or jumped is abandoned for grab time, which carries the capture's
        latency jitter): said when it happens, not only in ``session.json``."""
        out = []
        for k, src in enumerate(self.sources):
            clock = getattr(src, "clock", None)
            if clock != self._clocks[k] and self._clocks[k] == "driver" and str(clock).startswith("grab"):
                name = f"camera {k}: " if len(self._clocks) > 1 else ""
                out.append(f"{name}timestamps now from grab time, not the driver's: {clock}")
            self._clocks[k] = clock
        return out

    def _wait(self) -> float | None:
        """How long to wait for the next frame (s), or None when a limit is reached."""
        cfg = self.cfg
        if self.stop.is_set() or (cfg.max_frames is not None and self.frames >= cfg.max_frames):
            return None
        wait = 0.25
        if cfg.max_seconds is not None:
            wait = min(wait, cfg.max_seconds - (time.monotonic() - self.t_start))
            if wait <= 0:
                return None
        return wait

    def _no_frame_waiting(self) -> bool:
        has_frame = getattr(self.cap, "has_frame", None)
        return has_frame is None or not has_frame()

    def loop(self, outputs: Outputs, writer: SessionWriter | None) -> None:
        """Process frames until the source ends, a limit is reached or ``stop`` is set (BLAS and
        OpenCV on one thread each meanwhile, :func:`tagloc.pipeline.run.single_threaded`)."""
        from tagloc.pipeline.run import single_threaded

        with single_threaded():
            self._loop(outputs, writer)

    def _loop(self, outputs: Outputs, writer: SessionWriter | None) -> None:
        self.cap.start()
        self.t_start = time.monotonic()
        while (wait := self._wait()) is not None:
            item = self.cap.get(timeout=wait)
            for why in self.cap.take_skipped():
                outputs.warn_skipped(why)  # named as replay names its unreadable frames
            for why in getattr(self.cap, "take_failed", list)():
                outputs.warn(why)  # a rig camera lost: said when it happens, not in the summary only
            for why in self._clock_changes():
                outputs.warn(why)
            if item is None:
                if self.cap.finished:
                    break
                outputs.check()  # no frames: still tell the user about a sink that cannot publish
                continue
            frame = item.frame
            if writer is not None:
                # Before processing: a crash inside the localiser must still leave this frame recorded.
                writer.write(frame.index, frame.timestamp, frame.image, frame.camera)
            result = self.localiser.process(frame)
            self.latencies.append(outputs.emit(result, frame, grabbed=item.grabbed))
            self.fixes += sum(o.accepted is True for o in result.observations)
            deferred = getattr(self.localiser, "deferred_work", None)
            late: list = []
            if deferred is not None:
                # Published: the work the frame put off runs now, while no next frame is waiting
                # (its fixes count with the run's, though its frame went out without them).
                counts = getattr(self.localiser, "counts", {})
                late_fixes = ("deferred_fixes", "held_fixes")  # (a deferred decode's, a held fix's)
                before = sum(counts.get(k, 0) for k in late_fixes)
                deferred(self._no_frame_waiting)
                self.fixes += sum(counts.get(k, 0) for k in late_fixes) - before
                # (all of this frame's: deferred work only finishes the frame just published)
                late = [obs for index, obs in getattr(self.localiser, "late", []) if index == frame.index]
                outputs.emit_late(frame.index, frame.timestamp, late)
            if self.cfg.stride_when_behind and hasattr(self.localiser, "behind"):
                self.localiser.behind = not self._no_frame_waiting()
            self.frames += 1
            self.state = result.output.state.value
            if self.bag is not None:
                self.bag.write_frame(frame, result, late=late)


def _stop_on_signals(stop: threading.Event):
    """Make SIGTERM set ``stop`` (main thread only); returns the function restoring the old handler."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    old = signal.signal(signal.SIGTERM, lambda signum, frame: stop.set())
    return lambda: signal.signal(signal.SIGTERM, old)
