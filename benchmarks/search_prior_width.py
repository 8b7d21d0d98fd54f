"""How wide the region search's prior is, in a replay's order and in ``tagloc live``'s.

The localiser searches for stickers near where the tracker predicts them
(:meth:`tracker.tracker.Tracker.search_prior`). In live's order (``LocaliserConfig.defer_odometry``)
a frame's odometry step is fused after the search; this prints, for each order, the median over the
frames of the prior's position sigma (the square root of the largest eigenvalue of its (x, y)
covariance) as the search takes it, beside what :meth:`~tracker.tracker.Tracker.prior` (the
covariance predicted to the frame, with the walking model's noise for the interval) would give.

Example::

    tagloc simulate --map maps/demo.csv --seconds 20 --lux 300 --seed 1 -o out/walk300 --quiet
    python benchmarks/search_prior_width.py out/walk300
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

import numpy as np

from tagloc.io.session import SessionReader
from tagloc.pipeline.localiser import Localiser, LocaliserConfig
from tracker.ekf import largest_eig_2x2
from tracker.tracker import Tracker


def prior_widths(session: Path, live_order: bool) -> np.ndarray:
    """(K, 2) position sigmas (m) at each of the K region searches: the search prior's, prior()'s."""
    reader = SessionReader(session)
    widths: list[tuple[float, float]] = []
    search_prior = Tracker.search_prior

    def recorded(self: Tracker):
        out = search_prior(self)
        if out is not None:
            widths.append((math.sqrt(largest_eig_2x2(out[1])), math.sqrt(largest_eig_2x2(self.prior()[1]))))
        return out

    Tracker.search_prior = recorded  # type: ignore[method-assign]
    try:
        config = dataclasses.replace(LocaliserConfig(), defer_odometry=live_order)
        loc = Localiser(reader.map, reader.rig, config=config, map_path=session / "map.csv")
        for frame in reader.frames():
            loc.process(frame)
            if live_order:
                loc.deferred_work()  # as the live loop does after publishing the frame
    finally:
        Tracker.search_prior = search_prior  # type: ignore[method-assign]
    return np.array(widths).reshape(-1, 2)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("session", type=Path, help="session directory (tagloc simulate ... -o DIR)")
    args = p.parse_args(argv)
    print(f"{'order':<16} {'searches':>8} {'search prior, mm':>17} {'prior(), mm':>12}")
    for name, live in (("a replay's", False), ("tagloc live's", True)):
        w = prior_widths(args.session, live) * 1e3
        print(f"{name:<16} {len(w):>8} {np.median(w[:, 0]):>17.1f} {np.median(w[:, 1]):>12.1f}")
    return 0


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("search_prior_width.py", main))
