"""Map refinement measured: survey-error map against refined map, and the localiser with each.

The site is a strip of 4 x 20 stickers 0.4 m apart (``tagloc.eval.mapbench.strip_site``). The
simulator renders the stickers at their true poses; each session's map carries the survey error of
``tagloc.sim.survey`` (2 cm RMS in position, 2 degrees, stated in the map's sigma columns; one site
survey) with one sticker moved 15 cm since the survey; the audited map also lists a sticker that is no
longer on the floor and lacks one that is. Three walks refine the map (with and without the floor
odometry's links); they and two fresh walks are then localised with the survey-error map, the
refined map and the true map, and scored as ``tagloc eval`` scores a walk.

With ``--sparse`` it measures instead what the odometry links add where frames rarely see two
stickers: one aisle of 12 stickers 1.5 m apart (a warehouse's spacing), the same survey error (no
moved sticker), three 10 s walks refined with and without the links.

    nice python benchmarks/map_refine.py -o out/map_refine [--seconds 8]
    nice python benchmarks/map_refine.py -o out/map_refine_sparse --sparse

With ``--refined-exact`` (after a run) it localises the five walks with the refined map's positions
but its sigma columns set to 0, to separate the refined positions' own error from how the localiser
weighs a map that states small sigmas.

    nice python benchmarks/map_refine.py -o out/map_refine --refined-exact
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import shutil
from pathlib import Path

import numpy as np

from tagloc.core.stickermap import StickerMap, load_map, save_map
from tagloc.eval.consistency import bounds_text
from tagloc.eval.mapbench import (
    MISSING,
    MOVED,
    SITE_SURVEY,
    UNMAPPED,
    MapBenchResult,
    map_bench,
    pooled,
    rms,
    score_refinement,
    site_map,
    stated_exact,
    strip_site,
    walk_metrics,
    without,
)
from tagloc.eval.mapobs import collect_walk
from tagloc.eval.maprefine import RefineConfig, refine_map
from tagloc.sim.simulate import SIM_REVISION, SimConfig, simulate_session
from tagloc.sim.survey import SurveyConfig, surveyed_map


def make_sessions(
    out: Path, seeds: list[int], seconds: float, floor: StickerMap | None = None, survey: SurveyConfig = SITE_SURVEY
) -> list[Path]:
    """The site's walks (made once, reused while the simulator and settings are the same)."""
    floor = floor if floor is not None else without(strip_site(), MISSING)
    sessions = []
    for seed in seeds:
        path = out / f"walk{seed}"
        cfg = SimConfig(seconds=seconds, lux=150, speed_mps=1.0, seed=seed, survey=survey)
        stamp = json.loads(json.dumps({"sim": SIM_REVISION, "config": cfg.to_json()}))
        meta = path / "made.json"
        if not (meta.exists() and json.loads(meta.read_text()) == stamp):
            if path.exists():
                shutil.rmtree(path)  # made by another simulator or settings
            simulate_session(floor, path, cfg, progress=True)
            meta.write_text(json.dumps(stamp))
        sessions.append(path)
    return sessions


def sparse(out: Path, seconds: float) -> None:
    """What the odometry links add on a sparse aisle (see the module docstring)."""
    truth = strip_site(1, 12, 1.5)
    survey_cfg = dataclasses.replace(SITE_SURVEY, moved=())
    sessions = make_sessions(out, [1, 2, 3], seconds, truth, survey_cfg)
    save_map(surveyed_map(truth, survey_cfg, seed=0), out / "survey.csv")
    survey = load_map(out / "survey.csv")
    walks = [collect_walk(s, survey, map_path=out / "survey.csv", progress=True) for s in sessions]
    for odometry in (False, True):
        res = refine_map(walks, survey, RefineConfig(odometry=odometry))
        label = "corners + odometry" if odometry else "corners only"
        if not res.changes:
            print(f"{label}: {res.note}")
            continue
        print(describe(score_refinement(res, truth, survey, []), label))


def describe(res: MapBenchResult, label: str) -> str:
    """The map figures of one refinement, as lines."""
    r, b = res.refine, res.bound
    moved = f"  moved sticker found within {res.moved_after_m[0] * 100:.2f} cm; " if len(res.moved_after_m) else "  "
    return "\n".join(
        [
            f"{label}: {len(res.seen)} stickers refined from {r.frames_used} frames"
            f" ({r.odometry_links} odometry links), RMS corner residual {r.rms_px:.2f} px, {r.solve_s:.1f} s",
            f"  seen stickers (not the moved one): position RMS {rms(res.before_m) * 100:.2f} ->"
            f" {rms(res.after_m) * 100:.2f} cm, yaw RMS {np.degrees(rms(res.before_yaw)):.2f} ->"
            f" {np.degrees(rms(res.after_yaw)):.2f} deg",
            f"  anchoring bound: the true shape placed by the priors {rms(b.oracle_m) * 100:.2f} cm"
            f" (expected over surveys {b.expected_rms_m * 100:.2f} cm); refined shape alone {b.shape_rms_m * 100:.2f} cm",
            moved + f"unseen unchanged: {res.unseen_unchanged}",
        ]
    )


def refined_exact(out: Path) -> None:
    """The walks localised with ``out``/refined.csv stated exact (see the module docstring)."""
    smap = stated_exact(load_map(out / "refined.csv"))
    print("| walk | RMSE cm | heading deg | mean NEES | wrong IDs | gated fixes |\n|---|---|---|---|---|---|")
    metrics = {}
    for k in (1, 2, 3, 4, 5):
        m = walk_metrics(collect_walk(out / f"walk{k}", smap, progress=True))
        metrics[f"walk{k}"] = m
        print(
            f"| walk{k} | {m['rmse_m'] * 100:.2f} | {m['heading_rmse_deg']:.2f} | {m['nees_mean']:.2f}"
            f" | {m['wrong_id_fixes']} | {m['gated_fixes']} |"
        )
    s = pooled(metrics)
    print(f"pooled: RMSE {s['rmse_m'] * 100:.2f} cm, NEES {s['nees_mean']:.2f} ({s['nees_verdict']})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--out", type=Path, default=Path("out/map_refine"))
    ap.add_argument("--seconds", type=float, default=None, help="length of each walk, s (8; 10 with --sparse)")
    ap.add_argument("--sparse", action="store_true", help="measure the odometry links on a sparse aisle instead")
    ap.add_argument("--refined-exact", action="store_true", help="localise with the refined map stated exact")
    args = ap.parse_args()
    if args.refined_exact:
        refined_exact(args.out)
        return
    if args.sparse:
        sparse(args.out, args.seconds or 10.0)
        return
    sessions = make_sessions(args.out, [1, 2, 3, 4, 5], args.seconds or 8.0)
    truth = without(strip_site(), UNMAPPED)
    save_map(truth, args.out / "true.csv")
    save_map(site_map(strip_site()), args.out / "survey.csv")
    survey = load_map(args.out / "survey.csv")
    res = map_bench(
        truth, survey, sessions[:3], sessions[3:], [MOVED], progress=True, survey_path=args.out / "survey.csv"
    )
    save_map(res.refine.refined, args.out / "refined.csv")
    (args.out / "metrics.json").write_text(json.dumps(res.metrics, indent=1, default=float))
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
            return " / ".join(format(x[key] * scale if scale != 1.0 else x[key], fmt) for x in m)

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
        print(
            f"| {n} | {s['frames']} | {s['rmse_m'] * 100:.2f} | {s['heading_rmse_deg']:.2f} | {s['nees_mean']:.2f}"
            f" {bounds_text(s['nees_bounds_95_effective'])} | {s['nees_verdict']} | {s['fixes']} | {s['gated_fixes']} | {s['wrong_id_fixes']} |"
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
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("map_refine.py", main))
