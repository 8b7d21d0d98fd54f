"""What ``tagloc live``'s deferred least-squares decoding costs in accuracy: each session replayed
twice by the same localiser, as a replay runs it (every decode inside its frame) and as ``tagloc
live`` runs it (``LocaliserConfig(defer_lsq=True, defer_odometry=True)``, the deferred decodes and
the frame's odometry step run after each frame, as the live loop runs them while it waits for the
next frame), with the scores ``tagloc eval`` gives:
RMSE, share of frames within 10 cm, heading RMSE, mean NEES, wrong-ID fixes against the simulator's
ground truth, the fixes the tracker fused, and the accepted fixes of the published frames by source
(a deferred detection's fix is fused before the next frame but was not in its own frame's output); and the per-frame CPU time (mean, p99) without the
deferred work, which is what sets the latency from grab to publication.

Run (on sessions made by ``tagloc eval`` or ``tagloc simulate``)::

    PYTHONPATH=$PWD python benchmarks/live_defer.py SESSION [SESSION ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
import types
from pathlib import Path

import cv2
import numpy as np

import tagloc.pipeline.localiser as localiser_mod
from tagloc.eval.evaluate import wrong_id_fixes
from tagloc.eval.metrics import error_metrics, trajectory_errors
from tagloc.io.session import SessionReader
from tagloc.pipeline.localiser import Localiser, LocaliserConfig
from tagloc.pipeline.run import run_session


class _AsLive:
    """A localiser whose deferred work runs right after each frame, as the live loop runs it; the
    frame's own CPU time (what delays its publication) is kept apart."""

    def __init__(self, loc: Localiser):
        self.loc, self.map, self.rig, self.counts = loc, loc.map, loc.rig, loc.counts
        self.frame_cpu_ms: list[float] = []

    def process(self, frame):
        c0 = time.thread_time()
        res = self.loc.process(frame)
        self.frame_cpu_ms.append((time.thread_time() - c0) * 1e3)
        self.loc.deferred_work()
        # What the frame's deferred work finished, with it (see run_session), as the live loop logs
        # it: handed out with the next frame, the last frame's fused fixes were in no run log.
        return dataclasses.replace(res, late=list(self.loc.late))

    def stats(self) -> dict[str, int]:
        return self.loc.stats()


def run(session: Path, defer: bool) -> dict:
    """Scores of one replay of ``session`` (``defer``: as ``tagloc live`` runs the localiser)."""
    reader = SessionReader(session)
    loc = _AsLive(
        Localiser(
            reader.map, reader.rig, LocaliserConfig(defer_lsq=defer, defer_odometry=defer), map_path=session / "map.csv"
        )
    )
    log = run_session(reader, localiser=loc)
    v = log.valid
    m = error_metrics(trajectory_errors(log.stamps[v], log.poses[v], log.covs[v], *reader.groundtruth()))
    wrong, _ = wrong_id_fixes(session, log)
    by_source: dict[str, int] = {}
    for fx in log.fixes:
        by_source[fx["source"]] = by_source.get(fx["source"], 0) + 1
    cpu = np.array(loc.frame_cpu_ms)
    return {
        "rmse_cm": 100 * m["rmse_m"],
        "within_10cm": 100 * m["within_10cm"],
        "heading_deg": m["heading_rmse_deg"],
        "nees": m["nees_mean"],
        "fixes": by_source,
        "wrong": wrong,
        "cpu_mean_ms": float(cpu.mean()),
        "cpu_p99_ms": float(np.percentile(cpu, 99)),
        "fused": sum(v for k, v in loc.stats().items() if k.startswith("tracker_accepted_")),
        "deferred": loc.counts.get("lsq_deferred", 0),
        "deferred_named": loc.counts.get("deferred_named", 0),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sessions", type=Path, nargs="+", help="session directories with ground truth")
    args = p.parse_args(argv)
    cv2.setNumThreads(1)
    # The stage clock becomes this thread's CPU clock (as benchmarks/replay_cost.py does).
    localiser_mod.time = types.SimpleNamespace(perf_counter=time.thread_time)
    print(
        f"{'session':<10} {'decodes':<14} {'RMSE cm':>8} {'<10 cm':>7} {'head deg':>8} {'NEES':>6} {'wrong':>5}"
        f" {'CPU mean':>8} {'p99 ms':>7} {'fused':>5}  fixes published (deferred decodes, named)"
    )
    for s in args.sessions:
        for defer in (False, True):
            r = run(s, defer)
            fixes = " ".join(f"{k}:{v}" for k, v in sorted(r["fixes"].items()))
            print(
                f"{s.name:<10} {'after frame' if defer else 'in frame':<14} {r['rmse_cm']:8.2f} {r['within_10cm']:6.1f}%"
                f" {r['heading_deg']:8.2f} {r['nees']:6.2f} {r['wrong']:5d} {r['cpu_mean_ms']:8.2f} {r['cpu_p99_ms']:7.2f} {r['fused']:5d}"
                f"  {fixes}" + (f" ({r['deferred']}, {r['deferred_named']})" if defer else "")
            )
    return 0


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("live_defer.py", main))
