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
    assert fs.counts() == {"vests": 1, "received": 2, "invalid": 1, "reordered": 0, "expired": 0, "timeline_resets": 0}
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
    assert kinds == [("gone", "lost"), ("new", "initialising"), ("wide", "uncertain")]
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
    assert parse_mqtt_url("mqtt://h:1884/#") == ("h", 1884, "#")
    assert parse_mqtt_url("mqtt://h/+/+/pose") == ("h", 1883, "+/+/pose")


@pytest.mark.parametrize("topic", ["tagloc/#/pose", "tag+/pose", "tagloc/v#", "tagloc/+/pose?x"])
def test_a_topic_filter_mqtt_cannot_take_is_refused(topic):
    """'tagloc/#/pose' was cut at the '#' (a URL fragment) to the topic 'tagloc/', which no vest uses: the
    monitor heard nothing and reported no vests; 'tag+/pose' raised in paho's thread (a traceback on the
    terminal, then the same silence). Both exited 0."""
    with pytest.raises(InputError, match="is not an MQTT topic filter"):
        parse_mqtt_url(f"mqtt://127.0.0.1:1/{topic}")


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


# Payloads valid enough for the JSON grammar that Python's decoders choke on them (the reviewer's).
GOOD_COV = "[[0.01,0,0],[0,0.01,0],[0,0,0.001]]"
POISON = {
    "t too large for a float": '{"schema":"tagloc.pose/1","vest":"v99","t":1' + "0" * 400 + ',"x":0,"y":0,"yaw":0,'
    '"cov":[[1,0,0],[0,1,0],[0,0,1]],"state":"tracking"}',
    "cov entry too large for a float": '{"schema":"tagloc.pose/1","vest":"v99","index":2,"t":11,"x":1,"y":2,"yaw":0,'
    '"cov":[[1' + "0" * 400 + ',0,0],[0,0.01,0],[0,0,0.001]],"state":"tracking"}',
    "nested past the recursion limit": '{"schema":"tagloc.pose/1","vest":"v99","x":'
    + "[" * 100000
    + "]" * 100000
    + "}",
    "integer over 4300 digits": '{"schema":"tagloc.pose/1","vest":"v99","t":11,"x":1' + "0" * 5000 + ',"y":2,"yaw":0,'
    '"cov":' + GOOD_COV + ',"state":"tracking"}',
    "cov of booleans": '{"schema":"tagloc.pose/1","vest":"v99","t":11,"x":1,"y":2,"yaw":0,'
    '"cov":[[true,false,false],[false,true,false],[false,false,true]],"state":"tracking"}',
}


@pytest.mark.parametrize("name", sorted(POISON))
def test_payloads_python_cannot_decode_are_invalid_messages(name):
    """OverflowError, RecursionError and the 4300-digit ValueError were raised out of handle()."""
    with pytest.raises(MessageError):
        parse_message(POISON[name].encode())
    fs = FleetState()
    fs.handle(msg(), EPOCH)
    assert fs.handle(POISON[name].encode(), EPOCH + 0.1) is None
    assert fs.handle(json.loads(msg(t=EPOCH + 0.2, index=1)), EPOCH + 0.2) is not None
    assert (fs.invalid, fs.vests["v1"].messages) == (1, 2) and fs.last_error


def test_a_refused_message_names_its_vest_and_quotes_little_of_it():
    doc = json.loads(msg("v7"))
    with pytest.raises(MessageError, match=r"^v7: 'x' is too large for a float$"):
        parse_message({**doc, "x": 10**400})
    with pytest.raises(MessageError) as err:
        parse_message({**doc, "state": "x" * 10_000})
    assert len(str(err.value)) < 120


class _Message:
    """What paho hands ``on_message``: only the payload is read."""

    def __init__(self, payload: bytes):
        self.payload = payload


def _offline_subscriber(state: FleetState, **kwargs) -> FleetSubscriber:
    """A subscriber whose broker is nowhere (it retries in the background): its callbacks are called directly."""
    import socket

    with socket.socket() as s:  # a port nothing listens on once this closes
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return FleetSubscriber("127.0.0.1", port, "tagloc/+/pose", state, **kwargs)


def test_the_network_thread_survives_anything_handling_raises(monkeypatch):
    """Backstop: an exception out of on_message ends paho's network thread, and the subscription with it."""
    fs = FleetState()
    sub = _offline_subscriber(fs, on_message=lambda track, payload, received: 1 / 0)
    try:

        def broken(payload, received, seen=None):
            fs.received += 1
            raise KeyError("a bug")

        monkeypatch.setattr(fs, "handle", broken)
        sub._on_message(None, None, _Message(msg()))  # raises nothing
    finally:
        sub.close()
    assert (fs.received, fs.invalid, sub.hook_errors) == (1, 1, 1)
    assert fs.last_error == "could not handle a message: KeyError: 'a bug'"


@pytest.mark.skipif(MOSQUITTO is None, reason="mosquitto not installed")
def test_poisoned_messages_do_not_end_the_subscription(tmp_path):
    import paho.mqtt.client as mqtt

    broker = Broker(tmp_path).start()
    fs = FleetState()
    sub = FleetSubscriber("127.0.0.1", broker.port, "tagloc/+/pose", fs)
    pub = mqtt.Client(callback_api_version=mqtt.CallbackAPIVersion.VERSION2)
    try:
        assert sub.subscribed.wait(10)
        pub.connect("127.0.0.1", broker.port)
        pub.loop_start()
        payloads = [msg(t=time.time(), index=0)] + [p.encode() for p in POISON.values()]
        payloads += [msg(t=time.time(), index=i) for i in range(1, 4)]  # one connection: delivered in this order
        for p in payloads:
            pub.publish("tagloc/v1/pose", p, qos=0).wait_for_publish(10)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            with sub.lock:
                if fs.received == len(payloads):
                    break
            time.sleep(0.02)
    finally:
        pub.loop_stop()
        pub.disconnect()
        sub.close()
        broker.stop()
    with sub.lock:
        assert (fs.received, fs.invalid) == (len(payloads), len(POISON))
        assert fs.vests["v1"].last.index == 3 and fs.vests["v1"].messages == 4


def test_monitor_from_a_bag_counts_messages_python_cannot_decode(tmp_path, demo_map_path):
    """--from-bag stopped with an internal error: the bag reader caught only JSONDecodeError."""
    from tagloc.apps.monitor import MonitorConfig, run_monitor
    from tagloc.io.rosbag import STRING_TYPE, BagWriter, read_pose_messages
    from tagloc.io.session import SessionReader

    rig = SessionReader(Path(__file__).resolve().parent.parent / "logs" / "walk2s").rig
    bag = tmp_path / "v1"
    w = BagWriter(bag, "v1", rig)
    for i in range(10):
        w.publish(PoseMessage("v1", i, parse_to_output(EPOCH + i / 30, x=1.0)))
        if i == 4:
            for k, p in enumerate(POISON.values()):
                w._write(w._json, EPOCH + (i + 0.1 * (k + 1)) / 30, w._types[STRING_TYPE](data=p))
    w.close()
    assert sum(isinstance(m.doc, str) for m in read_pose_messages(bag)) == 2  # not JSON to Python: as text
    summary = run_monitor(MonitorConfig(map=demo_map_path, from_bag=[bag]))
    assert summary.counts["received"] == 10 + len(POISON) and summary.counts["invalid"] == len(POISON)
    assert summary.counts["vests"] == 1 and summary.last_error
    assert "last invalid message: v99: " in summary.format()


def test_monitor_from_a_bag_counts_pose_messages_it_cannot_read(tmp_path, demo_map_path):
    """A PoseWithCovarianceStamped whose quaternion is zero (no rotation) or whose bytes are cut
    stopped --from-bag with an internal error; each is one invalid message, the rest still shown."""
    from tagloc.apps.monitor import MonitorConfig, run_monitor
    from tagloc.io.rosbag import POSE_TYPE, BagWriter
    from tagloc.io.session import SessionReader

    rig = SessionReader(Path(__file__).resolve().parent.parent / "logs" / "walk2s").rig
    bag = tmp_path / "v1"
    w = BagWriter(bag, "v1", rig)
    for i in range(10):
        w.publish(PoseMessage("v1", i, parse_to_output(EPOCH + i / 30, x=1.0)))
    # Another vest's bare pose topic (no pose_json beside it): the monitor rebuilds its messages.
    conn = w._writer.add_connection("/tagloc/v2/pose", POSE_TYPE, typestore=w._store)
    T = w._types
    for k, (q, cut) in enumerate([((0, 0, 0, 0), False), ((0, 0, 0, 1), True), ((0, 0, 0, 1), False)]):
        t = EPOCH + (k + 0.5) / 30
        pose = T["geometry_msgs/msg/Pose"](
            T["geometry_msgs/msg/Point"](2.0, 1.0, 0.0), T["geometry_msgs/msg/Quaternion"](*q)
        )
        msg = T[POSE_TYPE](
            w._header(t, "map"), T["geometry_msgs/msg/PoseWithCovariance"](pose, np.eye(6).ravel() * 1e-3)
        )
        raw = w._store.serialize_cdr(msg, POSE_TYPE)
        w._writer.write(conn, round(t * 1e9), raw[:20] if cut else raw)
    w.close()
    summary = run_monitor(MonitorConfig(map=demo_map_path, from_bag=[bag]))
    assert summary.counts["received"] == 13 and summary.counts["invalid"] == 2
    assert summary.counts["vests"] == 2


def _cov_msg(cov, vest="v1", t=EPOCH, index=0) -> dict:
    return {**json.loads(msg(vest, t=t, index=index)), "cov": np.asarray(cov, float).tolist()}


def test_covariances_must_be_symmetric_positive_definite():
    """Negative variances and lopsided or indefinite matrices were taken and drawn as 0 m ellipses."""
    for cov, why in [
        ([[-4, 0, 0], [0, -4, 0], [0, 0, 0.01]], "positive definite"),
        ([[0.001, 100, 0], [0, 0.001, 0], [0, 0, 0.01]], "symmetric"),
        ([[9, 50, 0], [50, 9, 0], [0, 0, 0.01]], "positive definite"),
        ([[0.01, 0, 0], [0, 0.0, 0], [0, 0, 0.01]], "positive definite"),
    ]:
        with pytest.raises(MessageError, match=why):
            parse_message(_cov_msg(cov))
    # The sender's rounding to 1e-9 (TrackerOutput.to_json) of a nearly singular covariance, as the
    # tracker's eigenvalue floor (1e-10) allows, and mirrored entries one rounding step apart: taken.
    rng = np.random.default_rng(3)
    for _ in range(200):
        q, _r = np.linalg.qr(rng.normal(size=(3, 3)))
        spd = q @ np.diag([1e-10, rng.uniform(1e-6, 1e-2), rng.uniform(1e-4, 1.0)]) @ q.T
        parse_message(_cov_msg(np.round(spd, 9)))
    lopsided = np.diag([0.01, 0.01, 0.01])
    lopsided[0, 1] = 1e-9
    parse_message(_cov_msg(lopsided))
    parse_message(_cov_msg(np.diag([1e6, 1e6, math.pi**2 / 3])))  # an initialising vest's
    fs = FleetState()
    assert fs.handle(_cov_msg([[-4, 0, 0], [0, -4, 0], [0, 0, 0.01]]), EPOCH) is None and fs.invalid == 1


def test_staleness_follows_the_monotonic_clock_when_the_wall_clock_steps_back():
    """An NTP step back of D s kept a silent vest current for D s more (staleness was on time.time())."""
    fs = FleetState(FleetConfig(stale_s=1.0))
    wall, mono = [EPOCH + 0.05], [500.0]
    sub = _offline_subscriber(fs)
    sub.close()
    sub.wall_clock, sub.clock = (lambda: wall[0]), (lambda: mono[0])
    sub._on_message(None, None, _Message(msg("a", t=EPOCH)))
    tr = fs.vests["a"]
    assert (tr.received, tr.seen, tr.last_age_s) == (EPOCH + 0.05, 500.0, pytest.approx(0.05))
    wall[0] -= 10.0  # the host's clock steps back 10 s; 1.5 s pass
    mono[0] += 1.5
    assert [(w.vest, w.kind) for w in fs.warnings(mono[0])] == [("a", "stale")]
    # Age on arrival stays on the wall clock: the vest's stamps are compared with it.
    fs.handle(msg("b", t=EPOCH), EPOCH + 0.8, seen=mono[0])
    assert fs.vests["b"].last_age_s == pytest.approx(0.8)
    # Without ``seen`` (a bag), staleness is on ``received``, the bag's clock.
    fs2 = FleetState()
    fs2.handle(msg(), EPOCH)
    assert fs2.vests["v1"].seen == EPOCH and fs2.warnings(EPOCH + 1.5)[0].kind == "stale"


def test_the_live_monitor_prints_on_schedule_when_the_wall_clock_steps_back(demo_map_path, capsys, monkeypatch):
    """--print-every was scheduled on time.time(): a step back of D s stopped the status lines for D s."""
    import socket
    import types

    import tagloc.apps.monitor as monitor

    calls = [0]

    def stepping_wall_clock() -> float:
        calls[0] += 1
        return time.time() - (0.0 if calls[0] < 3 else 100.0)  # stepped back 100 s early in the run

    fake_time = types.SimpleNamespace(**{k: getattr(time, k) for k in ("monotonic", "strftime", "localtime")})
    fake_time.time = stepping_wall_clock
    monkeypatch.setattr(monitor, "time", fake_time)
    with socket.socket() as s:  # a port nothing listens on once this closes
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = monitor.MonitorConfig(map=demo_map_path, url=f"mqtt://127.0.0.1:{port}", max_seconds=1.2, print_every_s=0.2)
    monitor.run_monitor(cfg)
    blocks = [line for line in capsys.readouterr().out.splitlines() if " vests, " in line]
    assert len(blocks) >= 4


def test_a_time_ahead_of_the_monitors_clock_is_refused():
    """One message with t = 4e9 made every genuine message after it 'out of order' until a restart."""
    fs = FleetState(FleetConfig(max_skew_s=2.0))
    fs.handle(msg(t=EPOCH, index=0), EPOCH + 0.03)
    assert fs.handle(msg(t=4.0e9, index=1), EPOCH + 0.06) is None
    assert fs.last_error.startswith("v1: 't' is 2.2e+09 s ahead of the monitor's clock (bound 2 s)")
    for i in range(2, 10):
        assert fs.handle(msg(t=EPOCH + i / 30, x=float(i), index=i), EPOCH + i / 30 + 0.03) is not None
    assert fs.vests["v1"].last.x == 9.0 and fs.counts()["reordered"] == 0
    # The vest's wall clock at the grab (wall_t less the latency) is judged too; within the bound, taken.
    doc = {**json.loads(msg("w", t=EPOCH)), "wall_t": EPOCH + 3.2, "latency_ms": 100.0}
    assert fs.handle(doc, EPOCH) is None and "'wall_t' less 'latency_ms' is 3.1 s ahead" in fs.last_error
    assert fs.handle({**doc, "wall_t": EPOCH + 1.5}, EPOCH) is not None
    # A new vest's first message is refused like any other: it does not become the vest's pose.
    assert "z" not in fs.vests and fs.handle(msg("z", t=EPOCH + 10), EPOCH) is None and "z" not in fs.vests
    # A monitor on a bag's session clock (not the epoch) cannot judge it.
    replay = FleetState()
    assert replay.handle(msg(t=4.0e9), 5.0) is not None
    assert FleetState(clock_is_epoch=False).handle(msg(t=4.0e9), EPOCH) is not None


def test_a_vest_that_restarts_its_clock_is_followed_after_a_run_of_older_messages():
    """A session clock restarting (or one corrupt far-future t the skew bound cannot judge) locked the vest out."""
    fs = FleetState(FleetConfig(timeline_reset_n=30, stale_s=1.0))
    for i in range(60):
        fs.handle(msg(t=100.0 + i / 30, x=1.0, index=i), 100.0 + i / 30)
    assert len(fs.vests["v1"].trail) == 60
    for i in range(29):  # the vest restarted: its clock from 0 again
        tr = fs.handle(msg(t=i / 30, x=5.0, index=i), 102.0 + i / 30)
        assert tr.last.x == 1.0
    assert (tr.reordered, tr.timeline_resets) == (29, 0)
    w = fs.warnings(103.0)
    assert [(x.kind, x.text) for x in w] == [
        ("stale", "no new pose for 1.03 s (bound 1 s): its 29 messages since were older than the pose shown")
    ]
    tr = fs.handle(msg(t=29 / 30, x=5.0, index=29), 102.0 + 29 / 30)  # the 30th in a row: the new timeline
    assert (tr.last.x, tr.timeline_resets, tr.reordered, len(tr.trail)) == (5.0, 1, 29, 1)
    assert fs.counts()["timeline_resets"] == 1 and fs.warnings(102.0 + 30 / 30) == []
    fs.handle(msg(t=30 / 30, x=5.1, index=30), 103.0)
    assert tr.last.x == 5.1 and tr.older_run == 0 and len(tr.trail) == 2
    # A newer message in between ends the run: occasional duplicates never reset the timeline.
    fs2 = FleetState(FleetConfig(timeline_reset_n=3))
    for i in range(10):
        fs2.handle(msg(t=100.0 + i, index=i), 100.0 + i)
        fs2.handle(msg(t=100.0 + i, index=i), 100.0 + i)
    assert fs2.vests["v1"].timeline_resets == 0 and fs2.vests["v1"].reordered == 10


def test_stale_text_says_when_messages_arrive_but_are_refused():
    fs = FleetState(FleetConfig(max_skew_s=2.0, stale_s=1.0))
    fs.handle(msg(t=EPOCH), EPOCH)
    for i in range(1, 40):  # the vest's clock jumped 5 s ahead
        fs.handle(msg(t=EPOCH + 5 + i / 30, index=i), EPOCH + i / 30)
    (w,) = fs.warnings(EPOCH + 1.5)
    assert w.text == ("no new pose for 1.50 s (bound 1 s): its 39 messages since were ahead of the monitor's clock")
    fs.handle(msg(t=EPOCH + 1.4, index=50), EPOCH + 1.45)
    assert fs.warnings(EPOCH + 1.5) == []
    fs.vests["v1"].seen -= 5  # silent: no message at all
    assert fs.warnings(EPOCH + 1.5)[0].text == "no message for 5.05 s (bound 1 s)"


def test_status_and_summary_show_the_last_invalid_message_and_timeline_resets():
    from tagloc.apps.monitor import MonitorSummary, status_text

    fs = FleetState(FleetConfig(timeline_reset_n=2))
    fs.handle(b"garbage", EPOCH)
    fs.handle(msg(t=100.0), EPOCH + 1)  # a session clock, restarted
    fs.handle(msg(t=0.0, index=1), EPOCH + 1.1)
    fs.handle(msg(t=0.0, index=2), EPOCH + 1.2)
    text = status_text(fs, EPOCH + 1.3, wall=EPOCH)
    assert "(1 invalid, 0 expired, 1 timeline resets)" in text
    assert text.splitlines()[0].startswith(time.strftime("%H:%M:%S", time.localtime(EPOCH)))
    assert text.splitlines()[-1].startswith("  last invalid message: not JSON")
    summary = MonitorSummary(fs.counts(), fs.warnings(EPOCH + 1.3), 1.0, last_error=fs.last_error)
    assert "1 out of order, 0 expired; 1 timeline resets)" in summary.format()


def test_the_view_draws_a_long_trail_thinned(tmp_path):
    """Every redraw logs each trail whole: 30 s of a 30 Hz vest is drawn with at most 100 points,
    from its oldest to its newest, not 900 points ten times a second."""
    from rerun.chunk import RrdReader

    from tagloc.core.stickermap import StickerMap
    from tagloc.io.fleet_view import FleetView

    state = FleetState(clock_is_epoch=False)
    for k in range(900):
        state.handle(msg("v1", t=k / 30, x=k * 0.01, index=k), k / 30)
    view = FleetView(StickerMap(np.array([1]), np.zeros((1, 2)), np.zeros(1)), save=tmp_path / "f.rrd")
    view.update(state, 30.0, timestamp=False)
    view.close()
    trails = [
        s
        for c in RrdReader(str(tmp_path / "f.rrd")).stream()
        if c.entity_path == "/fleet/vests/trails"
        for s in c.to_record_batch().column("LineStrips3D:strips").to_pylist()[-1]
    ]
    (trail,) = trails
    assert 50 <= len(trail) <= 100
    assert trail[0][0] == pytest.approx(0.0) and trail[-1][0] == pytest.approx(8.99)


def test_a_sinks_delivery_probes_are_ignored_not_counted_invalid():
    """A monitor subscribed to tagloc/# also gets the MQTT sinks' probes (TOPIC/probe); the README asks
    subscribers to ignore that schema, and tagloc's own monitor counted each as an invalid message (10 a
    second per vest, the last-invalid line always quoting a probe)."""
    fs = FleetState()
    assert fs.handle(b'{"schema":"tagloc.probe/1","written":12}', EPOCH) is None  # as on the wire
    assert fs.handle(msg(), EPOCH) is not None
    assert fs.counts()["invalid"] == 0 and fs.counts()["received"] == 1 and fs.last_error is None
    from tagloc.io.sinks import probe_payload

    assert probe_payload(12) == b'{"schema":"tagloc.probe/1","written":12}'


@pytest.mark.skipif(MOSQUITTO is None, reason="mosquitto not installed")
def test_two_monitors_and_two_sinks_of_one_vest_share_a_broker(tmp_path, demo_map_path):
    """Every monitor connected as client 'tagloc-monitor' and every sink of a vest as 'tagloc-VEST': the
    broker closes a client's connection when another takes its ID, so two monitors (the README's
    several subscribers) or two --publish topics of one vest on one broker cut each other off, each
    missing what came while it reconnected. Now every client has its own ID and both get everything."""
    import threading

    from tagloc.apps.monitor import MonitorConfig, run_monitor
    from tagloc.io.sinks import open_sink

    broker = Broker(tmp_path).start()
    stop = threading.Event()
    subscribed = [threading.Event(), threading.Event()]
    results: list = [None, None]
    cfg = MonitorConfig(map=demo_map_path, url=f"mqtt://127.0.0.1:{broker.port}/tagloc/#")

    def monitor(k):
        results[k] = run_monitor(cfg, stop, subscribed[k])

    threads = [threading.Thread(target=monitor, args=(k,)) for k in range(2)]
    sinks = []
    try:
        for th, sub in zip(threads, subscribed):
            th.start()
            assert sub.wait(20)  # one after the other: the second's connection took the first's ID
        url = f"mqtt://127.0.0.1:{broker.port}"
        sinks = [open_sink(f"{url}/tagloc/v5/pose", "v5"), open_sink(f"{url}/tagloc/v5/pose2", "v5")]
        deadline = time.monotonic() + 10
        while not all(s.connected for s in sinks) and time.monotonic() < deadline:
            time.sleep(0.02)
        witness = Subscriber(broker.port, "tagloc/v5/+")
        assert witness.subscribed.wait(10)
        for i in range(20):
            for s in sinks:
                s.publish(PoseMessage("v5", i, parse_to_output(time.time(), x=3.0)))
            time.sleep(0.02)
        witness.wait_for(lambda idx: len(idx) == 40)
        witness.close()
        time.sleep(0.3)
    finally:
        stop.set()
        for th in threads:
            th.join(20)
        for s in sinks:
            s.close()
        broker.stop()
    assert [s.counts()["sent"] for s in sinks] == [20, 20]
    # Each monitor (subscribed to tagloc/#) has every pose of both topics.
    assert [r.counts["received"] for r in results] == [40, 40]


def test_a_vest_id_outside_the_schema_is_refused_and_forges_no_warning():
    """The receiver took any non-empty string as a vest ID (the README allows 1-64 letters, digits,
    '.', '_', '-'), and showed it as it came: a newline or '|' in it forged warning lines in the
    status text and rows in the warning table, and a megabyte of it was printed in every block."""
    from tagloc.apps.monitor import status_text
    from tagloc.io.fleet_view import warnings_markdown

    good = json.loads(msg("v1"))
    fs = FleetState()
    fs.handle(good, EPOCH)
    for vest in ("v2\n  v1: lost: forged", "v3 | lost | forged |", "v" * 65, "v/4", "v\u00e9"):
        assert fs.handle({**good, "vest": vest}, EPOCH) is None
        assert "is not 1-64 letters" in fs.last_error
    assert sorted(fs.vests) == ["v1"] and fs.invalid == 5
    assert "lost" not in status_text(fs, EPOCH + 0.1).split("last invalid message")[0]
    assert "lost" not in warnings_markdown(fs, EPOCH + 0.1).split("last invalid message")[0]
    for vest in ("v1", "vest-1", "A.b_c-9", "x" * 64):
        assert parse_message({**good, "vest": vest}).vest == vest


def test_a_vest_without_a_pose_is_flagged_not_left_off_the_map_unsaid():
    """An initialising vest is not drawn (its x, y are zeros), and had no warning either: the panel said
    "all vests current and certain" while a vest on the floor was nowhere on the map (at start, or
    when its track restarts)."""
    from tagloc.io.fleet_view import warnings_markdown

    fs = FleetState()
    fs.handle(msg("v1"), EPOCH)
    fs.handle(msg("v2", state="initialising", sigma=1000.0), EPOCH)
    assert [(w.vest, w.kind) for w in fs.warnings(EPOCH + 0.1)] == [("v2", "initialising")]
    assert "all vests current and certain" not in warnings_markdown(fs, EPOCH + 0.1)
    fs.handle(msg("v2", t=EPOCH + 0.2, index=1), EPOCH + 0.2)  # its first pose
    assert fs.warnings(EPOCH + 0.3) == []


def test_an_oversized_message_is_refused_unread():
    """Any length was decoded: a valid pose padded to 30 MB with an extra key was taken, holding the
    network thread and the view's lock for a second and taking 230 MB (a broker passes 256 MB)."""
    good = json.loads(msg())
    fs = FleetState()
    assert fs.handle(json.dumps({**good, "pad": "x" * 300}).encode(), EPOCH) is not None  # extra keys are fine
    big = json.dumps({**good, "t": EPOCH + 1, "pad": "x" * 100_000})
    for payload in (big.encode(), big):
        assert fs.handle(payload, EPOCH + 1) is None
        assert fs.last_error.startswith(f"{len(payload)} bytes long")
    assert fs.invalid == 2 and fs.vests["v1"].last.t == EPOCH
    assert FleetConfig().max_message_bytes >= 64 * len(msg("x" * 64))


@pytest.mark.parametrize(
    "args",
    [
        ["--vests", "abc"],
        ["--vests", "0"],
        ["--vests", "4,-1"],
        ["--rate", "0"],
        ["--rate", "nan"],
        ["--seconds", "-1"],
    ],
)
def test_the_fleet_benchmark_refuses_bad_arguments_in_one_line(args, tmp_path, capsys):
    """fleet_load.py took any number: letters were an internal error, no vests a formatting crash
    after the run, and a rate of 0 or NaN left the publishers dead and the run waiting minutes."""
    import importlib.util

    path = Path(__file__).resolve().parent.parent / "benchmarks" / "fleet_load.py"
    spec = importlib.util.spec_from_file_location("fleet_load", path)
    fleet_load = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fleet_load)
    # --stream a directory: were the arguments taken, the run would stop reading it, not start a broker.
    with pytest.raises(SystemExit) as exit_:
        fleet_load.main([*args, "--stream", str(tmp_path)])
    assert exit_.value.code == 2 and args[0] in capsys.readouterr().err


def test_a_negative_latency_cannot_make_an_old_pose_current():
    """latency_ms runs from grab to publication; a negative one was taken, and the age on arrival
    (now - wall_t + latency) of a pose published 1.4 s before it arrived came out 0.4 s: current."""
    good = json.loads(msg())
    fs = FleetState()
    sent = {**good, "t": EPOCH - 1.4, "wall_t": EPOCH - 1.4, "latency_ms": -1000.0}
    assert fs.handle(sent, EPOCH) is None and "'latency_ms' is negative" in fs.last_error
    assert fs.handle({**good, "since_fix": -0.5}, EPOCH) is None and "'since_fix' is negative" in fs.last_error
    assert fs.handle({**sent, "latency_ms": 0.0}, EPOCH).last_age_s == pytest.approx(1.4)


def _run_msg(run: str, t: float, x: float, index: int) -> dict:
    return {**json.loads(msg(t=t, x=x, index=index)), "run": run}


def test_two_senders_sharing_a_vest_id_are_flagged_and_a_restart_is_not():
    """Two vests left at one --vest interleave their runs: the pose shown jumps between two people, so
    the vest is flagged ``duplicate`` (and stays flagged for ``duplicate_hold_s`` after). A vest that
    restarts its process starts a new run and never returns to the old one: no warning."""
    cfg = FleetConfig()
    fs = FleetState(cfg)
    now = EPOCH
    for k in range(10):  # one vest's run, then it restarts (a new run; its clock goes on)
        run = "aaaa0001" if k < 5 else "bbbb0002"
        fs.handle(_run_msg(run, EPOCH + k / 30, 1.0, k), now + k / 30)
    now += 10 / 30
    assert [w.kind for w in fs.warnings(now)] == []
    assert fs.vests["v1"].duplicate_switches == 0

    fs2 = FleetState(cfg)
    for k in range(12):  # two vests, both "v1", at x = 1 and x = 20, alternating
        run, x = ("aaaa0001", 1.0) if k % 2 == 0 else ("cccc0003", 20.0)
        fs2.handle(_run_msg(run, EPOCH + k / 30, x, k), EPOCH + k / 30)
    last = EPOCH + 11 / 30
    kinds = [w.kind for w in fs2.warnings(last)]
    assert kinds[0] == "duplicate", kinds
    assert fs2.vests["v1"].duplicate_switches == 5  # every return to the first run after the second began
    # Held after the last return to an earlier run (message 10), then let go.
    back = EPOCH + 10 / 30
    assert "duplicate" in [w.kind for w in fs2.warnings(back + cfg.duplicate_hold_s - 0.01)]
    assert "duplicate" not in [w.kind for w in fs2.warnings(back + cfg.duplicate_hold_s + 0.01)]


def test_a_published_pose_carries_its_run_and_a_bad_run_is_refused():
    from tagloc.io.sinks import RUN_ID

    doc = parse_message(msg())
    assert doc.run == RUN_ID and len(RUN_ID) == 8
    good = json.loads(msg())
    for bad in ("", "a" * 33, "x y", 7, ["a"]):
        with pytest.raises(MessageError, match="run"):
            parse_message({**good, "run": bad})
    assert parse_message({k: v for k, v in good.items() if k != "run"}).run is None  # older senders
