"""``tagloc live`` on a core too slow for its camera: what its load shedding keeps.

A Pi-class core is 3-5x slower than one core of this machine. Here the camera is made 3-5x faster
instead: the session's frames, decoded ahead into memory, are delivered by a camera-like source
(its own clock, the newest frame kept, as ``tagloc live`` takes a camera) at ``--slowdown`` times
the session's rate, their timestamps unchanged, so the localiser has a third to a fifth of a frame
interval per frame, as on such a core at the session's rate. Everything runs on one pinned core
(``--core``), OpenCV on one thread.

For each slowdown, live's loop runs with its load shedding (``LiveConfig.stride_when_behind``:
while frames wait, the odometry strides and skips the floor flow after frames that read fixes
placed, see ``LocaliserConfig.skip_flow_after_fix``) and without it. Per run: frames processed and
dropped by the capture, odometry steps strided and flows skipped, grab-to-publication latency, and
the published poses against the session's ground truth: RMSE over the frames with a pose, and the
share of *all* the session's frames published within 10 cm (a dropped frame publishes nothing).
Per setting, ``over 10 cm`` counts the runs whose RMSE is over 10 cm (or that published no pose):
a run whose track went wrong, which a median over runs hides (on the field walk f01 at 5x, 1-2 of
6 runs, 2026-12-01; see the README's Speed section). ``NEES``: the runs' mean position NEES (2 DoF),
and ``overconfident`` counts the runs above their own effective-sample bound (``tagloc eval``'s
verdict; over one 20 s walk that bound is wide), and ``beyond 99.9 %`` is the share of frames
whose NEES is past chi^2's 99.9 % point (13.8), 0.1 % for a consistent filter: a track that went
wrong while it stated itself sure, which a robot manager cannot see.

Run (from the repository root)::

    tagloc simulate --map maps/demo.csv --seconds 20 --lux 300 --seed 1 -o out/walk300 --quiet
    PYTHONPATH=$PWD python benchmarks/load_shedding.py out/walk300 --slowdown 1,3,4,5 --repeat 3
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np


def run_once(session: Path, slowdown: float, shed: bool) -> dict:
    """One live run of ``session`` delivered ``slowdown`` times faster than its rate, with or without
    load shedding: counts, latency and the published poses' errors."""
    import tagloc.apps.live as live
    from tagloc.eval.consistency import nees_blocks, nees_test
    from tagloc.eval.metrics import error_metrics, trajectory_errors
    from tagloc.io.capture import FrameSource
    from tagloc.io.session import SessionReader

    reader = SessionReader(session)
    frames = list(reader.frames())
    fps = (reader.info.fps or 30.0) * slowdown

    class FastCamera(FrameSource):
        """The frames from memory on the source's own clock at ``fps`` (a camera: never waited for)."""

        live = True
        end_reason = "end of frames"

        def __init__(self) -> None:
            self.fps = fps
            self._i = 0
            self._t0: float | None = None

        def read(self):
            if self._i >= len(frames):
                return None
            now = time.monotonic()
            if self._t0 is None:
                self._t0 = now
            delay = self._t0 + self._i / self.fps - now
            if delay > 0:
                time.sleep(delay)
            frame = frames[self._i]
            self._i += 1
            return frame

    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "frames.jsonl"
        cfg = live.LiveConfig(source="memory", config_dir=session, log=log, stride_when_behind=shed)
        loc = live._make_localiser(cfg)
        summary = live.run_live(cfg, localiser=loc, source=FastCamera())
        lines = [json.loads(line) for line in log.read_text().splitlines()]
    outs = [d["output"] for d in lines if not d.get("late") and d["output"]["state"] != "initialising"]
    stamps = np.array([o["t"] for o in outs])
    poses = np.array([[o["x"], o["y"], o["yaw"]] for o in outs]).reshape(-1, 3)
    covs = np.array([o["cov"] for o in outs]).reshape(-1, 3, 3)
    e = trajectory_errors(stamps, poses, covs, *reader.groundtruth())
    counts = loc.stats()
    # The run judged by its own effective-sample bounds, as tagloc eval judges a walk.
    test = nees_test(nees_blocks(e.stamps, e.nees))
    return {
        "slowdown": slowdown,
        "shed": shed,
        "frames": len(frames),
        "processed": summary.frames,
        "dropped": summary.capture.dropped,
        "strided": counts.get("odometry_strided", 0),
        "flow_skipped": counts.get("flow_skipped", 0),
        "fixes": summary.fixes,
        "p50_ms": summary.latency(50),
        "p99_ms": summary.latency(99),
        "rmse_cm": float(np.sqrt(np.mean(e.position**2)) * 100) if len(e.position) else float("nan"),
        "within_10cm_of_all": float(np.sum(e.position < 0.10) / len(frames)),
        "nees": test.mean,
        "nees_verdict": test.verdict,
        "beyond_999": error_metrics(e)["beyond_999"],
    }


def _spread(values: list[float], fmt: str = "{:.2f}") -> str:
    """The median of ``values`` and their range, ``median (min-max)`` (an even count's median the
    mean of the middle two: it was the upper one)."""
    return f"{fmt.format(float(np.median(values)))} ({fmt.format(min(values))}-{fmt.format(max(values))})"


def _over(runs: list[dict], limit_cm: float = 10.0) -> str:
    """``n/N``: how many of the ``runs`` came out over ``limit_cm`` RMS, or with no pose at all (NaN)."""
    bad = sum(not r["rmse_cm"] <= limit_cm for r in runs)
    return f"{bad}/{len(runs)}"


def _overconfident(runs: list[dict]) -> str:
    """``n/N``: how many of the ``runs`` stated their position as surer than it was (mean position
    NEES above the run's own effective-sample bound, ``tagloc eval``'s verdict)."""
    return f"{sum(r['nees_verdict'] == 'overconfident' for r in runs)}/{len(runs)}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("session", type=Path, help="session directory with groundtruth.tum")
    p.add_argument("--slowdown", default="1,3,4,5", help="camera rate multiples (default 1,3,4,5)")
    p.add_argument("--repeat", type=int, default=3, help="runs of each (default 3)")
    p.add_argument("--core", type=int, default=0, help="CPU core to pin to (default 0; -1: no pinning)")
    p.add_argument("--json", type=Path, help="write every run's figures as JSON")
    args = p.parse_args(argv)
    from replay_cost import _check_run_options

    from tagloc.cli import checks

    # Checked before any run: a bad value was a ValueError or ZeroDivisionError, reported as a bug.
    slowdowns = checks.numbers(args.slowdown, "--slowdown", 0.0, math.inf, lo_open=True)
    core = _check_run_options(args.repeat, args.core)
    if core is not None:
        os.sched_setaffinity(0, {core})
    cv2.setNumThreads(1)
    runs = []
    print(f"tagloc live on {args.session}, the camera k times faster (a core k times slower), {args.repeat} runs each")
    print(
        f"{'k':>4} {'shedding':>8} {'processed':>10} {'dropped':>8} {'strided':>8} {'flow skip':>9} "
        f"{'p99 ms':>20} {'RMSE cm':>20} {'<10 cm of all':>22} {'over 10 cm':>10} {'NEES':>20} {'overconfident':>13} "
        f"{'beyond 99.9 %':>14}"
    )
    for k in slowdowns:
        for shed in (True, False):
            rs = [run_once(args.session, k, shed) for _ in range(args.repeat)]
            runs += rs
            print(
                f"{k:>4g} {'on' if shed else 'off':>8} {_spread([r['processed'] for r in rs], '{:g}'):>10} "
                f"{_spread([r['dropped'] for r in rs], '{:g}'):>8} {_spread([r['strided'] for r in rs], '{:g}'):>8} "
                f"{_spread([r['flow_skipped'] for r in rs], '{:g}'):>9} {_spread([r['p99_ms'] for r in rs]):>20} "
                f"{_spread([r['rmse_cm'] for r in rs]):>20} "
                f"{_spread([100 * r['within_10cm_of_all'] for r in rs], '{:.1f}'):>22} {_over(rs):>10} "
                f"{_spread([r['nees'] for r in rs]):>20} {_overconfident(rs):>13} "
                f"{_spread([100 * r['beyond_999'] for r in rs], '{:.1f}'):>14}",
                flush=True,
            )
    if args.json is not None:
        args.json.write_text(json.dumps(runs, indent=1))
    return 0


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("load_shedding.py", main))
