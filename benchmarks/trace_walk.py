"""One walk replayed frame by frame against its ground truth: where the track leaves the truth, what
the filter said of itself there, and what the localiser and tracker did in each frame.

Run (from the repository root)::

    PYTHONPATH=$PWD python benchmarks/trace_walk.py out/eval/field/sessions/f01 --from 16.5 --to 18
    PYTHONPATH=$PWD python benchmarks/trace_walk.py SESSION --config '{"tracker.blind_turn_max_rad": 0}'

Per frame in the window (session time, s): the horizontal position error (cm), the position NEES (2
DoF; chi-square's 99.9 % point is 13.8), the heading error and its stated standard deviation (deg),
and every localiser and tracker counter that changed in that frame (``+n``; the tracker's prefixed
``t.``): fixes accepted or refused by source, odometry steps fused, missed steps, blind-span
widenings, and so on. ``--config``: a JSON object of dotted settings, as ``eval_variants.py``'s
``--variant``. Frames without a pose (before the first fix, skipped frames) print ``-``.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from tagloc.core.errors import InputError
from tagloc.eval.metrics import trajectory_errors
from tagloc.io.session import SessionReader
from tagloc.pipeline.localiser import Localiser

#: Counters that change in (almost) every frame and say nothing of it.
QUIET = frozenset({"frames", "tracker_predictions"})


def trace(session: Path, overrides: dict, start: float = -math.inf, end: float = math.inf) -> list[dict]:
    """One row per frame with a timestamp in [``start``, ``end``] (s): ``t``, ``error_cm``, ``nees``,
    ``heading_error_deg``, ``heading_sd_deg`` (NaN without a pose or ground truth) and ``counts`` (the
    counters that changed in the frame, by how much)."""
    from eval_variants import configure  # the same dotted settings as the variants'

    cfg = configure(overrides, "--config")
    reader = SessionReader(session)
    truth = reader.groundtruth()
    if truth is None:
        raise InputError(f"{session}: no groundtruth.tum to trace against")
    loc = Localiser(reader.map, reader.rig, cfg, map_path=reader.map_path)
    before = dict(loc.stats())
    rows, posed = [], []  # posed: (row, pose (3,), covariance (3, 3)) of the frames with a pose
    for frame in reader.frames():
        res = loc.process(frame)
        now = loc.stats()
        changed = {k: v - before.get(k, 0) for k, v in now.items() if v != before.get(k, 0) and k not in QUIET}
        before = dict(now)
        if not start <= res.timestamp <= end:
            continue
        row = {"t": res.timestamp, "error_cm": math.nan, "nees": math.nan}
        row |= {"heading_error_deg": math.nan, "heading_sd_deg": math.nan, "counts": changed}
        rows.append(row)
        if res.output.pose is not None and res.skipped is None:
            posed.append((row, res.output.pose, res.output.cov))
    if posed:
        # Scored as tagloc eval scores a run (the same interpolation, coverage and NEES).
        e = trajectory_errors(
            np.array([r["t"] for r, _, _ in posed]),
            np.array([p for _, p, _ in posed], float),
            np.array([c for _, _, c in posed], float),
            *truth,
        )
        scored = [(row, cov) for (row, _, cov), ok in zip(posed, e.inside) if ok]
        for (row, cov), pos, nees, yaw in zip(scored, e.position, e.nees, e.yaw):
            row["error_cm"], row["nees"] = 100.0 * float(pos), float(nees)
            row["heading_error_deg"] = math.degrees(float(yaw))
            row["heading_sd_deg"] = math.degrees(math.sqrt(float(cov[2, 2])))
    return rows


def format_row(row: dict) -> str:
    """One printed line of :func:`trace`'s row."""

    def num(x: float, fmt: str) -> str:
        return format(x, fmt) if math.isfinite(x) else "-".rjust(len(format(0.0, fmt)))

    counts = " ".join(f"{k.replace('tracker_', 't.')}+{v}" for k, v in sorted(row["counts"].items()))
    return (
        f"{row['t']:8.3f} {num(row['error_cm'], '7.1f')} {num(row['nees'], '7.1f')}"
        f" {num(row['heading_error_deg'], '7.1f')} {num(row['heading_sd_deg'], '6.1f')}  {counts}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("session", type=Path, help="session directory with groundtruth.tum")
    ap.add_argument("--from", dest="start", type=float, default=-math.inf, help="first session time, s")
    ap.add_argument("--to", dest="end", type=float, default=math.inf, help="last session time, s")
    ap.add_argument("--config", default="{}", help='dotted settings, e.g. {"tracker.gate": 16}')
    ap.add_argument("--json", type=Path, help="also write the rows here")
    args = ap.parse_args(argv)
    from eval_variants import json_object

    rows = trace(args.session, json_object(args.config, "--config", "dotted settings"), args.start, args.end)
    print(f"{'t s':>8s} {'err cm':>7s} {'NEES':>7s} {'hdg deg':>7s} {'sd deg':>6s}  counters changed")
    for row in rows:
        print(format_row(row))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    import sys

    # eval_variants (the settings' parser) sits beside this script.
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("trace_walk.py", main))
