"""The wearer's own legs in the camera's view: what they do to tagloc, with the floor they can cover
left out of the odometry (the rig's ``legs_in_view``) and without.

Run: ``PYTHONPATH=$PWD python benchmarks/legs.py [-o out/legs] [--jobs 2] [--json FILE]``.

Each condition is one seeded 20 s walk over ``maps/demo.csv`` (a 25 ms rolling shutter), the camera
1.3 m up, with or without the legs and feet of :mod:`tagloc.sim.legs` rendered into the frames:
pitched 55 degrees at 1.3 m/s and 150 lux, 65 degrees at an unhurried 0.9 m/s and 250 lux (the
shadow benchmark's steep view), and 55 degrees at a brisk 1.6 m/s (longer steps: the feet reach
further). Every session's rig is marked ``legs_in_view`` (as the installer of such a vest would),
so each walk is replayed with the zone left out (``OdometryConfig.legs_reach_m`` as it is: rows
``floor out``) and with it set to 0 (the whole floor used: ``kept``). Sessions are cached in the
output directory. Columns: horizontal RMSE, worst error, heading RMSE, mean position NEES, fixes,
wrong-ID fixes.
"""

from __future__ import annotations

import sys
from pathlib import Path

# The table's driver and the replay's scoring are the flicker benchmark's.
sys.path.insert(0, str(Path(__file__).resolve().parent))

#: name -> (legs rendered, camera pitch deg, walking speed m/s, lux)
CONDITIONS = {
    "no legs 55deg": (False, 55.0, 1.3, 150.0),
    "legs 55deg": (True, 55.0, 1.3, 150.0),
    "no legs 65deg": (False, 65.0, 0.9, 250.0),
    "legs 65deg": (True, 65.0, 0.9, 250.0),
    "no legs 55deg 1.6m/s": (False, 55.0, 1.6, 150.0),
    "legs 55deg 1.6m/s": (True, 55.0, 1.6, 150.0),
}


def make(out: Path, name: str, seed: int) -> Path:
    """The condition's session in ``out`` (simulated unless the same settings made it before), its
    rig marked ``legs_in_view``."""
    from flicker import demo_session, walk_config

    from tagloc.core.rig import load_rig, save_rig

    legs, pitch, speed, lux = CONDITIONS[name]
    cfg = walk_config(seed, lux, pitch_deg=pitch, speed_mps=speed, rolling_shutter=True, legs=legs)
    path = demo_session(out / name.replace(" ", "_").replace("/", "p"), cfg)
    rig = load_rig(path / "rig.json")
    if not all(c.legs_in_view for c in rig.cameras):
        for c in rig.cameras:
            c.legs_in_view = True
        save_rig(rig, path / "rig.json", write_calibrations=False)
    return path


def replay(path: Path, zone: bool) -> dict:
    """One replay of ``path``'s session, scored against its ground truth; ``zone`` False: the legs'
    floor kept (``legs_reach_m`` 0)."""
    from dataclasses import replace

    from flicker import score_replay

    from tagloc.pipeline.localiser import LocaliserConfig

    cfg = LocaliserConfig()
    if not zone:
        cfg = replace(cfg, odometry_config=replace(cfg.odometry_config, legs_reach_m=0.0))
    return score_replay(path, cfg)


def main() -> None:
    from flicker import run_table

    run_table(__doc__, CONDITIONS, make, replay, Path("out/legs"), "legs_zone", "floor")


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("legs.py", main))
