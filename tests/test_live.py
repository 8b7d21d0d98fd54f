"""Capture sources and thread, the live loop, and `tagloc live` end to end (UDP, recording killed mid-run)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest_io import line_map, make_session, truth_xy, write_video
from mosquitto import MOSQUITTO, Broker, Subscriber

from tagloc.apps.live import LiveConfig, run_live
from tagloc.core.errors import InputError, SessionError
from tagloc.core.rig import default_rig
from tagloc.core.stickermap import StickerMap
from tagloc.core.types import Frame, FrameResult, IdSource, TrackerOutput, TrackState
from tagloc.io.capture import CaptureThread, FrameSource, SessionSource, VideoSource, open_source
from tagloc.io.session import SessionInfo, SessionReader, SessionWriter

FPS = 10.0
N = 20


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    return make_session(tmp_path_factory.mktemp("live") / "sess", N, FPS)


@pytest.fixture(scope="module")
def video(session, tmp_path_factory) -> Path:
    return write_video(session, tmp_path_factory.mktemp("video") / "walk.avi", FPS)


def counter_video(path: Path, n: int, fps: float) -> Path:
    """A tiny MJPG video whose frame k is uniformly grey at level 20 + 7 (k mod 30) (frames are identifiable)."""
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (64, 48))
    for k in range(n):
        vw.write(np.full((48, 64, 3), 20 + 7 * (k % 30), np.uint8))
    vw.release()
    return path


def level(frame: Frame) -> int:
    return round((float(frame.image.mean()) - 20) / 7)


class ListSource(FrameSource):
    """A live source with frames ready at once (the consumer decides when to take them)."""

    live = True

    def __init__(self, n: int, bad: tuple[int, ...] = ()):
        self.frames = [Frame(k, k * 0.1, None if k in bad else np.full((4, 4), k, np.uint8)) for k in range(n)]

    def read(self) -> Frame | None:
        return self.frames.pop(0) if self.frames else None


def drain(cap: CaptureThread) -> list[int]:
    out = []
    while (item := cap.get(timeout=10)) is not None:
        out.append(item.frame.index)
    return out


def test_video_source_reads_frames_with_the_file_clock(tmp_path):
    src = open_source(str(counter_video(tmp_path / "c.avi", 12, 25.0)))
    assert isinstance(src, VideoSource) and not src.live and src.fps == pytest.approx(25.0)
    frames = []
    while (f := src.read()) is not None:
        frames.append(f)
    src.close()
    assert [f.index for f in frames] == list(range(12))
    assert np.allclose([f.timestamp for f in frames], np.arange(12) / 25.0)
    assert [level(f) for f in frames] == list(range(12))
    assert frames[0].image.ndim == 2 and frames[0].image.dtype == np.uint8


def test_open_source_rejects_what_it_cannot_open(tmp_path):
    with pytest.raises(InputError):
        open_source(str(tmp_path / "missing.avi"))
    (tmp_path / "junk.avi").write_bytes(b"\0" * 100)
    with pytest.raises(InputError):
        open_source(str(tmp_path / "junk.avi"))
    (tmp_path / "empty_dir").mkdir()
    with pytest.raises(SessionError):
        open_source(str(tmp_path / "empty_dir"))


def test_full_buffer_drops_the_oldest_frames():
    cap = CaptureThread(ListSource(20, bad=(3, 11)), buffer=2).start()
    cap.join(timeout=10)  # let the reader run to the end before consuming anything
    got = drain(cap)
    cap.stop()
    assert got == [18, 19]  # the newest two, not the first two
    s = cap.stats
    assert (s.grabbed, s.skipped, s.dropped, s.delivered) == (20, 2, 16, 2)
    assert s.ended == "end of source"


def test_unpaced_file_loses_nothing_even_with_a_slow_consumer(tmp_path):
    cap = CaptureThread(
        VideoSource(str(counter_video(tmp_path / "c.avi", 15, 100.0)), live=False), buffer=1, pace=False
    ).start()
    got = []
    while (item := cap.get(timeout=10)) is not None:
        got.append(level(item.frame))
        time.sleep(0.02)
    cap.stop()
    assert got == list(range(15))
    assert cap.stats.dropped == 0 and cap.stats.delivered == 15 and cap.stats.ended == "end of file"


def test_paced_file_drops_when_processing_falls_behind(tmp_path):
    # 50 fps source, a consumer needing 100 ms per frame: about 4 of 5 frames must be dropped, and
    # what is processed is always recent (newest-first buffer, no growing lag).
    cap = CaptureThread(
        VideoSource(str(counter_video(tmp_path / "c.avi", 30, 50.0)), live=False), buffer=1, pace=True
    ).start()
    got = []
    while (item := cap.get(timeout=10)) is not None:
        got.append(item.frame.index)
        time.sleep(0.1)
    cap.stop()
    s = cap.stats
    assert s.grabbed == 30 and s.delivered == len(got) and s.dropped == 30 - len(got)
    assert s.dropped >= 15
    assert got == sorted(got) and got[-1] >= 27


def test_session_source_skips_and_counts_corrupt_frames(tmp_path):
    sess = tmp_path / "s"
    with SessionWriter(sess, line_map(), default_rig(), SessionInfo(fps=FPS)) as w:
        for k in range(6):
            w.write(k, k / FPS, np.full((48, 64), 10 * k, np.uint8))
    for k in (2, 4):
        (sess / "frames" / f"{k:06d}.jpg").write_bytes(b"\xff\xd8 truncated")
    cap = CaptureThread(SessionSource(sess), buffer=1, pace=False).start()
    got = drain(cap)
    cap.stop()
    assert got == [0, 1, 3, 5] and cap.stats.skipped == 2 and cap.stats.ended == "end of session"
    cut = "is corrupt: JPEG cut short (no end-of-image marker)"
    assert cap.take_skipped() == [f"frame 2: 000002.jpg {cut}", f"frame 4: 000004.jpg {cut}"]
    assert cap.take_skipped() == []  # each named once


def test_live_names_the_corrupt_frames_it_skips_as_replay_does(session, tmp_path, capsys):
    s = tmp_path / "s"
    shutil.copytree(session, s)
    for k in (3, 7):
        (s / "frames" / f"{k:06d}.jpg").write_bytes(b"\xff\xd8 truncated")
    summary = run_live(LiveConfig(source=str(s), pace=False), localiser=EchoLocaliser(session))
    assert summary.frames == N - 2 and summary.capture.skipped == 2
    warnings = [ln for ln in capsys.readouterr().err.splitlines() if "warning" in ln]
    # Rate-limited like replay's: the first named, the rest counted in the summary.
    assert warnings == [
        "tagloc: warning: skipped frame 3: 000003.jpg is corrupt: JPEG cut short (no end-of-image marker)"
    ]
    assert summary.outputs.warnings == 1 and "skipped 2 (corrupt)" in summary.format()


class EchoLocaliser:
    """Stands in for the localiser in plumbing tests: the pose encodes the frame it came from."""

    def __init__(self, session: Path):
        r = SessionReader(session)
        self.map, self.rig = r.map, r.rig

    def process(self, frame: Frame) -> FrameResult:
        out = TrackerOutput(
            frame.timestamp,
            np.array([frame.index * 0.1, 1.0, 0.0]),
            np.eye(3) * 1e-3,
            TrackState.TRACKING,
            0.0,
            100 + frame.index,
            IdSource.DECODED,
        )
        return FrameResult(frame.index, frame.timestamp, [], out, {"total": 1.0})


def udp_listener() -> socket.socket:
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.5)
    return rx


def receive_all(rx: socket.socket) -> list[dict]:
    msgs = []
    while True:
        try:
            msgs.append(json.loads(rx.recv(65536)))
        except TimeoutError:
            return msgs


def test_live_loop_publishes_records_and_logs(session, video, tmp_path):
    rx = udp_listener()
    cfg = LiveConfig(
        source=str(video),
        publish=[f"udp://127.0.0.1:{rx.getsockname()[1]}"],
        vest="v9",
        record=tmp_path / "rec",
        log=tmp_path / "frames.jsonl",
        rerun_save=tmp_path / "live.rrd",
        pace=False,
        max_frames=20,
    )
    summary = run_live(cfg, localiser=EchoLocaliser(session))
    msgs = receive_all(rx)
    rx.close()
    assert summary.frames == 20 and summary.recorded == 20 and summary.capture.dropped == 0
    assert [m["index"] for m in msgs] == list(range(20))
    assert all(m["vest"] == "v9" and m["latency_ms"] >= 0 for m in msgs)
    assert np.allclose([m["t"] for m in msgs], np.arange(20) / FPS)
    assert np.allclose([m["x"] for m in msgs], np.arange(20) * 0.1)
    assert summary.sinks[f"udp://127.0.0.1:{cfg.publish[0].rsplit(':', 1)[1]}"] == (20, 0)
    assert np.isfinite(summary.latency(50)) and summary.latency(95) >= summary.latency(50)
    rec = SessionReader(tmp_path / "rec")
    frames = list(rec.frames())
    assert [f.index for f in frames] == list(range(20)) and not rec.skipped
    assert np.allclose(rec.timestamps, np.arange(20) / FPS)
    assert len((tmp_path / "frames.jsonl").read_text().splitlines()) == 20
    from tagloc.io.rerun_view import read_rrd

    assert read_rrd(tmp_path / "live.rrd")["world/body"].frames == list(range(20))


def test_live_loop_stops_on_max_seconds(session, tmp_path):
    # A paced 20-frame session lasts 2 s; the limit stops it after about 0.5 s (5 or 6 frames).
    summary = run_live(LiveConfig(source=str(session), max_seconds=0.5), localiser=EchoLocaliser(session))
    assert 1 <= summary.frames <= 15


def cli(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "tagloc", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw
    )


def test_tagloc_live_publishes_poses_over_udp(session, video):
    rx = udp_listener()
    port = rx.getsockname()[1]
    p = cli(
        "live",
        "--camera",
        str(video),
        "--config",
        str(session),
        "--publish",
        f"udp://127.0.0.1:{port}",
        "--vest",
        "v1",
        "--no-pace",
    )
    out, err = p.communicate(timeout=120)
    msgs = receive_all(rx)
    rx.close()
    assert p.returncode == 0, err
    assert "latency: median" in err and f"frames: {N} processed" in err
    assert [m["index"] for m in msgs] == list(range(N))
    tracked = [m for m in msgs if m["state"] == "tracking"]
    assert len(tracked) >= N - 3
    est = np.array([[m["x"], m["y"]] for m in tracked])
    errs = np.hypot(*(est - truth_xy(session, [m["t"] for m in tracked])).T)
    assert np.median(errs) < 0.10
    assert all(m["last_source"] in ("decoded", "checked", "orb", "appearance") for m in tracked)


def test_recording_killed_mid_run_replays_every_written_frame(session, video, tmp_path):
    rec = tmp_path / "rec"
    p = cli("live", "--camera", str(video), "--config", str(session), "--record", str(rec), "--no-pace")
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline:
            csv = rec / "frames.csv"
            if csv.exists() and len(csv.read_text().splitlines()) >= 9:  # header + 8 frames
                break
            time.sleep(0.01)
        os.kill(p.pid, signal.SIGKILL)
    finally:
        p.communicate(timeout=30)
    assert p.returncode == -signal.SIGKILL
    reader = SessionReader(rec)
    frames = list(reader.frames())
    assert len(frames) >= 8 and not reader.skipped
    assert [f.index for f in frames] == list(range(len(frames)))
    assert all(f.image is not None and f.image.shape == (972, 1296) for f in frames)
    r = cli("replay", str(rec), "--out", str(tmp_path / "est.tum"), "--quiet")
    out, err = r.communicate(timeout=120)
    assert r.returncode == 0, err
    assert f"frames: {len(frames)} (0 skipped" in out


@pytest.mark.skipif(MOSQUITTO is None, reason="mosquitto binary not installed (apt install mosquitto)")
def test_live_loop_keeps_going_through_a_broker_restart(session, tmp_path):
    # 80 tiny frames played at 20 fps (4 s); the broker goes away after ~1 s and is back ~1 s later.
    video = counter_video(tmp_path / "c.avi", 80, 20.0)
    broker = Broker(tmp_path).start()
    sub = Subscriber(broker.port, "tagloc/v8/pose")
    assert sub.subscribed.wait(10)
    result: dict = {}
    loc = EchoLocaliser(session)
    cfg = LiveConfig(source=str(video), publish=[f"mqtt://127.0.0.1:{broker.port}"], vest="v8")
    runner = threading.Thread(target=lambda: result.update(summary=run_live(cfg, localiser=loc)))
    try:
        runner.start()
        assert sub.wait_for(lambda idx: len(idx) >= 5)
        broker.stop()
        time.sleep(1.0)
        sub.subscribed.clear()
        broker.start()
        assert sub.subscribed.wait(15)
        runner.join(timeout=30)
        assert not runner.is_alive()
    finally:
        sub.close()
        broker.stop()
    s = result["summary"]
    name = f"mqtt://127.0.0.1:{broker.port}/tagloc/v8/pose"
    sent, dropped = s.sinks[name]
    assert s.frames + s.capture.dropped == 80  # localisation never stopped for the broker
    assert sent + dropped == s.frames and dropped >= 10  # a second of outage at 20 fps
    with sub.lock:
        got = list(sub.indices)
    gap = np.diff(got)
    assert got == sorted(got) and gap.max() >= 10  # the outage: dropped, never replayed later
    assert got[-1] >= 75  # publication resumed after the restart


@pytest.mark.parametrize("stride", [True, False])
def test_live_loop_strides_the_odometry_only_when_behind(tmp_path, stride):
    """Unpaced, every frame is waiting when the last one is done (the computer is "behind"): the
    odometry then skips frames while walking straight, and the floor flow after frames that read
    fixes placed, unless ``stride_when_behind`` is off; a replay (no live loop) never does by
    default."""
    from tagloc.pipeline.localiser import Localiser, LocaliserConfig

    path = make_session(tmp_path / "sess", 40, 30.0)
    r = SessionReader(path)
    # Without the default skip after frames that two read fixes placed (not load shedding: it runs
    # in a replay too), so that what is counted here is the shedding alone.
    loc = Localiser(r.map, r.rig, LocaliserConfig(skip_flow_min_fixes=0))
    summary = run_live(LiveConfig(source=str(path), pace=False, stride_when_behind=stride), localiser=loc)
    assert summary.frames == 40
    # Steps measured: fused, or left out in frames that read fixes placed (skip_flow_after_fix).
    steps = loc.counts["odometry_steps"] + loc.counts["odometry_unfused"]
    if stride:
        assert loc.counts["odometry_strided"] >= 3
        assert steps + loc.counts["odometry_strided"] >= 36
        assert loc.counts["flow_skipped"] >= 3  # and the flow after frames read fixes placed
    else:
        assert loc.counts["odometry_strided"] == 0 and steps >= 36
        assert loc.counts["flow_skipped"] == 0


class ThreadsSeen(EchoLocaliser):
    """An echo localiser that notes how many threads BLAS and OpenCV had as each frame was processed."""

    def __init__(self, session: Path):
        super().__init__(session)
        self.threads: list[tuple[int, int]] = []

    def process(self, frame: Frame) -> FrameResult:
        self.threads.append(threads_now())
        return super().process(frame)

    def stats(self) -> dict:
        return {}


def threads_now() -> tuple[int, int]:
    """(BLAS threads, OpenCV threads) of this process."""
    import cv2
    from threadpoolctl import threadpool_info

    return max(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"), cv2.getNumThreads()


def test_frames_are_processed_on_one_thread_and_the_process_gets_its_own_back(session):
    """BLAS's threads spin while they wait and OpenCV's pool costs CPU for little time (see
    tagloc.pipeline.run.single_threaded): live's loop and the replay loop run the localiser with one
    thread of each, and leave the process's own settings as they were."""
    import cv2
    from threadpoolctl import threadpool_limits

    from tagloc.pipeline.run import run_session

    before = cv2.getNumThreads()
    cv2.setNumThreads(2)
    try:
        with threadpool_limits(limits=2, user_api="blas"):
            assert threads_now() == (2, 2)
            for run in (
                lambda loc: run_live(LiveConfig(source=str(session), pace=False), localiser=loc),
                lambda loc: run_session(SessionReader(session), localiser=loc),
            ):
                loc = ThreadsSeen(session)
                run(loc)
                assert loc.threads == [(1, 1)] * N
                assert threads_now() == (2, 2)
    finally:
        cv2.setNumThreads(before)


def test_a_bad_session_source_is_refused_before_the_reference_bank_is_built(session, tmp_path, monkeypatch):
    """Building a large map's bank takes a minute: a source that cannot be played is named first."""
    import tagloc.vision.refs as refs

    def no_bank(*args, **kwargs):
        raise AssertionError("the reference bank was built before the source was checked")

    monkeypatch.setattr(refs, "load_or_build_refs", no_bank)
    monkeypatch.setattr(refs, "build_refs", no_bank)
    bad = tmp_path / "bad"
    shutil.copytree(session, bad)
    lines = (bad / "frames.csv").read_text().splitlines()
    (bad / "frames.csv").write_text("\n".join([*lines[:3], lines[1], *lines[3:]]) + "\n")  # a time repeated
    with pytest.raises(SessionError, match="frames.csv"):
        run_live(LiveConfig(source=str(bad), config_dir=session, mode="full", pace=False))


class CountingSource(FrameSource):
    """A file-like source of ``n`` tiny frames on an epoch clock at 30 fps, each its own image."""

    live = False
    fps = 30.0

    def __init__(self, n: int):
        self.n, self.k = n, 0

    def read(self) -> Frame | None:
        if self.k >= self.n:
            return None
        self.k += 1
        img = np.zeros((8, 8), np.uint8)
        img[0, :2] = divmod(self.k, 256)
        return Frame(self.k, 1.8e9 + self.k / 30, img)


class MemoryProbe:
    """An echo localiser noting the traced memory at given frames (after a collection)."""

    def __init__(self, at: set[int]):
        self.map, self.rig = StickerMap(np.array([7]), np.zeros((1, 2)), np.zeros(1)), default_rig()
        self.at, self.seen, self.n = at, {}, 0

    def process(self, frame: Frame) -> FrameResult:
        import gc
        import tracemalloc

        self.n += 1
        if self.n in self.at:
            gc.collect()
            self.seen[self.n] = tracemalloc.get_traced_memory()[0]
        out = TrackerOutput(frame.timestamp, np.zeros(3), np.eye(3) * 1e-3, TrackState.TRACKING, 0.0)
        return FrameResult(frame.index, frame.timestamp, [], out, {"total": 1.0})


def test_a_long_live_run_keeps_little_per_frame(tmp_path):
    # Over a shift the loop keeps only each frame's latency for the summary: as a list of floats
    # that took 32 bytes a frame (28 MB over 8 hours at 30 fps), now 8.
    import tracemalloc

    n = 2000
    probe = MemoryProbe({500, 500 + n, 500 + 2 * n})
    cfg = LiveConfig(source="probe", publish=[str(tmp_path / "p.jsonl")], log=tmp_path / "l.jsonl", pace=False)
    tracemalloc.start()
    try:
        summary = run_live(cfg, localiser=probe, source=CountingSource(500 + 2 * n))
    finally:
        tracemalloc.stop()
    a, b, c = (probe.seen[k] for k in sorted(probe.seen))
    assert summary.frames == 500 + 2 * n and len(summary.latency_ms) == summary.frames
    assert (b - a) / n < 16 and (c - b) / n < 16  # bytes a frame, over n frames and the next n


def test_frames_still_buffered_at_the_stop_are_counted():
    """Stopped with frames in its buffer (the live loop's --max-seconds, a signal), the capture counts
    them as unprocessed: grabbed = delivered + dropped + skipped + unprocessed, so the summary accounts
    for every frame (before, 182 grabbed against 180 processed and 0 dropped)."""
    cap = CaptureThread(ListSource(10, bad=(4,)), buffer=20).start()
    cap.join(timeout=10)
    taken = [cap.get(timeout=10) for _ in range(3)]
    cap.stop()
    s = cap.stats
    assert all(t is not None for t in taken)
    assert (s.grabbed, s.delivered, s.dropped, s.skipped, s.unprocessed) == (10, 3, 0, 1, 6)

    from tagloc.io.capture import MultiCapture

    multi = MultiCapture([ListSource(6), ListSource(6)], buffer=20)
    multi.start()
    multi.join(timeout=10)
    first = multi.get(timeout=10)
    multi.stop()
    m = multi.stats
    assert first is not None
    assert m.grabbed == 12 and m.delivered == 1
    assert m.grabbed == m.delivered + m.dropped + m.skipped + m.unprocessed


class ClockSwitchingSource(CountingSource):
    """A source stamped on its driver's clock until frame 5, when the clock is abandoned for grab time."""

    clock = "driver"

    def read(self) -> Frame | None:
        frame = super().read()
        if frame is not None and frame.index == 5:
            self.clock = "grab (driver clock jumped +1e+03 s)"
        return frame


def test_a_camera_leaving_its_driver_clock_is_said_when_it_happens(tmp_path, capsys):
    """A driver clock that stopped or jumped is abandoned for grab time (its jitter then in every
    frame time); that was written only into session.json's "clock": now one warning, once."""
    probe = MemoryProbe(set())
    cfg = LiveConfig(source="probe", publish=[str(tmp_path / "p.jsonl")], pace=False)
    summary = run_live(cfg, localiser=probe, source=ClockSwitchingSource(12))
    assert summary.frames == 12
    err = [ln for ln in capsys.readouterr().err.splitlines() if "grab time" in ln]
    assert len(err) == 1 and "driver clock jumped" in err[0], err
