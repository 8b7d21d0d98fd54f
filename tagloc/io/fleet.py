"""The robot manager's side: every vest's latest pose from its messages, and which vests need attention.

:class:`FleetState` takes ``tagloc.pose/1`` messages (bytes from MQTT, or documents read back
from a bag) with the time they were received, keeps each vest's last pose and a trail, and says which
vests to warn about (:meth:`FleetState.warnings`). It knows nothing of MQTT or viewers, so its logic is
tested directly; :mod:`tagloc.apps.monitor` feeds it and draws it (:mod:`tagloc.io.fleet_view`).

Clocks: ``received`` is the monitor's clock (any monotonic seconds, e.g. ``time.time()``). A
message's ``t`` is the vest's frame clock: epoch seconds for a live camera, a session's own clock in
replay. The message's age on arrival is judged from the vest's wall clock at publication and its
latency (``wall_t``, ``latency_ms``, sent by live vests), else from ``t`` when it is on the epoch
(``EPOCH_MIN_S``), and only when the monitor's clock is the epoch too (``clock_is_epoch``).
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from urllib.parse import urlsplit

import numpy as np

from tagloc.core.errors import InputError
from tagloc.io.fleet_config import FleetConfig
from tagloc.io.sinks import SCHEMA, unix_socketpair

STATES = ("initialising", "tracking", "lost", "unknown")
EPOCH_MIN_S = 1e9  # t above this (Sept 2001) is an epoch timestamp, below it a session's own clock


@dataclass
class PoseDoc:
    """One validated pose message.

    Attributes:
        vest: vest ID; t: frame timestamp (s); x, y (m), yaw (rad); cov: (3, 3) over (x, y, yaw).
        state: one of STATES; index: camera frame index (-1 if absent); since_fix: s or None.
    """

    vest: str
    t: float
    x: float
    y: float
    yaw: float
    cov: np.ndarray
    state: str
    index: int = -1
    since_fix: float | None = None
    last_id: int | None = None
    latency_ms: float | None = None
    wall_t: float | None = None


class MessageError(ValueError):
    """A message that is not a valid tagloc pose message (counted by the monitor, never fatal)."""


def _number(doc: dict, key: str, required: bool = True) -> float | None:
    v = doc.get(key)
    if v is None and not required:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise MessageError(f"{key!r} is not a finite number")
    return float(v)


def parse_message(payload: bytes | str | dict) -> PoseDoc:
    """Validate a pose message (raw JSON or an already decoded document); raises MessageError."""
    if isinstance(payload, dict):
        doc = payload
    else:
        try:
            doc = json.loads(payload)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise MessageError(f"not JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise MessageError("not a JSON object")
    if doc.get("schema") != SCHEMA:
        raise MessageError(f"schema {doc.get('schema')!r} is not {SCHEMA!r}")
    vest = doc.get("vest")
    if not isinstance(vest, str) or not vest:
        raise MessageError("no vest ID")
    state = doc.get("state")
    if state not in STATES:
        raise MessageError(f"state {state!r} is not one of {', '.join(STATES)}")
    try:
        cov = np.array(doc.get("cov"), float)
    except (TypeError, ValueError):
        raise MessageError("'cov' is not a 3x3 matrix") from None
    if cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
        raise MessageError("'cov' is not a finite 3x3 matrix")
    index = doc.get("index", -1)
    last_id = doc.get("last_id")
    return PoseDoc(
        vest=vest,
        t=_number(doc, "t"),
        x=_number(doc, "x"),
        y=_number(doc, "y"),
        yaw=_number(doc, "yaw"),
        cov=cov,
        state=state,
        index=int(index) if isinstance(index, int) and not isinstance(index, bool) else -1,
        since_fix=_number(doc, "since_fix", required=False),
        last_id=last_id if isinstance(last_id, int) and not isinstance(last_id, bool) else None,
        latency_ms=_number(doc, "latency_ms", required=False),
        wall_t=_number(doc, "wall_t", required=False),
    )


def ellipse_2sigma(cov: np.ndarray) -> tuple[float, float, float]:
    """(major, minor half-axis (m), angle of the major axis (rad)) of the 2-sigma ellipse of a (2, 2)+ covariance."""
    evals, evecs = np.linalg.eigh(np.asarray(cov, float)[:2, :2])
    half = 2.0 * np.sqrt(np.clip(evals, 0.0, None))
    return float(half[1]), float(half[0]), math.atan2(evecs[1, 1], evecs[0, 1])


@dataclass
class VestTrack:
    """What the monitor knows about one vest.

    Attributes:
        last: its newest message; received: when it arrived (monitor clock).
        messages: messages taken; reordered: messages older than ``last`` (ignored);
        expired: messages that were older than ``max_age_s`` on arrival (counted, still shown as stale).
        trail: (t, x, y) of recent posed messages.
    """

    vest: str
    last: PoseDoc
    received: float
    messages: int = 0
    reordered: int = 0
    expired: int = 0
    last_age_s: float | None = None
    trail: deque = field(default_factory=deque)

    @property
    def posed(self) -> bool:
        """Whether the last message carries a usable pose (not initialising)."""
        return self.last.state not in ("initialising",)


@dataclass
class VestWarning:
    """Why a vest needs attention: ``kind`` is stale, expired, uncertain or lost."""

    vest: str
    kind: str
    text: str


class FleetState:
    """Latest pose, trail and counters of every vest, from messages as they arrive."""

    def __init__(self, config: FleetConfig | None = None, clock_is_epoch: bool = True):
        self.config = config or FleetConfig()
        self.clock_is_epoch = clock_is_epoch
        self.vests: dict[str, VestTrack] = {}
        self.received = 0
        self.invalid = 0
        self.last_error: str | None = None

    def handle(self, payload: bytes | str | dict, received: float) -> VestTrack | None:
        """Take one message received at ``received``; returns the vest's track, or None if it was invalid."""
        self.received += 1
        try:
            doc = parse_message(payload)
        except MessageError as exc:
            self.invalid += 1
            self.last_error = str(exc)
            return None
        track = self.vests.get(doc.vest)
        if track is None:
            track = self.vests[doc.vest] = VestTrack(doc.vest, doc, received)
        elif doc.t < track.last.t or (doc.t == track.last.t and doc.index <= track.last.index):
            # QoS 0 over one TCP connection keeps order; a vest restarting its session clock does not.
            # An older message must never replace a newer pose, so it is counted and dropped.
            track.reordered += 1
            return track
        track.messages += 1
        track.last, track.received = doc, received
        age = self.age_on_arrival(doc, received)
        track.last_age_s = age
        if age is not None and age > self.config.max_age_s:
            track.expired += 1
        if doc.state != "initialising":
            track.trail.append((doc.t, doc.x, doc.y))
            while track.trail and (
                len(track.trail) > self.config.trail_max or doc.t - track.trail[0][0] > self.config.trail_s
            ):
                track.trail.popleft()
        return track

    def age_on_arrival(self, doc: PoseDoc, received: float) -> float | None:
        """Seconds between the frame's grab and the message's arrival, or None when unknown.

        A live vest states its wall clock at publication (``wall_t``) and the grab-to-publication
        latency: age = received - wall_t + latency. Without them, a frame clock on the epoch gives
        received - t. Either needs the monitor's clock on the epoch too (and clocks in sync: NTP).
        """
        if not self.clock_is_epoch:
            return None
        if doc.wall_t is not None and doc.latency_ms is not None:
            return received - doc.wall_t + doc.latency_ms / 1e3
        if doc.t < EPOCH_MIN_S:
            return None
        return received - doc.t

    def warnings(self, now: float) -> list[VestWarning]:
        """Vests to warn about at monitor time ``now``, stale first, then by vest ID."""
        cfg = self.config
        out: list[VestWarning] = []
        for vest in sorted(self.vests):
            tr = self.vests[vest]
            silent = now - tr.received
            if silent > cfg.stale_s:
                out.append(VestWarning(vest, "stale", f"no message for {silent:.2f} s (bound {cfg.stale_s:g} s)"))
            if tr.last_age_s is not None and tr.last_age_s > cfg.max_age_s:
                out.append(
                    VestWarning(
                        vest,
                        "expired",
                        f"last pose was {tr.last_age_s:.2f} s old on arrival (bound {cfg.max_age_s:g} s)",
                    )
                )
            if tr.last.state == "lost":
                out.append(VestWarning(vest, "lost", "tracker lost: pose from odometry only"))
            if tr.posed:
                major = ellipse_2sigma(tr.last.cov)[0]
                if major > cfg.max_2sigma_m:
                    out.append(VestWarning(vest, "uncertain", f"2-sigma {major:.2f} m exceeds {cfg.max_2sigma_m:g} m"))
        order = {"stale": 0, "expired": 1, "lost": 2, "uncertain": 3}
        return sorted(out, key=lambda w: (order[w.kind], w.vest))

    def counts(self) -> dict[str, int]:
        """Totals over the fleet: received, invalid, reordered, expired messages and vests seen."""
        return {
            "vests": len(self.vests),
            "received": self.received,
            "invalid": self.invalid,
            "reordered": sum(t.reordered for t in self.vests.values()),
            "expired": sum(t.expired for t in self.vests.values()),
        }


def parse_mqtt_url(url: str, default_topic: str = "tagloc/+/pose") -> tuple[str, int, str]:
    """(host, port, topic filter) of ``mqtt://HOST[:PORT][/TOPIC]`` (port 1883, topic ``tagloc/+/pose`` by default)."""
    u = urlsplit(url)
    if u.scheme != "mqtt":
        raise InputError(f"{url}: want mqtt://HOST[:PORT][/TOPIC]")
    try:
        port = u.port or 1883
    except ValueError:
        raise InputError(f"{url}: bad port") from None
    if not u.hostname:
        raise InputError(f"{url}: no host (want mqtt://HOST[:PORT][/TOPIC])")
    # '+' and '#' are MQTT wildcards and legal in the path; a '#' would be parsed as a URL fragment.
    topic = (u.path.lstrip("/") + ("#" if url.endswith("#") else "")) or default_topic
    return u.hostname, port, topic


class FleetSubscriber:
    """Subscribe to vests' pose topics on an MQTT broker and feed a :class:`FleetState`.

    Connects out only (never listens), QoS 0, re-subscribes on every reconnection. Messages are
    handled in paho's network thread under ``lock``; read ``state`` under the same lock.
    ``on_message(track_or_None, payload, received)`` is called after each message (for measurements).
    """

    def __init__(
        self,
        host: str,
        port: int,
        topic: str,
        state: FleetState,
        on_message=None,
        client_id: str = "",
        keepalive: int = 10,
        subscribed=None,
    ):
        import paho.mqtt.client as mqtt

        self.state = state
        self.topic = topic
        self.lock = threading.Lock()
        self.subscribed = subscribed if subscribed is not None else threading.Event()  # set on the broker's SUBACK
        self._time = time.time
        self._hook = on_message
        self.client = mqtt.Client(callback_api_version=mqtt.CallbackAPIVersion.VERSION2, client_id=client_id)
        self.client.reconnect_delay_set(1, 2)
        # Whether the broker is there now, and was ever: a monitor that cannot reach its broker
        # must say so, not report an empty fleet as if the warehouse were empty.
        self.connected = threading.Event()
        self.ever_connected = threading.Event()
        self.client.on_connect = self._on_connect
        self.client.on_disconnect = lambda c, u, flags, rc, p: self.connected.clear()
        self.client.on_subscribe = lambda c, u, mid, rcs, p: self.subscribed.set()
        self.client.on_message = self._on_message
        self.client.connect_async(host, port, keepalive=keepalive)
        with unix_socketpair(mqtt):  # tagloc opens no listening socket (see unix_socketpair)
            self.client.loop_start()

    def _on_connect(self, client, userdata, flags, reason_code, properties) -> None:
        if reason_code.is_failure:
            return
        self.connected.set()
        self.ever_connected.set()
        client.subscribe(self.topic, qos=0)

    def _on_message(self, client, userdata, message) -> None:
        received = self._time()
        with self.lock:
            track = self.state.handle(message.payload, received)
        if self._hook is not None:
            self._hook(track, message.payload, received)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()
