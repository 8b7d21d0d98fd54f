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

Each fix is compared with the truth at its own time: on a rolling-shutter camera a sticker is
solved for the time its rows were read (the fix's ``row_time_s``, from
:attr:`tagloc.vision.pose.PoseSolution.row_time_s`: up to 15 ms from the frame's time at a 30 ms
read-out, 2 cm of walking), so the truth is interpolated to it. A second table bins the fixes by the vest point's distance from the sticker, with the error
split along that line (radial: its mean says whether the fixes read the sticker too near or too
far) and across it, each against the stated sigma in that direction.

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
_RANGE_BINS_M = ((0, 1), (1, 1.5), (1.5, 2), (2, 2.5), (2.5, np.inf))


def fixes(session: Path, true_map: bool) -> list[tuple]:
    """(source, blur px, error m, NEES, stated sigma m, distance m, radial error m, across error m,
    stated radial sigma m, stated across sigma m) of each accepted single-solution fix."""
    reader = SessionReader(session)
    gt_t, gt = reader.groundtruth()
    gt_xy = np.array([T[:2, 3] for T in gt]).reshape(-1, 2)
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
            rig_camera = reader.rig[res.frame.camera]
            t_fix = res.timestamp + fix.row_time_s
            truth = np.array([np.interp(t_fix, gt_t, gt_xy[:, k]) for k in (0, 1)])
            body = fix.poses[0].body[:2]
            d = body - truth
            cov = fix.poses[0].cov[:2, :2]
            lx, ly = blur_extent(gray, obs.detection, rig_camera.camera)
            blur_px = float(np.hypot(lx, ly)) * _shortest_side(obs.detection.outer) / RASTER_PX
            nees = float(d @ np.linalg.solve(cov, d))
            lever = body - smap.xy[smap.row(obs.sticker_id)]
            dist = float(np.hypot(*lever))
            u = lever / max(dist, 1e-9)
            v = np.array([-u[1], u[0]])
            out.append(
                (
                    obs.source.value,
                    blur_px,
                    float(np.hypot(*d)),
                    nees,
                    float(np.sqrt(np.trace(cov))),
                    dist,
                    float(d @ u),
                    float(d @ v),
                    float(np.sqrt(u @ cov @ u)),
                    float(np.sqrt(v @ cov @ v)),
                )
            )
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
    blur, err, nees, sigma, dist, rad, across, sig_rad, sig_across = (
        np.array([r[k] for r in rows]) for k in range(1, 10)
    )
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
    print("\nby the vest point's distance from the sticker (cm; radial: along the line to the sticker, + away)")
    print("distance m   fixes   mean NEES   radial mean   radial RMS / stated   across RMS / stated")
    for lo, hi in _RANGE_BINS_M:
        m = (dist >= lo) & (dist < hi)
        if m.any():
            label = f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">= {lo:g}"
            r_rad, r_sig_rad, r_across, r_sig_across = (
                float(np.sqrt(np.mean(x[m] ** 2))) * 100 for x in (rad, sig_rad, across, sig_across)
            )
            print(
                f"{label:>10s}  {m.sum():6d}  {nees[m].mean():10.2f}  {rad[m].mean() * 100:+12.2f}"
                f"  {r_rad:10.2f} / {r_sig_rad:<8.2f}  {r_across:10.2f} / {r_sig_across:.2f}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
