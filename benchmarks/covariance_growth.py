"""Where the tracker's stated uncertainty between stickers comes from, and how it compares with its error.

Replays each simulated session with the localiser as it is. In every frame after the last frame
with an accepted fix, up to the next one, three things are compared, binned by the time since
that fix:

- the tracker's stated vest position covariance (what it publishes);
- dead reckoning: the covariance at the fix's frame carried through the odometry steps the tracker
  fused since, each compounded with its own stated covariance (the vest pose x1 = x0 + R(yaw0) d,
  yaw1 = yaw0 + dyaw; first order, at the tracker's own yaws). If the two agree, the odometry's
  stated covariance is all that makes the tracker's grow between stickers (the walking model adds
  a little information, so the tracker may be slightly tighter); a tracker well above dead
  reckoning would have noise from somewhere else;
- the actual position error against the simulator's truth, and the mean position NEES (2 DoF; 2 if
  the stated covariance is honest, below it conservative).

A run of frames is followed only while every frame's odometry step was fused; a frame without one
ends it until the next fix. Position "sd" is the square root of the mean trace of the 2 x 2
covariance (comparable with the RMS of the 2-D error).

Example::

    python benchmarks/covariance_growth.py out/eval/field/sessions/* out/eval/standard/sessions/*
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
from tqdm import tqdm

from tagloc.eval.metrics import trajectory_errors
from tagloc.io.session import SessionReader
from tagloc.pipeline.localiser import Localiser
from tagloc.pipeline.run import iterate_results

#: Bins of the time since the last accepted fix, s.
BINS_S = ((0.0, 0.25), (0.25, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, math.inf))


def compound(P: np.ndarray, yaw0: float, delta: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Covariance (3, 3) of the pose after a step ``delta`` (3,) (dx, dy in the body frame at ``yaw0``
    rad, dyaw) with covariance ``C`` (3, 3), from a pose with covariance ``P`` (3, 3)."""
    c, s = math.cos(yaw0), math.sin(yaw0)
    dx, dy = float(delta[0]), float(delta[1])
    J0 = np.array([[1.0, 0.0, -s * dx - c * dy], [0.0, 1.0, c * dx - s * dy], [0.0, 0.0, 1.0]])
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return J0 @ P @ J0.T + R @ C @ R.T


def gaps(session: Path) -> np.ndarray:
    """(N, 5) per frame between fixes: seconds since the fix, tracker trace (m^2), dead-reckoning
    trace (m^2), squared error (m^2), position NEES."""
    reader = SessionReader(session)
    gt = reader.groundtruth()
    if gt is None:
        raise SystemExit(f"covariance_growth: {session} has no groundtruth.tum")
    loc = Localiser(reader.map, reader.rig, map_path=reader.map_path)
    fused: dict[float, object] = {}
    tracker_update = loc.tracker.update_odometry

    def noting(step, camera=None):
        """The tracker's own update, noting each step it fuses (by its end time)."""
        result = tracker_update(step, camera)
        if result.accepted:
            fused[round(float(step.t1), 9)] = step
        return result

    loc.tracker.update_odometry = noting
    rows = []
    P = None
    t_fix = 0.0
    prev_yaw = 0.0
    for res in tqdm(iterate_results(reader, loc), desc=session.name, unit="frame", leave=False):
        out = res.output
        if any(obs.accepted for obs in res.observations):
            P, t_fix = np.array(out.cov, float), res.timestamp
        elif P is not None:
            step = fused.get(round(res.timestamp, 9))
            if step is None:
                P = None
            else:
                P = compound(P, prev_yaw, np.asarray(step.delta, float), np.asarray(step.cov, float))
                rows.append((res.timestamp, res.timestamp - t_fix, out.pose, out.cov, np.trace(P[:2, :2])))
        prev_yaw = float(out.pose[2])
    if not rows:
        return np.zeros((0, 5))
    stamps, since, poses, covs, dead = (np.array([r[k] for r in rows]) for k in range(5))
    e = trajectory_errors(stamps, poses, covs, gt[0], gt[1])
    tracker = np.trace(covs[:, :2, :2], axis1=1, axis2=2)
    return np.column_stack([since[e.inside], tracker[e.inside], dead[e.inside], e.position**2, e.nees])


def print_table(name: str, g: np.ndarray) -> None:
    """One walk's (or the pool's) rows, one per bin of the time since the fix."""
    print(f"\n{name}")
    print(
        f"{'since fix s':<12} {'frames':>6} {'tracker sd cm':>14} {'dead-reck. sd cm':>17} {'error RMS cm':>13} {'NEES':>6}"
    )
    for lo, hi in BINS_S:
        m = (g[:, 0] > lo) & (g[:, 0] <= hi)
        if not m.any():
            continue
        sd_t, sd_d, rms = (100 * math.sqrt(float(g[m, k].mean())) for k in (1, 2, 3))
        label = f"{lo:g}-{hi:g}" if math.isfinite(hi) else f">{lo:g}"
        print(f"{label:<12} {int(m.sum()):>6} {sd_t:>14.2f} {sd_d:>17.2f} {rms:>13.2f} {float(g[m, 4].mean()):>6.2f}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sessions", nargs="+", type=Path, help="simulated session directories (with groundtruth.tum)")
    args = p.parse_args(argv)
    import cv2

    cv2.setNumThreads(1)
    pooled = []
    for s in args.sessions:
        g = gaps(s)
        pooled.append(g)
        print_table(s.name, g)
    if len(pooled) > 1:
        print_table("all walks", np.concatenate(pooled))
    return 0


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("covariance_growth.py", main))
