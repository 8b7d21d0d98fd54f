"""Camera timing as a capture driver delivers it: jittered timestamps and dropped frames.

The sensor is clocked steadily: frame ``k`` is exposed around ``k / fps`` (its true time). What a
session records is what the driver hands over:

* **timestamp jitter**: each stamp is the true time plus a uniform error in +-``jitter_s`` (the
  driver stamps a frame when its end-of-frame interrupt is served, and interrupt latency on a
  loaded Linux board varies by a millisecond or two);
* **isolated drops**: each frame is lost with probability ``drop_fraction`` (the consumer was late
  and the driver's buffer queue overran: 3-5 % on a busy Pi);
* **bursts**: runs of ``burst_frames`` (3-8) consecutive frames lost, starting as a Poisson
  process of ``bursts_per_min`` (a CPU stall, thermal throttling, a USB/CSI hiccup).

Dropped frames are absent from ``frames.csv``; the remaining frames keep their sequence numbers
(the index column skips), as V4L2 sequence numbers do. Seeded: the same config and seed give the
same schedule.

Each camera of a rig runs free, on its own driver and buffer queue: its jitter, drops and bursts
are its own, drawn from the seed and the camera's number (``camera``). Camera 0 draws exactly what
a single camera does, so a one-camera session does not change with this.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tagloc.core.errors import InputError


@dataclass
class TimingConfig:
    """Camera timing (see the module docstring). Zeros: every frame, stamped at its true time.

    Attributes:
        jitter_s: half-width of the uniform timestamp error, s.
        drop_fraction: probability that a frame is lost on its own.
        bursts_per_min: rate of bursts of lost frames, per minute of session.
        burst_frames: (shortest, longest) burst, frames (uniform, inclusive).
    """

    jitter_s: float = 0.0
    drop_fraction: float = 0.0
    bursts_per_min: float = 0.0
    burst_frames: tuple[int, int] = (3, 8)

    def __post_init__(self) -> None:
        if not (self.jitter_s >= 0 and 0 <= self.drop_fraction < 1 and self.bursts_per_min >= 0):
            raise InputError("timing: jitter and burst rate must be >= 0 and the drop fraction in [0, 1)")
        lo, hi = self.burst_frames
        if not 1 <= int(lo) <= int(hi):
            raise InputError(f"timing: burst length {lo}-{hi} frames is not a range of at least 1")


#: The field conditions of issue 14: +-2 ms jitter, 4 % isolated drops, and a burst of 3-8 frames
#: about every 20 s (the issue gives the lengths, not the rate: one burst per 20 s walk).
FIELD_TIMING = TimingConfig(jitter_s=0.002, drop_fraction=0.04, bursts_per_min=3.0)


@dataclass
class FrameSchedule:
    """Which frames a session keeps, and their stamps.

    Attributes:
        index: (M,) int64 sequence numbers of the frames delivered (increasing, with gaps).
        true_t: (M,) s, when each was exposed (middle row).
        stamp: (M,) s, the driver's timestamp (true time + jitter), strictly increasing.
        dropped: number of frames lost; bursts: number of bursts.
    """

    index: np.ndarray
    true_t: np.ndarray
    stamp: np.ndarray
    dropped: int
    bursts: int


def frame_schedule(n: int, fps: float, timing: TimingConfig, seed: int, camera: int = 0) -> FrameSchedule:
    """The frames out of ``n`` at ``fps`` that rig camera ``camera``'s driver delivers under ``timing``,
    and their stamps, in the camera's own time (frame ``k`` exposed at ``k / fps``)."""
    if timing.jitter_s >= 0.5 / fps:
        # Stamps +-jitter around frames 1/fps apart could swap order: no driver does that.
        raise InputError(f"timing: jitter {timing.jitter_s * 1e3:g} ms reorders frames at {fps:g} fps")
    if camera < 0:
        raise InputError(f"timing: camera {camera} is not a rig camera's number")
    # Free-running cameras have their own drivers and queues: an independent draw per camera. Camera 0
    # keeps the single camera's seed, so one-camera sessions are what they were before.
    rng = np.random.default_rng([seed, 31] if camera == 0 else [seed, 31, camera])
    keep = np.ones(n, bool)
    if timing.drop_fraction > 0:
        keep &= rng.random(n) >= timing.drop_fraction
    bursts = 0
    if timing.bursts_per_min > 0:
        p = timing.bursts_per_min / (60.0 * fps)  # chance a burst starts at a given frame
        lo, hi = int(timing.burst_frames[0]), int(timing.burst_frames[1])
        for k in np.flatnonzero(rng.random(n) < p):
            keep[k : k + int(rng.integers(lo, hi + 1))] = False
            bursts += 1
    if n:
        keep[0] = True  # a session starts with a frame
    index = np.flatnonzero(keep).astype(np.int64)
    true_t = index / fps
    jitter = rng.uniform(-timing.jitter_s, timing.jitter_s, n)[index] if timing.jitter_s > 0 else 0.0
    stamp = true_t + jitter
    return FrameSchedule(index, true_t, np.asarray(stamp, float), int(n - keep.sum()), bursts)
