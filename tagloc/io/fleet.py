"""The robot manager's side: every vest's latest pose from its messages, and which vests need attention.

:class:`FleetState` takes ``tagloc.pose/1`` messages (bytes from MQTT, or documents read back
from a bag) with the time they were received, keeps each vest's last pose and a trail, and says which
vests to warn about (:meth:`FleetState.warnings`). It knows nothing of MQTT or viewers, so its logic is
tested directly; :mod:`tagloc.apps.monitor` feeds it and draws it (:mod:`tagloc.io.fleet_view`).

Clocks: ``received`` is the monitor's clock for a message's age on arrival (``time.time()`` live:
epoch seconds, comparable with the vest's; the bag's clock in replay). ``seen`` is the clock
staleness is judged on (``time.monotonic()`` live, so that a step of the host's wall clock neither
hides nor invents a silent vest; ``received`` by default, as from a bag). A message's ``t`` is the
vest's frame clock: epoch seconds for a live camera, a session's own clock in replay. The message's
age on arrival is judged from the vest's wall clock at publication and its latency (``wall_t``,
``latency_ms``, sent by live vests), else from ``t`` when it is on the epoch (``EPOCH_MIN_S``), and
only when the monitor's clock is the epoch too (``clock_is_epoch``); so is a time ahead of arrival
(``FleetConfig.max_skew_s``).
"""

from __future__ import annotations

import json
import math
import re
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from urllib.parse import urlsplit

import numpy as np

from tagloc.core.errors import InputError
from tagloc.io.fleet_config import FleetConfig
from tagloc.io.sinks import PROBE_SCHEMA, SCHEMA, VEST_ID_PATTERN, unix_socketpair

#: A sender run token (``run``; tagloc's are 8 hex digits).
RUN_PATTERN = re.compile(r"[0-9A-Za-z]{1,32}")

STATES = ("initialising", "tracking", "lost", "unknown")
EPOCH_MIN_S = 1e9  # t above this (Sept 2001) is an epoch timestamp, below it a session's own clock


@dataclass
class PoseDoc:
    """One validated pose message.

    Attributes:
        vest: vest ID; t: frame timestamp (s); x, y (m), yaw (rad); cov: (3, 3) over (x, y, yaw).
        state: one of STATES; index: camera frame index (-1 if absent); since_fix: s or None.
        run: the sending process's run token (None from senders that state none).
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
    run: str | None = None


class MessageError(ValueError):
    """A message that is not a valid tagloc pose message (counted by the monitor, never fatal)."""


class ProbeMessage(MessageError):
    """A sink's delivery probe (``tagloc.probe/1``), seen by a subscriber to ``tagloc/#``: not a pose,
    and not an invalid one either (ignored, not counted)."""


def _short(v: object) -> str:
    """``repr(v)``, cut short: a sender's value is quoted in every status line until the next error."""
    try:
        r = repr(v)
    except RecursionError:  # JSON nested nearly as deep as the decoder allows
        return "(nested too deeply)"
    return r if len(r) <= 40 else r[:37] + "..."


def _is_number(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _number(doc: dict, key: str, required: bool = True) -> float | None:
    """``doc[key]`` as a finite float (None if absent and not ``required``); raises MessageError."""
    v = doc.get(key)
    if v is None and not required:
        return None
    if not _is_number(v):
        raise MessageError(f"{key!r} is not a finite number")
    try:
        f = float(v)
    except OverflowError:  # JSON integers are unbounded: 1 followed by 400 zeros is valid JSON
        raise MessageError(f"{key!r} is too large for a float") from None
    if not math.isfinite(f):
        raise MessageError(f"{key!r} is not a finite number")
    return f


def _duration(doc: dict, key: str) -> float | None:
    """``doc[key]``, a time since an earlier event (None if absent); raises MessageError if negative.

    A negative ``latency_ms`` would make a pose younger than it is: an old pose taken as current.
    """
    v = _number(doc, key, required=False)
    if v is not None and v < 0:
        raise MessageError(f"{key!r} is negative ({v:.6g})")
    return v


def _covariance(v: object, tol: float) -> np.ndarray:
    """A message's ``cov`` as a (3, 3) float array, if it is a covariance; raises MessageError.

    Symmetric and positive definite up to ``tol`` (the sender's rounding, see FleetConfig.cov_tol):
    the ellipse is drawn from it, and a negative or lopsided one would draw a confident 0 m ellipse.
    """
    if not (isinstance(v, (list, tuple)) and len(v) == 3 and all(isinstance(r, (list, tuple)) for r in v)):
        raise MessageError("'cov' is not a 3x3 matrix")
    if not all(len(r) == 3 and all(_is_number(e) for e in r) for r in v):
        raise MessageError("'cov' is not a 3x3 matrix of numbers")
    try:
        cov = np.array(v, float)
    except OverflowError:
        raise MessageError("'cov' has a number too large for a float") from None
    if not np.all(np.isfinite(cov)):
        raise MessageError("'cov' is not a finite 3x3 matrix")
    if np.abs(cov - cov.T).max() > tol:
        raise MessageError("'cov' is not symmetric")
    # eigvalsh's own error is a few float epsilons of the matrix's norm (an initialising vest's
    # variances are 1e6 m^2), on top of the sender's rounding.
    floor = -(tol + 3 * np.finfo(float).eps * np.abs(cov).max())
    if not np.all(np.diag(cov) > 0) or np.linalg.eigvalsh(cov)[0] < floor:
        raise MessageError("'cov' is not positive definite")
    return cov


def parse_message(
    payload: bytes | str | dict,
    cov_tol: float = FleetConfig.cov_tol,
    max_bytes: int = FleetConfig.max_message_bytes,
) -> PoseDoc:
    """Validate a pose message (raw JSON, at most ``max_bytes`` long, or an already decoded document);
    raises MessageError.

    Nothing a sender can put in a payload raises anything else.
    """
    if isinstance(payload, dict):
        doc = payload
    elif not isinstance(payload, (str, bytes, bytearray)):
        # An already decoded document that is no object (a bag's pose_json holding [1, 2], 5, null):
        # json.loads and len() raised TypeError on it, which stopped the monitor.
        raise MessageError(f"not a JSON object ({type(payload).__name__})")
    elif len(payload) > max_bytes:
        raise MessageError(f"{len(payload)} bytes long (a pose message is under 1 kB; bound {max_bytes})")
    else:
        try:
            doc = json.loads(payload)
        except RecursionError:
            raise MessageError("not JSON (nested too deeply)") from None
        except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError, and integers over 4300 digits
            raise MessageError(f"not JSON ({str(exc)[:120]})") from None
    if not isinstance(doc, dict):
        raise MessageError("not a JSON object")
    if doc.get("schema") == PROBE_SCHEMA:
        raise ProbeMessage("a tagloc MQTT sink's delivery probe, not a pose")
    if doc.get("schema") != SCHEMA:
        raise MessageError(f"schema {_short(doc.get('schema'))} is not {SCHEMA!r}")
    vest = doc.get("vest")
    if not isinstance(vest, str) or not vest:
        raise MessageError("no vest ID")
    if not VEST_ID_PATTERN.fullmatch(vest):
        # The schema's vest IDs (every sender checks its own): any other string would be shown as it
        # came, in status lines and the warning table, where a newline or '|' forges rows.
        raise MessageError(f"vest ID {_short(vest)} is not 1-64 letters, digits, '.', '_' or '-'")
    try:
        return _pose_doc(doc, vest, cov_tol)
    except MessageError as exc:
        # Which vest sent it is what the robot manager needs to chase it up.
        raise MessageError(f"{vest[:40]}: {exc}") from None


def _pose_doc(doc: dict, vest: str, cov_tol: float) -> PoseDoc:
    """The rest of :func:`parse_message`, once the document is an object from ``vest``."""
    state = doc.get("state")
    if state not in STATES:
        raise MessageError(f"state {_short(state)} is not one of {', '.join(STATES)}")
    cov = _covariance(doc.get("cov"), cov_tol)
    index = doc.get("index", -1)
    last_id = doc.get("last_id")
    run = doc.get("run")
    if run is not None and not (isinstance(run, str) and RUN_PATTERN.fullmatch(run)):
        raise MessageError(f"run {_short(run)} is not 1-32 letters or digits")
    return PoseDoc(
        vest=vest,
        t=_number(doc, "t"),
        x=_number(doc, "x"),
        y=_number(doc, "y"),
        yaw=_number(doc, "yaw"),
        cov=cov,
        state=state,
        index=int(index) if isinstance(index, int) and not isinstance(index, bool) else -1,
        since_fix=_duration(doc, "since_fix"),
        last_id=last_id if isinstance(last_id, int) and not isinstance(last_id, bool) else None,
        latency_ms=_duration(doc, "latency_ms"),
        wall_t=_number(doc, "wall_t", required=False),
        run=run,
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
        last: its newest message; received: when it arrived (monitor clock, as ``handle``'s
            ``received``); seen: the same on the staleness clock (``handle``'s ``seen``).
        messages: messages taken; reordered: messages older than ``last`` (ignored);
        expired: messages that were older than ``max_age_s`` on arrival (counted, still shown as stale).
        timeline_resets: times the vest was followed onto a new, older timeline (``timeline_reset_n``).
        older_run: messages in a row older than ``last`` (the run a timeline reset counts).
        dropped_since: messages from the vest since ``last`` that were not taken, and why the
            latest was not (``drop_reason``): the stale warning says so rather than "no message".
        trail: (t, x, y) of recent posed messages.
        runs: each sender run seen from this vest ID, with when it was first seen (staleness
            clock); last_run: the run of its latest message (taken or not).
        duplicate_seen: when a message last came from an earlier run than the message before it
            (two senders interleaving: see :meth:`FleetState.handle`); duplicate_switches: how often.
    """

    vest: str
    last: PoseDoc
    received: float
    seen: float
    messages: int = 0
    reordered: int = 0
    expired: int = 0
    timeline_resets: int = 0
    older_run: int = 0
    dropped_since: int = 0
    drop_reason: str = ""
    last_age_s: float | None = None
    trail: deque = field(default_factory=deque)
    runs: dict = field(default_factory=dict)
    last_run: str | None = None
    duplicate_seen: float | None = None
    duplicate_switches: int = 0

    @property
    def posed(self) -> bool:
        """Whether the last message carries a usable pose (not initialising)."""
        return self.last.state not in ("initialising",)


@dataclass
class VestWarning:
    """Why a vest needs attention: ``kind`` is duplicate (two senders share its ID), stale, expired,
    lost, initialising (no pose) or uncertain."""

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

    def refuse(self, error: str) -> None:
        """Count a message as invalid, with why (shown as the last invalid message)."""
        self.invalid += 1
        self.last_error = error

    def handle(self, payload: bytes | str | dict, received: float, seen: float | None = None) -> VestTrack | None:
        """Take one message received at ``received``; returns the vest's track, or None if it was invalid (or a probe).

        ``seen``: the arrival on the staleness clock (see the module's docstring; default ``received``).
        """
        cfg = self.config
        seen = received if seen is None else seen
        try:
            doc = parse_message(payload, cfg.cov_tol, cfg.max_message_bytes)
        except ProbeMessage:
            return None  # the README asks subscribers to tagloc/# to ignore probes; they are no vest's message
        except MessageError as exc:
            self.received += 1
            self.refuse(str(exc))
            return None
        self.received += 1
        track = self.vests.get(doc.vest)
        lead = self.lead_s(doc, received)
        if lead is not None and lead[1] > cfg.max_skew_s:
            # Taken, a time from the future would make every genuine message after it look older.
            self.refuse(
                f"{doc.vest}: {lead[0]} is {lead[1]:.3g} s ahead of the monitor's clock "
                f"(bound {cfg.max_skew_s:g} s): the vest's clock or message is wrong"
            )
            if track is not None:
                track.dropped_since += 1
                track.drop_reason = "ahead of the monitor's clock"
            return None
        first = track is None
        if first:
            track = self.vests[doc.vest] = VestTrack(doc.vest, doc, received, seen)
        # Before the order check: two senders on session clocks look "older" to each other.
        self._note_run(track, doc.run, seen)
        if not first and (doc.t < track.last.t or (doc.t == track.last.t and doc.index <= track.last.index)):
            # QoS 0 over one TCP connection keeps order, so an older message is a duplicate or a vest
            # that restarted its session clock. An older message must never replace a newer pose, so
            # it is counted and dropped, until a run of them shows a new timeline (or that the newest
            # was a corrupt time): then the vest is followed there.
            track.older_run += 1
            if track.older_run < cfg.timeline_reset_n:
                track.reordered += 1
                track.dropped_since += 1
                track.drop_reason = "older than the pose shown"
                return track
            track.timeline_resets += 1
            track.trail.clear()  # the old timeline's points would neither age out nor join the new ones
        track.older_run = track.dropped_since = 0
        track.messages += 1
        track.last, track.received, track.seen = doc, received, seen
        age = self.age_on_arrival(doc, received)
        track.last_age_s = age
        if age is not None and age > cfg.max_age_s:
            track.expired += 1
        if doc.state != "initialising":
            track.trail.append((doc.t, doc.x, doc.y))
            while track.trail and (len(track.trail) > cfg.trail_max or doc.t - track.trail[0][0] > cfg.trail_s):
                track.trail.popleft()
        return track

    def _note_run(self, track: VestTrack, run: str | None, seen: float) -> None:
        """Note the sender run of a message from ``track``'s vest, and whether it reveals two senders.

        One sender's messages carry one run; a restarted vest starts a new run and never goes back to
        the old one. So a message from a run first seen *before* the run of the message just before it
        means two senders are interleaving under one vest ID (two vests left at one ``--vest``): the
        poses shown jump between two people, which the robot manager must be told."""
        if run is None:
            return
        prev = track.last_run
        if prev is not None and run != prev and run in track.runs and track.runs[run] < track.runs[prev]:
            track.duplicate_seen = seen
            track.duplicate_switches += 1
        if run not in track.runs:
            track.runs[run] = seen
            while len(track.runs) > self.config.max_runs:
                del track.runs[min(track.runs, key=track.runs.get)]
        track.last_run = run

    def lead_s(self, doc: PoseDoc, received: float) -> tuple[str, float] | None:
        """(which time, seconds) of the message's time furthest ahead of its arrival, or None when the
        monitor's clock is not the epoch or the message has no epoch time.

        Both times are of the frame's grab, which precedes any arrival: ``t`` when on the epoch, and
        the grab on the vest's wall clock, ``wall_t`` less ``latency_ms`` (``wall_t`` alone without a
        latency). Less the latency, because a bag tagloc writes has the frame's ``t`` for its clock.
        """
        if not self.clock_is_epoch or received < EPOCH_MIN_S:
            return None
        times = [("'t'", doc.t)] if doc.t >= EPOCH_MIN_S else []
        if doc.wall_t is not None:
            if doc.latency_ms is None:
                times.append(("'wall_t'", doc.wall_t))
            else:
                times.append(("'wall_t' less 'latency_ms'", doc.wall_t - doc.latency_ms / 1e3))
        leads = [(which, v - received) for which, v in times]
        return max(leads, key=lambda kv: kv[1]) if leads else None

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
        """Vests to warn about at ``now`` on the staleness clock (``handle``'s ``seen``), stale first,
        then by vest ID."""
        cfg = self.config
        out: list[VestWarning] = []
        for vest in sorted(self.vests):
            tr = self.vests[vest]
            if tr.duplicate_seen is not None and now - tr.duplicate_seen <= cfg.duplicate_hold_s:
                out.append(
                    VestWarning(
                        vest,
                        "duplicate",
                        f"two senders use this vest ID (their messages interleaved {tr.duplicate_switches} times): "
                        "the pose shown jumps between them",
                    )
                )
            silent = now - tr.seen
            if silent > cfg.stale_s:
                bound = f"(bound {cfg.stale_s:g} s)"
                if tr.dropped_since:
                    # Messages do arrive: saying "no message" would send someone after the network.
                    text = f"no new pose for {silent:.2f} s {bound}: its {tr.dropped_since} messages since were {tr.drop_reason}"
                else:
                    text = f"no message for {silent:.2f} s {bound}"
                out.append(VestWarning(vest, "stale", text))
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
            if not tr.posed:
                # Not drawn (its x, y are zeros): without a warning, "all vests current and certain".
                out.append(VestWarning(vest, "initialising", "no pose yet: not on the map"))
            else:
                major = ellipse_2sigma(tr.last.cov)[0]
                if major > cfg.max_2sigma_m:
                    out.append(VestWarning(vest, "uncertain", f"2-sigma {major:.2f} m exceeds {cfg.max_2sigma_m:g} m"))
        order = {"duplicate": 0, "stale": 1, "expired": 2, "lost": 3, "initialising": 4, "uncertain": 5}
        return sorted(out, key=lambda w: (order[w.kind], w.vest))

    def counts(self) -> dict[str, int]:
        """Totals over the fleet: received, invalid, reordered, expired messages, vests seen and
        timeline resets (vests followed onto a restarted clock)."""
        return {
            "vests": len(self.vests),
            "received": self.received,
            "invalid": self.invalid,
            "reordered": sum(t.reordered for t in self.vests.values()),
            "expired": sum(t.expired for t in self.vests.values()),
            "timeline_resets": sum(t.timeline_resets for t in self.vests.values()),
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
    # '+' and '#' are MQTT wildcards and legal in the filter, but a URL parser takes a '#' for the start
    # of a fragment: the filter is all that follows HOST[:PORT].
    topic = url.split("://", 1)[1][len(u.netloc) :].lstrip("/") or default_topic
    levels = topic.split("/")
    for i, level in enumerate(levels):
        misplaced = ("+" in level and level != "+") or ("#" in level and (level != "#" or i < len(levels) - 1))
        if misplaced or "?" in level or "\0" in level:
            # paho raised it in its network thread (a traceback, then a monitor hearing nothing), or
            # the filter was cut at a '#' or '?' to one that matched no vest's topic.
            raise InputError(
                f"{url}: {topic!r} is not an MQTT topic filter ('+' stands for a whole level, '#' for the last; no '?')"
            )
    return u.hostname, port, topic


class FleetSubscriber:
    """Subscribe to vests' pose topics on an MQTT broker and feed a :class:`FleetState`.

    Connects out only (never listens), QoS 0, re-subscribes on every reconnection. Messages are
    handled in paho's network thread under ``lock``; read ``state`` under the same lock. Each is
    stamped with ``wall_clock()`` (``received``: its age) and ``clock()`` (``seen``: staleness; judge
    ``state.warnings`` on the same clock). ``on_message(track_or_None, payload, received)`` is
    called after each message (for measurements).
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
        self.wall_clock = time.time
        self.clock = time.monotonic
        self.hook_errors = 0  # on_message calls that raised (the network thread goes on)
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
        # paho's network thread dies with any exception raised here, and with it the subscription:
        # the monitor would go on showing every vest going stale. So nothing escapes.
        received, seen = self.wall_clock(), self.clock()
        with self.lock:
            try:
                track = self.state.handle(message.payload, received, seen)
            except Exception as exc:  # noqa: BLE001 - parse_message raises MessageError only; this is the backstop
                track = None
                self.state.refuse(f"could not handle a message: {type(exc).__name__}: {str(exc)[:120]}")
        if self._hook is not None:
            try:
                self._hook(track, message.payload, received)
            except Exception:  # noqa: BLE001 - a measurement hook must not stop the subscription either
                self.hook_errors += 1

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()
