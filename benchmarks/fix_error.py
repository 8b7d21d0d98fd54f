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

``--survey`` instead splits each walk's error in the frames with an accepted fix: the tracker's
output there, the fixes, the error the map's survey alone puts into them (a sticker surveyed off by
(dx, dy, dyaw) moves a fix of the vest point p by (dx, dy) + (R(dyaw) - I)(p - s), s its true centre:
the yaw error's lever to the vest point), and the fixes less that (their own error). The tracker
below the fixes says how much of the survey error it took out with the odometry between stickers.

Example::

    python benchmarks/fix_error.py out/eval/standard/sessions/*
    python benchmarks/fix_error.py out/eval/field/sessions/* --true-map
    python benchmarks/fix_error.py out/eval/field/sessions/* --survey
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


def _accepted_fixes(res, gt_t: np.ndarray, gt_xy: np.ndarray):
    """(observation, fix, true vest point (2,) m at the fix's own time) of each accepted
    single-solution fix of the frame result ``res``; ``gt_t`` (N,) s and ``gt_xy`` (N, 2) m the truth."""
    for obs in res.observations:
        fix = obs.fix
        if fix is None or fix.accepted is not True or len(fix.poses) != 1:
            continue
        t_fix = res.timestamp + fix.row_time_s
        yield obs, fix, np.array([np.interp(t_fix, gt_t, gt_xy[:, k]) for k in (0, 1)])


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
        for obs, fix, truth in _accepted_fixes(res, gt_t, gt_xy):
            rig_camera = reader.rig[res.frame.camera]
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


def survey_share(session: Path) -> dict[str, float]:
    """RMS errors (m) over the frames of ``session`` with an accepted single-solution fix of a
    sticker in both maps: the tracker's output (``track``), the fixes (``fixes``), the survey's part
    of the fixes (``survey``) and the fixes less it (``own``), with the frames counted
    (``frames``) and the tracker over all its frames (``all``). Needs the simulator's
    ``map_true.csv``."""
    reader = SessionReader(session)
    truth_path = session / "map_true.csv"
    if not truth_path.exists():
        raise SystemExit(f"{truth_path}: no true map (the simulator writes one for walks with survey error)")
    true_map, smap = load_map(truth_path), reader.map
    gt_t, gt = reader.groundtruth()
    gt_xy = np.array([T[:2, 3] for T in gt]).reshape(-1, 2)
    loc = Localiser(smap, reader.rig, LocaliserConfig(), map_path=reader.map_path)
    sq = {"all": [], "track": [], "fixes": [], "survey": [], "own": []}
    for res in tqdm(iterate_results(reader, loc), desc=session.name, unit="frame", leave=False):
        i = int(np.argmin(np.abs(gt_t - res.timestamp)))
        if (
            abs(gt_t[i] - res.timestamp) > _MAX_TRUTH_GAP_S
            or res.output is None
            or res.output.state.value != "tracking"
        ):
            continue
        err = res.output.pose[:2] - gt_xy[i]
        sq["all"].append(err @ err)
        per_fix = []
        for obs, fix, p in _accepted_fixes(res, gt_t, gt_xy):
            if obs.sticker_id not in smap or obs.sticker_id not in true_map:
                continue
            r_map, r_true = smap.row(obs.sticker_id), true_map.row(obs.sticker_id)
            dyaw = smap.yaw[r_map] - true_map.yaw[r_true]
            c, sn = np.cos(dyaw), np.sin(dyaw)
            lever = p - true_map.xy[r_true]
            survey = smap.xy[r_map] - true_map.xy[r_true] + np.array([[c, -sn], [sn, c]]) @ lever - lever
            per_fix.append((fix.poses[0].body[:2] - p, survey))
        if per_fix:
            fix_err, survey = (np.mean([f[k] for f in per_fix], axis=0) for k in (0, 1))
            for key, e in (("track", err), ("fixes", fix_err), ("survey", survey), ("own", fix_err - survey)):
                sq[key].append(e @ e)
    out = {k: float(np.sqrt(np.mean(v))) if v else float("nan") for k, v in sq.items()}
    return out | {"frames": float(len(sq["track"]))}


def _print_survey_table(sessions: list[Path]) -> None:
    print("RMS error, cm: the tracker over all its frames, then over the frames with an accepted fix")
    print(
        f"{'walk':<12s} {'all':>6s} {'frames':>7s} {'tracker':>8s} {'fixes':>6s} {'survey':>7s} {'fixes less survey':>18s}"
    )
    for s in sessions:
        r = survey_share(s)
        print(
            f"{s.name:<12s} {r['all'] * 100:6.2f} {int(r['frames']):7d} {r['track'] * 100:8.2f} {r['fixes'] * 100:6.2f}"
            f" {r['survey'] * 100:7.2f} {r['own'] * 100:18.2f}"
        )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sessions", type=Path, nargs="+", help="simulated sessions (with groundtruth.tum)")
    p.add_argument("--true-map", action="store_true", help="localise with each session's map_true.csv")
    p.add_argument("--survey", action="store_true", help="instead: how much of each walk's error is the survey's")
    args = p.parse_args(argv)
    if args.survey:
        _print_survey_table(args.sessions)
        return 0
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
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("fix_error.py", main))
