"""Load test of the fleet path through a real MQTT broker, on loopback only.

    python benchmarks/fleet_load.py --vests 1,10,50,100 --rate 30 --seconds 60

For each vest count: starts mosquitto on 127.0.0.1 (a fresh broker per count), N simulated vests
that replay a recorded pose stream through tagloc's own MQTT sink (no vision: the stream is recorded
once by localising logs/walk2s), each at ``--rate`` messages/s with a random phase, spread over a few
publisher processes; and one monitor-side subscriber (tagloc.io.fleet.FleetSubscriber, headless)
that feeds a FleetState. Each message's ``t`` is its send time (epoch, as a live vest stamps), so
latency = receipt - t on the one machine clock. Prints, per count:

- sent: messages the vests' sinks handed to the broker connection; dropped at vest: refused by the
  sink (not connected, or more than ``max_pending`` unsent: the sink drops rather than queue);
- delivered: received by the subscriber; lost: sent - delivered (not arrived once the subscriber has
  been idle for DRAIN_S after the last send, or DRAIN_MAX_S at most);
- expired: delivered later than FleetConfig.max_age_s (0.5 s) after the frame;
- latency p50 / p99 / max (ms);
- broker CPU: mosquitto's CPU time over the publishing time (%); load: the machine's 1-minute load
  average at the end (other work on the machine shows here).

Nothing listens except mosquitto on 127.0.0.1. Runs are bounded by --seconds; use ``nice``.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import os
import random
import sys
import tempfile
import threading
import time
import zlib
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))  # the loopback broker the MQTT tests use

DRAIN_S = 3.0  # after the last send, wait until no message has arrived for this long ...
DRAIN_MAX_S = 120.0  # ... but no longer than this; what has not arrived by then is lost
PUBLISHER_PROCESSES = 4  # vests are spread over this many processes (a process per vest would swamp 2 cores)


def record_stream(path: Path) -> list[dict]:
    """Pose messages of logs/walk2s localised once (the vests replay these, shifted per vest)."""
    if path.exists():
        return [json.loads(line) for line in path.read_text().splitlines()]
    from tagloc.io.session import SessionReader
    from tagloc.io.sinks import PoseMessage
    from tagloc.pipeline.run import run_session

    docs: list[dict] = []
    session = SessionReader(REPO / "logs" / "walk2s")
    run_session(session, on_result=lambda r: docs.append(PoseMessage("vest", r.index, r.output).to_json()))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(json.dumps(d, separators=(",", ":")) + "\n" for d in docs))
    return docs


class _Encoded:
    """What MqttSink.publish needs of a message: its bytes and its age."""

    def __init__(self, data: bytes):
        self.data = data

    def encode(self) -> bytes:
        return self.data

    def age_s(self, now: float | None = None) -> float:
        """Made the moment it is published: no age (the sink's staleness bound never applies)."""
        return 0.0


def _publisher(port: int, vests: list[str], stream: list[dict], rate: float, seconds: float, go, out) -> None:
    """One process: several vests, each replaying ``stream`` at ``rate`` Hz for ``seconds`` once ``go`` is set."""
    from tagloc.io.sinks import MqttSink

    sinks = {v: MqttSink("127.0.0.1", port, f"tagloc/{v}/pose", client_id=v) for v in vests}
    deadline = time.monotonic() + 10
    while not all(s.connected for s in sinks.values()) and time.monotonic() < deadline:
        time.sleep(0.01)
    out.put(("ready", len(vests)))
    go.wait()  # every process connected: start together, so a slow start is not a burst
    start = time.time()
    rng = random.Random(zlib.crc32(",".join(vests).encode()))
    period = 1.0 / rate
    # Vests are not synchronised: each starts at a random phase within one period.
    nxt = {v: start + rng.random() * period for v in vests}
    count = {v: 0 for v in vests}
    offset = {v: (3.0 * (k % 10), 2.5 * (k // 10)) for k, v in enumerate(vests)}
    end = start + seconds
    while True:
        v = min(nxt, key=nxt.get)
        t_next = nxt[v]
        if t_next >= end:
            break
        delay = t_next - time.time()
        if delay > 0:
            time.sleep(delay)
        i = count[v]
        doc = dict(stream[i % len(stream)])
        doc.update(vest=v, index=i, t=round(time.time(), 6))
        doc["x"] = round(doc["x"] + offset[v][0], 5)
        doc["y"] = round(doc["y"] + offset[v][1], 5)
        sinks[v].publish(_Encoded(json.dumps(doc, separators=(",", ":")).encode()))
        count[v] = i + 1
        nxt[v] = t_next + period
    time.sleep(0.5)  # let the sinks' network threads write what is queued
    for s in sinks.values():
        s.close()
    out.put(("done", {v: (s.sent, s.dropped) for v, s in sinks.items()}))


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far (Linux /proc), s."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run_count(n: int, rate: float, seconds: float, stream: list[dict], workdir: Path) -> dict:
    """One load run with ``n`` vests; returns its figures."""
    from mosquitto import Broker

    from tagloc.io.fleet import FleetConfig, FleetState, FleetSubscriber

    broker = Broker(workdir).start()
    state = FleetState(FleetConfig())
    latencies: list[float] = []
    lock = threading.Lock()

    def on_message(track, payload, received):
        if track is not None:
            with lock:
                latencies.append(received - track.last.t)

    sub = FleetSubscriber("127.0.0.1", broker.port, "tagloc/+/pose", state, on_message=on_message)
    try:
        if not sub.subscribed.wait(10):
            raise RuntimeError("subscriber did not subscribe")
        vests = [f"v{k:03d}" for k in range(n)]
        groups = [vests[k::PUBLISHER_PROCESSES] for k in range(min(PUBLISHER_PROCESSES, n))]
        ctx = mp.get_context("spawn")
        q, go = ctx.Queue(), ctx.Event()
        procs = [ctx.Process(target=_publisher, args=(broker.port, g, stream, rate, seconds, go, q)) for g in groups]
        for p in procs:
            p.start()
        for _ in procs:
            q.get(timeout=120)  # "ready"
        go.set()
        counts: dict[str, tuple[int, int]] = {}
        for _ in procs:
            counts.update(q.get(timeout=seconds + 120)[1])
        for p in procs:
            p.join(timeout=30)
        # Drain: wait until nothing has arrived for DRAIN_S (messages still queued are not lost yet).
        last, quiet_since, give_up = -1, time.monotonic(), time.monotonic() + DRAIN_MAX_S
        while time.monotonic() < give_up and time.monotonic() - quiet_since < DRAIN_S:
            with sub.lock:
                got = state.received
            if got != last:
                last, quiet_since = got, time.monotonic()
            time.sleep(0.1)
        broker_cpu = _cpu_seconds(broker.proc.pid)
    finally:
        sub.close()
        broker.stop()
    with sub.lock:
        c = state.counts()
        delivered = sum(t.messages + t.reordered for t in state.vests.values())
    sent = sum(s for s, _ in counts.values())
    lat = np.array(latencies) * 1e3
    return {
        "vests": n,
        "rate_hz": rate,
        "seconds": seconds,
        "offered": int(round(n * rate * seconds)),
        "sent": sent,
        "dropped_at_vest": sum(d for _, d in counts.values()),
        "delivered": delivered,
        "lost": sent - delivered,
        "expired": c["expired"],
        "invalid": c["invalid"],
        "broker_cpu_s": broker_cpu,
        "load_average": os.getloadavg()[0],
        "latency_ms": {
            "p50": float(np.percentile(lat, 50)) if len(lat) else None,
            "p99": float(np.percentile(lat, 99)) if len(lat) else None,
            "max": float(lat.max()) if len(lat) else None,
        },
    }


def _vest_counts(text: str) -> list[int]:
    """``--vests``: comma-separated positive whole numbers."""
    try:
        counts = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"want comma-separated whole numbers, not {text!r}") from None
    if min(counts) < 1:
        raise argparse.ArgumentTypeError(f"vest counts must be at least 1, not {text!r}")
    return counts


def _positive(text: str) -> float:
    """A finite number above 0 (a rate or a duration: 0 or NaN left the publishers dividing by it or
    never starting, and the run waiting minutes for them)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"want a number, not {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"want a finite number above 0, not {text!r}")
    return value


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--vests", type=_vest_counts, default="1,10,50,100", help="vest counts, comma-separated (default 1,10,50,100)"
    )
    p.add_argument("--rate", type=_positive, default=30.0, help="messages per second per vest (default 30)")
    p.add_argument("--seconds", type=_positive, default=60.0, help="seconds of publishing per count (default 60)")
    p.add_argument("--stream", type=Path, default=REPO / "out" / "fleet_load" / "stream.jsonl", help="pose stream")
    p.add_argument("--json", type=Path, help="also write the figures as JSON")
    args = p.parse_args(argv)
    counts = args.vests
    stream = record_stream(args.stream)
    rows = []
    print(
        f"{'vests':>5} {'offered':>8} {'sent':>8} {'drop@vest':>9} {'delivered':>9} {'lost':>6} {'expired':>7} "
        f"{'p50 ms':>7} {'p99 ms':>7} {'max ms':>7} {'broker CPU':>10} {'load':>5}"
    )
    for n in counts:
        with tempfile.TemporaryDirectory() as tmp:
            r = run_count(n, args.rate, args.seconds, stream, Path(tmp))
        rows.append(r)
        lat = r["latency_ms"]
        print(
            f"{n:>5} {r['offered']:>8} {r['sent']:>8} {r['dropped_at_vest']:>9} {r['delivered']:>9} {r['lost']:>6} "
            f"{r['expired']:>7} {lat['p50']:>7.2f} {lat['p99']:>7.2f} {lat['max']:>7.1f} "
            f"{100 * r['broker_cpu_s'] / args.seconds:>9.1f}% {r['load_average']:>5.1f}",
            flush=True,
        )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("fleet_load.py", main))
