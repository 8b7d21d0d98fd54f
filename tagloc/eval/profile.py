"""``tagloc bench --profile SESSION``: where a replay's CPU time goes, from cProfile.

The session is replayed in this process (as ``tagloc replay`` does, no outputs written) with OpenCV
on one thread under :mod:`cProfile`. The summary lists the pipeline's stages (the calls the
localiser makes per frame) and the functions with the most time of their own, each with its share
of the profiled time, calls and time per frame. cProfile adds overhead to every Python call (about
a third on this pipeline), so the shares, not the absolute times, are what to read; per-frame times
without it come from ``benchmarks/replay_cost.py``.
"""

from __future__ import annotations

import cProfile
import pstats
from dataclasses import dataclass
from pathlib import Path

#: The per-frame stages, as (label, module path suffix, function name) of the call that runs each.
STAGES = (
    ("read JPEG (replay only)", "session.py", "frames"),
    ("odometry", "localiser.py", "_odometry_step"),
    ("detect", "detect.py", "detect"),
    ("  refine (edge profiles)", "detect.py", "_refine"),
    ("  candidates (contours)", "detect.py", "_candidates"),
    ("decode", "localiser.py", "_decode"),
    ("identify", "localiser.py", "_identify"),
    ("pose", "pose.py", "solve_pose"),
    ("tracker predict", "tracker.py", "predict"),
    ("tracker update", "tracker.py", "update"),
    ("tracker candidates", "localiser.py", "_candidates"),
)


@dataclass
class ProfileSummary:
    """A replay's profile: ``frames`` processed, ``total_s`` profiled, stage rows (label, calls,
    cumulative s) and the top functions by own time (name, calls, own s, cumulative s)."""

    session: str
    frames: int
    total_s: float
    stages: list[tuple[str, int, float]]
    top: list[tuple[str, int, float, float]]

    def format(self) -> str:
        """Readable tables."""
        n = max(self.frames, 1)
        lines = [
            f"cProfile of a replay of {self.session}: {self.frames} frames, {self.total_s:.2f} s profiled "
            f"(cProfile overhead included; read the shares)",
            "",
            f"{'stage':<28}{'calls':>8}{'s':>9}{'share':>8}{'ms/frame':>10}",
        ]
        for label, calls, cum in self.stages:
            share = 100 * cum / self.total_s if self.total_s else 0.0
            lines.append(f"{label:<28}{calls:>8}{cum:>9.2f}{share:>7.1f}%{1e3 * cum / n:>10.2f}")
        lines += ["", f"{'function (most own time)':<58}{'calls':>8}{'own s':>8}{'cum s':>8}{'share':>8}"]
        for name, calls, own, cum in self.top:
            share = 100 * own / self.total_s if self.total_s else 0.0
            lines.append(f"{name[:57]:<58}{calls:>8}{own:>8.2f}{cum:>8.2f}{share:>7.1f}%")
        return "\n".join(lines)


def _label(func: tuple[str, int, str]) -> str:
    path, line, name = func
    if path == "~":
        return name  # a built-in
    parts = Path(path).parts
    short = "/".join(parts[-2:]) if len(parts) >= 2 else path
    return f"{short}:{line}({name})"


def profile_replay(session: str | Path, top: int = 25) -> ProfileSummary:
    """Replay ``session`` under cProfile (BLAS and OpenCV on one thread each, as a replay runs) and
    summarise where the time went."""
    from tagloc.io.session import SessionReader
    from tagloc.pipeline.localiser import Localiser
    from tagloc.pipeline.run import single_threaded

    with single_threaded():  # as a replay runs its frames
        reader = SessionReader(session)
        loc = Localiser(reader.map, reader.rig, map_path=Path(session) / "map.csv")
        prof = cProfile.Profile()
        frames = 0
        prof.enable()
        for frame in reader.frames():
            loc.process(frame)
            frames += 1
        prof.disable()
    stats = pstats.Stats(prof).stats  # {(file, line, name): (cc, nc, tt, ct, callers)}
    total = sum(v[2] for v in stats.values())
    stages = []
    for label, suffix, name in STAGES:
        rows = [v for (path, _, fn), v in stats.items() if fn == name and path.endswith(suffix)]
        stages.append((label, sum(v[1] for v in rows), sum(v[3] for v in rows)))
    ranked = sorted(stats.items(), key=lambda kv: -kv[1][2])[:top]
    return ProfileSummary(str(session), frames, total, stages, [(_label(f), v[1], v[2], v[3]) for f, v in ranked])
