"""How far off are the sticker fixes the tracker accepts, and does their stated covariance say so?

Replays each simulated session with the localiser as it is and compares every accepted fix that
has one pose solution (the vest point's (x, y), :class:`tagloc.core.types.PoseFix`) with the
simulator's truth at that frame: its position error and its NEES against the fix's own covariance
(2 DoF: 2 on average if the covariance is honest, above 2 overconfident). The fixes are binned by
the sticker's motion blur in image pixels (:func:`tagloc.vision.decode.blur_extent`, measured on
its frame edges) and split by identity source.

A fix is solved as if the map were exact (the tracker carries the sticker's survey error as a
state), so on walks whose map has survey error the error against the truth is mostly the map's.
``--true-map`` localises with the session's ``map_true.csv`` instead (the simulator writes it for
such walks), which leaves the fixes' own error.

Example::

    python benchmarks/fix_error.py out/eval/standard/sessions/*
    python benchmarks/fix_error.py out/eval/field/sessions/* --true-map
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from tqdm import tqdm

from tagloc.core.stickermap import load_map
from tagloc.io.session import SessionReader
from tagloc.pipeline.localiser import Localiser, LocaliserConfig, _shortest_side
from tagloc.pipeline.run import iterate_results
from tagloc.vision.decode import blur_extent
from tagloc.vision.decode.grid import RASTER_PX
from tagloc.vision.image import as_gray

_MAX_TRUTH_GAP_S = 0.02  # a fix is compared with a ground-truth pose at most this far in time
_BLUR_BINS_PX = ((0, 1), (1, 2), (2, 4), (4, 8), (8, np.inf))


def fixes(session: Path, true_map: bool) -> list[tuple[str, float, float, float, float]]:
    """(source, blur px, error m, NEES, stated sigma m) of each accepted single-solution fix."""
    reader = SessionReader(session)
    gt_t, gt = reader.groundtruth()
    truth_map = session / "map_true.csv"
    smap = load_map(truth_map) if true_map and truth_map.exists() else reader.map
    # A different map's identification references are made in memory, not cached beside the session's.
    loc = Localiser(smap, reader.rig, LocaliserConfig(), map_path=None if smap is not reader.map else reader.map_path)
    out = []
    for res in tqdm(iterate_results(reader, loc), desc=session.name, unit="frame", leave=False):
        if res.frame is None or res.frame.image is None:
            continue
        i = int(np.argmin(np.abs(gt_t - res.timestamp)))
        if abs(gt_t[i] - res.timestamp) > _MAX_TRUTH_GAP_S:
            continue
        gray = as_gray(res.frame.image)
        for obs in res.observations:
            fix = obs.fix
            if fix is None or fix.accepted is not True or len(fix.poses) != 1:
                continue
            d = fix.poses[0].body[:2] - gt[i][:2, 3]
            cov = fix.poses[0].cov[:2, :2]
            lx, ly = blur_extent(gray, obs.detection, reader.rig[res.frame.camera].camera)
            blur_px = float(np.hypot(lx, ly)) * _shortest_side(obs.detection.outer) / RASTER_PX
            nees = float(d @ np.linalg.solve(cov, d))
            out.append((obs.source.value, blur_px, float(np.hypot(*d)), nees, float(np.sqrt(np.trace(cov)))))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sessions", type=Path, nargs="+", help="simulated sessions (with groundtruth.tum)")
    p.add_argument("--true-map", action="store_true", help="localise with each session's map_true.csv")
    args = p.parse_args(argv)
    rows = [r for s in args.sessions for r in fixes(s, args.true_map)]
    if not rows:
        print("no accepted fixes")
        return 0
    src = np.array([r[0] for r in rows])
    blur, err, nees, sigma = (np.array([r[k] for r in rows]) for k in range(1, 5))
    print(f"{len(rows)} accepted single-solution fixes in {len(args.sessions)} sessions")
    print("blur (image px)   fixes   RMS error cm   stated sigma cm (RMS)   mean NEES (2 if honest)")
    for lo, hi in _BLUR_BINS_PX:
        m = (blur >= lo) & (blur < hi)
        if m.any():
            label = f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">= {lo:g}"
            print(
                f"{label:>15s}  {m.sum():6d}  {np.sqrt(np.mean(err[m] ** 2)) * 100:12.2f}"
                f"  {np.sqrt(np.mean(sigma[m] ** 2)) * 100:21.2f}  {nees[m].mean():22.2f}"
            )
    for s in sorted(set(src)):
        m = src == s
        print(
            f"{s:>15s}  {m.sum():6d}  {np.sqrt(np.mean(err[m] ** 2)) * 100:12.2f}"
            f"  {np.sqrt(np.mean(sigma[m] ** 2)) * 100:21.2f}  {nees[m].mean():22.2f}"
            f"   (blur median {np.median(blur[m]):.1f} px)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
