"""How the localiser's accuracy depends on the map's survey: the same walks replayed with the map's
error scaled.

Run (from the repository root, on sessions rendered with survey error, e.g. the field preset's)::

    PYTHONPATH=$PWD python benchmarks/survey_sensitivity.py out/eval/field/sessions/* \\
        [--factors 0,0.33,0.67,1] [-o out/survey_sensitivity] [--jobs 2] [--json F] [--plot F.png]

A simulated session carries the map it was localised with (``map.csv``, the survey) and the one
its stickers were rendered at (``map_true.csv``). For each factor ``f`` every session is replayed
with the map ``true + f (survey - true)`` (each sticker's position and yaw error times ``f``), which
states its own accuracy in the ``sigma_m``/``sigma_deg`` columns: ``f`` times the survey sigmas
the session was simulated with. So ``f`` = 0 is an exact map stated exact, and ``f`` = 1 the
session's own survey stated as it was made. Nothing is rendered again: the copies under ``-o``
link every file of the session but the map. Per factor, pooled by frame over the walks as ``tagloc
eval`` pools them: horizontal RMSE, the worst walk, heading RMSE, mean position NEES and its
verdict, the share of all frames within 10 cm (a frame without a pose is a miss), wrong-ID fixes;
``--plot`` draws the pooled and the worst walk's RMSE against the survey, with issue 14's goals.

The question it answers: how well must a site be surveyed (or its map refined, ``tagloc map
refine``) for a given accuracy.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from eval_variants import pooled, run_walk
from tqdm import tqdm

from tagloc.core.errors import InputError
from tagloc.core.geometry import wrap_angle
from tagloc.core.stickermap import StickerMap, load_map, save_map
from tagloc.eval.consistency import bounds_text, nees_test


def simulated_survey(session: Path) -> tuple[float, float]:
    """(sigma per axis m, sigma yaw deg) of the survey error ``session`` was simulated with."""
    try:
        survey = json.loads((session / "session.json").read_text())["simulation"]["config"]["survey"]
        return float(survey["sigma_m"]), float(survey["sigma_deg"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{session / 'session.json'}: no simulated survey stated ({exc})") from None


def scaled_map(true: StickerMap, surveyed: StickerMap, factor: float, sigma_m: float, sigma_deg: float) -> StickerMap:
    """``true + factor (surveyed - true)`` per sticker (yaw error wrapped to +-pi before scaling),
    stating ``factor`` times the sigmas (m per axis, degrees) in its survey columns."""
    if not np.array_equal(np.sort(true.ids), np.sort(surveyed.ids)):
        raise InputError("survey_sensitivity: the survey and the true map list different stickers")
    rows = np.array([surveyed.row(int(i)) for i in true.ids])
    d_xy = surveyed.xy[rows] - true.xy
    d_yaw = wrap_angle(surveyed.yaw[rows] - true.yaw)
    n = len(true)
    return StickerMap(
        true.ids.copy(),
        true.xy + factor * d_xy,
        true.yaw + factor * d_yaw,
        sigma_xy=np.full(n, factor * sigma_m),
        sigma_yaw=np.full(n, math.radians(factor * sigma_deg)),
    )


def copy_name(session: Path) -> str:
    """The copy's name: an eval output's group and walk (``field-f00``), else the session's own."""
    return f"{session.parent.parent.name}-{session.name}" if session.parent.name == "sessions" else session.name


def prepare(session: Path, factor: float, out: Path) -> Path:
    """A copy of ``session`` under ``out/x<factor>/sessions/`` with its map's error scaled by
    ``factor`` (every other file linked); returns its path."""
    dest = out / f"x{factor:g}" / "sessions" / copy_name(session)
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    for entry in session.iterdir():
        if entry.name != "map.csv":
            (dest / entry.name).symlink_to(entry.resolve())
    sigma_m, sigma_deg = simulated_survey(session)
    smap = scaled_map(load_map(session / "map_true.csv"), load_map(session / "map.csv"), factor, sigma_m, sigma_deg)
    save_map(smap, dest / "map.csv")
    return dest


def plot(summary: dict, sigma_m: float, sigma_deg: float, path: Path) -> None:
    """PNG of the pooled RMSE and the worst walk's against the survey sigma, with the 2 and 3 cm goals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f = np.array([float(k) for k in summary])
    # Along the position sigma (the yaw's scales with it), or the yaw's when the survey had no position error.
    if sigma_m > 0:
        x, label = (
            100 * f * sigma_m,
            f"map survey sigma per axis, cm (and {sigma_deg / (100 * sigma_m):g} deg of yaw per cm)",
        )
    else:
        x, label = f * sigma_deg, "map survey sigma of yaw, deg"
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(x, [p["rmse_cm"] for p in summary.values()], "o-", label="all walks, pooled")
    ax.plot(x, [p["worst_cm"] for p in summary.values()], "s--", label="worst walk")
    ax.axhline(2.0, color="0.5", lw=0.8, ls=":", label="goals: 2 cm pooled, 3 cm every walk")
    ax.axhline(3.0, color="0.5", lw=0.8, ls=":")
    ax.set_xlabel(label)
    ax.set_ylabel("horizontal RMSE, cm")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sessions", type=Path, nargs="+", help="simulated sessions with map_true.csv and survey error")
    ap.add_argument("--factors", default="0,0.33,0.67,1", help="scales of the map's error (default 0,0.33,0.67,1)")
    ap.add_argument("-o", "--out", type=Path, default=Path("out/survey_sensitivity"), help="where the copies go")
    ap.add_argument("--jobs", type=int, default=1, help="processes (default 1)")
    ap.add_argument("--json", type=Path, help="write the rows and the pooled figures here")
    ap.add_argument("--plot", type=Path, help="write a PNG of RMSE against the survey here")
    args = ap.parse_args()
    try:
        factors = list(dict.fromkeys(float(f) for f in args.factors.split(",")))
    except ValueError:
        raise SystemExit(f"survey_sensitivity: --factors {args.factors!r}: not comma-separated numbers") from None
    if not all(math.isfinite(f) and f >= 0 for f in factors):
        raise SystemExit(f"survey_sensitivity: --factors {args.factors!r}: each must be >= 0")
    sessions = args.sessions
    for s in sessions:
        if not (s / "session.json").is_file():
            raise InputError(f"{s}: not a session directory")
        if not (s / "map_true.csv").exists():
            raise SystemExit(f"survey_sensitivity: {s}: no map_true.csv (not a simulated session)")
    surveys = {simulated_survey(s) for s in sessions}  # refuses a session without one before any work
    if surveys == {(0.0, 0.0)}:
        raise SystemExit("survey_sensitivity: the sessions were simulated with an exact map: no survey error to scale")
    if len(surveys) > 1:
        raise SystemExit(
            "survey_sensitivity: the sessions were simulated with different surveys: give one kind at a time"
        )
    names = [copy_name(s) for s in sessions]
    if len(set(names)) < len(names):
        raise SystemExit("survey_sensitivity: two sessions of the same name (give each once)")
    jobs = [("default", {}, str(prepare(s, f, args.out))) for f in factors for s in sessions]
    with ProcessPoolExecutor(max(1, args.jobs)) as ex:
        rows = list(tqdm(ex.map(run_walk, jobs), total=len(jobs), desc="replays", unit="walk"))
    sigma_m, sigma_deg = simulated_survey(sessions[0])
    print(f"{'factor':>6s} {'walk':16s} {'RMSE cm':>8s} {'hdg deg':>8s} {'NEES':>6s} {'<10 cm':>7s} {'wrong':>6s}")
    for r in rows:
        print(
            f"{r['preset'][1:]:>6s} {r['walk']:16s} {r['rmse_cm']:8.2f} {r['heading_deg']:8.2f} {r['nees']:6.2f}"
            f" {100 * r['within_10cm_all']:6.1f}% {r['wrong_ids']:6d}"
        )
    print(
        f"\nPooled over {len(sessions)} walks (survey simulated: {100 * sigma_m:g} cm per axis, {sigma_deg:g} deg)\n"
        f"{'factor':>6s} {'survey cm/deg':>14s} {'RMSE cm':>8s} {'worst walk':>23s} {'hdg deg':>8s} {'NEES':>6s}"
        f" {'verdict (95 % bounds)':>28s} {'<10 cm':>7s} {'wrong':>6s}"
    )
    summary = {}
    for f in factors:
        group = [r for r in rows if r["preset"] == f"x{f:g}"]
        p = pooled(group)
        frames = sum(r["frames_all"] for r in group)
        within = sum(r["within_10cm_all"] * r["frames_all"] for r in group)
        t = nees_test(np.array([b for r in group for b in r["nees_blocks"]], float).reshape(-1, 3))
        worst = max(group, key=lambda r: r["rmse_cm"])
        p |= {"worst_walk": worst["walk"], "worst_cm": worst["rmse_cm"], "within_10cm_all": within / max(frames, 1)}
        summary[f"{f:g}"] = p
        verdict = f"{t.verdict} {bounds_text(t.bounds_effective)}"
        print(
            f"{f:6.2f} {f'{100 * f * sigma_m:.2f} / {f * sigma_deg:.2f}':>14s} {p['rmse_cm']:8.2f}"
            f" {worst['rmse_cm']:6.2f} {worst['walk']:>16s} {p['heading_deg']:8.2f} {p['nees']:6.2f} {verdict:>28s}"
            f" {100 * p['within_10cm_all']:6.1f}% {p['wrong_ids']:6d}"
        )
    if args.json:
        args.json.write_text(json.dumps({"factors": factors, "rows": rows, "summary": summary}, indent=1))
    if args.plot:
        plot(summary, sigma_m, sigma_deg, args.plot)
        print(f"plot: {args.plot}")


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("survey_sensitivity.py", main))
