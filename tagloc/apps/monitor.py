"""``tagloc monitor``: every vest on the warehouse map, live from MQTT or from a recorded bag.

Live: subscribes (connects out; never listens) to ``mqtt://HOST:PORT/tagloc/+/pose``, feeds each
message to a :class:`tagloc.io.fleet.FleetState` and redraws the fleet in Rerun ``refresh_hz`` times a
second. From a bag: the ``/tagloc/*/pose_json`` (or ``/tagloc/*/pose``) messages in bag-time order,
the bag's clock standing in for the monitor's.

Live, staleness and the redraw and print schedules follow ``time.monotonic()``; the wall clock
(``time.time()``) is only shown and compared with the vests' clocks, so an NTP step of the host's
clock neither keeps a silent vest current nor stops the status lines.
"""

from __future__ import annotations

import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from tagloc.core.errors import InputError
from tagloc.core.stickermap import load_map
from tagloc.io.fleet import EPOCH_MIN_S, FleetConfig, FleetState, FleetSubscriber, parse_mqtt_url
from tagloc.io.sinks import unique_client_id


@dataclass
class MonitorConfig:
    """What ``tagloc monitor`` does.

    Attributes:
        url: ``mqtt://HOST[:PORT][/TOPIC]`` to subscribe to (topic filter default ``tagloc/+/pose``).
        from_bag: rosbag2/ROS 1 bags with tagloc pose topics (e.g. one per vest), instead of ``url``;
            their messages are merged in bag-time order.
        map: sticker map CSV drawn under the vests.
        save: .rrd file to record; spawn: start a viewer; connect: viewer URL. None of them: no viewer
            (the warnings still go to ``report``).
        fleet: staleness, uncertainty and drawing bounds.
        refresh_hz: redraws per second (monitor clock).
        max_seconds: stop after this long (live only).
        print_every_s: print the fleet's counts and warnings to stdout this often (live; None: never).
        png: write the fleet as it is at the end as a PNG (matplotlib; the same content as the view).
    """

    map: Path
    url: str | None = None
    from_bag: list[Path] = field(default_factory=list)
    save: Path | None = None
    spawn: bool = False
    connect: str | None = None
    fleet: FleetConfig = field(default_factory=FleetConfig)
    refresh_hz: float = 10.0
    max_seconds: float | None = None
    png: Path | None = None
    print_every_s: float | None = None


def status_text(state: FleetState, now: float, wall: float | None = None) -> str:
    """One block of text: the time, the fleet's counts and one line per warning (for a terminal).

    ``now``: the staleness clock (as given to ``state.handle``); ``wall``: epoch seconds shown
    (default ``now``).
    """
    c = state.counts()
    warnings = state.warnings(now)
    resets = f", {c['timeline_resets']} timeline resets" if c["timeline_resets"] else ""
    head = (
        f"{time.strftime('%H:%M:%S', time.localtime(now if wall is None else wall))} {c['vests']} vests, "
        f"{len(warnings)} warnings; {c['received']} messages ({c['invalid']} invalid, {c['expired']} expired{resets})"
    )
    lines = [head] + [f"  {w.vest}: {w.kind}: {w.text}" for w in warnings]
    if state.last_error:
        lines.append(f"  last invalid message: {state.last_error}")
    return "\n".join(lines)


@dataclass
class MonitorSummary:
    """End of a monitor run: the fleet's counters and the warnings at the end."""

    counts: dict
    warnings: list
    seconds: float
    broker: str | None = None  # why the broker's messages may be missing (live), else None
    broker_reached: bool = True  # False: a live monitor never reached its broker (the CLI exits 1)
    last_error: str | None = None  # why the last invalid message was refused

    def format(self) -> str:
        c = self.counts
        lines = [
            f"{c['vests']} vests; {c['received']} messages ({c['invalid']} invalid, {c['reordered']} out of order, "
            f"{c['expired']} expired; {c['timeline_resets']} timeline resets) in {self.seconds:.1f} s"
        ]
        if self.last_error is not None:
            lines.append(f"last invalid message: {self.last_error}")
        if self.broker is not None:
            lines.append(f"warning: {self.broker}")
        lines += [f"warning: {w.vest}: {w.kind}: {w.text}" for w in self.warnings]
        return "\n".join(lines)


def run_monitor(
    cfg: MonitorConfig, stop: threading.Event | None = None, subscribed: threading.Event | None = None
) -> MonitorSummary:
    """Run the monitor until ``max_seconds``, SIGINT/SIGTERM or ``stop`` (live), or the bag's end.

    ``subscribed`` is set once the broker has acknowledged the subscription (live).
    """
    if (cfg.url is None) == (not cfg.from_bag):
        raise InputError("give either an mqtt:// URL or --from-bag BAG")
    if cfg.print_every_s is not None and not cfg.print_every_s > 0:
        raise InputError(f"--print-every must be positive, not {cfg.print_every_s}")
    if not cfg.refresh_hz > 0:
        raise InputError(f"--refresh must be positive, not {cfg.refresh_hz}")
    smap = load_map(cfg.map)
    view = None
    if cfg.save or cfg.spawn or cfg.connect:
        from tagloc.io.fleet_view import FleetView

        view = FleetView(smap, save=cfg.save, spawn=cfg.spawn, connect=cfg.connect)
    t0 = time.monotonic()
    try:
        broker, reached = None, True
        if cfg.from_bag:
            state, now = _from_bag(cfg, view)
        else:
            state, now, broker, reached = _live(cfg, view, stop or threading.Event(), subscribed)
    finally:
        if view is not None:
            view.close()
    if cfg.png is not None:
        from tagloc.io.fleet_plot import plot_fleet

        plot_fleet(state, smap, now, cfg.png)
    return MonitorSummary(state.counts(), state.warnings(now), time.monotonic() - t0, broker, reached, state.last_error)


def _from_bag(cfg: MonitorConfig, view) -> tuple[FleetState, float]:
    import heapq

    from tagloc.io.rosbag import read_pose_messages

    state = FleetState(cfg.fleet)
    period = 1.0 / cfg.refresh_hz
    next_draw = None
    now = 0.0
    for msg in heapq.merge(*(read_pose_messages(b) for b in cfg.from_bag), key=lambda m: m.t_bag):
        now = msg.t_bag
        if msg.error is not None:
            state.received += 1
            state.refuse(msg.error)
        else:
            state.handle(msg.doc, now)
        if next_draw is None:
            next_draw = now
        if view is not None and now >= next_draw:
            view.update(state, now, timestamp=now > EPOCH_MIN_S)
            next_draw = now + period
    if view is not None and state.vests:
        view.update(state, now, timestamp=now > EPOCH_MIN_S)
    return state, now


def _live(
    cfg: MonitorConfig, view, stop: threading.Event, subscribed: threading.Event | None
) -> tuple[FleetState, float, str | None, bool]:
    """Follow the broker until stopped: (the fleet, the time on its staleness clock, a note if the
    broker was not reached or was lost, whether it was ever reached)."""
    host, port, topic = parse_mqtt_url(cfg.url)
    state = FleetState(cfg.fleet)
    sub = FleetSubscriber(host, port, topic, state, client_id=unique_client_id("tagloc-monitor"), subscribed=subscribed)
    restore = _stop_on_signals(stop)
    # The subscriber stamps staleness with time.monotonic(): ``now`` below is on the same clock.
    t0 = time.monotonic()
    period = 1.0 / cfg.refresh_hz
    next_print = t0 + (cfg.print_every_s or 0.0)
    try:
        while not stop.is_set():
            now, wall = time.monotonic(), time.time()
            if cfg.max_seconds is not None and now - t0 >= cfg.max_seconds:
                break
            with sub.lock:
                if view is not None:
                    view.update(state, now, wall=wall)
                if cfg.print_every_s and now >= next_print:
                    print(status_text(state, now, wall), flush=True)
                    if not sub.connected.is_set():
                        print(f"  not connected to the broker {host}:{port} (retrying)", flush=True)
                    next_print = now + cfg.print_every_s
            stop.wait(period)
    except KeyboardInterrupt:
        pass
    finally:
        restore()
        # Read before closing: the close disconnects.
        ever, still = sub.ever_connected.is_set(), sub.connected.is_set()
        sub.close()
    note = None
    if not ever:
        note = f"never connected to the broker {host}:{port}: no vest's messages were received"
    elif not still:
        note = f"the connection to the broker {host}:{port} was lost before the end"
    return state, time.monotonic(), note, ever


def _stop_on_signals(stop: threading.Event):
    """SIGTERM sets ``stop`` (main thread only); returns the function restoring the old handler."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    old = signal.signal(signal.SIGTERM, lambda signum, frame: stop.set())
    return lambda: signal.signal(signal.SIGTERM, old)
