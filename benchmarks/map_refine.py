"""Map refinement measured: survey-error map against refined map, and the localiser with each.

The floor is one aisle of 15 stickers 0.5 m apart (the test's site); the audited map has survey
errors (2 cm radial RMS, 2 deg), one sticker moved by 15 cm, one mapped sticker missing from the
floor and one floor sticker not mapped. Three walks refine the map; they and two fresh walks are
then localised with the survey-error map, the refined map and the true map.

    nice python benchmarks/map_refine.py -o out/map_refine [--seconds 8]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from tagloc.core.stickermap import StickerMap, load_map, save_map
from tagloc.eval.mapbench import map_bench, survey_error_map
from tagloc.sim.simulate import SimConfig, simulate_session

MISSING, UNMAPPED, MOVED = 1007, 1011, 1004


def aisle() -> StickerMap:
    xs = np.arange(0.0, 7.01, 0.5)
    ids = np.arange(1000, 1000 + len(xs))
    yaw = np.radians(np.resize([0.0, 90.0, 35.0, 180.0, -60.0, 120.0], len(ids)))
    return StickerMap(ids, np.c_[xs, np.zeros_like(xs)], yaw)


def without(smap: StickerMap, sid: int) -> StickerMap:
    keep = smap.ids != sid
    return StickerMap(smap.ids[keep], smap.xy[keep], smap.yaw[keep])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--out", type=Path, default=Path("out/map_refine"))
    ap.add_argument("--seconds", type=float, default=8.0)
    args = ap.parse_args()
    truth = aisle()
    floor = without(truth, MISSING)
    sessions = []
    for seed in (1, 2, 3, 4, 5):
        path = args.out / f"walk{seed}"
        if not (path / "groundtruth.tum").exists():
            cfg = SimConfig(seconds=args.seconds, lux=150, speed_mps=1.0, seed=seed)
            simulate_session(floor, path, cfg, progress=True)
        sessions.append(path)
    save_map(truth, args.out / "true.csv")
    survey = survey_error_map(without(truth, UNMAPPED), 0.02, 2.0, seed=5, moved={MOVED: (0.09, 0.12)})
    save_map(survey, args.out / "survey.csv")
    survey = load_map(args.out / "survey.csv")
    truth_in_survey = without(truth, UNMAPPED)
    res = map_bench(truth_in_survey, survey, sessions[:3], sessions[3:], [MOVED], progress=True)
    save_map(res.refine.refined, args.out / "refined.csv")
    rms = lambda a: float(np.sqrt(np.mean(np.square(a))))  # noqa: E731
    print(f"stickers refined: {len(res.seen)} of {len(survey)}; frames used {res.refine.frames_used}")
    print(
        f"seen stickers (not the moved one): position RMS {rms(res.before_m) * 100:.2f} -> {rms(res.after_m) * 100:.2f} cm,"
        f" yaw RMS {np.degrees(rms(res.before_yaw)):.2f} -> {np.degrees(rms(res.after_yaw)):.2f} deg"
    )
    print(f"moved sticker found within {res.moved_after_m[0] * 100:.2f} cm; unseen unchanged: {res.unseen_unchanged}")
    print(
        "\n| walk | used to refine | RMSE cm survey map | refined map | true map | heading deg survey / refined / true |"
    )
    print("|---|---|---|---|---|---|")
    for k, p in enumerate(sessions):
        m = {name: res.metrics[name][p.name] for name in ("survey", "refined", "true")}
        print(
            f"| {p.name} | {'yes' if k < 3 else 'no'} | {m['survey']['rmse_m'] * 100:.2f} | {m['refined']['rmse_m'] * 100:.2f}"
            f" | {m['true']['rmse_m'] * 100:.2f} | {m['survey']['heading_rmse_deg']:.2f} / {m['refined']['heading_rmse_deg']:.2f}"
            f" / {m['true']['heading_rmse_deg']:.2f} |"
        )


if __name__ == "__main__":
    main()
