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

import sys
from pathlib import Path

# The table's driver and the replay's scoring are the flicker benchmark's.
sys.path.insert(0, str(Path(__file__).resolve().parent))

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
    from flicker import demo_session, walk_config

    from tagloc.sim.lamps import LampConfig

    shadow, spacing, height, lux, pitch, speed = CONDITIONS[name]
    lamps = LampConfig(spacing_m=spacing, height_m=height)
    cfg = walk_config(seed, lux, pitch_deg=pitch, speed_mps=speed, rolling_shutter=True, shadow=shadow, lamps=lamps)
    return demo_session(out / name.replace(" ", "_"), cfg)


def replay(path: Path, flatten: bool) -> dict:
    """One replay of ``path``'s session, scored against its ground truth."""
    from dataclasses import replace

    from flicker import score_replay

    from tagloc.pipeline.localiser import LocaliserConfig

    cfg = LocaliserConfig()
    if not flatten:
        odo = cfg.odometry_config
        cfg = replace(cfg, odometry_config=replace(odo, flow_config=replace(odo.flow_config, flatten_px=0)))
    return score_replay(path, cfg)


def main() -> None:
    from flicker import run_table

    run_table(__doc__, CONDITIONS, make, replay, Path("out/shadow"), "flatten", "shading")


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("shadow.py", main))
