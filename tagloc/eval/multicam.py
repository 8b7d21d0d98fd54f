"""One camera against two (front-down and rear-down) on the same simulated walks.

Each walk is simulated once with the two-camera rig (:func:`front_rear_rig`; the rear camera looks
back at the same pitch and is exposed half a frame after the front one); the one-camera run is the
same session with the rear camera's frames left out. The simulator renders camera 0 of a rig exactly
as it renders a one-camera rig (same walk, floor, lighting, sensor seed and per-frame noise), so both
runs see the same front frames and differ only by the rear camera. Measured per walk and rig: the
fraction of frame times with a mapped sticker fully in view of some camera (from the simulator's
ground truth), the fraction of frames with a pose, the fixes, the horizontal RMSE and maximum error
against ground truth, and the position NEES (2 DoF; see :mod:`tagloc.eval.consistency`).

``tagloc eval --preset two-camera`` runs :data:`TWO_CAMERA_WALKS` (:func:`run_two_camera`);
``benchmarks/two_cameras.py`` the same with other seeds or lengths.
"""

from __future__ import annotations

import copy
import json
import math
from collections.abc import Collection
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tagloc.core.camera import Camera, default_camera
from tagloc.core.rig import Rig, RigCamera, default_rig, looking_forward
from tagloc.eval.consistency import bounds_text, nees_blocks, nees_test
from tagloc.eval.metrics import error_metrics, frames_in_span, trajectory_errors
from tagloc.io.session import FRAMES_CSV, SessionReader
from tagloc.pipeline.localiser import LocaliserConfig
from tagloc.pipeline.run import RunLog, run_session
from tagloc.sim.simulate import SIM_REVISION, SimConfig, read_groundtruth_frames, simulate_session

#: The rear camera sits this far behind the front one on the vest (m): a back-plate mount.
REAR_OFFSET_M = 0.25

#: The rigs compared: name -> the rig cameras whose frames the localiser gets.
RIGS: dict[str, tuple[int, ...]] = {"front": (0,), "front+rear": (0, 1)}


def front_rear_rig(height_m: float = 1.3, pitch_deg: float = 55.0, camera: Camera | None = None) -> Rig:
    """The default front camera plus one on the back looking backwards and down at the same pitch."""
    cam = camera or default_camera()
    front = default_rig(height_m, pitch_deg, cam).cameras[0]
    rear = RigCamera("rear", cam, looking_forward(height_m, pitch_deg, 180.0, x_m=-REAR_OFFSET_M), "camera.yaml")
    return Rig([front, rear])


@dataclass(frozen=True)
class MultiCamConfig:
    """The comparison: ``seeds`` walks of ``seconds`` at ``fps`` per camera and ``lux`` over
    ``map_path``, rendered at ``scale`` of the full resolution; sessions and report under ``out``."""

    map_path: Path = Path(__file__).resolve().parents[2] / "maps" / "demo.csv"  # the source tree's
    out: Path = Path("out/multicam")
    seeds: tuple[int, ...] = (1, 2, 3)
    seconds: float = 20.0
    fps: float = 15.0
    lux: float = 100.0
    scale: float = 1.0
    progress: bool = True
    sim_extra: dict = field(default_factory=dict)  # further SimConfig fields (e.g. rolling_shutter)
    odometry_cameras: tuple[int, ...] | None = None  # LocaliserConfig.odometry_cameras (None: all)


#: The fixed walks of ``tagloc eval --preset two-camera``: three seeded 20 s walks over the demo map,
#: 15 fps per camera (30 frames/s in all, the one-camera rate of the other presets), 100 lux.
TWO_CAMERA_WALKS = MultiCamConfig()


def sticker_in_view(session_dir: Path, cameras: int, only: Collection[int] | None = None) -> float:
    """Fraction of frame times at which some camera (of ``only``, default all ``cameras`` of the rig)
    has a mapped sticker fully inside its image."""
    seen: dict[int, bool] = {}
    for rec in read_groundtruth_frames(session_dir):
        if only is not None and int(rec.get("camera", 0)) not in only:
            continue
        step = rec["index"] // cameras
        hit = any(v.get("in_map") and v.get("inside") for v in rec["visible"])
        seen[step] = seen.get(step, False) or hit
    return float(np.mean(list(seen.values()))) if seen else math.nan


def camera_subset(session: SessionReader, cameras: Collection[int]) -> SessionReader:
    """The session with only the frames of rig cameras ``cameras`` (the rig stays whole)."""
    keep = np.isin(session.cameras, list(cameras))
    sub = copy.copy(session)
    sub.index, sub.timestamps, sub.cameras = session.index[keep], session.timestamps[keep], session.cameras[keep]
    sub.skipped = []
    return sub


def make_walk(cfg: MultiCamConfig, seed: int) -> Path:
    """Simulate walk ``seed`` with the two-camera rig (reused when made with the same conditions)."""
    path = Path(cfg.out) / "sessions" / f"s{seed}"
    sim = SimConfig(
        seconds=cfg.seconds,
        fps=cfg.fps,
        lux=cfg.lux,
        seed=seed,
        scale=cfg.scale,
        rig=front_rear_rig(),
        **cfg.sim_extra,
    )
    made = {"sim": sim.to_json(), "map": str(cfg.map_path), "simulator": SIM_REVISION}
    stamp = path / "walk.json"
    if stamp.exists() and json.loads(stamp.read_text()) == made and (path / FRAMES_CSV).exists():
        return path
    if path.exists():
        import shutil

        shutil.rmtree(path)
    simulate_session(cfg.map_path, path, sim, progress=cfg.progress)
    stamp.write_text(json.dumps(made))
    return path


def score_run(session: SessionReader, log: RunLog) -> dict:
    """Accuracy, NEES and counters of one run against the session's ground truth."""
    gt = session.groundtruth()
    v = log.valid  # (a skipped frame has none: the filter's prediction is no pose of it)
    e = trajectory_errors(log.stamps[v], log.poses[v], log.covs[v], *gt)
    m = error_metrics(e)
    return {
        "frames": len(log.stamps),
        "frames_in_gt": frames_in_span(log.stamps, gt[0]),  # the frames the ground truth can score
        "coverage": float(np.mean(v)) if len(v) else 0.0,
        "fixes": len(log.fixes),
        "rmse_m": m["rmse_m"],
        "max_m": m["max_m"],
        "heading_rmse_deg": m["heading_rmse_deg"],
        "nees_mean": m["nees_mean"],
        "beyond_999": m["beyond_999"],
        "nees_blocks": nees_blocks(e.stamps, e.nees).tolist(),
        "odometry_fused": int(log.counts.get("tracker_odometry_accepted", 0)),
        "odometry_unmatched": int(log.counts.get("tracker_odometry_unmatched", 0)),
        "errors": (e.stamps.tolist(), e.position.tolist()),
    }


def compare_cameras(cfg: MultiCamConfig | None = None) -> list[dict]:
    """Simulate every walk once with both cameras and localise it with each rig of :data:`RIGS`; one row
    per (walk, rig)."""
    cfg = cfg or MultiCamConfig()
    rows = []
    for seed in cfg.seeds:
        path = make_walk(cfg, seed)
        full = SessionReader(path)
        n_cams = len(full.rig)
        for name, cams in RIGS.items():
            session = camera_subset(full, cams)
            log = run_session(session, LocaliserConfig(odometry_cameras=cfg.odometry_cameras), progress=cfg.progress)
            rows.append(
                {
                    "walk": f"s{seed}",
                    "rig": name,
                    "sticker_in_view": sticker_in_view(path, n_cams, cams),
                    **score_run(session, log),
                }
            )
    return rows


def summarise(rows: list[dict]) -> dict[str, dict]:
    """Per rig over all walks: RMSE pooled by frame, and the pooled NEES test."""
    out = {}
    for name in dict.fromkeys(r["rig"] for r in rows):
        rs = [r for r in rows if r["rig"] == name]
        sq = sum(float(np.sum(np.square(r["errors"][1]))) for r in rs)
        n = sum(len(r["errors"][1]) for r in rs)
        test = nees_test(np.array([b for r in rs for b in r["nees_blocks"]], float).reshape(-1, 3))
        out[name] = {
            "rmse_m": math.sqrt(sq / n) if n else math.nan,
            "sticker_in_view": float(np.mean([r["sticker_in_view"] for r in rs])),
            "fixes": int(sum(r["fixes"] for r in rs)),
            "nees_mean": test.mean,
            "nees_bounds_95_effective": list(test.bounds_effective),
            "nees_verdict": test.verdict,
        }
    return out


def format_rows(rows: list[dict], summary: dict[str, dict] | None = None) -> str:
    """The comparison as a Markdown table (per walk and rig, then per rig over all walks)."""
    head = (
        "| walk | rig | frames | sticker in view | pose | fixes | odometry fused (unmatched) | RMSE cm | max cm |"
        " heading deg | NEES |"
    )
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        lines.append(
            f"| {r['walk']} | {r['rig']} | {r['frames']} | {r['sticker_in_view']:.0%} | {r['coverage']:.0%} |"
            f" {r['fixes']} | {r['odometry_fused']} ({r['odometry_unmatched']}) | {100 * r['rmse_m']:.2f} |"
            f" {100 * r['max_m']:.1f} | {r['heading_rmse_deg']:.2f} | {r['nees_mean']:.2f} |"
        )
    for name, s in (summary or {}).items():
        lines.append(
            f"| **all** | {name} | | {s['sticker_in_view']:.0%} | | {s['fixes']} | | **{100 * s['rmse_m']:.2f}** | |"
            f" | {s['nees_mean']:.2f} ({s['nees_verdict']}, 95% {bounds_text(s['nees_bounds_95_effective'])}) |"
        )
    return "\n".join(lines)


def plot_errors(rows: list[dict], path: Path) -> Path:
    """Position error over time per walk, one camera against two, as one PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    walks = list(dict.fromkeys(r["walk"] for r in rows))
    fig, axes = plt.subplots(len(walks), 1, figsize=(10, 2.4 * len(walks)), squeeze=False, sharex=True)
    for ax, walk in zip(axes[:, 0], walks):
        for r in (r for r in rows if r["walk"] == walk):
            t, err = r["errors"]
            ax.plot(t, 100 * np.asarray(err), lw=1, label=f"{r['rig']} (RMSE {100 * r['rmse_m']:.1f} cm)")
        ax.set_ylabel(f"{walk}: error cm")
        ax.legend(loc="upper right", fontsize=8)
    axes[-1, 0].set_xlabel("time (s)")
    fig.suptitle("horizontal position error: one camera against front + rear", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def run_two_camera(cfg: MultiCamConfig | None = None) -> str:
    """Run the comparison, write ``results.json``, ``report.md`` and ``two_camera.png`` under ``cfg.out``;
    return the table to print."""
    cfg = cfg or TWO_CAMERA_WALKS
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = compare_cameras(cfg)
    summary = summarise(rows)
    table = format_rows(rows, summary)
    plot = plot_errors(rows, out / "two_camera.png")
    from tagloc.core.jsonfile import write_json

    slim = [{k: v for k, v in r.items() if k != "errors"} for r in rows]
    write_json(out / "results.json", {"rows": slim, "summary": summary})
    conditions = (
        f"{len(cfg.seeds)} walks (seeds {', '.join(map(str, cfg.seeds))}) of {cfg.seconds:g} s over"
        f" {Path(cfg.map_path).name}, {cfg.fps:g} fps per camera, {cfg.lux:g} lux"
        + "".join(f", {k} {v}" for k, v in cfg.sim_extra.items())
        + ("" if cfg.odometry_cameras is None else f", floor odometry from cameras {list(cfg.odometry_cameras)}")
    )
    report = [
        "# tagloc eval: one camera against front + rear",
        "",
        conditions,
        "",
        table,
        "",
        f"![errors]({plot.name})",
    ]
    (out / "report.md").write_text("\n".join(report) + "\n", encoding="utf-8")
    return f"{conditions}\n\n{table}\n\nreport: {out / 'report.md'}"
