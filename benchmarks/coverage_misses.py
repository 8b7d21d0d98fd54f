"""Where a walk's frames miss the 10 cm bar, and why.

``tagloc eval`` counts a frame as a miss when it has no pose or one more than 10 cm off. This
replays each simulated session with the localiser as it is (``tagloc eval``'s ``full`` mode) and
splits its frames, by the simulator's per-frame truth (``groundtruth_frames.jsonl``), into:

- ``before sticker``: before a mapped sticker first lies wholly in the image (no localiser has a
  pose there without one given from outside: the ``(reachable)`` column of ``tagloc eval``);
- ``to first pose``: after that, before the localiser's first pose (no sticker read yet);
- ``no pose later``: after the first pose, frames without one (skipped or lost frames);
- ``over 10 cm``: frames with a pose more than 10 cm from the truth;
- ``within``: the rest.

Example::

    python benchmarks/coverage_misses.py out/eval/standard/sessions/*
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from tagloc.core.errors import InputError
from tagloc.eval.evaluate import score_session
from tagloc.eval.metrics import gt_covers, trajectory_errors

#: The bar ``tagloc eval``'s "<10 cm of all frames" counts against (m).
BAR_M = 0.10
COLUMNS = ("before sticker", "to first pose", "no pose later", "over 10 cm", "within")


def misses(path: Path) -> dict[str, int]:
    """The frames of the session at ``path`` that its ground truth covers, counted by
    :data:`COLUMNS` (see the module)."""
    row, _, log, gt = score_session(path, "full", progress=False)
    if row["frames_before_sticker"] is None:
        raise InputError(f"{path}: wants groundtruth_frames.jsonl (a simulated session)")
    covered = gt_covers(log.stamps, gt[0])
    k = np.arange(len(log.stamps))
    posed = np.flatnonzero(log.valid & covered)
    first_pose = int(posed[0]) if len(posed) else len(k)
    first_covered = int(np.flatnonzero(covered)[0]) if covered.any() else len(k)
    sticker_at = first_covered + row["frames_before_sticker"]
    err = np.full(len(k), np.nan)
    e = trajectory_errors(log.stamps[posed], log.poses[posed], log.covs[posed], *gt)
    err[posed[e.inside]] = e.position
    valid = log.valid & covered
    counts = {
        "before sticker": covered & (k < sticker_at),
        "to first pose": covered & (k >= sticker_at) & (k < first_pose),
        "no pose later": covered & (k >= first_pose) & ~log.valid,
        "over 10 cm": valid & (err > BAR_M),
        "within": valid & (err <= BAR_M),
    }
    return {name: int(np.sum(m)) for name, m in counts.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sessions", nargs="+", type=Path, help="simulated session directories")
    args = ap.parse_args(argv)
    total = dict.fromkeys(COLUMNS, 0)
    print(f"{'walk':14s} {'frames':>6s} " + " ".join(f"{c:>14s}" for c in COLUMNS))
    for path in args.sessions:
        row = misses(path)
        n = sum(row.values())
        for c in COLUMNS:
            total[c] += row[c]
        print(f"{path.name:14s} {n:6d} " + " ".join(f"{row[c]:14d}" for c in COLUMNS))
    n = sum(total.values())
    print(f"{'all':14s} {n:6d} " + " ".join(f"{total[c]:14d}" for c in COLUMNS))
    if n:
        print(
            f"within 10 cm: {100 * total['within'] / n:.2f} % of all frames; the most any localiser can place"
            f" (after a sticker is in view): {100 * (1 - total['before sticker'] / n):.2f} %"
        )
    return 0


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("coverage_misses.py", main))
