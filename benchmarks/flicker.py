"""Lamp flicker under a rolling shutter: what it does to tagloc, with the bands divided out and without.

Run: ``PYTHONPATH=$PWD python benchmarks/flicker.py [-o out/flicker] [--jobs 2] [--json FILE]``.

Each condition is one seeded 20 s walk over ``maps/demo.csv`` (the Speed walk's map and path,
``--seed``), with a rolling shutter read out in 25 ms, under lamps of the given percent flicker at
twice the mains frequency (:class:`tagloc.sim.render.Flicker`). With 50 Hz mains at 30 fps the
bands move a third of a period a frame; with 60 Hz they stand still. Sessions are cached in the
output directory. Each walk is replayed with ``LocaliserConfig.deflicker`` on (the default) and
off: horizontal RMSE, worst error, heading RMSE, mean position NEES, fixes, wrong-ID fixes, and the
frames whose bands were divided out.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

#: name -> (percent flicker, mains Hz, lux, rolling shutter)
CONDITIONS = {
    "steady": (0.0, 50.0, 300.0, True),
    "5% 50Hz": (5.0, 50.0, 300.0, True),
    "5% 60Hz": (5.0, 60.0, 300.0, True),
    "10% 50Hz": (10.0, 50.0, 300.0, True),
    "10% 60Hz": (10.0, 60.0, 300.0, True),
    "30% 50Hz": (30.0, 50.0, 300.0, True),
    "30% 60Hz": (30.0, 60.0, 300.0, True),
    "steady 100lx": (0.0, 50.0, 100.0, True),
    "30% 50Hz 100lx": (30.0, 50.0, 100.0, True),
    "steady global": (0.0, 50.0, 300.0, False),
    "30% 50Hz global": (30.0, 50.0, 300.0, False),
}


def make(out: Path, name: str, seed: int) -> Path:
    """The condition's session in ``out`` (simulated unless the same settings made it before)."""
    flicker, mains, lux, rolling = CONDITIONS[name]
    cfg = walk_config(seed, lux, rolling_shutter=rolling, flicker=flicker / 100.0, mains_hz=mains)
    return demo_session(out / name.replace(" ", "_").replace("%", "pc"), cfg)


def walk_config(seed: int, lux: float, **settings):
    """These benchmarks' 20 s walk (a ``SimConfig``): ``lux``, ``seed``, a 25 ms read-out when the
    shutter rolls, and the condition's ``settings`` (any other ``SimConfig`` fields)."""
    from tagloc.sim.render import ExposureConfig
    from tagloc.sim.simulate import SimConfig

    return SimConfig(seconds=20.0, lux=lux, seed=seed, exposure=ExposureConfig(readout_s=0.025), **settings)


def demo_session(path: Path, cfg) -> Path:
    """The session of ``cfg`` (a ``SimConfig``) over ``maps/demo.csv`` at ``path``, simulated unless
    the same simulator and settings made it before."""
    from tagloc.sim.simulate import SIM_REVISION, simulate_session

    stamp = json.loads(json.dumps({"sim": SIM_REVISION, "config": cfg.to_json()}))
    meta = path / "made.json"
    if not (meta.exists() and json.loads(meta.read_text()) == stamp):
        if path.exists():
            # Made by another simulator or settings: made again (a session directory is never
            # written over).
            shutil.rmtree(path)
        simulate_session(Path(__file__).resolve().parent.parent / "maps" / "demo.csv", path, cfg, progress=False)
        meta.write_text(json.dumps(stamp))
    return path


def score_replay(path: Path, cfg) -> dict:
    """One replay of ``path``'s session with ``cfg`` (a ``LocaliserConfig``), scored against its
    ground truth; ``counts``: the localiser's counters."""
    import cv2

    from tagloc.eval.evaluate import wrong_id_fixes
    from tagloc.eval.metrics import trajectory_errors
    from tagloc.io.session import SessionReader
    from tagloc.pipeline.localiser import Localiser
    from tagloc.pipeline.run import run_session

    cv2.setNumThreads(1)
    session = SessionReader(path)
    loc = Localiser(session.map, session.rig, config=cfg, map_path=session.map_path)
    loc.warm_up()
    log = run_session(session, localiser=loc)
    v = log.valid
    e = trajectory_errors(log.stamps[v], log.poses[v], log.covs[v], *session.groundtruth())
    return {
        "rmse_cm": 100 * math.sqrt(float(np.mean(e.position**2))),
        "max_cm": 100 * float(np.max(e.position)),
        "heading_deg": math.degrees(math.sqrt(float(np.mean(e.yaw**2)))),
        "nees": float(np.mean(e.nees)),
        "fixes": len(log.fixes),
        "wrong_ids": wrong_id_fixes(path, log)[0],
        "frames": len(log.stamps),
        "counts": dict(loc.counts),
    }


def replay(path: Path, deflicker: bool) -> dict:
    """One replay of ``path``'s session, with the bands divided out or not."""
    from tagloc.pipeline.localiser import LocaliserConfig

    r = score_replay(path, LocaliserConfig() if deflicker else LocaliserConfig(deflicker=None))
    return r | {"deflickered": int(r["counts"].get("deflickered", 0))}


def run_table(doc: str, conditions: dict, make, replay, out: Path, toggle: str, column: str, extra=None) -> None:
    """The command line of a benchmark over ``conditions`` (name -> settings): each condition's
    session made by ``make(out, name, seed)`` and replayed by ``replay(path, on)`` with the
    correction named ``toggle`` on and off (rows ``out`` / ``kept`` under ``column``); ``extra``:
    (header, row -> text) of one more column."""
    from tqdm import tqdm

    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--out", type=Path, default=out)
    ap.add_argument("--seed", type=int, default=4)
    ap.add_argument("--conditions", default=",".join(conditions), help="comma-separated names (default: all)")
    ap.add_argument("--jobs", type=int, default=2, help="processes (default 2)")
    ap.add_argument("--json", type=Path, help="also write the rows as JSON")
    args = ap.parse_args()
    names = [n.strip() for n in args.conditions.split(",")]
    unknown = [n for n in names if n not in conditions]
    if unknown:
        raise SystemExit(f"unknown condition(s) {', '.join(unknown)}; known: {', '.join(conditions)}")
    args.out.mkdir(parents=True, exist_ok=True)
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        made = list(
            tqdm(
                pool.map(make, [args.out] * len(names), names, [args.seed] * len(names)),
                total=len(names),
                desc="simulate",
                unit="walk",
            )
        )
        jobs = [(p, d) for p in made for d in (True, False)]
        scored = list(tqdm(pool.map(replay, *zip(*jobs)), total=len(jobs), desc="replay", unit="replay"))
    width = max(len(n) for n in names) + 1
    print(
        f"{'condition':{width}s} {column:>7s} {'RMSE cm':>8s} {'max cm':>7s} {'head deg':>8s} {'NEES':>6s}"
        f" {'fixes':>6s} {'wrong':>5s}" + (f" {extra[0]}" if extra else "")
    )
    rows = []
    for k, (name, (path, on)) in enumerate(zip([n for n in names for _ in (0, 1)], jobs)):
        r = scored[k] | {"condition": name, toggle: on, "session": str(path)}
        rows.append(r)
        print(
            f"{name:{width}s} {'out' if on else 'kept':>7s} {r['rmse_cm']:8.2f} {r['max_cm']:7.1f}"
            f" {r['heading_deg']:8.2f} {r['nees']:6.2f} {r['fixes']:6d} {r['wrong_ids']:5d}"
            + (f" {extra[1](r)}" if extra else "")
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


def main() -> None:
    run_table(
        __doc__,
        CONDITIONS,
        make,
        replay,
        Path("out/flicker"),
        "deflicker",
        "bands",
        ("divided out", lambda r: f"{r['deflickered']:5d}/{r['frames']}"),
    )


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("flicker.py", main))
