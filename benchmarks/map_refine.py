"""Map refinement measured: survey-error map against refined map, and the localiser with each.

The site is a strip of 4 x 20 stickers 0.4 m apart (``tagloc.eval.mapbench.strip_site``). The
simulator renders the stickers at their true poses; each session's map carries the survey error of
``tagloc.sim.survey`` (2 cm RMS in position, 2 degrees, stated in the map's sigma columns; one site
survey) with one sticker moved 15 cm since the survey; the audited map also lists a sticker that is no
longer on the floor and lacks one that is. Three walks refine the map (with and without the floor
odometry's links); they and two fresh walks are then localised with the survey-error map, the
refined map and the true map, and scored as ``tagloc eval`` scores a walk.

    nice python benchmarks/map_refine.py -o out/map_refine [--seconds 8]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from tagloc.core.stickermap import load_map, save_map
from tagloc.eval.mapbench import (
    MISSING,
    MOVED,
    SITE_SURVEY,
    UNMAPPED,
    MapBenchResult,
    map_bench,
    rms,
    score_refinement,
    site_map,
    strip_site,
    without,
)
from tagloc.eval.maprefine import RefineConfig, refine_map
from tagloc.sim.simulate import SimConfig, simulate_session


def make_sessions(out: Path, seeds: list[int], seconds: float) -> list[Path]:
    """The site's walks (made once, reused when present)."""
    floor = without(strip_site(), MISSING)
    sessions = []
    for seed in seeds:
        path = out / f"walk{seed}"
        if not (path / "groundtruth_frames.jsonl").exists():
            cfg = SimConfig(seconds=seconds, lux=150, speed_mps=1.0, seed=seed, survey=SITE_SURVEY)
            simulate_session(floor, path, cfg, progress=True)
        sessions.append(path)
    return sessions


def describe(res: MapBenchResult, label: str) -> str:
    """The map figures of one refinement, as lines."""
    r, b = res.refine, res.bound
    return "\n".join(
        [
            f"{label}: {len(res.seen)} stickers refined from {r.frames_used} frames"
            f" ({r.odometry_links} odometry links), RMS corner residual {r.rms_px:.2f} px, {r.solve_s:.1f} s",
            f"  seen stickers (not the moved one): position RMS {rms(res.before_m) * 100:.2f} ->"
            f" {rms(res.after_m) * 100:.2f} cm, yaw RMS {np.degrees(rms(res.before_yaw)):.2f} ->"
            f" {np.degrees(rms(res.after_yaw)):.2f} deg",
            f"  anchoring bound: the true shape placed by the priors {rms(b.oracle_m) * 100:.2f} cm"
            f" (expected over surveys {b.expected_rms_m * 100:.2f} cm); refined shape alone {b.shape_rms_m * 100:.2f} cm",
            f"  moved sticker found within {res.moved_after_m[0] * 100:.2f} cm; unseen unchanged: {res.unseen_unchanged}",
        ]
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--out", type=Path, default=Path("out/map_refine"))
    ap.add_argument("--seconds", type=float, default=8.0)
    args = ap.parse_args()
    sessions = make_sessions(args.out, [1, 2, 3, 4, 5], args.seconds)
    truth = without(strip_site(), UNMAPPED)
    save_map(truth, args.out / "true.csv")
    save_map(site_map(strip_site()), args.out / "survey.csv")
    survey = load_map(args.out / "survey.csv")
    res = map_bench(
        truth, survey, sessions[:3], sessions[3:], [MOVED], progress=True, survey_path=args.out / "survey.csv"
    )
    save_map(res.refine.refined, args.out / "refined.csv")
    # The same walks refined without the odometry links: what the links add.
    plain = refine_map(res.walks, survey, dataclasses.replace(RefineConfig(), odometry=False))
    print(describe(score_refinement(plain, truth, survey, [MOVED]), "corners only"))
    print(describe(res, "corners + odometry"))
    print(
        "\n| walk | used to refine | RMSE cm: survey map / refined / true | heading deg | NEES | wrong IDs | gated fixes |"
    )
    print("|---|---|---|---|---|---|---|")
    names = ("survey", "refined", "true")
    for k, p in enumerate(sessions):
        m = [res.metrics[n][p.name] for n in names]

        def each(key: str, fmt: str, m=m, scale: float = 1.0) -> str:
            return " / ".join(format(x[key] * scale, fmt) for x in m)

        print(
            f"| {p.name} | {'yes' if k < 3 else 'no'} | {each('rmse_m', '.2f', scale=100)} | {each('heading_rmse_deg', '.2f')}"
            f" | {each('nees_mean', '.2f')} | {each('wrong_id_fixes', 'd')} | {each('gated_fixes', 'd')} |"
        )
    print("\n| map | frames | RMSE cm | heading deg | NEES (95 % bounds) | verdict | fixes | gated | wrong IDs |")
    print("|---|---|---|---|---|---|---|---|---|")
    summary = {}
    for n in names:
        s = res.pooled(n)
        summary[n] = s
        lo, hi = s["nees_bounds_95_effective"]
        print(
            f"| {n} | {s['frames']} | {s['rmse_m'] * 100:.2f} | {s['heading_rmse_deg']:.2f} | {s['nees_mean']:.2f}"
            f" ({lo:.2f}-{hi:.2f}) | {s['nees_verdict']} | {s['fixes']} | {s['gated_fixes']} | {s['wrong_id_fixes']} |"
        )
    figures = {
        "seen": len(res.seen),
        "before_cm": rms(res.before_m) * 100,
        "after_cm": rms(res.after_m) * 100,
        "after_cm_corners_only": rms(score_refinement(plain, truth, survey, [MOVED]).after_m) * 100,
        "bound_cm": rms(res.bound.oracle_m) * 100,
        "bound_expected_cm": res.bound.expected_rms_m * 100,
        "shape_cm": res.bound.shape_rms_m * 100,
        "moved_cm": float(res.moved_after_m[0] * 100) if len(res.moved_after_m) else math.nan,
        "localisation": summary,
    }
    (args.out / "figures.json").write_text(json.dumps(figures, indent=1, default=float))


if __name__ == "__main__":
    main()
