"""The fleet monitor: message handling and staleness without a viewer, MQTT through a real broker, the view."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest
from mosquitto import MOSQUITTO, Broker, Subscriber

from tagloc.core.errors import InputError
from tagloc.core.types import IdSource, TrackerOutput, TrackState
from tagloc.io.fleet import (
    FleetConfig,
    FleetState,
    FleetSubscriber,
    MessageError,
    ellipse_2sigma,
    parse_message,
    parse_mqtt_url,
)
from tagloc.io.sinks import MqttSink, PoseMessage

EPOCH = 1.8e9  # a live vest's epoch clock


def msg(vest="v1", t=EPOCH, x=1.0, y=2.0, yaw=0.3, sigma=0.05, state="tracking", index=0) -> bytes:
    cov = np.diag([sigma**2, sigma**2, 0.01])
    out = TrackerOutput(t, np.array([x, y, yaw]), cov, TrackState(state), 0.1, 7, IdSource.DECODED)
    return PoseMessage(vest, index, out).encode()


def test_parse_accepts_the_published_schema_and_rejects_the_rest():
    d = parse_message(msg())
    assert (d.vest, d.t, d.x, d.y, d.state, d.last_id) == ("v1", EPOCH, 1.0, 2.0, "tracking", 7)
    good = json.loads(msg())
    for bad, why in [
        (b"{not json", "not JSON"),
        (b"[1, 2]", "not a JSON object"),
        ({**good, "schema": "other/1"}, "schema"),
        ({**good, "vest": ""}, "vest"),
        ({**good, "x": None}, "'x'"),
        ({**good, "y": "3"}, "'y'"),
        ({**good, "cov": [[1, 0], [0, 1]]}, "cov"),
        ({**good, "cov": [[1, 0, 0], [0, 1, 0], [0, 0, float("nan")]]}, "cov"),
        ({**good, "state": "flying"}, "state"),
    ]:
        with pytest.raises(MessageError, match=why):
            parse_message(bad)


def test_invalid_messages_are_counted_not_fatal():
    fs = FleetState()
    assert fs.handle(b"garbage", EPOCH) is None
    assert fs.handle(msg(), EPOCH) is not None
    assert fs.counts() == {"vests": 1, "received": 2, "invalid": 1, "reordered": 0, "expired": 0}
    assert "not JSON" in fs.last_error


def test_staleness_follows_the_monitor_clock():
    fs = FleetState(FleetConfig(stale_s=1.0))
    fs.handle(msg("a", t=EPOCH), EPOCH + 0.05)
    fs.handle(msg("b", t=EPOCH), EPOCH + 0.05)
    assert fs.warnings(EPOCH + 1.0) == []
    fs.handle(msg("b", t=EPOCH + 1.0, index=30), EPOCH + 1.02)
    w = fs.warnings(EPOCH + 1.1)
    assert [(x.vest, x.kind) for x in w] == [("a", "stale")]
    assert "1.05 s" in w[0].text


def test_expired_on_arrival_needs_epoch_clocks():
    fs = FleetState(FleetConfig(max_age_s=0.5))
    fs.handle(msg("late", t=EPOCH), EPOCH + 0.8)
    fs.handle(msg("ok", t=EPOCH), EPOCH + 0.1)
    # A replayed session's clock (t from 0) says nothing about age: never judged expired.
    fs.handle(msg("replay", t=12.0), EPOCH + 5.0)
    kinds = {(w.vest, w.kind) for w in fs.warnings(EPOCH + 0.9)}
    assert kinds == {("late", "expired")}
    assert fs.vests["late"].expired == 1 and fs.vests["late"].last_age_s == pytest.approx(0.8)
    assert fs.vests["replay"].last_age_s is None
    # A live vest's message states its wall clock at publication and its latency since the grab.
    doc = json.loads(msg("live", t=12.0))
    doc.update(wall_t=EPOCH + 10.0, latency_ms=300.0)
    fs.handle(doc, EPOCH + 10.3)
    assert fs.vests["live"].last_age_s == pytest.approx(0.6) and fs.vests["live"].expired == 1


def test_uncertain_and_lost_vests_are_flagged():
    fs = FleetState(FleetConfig(max_2sigma_m=0.5))
    fs.handle(msg("wide", sigma=0.3), EPOCH)  # 2-sigma 0.6 m
    fs.handle(msg("narrow", sigma=0.2), EPOCH)  # 2-sigma 0.4 m
    fs.handle(msg("gone", state="lost", sigma=0.1), EPOCH)
    fs.handle(msg("new", state="initialising", sigma=10.0), EPOCH)  # no pose yet: not judged on its covariance
    kinds = [(w.vest, w.kind) for w in fs.warnings(EPOCH + 0.1)]
    assert kinds == [("gone", "lost"), ("wide", "uncertain")]
    assert ellipse_2sigma(np.diag([0.09, 0.04, 1.0]))[:2] == pytest.approx((0.6, 0.4))
    a, b, ang = ellipse_2sigma(np.array([[0.04, 0.0], [0.0, 0.09]]))
    assert (a, b) == pytest.approx((0.6, 0.4)) and abs(math.sin(ang)) == pytest.approx(1.0)


def test_older_messages_never_replace_newer_poses():
    fs = FleetState()
    fs.handle(msg(t=EPOCH + 1.0, x=5.0, index=30), EPOCH + 1.0)
    fs.handle(msg(t=EPOCH + 0.5, x=9.0, index=15), EPOCH + 1.1)
    fs.handle(msg(t=EPOCH + 1.0, x=9.0, index=30), EPOCH + 1.1)  # a duplicate
    tr = fs.vests["v1"]
    assert tr.last.x == 5.0 and tr.reordered == 2 and tr.messages == 1


def test_trail_is_bounded_in_time_and_points():
    fs = FleetState(FleetConfig(trail_s=1.0, trail_max=20))
    for i in range(60):
        fs.handle(msg(t=EPOCH + i / 30, x=i * 0.05, index=i), EPOCH + i / 30)
    tr = fs.vests["v1"].trail
    assert len(tr) == 20 and tr[-1][1] == pytest.approx(59 * 0.05)
    fs2 = FleetState(FleetConfig(trail_s=0.5, trail_max=1000))
    for i in range(60):
        fs2.handle(msg(t=EPOCH + i / 30, index=i), EPOCH + i / 30)
    assert len(fs2.vests["v1"].trail) == 16  # 0.5 s at 30 Hz, both ends included
    fs2.handle(msg("w", state="initialising"), EPOCH)
    assert len(fs2.vests["w"].trail) == 0


def test_status_text_lists_warnings():
    from tagloc.apps.monitor import status_text

    fs = FleetState()
    fs.handle(msg("a", state="lost"), EPOCH)
    fs.handle(msg("b"), EPOCH)
    text = status_text(fs, EPOCH + 2.0).splitlines()
    assert "2 vests, 3 warnings; 2 messages (0 invalid, 0 expired)" in text[0]
    assert text[1:] == [
        "  a: stale: no message for 2.00 s (bound 1 s)",
        "  b: stale: no message for 2.00 s (bound 1 s)",
        "  a: lost: tracker lost: pose from odometry only",
    ]


def test_parse_mqtt_url():
    assert parse_mqtt_url("mqtt://broker") == ("broker", 1883, "tagloc/+/pose")
    assert parse_mqtt_url("mqtt://10.0.0.2:1884/site/+/pose") == ("10.0.0.2", 1884, "site/+/pose")
    assert parse_mqtt_url("mqtt://h/tagloc/#") == ("h", 1883, "tagloc/#")
    for bad in ("udp://h:1", "mqtt://:1883/x", "mqtt://h:port/x"):
        with pytest.raises(InputError):
            parse_mqtt_url(bad)


@pytest.mark.skipif(MOSQUITTO is None, reason="mosquitto not installed")
def test_vests_through_a_real_broker(tmp_path):
    broker = Broker(tmp_path).start()
    fs = FleetState()
    seen = []
    sub = FleetSubscriber("127.0.0.1", broker.port, "tagloc/+/pose", fs, on_message=lambda tr, p, r: seen.append(r))
    sinks = []
    try:
        assert sub.subscribed.wait(10)
        sinks = [MqttSink("127.0.0.1", broker.port, f"tagloc/{v}/pose", client_id=v) for v in ("v1", "v2", "v3")]
        deadline = time.monotonic() + 10
        while not all(s.connected for s in sinks) and time.monotonic() < deadline:
            time.sleep(0.02)
        for i in range(10):
            for k, s in enumerate(sinks):
                s.publish(PoseMessage(f"v{k + 1}", i, parse_to_output(time.time(), x=float(k))))
            time.sleep(0.01)
        deadline = time.monotonic() + 10
        while len(seen) < 30 and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        for s in sinks:
            s.close()
        sub.close()
        broker.stop()
    with sub.lock:
        assert sorted(fs.vests) == ["v1", "v2", "v3"]
        assert all(tr.messages == 10 and tr.last.index == 9 for tr in fs.vests.values())
        assert fs.vests["v3"].last.x == 2.0 and fs.counts()["invalid"] == 0


def parse_to_output(t: float, x: float) -> TrackerOutput:
    return TrackerOutput(t, np.array([x, 0.0, 0.0]), np.eye(3) * 1e-3, TrackState.TRACKING, 0.1, 3, IdSource.DECODED)


def test_monitor_from_bags_draws_the_fleet(tmp_path, demo_map_path):
    from tagloc.apps.monitor import MonitorConfig, run_monitor
    from tagloc.io.rerun_view import read_rrd
    from tagloc.io.rosbag import BagWriter
    from tagloc.io.session import SessionReader

    rig = SessionReader(Path(__file__).resolve().parent.parent / "logs" / "walk2s").rig
    bags = []
    for vest, n in (("v1", 30), ("v2", 90)):  # v1 stops after 1 s, v2 goes on for 3 s
        bags.append(tmp_path / vest)
        w = BagWriter(bags[-1], vest, rig)
        for i in range(n):
            w.publish(PoseMessage(vest, i, parse_to_output(EPOCH + i / 30, x=1.0 + i * 0.04)))
        w.close()
    rrd, png = tmp_path / "fleet.rrd", tmp_path / "fleet.png"
    summary = run_monitor(MonitorConfig(map=demo_map_path, from_bag=bags, save=rrd, png=png, refresh_hz=10))
    assert summary.counts["vests"] == 2 and summary.counts["received"] == 120
    assert [(w.vest, w.kind) for w in summary.warnings] == [("v1", "stale")]
    ents = read_rrd(rrd)
    assert ents["fleet/map/stickers"].static
    assert {
        "fleet/vests/markers",
        "fleet/vests/ellipses",
        "fleet/vests/safety",
        "fleet/vests/trails",
        "warnings",
    } <= set(ents)
    assert png.stat().st_size > 10_000


@pytest.mark.skipif(MOSQUITTO is None, reason="mosquitto not installed")
def test_live_monitor_through_a_real_broker(tmp_path, demo_map_path, capsys):
    import threading

    from tagloc.apps.monitor import MonitorConfig, run_monitor
    from tagloc.io.rerun_view import read_rrd

    broker = Broker(tmp_path).start()
    stop, subscribed = threading.Event(), threading.Event()
    result = {}
    url = f"mqtt://127.0.0.1:{broker.port}"
    cfg = MonitorConfig(map=demo_map_path, url=url, save=tmp_path / "m.rrd", print_every_s=0.2)
    thread = threading.Thread(target=lambda: result.update(summary=run_monitor(cfg, stop, subscribed)))
    sink = None
    try:
        thread.start()
        sink = MqttSink("127.0.0.1", broker.port, "tagloc/v9/pose", client_id="v9")
        deadline = time.monotonic() + 10
        while not sink.connected and time.monotonic() < deadline:
            time.sleep(0.02)
        assert subscribed.wait(20)
        witness = Subscriber(broker.port, "tagloc/+/pose")  # a second subscriber: when it has all, so has the monitor
        assert witness.subscribed.wait(10)
        for i in range(20):
            sink.publish(PoseMessage("v9", i, parse_to_output(time.time(), x=3.0)))
            time.sleep(0.02)
        assert witness.wait_for(lambda idx: len(idx) == 20)
        witness.close()
        time.sleep(0.2)
    finally:
        stop.set()
        thread.join(20)
        if sink is not None:
            sink.close()
        broker.stop()
    s = result["summary"]
    assert s.broker_reached and s.broker is None  # connected to the end
    assert s.counts["vests"] == 1 and s.counts["received"] == 20 and s.counts["invalid"] == 0
    assert "fleet/vests/markers" in read_rrd(tmp_path / "m.rrd")
    assert " 1 vests, " in capsys.readouterr().out  # the headless status lines


def test_a_monitor_that_cannot_reach_its_broker_says_so(demo_map_path, capsys):
    """No broker: not an empty fleet reported as if the warehouse were empty (exit 1, and every status
    block says the broker is not connected)."""
    import socket

    from tagloc.cli import main

    with socket.socket() as s:  # a port nothing listens on once this closes
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code = main(
        [
            "monitor",
            "--map",
            str(demo_map_path),
            f"mqtt://127.0.0.1:{port}",
            "--max-seconds",
            "1",
            "--print-every",
            "0.3",
        ]
    )
    out = capsys.readouterr().out
    assert code == 1
    assert f"  not connected to the broker 127.0.0.1:{port} (retrying)" in out
    assert out.rstrip().endswith(
        f"warning: never connected to the broker 127.0.0.1:{port}: no vest's messages were received"
    )


def test_the_monitor_and_the_mqtt_sink_open_no_listening_socket(monkeypatch):
    """paho's loop thread wakes itself through a socket pair it builds by listening on 127.0.0.1;
    tagloc hands it a Unix pair instead, for the sink and the monitor's subscriber alike."""
    import socket

    from tagloc.io.fleet import FleetState, FleetSubscriber
    from tagloc.io.sinks import MqttSink

    listened = []
    real_listen = socket.socket.listen

    def listen(self, *args):
        listened.append(self.getsockname())
        return real_listen(self, *args)

    monkeypatch.setattr(socket.socket, "listen", listen)
    with socket.socket() as s:  # a port nothing listens on once this closes
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    listened.clear()
    sub = FleetSubscriber("127.0.0.1", port, "tagloc/+/pose", FleetState(FleetConfig()))
    sink = MqttSink("127.0.0.1", port, "tagloc/v1/pose")
    try:
        assert listened == []
    finally:
        sub.close()
        sink.close(flush_s=0.0)
