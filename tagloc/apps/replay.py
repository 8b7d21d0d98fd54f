"""``tagloc replay``: run the localiser over a recorded session, offline.

Frames go through :func:`tagloc.pipeline.run.run_session` (the same loop ``tagloc eval`` measures), as fast
as possible or at the recorded rate. Outputs: the TUM trajectory of the body (frames with a pose),
the per-frame JSON lines log, optional pose sinks and a Rerun recording, and, when the session
has ``groundtruth.tum``, the accuracy metrics. The same session replayed twice gives byte-identical
TUM and log files (stage timings, which vary, are only logged on request).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from tagloc.core.errors import InputError
from tagloc.core.types import FrameResult
from tagloc.eval.metrics import trajectory_metrics
from tagloc.io.session import CAMERA_FILE, MAP_FILE, RIG_FILE, SessionReader
from tagloc.pipeline.output import OutputConfig, Outputs, OutputSummary


@dataclass
class ReplayConfig:
    """What ``tagloc replay`` does.

    Attributes:
        session: session directory.
        out: TUM trajectory to write.
        log: per-frame JSON lines log to write; ``log_times`` adds stage timings (not reproducible).
        rerun_save: .rrd file to write; ``spawn``: stream to a new Rerun viewer.
        realtime: pace frames at their timestamps instead of as fast as possible.
        publish: pose sinks (see :func:`tagloc.io.sinks.open_sink`), ``vest`` the ID in messages.
        mode: localiser mode; detector, decoder: per-frame methods (see LocaliserConfig).
        progress: show a progress bar.
        bag: rosbag2 directory to write (poses, /tf, detections; images too with ``bag_images``).
        topic, map, rig, calibration, info_topic: when ``session`` is a bag (rosbag2 directory or ROS 1
            .bag), its image topic, the sticker map, the rig and calibration (see
            :class:`tagloc.io.rosbag.BagSession`).
        png: write the walk's floor plan (trajectory, 2-sigma ellipses, ground truth) as a PNG.
    """

    session: Path
    out: Path | None = None
    log: Path | None = None
    log_times: bool = False
    rerun_save: Path | None = None
    spawn: bool = False
    realtime: bool = False
    publish: list[str] = field(default_factory=list)
    vest: str = "replay"
    mode: str = "full"
    detector: str = "contour"
    decoder: str = "zxing"
    progress: bool = True
    bag: Path | None = None
    bag_images: bool = False
    topic: str | None = None
    map: Path | None = None
    rig: Path | None = None
    calibration: Path | None = None
    info_topic: str | None = None
    png: Path | None = None


def open_replay_source(cfg: ReplayConfig):
    """The session to replay: a session directory, or a bag's camera topic."""
    from tagloc.io.rosbag import BagSession, is_bag

    if not is_bag(cfg.session) and cfg.topic is None:
        # A session is localised with its own map.csv, rig.json and camera.yaml: one of these options
        # given with it was ignored without a word (a replay "with" a refined map ran the old one).
        given = [
            option
            for option, value in (
                ("--map", cfg.map),
                ("--rig", cfg.rig),
                ("--calibration", cfg.calibration),
                ("--info-topic", cfg.info_topic),
            )
            if value is not None
        ]
        if given:
            raise InputError(
                f"{cfg.session}: {', '.join(given)} only with a bag (--topic); a session is replayed with its own "
                f"{MAP_FILE}, {RIG_FILE} and {CAMERA_FILE}"
            )
        return SessionReader(cfg.session)
    if cfg.topic is None or cfg.map is None:
        raise InputError(f"{cfg.session}: replaying a bag needs --topic IMAGE_TOPIC and --map MAP.csv")
    return BagSession(cfg.session, cfg.topic, cfg.map, cfg.rig, cfg.calibration, cfg.info_topic)


@dataclass
class ReplayResult:
    """What a replay produced.

    Attributes:
        frames: frames processed; skipped: frames skipped (unreadable, or not the calibration's
            size); posed: frames with a pose.
        fixes: accepted fixes by identification source.
        seconds: wall time; metrics: :func:`tagloc.eval.metrics.trajectory_metrics` or None without GT.
        outputs: the output path's counts; warnings: what the session reader noticed (e.g. clock jumps).
    """

    frames: int
    skipped: int
    posed: int
    fixes: dict[str, int]
    seconds: float
    metrics: dict | None = None
    outputs: OutputSummary = field(default_factory=OutputSummary)
    warnings: list[str] = field(default_factory=list)

    def format(self) -> str:
        """Human-readable summary."""
        fps = self.frames / self.seconds if self.seconds > 0 else 0.0
        by = ", ".join(f"{k} {v}" for k, v in sorted(self.fixes.items())) or "none"
        lines = [
            f"frames: {self.frames} ({self.skipped} skipped, {self.posed} with a pose) in "
            f"{self.seconds:.1f} s ({fps:.1f} fps)",
            f"fixes: {sum(self.fixes.values())} ({by})",
            *self.warnings,
            *self.outputs.format(),
        ]
        m = self.metrics
        if m is not None:
            if m["frames"] == 0:
                lines.append("ground truth: no estimate inside its time span")
            else:
                lines.append(
                    f"error vs ground truth over {m['frames']} frames: RMSE {100 * m['rmse_m']:.1f} cm, median "
                    f"{100 * m['median_m']:.1f} cm, p95 {100 * m['p95_m']:.1f} cm, max {100 * m['max_m']:.1f} cm; "
                    f"heading RMSE {m['heading_rmse_deg']:.2f} deg; within 10 cm {100 * m['within_10cm']:.0f}%, "
                    f"25 cm {100 * m['within_25cm']:.0f}%; NEES {m['nees_mean']:.2f} (2 if consistent), "
                    f"{100 * m['beyond_999']:.1f}% of frames beyond its 99.9% point (0.1% if consistent)"
                )
        return "\n".join(lines)


def replay(cfg: ReplayConfig) -> ReplayResult:
    """Replay a session through the localiser and write what ``cfg`` asks for."""
    from tagloc.eval.baselines import make_localiser
    from tagloc.pipeline.localiser import LocaliserConfig
    from tagloc.pipeline.run import run_session

    session = open_replay_source(cfg)
    stamps = getattr(session, "timestamps", None)  # a bag source streams its stamps (all a bag can hold)
    if cfg.bag is not None and stamps is not None and len(stamps):
        from tagloc.io.rosbag import check_bag_time

        for k in (0, -1):  # the stamps increase: the first and last bound them
            check_bag_time(float(stamps[k]), f"{cfg.session}: frame {int(session.index[k])}")
    # Ground truth only serves the metrics after the run, and the Rerun view: read it when needed
    # (its quaternions pull in scipy.spatial, which a replay's start-up need not wait for).
    gt = session.groundtruth() if cfg.rerun_save or cfg.spawn else None
    fixes: dict[str, int] = {}
    outputs = Outputs(
        session.map,
        session.rig,
        OutputConfig(
            publish=list(cfg.publish),
            vest=cfg.vest,
            tum=cfg.out,
            log=cfg.log,
            log_times=cfg.log_times,
            rerun_save=cfg.rerun_save,
            rerun_spawn=cfg.spawn,
            groundtruth=gt,
        ),
    )
    try:
        bag = None
        if cfg.bag is not None:
            from tagloc.io.rosbag import BagWriter

            bag = BagWriter(cfg.bag, cfg.vest, session.rig, images=cfg.bag_images)
            outputs.add_sink(bag)

        def on_result(res: FrameResult) -> None:
            for o in res.observations:
                if o.accepted:
                    fixes[o.source.value] = fixes.get(o.source.value, 0) + 1
            outputs.emit(res, res.frame)
            if bag is not None:
                # A session's JPEG goes into the bag byte for byte; a bag source's frame is re-encoded.
                p = (
                    session.frame_path(res.index, res.frame.camera if res.frame is not None else 0)
                    if cfg.bag_images
                    else None
                )
                bag.write_frame(res.frame, res, p.read_bytes() if p is not None else None)

        t0 = time.monotonic()
        run = run_session(
            session,
            localiser=make_localiser(
                cfg.mode,
                session.map,
                session.rig,
                LocaliserConfig(detector=cfg.detector, decoder=cfg.decoder),
                map_path=session.map_path,
            ),
            progress=cfg.progress,
            on_result=on_result,
            realtime=cfg.realtime,
        )
        seconds = time.monotonic() - t0
    finally:
        summary = outputs.close()
    run.require_frames(cfg.session)
    metrics = None
    if gt is None and not (cfg.rerun_save or cfg.spawn):
        gt = session.groundtruth()
    if gt is not None:
        metrics = trajectory_metrics(run.stamps[run.valid], run.poses[run.valid], run.covs[run.valid], *gt)
    if cfg.png is not None:
        from tagloc.io.fleet_plot import plot_walk

        v = run.valid
        plot_walk(session.map, run.stamps[v], run.poses[v], run.covs[v], cfg.png, gt, title=f"{cfg.session.name}")
    notes = list(session.warnings)
    flickered = int(run.counts.get("deflickered", 0))
    if flickered:
        # Worth knowing on site: the lamps flicker (see the README's "Lamp flicker").
        notes.append(f"lamp flicker: divided out of {flickered} of {len(run.stamps)} frames")
    return ReplayResult(len(run.stamps), run.skipped, int(run.valid.sum()), fixes, seconds, metrics, summary, notes)
