"""Pose sinks: message schema, JSON lines, UDP, TUM, frame log, and MQTT against a real broker."""

from __future__ import annotations

import io
import json
import math
import socket
import time
from pathlib import Path

import numpy as np
import pytest
from mosquitto import MOSQUITTO, Broker, Subscriber

from tagloc.core.errors import InputError
from tagloc.core.rig import default_rig
from tagloc.core.stickermap import StickerMap
from tagloc.core.types import (
    Detection,
    Fix,
    FrameResult,
    Identity,
    IdSource,
    Observation,
    PoseFix,
    TrackerOutput,
    TrackState,
)
from tagloc.io.session import read_tum
from tagloc.io.sinks import (
    SCHEMA,
    FrameLog,
    JsonLinesSink,
    MqttSink,
    PoseMessage,
    TumSink,
    UdpSink,
    frame_result_json,
    open_sink,
)
from tagloc.pipeline.output import OutputConfig, Outputs


def output(t: float = 1.25, state: TrackState = TrackState.TRACKING, yaw: float = 0.5) -> TrackerOutput:
    cov = np.array([[4e-4, 1e-5, 0.0], [1e-5, 9e-4, 2e-6], [0.0, 2e-6, 1e-3]])
    return TrackerOutput(t, np.array([3.5, -1.25, yaw]), cov, state, 0.2, 42, IdSource.DECODED)


def result(index: int, t: float) -> FrameResult:
    det = Detection(np.array([[10.0, 10.0], [60.0, 12.0], [58.0, 61.0], [9.0, 59.0]]))
    fix = PoseFix(np.eye(4), np.array([3.5, -1.25, 0.5]), np.eye(3) * 1e-4, 0.42)
    obs = Observation(det, 0, Identity(42, 1, IdSource.DECODED), Fix([fix], accepted=True))
    return FrameResult(index, t, [obs], output(t), {"detect": 5.5, "total": 9.25})


def test_message_schema_fields_and_units():
    msg = PoseMessage("v07", 12, output(), latency_ms=23.456).to_json()
    assert msg["schema"] == SCHEMA == "tagloc.pose/1"
    assert (msg["vest"], msg["frame"], msg["index"], msg["t"]) == ("v07", "world", 12, 1.25)
    assert (msg["x"], msg["y"]) == pytest.approx((3.5, -1.25))
    assert msg["yaw"] == pytest.approx(0.5) and msg["yaw_deg"] == pytest.approx(math.degrees(0.5), abs=1e-4)
    assert np.allclose(msg["cov"], output().cov)
    assert (msg["state"], msg["since_fix"], msg["last_id"], msg["last_source"]) == ("tracking", 0.2, 42, "decoded")
    assert msg["latency_ms"] == pytest.approx(23.456)
    # Before any fix: since_fix is null and the message is still valid JSON (no Infinity).
    first = TrackerOutput(0.0, np.zeros(3), np.eye(3), TrackState.INITIALISING, math.inf)
    doc = json.loads(PoseMessage("v07", 0, first).encode())
    assert doc["since_fix"] is None and doc["last_source"] is None and doc["latency_ms"] is None


def test_json_lines_to_stream():
    buf = io.StringIO()
    sink = JsonLinesSink(buf)
    for i in range(3):
        sink.publish(PoseMessage("v1", i, output(t=i * 0.1)))
    lines = buf.getvalue().splitlines()
    assert [json.loads(s)["index"] for s in lines] == [0, 1, 2]
    assert sink.sent == 3 and sink.dropped == 0


def test_udp_sink_delivers_datagrams_to_a_listener():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", 0))
        rx.settimeout(5.0)
        sink = open_sink(f"udp://127.0.0.1:{rx.getsockname()[1]}", vest="v2")
        assert isinstance(sink, UdpSink)
        for i in range(5):
            assert sink.publish(PoseMessage("v2", i, output(t=i / 30)))
        got = [json.loads(rx.recv(65536)) for _ in range(5)]
        sink.close()
    assert [g["index"] for g in got] == list(range(5))
    assert got[3]["t"] == pytest.approx(0.1) and got[0]["vest"] == "v2"


def test_tum_sink_skips_initialising_and_encodes_yaw(tmp_path):
    path = tmp_path / "est.tum"
    with TumSink(path) as sink:
        sink.publish(PoseMessage("v", 0, output(t=0.0, state=TrackState.INITIALISING)))
        sink.publish(PoseMessage("v", 1, output(t=0.5, yaw=math.pi / 2)))
        sink.publish(PoseMessage("v", 2, output(t=1.0, state=TrackState.LOST, yaw=-2.0)))
    assert (sink.sent, sink.dropped) == (2, 1)
    stamps, T = read_tum(path)
    assert np.allclose(stamps, [0.5, 1.0])
    assert np.allclose(T[:, :3, 3], [[3.5, -1.25, 0.0]] * 2, atol=1e-6)
    assert math.atan2(T[0, 1, 0], T[0, 0, 0]) == pytest.approx(math.pi / 2, abs=1e-5)
    assert math.atan2(T[1, 1, 0], T[1, 0, 0]) == pytest.approx(-2.0, abs=1e-5)
    # Planar: no roll or pitch.
    assert np.allclose(T[:, 2, :3], [0, 0, 1], atol=1e-6)


def test_frame_log_is_reproducible_without_times(tmp_path):
    a, b = tmp_path / "a.jsonl", tmp_path / "b.jsonl"
    for path, extra in ((a, 0.0), (b, 7.0)):
        with FrameLog(path) as log:
            for i in range(3):
                r = result(i, i / 30)
                r.times_ms = {k: v + extra for k, v in r.times_ms.items()}  # timings differ run to run
                log.write(r)
    assert a.read_bytes() == b.read_bytes()
    doc = json.loads(a.read_text().splitlines()[1])
    assert doc["index"] == 1 and doc["output"]["last_id"] == 42
    assert doc["observations"][0]["sticker_id"] == 42 and doc["observations"][0]["accepted"] is True
    assert "times_ms" not in doc and "times_ms" not in doc["observations"][0]
    timed = frame_result_json(result(0, 0.0), include_times=True)
    assert timed["times_ms"]["detect"] == pytest.approx(5.5)


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (Linux)")
def test_a_frame_log_on_a_full_disk_is_named_in_the_error():
    smap = StickerMap([42], [[0.0, 0.0]], [0.0])
    out = Outputs(smap, default_rig(), OutputConfig(log=Path("/dev/full")), warn=lambda m: None)
    with pytest.raises(OSError):
        out.emit(result(0, 0.0))  # the line's flush
    with pytest.raises(InputError) as info:
        out.close()  # the rest of the buffer, again: reported with the file's name
    assert str(info.value) == "/dev/full: No space left on device"


@pytest.mark.parametrize(
    "bad", ["udp://127.0.0.1", "tcp://host:1", "udp://:9000", "udp://h:notaport", "udp://h:9000/tagloc/v1/pose"]
)
def test_open_sink_rejects_bad_targets(bad):
    with pytest.raises(InputError):
        open_sink(bad)


@pytest.mark.parametrize(
    "target", ["mqtt://127.0.0.1:1/tagloc/+/pose", "mqtt://127.0.0.1:1/tagloc/#", "mqtt://127.0.0.1:1/tagloc/v1/pose?x"]
)
def test_an_mqtt_topic_filter_is_refused_as_a_publish_target(target):
    """The monitor's topic filter given to --publish: paho raised at the first pose (an internal error
    in the middle of a run) for '+', and cut a '#' or '?' part off to publish on another topic."""
    with pytest.raises(InputError, match="cannot hold"):
        open_sink(target, "v1").close()


def test_open_sink_picks_the_sink(tmp_path):
    assert isinstance(open_sink("stdout"), JsonLinesSink)
    s = open_sink(str(tmp_path / "x.tum"))
    assert isinstance(s, TumSink)
    s.close()
    s = open_sink(str(tmp_path / "x.jsonl"))
    assert isinstance(s, JsonLinesSink)
    s.close()


def wait(cond, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.02)
    return False


needs_mosquitto = pytest.mark.skipif(MOSQUITTO is None, reason="mosquitto binary not installed (apt install mosquitto)")


@needs_mosquitto
def test_mqtt_publishes_to_a_real_subscriber(tmp_path):
    broker = Broker(tmp_path).start()
    sub = sink = None
    try:
        sub = Subscriber(broker.port, "tagloc/v3/pose")
        assert sub.subscribed.wait(10)
        sink = open_sink(f"mqtt://127.0.0.1:{broker.port}", vest="v3")  # default topic tagloc/VEST/pose
        assert isinstance(sink, MqttSink) and sink.topic == "tagloc/v3/pose"
        assert wait(lambda: sink.connected)
        for i in range(10):
            assert sink.publish(PoseMessage("v3", i, output(t=i / 30)))
            time.sleep(0.005)
        assert sub.wait_for(lambda idx: len(idx) >= 10)
        assert sub.indices == list(range(10))
        assert (sink.sent, sink.dropped) == (10, 0)
    finally:
        for c in (sink, sub):
            if c is not None:
                c.close()
        broker.stop()


@needs_mosquitto
def test_mqtt_survives_broker_restart_without_queueing(tmp_path):
    broker = Broker(tmp_path).start()
    sub = sink = None
    try:
        sub = Subscriber(broker.port, "site/v4")
        assert sub.subscribed.wait(10)
        sink = MqttSink("127.0.0.1", broker.port, "site/v4", max_pending=5, reconnect_max_s=1.0)
        assert wait(lambda: sink.connected)
        i = 0
        for _ in range(10):
            sink.publish(PoseMessage("v4", i, output()))
            i += 1
            time.sleep(0.01)  # a frame rate, not a burst: a burst would hit max_pending
        assert sub.wait_for(lambda idx: len(idx) >= 10)

        broker.stop()
        assert wait(lambda: not sink.connected)
        down_from = i
        for _ in range(200):  # localisation goes on while the broker is away
            assert not sink.publish(PoseMessage("v4", i, output()))
            i += 1
        down_to = i
        assert sink.dropped == 200

        sub.subscribed.clear()
        broker.start()
        assert sub.subscribed.wait(15), "subscriber did not come back"
        assert wait(lambda: sink.connected, 15), "sink did not reconnect"
        for _ in range(20):
            sink.publish(PoseMessage("v4", i, output()))
            i += 1
            time.sleep(0.01)
        assert sub.wait_for(lambda idx: any(k >= down_to for k in idx))
        with sub.lock:
            got = list(sub.indices)
        # Messages from the outage were dropped, not queued and flushed on reconnect.
        assert not any(down_from <= k < down_to for k in got)
        assert sink.connects == 2
        assert sum(k >= down_to for k in got) >= 15
    finally:
        for c in (sink, sub):
            if c is not None:
                c.close()
        broker.stop()


@needs_mosquitto
def test_mqtt_sink_starts_without_a_broker_and_connects_later(tmp_path):
    broker = Broker(tmp_path)  # not started yet
    sink = MqttSink("127.0.0.1", broker.port, "late/topic", reconnect_max_s=1.0)
    try:
        assert not sink.publish(PoseMessage("v5", 0, output()))
        assert sink.dropped == 1
        broker.start()
        assert wait(lambda: sink.connected, 15)
        assert sink.publish(PoseMessage("v5", 1, output()))
    finally:
        sink.close()
        broker.stop()


def test_a_vest_id_must_name_the_vest_in_topics_and_messages(tmp_path):
    """An empty ID (messages the monitor refuses: a vest it never sees) or one with a character MQTT
    or ROS names treat specially is refused before anything is published, by the sinks, the
    outputs and the bag writer alike; the IDs the README uses pass."""
    from tagloc.io.rosbag import BagWriter
    from tagloc.io.sinks import check_vest_id, open_sink

    for good in ("vest-1", "v07", "replay", "A.b_9"):
        assert check_vest_id(good) == good
    rig = default_rig()
    for bad in ("", "a/b", "v+", "v#", "vest 1", "x" * 65, None):
        with pytest.raises(InputError, match="vest ID"):
            check_vest_id(bad)
        with pytest.raises(InputError, match="vest ID"):
            open_sink(str(tmp_path / "p.jsonl"), vest=bad)
        with pytest.raises(InputError, match="vest ID"):
            OutputConfig(vest=bad)
        with pytest.raises(InputError, match="vest ID"):
            BagWriter(tmp_path / "bag", bad, rig)
    assert not (tmp_path / "p.jsonl").exists() and not (tmp_path / "bag").exists()


def test_file_outputs_make_their_missing_directories(tmp_path):
    """``--out out/run.tum`` on a fresh clone, where ``out/`` does not exist yet: made, as ``--png`` and
    ``simulate -o`` make theirs (the CLI has checked that it can be)."""
    from tagloc.io.sinks import FrameLog, JsonLinesSink, TumSink

    sinks = [JsonLinesSink(tmp_path / "a" / "p.jsonl"), TumSink(tmp_path / "b" / "c" / "p.tum")]
    log = FrameLog(tmp_path / "d" / "frames.jsonl")
    for s in sinks:
        s.close()
    log.close()
    assert [p.is_file() for p in (tmp_path / "a" / "p.jsonl", tmp_path / "b" / "c" / "p.tum")] == [True, True]
    assert (tmp_path / "d" / "frames.jsonl").is_file()
