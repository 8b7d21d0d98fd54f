"""Frame sources for ``tagloc live`` and the capture thread that keeps only the newest frames.

Sources (:func:`open_source`):

- a camera index (``0``): ``cv2.VideoCapture(0)``;
- a stream URL (``rtsp://...``, ``http://...``; anything ``cv2.VideoCapture`` opens);
- a video file;
- a session directory: its frames at their recorded timestamps;
- ``picam`` or ``picam:N``: a Raspberry Pi camera through ``picamera2`` (optional; only where it
  is installed), stamped with the sensor's own start-of-exposure timestamp.

Camera control (:class:`CameraSettings`: exposure, gain, frame rate, resolution) is applied to a
camera index through OpenCV's capture properties (V4L2 on Linux: manual exposure in units of
100 us, the driver's own gain units) and to ``picam`` through picamera2's controls (exposure in
us, analogue gain); what the driver accepted is read back (:meth:`FrameSource.settings_report`),
because drivers round, clamp or ignore requests without an error.

Timestamps: the localiser takes a frame's time to be the middle row's exposure centre (see
:mod:`tagloc.core.rig`), and no driver stamps that instant, so a live source converts its stamps
(:func:`frame_time`, from the rig camera's read-out and the frame's exposure, given by
:meth:`FrameSource.set_timing`). When the driver gives each buffer its own timestamp (V4L2 through
``CAP_PROP_POS_MSEC``, picamera2's ``SensorTimestamp``) on the kernel's monotonic clock, that
stamp is used, moved to the epoch by the clocks' difference: it marks the start of the frame (the
first row's read-out) and carries no jitter from when Python got round to the frame. Otherwise a
frame is stamped when it is grabbed, on a monotonic clock shifted once to the epoch (so steps never
jump with NTP, yet other machines can read the time): that is after its last row was read out. A
driver whose stamps are on another clock is aligned to the first frame's grab, as a grab stamp. A
rig camera's ``stamp_offset_s`` replaces the conversion with a measured offset. A video file or a
session uses its own clock (frame number / fps, or the recorded timestamps) as frame times.

Pacing: by default a file or session is played *as if live*, at its own rate: the capture thread
runs ahead of nothing, and when processing falls behind the oldest buffered frames are dropped,
exactly as with a camera. With ``pace=False`` every frame is processed, as fast as possible: the
capture thread then waits for the consumer instead of dropping.
"""

from __future__ import annotations

import collections
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from tagloc.core.errors import BackendUnavailable, InputError
from tagloc.core.types import Frame
from tagloc.io.session import CLOCK_JUMP_S, SessionReader, after_last

#: OpenCV's V4L2 backend passes CAP_PROP_AUTO_EXPOSURE through to V4L2's exposure_auto menu: 1 = manual.
V4L2_MANUAL_EXPOSURE = 1
#: A driver stamp this much older than the monotonic clock when its frame arrives, or more, is not
#: on that clock (a frame arrives within a few frame intervals of its start).
_MAX_DRIVER_LAG_S = 1.0


@dataclass
class CapturedFrame:
    """A frame and when it was grabbed (``time.monotonic()``, s), for latency."""

    frame: Frame
    grabbed: float


@dataclass
class CaptureStats:
    """Counters of a capture thread.

    Attributes:
        grabbed: frames read from the source (good or not).
        delivered: frames handed to the consumer.
        dropped: good frames discarded because the consumer fell behind.
        skipped: corrupt or empty frames skipped.
        unprocessed: good frames still buffered when the capture was stopped (never handed over):
            with the others, every frame grabbed is accounted for.
        ended: why reading stopped ("" while running).
        failed: reading stopped because the source failed (a camera gone, an error), not at its end
            or when told to stop.
    """

    grabbed: int = 0
    delivered: int = 0
    dropped: int = 0
    skipped: int = 0
    unprocessed: int = 0
    ended: str = ""
    failed: bool = False


@dataclass(frozen=True)
class CameraSettings:
    """What ``tagloc live`` asks of a camera; None leaves the driver's value.

    Attributes:
        exposure_ms: manual exposure time, ms (turns auto exposure off).
        gain: sensor gain (picamera2: analogue gain, 1 = unity; V4L2: the driver's own units).
        fps: frame rate.
        resolution: (width, height), pixels.
    """

    exposure_ms: float | None = None
    gain: float | None = None
    fps: float | None = None
    resolution: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        if self.exposure_ms is not None and not 0 < self.exposure_ms < 10000:
            raise InputError(f"--exposure-ms {self.exposure_ms} must be between 0 and 10000 ms")
        if self.gain is not None and not self.gain >= 0:
            raise InputError(f"--gain {self.gain} must not be negative")
        if self.fps is not None and not 0 < self.fps <= 1000:
            raise InputError(f"--fps {self.fps} must be in (0, 1000]")
        if self.resolution is not None and (min(self.resolution) < 1 or len(self.resolution) != 2):
            raise InputError(f"--resolution {self.resolution} must be two positive numbers, WxH")

    @property
    def empty(self) -> bool:
        """True when nothing is requested."""
        return all(v is None for v in (self.exposure_ms, self.gain, self.fps, self.resolution))

    def to_json(self) -> dict:
        """Plain data (requested values; None: driver default)."""
        return {
            "exposure_ms": self.exposure_ms,
            "gain": self.gain,
            "fps": self.fps,
            "resolution": list(self.resolution) if self.resolution else None,
        }


def parse_resolution(text: str) -> tuple[int, int]:
    """``"1296x972"`` -> (1296, 972); InputError otherwise."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--resolution {text!r} is not WIDTHxHEIGHT such as 1296x972") from None
    if w < 1 or h < 1:
        raise InputError(f"--resolution {text!r} must be positive")
    return w, h


#: Where a source's raw stamp sits in its frame (see :func:`frame_time`).
STAMP_FRAME = "frame"  # the frame's time already (files, sessions)
STAMP_FRAME_START = "frame start"  # the first row's read-out begins (V4L2 buffers, picamera2)
STAMP_GRAB = "grab"  # the frame reached tagloc: its last row was read out before


def frame_time(
    stamp: float, stamp_at: str, readout_s: float, exposure_s: float, offset_s: float | None = None
) -> float:
    """The frame's time, the middle row's exposure centre (s), from a source's stamp (s).

    A rolling shutter reads row after row over ``readout_s``; each row is exposed for ``exposure_s``
    up to its read-out. A stamp at the frame's start marks the first row's read-out: that row was
    exposed over [stamp - E, stamp], and the middle row is read readout/2 later, so its centre is
    stamp + readout/2 - E/2. A grab stamp comes after the last row's read-out, readout/2 after the
    middle row's, so stamp - readout/2 - E/2; the transfer and queueing between (a USB camera's
    compression, a few ms to a frame) are not known here and are not counted: measure them and give
    the rig camera's ``stamp_offset_s``, which replaces the rule (stamp + offset). A global shutter
    (readout 0) reads every row at once. Unknown exposure: 0 (the time is then up to E/2 late).
    """
    if offset_s is not None:
        return stamp + offset_s
    if stamp_at == STAMP_FRAME_START:
        return stamp + 0.5 * readout_s - 0.5 * exposure_s
    if stamp_at == STAMP_GRAB:
        return stamp - 0.5 * readout_s - 0.5 * exposure_s
    return stamp


def _driver_clock(driver_s: float, now: float, epoch_offset: float) -> tuple[float, str]:
    """(seconds putting a driver's stamps on the epoch, where they sit in the frame: see
    :func:`frame_time`) from its first stamp ``driver_s`` (s), read at monotonic time ``now``, with
    ``epoch_offset`` the epoch less the monotonic clock. A stamp on the monotonic clock (younger than
    ``_MAX_DRIVER_LAG_S``) marks the frame's start and moves to the epoch as the clock does; one on
    another clock is aligned to now, as a grab stamp."""
    if 0.0 <= now - driver_s < _MAX_DRIVER_LAG_S:
        return epoch_offset, STAMP_FRAME_START
    return now + epoch_offset - driver_s, STAMP_GRAB


class FrameSource:
    """A source of greyscale frames. ``read()`` returns a frame (image None if corrupt) or None at the end."""

    live = False  # True: the source runs on its own clock (camera), so pacing is meaningless
    fps = 0.0
    end_reason = "end of source"  # set by read() before it returns None
    end_failed = False  # set by read() before it returns None when the source failed, not ended
    clock = "file"  # where timestamps come from: "file", "grab" (monotonic at read) or "driver"
    stamp_at = STAMP_FRAME  # where the raw stamps sit in the frame (see frame_time)
    readout_s = 0.0  # the rig camera's read-out and stamp offset (set_timing)
    stamp_offset_s: float | None = None
    _last_stamp = -math.inf  # the last frame time a live source gave

    def set_timing(self, readout_s: float, stamp_offset_s: float | None = None) -> None:
        """Convert this camera's stamps to frame times with its rig camera's read-out (s) and, when
        measured, its ``stamp_offset_s`` (see :func:`frame_time`); a file keeps its own clock."""
        self.readout_s = float(readout_s)
        self.stamp_offset_s = stamp_offset_s

    def _frame_time(self, stamp: float, exposure_s: float = 0.0) -> float:
        """``stamp`` as a frame time (live sources); a file's or session's stamps are frame times."""
        if not self.live:
            return stamp
        return frame_time(stamp, self.stamp_at, self.readout_s, exposure_s, self.stamp_offset_s)

    def _live_stamp(self, raw: float, exposure_s: float = 0.0) -> float:
        """A live source's ``raw`` stamp (where ``stamp_at`` says) as a frame time, in a microsecond
        after the last one it gave (:func:`~tagloc.io.session.after_last`: a switch of clocks must not
        step back). The last stamp plus a microsecond, the rule before, fell in the last stamp's
        microsecond as frames.csv and pose messages round it for one epoch stamp in 20, and the
        recording was refused on replay for a repeated time."""
        stamp = after_last(self._frame_time(raw, exposure_s), self._last_stamp)
        self._last_stamp = stamp
        return stamp

    def read(self) -> Frame | None:
        raise NotImplementedError

    def close(self) -> None:
        """Release the device or file."""

    def apply_settings(self, settings: CameraSettings) -> None:
        """Ask the camera for ``settings``; a source that cannot be controlled refuses any request."""
        if not settings.empty:
            raise InputError(f"{type(self).__name__}: camera settings apply only to a camera, not to this source")

    def settings_report(self) -> dict:
        """What the source runs at (as read back from the driver) and its timestamp clock."""
        return {"clock": self.clock, "fps": self.fps, "stamp": self.stamp_at}

    def report_after_run(self, report: dict) -> dict:
        """``report`` (:meth:`settings_report` from before the first frame) brought up to date once
        the frames came, without the driver (released by then, its properties would read 0): the
        clock and stamp the frames were given (a driver's are taken up at the first frame)."""
        return {**report, "clock": self.clock, "stamp": self.stamp_at} if report else report


def _grey(image: np.ndarray | None) -> np.ndarray | None:
    if image is None or image.size == 0:
        return None
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    return image


def _read_back(value: float | None, above: float, below: float = math.inf) -> float | None:
    """A driver's read-back ``value`` when it lies in (``above``, ``below``), else None (not reported)."""
    v = float(value or 0.0)
    return v if above < v < below else None


class VideoSource(FrameSource):
    """A camera, stream or video file read through ``cv2.VideoCapture``.

    ``max_failures`` consecutive failed reads end a live source (the camera is gone); for a file
    they mean the end (corrupt frames inside a file are skipped as they come).
    """

    def __init__(self, spec: str | int, live: bool, max_failures: int = 30):
        self.spec = spec
        self.live = live
        self._cap = cv2.VideoCapture(spec)
        if not self._cap.isOpened():
            raise InputError(f"{spec}: cannot open as a camera, stream or video file")
        fps = float(self._cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self.fps = fps if 0.0 < fps < 1000.0 else 30.0
        self.max_failures = max_failures
        self._index = 0
        self._failures = 0
        self._n_frames = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0) if not live else 0
        # Epoch time of monotonic zero, fixed once: stamps are monotonic but readable elsewhere.
        self._epoch_offset = time.time() - time.monotonic()
        self.clock = "grab" if live else "file"
        self.stamp_at = STAMP_GRAB if live else STAMP_FRAME
        self._requested: CameraSettings | None = None
        self._driver_offset = 0.0  # epoch - driver clock, fixed at the first frame
        self._last_driver = -math.inf
        self._last_grab = -math.inf  # monotonic time of the last good frame
        self._exposure_s = 0.0  # the manual exposure (s); 0: unknown (auto exposure)
        self._clock_chosen = False  # whether the first good frame has chosen the driver's or grab clock

    def apply_settings(self, settings: CameraSettings) -> None:
        """Set resolution, frame rate, manual exposure and gain through OpenCV's capture properties."""
        if settings.empty:
            return
        if not self.live:
            raise InputError(f"{self.spec}: camera settings apply only to a camera, not to a file")
        self._requested = settings
        cap = self._cap
        if settings.resolution is not None:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, settings.resolution[0])
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, settings.resolution[1])
        if settings.fps is not None:
            cap.set(cv2.CAP_PROP_FPS, settings.fps)
        if settings.exposure_ms is not None:
            # V4L2 backend: auto-exposure menu 1 = manual; exposure_time_absolute in 100 us units.
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_MANUAL_EXPOSURE)
            cap.set(cv2.CAP_PROP_EXPOSURE, settings.exposure_ms * 10.0)
            # The frames' times take the exposure the driver set (it rounds and clamps without an
            # error), the request only when it reads none back.
            got = _read_back(cap.get(cv2.CAP_PROP_EXPOSURE), 0.0)
            self._exposure_s = got * 1e-4 if got is not None else settings.exposure_ms * 1e-3
        if settings.gain is not None:
            cap.set(cv2.CAP_PROP_GAIN, settings.gain)
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        if 0.0 < fps < 1000.0:
            self.fps = fps

    def settings_report(self) -> dict:
        """Requested and read-back values (exposure in ms, assuming V4L2's 100 us units). A camera's
        value the driver does not report (OpenCV reads 0 or -1 for a property the backend lacks: a
        0 fps, a negative exposure or gain) is None, not the 30 fps assumed for pacing or a
        -0.1 ms exposure."""
        cap = self._cap
        size = [int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))]
        out = {
            "clock": self.clock,
            "fps": _read_back(cap.get(cv2.CAP_PROP_FPS), 0.0, 1000.0) if self.live else self.fps,
            "resolution": size if min(size) > 0 else None,
            "backend": cap.getBackendName() if hasattr(cap, "getBackendName") else "",
            "stamp": self.stamp_at,
        }
        if self.live:
            exposure = _read_back(cap.get(cv2.CAP_PROP_EXPOSURE), 0.0)
            out["exposure_ms"] = exposure / 10.0 if exposure is not None else None
            out["auto_exposure"] = float(cap.get(cv2.CAP_PROP_AUTO_EXPOSURE))
            gain = float(cap.get(cv2.CAP_PROP_GAIN) or 0.0)
            out["gain"] = gain if 0.0 <= gain < math.inf else None
        if self._requested is not None:
            out["requested"] = self._requested.to_json()
        return out

    def _stamp(self) -> float:
        """This frame's time: from the driver's buffer timestamp while it gives rising ones, else from
        the grab time, each converted to the frame's time (:func:`frame_time`).

        A driver clock that stops rising, or jumps (its step from the last good frame differs from the
        monotonic clock's by ``CLOCK_JUMP_S`` or more: a driver reset, a wrap), is abandoned for good
        (never mixed back in), and stamps never go backwards across the switch. Called for good frames only: a failed read leaves the
        driver's stamp at the last buffer's, which is neither a clock that stopped nor a first frame.
        """
        if not self.live:
            return self._index / self.fps
        now = time.monotonic()
        raw = now + self._epoch_offset  # the grab time
        if self.clock == "driver":
            driver_s = float(self._cap.get(cv2.CAP_PROP_POS_MSEC) or 0.0) * 1e-3
            step_s = driver_s - self._last_driver
            if step_s > 0 and abs(step_s - (now - self._last_grab)) < CLOCK_JUMP_S:
                self._last_driver = driver_s
                raw = driver_s + self._driver_offset
            else:
                why = "stopped rising" if not step_s > 0 else f"jumped {step_s:+.3g} s"
                self.clock, self.stamp_at = f"grab (driver clock {why})", STAMP_GRAB
        elif self.clock == "grab" and not self._clock_chosen:
            driver_s = float(self._cap.get(cv2.CAP_PROP_POS_MSEC) or 0.0) * 1e-3
            if driver_s > 0:  # the driver stamps its buffers: use that clock from now on
                self._last_driver, self.clock = driver_s, "driver"
                self._driver_offset, self.stamp_at = _driver_clock(driver_s, now, self._epoch_offset)
                raw = driver_s + self._driver_offset
        self._clock_chosen = True
        self._last_grab = now
        return self._live_stamp(raw, self._exposure_s)

    def _failed_stamp(self) -> float:
        """A failed read's stamp: a file's frame time; live, the last frame time given (or the grab
        time before any), without consulting or moving the clock."""
        if not self.live:
            return self._index / self.fps
        return self._last_stamp if math.isfinite(self._last_stamp) else time.monotonic() + self._epoch_offset

    def read(self) -> Frame | None:
        while True:
            ok, image = self._cap.read()
            index = self._index
            if ok and image is not None and image.size:
                stamp = self._stamp()
                self._failures = 0
                self._index += 1
                return Frame(index, stamp, _grey(image))
            # A failed read is skipped, never processed: it takes the last stamp given and leaves the
            # clock alone (one timed-out buffer had abandoned the driver's stamps for the whole run).
            stamp = self._failed_stamp()
            self._failures += 1
            at_end = not self.live and (self._n_frames <= 0 or self._index >= self._n_frames - 1)
            if at_end or self._failures >= self.max_failures:
                self.end_reason = "end of file" if at_end else f"{self.max_failures} reads failed in a row"
                # Only a live source fails: a file's failed reads end it, as the class says (one
                # cut short, its header counting frames no longer there, had exited 1).
                self.end_failed = self.live and not at_end
                return None
            self._index += 1
            return Frame(index, stamp, None, error=f"frame {index}: empty or corrupt frame from {self.spec}")

    def close(self) -> None:
        self._cap.release()


class SessionSource(FrameSource):
    """A session directory's frames, with their recorded timestamps."""

    end_reason = "end of session"

    def __init__(self, path: str | Path):
        self.session = SessionReader(path)
        self.fps = self.session.info.fps or 30.0
        self._frames = self.session.frames()

    def read(self) -> Frame | None:
        return next(self._frames, None)


class PiCamera2Source(FrameSource):
    """A Raspberry Pi camera through ``picamera2`` (optional dependency, present on Raspberry Pi OS).

    The Y plane of a YUV420 stream is the greyscale frame. Exposure (us) and analogue gain are set as
    controls with auto exposure off; the frame duration limits fix the frame rate. Each frame is
    stamped with the request's ``SensorTimestamp`` (ns on the kernel's monotonic clock: the frame's
    start as the CSI receiver saw it, per the picamera2 maintainers; libcamera's own documentation
    calls it the first row's start of exposure, an exposure earlier), moved to the epoch by the
    clocks' difference and converted to the frame's time with the frame's ``ExposureTime``
    (:func:`frame_time`).
    """

    live = True
    clock = "driver"

    def __init__(self, camera_num: int = 0, settings: CameraSettings | None = None):
        try:
            from picamera2 import Picamera2
        except ImportError as exc:
            raise BackendUnavailable("picam: the picamera2 package is not installed (Raspberry Pi OS only)") from exc
        settings = settings or CameraSettings()
        self._requested = settings
        self._cam = Picamera2(camera_num)
        size = settings.resolution or (1296, 972)
        controls: dict = {}
        if settings.exposure_ms is not None or settings.gain is not None:
            controls["AeEnable"] = False
        if settings.exposure_ms is not None:
            controls["ExposureTime"] = int(round(settings.exposure_ms * 1000.0))
        if settings.gain is not None:
            controls["AnalogueGain"] = float(settings.gain)
        if settings.fps is not None:
            period_us = int(round(1e6 / settings.fps))
            controls["FrameDurationLimits"] = (period_us, period_us)
        config = self._cam.create_video_configuration(main={"size": tuple(size), "format": "YUV420"}, controls=controls)
        self._cam.configure(config)
        self._size = tuple(config["main"]["size"]) if isinstance(config, dict) and "main" in config else size
        self._cam.start()
        self.fps = float(settings.fps or 30.0)
        self._index = 0
        self._offset: float | None = None
        self._metadata: dict = {}
        # Epoch time of monotonic zero, fixed once: grab stamps must not step with NTP (see VideoSource).
        self._epoch_offset = time.time() - time.monotonic()

    def apply_settings(self, settings: CameraSettings) -> None:
        """Settings are given at construction (picamera2 configures before starting)."""

    def read(self) -> Frame | None:
        request = self._cam.capture_request()
        try:
            yuv = request.make_array("main")
            md = request.get_metadata()
        finally:
            request.release()
        self._metadata = md
        h = self._size[1]
        image = np.ascontiguousarray(yuv[:h]) if yuv is not None and yuv.size else None
        sensor_s = float(md.get("SensorTimestamp") or 0) * 1e-9
        if sensor_s <= 0.0 or self.clock.startswith("grab"):
            # No sensor stamp: grab time from then on (never mixed back in), as for a camera whose
            # driver stamps nothing.
            self.clock, self.stamp_at = "grab (no SensorTimestamp)", STAMP_GRAB
            # Monotonic, not time.time(): an NTP step back had stamped every frame 1 us after the
            # last for as long as the step, a step ahead had jumped the track.
            raw = time.monotonic() + self._epoch_offset
        else:
            if self._offset is None:
                now = time.monotonic()
                self._offset, self.stamp_at = _driver_clock(sensor_s, now, time.time() - now)
            raw = sensor_s + self._offset
        stamp = self._live_stamp(raw, float(md.get("ExposureTime", 0) or 0) * 1e-6)
        error = None if image is not None else f"frame {self._index}: empty frame"
        frame = Frame(self._index, stamp, image, error=error)
        self._index += 1
        return frame

    def settings_report(self) -> dict:
        md = self._metadata
        out: dict = {
            "clock": self.clock,
            "fps": self.fps,
            "resolution": list(self._size),
            "backend": "picamera2",
            "stamp": self.stamp_at,
        }
        if "ExposureTime" in md:
            out["exposure_ms"] = float(md["ExposureTime"]) / 1000.0
        if "AnalogueGain" in md:
            out["gain"] = float(md["AnalogueGain"])
        if md.get("FrameDuration"):
            out["fps"] = 1e6 / float(md["FrameDuration"])
        out["requested"] = self._requested.to_json()
        return out

    def report_after_run(self, report: dict) -> dict:
        """As read back from the last frame's metadata (exposure, gain, frame rate): before the
        first frame, when the report printed at start was taken, there was none, and a recording's
        session.json had held the requested frame rate and no exposure or gain at all."""
        return {**report, **self.settings_report()} if self._metadata else super().report_after_run(report)

    def close(self) -> None:
        self._cam.stop()
        self._cam.close()


def open_source(spec: str, settings: CameraSettings | None = None) -> FrameSource:
    """Open ``spec``: a camera index, ``picam[:N]``, a session directory, a video file or a stream URL,
    and apply camera ``settings`` (a camera only)."""
    settings = settings or CameraSettings()
    if spec == "picam" or spec.startswith("picam:"):
        num = spec.partition(":")[2] or "0"
        if not (num.isascii() and num.isdigit()):
            raise InputError(f"{spec}: want picam or picam:N")
        return PiCamera2Source(int(num), settings)
    if spec.isascii() and spec.isdigit():
        src: FrameSource = VideoSource(int(spec), live=True)
    elif Path(spec).is_dir():
        src = SessionSource(Path(spec))
    elif Path(spec).is_file():
        src = VideoSource(spec, live=False)
    elif "://" in spec:
        src = VideoSource(spec, live=True)
    else:
        raise InputError(f"{spec}: no such camera index, file, session directory or stream URL")
    try:
        src.apply_settings(settings)
    except BaseException:
        src.close()
        raise
    return src


class CaptureThread:
    """Read a source in a background thread into a buffer of the newest ``buffer`` frames.

    With ``drop_oldest`` (live, or a file/session played at its own rate) a full buffer discards
    its oldest frame to make room, so processing always sees the newest frame; otherwise the reader
    waits for room and nothing is lost. A file or session is paced at its own clock when ``pace``.
    """

    def __init__(self, source: FrameSource, buffer: int = 1, pace: bool = True):
        if buffer < 1:
            raise InputError("capture buffer must hold at least 1 frame")
        self.source = source
        self.pace = pace and not source.live
        self.drop_oldest = source.live or pace
        self.stats = CaptureStats()
        self._buf: collections.deque[CapturedFrame] = collections.deque()
        # Why each corrupt frame was skipped, until the consumer takes them (bounded: a dead camera
        # at 30 fps must not fill the memory; every one is counted in stats.skipped regardless).
        self._skipped_why: collections.deque[str] = collections.deque(maxlen=1000)
        self._size = buffer
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._done = False
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="tagloc-capture", daemon=True)

    def start(self) -> CaptureThread:
        self._thread.start()
        return self

    def _run(self) -> None:
        start_wall = start_t = None
        last_t = 0.0
        try:
            while not self._stop.is_set():
                frame = self.source.read()
                if frame is None:
                    self.stats.ended = self.source.end_reason
                    self.stats.failed = self.source.end_failed
                    break
                self.stats.grabbed += 1
                if frame.image is None:
                    # Corrupt frames never reach the localiser; they are counted (and named) here.
                    self.stats.skipped += 1
                    self._skipped_why.append(frame.error or f"frame {frame.index}: unreadable")
                    continue
                if self.pace:
                    now = time.monotonic()
                    if start_wall is None or frame.timestamp - last_t > CLOCK_JUMP_S:
                        # A gap in the recording is not waited out: pacing starts afresh after it.
                        start_wall, start_t = now, frame.timestamp
                    last_t = frame.timestamp
                    delay = (frame.timestamp - start_t) - (now - start_wall)
                    if delay > 0 and self._stop.wait(delay):
                        break
                item = CapturedFrame(frame, time.monotonic())
                with self._cond:
                    if self.drop_oldest:
                        while len(self._buf) >= self._size:
                            self._buf.popleft()
                            self.stats.dropped += 1
                    else:
                        while len(self._buf) >= self._size and not self._stop.is_set():
                            self._cond.wait(0.1)
                    self._buf.append(item)
                    self._cond.notify_all()
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, which re-raises
            self.error = exc
            self.stats.ended = f"error: {exc}"
            self.stats.failed = True
        finally:
            self.stats.ended = self.stats.ended or "stopped"
            with self._cond:
                self._done = True
                self._cond.notify_all()

    def get(self, timeout: float | None = None) -> CapturedFrame | None:
        """The oldest buffered frame; None at the end of the source (or on ``timeout``, s)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while not self._buf:
                if self._done:
                    if self.error is not None:
                        raise self.error
                    return None
                wait = None if deadline is None else deadline - time.monotonic()
                if wait is not None and wait <= 0:
                    return None
                self._cond.wait(wait if wait is not None else 0.5)
            item = self._buf.popleft()
            self.stats.delivered += 1
            self._cond.notify_all()
            return item

    def take_skipped(self) -> list[str]:
        """Why each frame skipped since the last call was skipped (``"frame N: ..."``), oldest first."""
        out = []
        while self._skipped_why:
            out.append(self._skipped_why.popleft())
        return out

    def join(self, timeout: float | None = None) -> None:
        """Wait until the reader has reached the end of the source (frames may still be buffered)."""
        self._thread.join(timeout)

    def has_frame(self) -> bool:
        """Whether a frame is buffered, waiting for :meth:`get`."""
        with self._cond:
            return bool(self._buf)

    @property
    def finished(self) -> bool:
        """True once the source is exhausted and the buffer empty."""
        with self._cond:
            return self._done and not self._buf

    def stop(self) -> None:
        """Stop reading and release the source; frames still buffered are counted as unprocessed."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread.ident is not None:  # started
            self._thread.join(timeout=5.0)
        with self._cond:
            self.stats.unprocessed += len(self._buf)
            self._buf.clear()
        self.source.close()


class MultiCapture:
    """Several cameras, one capture thread each, merged into one stream in timestamp order.

    Each frame is tagged with its camera's position in ``sources`` (its rig camera) and renumbered
    in delivery order (indices unique over all cameras, as a session needs). ``get`` waits
    until every running camera has a frame buffered, or ``merge_wait_s`` has passed, then hands
    over the oldest; a frame older than one already handed over (a camera that lagged past the
    wait) would make the tracker go back in time, so it is dropped and counted as late. A frame of
    another camera stamped as the one just handed over, or within its microsecond (two video files,
    each stamping frame k at k/fps; free-running cameras a few hundred nanoseconds apart now and
    then), is not older: it goes on at the next microsecond (``STAMP_RESOLUTION_S``), since every
    stage after the merge needs its frames' times to advance, and a recording and the pose messages
    hold them to the microsecond.
    A camera whose reader raises ends the merge with that error at once, as one camera's does; one
    that fails otherwise (unplugged: its reads failing) leaves the others running, and is named once
    by :meth:`take_failed` as soon as it has.
    Presents the interface of :class:`CaptureThread` that the live loop uses.
    """

    def __init__(
        self, sources: list[FrameSource], buffer: int = 1, pace: bool = True, merge_wait_s: float | None = None
    ):
        if len(sources) < 2:
            raise InputError("MultiCapture needs at least two sources")
        self.threads = [CaptureThread(s, buffer=buffer, pace=pace) for s in sources]
        self.source = sources[0]
        self.drop_oldest = any(t.drop_oldest for t in self.threads)
        fps = max(s.fps for s in sources) or 30.0
        # Cameras: one frame period, long enough for the other camera's frame of the same instant to
        # arrive. Files and sessions always deliver their next frame: wait for it (exact order).
        live = any(s.live for s in sources)
        default_wait = 1.0 / fps if live else math.inf
        self.merge_wait_s = merge_wait_s if merge_wait_s is not None else default_wait
        self.late = [0] * len(sources)
        self._pending: list[CapturedFrame | None] = [None] * len(sources)
        self._stopped = False
        self._last_t = -math.inf  # the time of the last frame handed over (moved on, see get)
        self._last_stamp = -math.inf  # and its source stamp
        self._camera_stamp = [-math.inf] * len(sources)  # each camera's last stamp handed over
        self._next_index = 0
        self._failed_named: set[int] = set()  # cameras take_failed has named

    def start(self) -> MultiCapture:
        for t in self.threads:
            t.start()
        return self

    def _fill(self) -> None:
        for t in self.threads:
            if t.error is not None and t.finished:
                # As with one camera: a reader that raised (a driver error) is not left to the end of
                # the others, which had gone on with nothing said and exited 0.
                raise t.error
        for c, t in enumerate(self.threads):
            if self._pending[c] is None and not t.finished:
                item = t.get(timeout=0.0)
                if item is not None:
                    item.frame.camera = c
                    self._pending[c] = item

    def get(self, timeout: float | None = None) -> CapturedFrame | None:
        """The oldest frame over all cameras; None when all have ended (or on ``timeout``, s)."""
        start = time.monotonic()
        while True:
            self._fill()
            waiting = [c for c, t in enumerate(self.threads) if self._pending[c] is None and not t.finished]
            ready = [c for c in range(len(self.threads)) if self._pending[c] is not None]
            waited = time.monotonic() - start
            if ready and (not waiting or waited >= self.merge_wait_s):
                c = min(ready, key=lambda k: self._pending[k].frame.timestamp)
                item, self._pending[c] = self._pending[c], None
                stamp = item.frame.timestamp
                if stamp < self._last_stamp or stamp <= self._camera_stamp[c]:
                    self.late[c] += 1
                    continue
                if math.isfinite(stamp):  # (one that is not goes on: the localiser refuses it, named)
                    self._last_stamp = self._camera_stamp[c] = stamp
                    item.frame.timestamp = self._last_t = after_last(stamp, self._last_t)
                # One index over all cameras, in delivery order: a recording needs unique indices.
                item.frame.index = self._next_index
                self._next_index += 1
                return item
            if not ready and not waiting:
                for t in self.threads:
                    if t.error is not None:
                        raise t.error
                return None
            if timeout is not None and waited >= timeout:
                return None
            time.sleep(0.001)

    def take_skipped(self) -> list[str]:
        """Every camera's skipped frames since the last call (see :meth:`CaptureThread.take_skipped`)."""
        return [f"camera {c}: {why}" for c, t in enumerate(self.threads) for why in t.take_skipped()]

    def take_failed(self) -> list[str]:
        """Cameras whose capture has failed since the last call (``"camera C: why"``), each named once."""
        out = []
        for c, t in enumerate(self.threads):
            if t.stats.failed and c not in self._failed_named:
                self._failed_named.add(c)
                out.append(f"camera {c}: capture failed ({t.stats.ended}); going on with the others")
        return out

    def has_frame(self) -> bool:
        """Whether any camera has a frame waiting."""
        return any(p is not None for p in self._pending) or any(t.has_frame() for t in self.threads)

    @property
    def finished(self) -> bool:
        """True once every camera has ended and nothing is left to hand over."""
        return all(t.finished for t in self.threads) and all(p is None for p in self._pending)

    @property
    def stats(self) -> CaptureStats:
        """All cameras' counters summed; late frames count as dropped."""
        s = CaptureStats()
        for t, late in zip(self.threads, self.late):
            s.grabbed += t.stats.grabbed
            s.delivered += t.stats.delivered - late
            s.dropped += t.stats.dropped + late
            s.skipped += t.stats.skipped
            s.unprocessed += t.stats.unprocessed
            s.failed = s.failed or t.stats.failed
        # Taken from their cameras, waiting to be merged in time order when the capture stopped.
        held = sum(p is not None for p in self._pending) if self._stopped else 0
        s.delivered -= held
        s.unprocessed += held
        s.ended = "; ".join(f"camera {c}: {t.stats.ended or 'running'}" for c, t in enumerate(self.threads))
        return s

    def per_camera(self) -> list[dict]:
        """Each camera's counters (dropped: processing behind; late: out of time order)."""
        return [
            {"grabbed": t.stats.grabbed, "dropped": t.stats.dropped, "late": late, "skipped": t.stats.skipped}
            for t, late in zip(self.threads, self.late)
        ]

    def join(self, timeout: float | None = None) -> None:
        for t in self.threads:
            t.join(timeout)

    def stop(self) -> None:
        """Stop every camera; frames buffered or waiting to be merged are counted as unprocessed."""
        self._stopped = True
        for t in self.threads:
            t.stop()
