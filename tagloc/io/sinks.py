"""Where poses go: JSON lines (stdout or file), UDP datagrams, MQTT, TUM trajectories, frame logs.

Every published pose is one JSON object of schema ``tagloc.pose/1``::

    {"schema": "tagloc.pose/1", "vest": "vest-07", "frame": "world", "index": 1234, "t": 41.133333,
     "x": 12.3456, "y": 3.21, "yaw": 1.570796, "yaw_deg": 90.0,
     "cov": [[sxx, sxy, sxyaw], [syx, syy, syyaw], [syawx, syawy, syawyaw]],
     "state": "tracking", "since_fix": 0.2667, "last_id": 42, "last_source": "decoded",
     "latency_ms": 23.4, "wall_t": 1795000000.123}

``t`` is the frame's timestamp (s, the source clock), ``frame`` names the frame the pose is in and
``index`` the camera frame it follows. ``x``, ``y`` (m) and ``yaw`` (rad, CCW from world +x) place
the body frame (on the floor under the vest, +x forward) in the world; ``cov`` is their 3x3
covariance (m^2, m*rad, rad^2). ``state`` is "initialising" (no pose yet: x, y, yaw are zeros and
meaningless), "tracking" or "lost". ``since_fix`` is seconds since the last accepted sticker fix
(null before the first). ``latency_ms`` is from frame capture to publication and ``wall_t`` the
sender's wall clock at publication, epoch s (both null offline): a receiver with a synchronised clock
knows a pose's age as ``now - wall_t + latency_ms / 1000`` and drops it past its own bound.

Sinks never listen: UDP only sends, MQTT only connects out. A network sink never blocks or stops
localisation: UDP errors are counted, MQTT messages are dropped (and counted) while the broker is
away, hung or behind, and the client reconnects in the background. Neither sends a pose older than
its ``max_age_s``.
"""

from __future__ import annotations

import collections
import contextlib
import json
import math
import re
import secrets
import socket
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TYPE_CHECKING
from urllib.parse import urlsplit

import numpy as np

from tagloc.core.errors import BackendUnavailable, InputError
from tagloc.core.geometry import planar_T
from tagloc.core.types import FrameResult, Observation, TrackerOutput, TrackState
from tagloc.io.session import tum_line

if TYPE_CHECKING:
    import paho.mqtt.client as mqtt

SCHEMA = "tagloc.pose/1"
#: This process's run: a random token every pose it publishes carries (``run``). Two senders that use
#: one vest ID (two vests left at one ``--vest``) interleave two runs, which a receiver sees at once
#: (:class:`tagloc.io.fleet.FleetState` warns ``duplicate``); a restarted vest starts a new run and
#: never returns to its old one.
RUN_ID = secrets.token_hex(4)
#: The MQTT sink's delivery probe (``TOPIC/probe``): not a pose; subscribers to ``tagloc/#`` ignore it.
PROBE_SCHEMA = "tagloc.probe/1"


def probe_payload(written: int) -> bytes:
    """The MQTT sink's probe message, sent after ``written`` poses."""
    return json.dumps({"schema": PROBE_SCHEMA, "written": written}, separators=(",", ":")).encode()


@dataclass
class PoseMessage:
    """One published pose: the tracker's output after a frame, tagged with the vest and frame.

    Attributes:
        vest: operator/vest ID.
        index: index of the frame the pose follows.
        output: the tracker's output.
        latency_ms: capture-to-publication latency, ms, or None (offline replay).
        frame: name of the frame the pose is expressed in.
        grabbed: when the frame was grabbed (``time.monotonic()``, s), or None when age does not
            count (offline, or a file played as fast as possible); network sinks drop a pose older
            than their bound instead of sending it late.
    """

    vest: str
    index: int
    output: TrackerOutput
    latency_ms: float | None = None
    frame: str = "world"
    grabbed: float | None = None

    def age_s(self, now: float | None = None) -> float:
        """Seconds since the frame was grabbed (0 offline)."""
        if self.grabbed is None:
            return 0.0
        return (time.monotonic() if now is None else now) - self.grabbed

    def to_json(self) -> dict:
        """The ``tagloc.pose/1`` object."""
        o = self.output.to_json()
        return {
            "schema": SCHEMA,
            "vest": self.vest,
            "frame": self.frame,
            "index": int(self.index),
            "t": o["t"],
            "x": o["x"],
            "y": o["y"],
            "yaw": o["yaw"],
            "yaw_deg": round(math.degrees(o["yaw"]), 4),
            "cov": o["cov"],
            "state": o["state"],
            "since_fix": o["since_fix"],
            "last_id": o["last_id"],
            "last_source": o["last_source"],
            "latency_ms": None if self.latency_ms is None else round(float(self.latency_ms), 3),
            # Sender's wall clock at publication (live only): with clocks in sync (NTP), a receiver
            # knows a pose's age as now - wall_t + latency_ms / 1000 and drops it past its bound.
            "wall_t": None if self.latency_ms is None else round(time.time(), 3),
            "run": RUN_ID,
        }

    def encode(self) -> bytes:
        """Compact UTF-8 JSON, as sent on the wire."""
        return json.dumps(self.to_json(), separators=(",", ":")).encode()


class Sink:
    """A destination for poses. ``sent`` and ``dropped`` count messages."""

    name = "sink"

    def __init__(self) -> None:
        self.sent = 0
        self.dropped = 0

    def publish(self, message: PoseMessage) -> bool:
        """Send one pose; True if it went out (never raises for network trouble)."""
        raise NotImplementedError

    def counts(self) -> dict[str, int]:
        """Message counters for the summary (at least ``sent`` and ``dropped``)."""
        return {"sent": self.sent, "dropped": self.dropped}

    def status(self) -> str | None:
        """What keeps poses from going out now (for a warning), or None if they flow."""
        return None

    def close(self) -> None:
        """Flush and release resources."""

    def __enter__(self) -> Sink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_for_writing(path: Path) -> IO[str]:
    """``path`` opened for writing text, its missing directories made first, as every tagloc output
    does (``--png``, ``--rerun``, ``simulate -o``): ``--out out/run.tum`` on a fresh clone has no
    ``out/`` yet. The CLI has checked that they can be made (:func:`tagloc.cli.checks.output_file`)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    return path.open("w", encoding="utf-8")


class JsonLinesSink(Sink):
    """One ``tagloc.pose/1`` object per line, to a stream or a file (flushed per line)."""

    def __init__(self, target: str | Path | IO[str]):
        super().__init__()
        if isinstance(target, (str, Path)):
            self.name = str(target)
            try:
                self._f: IO[str] = open_for_writing(Path(target))
            except OSError as exc:
                raise InputError(f"{target}: cannot write ({exc.strerror})") from exc
            self._own = True
        else:
            self.name = getattr(target, "name", "stream")
            self._f, self._own = target, False

    def publish(self, message: PoseMessage) -> bool:
        self._f.write(message.encode().decode() + "\n")
        self._f.flush()
        self.sent += 1
        return True

    def close(self) -> None:
        if self._own and not self._f.closed:
            self._f.close()
        elif not self._own:
            self._f.flush()


# A UDP destination counts as reached again after this long without a failed send (s): a refused
# port fails every other send, and a warning per frame is noise (see UdpSink.status).
UDP_RECOVERED_S = 1.0


class UdpSink(Sink):
    """One datagram per pose to ``host:port``.

    The socket is connected to the destination, so the kernel binds it to the routing interface's
    address and an ephemeral port (never the wildcard address) and delivers it only the
    destination's replies (ICMP errors); nothing listens.
    """

    def __init__(self, host: str, port: int, max_age_s: float = 0.5):
        super().__init__()
        self.name = f"udp://{host}:{port}"
        self.max_age_s = float(max_age_s)
        self.stale = 0
        try:
            family, _, _, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
        except socket.gaierror as exc:
            raise InputError(f"{self.name}: cannot resolve host ({exc.strerror})") from exc
        self._sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            self._sock.connect(addr)
        except OSError as exc:
            self._sock.close()
            raise InputError(f"{self.name}: cannot send there ({exc.strerror})") from exc
        self.errors = 0
        self._last_error = ""
        self._last_error_t = -math.inf  # time.monotonic() of the last failed send

    def publish(self, message: PoseMessage) -> bool:
        if message.age_s() > self.max_age_s:
            self.stale += 1
            self.dropped += 1
            return False
        try:
            self._sock.send(message.encode())
        except OSError as exc:
            # Network trouble (no route, ICMP refusals) must never stop localisation.
            self.errors += 1
            self._last_error = exc.strerror or str(exc)
            self._last_error_t = time.monotonic()
            self.dropped += 1
            return False
        self.sent += 1
        return True

    def status(self) -> str | None:
        # A port nobody listens on refuses every other datagram (the ICMP refusal of one fails the
        # next send), so one good send is no recovery: failing until UDP_RECOVERED_S without error.
        if time.monotonic() - self._last_error_t < UDP_RECOVERED_S:
            return f"send failed ({self._last_error})"
        return None

    def close(self) -> None:
        self._sock.close()


def unique_client_id(name: str) -> str:
    """An MQTT client ID: ``name`` (what the broker's log shows) and a random suffix.

    A broker closes a client's connection when another connects with the same ID, and paho reconnects
    a second later, closing the other's: two monitors, two vests left at one ``--vest``, or two
    ``--publish`` topics on one broker would each be cut off about half the time. Sessions are clean,
    so nothing is lost by never reusing an ID.
    """
    return f"{name}-{secrets.token_hex(4)}"


@contextlib.contextmanager
def unix_socketpair(mqtt_module: object) -> Iterator[None]:
    """Make paho's wake-up socket pair a Unix one while it starts its thread.

    paho builds the pair from a TCP socket that briefly listens on 127.0.0.1; tagloc opens no
    listening socket, so for the duration of ``loop_start`` paho gets ``socket.socketpair()``
    (AF_UNIX on Linux: nothing is bound to any address).
    """

    def pair() -> tuple[socket.socket, socket.socket]:
        a, b = socket.socketpair()
        a.setblocking(False)
        b.setblocking(False)
        return a, b

    original = getattr(mqtt_module, "_socketpair_compat", None)
    if original is None or not hasattr(socket, "AF_UNIX"):
        yield
        return
    mqtt_module._socketpair_compat = pair
    try:
        yield
    finally:
        mqtt_module._socketpair_compat = original


class MqttSink(Sink):
    """Publish poses at QoS 0 to an MQTT 5 broker, reconnecting in the background; never deliver stale ones.

    Nothing is queued for later: while the broker is unreachable, while the link is stalled, or while
    ``max_pending`` poses already wait to be written to the socket, a pose is dropped (counted).
    A pose older than ``max_age_s`` (from the frame's grab) is never handed to the socket, and each
    carries an MQTT 5 message expiry of ``ceil(max_age_s)`` s so that the broker discards it rather
    than forward it late to a slow subscriber.

    QoS 0 gets no acknowledgement, so the sink sends a small QoS 1 probe (``TOPIC/probe``, payload
    ``{"schema": "tagloc.probe/1", ...}``) every ``probe_s`` while connected, one at a time. The broker
    handles one connection's packets in order, so a probe's PUBACK proves that every pose written
    before it reached the broker (``confirmed``). A probe unanswered for ``max_age_s`` means the link
    is stalled (a hung broker, a partition): poses are dropped as stale until it answers or paho's
    keepalive gives up and reconnects. Poses written but never confirmed are ``unconfirmed``: lost
    or delivered, QoS 0 cannot tell. Whether subscribers received anything is beyond any publisher.
    """

    def __init__(
        self,
        host: str,
        port: int,
        topic: str,
        client_id: str = "",
        keepalive: int = 5,
        max_pending: int = 4,
        reconnect_max_s: float = 2.0,
        max_age_s: float = 0.5,
        probe_s: float = 0.1,
    ):
        super().__init__()
        try:
            import paho.mqtt.client as mqtt
            from paho.mqtt.packettypes import PacketTypes
            from paho.mqtt.properties import Properties
        except ImportError as exc:  # pragma: no cover - paho is a dependency
            raise BackendUnavailable("paho-mqtt is not installed; pip install paho-mqtt") from exc
        if not max_age_s > 0:
            raise InputError(f"{host}: MQTT max age must be positive, not {max_age_s}")
        self.name = f"mqtt://{host}:{port}/{topic}"
        self._success = mqtt.MQTT_ERR_SUCCESS
        self.topic = topic
        self.max_pending = int(max_pending)
        self.max_age_s = float(max_age_s)
        self.probe_s = float(probe_s)
        self.connects = 0
        self.stale = 0  # dropped: older than max_age_s, or the link stalled
        self.confirmed = 0  # written before a probe the broker acknowledged, on the same connection
        self._settled = 0  # poses written so far whose fate is decided (confirmed, or lost with a connection)
        self._lock = threading.Lock()
        self._pending = 0
        self._probe: tuple[int, float, int] | None = None  # (mid, monotonic send time, poses written before it)
        self._last_probe = -math.inf
        self._probe_mids: set[int] = set()  # probes sent and not yet acknowledged
        self._recent_mids: collections.deque[int] = collections.deque(maxlen=64)  # recent unknown acks
        self._props = Properties(PacketTypes.PUBLISH)
        self._props.MessageExpiryInterval = max(1, math.ceil(self.max_age_s))
        self._client: mqtt.Client = mqtt.Client(
            callback_api_version=mqtt.CallbackAPIVersion.VERSION2, client_id=client_id, protocol=mqtt.MQTTv5
        )
        # One probe in flight at a time; a probe left over from a dead connection is not resent late.
        self._client.max_inflight_messages_set(1)
        self._client.reconnect_delay_set(min_delay=1, max_delay=max(1, int(math.ceil(reconnect_max_s))))
        self._client.on_connect = self._on_connect
        self._client.on_disconnect = self._on_disconnect
        self._client.on_publish = self._on_publish
        self._client.connect_async(host, port, keepalive=keepalive, clean_start=True)
        with unix_socketpair(mqtt):
            self._client.loop_start()

    def _on_connect(
        self, client: mqtt.Client, userdata: object, flags: object, reason: object, properties: object
    ) -> None:
        if not getattr(reason, "is_failure", False):
            with self._lock:
                # paho discards unsent packets when it reconnects; start counting afresh.
                self._pending = 0
                self._probe = None
                self.connects += 1

    def _on_disconnect(
        self, client: mqtt.Client, userdata: object, flags: object, reason: object, props: object
    ) -> None:
        with self._lock:
            # A probe of a dead connection will never be answered, and no later probe speaks for
            # what was written on this one: those poses stay unconfirmed for good.
            self._probe = None
            self._settled = self.sent

    def _on_publish(self, client: mqtt.Client, userdata: object, mid: int, reason: object, properties: object) -> None:
        with self._lock:
            if mid in self._probe_mids:
                # A probe's PUBACK (perhaps of one paho resent after a reconnect: it vouches for nothing).
                self._probe_mids.discard(mid)
                if self._probe is not None and mid == self._probe[0]:
                    self._settle(self._probe[2])
                return
            # A pose written, or a probe acknowledged before _send_probe could note its mid.
            self._recent_mids.append(mid)
            self._pending = max(0, self._pending - 1)

    def _settle(self, written: int) -> None:
        """The broker acknowledged a probe sent after ``written`` poses (call with the lock held)."""
        if written > self._settled:
            self.confirmed += written - self._settled
            self._settled = written
        self._probe = None

    @property
    def connected(self) -> bool:
        """Whether the client is connected to the broker now."""
        return self._client.is_connected()

    @property
    def unconfirmed(self) -> int:
        """Poses written to the socket that no broker acknowledgement covers (lost or unknown)."""
        with self._lock:
            return self.sent - self.confirmed

    def stalled_s(self, now: float | None = None) -> float:
        """How long the outstanding probe has waited for the broker, s (0 if none)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            return 0.0 if self._probe is None else now - self._probe[1]

    def status(self) -> str | None:
        """What is wrong now (for warnings), or None when poses flow."""
        if not self._client.is_connected():
            return "not connected to the broker: poses are dropped"
        stalled = self.stalled_s()
        if stalled > self.max_age_s:
            return f"broker has not answered for {stalled:.1f} s (hung or partitioned): poses are dropped"
        return None

    def _send_probe(self, now: float) -> None:
        with self._lock:
            if self._probe is not None or now - self._last_probe < self.probe_s:
                return
            written = self.sent
            self._last_probe = now
        info = self._client.publish(self.topic + "/probe", probe_payload(written), qos=1)
        if info.rc == self._success:
            with self._lock:
                if info.mid in self._recent_mids:
                    # Acknowledged already (loopback is fast): it was counted as a pose; undo that.
                    self._pending += 1
                    self._settle(written)
                    return
                if len(self._probe_mids) > 64:  # acknowledgements lost with dead connections
                    self._probe_mids.clear()
                self._probe_mids.add(info.mid)
                if self._probe is None:
                    self._probe = (info.mid, now, written)

    def publish(self, message: PoseMessage) -> bool:
        now = time.monotonic()
        if not self._client.is_connected():
            self.dropped += 1
            return False
        self._send_probe(now)
        with self._lock:
            age = message.age_s(now)
            stalled = self._probe is not None and now - self._probe[1] > self.max_age_s
            if age > self.max_age_s or stalled:
                self.stale += 1
                self.dropped += 1
                return False
            if self._pending >= self.max_pending:
                self.dropped += 1
                return False
            self._pending += 1
        info = self._client.publish(self.topic, message.encode(), qos=0, properties=self._props)
        if info.rc != self._success:
            with self._lock:
                self._pending = max(0, self._pending - 1)
                self.dropped += 1
            return False
        self.sent += 1
        return True

    def counts(self) -> dict[str, int]:
        with self._lock:
            return {
                "sent": self.sent,
                "confirmed": self.confirmed,
                "unconfirmed": self.sent - self.confirmed,
                "dropped": self.dropped,
                "stale": self.stale,
            }

    def close(self, flush_s: float = 1.0) -> None:
        """Confirm what was written if the broker answers within ``flush_s``, then disconnect."""
        if self._client.is_connected() and self.sent > self._settled:
            deadline = time.monotonic() + flush_s
            self._last_probe = -math.inf
            while time.monotonic() < deadline and self.sent > self._settled and self._client.is_connected():
                self._send_probe(time.monotonic())
                time.sleep(0.01)
        self._client.disconnect()
        self._client.loop_stop()


class TumSink(Sink):
    """TUM trajectory of the body frame (``timestamp x y z qx qy qz qw``, z = 0).

    Outputs while initialising carry no pose and are not written (counted in ``dropped``).
    """

    def __init__(self, path: str | Path):
        super().__init__()
        self.name = str(path)
        try:
            self._f = open_for_writing(Path(path))
        except OSError as exc:
            raise InputError(f"{path}: cannot write ({exc.strerror})") from exc

    def publish(self, message: PoseMessage) -> bool:
        return self.write(message.output)

    def write(self, out: TrackerOutput) -> bool:
        """Append one pose line (:func:`tagloc.io.session.tum_line`)."""
        if out.state == TrackState.INITIALISING:
            self.dropped += 1
            return False
        T = planar_T(float(out.pose[0]), float(out.pose[1]), float(out.pose[2]))
        self._f.write(tum_line(out.t, T))
        self._f.flush()
        self.sent += 1
        return True

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()


def frame_result_json(result: FrameResult, include_times: bool = False) -> dict:
    """Plain-data form of a frame's result, for the per-frame log.

    Wall-clock stage timings vary run to run, so they are left out unless ``include_times``:
    without them a replay's log is byte-for-byte reproducible.
    """
    obs = _observations_json(result.observations, include_times)
    doc = {
        "index": int(result.index),
        "t": round(float(result.timestamp), 6),
        "skipped": result.skipped,
        "output": result.output.to_json(),
        "observations": obs,
    }
    if include_times:
        doc["times_ms"] = {k: round(float(v), 3) for k, v in result.times_ms.items()}
    return doc


def _observations_json(observations: list[Observation], include_times: bool) -> list[dict]:
    out = []
    for o in observations:
        d = o.to_json()
        if not include_times:
            d.pop("times_ms", None)
        out.append(d)
    return out


def late_observations_json(index: int, t: float, observations: list[Observation], include_times: bool = False) -> dict:
    """Plain-data form of observations finished after frame ``index`` (time ``t`` s) was published
    (``tagloc live``'s deferred work: a decode and its fix, fused at that frame's time), for the
    per-frame log: ``{"index", "t", "late": true, "observations"}``."""
    return {
        "index": int(index),
        "t": round(float(t), 6),
        "late": True,
        "observations": _observations_json(observations, include_times),
    }


class FrameLog:
    """Per-frame JSON lines log: observations and tracker output of every frame, and (live) a
    ``"late": true`` line for the observations a frame's deferred work finished after it."""

    def __init__(self, path: str | Path, include_times: bool = False):
        self.path = Path(path)
        self.name = str(path)  # what errors and summaries call it, as the sinks' ``name``
        self.include_times = include_times
        try:
            self._f = open_for_writing(self.path)
        except OSError as exc:
            raise InputError(f"{path}: cannot write ({exc.strerror})") from exc

    def write(self, result: FrameResult) -> None:
        """Append one frame's line."""
        self._line(frame_result_json(result, self.include_times))

    def write_late(self, index: int, t: float, observations: list[Observation]) -> None:
        """Append one line of observations finished after frame ``index`` (time ``t``) was logged."""
        self._line(late_observations_json(index, t, observations, self.include_times))

    def _line(self, doc: dict) -> None:
        self._f.write(json.dumps(doc, separators=(",", ":"), default=_json_default) + "\n")
        self._f.flush()

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()

    def __enter__(self) -> FrameLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _json_default(value: object) -> object:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def sink_file(target: str) -> Path | None:
    """The file a ``--publish`` target writes (a ``.tum`` or JSON-lines path), or None for stdout and
    the network: :func:`open_sink`'s own rule, so that the commands can check it as an output."""
    if target in ("stdout", "-") or "://" in target:
        return None
    return Path(target)


#: A vest ID names the operator to the robot manager: in every message, in the default MQTT topic
#: and in a bag's topics. Letters, digits, ".", "_" and "-" (nothing MQTT or ROS names treat
#: specially: "/", "+" and "#" would change the topic), 1-64 characters.
VEST_ID_PATTERN = re.compile(r"[A-Za-z0-9._-]{1,64}")


def check_vest_id(vest: object) -> str:
    """``vest`` if it is a valid vest ID (:data:`VEST_ID_PATTERN`), else InputError. An empty ID
    reached the monitor as messages it refuses: a vest the robot manager never sees."""
    if not isinstance(vest, str) or not VEST_ID_PATTERN.fullmatch(vest):
        raise InputError(f"vest ID {str(vest)[:70]!r}: want 1-64 letters, digits, '.', '_' or '-'")
    return vest


def open_sink(target: str, vest: str = "vest", max_age_s: float = 0.5) -> Sink:
    """Open a sink from its description.

    ``stdout`` or ``-``: JSON lines on stdout. ``udp://HOST:PORT``: datagrams. ``mqtt://HOST[:PORT][/TOPIC]``:
    MQTT (default port 1883, default topic ``tagloc/VEST/pose``). A path ending in ``.tum``: TUM
    trajectory. Any other path: JSON lines file. ``max_age_s``: network sinks never send an older pose.
    """
    check_vest_id(vest)
    if sink_file(target) is not None:
        return TumSink(target) if target.lower().endswith(".tum") else JsonLinesSink(target)
    if target in ("stdout", "-"):
        return JsonLinesSink(sys.stdout)
    # The network (sink_file: neither a file nor stdout has "://").
    url = urlsplit(target)
    try:
        port = url.port
    except ValueError:
        raise InputError(f"{target}: bad port") from None
    if not url.hostname:
        raise InputError(f"{target}: no host (want {url.scheme}://HOST:PORT)")
    if url.scheme == "udp":
        if port is None:
            raise InputError(f"{target}: UDP needs a port (udp://HOST:PORT)")
        if url.path not in ("", "/") or url.query or url.fragment:
            # A datagram has no topic: a path (as an MQTT target has) would be dropped without a word.
            raise InputError(f"{target}: a UDP target is udp://HOST:PORT, with no path (a topic is for mqtt://)")
        return UdpSink(url.hostname, port, max_age_s=max_age_s)
    if url.scheme == "mqtt":
        # A topic filter copied from the monitor's command line is no topic to publish on: paho raised
        # at the first pose (an internal error mid-run), and a '#' or '?' part was silently cut off.
        if any(c in target.split("://", 1)[1] for c in "+#?"):
            raise InputError(
                f"{target}: a topic to publish on cannot hold '+', '#' (wildcards, for subscribing) or '?'"
            )
        topic = url.path.lstrip("/") or f"tagloc/{vest}/pose"
        return MqttSink(
            url.hostname, port or 1883, topic, client_id=unique_client_id(f"tagloc-{vest}"), max_age_s=max_age_s
        )
    raise InputError(f"{target}: unknown sink scheme {url.scheme!r} (want udp://, mqtt://, stdout or a file)")
