"""``tagloc demo``: the whole job on the bundled example, with no camera and no arguments.

Simulates a walk on ``maps/demo.csv``, replays it through the localiser, prints the accuracy
against ground truth, and writes the trajectory (TUM), the per-frame log and a Rerun recording.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from tagloc.core.errors import InputError


@dataclass
class DemoConfig:
    """What the demo simulates and where it writes (all defaults are the README's example)."""

    out: Path = Path("out/demo")
    map: Path | None = None
    seconds: float = 20.0
    lux: float = 150.0
    speed: float = 1.3
    seed: int = 1
    rerun: bool = True
    progress: bool = True


def demo_map_path() -> Path:
    """``maps/demo.csv`` of the source tree (or of the current directory)."""
    for base in (Path(__file__).resolve().parents[1], Path.cwd()):
        p = base / "maps" / "demo.csv"
        if p.exists():
            return p
    raise InputError("maps/demo.csv not found: run from the tagloc source tree or pass --map")


#: What a simulated session holds (``tagloc simulate``, and so the demo's earlier run): a directory
#: with anything else in it is not one the demo made, and is never deleted.
SIMULATED_SESSION_FILES = frozenset(
    {
        "frames",
        "frames.csv",
        "session.json",
        "map.csv",
        "map_true.csv",
        "map.refs.npz",
        "rig.json",
        "camera.yaml",
        "groundtruth.tum",
        "groundtruth_frames.jsonl",
    }
)


def _check_replaceable(session: Path, map_path: Path) -> None:
    """Refuse to delete ``session`` (the demo's earlier output, replaced on each run) unless it is a
    simulated session and nothing else, and does not hold the map this run reads."""
    import json
    import os

    refuse = f"{session} exists and is not a session an earlier tagloc demo wrote; choose another -o (nothing deleted)"
    if not session.is_dir() or session.is_symlink():
        raise InputError(refuse)
    names = {p.name for p in session.iterdir()}
    try:
        info = json.loads((session / "session.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        raise InputError(refuse) from None
    if not isinstance(info, dict) or info.get("source") != "simulated" or not names <= SIMULATED_SESSION_FILES:
        raise InputError(refuse)
    real = Path(os.path.realpath(session))
    if real in Path(os.path.realpath(map_path)).parents:
        raise InputError(f"{map_path}: the map lies inside {session}, which the demo replaces; choose another -o")


def _rerun_command() -> str:
    """How to start the Rerun viewer from here: the ``rerun`` beside this Python (a virtual
    environment's, which the README's set-up does not put on the shell's path), else ``rerun``."""
    import os
    import shutil
    import sys

    beside = Path(sys.executable).parent / "rerun"
    if beside.exists() and shutil.which("rerun") != str(beside):
        return os.path.relpath(beside) if not os.path.relpath(beside).startswith("..") else str(beside)
    return "rerun"


def run_demo(cfg: DemoConfig) -> str:
    """Simulate, replay and write the outputs; returns the text to print."""
    from tagloc.apps.replay import ReplayConfig, replay
    from tagloc.sim.simulate import SimConfig, simulate_session

    out = Path(cfg.out)
    session = out / "session"
    map_path = Path(cfg.map) if cfg.map is not None else demo_map_path()
    if session.exists():
        _check_replaceable(session, map_path)
        import shutil

        shutil.rmtree(session)
    out.mkdir(parents=True, exist_ok=True)
    sim = simulate_session(
        map_path,
        session,
        SimConfig(seconds=cfg.seconds, lux=cfg.lux, speed_mps=cfg.speed, seed=cfg.seed),
        progress=cfg.progress,
    )
    rrd = out / "demo.rrd" if cfg.rerun else None
    res = replay(
        ReplayConfig(
            session=session, out=out / "estimate.tum", log=out / "frames.jsonl", rerun_save=rrd, progress=cfg.progress
        )
    )
    lines = [
        f"simulated {sim.frames} frames of a {cfg.seconds:g} s walk at {cfg.lux:g} lux into {session}",
        res.format(),
        f"trajectory: {out / 'estimate.tum'} (TUM; ground truth: {session / 'groundtruth.tum'})",
        f"per-frame log: {out / 'frames.jsonl'}",
    ]
    if rrd is not None:
        lines.append(f"Rerun recording: {rrd}  -> open it with:  {_rerun_command()} {rrd}")
    return "\n".join(lines)
