"""The operator's own shadow under overhead lamps: what it does to tagloc, with the floor flow's
coarse levels flattened (the default) and without.

Run: ``PYTHONPATH=$PWD python benchmarks/shadow.py [-o out/shadow] [--jobs 2] [--json FILE]``.

Each condition is one seeded 20 s walk over ``maps/demo.csv`` (the Speed walk's map, ``--seed``;
a 25 ms rolling shutter), with the operator's body casting its shadow under a square grid of lamps
(:mod:`tagloc.sim.lamps`): high-bay lamps 6 m apart 9 m up, or a low bay (a mezzanine, an office
corridor) with lamps 4 m apart 4.5 m up, where fewer lamps light each point and the shadows are
deeper; the camera pitched 55 degrees at 1.3 m/s, or 65 degrees (it sees the floor from 0.1 m ahead
of the chest, where the shadow lies) at an unhurried 0.9 m/s (less floor motion a frame, against
which the shadow's pull weighs more). Sessions are cached
in the output directory. Each walk is replayed with ``FloorFlowConfig.flatten_px`` as it is (the
frames divided by their local mean before Lucas-Kanade's coarse levels) and at 0 (the frames as
they are): horizontal RMSE, worst error, heading RMSE, mean position NEES, fixes and wrong-ID fixes.
Rows: ``shading out`` / ``kept``.
"""

from __future__ import annotations

import argparse
import json
import math
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

#: name -> (shadow, lamp spacing m, lamp height m, lux, camera pitch deg, walking speed m/s)
CONDITIONS = {
    "no shadow": (False, 6.0, 9.0, 300.0, 55.0, 1.3),
    "high bay": (True, 6.0, 9.0, 300.0, 55.0, 1.3),
    "low bay": (True, 4.0, 4.5, 300.0, 55.0, 1.3),
    "low bay 100lx": (True, 4.0, 4.5, 100.0, 55.0, 1.3),
    "no shadow 65deg": (False, 6.0, 9.0, 250.0, 65.0, 0.9),
    "high bay 65deg": (True, 6.0, 9.0, 250.0, 65.0, 0.9),
    "low bay 65deg": (True, 4.0, 4.5, 250.0, 65.0, 0.9),
}


def make(out: Path, name: str, seed: int) -> Path:
    """The condition's session in ``out`` (simulated unless the same settings made it before)."""
    from tagloc.sim.lamps import LampConfig
    from tagloc.sim.render import ExposureConfig
    from tagloc.sim.simulate import SIM_REVISION, SimConfig, simulate_session

    shadow, spacing, height, lux, pitch, speed = CONDITIONS[name]
    cfg = SimConfig(
        seconds=20.0,
        lux=lux,
        seed=seed,
        pitch_deg=pitch,
        speed_mps=speed,
        rolling_shutter=True,
        exposure=ExposureConfig(readout_s=0.025),
        shadow=shadow,
        lamps=LampConfig(spacing_m=spacing, height_m=height),
    )
    path = out / name.replace(" ", "_")
    stamp = json.loads(json.dumps({"sim": SIM_REVISION, "config": cfg.to_json()}))
    meta = path / "made.json"
    if not (meta.exists() and json.loads(meta.read_text()) == stamp):
        simulate_session(Path(__file__).resolve().parent.parent / "maps" / "demo.csv", path, cfg, progress=False)
        meta.write_text(json.dumps(stamp))
    return path


def replay(path: Path, flatten: bool) -> dict:
    """One replay of ``path``'s session, scored against its ground truth."""
    from dataclasses import replace

    import cv2

    from tagloc.eval.evaluate import wrong_id_fixes
    from tagloc.eval.metrics import trajectory_errors
    from tagloc.io.session import SessionReader
    from tagloc.pipeline.localiser import Localiser, LocaliserConfig
    from tagloc.pipeline.run import run_session

    cv2.setNumThreads(1)
    session = SessionReader(path)
    cfg = LocaliserConfig()
    if not flatten:
        odo = cfg.odometry_config
        cfg = replace(cfg, odometry_config=replace(odo, flow_config=replace(odo.flow_config, flatten_px=0)))
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
    }


def main() -> None:
    from tqdm import tqdm

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--out", type=Path, default=Path("out/shadow"))
    ap.add_argument("--seed", type=int, default=4)
    ap.add_argument("--conditions", default=",".join(CONDITIONS), help="comma-separated names (default: all)")
    ap.add_argument("--jobs", type=int, default=2, help="processes (default 2)")
    ap.add_argument("--json", type=Path, help="also write the rows as JSON")
    args = ap.parse_args()
    names = [n.strip() for n in args.conditions.split(",")]
    unknown = [n for n in names if n not in CONDITIONS]
    if unknown:
        raise SystemExit(f"unknown condition(s) {', '.join(unknown)}; known: {', '.join(CONDITIONS)}")
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
    rows = []
    print(
        f"{'condition':17s} {'shading':>7s} {'RMSE cm':>8s} {'max cm':>7s} {'head deg':>8s} {'NEES':>6s}"
        f" {'fixes':>6s} {'wrong':>5s}"
    )
    for k, (name, (path, on)) in enumerate(zip([n for n in names for _ in (0, 1)], jobs)):
        r = scored[k] | {"condition": name, "flatten": on, "session": str(path)}
        rows.append(r)
        print(
            f"{name:17s} {'out' if on else 'kept':>7s} {r['rmse_cm']:8.2f} {r['max_cm']:7.1f}"
            f" {r['heading_deg']:8.2f} {r['nees']:6.2f} {r['fixes']:6d} {r['wrong_ids']:5d}"
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
