"""Camera control in tagloc live: V4L2 properties through OpenCV, the picamera2 backend, driver timestamps."""

from __future__ import annotations

import json
import sys
import types

import cv2
import numpy as np
import pytest
from conftest_io import make_session

from tagloc.apps.live import LiveConfig, format_camera_report, run_live
from tagloc.core.errors import BackendUnavailable, InputError
from tagloc.core.types import Frame, FrameResult, IdSource, TrackerOutput, TrackState
from tagloc.io import capture
from tagloc.io.capture import CameraSettings, open_source, parse_resolution
from tagloc.io.session import SessionReader

W, H = 64, 48


class FakeV4L2:
    """cv2.VideoCapture of a V4L2 camera: clamps exposure to 5-10000 (100 us units), rounds the
    frame rate to what the sensor mode offers, and stamps buffers 33.3 ms apart (plus jitter) on
    its own clock."""

    instances: list = []

    def __init__(self, spec):
        self.props = {
            cv2.CAP_PROP_FPS: 30.0,
            cv2.CAP_PROP_FRAME_WIDTH: 640.0,
            cv2.CAP_PROP_FRAME_HEIGHT: 480.0,
            cv2.CAP_PROP_EXPOSURE: 156.0,
            cv2.CAP_PROP_AUTO_EXPOSURE: 3.0,
            cv2.CAP_PROP_GAIN: 0.0,
            cv2.CAP_PROP_POS_MSEC: 0.0,
        }
        self.calls = []
        self.n = 0
        self.stall_after = None
        self.released = False
        FakeV4L2.instances.append(self)

    def isOpened(self):  # noqa: N802 - OpenCV's name
        return True

    def set(self, prop, value):
        self.calls.append((prop, value))
        if prop == cv2.CAP_PROP_EXPOSURE:
            value = float(np.clip(round(value), 5, 10000))
        if prop == cv2.CAP_PROP_FPS:
            value = 30.0 if value > 20 else 15.0
        self.props[prop] = float(value)
        return True

    def get(self, prop):
        return self.props.get(prop, 0.0)

    def getBackendName(self):  # noqa: N802
        return "V4L2"

    def read(self):
        self.n += 1
        stalled = self.stall_after is not None and self.n > self.stall_after
        if not stalled:
            self.props[cv2.CAP_PROP_POS_MSEC] = 5e6 + self.n * 33.3 + (0.4 if self.n % 2 else -0.4)
        w, h = int(self.props[cv2.CAP_PROP_FRAME_WIDTH]), int(self.props[cv2.CAP_PROP_FRAME_HEIGHT])
        return True, np.full((h, w, 3), self.n % 256, np.uint8)

    def release(self):
        self.released = True


@pytest.fixture
def v4l2(monkeypatch):
    FakeV4L2.instances = []
    monkeypatch.setattr(capture.cv2, "VideoCapture", FakeV4L2)
    return FakeV4L2


def test_v4l2_settings_applied_and_read_back(v4l2):
    src = open_source("0", CameraSettings(exposure_ms=2.04, gain=12, fps=25, resolution=(W, H)))
    cap = v4l2.instances[0]
    calls = dict(cap.calls)
    assert calls[cv2.CAP_PROP_AUTO_EXPOSURE] == capture.V4L2_MANUAL_EXPOSURE
    assert calls[cv2.CAP_PROP_EXPOSURE] == pytest.approx(20.4)  # V4L2 units of 100 us
    assert calls[cv2.CAP_PROP_GAIN] == 12 and calls[cv2.CAP_PROP_FRAME_WIDTH] == W
    rep = src.settings_report()
    # What the driver accepted, not what was asked: exposure rounded to 2.0 ms, 30 fps instead of 25.
    assert rep["exposure_ms"] == pytest.approx(2.0) and rep["fps"] == 30.0 and src.fps == 30.0
    assert rep["gain"] == 12 and rep["resolution"] == [W, H] and rep["requested"]["fps"] == 25
    assert "requested" in format_camera_report(rep) and "2 ms exposure" in format_camera_report(rep)
    src.close()


def test_driver_timestamps_and_a_clock_that_stops(v4l2):
    src = open_source("0")
    cap = v4l2.instances[0]
    cap.stall_after = 6
    frames = [src.read() for _ in range(10)]
    t = np.array([f.timestamp for f in frames])
    driver = 5e6 + np.arange(1, 7) * 33.3 + np.where(np.arange(1, 7) % 2, 0.4, -0.4)
    # While the driver clock rises, the stamps are exactly its intervals (its jitter, not Python's).
    assert np.diff(t[:6]) == pytest.approx(np.diff(driver) * 1e-3, abs=1e-6)
    assert abs(t[0] - __import__("time").time()) < 5.0  # on the epoch
    assert src.clock.startswith("grab") and np.all(np.diff(t) > 0)  # abandoned, never backwards
    assert frames[0].image.shape == (480, 640)
    src.close()


def test_settings_refused_for_files_and_sessions(tmp_path, v4l2):
    sess = make_session(tmp_path / "s", 3, 10.0)
    with pytest.raises(InputError, match="camera settings"):
        open_source(str(sess), CameraSettings(exposure_ms=2.0))
    with pytest.raises(InputError, match="exposure"):
        CameraSettings(exposure_ms=0.0)
    assert parse_resolution("1296x972") == (1296, 972)
    with pytest.raises(InputError, match="WIDTHxHEIGHT"):
        parse_resolution("1296")


class FakeRequest:
    def __init__(self, cam, n):
        self.cam, self.n = cam, n

    def make_array(self, name):
        assert name == "main"
        w, h = self.cam.config["main"]["size"]
        yuv = np.zeros((h * 3 // 2, w), np.uint8)
        yuv[:h] = self.n % 256  # the Y plane (a live run grabs hundreds ahead of its frames)
        yuv[h:] = 128
        return yuv

    def get_metadata(self):
        c = self.cam.controls
        return {
            "SensorTimestamp": 10**12 + self.n * 33_333_000 + (500_000 if self.n == 3 else 0),
            "ExposureTime": int(round(c.get("ExposureTime", 10000) / 10) * 10),  # the sensor's line time
            "AnalogueGain": min(c.get("AnalogueGain", 1.0), 16.0),
            "FrameDuration": c.get("FrameDurationLimits", (33333, 33333))[0],
        }

    def release(self):
        self.cam.released += 1


class FakePicamera2:
    last = None

    def __init__(self, camera_num=0):
        self.num, self.n, self.released, self.state = camera_num, 0, 0, "open"
        FakePicamera2.last = self

    def create_video_configuration(self, main, controls):
        return {"main": dict(main), "controls": dict(controls)}

    def configure(self, config):
        self.config, self.controls = config, config["controls"]

    def start(self):
        self.state = "started"

    def capture_request(self):
        self.n += 1
        return FakeRequest(self, self.n)

    def stop(self):
        self.state = "stopped"

    def close(self):
        self.state = "closed"


def test_picamera2_backend_with_a_fake_module(monkeypatch):
    monkeypatch.setitem(sys.modules, "picamera2", types.SimpleNamespace(Picamera2=FakePicamera2))
    src = open_source("picam:1", CameraSettings(exposure_ms=2.004, gain=20.0, fps=30.0, resolution=(W, H)))
    cam = FakePicamera2.last
    assert cam.num == 1 and cam.state == "started"
    assert cam.controls == {
        "AeEnable": False,
        "ExposureTime": 2004,
        "AnalogueGain": 20.0,
        "FrameDurationLimits": (33333, 33333),
    }
    assert cam.config["main"] == {"size": (W, H), "format": "YUV420"}
    frames = [src.read() for _ in range(4)]
    assert all(f.image.shape == (H, W) for f in frames) and [int(f.image[0, 0]) for f in frames] == [1, 2, 3, 4]
    assert cam.released == 4
    # Sensor timestamps: their intervals exactly, jitter included.
    assert np.diff([f.timestamp for f in frames]) == pytest.approx([0.033333, 0.033833, 0.032833], abs=1e-6)
    rep = src.settings_report()
    assert rep["exposure_ms"] == pytest.approx(2.0) and rep["gain"] == 16.0  # what the sensor did
    assert rep["fps"] == pytest.approx(1e6 / 33333) and rep["clock"] == "driver"
    src.close()
    assert cam.state == "closed"


def test_picamera2_missing_is_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "picamera2", None)  # import raises ImportError
    with pytest.raises(BackendUnavailable, match="picamera2"):
        open_source("picam")
    with pytest.raises(InputError, match="picam:N"):
        open_source("picam:x")


class Echo:
    def __init__(self, session):
        r = SessionReader(session)
        self.map, self.rig = r.map, r.rig

    def process(self, frame: Frame) -> FrameResult:
        out = TrackerOutput(frame.timestamp, np.zeros(3), np.eye(3), TrackState.TRACKING, 0.0, 1, IdSource.DECODED)
        return FrameResult(frame.index, frame.timestamp, [], out, {"total": 1.0})


def test_live_records_the_camera_settings_and_driver_stamps(tmp_path, v4l2, capsys):
    sess = make_session(tmp_path / "s", 3, 10.0)
    cfg = LiveConfig(source="0", record=tmp_path / "rec", max_frames=5, camera_settings=CameraSettings(exposure_ms=3.0))
    summary = run_live(cfg, localiser=Echo(sess))
    assert summary.frames >= 1
    assert "3 ms exposure" in capsys.readouterr().err
    info = json.loads((tmp_path / "rec" / "session.json").read_text())
    assert info["camera"]["exposure_ms"] == pytest.approx(3.0) and info["camera"]["requested"]["exposure_ms"] == 3.0
    rec = SessionReader(tmp_path / "rec")
    assert np.all(np.diff(rec.timestamps) > 0.03)  # the driver's 33 ms intervals, not grab times


class Stamped(capture.FrameSource):
    """A file-like source with given timestamps (one grey level per frame)."""

    def __init__(self, stamps, level0=0):
        self.stamps, self.k, self.level0 = list(stamps), 0, level0
        self.fps = 10.0

    def read(self):
        if self.k >= len(self.stamps):
            return None
        f = Frame(self.k, self.stamps[self.k], np.full((H, W), self.level0 + self.k, np.uint8))
        self.k += 1
        return f


def test_multi_capture_merges_cameras_in_time_order():
    front = Stamped([0.0, 0.1, 0.2, 0.3])
    rear = Stamped([0.05, 0.15, 0.1, 0.35], level0=100)  # its third frame is out of order: late
    cap = capture.MultiCapture([front, rear], buffer=8, pace=False).start()
    got = []
    while (item := cap.get(timeout=5.0)) is not None:
        got.append(item.frame)
    t = [f.timestamp for f in got]
    assert t == [0.0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.35] and [f.index for f in got] == list(range(7))
    assert [f.camera for f in got] == [0, 1, 0, 1, 0, 0, 1]
    assert cap.late == [0, 1] and cap.stats.dropped == 1 and cap.stats.grabbed == 8 and cap.finished
    assert cap.per_camera()[1]["late"] == 1
    cap.stop()


def test_multi_capture_keeps_frames_stamped_as_the_other_cameras():
    # Two video files each stamp frame k at k/fps: every rear frame had the front frame's stamp and
    # was dropped as late (a review: `tagloc live --camera front.avi --camera rear.avi` ran on the
    # front camera alone, 90 of 90 rear frames late). A camera's own repeated stamp is still late.
    front = Stamped([0.0, 0.1, 0.2])
    rear = Stamped([0.0, 0.1, 0.1, 0.2], level0=100)
    cap = capture.MultiCapture([front, rear], buffer=8, pace=False).start()
    got = []
    while (item := cap.get(timeout=5.0)) is not None:
        got.append(item.frame)
    assert [f.camera for f in got] == [0, 1, 0, 1, 0, 1]
    t = [f.timestamp for f in got]
    assert np.all(np.diff(t) > 0) and t == pytest.approx([0.0, 1e-6, 0.1, 0.1 + 1e-6, 0.2, 0.2 + 1e-6], abs=1e-9)
    assert cap.late == [0, 1]
    cap.stop()


def test_a_two_camera_recording_with_stamps_within_a_microsecond_replays(tmp_path, monkeypatch):
    # Two free-running cameras now and then stamp frames within the same microsecond, the
    # resolution of frames.csv and of a pose message's "t": the recording held two equal stamps
    # and was refused whole on replay (a review), and two poses went out with the same "t".
    from tagloc.apps import live
    from tagloc.eval.multicam import front_rear_rig

    loc = Echo(make_session(tmp_path / "a", 2, 10.0))
    loc.rig = front_rear_rig()
    sources = [Stamped([1e9 + 1e-7, 1e9 + 0.1]), Stamped([1e9 + 3e-7, 1e9 + 0.15], level0=100)]
    monkeypatch.setattr(live, "_open_sources", lambda cfg, n: sources)
    out = tmp_path / "poses.jsonl"
    cfg = LiveConfig(source="0", more_cameras=["1"], record=tmp_path / "rec", publish=[str(out)], pace=False)
    assert run_live(cfg, localiser=loc).frames == 4
    rec = SessionReader(tmp_path / "rec")
    assert list(rec.cameras) == [0, 1, 0, 1] and np.all(np.diff(rec.timestamps) > 0)
    t = [json.loads(line)["t"] for line in out.read_text().splitlines()]
    assert len(t) == 4 and all(b > a for a, b in zip(t, t[1:]))


def test_multi_capture_moves_a_frame_on_at_epoch_times_as_frames_csv_rounds_them():
    # At epoch times a float is 2.4e-7 s fine: counted as round(t / 1e-6), a frame 0.3 us after the
    # last (1700000000.7048373 after .704837) was taken as the next microsecond and went on unmoved,
    # into the same microsecond of frames.csv and of a pose message's "t" (a review).
    front = Stamped([1700000000.704837, 1700000000.8])
    rear = Stamped([1700000000.7048373, 1700000000.9], level0=100)
    cap = capture.MultiCapture([front, rear], buffer=8, pace=False).start()
    got = []
    while (item := cap.get(timeout=5.0)) is not None:
        got.append(item.frame)
    assert [f.camera for f in got] == [0, 1, 0, 1]
    held = [f"{f.timestamp:.6f}" for f in got]
    assert held[:2] == ["1700000000.704837", "1700000000.704838"]
    assert all(float(b) > float(a) for a, b in zip(held, held[1:]))
    assert all(round(b.timestamp, 6) > round(a.timestamp, 6) for a, b in zip(got, got[1:]))
    cap.stop()


def test_multi_capture_names_each_cameras_skipped_frames():
    class Blank(Stamped):
        def read(self):
            f = super().read()
            if f is not None and f.index == 1:
                f.image, f.error = None, "frame 1: empty frame"
            return f

    cap = capture.MultiCapture([Stamped([0.0, 0.1]), Blank([0.05, 0.15])], buffer=8, pace=False).start()
    while cap.get(timeout=5.0) is not None:
        pass
    assert cap.take_skipped() == ["camera 1: frame 1: empty frame"] and cap.stats.skipped == 1
    cap.stop()


def test_live_with_two_cameras_records_both(tmp_path):
    from tagloc.eval.multicam import front_rear_rig

    a = make_session(tmp_path / "a", 6, 10.0)
    b = make_session(tmp_path / "b", 6, 7.0)  # its own clock: frames between the other camera's
    loc = Echo(a)
    loc.rig = front_rear_rig()
    cfg = LiveConfig(source=str(a), more_cameras=[str(b)], record=tmp_path / "rec", pace=False, buffer=16)
    summary = run_live(cfg, localiser=loc)
    assert len(summary.per_camera) == 2 and summary.per_camera[1]["grabbed"] == 6
    # 12 frames: the second camera's first, stamped as the first camera's, goes on 1 us after it.
    assert summary.frames == 12 and summary.per_camera[1]["late"] == 0
    assert "camera 1: grabbed 6" in summary.format()
    rec = SessionReader(tmp_path / "rec")
    assert set(rec.cameras) == {0, 1} and np.all(np.diff(rec.timestamps) > 0)
    with pytest.raises(InputError, match="rig has 2"):
        run_live(LiveConfig(source=str(a), more_cameras=[str(b), str(b)]), localiser=loc)


def test_frame_time_puts_each_stamp_at_the_middle_rows_exposure_centre():
    """30 ms read-out, 4 ms exposure: the middle row's exposure centre is 15 - 2 = 13 ms after the
    frame's start (the first row's read-out) and 15 + 2 = 17 ms before its grab (the last row's)."""
    ft = capture.frame_time
    assert ft(10.0, capture.STAMP_FRAME_START, 0.030, 0.004) == pytest.approx(10.013)
    assert ft(10.0, capture.STAMP_GRAB, 0.030, 0.004) == pytest.approx(9.983)
    assert ft(10.0, capture.STAMP_FRAME, 0.030, 0.004) == 10.0  # a file's stamps are frame times
    assert ft(10.0, capture.STAMP_GRAB, 0.030, 0.004, offset_s=-0.040) == pytest.approx(9.960)  # measured
    assert ft(10.0, capture.STAMP_FRAME_START, 0.0, 0.0) == 10.0  # global shutter, exposure unknown


def test_driver_stamps_on_the_monotonic_clock_are_frame_starts(monkeypatch, v4l2):
    """A V4L2 buffer stamp on the monotonic clock (the kernel's) is the frame's start: it is moved to
    the epoch by the clocks' difference, not aligned to the first grab, and converted with the
    rig camera's read-out and the requested exposure."""
    import time as _time

    mono0 = _time.monotonic()

    def read(self):
        self.n += 1
        self.props[cv2.CAP_PROP_POS_MSEC] = (mono0 - 0.050 + self.n / 30) * 1e3  # 50 ms before "now"
        return True, np.full((480, 640, 3), self.n % 256, np.uint8)

    monkeypatch.setattr(FakeV4L2, "read", read)
    src = open_source("0", CameraSettings(exposure_ms=4.0))
    src.set_timing(0.030)
    epoch = _time.time() - _time.monotonic()
    frames = [src.read() for _ in range(3)]
    assert src.clock == "driver" and src.stamp_at == capture.STAMP_FRAME_START
    for k, f in enumerate(frames, start=1):
        assert f.timestamp == pytest.approx(mono0 - 0.050 + k / 30 + epoch + 0.015 - 0.002, abs=2e-3)
    src.close()


def test_picamera2_sensor_timestamps_become_frame_times(monkeypatch):
    """picamera2's SensorTimestamp (the frame's start, on the monotonic clock) plus half the read-out
    minus half the frame's own ExposureTime."""
    import time as _time

    def get_metadata(self):
        return {"SensorTimestamp": int((_time.monotonic() - 0.040) * 1e9), "ExposureTime": 6000}

    monkeypatch.setitem(sys.modules, "picamera2", types.SimpleNamespace(Picamera2=FakePicamera2))
    monkeypatch.setattr(FakeRequest, "get_metadata", get_metadata)
    src = open_source("picam")
    src.set_timing(0.024)
    before = _time.time()
    f = src.read()
    after = _time.time()
    assert src.stamp_at == capture.STAMP_FRAME_START
    # 40 ms before the read, then + 12 ms (half the read-out) - 3 ms (half the exposure): bounded by
    # the times before and after the read, however long a loaded machine makes it.
    assert before - 0.031 - 1e-4 <= f.timestamp <= after - 0.031 + 1e-4
    src.close()


def test_live_gives_each_camera_its_rig_cameras_read_out_and_offset(tmp_path, v4l2):
    """``tagloc live`` hands each source its rig camera's read-out and measured stamp offset."""
    import dataclasses

    sess = make_session(tmp_path / "s", 3, 10.0)
    loc = Echo(sess)
    loc.rig.cameras[0] = dataclasses.replace(loc.rig.cameras[0], readout_s=0.025, stamp_offset_s=-0.031)
    src = open_source("0")
    run_live(LiveConfig(source="0", max_frames=2), localiser=loc, source=src)
    assert (src.readout_s, src.stamp_offset_s) == (0.025, -0.031)


def test_picamera2_without_sensor_timestamps_falls_back_to_grab_time(monkeypatch):
    """A request without ``SensorTimestamp`` is stamped when grabbed (as a grab stamp), not at one
    time plus microsecond steps; the source says so in its clock."""
    import time as _time

    def get_metadata(self):
        return {"ExposureTime": 4000}

    monkeypatch.setitem(sys.modules, "picamera2", types.SimpleNamespace(Picamera2=FakePicamera2))
    monkeypatch.setattr(FakeRequest, "get_metadata", get_metadata)
    src = open_source("picam")
    src.set_timing(0.020)
    frames = []
    for _ in range(3):
        before = _time.time()
        f = src.read()
        frames.append((before, f, _time.time()))
        _time.sleep(0.02)
    assert src.clock.startswith("grab") and src.stamp_at == capture.STAMP_GRAB
    # Grab time - 10 ms (half the read-out) - 2 ms (half the exposure); the grab lies within the
    # read, however long a loaded machine makes it (a fixed tolerance on the delay failed under load).
    for before, f, after in frames:
        assert before - 0.012 - 1e-4 <= f.timestamp <= after - 0.012 + 1e-4
    assert np.diff([f.timestamp for _, f, _ in frames]).min() > 0.015
    src.close()


@pytest.mark.parametrize("fail_at", [1, 3])
def test_a_failed_read_keeps_the_driver_clock(monkeypatch, v4l2, fail_at):
    """A read that fails (a timed-out or corrupt buffer) leaves the driver's stamp at the last buffer's:
    it is skipped, and the driver's stamps go on (a review: one failed read, the first or a later one,
    put the camera on grab time, jitter and transfer delay included, for the whole run)."""
    import time as _time

    def read(self):
        self.n += 1
        if self.n == fail_at:
            return False, None
        self.props[cv2.CAP_PROP_POS_MSEC] = (_time.monotonic() - 0.040) * 1e3
        return True, np.full((480, 640, 3), self.n % 256, np.uint8)

    monkeypatch.setattr(FakeV4L2, "read", read)
    src = open_source("0")
    src.set_timing(0.030)
    frames = [src.read() for _ in range(6)]
    assert [f.image is None for f in frames] == [k + 1 == fail_at for k in range(6)]
    assert src.clock == "driver" and src.stamp_at == capture.STAMP_FRAME_START
    good = [f.timestamp for f in frames if f.image is not None]
    assert np.all(np.diff(good) > 0)
    src.close()


class Failing(capture.FrameSource):
    """A live camera at 100 fps that, after ``good`` frames, raises (``raises``) or fails its reads."""

    live = True

    def __init__(self, good: int, raises: bool = False):
        self.n, self.good, self.raises, self.fps = 0, good, raises, 100.0

    def read(self):
        import time as _time

        _time.sleep(0.01)
        self.n += 1
        if self.n > self.good:
            if self.raises:
                raise RuntimeError("VIDIOC_DQBUF: No such device")
            self.end_reason, self.end_failed = "30 reads failed in a row", True
            return None
        return Frame(self.n, _time.time(), np.full((H, W), self.n % 256, np.uint8))


def test_multi_capture_raises_a_cameras_error_at_once():
    """A camera whose driver raises ends the merge with its error, as one camera's does (a review: the
    other camera went on alone, nothing said, until the run ended with exit code 0)."""
    cap = capture.MultiCapture([Failing(10**6), Failing(5, raises=True)]).start()
    with pytest.raises(RuntimeError, match="No such device"):
        for _ in range(500):
            cap.get(timeout=0.25)
    cap.stop()


def test_live_names_a_rig_camera_lost_mid_run_when_it_happens(tmp_path, monkeypatch, capsys):
    from tagloc.apps import live
    from tagloc.eval.multicam import front_rear_rig

    loc = Echo(make_session(tmp_path / "a", 2, 10.0))
    loc.rig = front_rear_rig()
    monkeypatch.setattr(live, "_open_sources", lambda cfg, n: [Failing(10**6), Failing(5)])
    lost_at = []
    process = loc.process

    def watch(frame):
        if not lost_at and "camera 1: capture failed" in capsys.readouterr().err:
            lost_at.append(frame.index)
        return process(frame)

    loc.process = watch
    summary = run_live(LiveConfig(source="0", more_cameras=["1"], max_frames=60), localiser=loc)
    assert lost_at and summary.frames == 60  # said during the run, which goes on with camera 0
    assert summary.capture.failed and summary.per_camera[1]["grabbed"] == 5


def test_picamera2_grab_stamps_do_not_step_with_the_wall_clock(monkeypatch):
    """Without ``SensorTimestamp`` frames are stamped on the monotonic clock shifted once to the epoch,
    as a camera index's are (a review: on time.time(), an NTP step back of 5 s stamped every frame
    1 us after the last for those 5 s)."""
    import time as _time

    monkeypatch.setitem(sys.modules, "picamera2", types.SimpleNamespace(Picamera2=FakePicamera2))
    monkeypatch.setattr(FakeRequest, "get_metadata", lambda self: {"ExposureTime": 4000})
    src = open_source("picam")
    real, step = _time.time, [0.0]
    monkeypatch.setattr(capture.time, "time", lambda: real() + step[0])
    t = []
    for k in range(5):
        step[0] = -5.0 if k >= 2 else 0.0  # NTP steps the wall clock back
        t.append(src.read().timestamp)
        _time.sleep(0.02)
    assert np.diff(t).min() > 0.015
    src.close()


def test_a_recording_names_the_clock_its_frames_were_stamped_on(tmp_path, monkeypatch, v4l2):
    """session.json's camera clock is the one the frames used: a driver's stamps are taken up at the
    first frame, after the report printed at start (a review: recorded "grab" for driver stamps)."""
    import time as _time

    def read(self):
        self.n += 1
        self.props[cv2.CAP_PROP_POS_MSEC] = (_time.monotonic() - 0.040) * 1e3
        return True, np.full((480, 640, 3), self.n % 256, np.uint8)

    monkeypatch.setattr(FakeV4L2, "read", read)
    sess = make_session(tmp_path / "s", 3, 10.0)
    run_live(LiveConfig(source="0", record=tmp_path / "rec", max_frames=3), localiser=Echo(sess))
    cam = json.loads((tmp_path / "rec" / "session.json").read_text())["camera"]
    assert (cam["clock"], cam["stamp"]) == ("driver", capture.STAMP_FRAME_START)
    assert cam["resolution"] == [640, 480]  # read back at start, while the camera was open


def test_a_video_file_shorter_than_its_header_says_ends_without_failing(tmp_path):
    """A video file cut short (its header counting frames no longer there) ends at its last frame as
    a file does: its failed reads past the end are not a camera lost mid-run (exit 1)."""
    path = tmp_path / "cut.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (160, 120))
    rng = np.random.default_rng(0)
    for _ in range(100):
        writer.write(rng.integers(0, 255, (120, 160, 3), dtype=np.uint8))
    writer.release()
    with path.open("r+b") as f:
        f.truncate(path.stat().st_size // 2)
    src = open_source(str(path))
    t = capture.CaptureThread(src, buffer=1000, pace=False).start()
    t.join(30.0)
    t.stop()
    good = t.stats.grabbed - t.stats.skipped
    assert 0 < good and src._n_frames - good > src.max_failures, t.stats  # the header overstates the frames
    assert not t.stats.failed, t.stats


def test_a_live_stamp_held_back_by_the_last_one_lands_in_a_later_microsecond(tmp_path):
    """A live source's frame time that is not after its last (a driver clock abandoned for grab
    time, which runs behind it) goes on after the last. As the last plus a microsecond it fell, for
    one epoch stamp in 20, within the last's microsecond as frames.csv writes it: the recording was
    refused on replay ("frame 2: timestamp ... is not after the previous frame's")."""
    from tagloc.core.rig import default_rig
    from tagloc.core.stickermap import StickerMap
    from tagloc.io.session import SessionInfo, SessionWriter

    class Held(capture.FrameSource):
        live = True

        def read(self) -> Frame:
            return Frame(0, self._live_stamp(1800000000.0737195), None)

    src = Held()
    stamps = [src.read().timestamp for _ in range(30)]
    assert all(f"{a:.6f}" < f"{b:.6f}" for a, b in zip(stamps, stamps[1:]))
    smap = StickerMap(np.array([7]), np.zeros((1, 2)), np.zeros(1))
    writer = SessionWriter(tmp_path / "rec", smap, default_rig(), SessionInfo(source="test", fps=30.0))
    for k, t in enumerate(stamps):
        writer.write(k, t, np.full((972, 1296), k, np.uint8))
    writer.close()
    assert np.all(np.diff(SessionReader(tmp_path / "rec").timestamps) > 0)


def test_a_driver_clock_that_jumps_is_abandoned(monkeypatch, v4l2):
    """A driver clock that jumps ahead (a driver reset, a wrap) is left for grab time, as one that
    stops rising is (a review: a jump of 1000 s stamped every later frame 1000 s in the future)."""
    import time as _time

    def read(self):
        self.n += 1
        self.props[cv2.CAP_PROP_POS_MSEC] = 5e6 + self.n * 33.3 + (1e6 if self.n >= 5 else 0.0)
        return True, np.full((480, 640, 3), self.n % 256, np.uint8)

    monkeypatch.setattr(FakeV4L2, "read", read)
    src = open_source("0")
    frames = [src.read() for _ in range(8)]
    t = np.array([f.timestamp for f in frames])
    assert src.clock.startswith("grab (driver clock jumped") and src.stamp_at == capture.STAMP_GRAB
    assert np.all(np.diff(t) > 0) and np.diff(t).max() < 1.0
    assert abs(t[-1] - _time.time()) < 5.0
    src.close()


def test_a_picam_recording_holds_what_the_sensor_did(tmp_path, monkeypatch):
    """picamera2 reads exposure, gain and frame duration back from each frame's metadata, and there
    is none before the first frame, when the report is taken (a review: session.json held the
    requested 25 fps and no exposure or gain; the sensor ran 2.0 ms, gain 16, 30 fps)."""
    monkeypatch.setitem(sys.modules, "picamera2", types.SimpleNamespace(Picamera2=FakePicamera2))
    get_metadata = FakeRequest.get_metadata
    monkeypatch.setattr(FakeRequest, "get_metadata", lambda self: {**get_metadata(self), "FrameDuration": 33333})
    sess = make_session(tmp_path / "s", 3, 10.0)
    settings = CameraSettings(exposure_ms=2.004, gain=20.0, fps=25.0, resolution=(W, H))
    run_live(LiveConfig(source="picam", record=tmp_path / "rec", max_frames=3, camera_settings=settings), Echo(sess))
    cam = json.loads((tmp_path / "rec" / "session.json").read_text())["camera"]
    assert cam["exposure_ms"] == pytest.approx(2.0) and cam["gain"] == 16.0
    assert cam["fps"] == pytest.approx(30.0, abs=0.01) and cam["requested"]["fps"] == 25.0
    assert cam["resolution"] == [W, H] and cam["clock"] == "driver"


def test_values_a_driver_does_not_report_are_named_so_not_made_up(tmp_path, monkeypatch, v4l2, capsys):
    """OpenCV reads 0 or -1 for a property the backend lacks. A camera reporting 0 fps was printed
    and recorded at the 30 fps assumed for pacing, an exposure of -1 as -0.1 ms, a gain of -1 as -1
    (a review); they are now said to be not reported, and recorded as null."""

    def set_nothing(self, prop, value):
        self.calls.append((prop, value))
        return False  # a driver that ignores every request

    monkeypatch.setattr(FakeV4L2, "set", set_nothing)
    sess = make_session(tmp_path / "s", 3, 10.0)
    src = open_source("0", CameraSettings(exposure_ms=2.0, gain=4.0))
    cap = v4l2.instances[0]
    cap.props.update({cv2.CAP_PROP_FPS: 0.0, cv2.CAP_PROP_EXPOSURE: -1.0, cv2.CAP_PROP_GAIN: -1.0})
    run_live(LiveConfig(source="0", record=tmp_path / "rec", max_frames=2), localiser=Echo(sess), source=src)
    line = capsys.readouterr().err.splitlines()[0]
    assert "fps not reported, exposure not reported, gain not reported" in line and "requested" in line
    cam = json.loads((tmp_path / "rec" / "session.json").read_text())["camera"]
    assert cam["fps"] is None and cam["exposure_ms"] is None and cam["gain"] is None
    assert cam["requested"]["exposure_ms"] == 2.0 and cam["resolution"] == [640, 480]


def test_frame_times_take_the_exposure_the_driver_set(monkeypatch, v4l2):
    """A frame's time is its stamp less half its exposure: the one the driver set, read back, not the
    one asked for (a review: 30 ms asked, 10 ms set, every frame time 10 ms early)."""
    import time as _time

    mono0 = _time.monotonic()

    def read(self):
        self.n += 1
        self.props[cv2.CAP_PROP_POS_MSEC] = (mono0 - 0.050 + self.n / 30) * 1e3
        return True, np.full((480, 640, 3), self.n % 256, np.uint8)

    clamp = FakeV4L2.set

    def set_clamped(self, prop, value):  # this sensor's longest exposure is 10 ms
        return clamp(self, prop, min(value, 100.0) if prop == cv2.CAP_PROP_EXPOSURE else value)

    monkeypatch.setattr(FakeV4L2, "read", read)
    monkeypatch.setattr(FakeV4L2, "set", set_clamped)
    src = open_source("0", CameraSettings(exposure_ms=30.0))
    src.set_timing(0.030)
    epoch = _time.time() - _time.monotonic()
    f = src.read()
    assert src.settings_report()["exposure_ms"] == pytest.approx(10.0)
    assert f.timestamp == pytest.approx(mono0 - 0.050 + 1 / 30 + epoch + 0.015 - 0.005, abs=2e-3)
    src.close()
