"""One camera against two (front-down and rear-down) on the same simulated walks.

The same seed gives the same walk, floor and lighting; the two-camera rig adds a camera looking back
at the same pitch, exposed half a frame after the front one (:func:`tagloc.sim.simulate.simulate_session`
renders every camera of the rig into one session). Measured per walk: the fraction of frame times
with a mapped sticker fully in view of some camera (from the simulator's ground truth), the
fraction of frames with a pose, the fixes, and the horizontal RMSE against ground truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tagloc.core.camera import Camera, default_camera
from tagloc.core.rig import Rig, RigCamera, default_rig, looking_forward
from tagloc.eval.metrics import error_metrics, trajectory_errors
from tagloc.io.session import SessionReader
from tagloc.pipeline.run import run_session
from tagloc.sim.simulate import SimConfig, read_groundtruth_frames, simulate_session

#: The rear camera sits this far behind the front one on the vest (m): a back-plate mount.
REAR_OFFSET_M = 0.25


def front_rear_rig(height_m: float = 1.3, pitch_deg: float = 55.0, camera: Camera | None = None) -> Rig:
    """The default front camera plus one on the back looking backwards and down at the same pitch."""
    cam = camera or default_camera()
    front = default_rig(height_m, pitch_deg, cam).cameras[0]
    rear = RigCamera("rear", cam, looking_forward(height_m, pitch_deg, 180.0, x_m=-REAR_OFFSET_M), "camera.yaml")
    return Rig([front, rear])


@dataclass(frozen=True)
class MultiCamConfig:
    """The comparison: ``seeds`` walks of ``seconds`` at ``fps`` over ``map_path``, both rigs."""

    map_path: Path = Path("maps/demo.csv")
    out: Path = Path("out/multicam")
    seeds: tuple[int, ...] = (1, 2, 3)
    seconds: float = 20.0
    fps: float = 15.0
    lux: float = 100.0
    scale: float = 1.0
    progress: bool = True


def sticker_in_view(session_dir: Path, cameras: int) -> float:
    """Fraction of frame times at which some camera has a mapped sticker fully inside its image."""
    seen: dict[int, bool] = {}
    for rec in read_groundtruth_frames(session_dir):
        step = rec["index"] // cameras
        hit = any(v.get("in_map") and v.get("inside") for v in rec["visible"])
        seen[step] = seen.get(step, False) or hit
    return float(np.mean(list(seen.values()))) if seen else math.nan


def compare_cameras(cfg: MultiCamConfig | None = None) -> list[dict]:
    """Simulate and localise every walk with both rigs; one row per (walk, rig)."""
    cfg = cfg or MultiCamConfig()
    rows = []
    for seed in cfg.seeds:
        for name, rig in (("front", default_rig()), ("front+rear", front_rear_rig())):
            path = Path(cfg.out) / f"{name.replace('+', '_')}_s{seed}"
            sim = SimConfig(seconds=cfg.seconds, fps=cfg.fps, lux=cfg.lux, seed=seed, scale=cfg.scale, rig=rig)
            if not (path / "frames.csv").exists():
                simulate_session(cfg.map_path, path, sim, progress=cfg.progress)
            session = SessionReader(path)
            log = run_session(session, progress=cfg.progress)
            e = trajectory_errors(
                log.stamps[log.valid], log.poses[log.valid], log.covs[log.valid], *session.groundtruth()
            )
            m = error_metrics(e)
            rows.append(
                {
                    "walk": f"s{seed}",
                    "rig": name,
                    "frames": len(log.stamps),
                    "sticker_in_view": sticker_in_view(path, len(rig)),
                    "coverage": float(np.mean(log.valid)) if len(log.valid) else 0.0,
                    "fixes": len(log.fixes),
                    "rmse_m": m["rmse_m"],
                    "max_m": m["max_m"],
                    "heading_rmse_deg": m["heading_rmse_deg"],
                }
            )
    return rows


def format_rows(rows: list[dict]) -> str:
    """The comparison as a table."""
    lines = [f"{'walk':<6}{'rig':<12}{'frames':>7}{'in view':>9}{'pose':>7}{'fixes':>7}{'RMSE cm':>9}{'max cm':>8}"]
    for r in rows:
        lines.append(
            f"{r['walk']:<6}{r['rig']:<12}{r['frames']:>7}{r['sticker_in_view']:>9.0%}{r['coverage']:>7.0%}"
            f"{r['fixes']:>7}{100 * r['rmse_m']:>9.2f}{100 * r['max_m']:>8.2f}"
        )
    return "\n".join(lines)
