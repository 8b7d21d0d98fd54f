"""How honest the tracker's stated uncertainty stays while the camera sees nothing.

A lens covered by a sleeve or a hand, a camera pointed at a wall, a stretch of glare: for a while no
sticker and no floor texture, and the tracker has only its walking model. Where the walk turns, the
model carries the last turn rate on into the blind span, the heading drifts by a radian or more and
the (x, y) ellipse, oriented by that heading, can be thin exactly where the walker is.

Each session is replayed once per blind span: the frames of the span replaced by a dark, noisy
image (a covered lens: grey level 2 +- 1.5, seeded), the rest as recorded; with ``--stall``, left
out instead (a camera that delivered no frame at all: the tracker then predicts across the whole
span at once). Spans of each
``--durations`` start every ``--every`` s from ``--start`` s on. Scored are the frames from the
span's start to ``--tail`` s after its end, against the simulator's truth: horizontal error, and
the position NEES (2 DoF) of the published pose (its mean 2 if honest; a single frame's above
5.99 one time in 20). Each span is run with the default configuration and with each
``--variant NAME=JSON`` (dotted settings, as ``benchmarks/eval_variants.py`` takes them), so the
table shows what a setting does.

Run from the repository root on sessions with ground truth (e.g. ``tagloc eval``'s)::

    PYTHONPATH=$PWD python benchmarks/blind_spans.py out/eval/standard/sessions/* \\
        out/eval/field/sessions/f0[012] --jobs 2 \\
        --variant 'filter-ellipse={"tracker.heading_widening": false}' \\
        --variant 'steps-always={"tracker.odometry_max_yaw_sd": 100}'
"""

from __future__ import annotations

import argparse
import json
import math
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from eval_variants import variant_configs  # (benchmarks/ is on the path of a script run from it)

from tagloc.cli import checks
from tagloc.core.types import Frame
from tagloc.eval.metrics import trajectory_errors
from tagloc.io.session import SessionReader
from tagloc.pipeline.localiser import Localiser, LocaliserConfig
from tagloc.pipeline.run import single_threaded

#: Single-frame 95 % point of chi-square with 2 DoF: an honest filter exceeds it one frame in 20.
CHI2_2_95 = 5.991
#: Grey level of a covered lens (mean, sd): dark sensor noise, nothing to detect or track.
DARK_LEVEL = (2.0, 1.5)


def _blind_runs(args: tuple[str, list[float], float, float, float, dict[str, LocaliserConfig], bool]) -> list[dict]:
    path, durations, start, every, tail, variants, stall = args
    session = SessionReader(Path(path))
    gt = session.groundtruth()
    frames = [f for f in session.frames() if f.image is not None]
    t0, t1 = frames[0].timestamp, frames[-1].timestamp
    rows = []
    for dur in durations:
        s = t0 + start
        while s + dur + tail <= t1:
            for name, cfg in variants.items():
                rows.append(
                    _one(session, frames, gt, s, s + dur, tail, cfg, stall)
                    | {"walk": path, "duration": dur, "variant": name}
                )
            s += every
    return rows


def _one(
    session: SessionReader,
    frames: list[Frame],
    gt,
    a: float,
    b: float,
    tail: float,
    cfg: LocaliserConfig,
    stall: bool = False,
) -> dict:
    loc = Localiser(session.map, session.rig, cfg, map_path=session.map_path)
    rng = np.random.default_rng(0)
    T, P, C = [], [], []
    with single_threaded():
        for f in frames:
            if f.timestamp > b + tail:
                break
            img = f.image
            if a <= f.timestamp < b:
                if stall:
                    continue
                img = np.clip(rng.normal(*DARK_LEVEL, img.shape), 0, 255).astype(np.uint8)
            o = loc.process(Frame(f.index, f.timestamp, img, camera=f.camera)).output
            if f.timestamp >= a and o.state.value != "initialising":
                T.append(f.timestamp), P.append(o.pose), C.append(o.cov)
    e = trajectory_errors(np.array(T), np.array(P).reshape(-1, 3), np.array(C).reshape(-1, 3, 3), *gt)
    return {
        "start": a,
        "frames": int(len(e.nees)),
        "sq": float(np.sum(e.position**2)),
        "nees_sum": float(np.sum(e.nees)),
        "nees_max": float(np.max(e.nees)) if len(e.nees) else 0.0,
        "over95": int(np.sum(e.nees > CHI2_2_95)),
        "max_err": float(np.max(e.position)) if len(e.position) else 0.0,
    }


def summarise(rows: list[dict]) -> str:
    """The table: per blind duration and variant, pooled over spans and walks."""
    names = list(dict.fromkeys(r["variant"] for r in rows))
    w = max(7, *(len(n) for n in names))
    lines = [
        f"blind s  {'variant':<{w}}  spans  frames  RMSE cm  max err cm  mean NEES  max NEES  frames NEES>5.99",
        f"-------  {'-' * w}  -----  ------  -------  ----------  ---------  --------  ----------------",
    ]
    for dur in sorted({r["duration"] for r in rows}):
        for name in names:
            sel = [r for r in rows if r["duration"] == dur and r["variant"] == name]
            n = sum(r["frames"] for r in sel)
            if not n:
                continue
            lines.append(
                f"{dur:7.1f}  {name:<{w}}  {len(sel):5d}  {n:6d}  "
                f"{100 * math.sqrt(sum(r['sq'] for r in sel) / n):7.1f}  "
                f"{100 * max(r['max_err'] for r in sel):10.1f}  {sum(r['nees_sum'] for r in sel) / n:9.2f}  "
                f"{max(r['nees_max'] for r in sel):8.1f}  {100 * sum(r['over95'] for r in sel) / n:15.1f}%"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Replay each session with blind spans; print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sessions", nargs="+", help="session directories with groundtruth.tum")
    ap.add_argument("--durations", default="0.5,1,2", help="blind span lengths, s (comma-separated)")
    ap.add_argument("--start", type=float, default=2.0, help="first span's start after the first frame, s")
    ap.add_argument("--every", type=float, default=4.0, help="spans start this often, s")
    ap.add_argument("--tail", type=float, default=1.0, help="frames scored after a span's end, s")
    ap.add_argument("--jobs", type=int, default=1, help="sessions replayed in parallel")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME=JSON", help="settings to compare")
    ap.add_argument("--stall", action="store_true", help="leave the span's frames out instead of darkening them")
    ap.add_argument("--json", type=Path, help="write every span's row here")
    a = ap.parse_args(argv)
    durations = list(checks.numbers(a.durations, "--durations", 0.0, math.inf, lo_open=True))
    if a.every <= 0 or a.tail < 0:
        ap.error("--every must be positive, --tail not negative")
    variants = variant_configs(a.variant)
    for s in a.sessions:
        if not (Path(s) / "groundtruth.tum").is_file():
            ap.error(f"{s}: no groundtruth.tum")
    jobs = [(s, durations, a.start, a.every, a.tail, variants, a.stall) for s in a.sessions]
    with ProcessPoolExecutor(max_workers=max(1, a.jobs)) as pool:
        rows = [r for part in pool.map(_blind_runs, jobs) for r in part]
    print(summarise(rows))
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("blind_spans.py", main))
