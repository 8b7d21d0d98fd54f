"""Time candidate selection and the tracker's per-frame work on a 100,000-sticker map.

Run from the repository root, as the README runs the benchmarks: ``PYTHONPATH=$PWD python
benchmarks/bench_candidates.py [--n 100000] [--calls 2000]``.
The map is a jittered 1.5 m grid (stickers 1.2-1.8 m apart, ~470 m square). Prints median and
95th-percentile wall time per call.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from tagloc.core.rig import default_rig
from tagloc.core.stickermap import StickerMap
from tagloc.core.types import IdSource, PoseFix
from tagloc.pipeline.run import single_threaded
from tracker.candidates import project_map, select_candidates
from tracker.tracker import Tracker


def _stats(name: str, times: list[float]) -> None:
    t = np.array(times) * 1e3
    print(f"{name:32s} median {np.median(t):.3f} ms   p95 {np.percentile(t, 95):.3f} ms   (n={len(t)})")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=100_000, help="stickers in the random map (at least 9)")
    ap.add_argument("--calls", type=int, default=2000, help="timed calls per measurement")
    args = ap.parse_args(argv)
    from tagloc.cli import checks

    # The poses keep 2 m inside the map's square: a 3 x 3 grid (4.5 m) at least. Fewer stickers, or
    # no calls, were a ValueError or IndexError reported as a bug.
    checks.number(args.n, "--n", 9)
    checks.number(args.calls, "--calls", 1)
    rng = np.random.default_rng(1)
    side = math.ceil(math.sqrt(args.n))
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[: args.n] * 1.5
    smap = StickerMap(np.arange(args.n), g + rng.uniform(-0.3, 0.3, g.shape), rng.uniform(-np.pi, np.pi, args.n))
    rc = default_rig()[0]
    extent = side * 1.5
    cov = np.diag([0.2**2, 0.2**2, math.radians(6) ** 2])

    cases = []
    while len(cases) < args.calls:
        truth = np.array([rng.uniform(2, extent - 2), rng.uniform(2, extent - 2), rng.uniform(-np.pi, np.pi)])
        pr = project_map(truth, smap, rc)
        if pr.in_image.any():
            k = int(rng.choice(np.flatnonzero(pr.in_image)))
            cases.append((truth + rng.multivariate_normal(np.zeros(3), cov), pr.pixels[k], int(pr.ids[k])))

    # Timed as the localiser runs: BLAS's idle threads spin, and on a busy machine count in its time.
    with single_threaded():
        select_candidates(cases[0][0], cov, smap, rc, cases[0][1])  # warm the footprint cache
        times, hits, sizes = [], 0, []
        for prior, px, true_id in cases:
            t0 = time.perf_counter()
            ids = select_candidates(prior, cov, smap, rc, px, k=5)
            times.append(time.perf_counter() - t0)
            hits += true_id in ids
            sizes.append(len(ids))
        _stats("select_candidates", times)
        print(
            f"{'':32s} true sticker listed in {hits / len(cases):.1%} of calls, mean list length {np.mean(sizes):.2f}"
        )

        times = []
        for prior, _, _ in cases:
            t0 = time.perf_counter()
            project_map(prior, smap, rc)
            times.append(time.perf_counter() - t0)
        _stats("project_map (all visible)", times)

        tr = Tracker()
        fix = PoseFix(np.eye(4), np.zeros(3), np.diag([1e-4, 1e-4, 1e-4]), 0.3)
        t_pred, t_upd, t_out = [], [], []
        for i in range(args.calls):
            t = i / 30.0
            a = time.perf_counter()
            tr.predict(t)
            b = time.perf_counter()
            if i % 10 == 0:
                fix.body = np.array([1.3 * t, 0.0, 0.0]) + rng.normal(0, 0.02, 3)
                tr.update([fix], i, IdSource.DECODED, t)
            c = time.perf_counter()
            tr.output(t)
            d = time.perf_counter()
            t_pred.append(b - a)
            t_out.append(d - c)
            if i % 10 == 0:
                t_upd.append(c - b)
        _stats("Tracker.predict (30 fps)", t_pred)
        _stats("Tracker.update (one fix)", t_upd)
        _stats("Tracker.output", t_out)


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("bench_candidates.py", main))
