"""Soak benchmark: ``tagloc live`` for a long time, publishing over MQTT to a real mosquitto that is
restarted and hung (SIGSTOP) on the way. Not a test: it takes minutes and measures.

Run: ``nice python benchmarks/soak.py [--minutes 10] [--bucket 60] [--max-age 0.5]``
(from the repository root, with the venv's python; mosquitto must be installed).

What it does: simulates a short walk once (``--sim-seconds`` at ``--fps``, cached in ``--work``),
plays it in a loop as if from a camera (frames at their own rate, dropped when processing falls
behind, timestamps continuing across loops) through the real live loop and localiser, and publishes
every pose to a mosquitto on a free loopback port, read back by a subscriber. At 40% of the run
the broker is stopped for ``--restart-gap`` s and started again (a restart); at 70% it is
SIGSTOPped for ``--hang`` s (a partition: TCP stays up, nothing answers).

Prints per bucket (default a minute): frames processed, frames dropped by capture, latency p50/p99
(grab to publication), RSS; then the messages: published (written to the socket), confirmed by
the broker, unconfirmed, dropped (of which stale), received by the subscriber, and received later
than ``--max-age`` after publication (what a receiver checking ``wall_t`` would discard).
"""

from __future__ import annotations

import argparse
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

import numpy as np

from tagloc.apps.live import LiveConfig, _make_localiser, run_live
from tagloc.core.types import Frame
from tagloc.io.capture import FrameSource
from tagloc.io.session import SessionReader
from tagloc.pipeline.localiser import Localiser
from tagloc.sim.simulate import SimConfig, simulate_session

REPO = Path(__file__).resolve().parent.parent
#: The localiser's counters of the work live puts after publication or sheds when behind, reported.
SHED = ("lsq_deferred", "deferred_fixes", "odometry_strided", "flow_skipped")


class LoopSource(FrameSource):
    """A session's frames, in memory, played again and again with the clock running on."""

    live = False

    def __init__(self, session: SessionReader):
        frames = [f for f in session.frames() if f.image is not None]
        self.images = [f.image for f in frames]
        self.stamps = np.array([f.timestamp for f in frames])
        self.fps = session.info.fps or 10.0
        self.period = float(self.stamps[-1] - self.stamps[0]) + 1.0 / self.fps
        self.k = 0

    def read(self) -> Frame | None:
        n = len(self.images)
        loop, i = divmod(self.k, n)
        frame = Frame(self.k, float(self.stamps[i] - self.stamps[0] + loop * self.period), self.images[i])
        self.k += 1
        return frame


class Broker:
    """mosquitto on 127.0.0.1:port, restartable on the same port."""

    def __init__(self, work: Path):
        exe = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
        if not Path(exe).exists():
            sys.exit("soak: mosquitto is not installed (scripts/setup installs it)")
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.exe = exe
        self.conf = work / "mosquitto.conf"
        self.conf.write_text(f"listener {self.port} 127.0.0.1\nallow_anonymous true\npersistence false\n")
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [self.exe, "-c", str(self.conf)], stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT
        )
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2).close()
                return
            except OSError:
                time.sleep(0.05)
        raise RuntimeError("mosquitto did not start")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(timeout=10)


class Subscriber:
    """Counts poses received and those received later than ``max_age`` after publication."""

    def __init__(self, port: int, topic: str, max_age: float):
        import paho.mqtt.client as mqtt

        self.max_age = max_age
        self.received = self.late = 0
        self.lock = threading.Lock()
        self.client = mqtt.Client(callback_api_version=mqtt.CallbackAPIVersion.VERSION2)
        self.client.reconnect_delay_set(1, 1)
        self.client.on_connect = lambda c, u, f, rc, p: c.subscribe(topic, qos=0)
        self.client.on_message = self._on
        self.client.connect_async("127.0.0.1", port, keepalive=60)
        self.client.loop_start()

    def _on(self, client, userdata, message) -> None:
        doc = json.loads(message.payload)
        with self.lock:
            self.received += 1
            if doc.get("wall_t") is not None and time.time() - doc["wall_t"] > self.max_age:
                self.late += 1

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def timed(loc: Localiser) -> list[float]:
    """Note when ``loc`` finishes each frame (to bucket the live loop's latencies): its ``process``
    wrapped on the instance, so that the live loop still finds the localiser's deferred work,
    ``behind`` and ``warm_up`` as ``tagloc live`` does (a wrapper object offering ``process`` alone
    had run every frame's work before publishing and never shed load). Returns the list of times."""
    done: list[float] = []
    process = loc.process

    def timed_process(frame: Frame):
        res = process(frame)
        done.append(time.monotonic())
        return res

    loc.process = timed_process
    return done


def rss_mb() -> float:
    """Resident set size of this process, MB (Linux /proc)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=10.0, help="length of the soak (default 10)")
    ap.add_argument("--bucket", type=float, default=60.0, help="seconds per table row (default 60)")
    ap.add_argument("--max-age", type=float, default=0.5, help="pose age bound of the MQTT sink, s (default 0.5)")
    ap.add_argument("--restart-gap", type=float, default=3.0, help="broker down for this long at 40%% (s)")
    ap.add_argument("--hang", type=float, default=6.0, help="broker SIGSTOPped for this long at 70%% (s)")
    ap.add_argument("--sim-seconds", type=float, default=10.0, help="length of the looped walk (default 10 s)")
    ap.add_argument("--fps", type=float, default=10.0, help="frame rate of the looped walk (default 10)")
    ap.add_argument("--work", type=Path, default=REPO / "out" / "soak", help="work directory (default out/soak)")
    ap.add_argument("--json", type=Path, help="also write the figures as JSON")
    return ap.parse_args()


def prepare(args: argparse.Namespace) -> tuple[LoopSource, Localiser, list[float]]:
    """The looped walk (simulated once, cached), and the localiser ``tagloc live`` makes for it
    (reference bank ready, the least-squares decodes and odometry deferred) with its list of frame
    finishing times (:func:`timed`)."""
    args.work.mkdir(parents=True, exist_ok=True)
    sess_dir = args.work / f"walk_{args.sim_seconds:g}s_{args.fps:g}fps"
    if not (sess_dir / "frames.csv").exists():
        shutil.rmtree(sess_dir, ignore_errors=True)
        print(f"soak: simulating a {args.sim_seconds:g} s walk at {args.fps:g} fps into {sess_dir}", file=sys.stderr)
        simulate_session(
            REPO / "maps" / "demo.csv", sess_dir, SimConfig(seconds=args.sim_seconds, fps=args.fps, seed=1)
        )
    session = SessionReader(sess_dir)
    loc = _make_localiser(LiveConfig(source="soak-loop", config_dir=sess_dir))
    return LoopSource(session), loc, timed(loc)


class Chaos:
    """Restarts the broker at 40% of the run, hangs it at 70%, and samples RSS, in background threads."""

    def __init__(self, broker: Broker, seconds: float, args: argparse.Namespace):
        self.broker, self.seconds, self.args = broker, seconds, args
        self.stop = threading.Event()
        self.rss: list[tuple[float, float]] = []
        self.events: list[str] = []
        self.t0 = time.monotonic()
        self.threads = [threading.Thread(target=f, daemon=True) for f in (self._chaos, self._sample_rss)]
        for th in self.threads:
            th.start()

    def _at(self, frac: float) -> bool:
        return not self.stop.wait(max(0.0, self.t0 + frac * self.seconds - time.monotonic()))

    def _chaos(self) -> None:
        a, b = self.args, self.broker
        if self._at(0.4):
            self.events.append(f"{time.monotonic() - self.t0:.0f} s: broker stopped for {a.restart_gap:g} s (restart)")
            b.stop()
            if self.stop.wait(a.restart_gap):
                return
            b.start()
        if self._at(0.7):
            self.events.append(f"{time.monotonic() - self.t0:.0f} s: broker hung (SIGSTOP) for {a.hang:g} s")
            os.kill(b.proc.pid, signal.SIGSTOP)
            self.stop.wait(a.hang)
            os.kill(b.proc.pid, signal.SIGCONT)

    def _sample_rss(self) -> None:
        while True:
            self.rss.append((time.monotonic() - self.t0, rss_mb()))
            if self.stop.wait(min(self.args.bucket, 10.0)):
                return

    def end(self) -> None:
        self.stop.set()
        for th in self.threads:
            th.join(timeout=5)


def buckets(done: np.ndarray, lat: np.ndarray, rss: list[tuple[float, float]], seconds: float, width: float) -> list:
    """Per-bucket frames, latency p50/p99 (ms) and peak RSS (MB)."""
    rows = []
    for b in range(int(np.ceil(seconds / width))):
        lo, hi = b * width, (b + 1) * width
        sel = (done >= lo) & (done < hi)
        r = [m for t, m in rss if lo <= t < hi]
        rows.append(
            {
                "from_s": lo,
                "frames": int(sel.sum()),
                "latency_p50_ms": float(np.percentile(lat[sel], 50)) if sel.any() else float("nan"),
                "latency_p99_ms": float(np.percentile(lat[sel], 99)) if sel.any() else float("nan"),
                "rss_mb": float(max(r)) if r else float("nan"),
            }
        )
    return rows


def report(result: dict, max_age: float) -> None:
    print(
        f"soak: {result['seconds']:.0f} s, {result['frames']} frames processed, "
        f"{result['capture_dropped']} dropped by capture"
    )
    for e in result["events"]:
        print(f"  event at {e}")
    print(f"{'from':>6} {'frames':>7} {'p50 ms':>8} {'p99 ms':>8} {'RSS MB':>8}")
    for r in result["rows"]:
        print(
            f"{r['from_s']:>5.0f}s {r['frames']:>7d} {r['latency_p50_ms']:>8.1f} {r['latency_p99_ms']:>8.1f} "
            f"{r['rss_mb']:>8.1f}"
        )
    print("localiser: " + ", ".join(f"{k} {v}" for k, v in result["localiser"].items()))
    m = result["messages"]
    print(
        f"messages: published {m['sent']} (broker confirmed {m['confirmed']}, unconfirmed {m['unconfirmed']}), "
        f"dropped {m['dropped']} (stale {m['stale']}); subscriber received {m['received']}, "
        f"of which later than {max_age:g} s after publication {m['received_late']}; warnings {result['warnings']}"
    )


def main() -> None:
    args = parse_args()
    seconds = args.minutes * 60.0
    source, loc, done = prepare(args)
    broker = Broker(args.work)
    broker.start()
    topic = "tagloc/soak/pose"
    sub = Subscriber(broker.port, topic, args.max_age)
    chaos = Chaos(broker, seconds, args)
    cfg = LiveConfig(
        source="soak-loop",
        publish=[f"mqtt://127.0.0.1:{broker.port}/{topic}"],
        max_seconds=seconds,
        max_age_s=args.max_age,
    )
    try:
        summary = run_live(cfg, localiser=loc, stop=chaos.stop, source=source)
    finally:
        chaos.end()
        time.sleep(1.0)
        sub.close()
        if broker.proc is not None and broker.proc.poll() is None:
            os.kill(broker.proc.pid, signal.SIGCONT)
        broker.stop()
    sink = next(iter(summary.outputs.sinks.values()))
    result = {
        "seconds": summary.seconds,
        "frames": summary.frames,
        "capture_dropped": summary.capture.dropped,
        "rows": buckets(np.array(done) - chaos.t0, summary.latency_ms, chaos.rss, seconds, args.bucket),
        "events": chaos.events,
        "messages": {**sink, "received": sub.received, "received_late": sub.late},
        "warnings": summary.outputs.warnings,
        "localiser": {k: loc.counts[k] for k in SHED},
    }
    report(result, args.max_age)
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("soak.py", main))
