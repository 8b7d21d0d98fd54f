"""The one output path of ``tagloc live`` and ``tagloc replay``: frame results to every destination.

:class:`Outputs` takes each :class:`~tagloc.core.types.FrameResult` and fans it out, in this order, to
the pose sinks (stdout, files, UDP, MQTT, TUM; see :func:`tagloc.io.sinks.open_sink`), the per-frame
JSON lines log and the Rerun view; :meth:`Outputs.close` closes them all once and returns the counts.

Guarantees kept here, whatever the sink:

- No pose is published twice or stale: the result of a skipped frame (refused timestamp, wrong
  size, unreadable) is logged, never published: its output is the filter's prediction, not a
  measurement of that frame (live's capture withholds the frames it cannot decode the same way).
- Published stamps only increase, per run: after a reset source clock the localiser restarts the
  track on the new clock, and the poses published from then on are stamped on from the last one
  (the new clock plus an offset, warned once); the frame log keeps the source's own times.
- A pose older than ``max_age_s`` (from the frame's grab, live only) is never sent by a network sink
  (see :class:`tagloc.io.sinks.MqttSink`); offline replays have no age.
- A sink that cannot publish is reported on the warning stream as soon as it is noticed (after a
  grace of ``connect_grace_s`` for connecting), again every ``warn_every_s`` while it lasts, and
  once when it recovers. Every summary carries every sink's counts.

To add a destination, give :class:`Outputs` a :class:`~tagloc.io.sinks.Sink` (``add_sink``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from tagloc.core.errors import InputError, warn_stderr
from tagloc.core.rig import Rig
from tagloc.core.stickermap import StickerMap
from tagloc.core.types import Frame, FrameResult, Observation, TrackerOutput
from tagloc.io.sinks import FrameLog, PoseMessage, Sink, TumSink, check_vest_id, open_sink


@dataclass
class OutputConfig:
    """Where results go.

    Attributes:
        publish: sink descriptions (see :func:`tagloc.io.sinks.open_sink`); ``vest`` the ID in messages.
        tum: TUM trajectory file of the body; log: per-frame JSON lines log (``log_times``: with
            stage timings, which vary run to run).
        rerun_save, rerun_spawn, rerun_connect: .rrd file, new viewer, viewer URL;
            ``rerun_clock`` "duration" (session clock), "timestamp" (epoch clock of a live camera) or
            "auto" (a timestamp when the first frame's time is on the epoch: a replayed live recording).
        groundtruth: (stamps, T_world_body) for Rerun, when known.
        max_age_s: network sinks never send a pose older than this (s, from the frame's grab). 0.5 s:
            at walking speed (1.5 m/s) a pose that old is 0.75 m behind the person, more than
            the sticker spacing's worth of error a robot manager can plan around.
        drop_stale: apply ``max_age_s`` to each pose's age since its grab (False for a file played
            as fast as possible, where the grab time is not the moment the frame shows; a stalled
            link is still detected).
        warn_every_s: repeat a sink's warning this often while it lasts (s).
        connect_grace_s: a network sink may take this long to connect before it is reported (s).
        reset_step_s: after a reset source clock, the published stamps carry on from the last one by
            the last step between two published stamps; this step (s) until two have been
            published: one frame at 30 fps, the rate of tagloc's cameras.
    """

    publish: list[str] = field(default_factory=list)
    vest: str = "vest-1"
    tum: Path | None = None
    log: Path | None = None
    log_times: bool = False
    rerun_save: Path | None = None
    rerun_spawn: bool = False
    rerun_connect: str | None = None
    rerun_clock: str = "auto"
    groundtruth: tuple | None = None
    max_age_s: float = 0.5
    drop_stale: bool = True
    warn_every_s: float = 10.0
    connect_grace_s: float = 1.0
    reset_step_s: float = 1.0 / 30.0

    def __post_init__(self) -> None:
        check_vest_id(self.vest)  # refused before any frame, not first met by the monitor


@dataclass
class OutputSummary:
    """Counts of one run's outputs.

    Attributes:
        published: results handed to the sinks; skipped: results of frames the localiser skipped
            (unreadable, wrong size, refused timestamp), none of them published (``refused``, the
            same count); clock_resets: times the published stamps were carried on across a reset
            source clock.
        sinks: per sink name: its counters (``sent``, ``dropped``, and for MQTT ``confirmed``,
            ``unconfirmed``, ``stale``).
        warnings: warning lines emitted.
    """

    published: int = 0
    skipped: int = 0
    clock_resets: int = 0
    sinks: dict[str, dict[str, int]] = field(default_factory=dict)
    warnings: int = 0

    @property
    def refused(self) -> int:
        """Results not published: every skipped frame's (its output is the filter's prediction)."""
        return self.skipped

    def format(self) -> list[str]:
        """One line per sink."""
        lines = []
        for name, c in self.sinks.items():
            line = f"sink {name}: sent {c['sent']}, dropped {c['dropped']}"
            if "confirmed" in c:
                line += (
                    f" (of which stale {c['stale']}); broker confirmed {c['confirmed']}, unconfirmed "
                    f"{c['unconfirmed']} (QoS 0: lost or delivered, unknown)"
                )
            lines.append(line)
        if self.skipped:
            lines.append(f"skipped by the localiser: {self.skipped} frames (unreadable, wrong size or bad timestamp)")
        if self.refused:
            lines.append(f"not published: {self.refused} skipped frames (the filter's prediction, not a pose of them)")
        return lines


class Outputs:
    """Fan frame results out to sinks, the frame log, TUM and Rerun; close them all once."""

    def __init__(
        self,
        smap: StickerMap,
        rig: Rig,
        config: OutputConfig,
        warn: Callable[[str], None] = warn_stderr,
    ) -> None:
        self.config = config
        self._warn = warn
        self.summary = OutputSummary()
        self.sinks: list[Sink] = []
        self.log: FrameLog | None = None
        self.view = None
        self._last_t = -float("inf")
        self._offset = 0.0  # added to the source's stamps since its clock was last reset
        self._interval = config.reset_step_s  # the last step between two published stamps (s)
        self._started = time.monotonic()
        self._warned: dict[str, float] = {}  # sink name -> when its last warning went out
        self._closed = False
        try:
            if config.tum is not None:
                self.add_sink(TumSink(config.tum))
            for target in config.publish:
                self.add_sink(open_sink(target, config.vest, max_age_s=config.max_age_s))
            if config.log is not None:
                self.log = FrameLog(config.log, include_times=config.log_times)
            if config.rerun_save or config.rerun_spawn or config.rerun_connect:
                from tagloc.io.rerun_view import RerunView

                self.view = RerunView(
                    smap,
                    rig,
                    save=config.rerun_save,
                    spawn=config.rerun_spawn,
                    connect=config.rerun_connect,
                    clock=config.rerun_clock,
                    groundtruth=config.groundtruth,
                )
        except BaseException:
            self.close()
            raise

    def add_sink(self, sink: Sink) -> None:
        """Publish every later result to ``sink`` too (closed with the others)."""
        self.sinks.append(sink)

    def emit(self, result: FrameResult, frame: Frame | None = None, grabbed: float | None = None) -> float | None:
        """Publish, log and show one frame's result.

        ``frame`` (with its image) is for Rerun; ``grabbed`` is when it was grabbed
        (``time.monotonic()``, live only). Returns the grab-to-publication latency, ms (None offline).
        """
        latency = None
        if result.skipped:
            self.summary.skipped += 1
            self.warn_skipped(result.skipped)
        else:
            out = self._stamped(result.output)
            age_ms = None if grabbed is None else (time.monotonic() - grabbed) * 1e3
            msg = PoseMessage(
                self.config.vest, result.index, out, age_ms, grabbed=grabbed if self.config.drop_stale else None
            )
            for s in self.sinks:
                s.publish(msg)
            self.summary.published += 1
            latency = None if grabbed is None else (time.monotonic() - grabbed) * 1e3
        self.check()
        if self.log is not None:
            self.log.write(result)
        if self.view is not None:
            # On the published clock: after the source's clock is reset the recording carries on
            # rather than drawing the new track over the old one's times.
            self.view.log(
                frame if frame is not None else Frame(result.index, result.timestamp, None),
                result,
                result.timestamp + self._offset,
            )
        if latency is None and grabbed is not None:
            latency = (time.monotonic() - grabbed) * 1e3
        return latency

    def _stamped(self, out: TrackerOutput) -> TrackerOutput:
        """``out`` stamped for publication: the source's time plus the offset of its clock resets, so
        the stamps only increase (a receiver keyed on time, tagloc's monitor among them, would drop
        every pose after a reset as older)."""
        t = out.t + self._offset
        if t < self._last_t:
            # Not skipped, yet before the last (the filter's time never goes back, two cameras' equal
            # stamps aside): the localiser restarted on a reset clock.
            self._offset = self._last_t + self._interval - out.t
            self.summary.clock_resets += 1
            self._warn(
                f"the source's clock went back {self._last_t - t:.3f} s; published times carry on from "
                f"{self._last_t:.3f} s (offset {self._offset:+.3f} s)"
            )
            t = out.t + self._offset
        elif math.isfinite(self._last_t) and t > self._last_t:
            self._interval = t - self._last_t
        self._last_t = t
        return out if self._offset == 0.0 else dataclasses.replace(out, t=t)

    def warn_skipped(self, why: str) -> None:
        """Warn that a frame was skipped (``why``: ``"frame N: ..."``), at most once per ``warn_every_s``
        for all skipped frames together, whether the localiser or the capture skipped them."""
        self._rate_limited("#skipped frames", f"skipped {why}")

    def warn(self, text: str) -> None:
        """Warn once, now (not rate-limited: an event that happens once, such as a camera lost)."""
        self._emit_warning(text)

    def emit_late(self, index: int, t: float, observations: list[Observation]) -> None:
        """Log the observations that frame ``index``'s deferred work finished after the frame was
        published (``tagloc live``; :attr:`Localiser.late`), with the frame's time ``t`` (s), as a
        ``"late"`` line of the per-frame log, and relabel them on that frame's image in Rerun. Their
        fixes are in the filter already; the sinks see them in the next frame's pose."""
        if self.log is not None and observations:
            self.log.write_late(index, t, observations)
        if self.view is not None and observations:
            self.view.log_late(index, observations)

    def check(self, now: float | None = None) -> None:
        """Warn about sinks that cannot publish (rate-limited), and once when one recovers."""
        now = time.monotonic() if now is None else now
        if now - self._started < self.config.connect_grace_s:
            return
        for s in self.sinks:
            problem = s.status()
            last = self._warned.get(s.name)
            if problem is None:
                if last is not None:
                    del self._warned[s.name]
                    self._emit_warning(f"{s.name}: publishing again ({_counts_text(s.counts())})")
                continue
            if last is None or now - last >= self.config.warn_every_s:
                self._warned[s.name] = now
                self._emit_warning(f"{s.name}: {problem} ({_counts_text(s.counts())})")

    def _rate_limited(self, key: str, text: str) -> None:
        now = time.monotonic()
        last = self._warned.get(key)
        if last is None or now - last >= self.config.warn_every_s:
            self._warned[key] = now
            self._emit_warning(text)

    def _emit_warning(self, text: str) -> None:
        self.summary.warnings += 1
        self._warn(text)

    def close(self) -> OutputSummary:
        """Close every destination (once) and return the counts."""
        if not self._closed:
            self._closed = True
            errors = []
            for c in (*self.sinks, self.log, self.view):
                if c is None:
                    continue
                try:
                    c.close()
                except OSError as exc:  # a full disk on the last flush: report it, close the rest
                    errors.append(f"{getattr(c, 'name', type(c).__name__)}: {exc.strerror or exc}")
            self.summary.sinks = {s.name: s.counts() for s in self.sinks}
            if errors:
                raise InputError("; ".join(errors))
        return self.summary

    def __enter__(self) -> Outputs:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _counts_text(counts: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in counts.items())
