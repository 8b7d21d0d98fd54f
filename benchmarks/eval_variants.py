"""Localiser settings compared on the walks of ``tagloc eval``: one row per (variant, walk), pooled per preset.

Run (from the repository root, on the output directory of ``tagloc eval --preset all``)::

    PYTHONPATH=$PWD python benchmarks/eval_variants.py out/eval \\
        --variant 'no-overrule={"tracker.overrule_odometry": false}' \\
        --variant 'homography-5={"odometry_config.homography_iterations": 5}' [--jobs 2] [--json F]

The cached sessions under ``OUT/<preset>/sessions/*`` are replayed as they are (nothing is
rendered) through :class:`tagloc.pipeline.localiser.Localiser` with the default
:class:`tagloc.pipeline.localiser.LocaliserConfig` (variant ``default``, always run) and with each
``--variant NAME=JSON``: a JSON object of dotted field paths into the configuration (``tracker.``,
``odometry_config.``, ``pose.``, ...) and their values. A variant that defers work
(``defer_lsq``, ``defer_odometry``) runs in live's order
(:class:`tagloc.eval.baselines.LiveOrderLocaliser`, as eval's ``full-live``; before 2026-11-29
its deferred decodes were dropped, never run). Per walk: horizontal RMSE, heading RMSE, mean
position NEES, share of all frames within 10 cm (a frame without a pose is a miss), fixes
fused and wrong-ID fixes (as ``tagloc eval`` counts them). Per preset, pooled by frame like
``tagloc eval``'s summary: RMSE, heading, NEES and its verdict against the effective-sample bound, and
the share of frames whose NEES is beyond chi-square's 99.9 % point (``>99.9 %``: 0.1 % if consistent).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from tagloc.core.errors import InputError
from tagloc.eval.baselines import LiveOrderLocaliser
from tagloc.eval.consistency import bounds_text, nees_test
from tagloc.eval.evaluate import wrong_id_fixes
from tagloc.eval.multicam import score_run
from tagloc.io.session import SessionReader
from tagloc.pipeline.localiser import Localiser, LocaliserConfig
from tagloc.pipeline.run import run_session


def configure(overrides: dict, option: str = "--variant") -> LocaliserConfig:
    """The default configuration with ``overrides`` ({"a.b.c": value}) applied (nested dataclasses);
    a path that names no setting, or a group of settings given one value, is the user's error
    naming ``option``."""

    def put(obj, path: list[str], value):
        if not dataclasses.is_dataclass(obj) or path[0] not in {f.name for f in dataclasses.fields(obj)}:
            raise InputError(f"{option}: no setting {path[0]!r} in {type(obj).__name__}")
        if len(path) == 1:
            old = getattr(obj, path[0])
            if dataclasses.is_dataclass(old):
                # Replaced by a plain value, it failed in the first replay (after the default's runs).
                raise InputError(f"{option}: {path[0]!r} is a group of settings ({type(old).__name__}): name one field")
            if isinstance(old, tuple):
                value = tuple(value)
            return dataclasses.replace(obj, **{path[0]: value})
        return dataclasses.replace(obj, **{path[0]: put(getattr(obj, path[0]), path[1:], value)})

    cfg = LocaliserConfig()
    for key, value in overrides.items():
        cfg = put(cfg, key.split("."), value)
    return cfg


def json_object(text: str, option: str, what: str) -> dict:
    """The JSON object ``text`` given to ``option``; a one-line error naming the option for text that
    is not JSON or not an object (of ``what``, for the message)."""
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"{option}: not JSON ({exc})") from None
    if not isinstance(obj, dict):
        raise InputError(f"{option}: want a JSON object of {what}, not {text!r}")
    return obj


def parse_variant(spec: str) -> tuple[str, dict]:
    """``--variant NAME=JSON`` as (NAME, its overrides {"a.b.c": value}), checked against the
    configuration (:func:`configure`) so that a misspelt setting is refused before any work."""
    name, _, text = spec.partition("=")
    overrides = json_object(text, f"--variant {name}", "dotted settings")
    configure(overrides, f"--variant {name}")
    return name, overrides


def variant_configs(specs: list[str]) -> dict[str, LocaliserConfig]:
    """``default`` and each ``--variant NAME=JSON`` of ``specs`` (:func:`parse_variant`) as
    configurations, in order; a variant without a name, or named ``default``, is the user's error."""
    configs = {"default": LocaliserConfig()}
    for spec in specs:
        name, overrides = parse_variant(spec)
        if not name or name == "default":
            raise InputError(f"--variant {spec!r}: want NAME=JSON with a name other than 'default'")
        configs[name] = configure(overrides)
    return configs


def run_walk(job: tuple[str, dict, str]) -> dict:
    """Replay one session with one variant; its row (errors kept for pooling)."""
    import cv2

    cv2.setNumThreads(1)
    name, overrides, path = job
    session = SessionReader(path)
    cfg = configure(overrides)
    loc = Localiser(session.map, session.rig, cfg, map_path=session.map_path)
    if cfg.defer_lsq or cfg.defer_odometry:
        # Live's order: the work a frame defers runs before the next frame, as tagloc live and eval's
        # full-live run it. Driven as a replay, a deferred decode would be dropped, never run.
        loc = LiveOrderLocaliser(loc)
    log = run_session(session, localiser=loc)
    m = score_run(session, log)
    position = np.asarray(m["errors"][1], float)  # the scored frames' horizontal errors, m
    n = len(position)
    return {
        "variant": name,
        "preset": Path(path).parent.parent.name,
        "walk": Path(path).name,
        "rmse_cm": 100 * m["rmse_m"],
        "heading_deg": m["heading_rmse_deg"],
        "nees": m["nees_mean"],
        "beyond_999": m["beyond_999"],
        # A frame without a pose is a miss: the share of all frames with a pose within 10 cm.
        "within_10cm_all": float(np.sum(position <= 0.10)) / max(m["frames_in_gt"], 1),
        "fixes": m["fixes"],
        "wrong_ids": wrong_id_fixes(Path(path), log)[0],
        "sq_position": float(np.sum(position**2)),
        "sq_heading": m["heading_rmse_deg"] ** 2 * n if n else 0.0,
        "frames": n,  # with a pose, scored
        "frames_all": m["frames_in_gt"],
        "nees_blocks": m["nees_blocks"],
    }


def pooled(rows: list[dict]) -> dict:
    """Per-preset figures pooled by frame."""
    n = sum(r["frames"] for r in rows)
    test = nees_test(np.array([b for r in rows for b in r["nees_blocks"]], float).reshape(-1, 3))
    scored = [r for r in rows if r["frames"] > 0]  # (a walk without a scored frame has NaN figures)
    return {
        "rmse_cm": 100 * math.sqrt(sum(r["sq_position"] for r in rows) / n) if n else math.nan,
        "heading_deg": math.sqrt(sum(r["sq_heading"] for r in rows) / n) if n else math.nan,
        "nees": sum(r["nees"] * r["frames"] for r in scored) / n if n else math.nan,
        "beyond_999": sum(r["beyond_999"] * r["frames"] for r in scored) / n if n else math.nan,
        "nees_verdict": test.verdict,
        "wrong_ids": sum(r["wrong_ids"] for r in rows),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("eval_dir", type=Path, help="output directory of `tagloc eval` (holds <preset>/sessions/*)")
    ap.add_argument("--variant", action="append", default=[], help='NAME={"dotted.field": value, ...}')
    ap.add_argument("--jobs", type=int, default=1, help="processes (default 1)")
    ap.add_argument("--json", type=Path, help="write the rows and the pooled figures here")
    args = ap.parse_args(argv)
    variants = {"default": {}}
    for spec in args.variant:
        name, overrides = parse_variant(spec)
        variants[name] = overrides
    walks = sorted(str(p) for p in args.eval_dir.glob("*/sessions/*") if (p / "session.json").exists())
    if not walks:
        raise InputError(f"no sessions under {args.eval_dir}/*/sessions")
    jobs = [(name, ov, w) for name, ov in variants.items() for w in walks]
    with ProcessPoolExecutor(max(1, args.jobs)) as ex:
        rows = list(ex.map(run_walk, jobs))
    print(
        f"{'variant':24s} {'walk':10s} {'RMSE cm':>8s} {'hdg deg':>8s} {'NEES':>6s} {'verdict (95 % bounds)':>28s}"
        f" {'>99.9 %':>8s} {'<10 cm':>7s} {'fixes':>6s} {'wrong':>6s}"
    )
    for r in rows:
        # The walk's own verdict, by its effective-sample bounds (as tagloc eval judges each walk).
        t = nees_test(np.array(r["nees_blocks"], float).reshape(-1, 3))
        verdict = f"{t.verdict} {bounds_text(t.bounds_effective)}"
        print(
            f"{r['variant']:24s} {r['walk']:10s} {r['rmse_cm']:8.2f} {r['heading_deg']:8.2f} {r['nees']:6.2f}"
            f" {verdict:>28s} {100 * r['beyond_999']:7.2f}% {100 * r['within_10cm_all']:6.1f}% {r['fixes']:6d}"
            f" {r['wrong_ids']:6d}"
        )
    summary = {}
    print(
        f"\n{'variant':24s} {'preset':10s} {'RMSE cm':>8s} {'hdg deg':>8s} {'NEES':>6s} {'verdict':>14s}"
        f" {'>99.9 %':>8s} {'wrong':>6s}"
    )
    for name in variants:
        for preset in dict.fromkeys(r["preset"] for r in rows):
            p = pooled([r for r in rows if r["variant"] == name and r["preset"] == preset])
            summary[f"{name}/{preset}"] = p
            print(
                f"{name:24s} {preset:10s} {p['rmse_cm']:8.2f} {p['heading_deg']:8.2f} {p['nees']:6.2f}"
                f" {p['nees_verdict']:>14s} {100 * p['beyond_999']:7.2f}% {p['wrong_ids']:6d}"
            )
    if args.json:
        args.json.write_text(json.dumps({"variants": variants, "rows": rows, "summary": summary}, indent=1))


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("eval_variants.py", main))
