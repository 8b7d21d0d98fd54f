"""Frame sources for ``tagloc live`` and the capture thread that keeps only the newest frames.

Sources (:func:`open_source`):

- a camera index (``0``): ``cv2.VideoCapture(0)``;
- a stream URL (``rtsp://...``, ``http://...``; anything ``cv2.VideoCapture`` opens);
- a video file;
- a session directory: its frames at their recorded timestamps.

Timestamps: a live camera or stream is stamped at grab time with a monotonic clock shifted once to
the epoch (so steps never jump with NTP, yet other machines can read the time). A video file or a
session uses its own clock (frame number / fps, or the recorded timestamps).

Pacing: by default a file or session is played *as if live*, at its own rate: the capture thread
runs ahead of nothing, and when processing falls behind the oldest buffered frames are dropped,
exactly as with a camera. With ``pace=False`` every frame is processed, as fast as possible: the
capture thread then waits for the consumer instead of dropping.
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from tagloc.core.errors import InputError
from tagloc.core.types import Frame
from tagloc.io.session import CLOCK_JUMP_S, SessionReader


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
        ended: why reading stopped ("" while running).
    """

    grabbed: int = 0
    delivered: int = 0
    dropped: int = 0
    skipped: int = 0
    ended: str = ""


class FrameSource:
    """A source of greyscale frames. ``read()`` returns a frame (image None if corrupt) or None at the end."""

    live = False  # True: the source runs on its own clock (camera), so pacing is meaningless
    fps = 0.0
    end_reason = "end of source"  # set by read() before it returns None

    def read(self) -> Frame | None:
        raise NotImplementedError

    def close(self) -> None:
        """Release the device or file."""


def _grey(image: np.ndarray | None) -> np.ndarray | None:
    if image is None or image.size == 0:
        return None
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    return image


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

    def read(self) -> Frame | None:
        while True:
            ok, image = self._cap.read()
            stamp = time.monotonic() + self._epoch_offset if self.live else self._index / self.fps
            index = self._index
            if ok and image is not None and image.size:
                self._failures = 0
                self._index += 1
                return Frame(index, stamp, _grey(image))
            self._failures += 1
            at_end = not self.live and (self._n_frames <= 0 or self._index >= self._n_frames - 1)
            if at_end or self._failures >= self.max_failures:
                self.end_reason = "end of file" if at_end else f"{self.max_failures} reads failed in a row"
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


def open_source(spec: str) -> FrameSource:
    """Open ``spec``: a camera index, a session directory, a video file or a stream URL."""
    if spec.isdigit():
        return VideoSource(int(spec), live=True)
    p = Path(spec)
    if p.is_dir():
        return SessionSource(p)
    if p.is_file():
        return VideoSource(str(p), live=False)
    if "://" in spec:
        return VideoSource(spec, live=True)
    raise InputError(f"{spec}: no such camera index, file, session directory or stream URL")


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
                    break
                self.stats.grabbed += 1
                if frame.image is None:
                    # Corrupt frames never reach the localiser; they are counted here.
                    self.stats.skipped += 1
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

    def join(self, timeout: float | None = None) -> None:
        """Wait until the reader has reached the end of the source (frames may still be buffered)."""
        self._thread.join(timeout)

    @property
    def finished(self) -> bool:
        """True once the source is exhausted and the buffer empty."""
        with self._cond:
            return self._done and not self._buf

    def stop(self) -> None:
        """Stop reading and release the source."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread.ident is not None:  # started
            self._thread.join(timeout=5.0)
        self.source.close()
