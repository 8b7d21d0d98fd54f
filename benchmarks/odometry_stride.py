"""Floor odometry with and without the stride (``OdometryConfig.max_stride``): cost and accuracy.

Each session's frames go through :class:`tagloc.vision.odometry.FloorOdometry` alone (no tracker),
once measuring every frame (``max_stride`` 1) and once as the localiser calls it (``wants``, and
``hold`` for a frame it skips). The steps are chained over consecutive windows of ``--window``
seconds (the gaps between sticker passes that odometry bridges) and compared with the vest's true
motion over the same interval (the ground truth's camera pose carried through the nominal rig to the
vest point). Printed per walk and configuration: the share of frames skipped, the CPU time per frame
(process time, the skipped frames included), and the RMS of the windows' forward, sideways (mm) and
turn (deg) errors.

With ``--localiser`` the sessions go through the whole localiser instead, with
``LocaliserConfig.odometry_stride`` off and on: per walk and over all walks, the body's RMSE (cm) and
heading RMSE (deg) against the ground truth, over the frames with a pose.

Run (from the repository root, on sessions made by ``tagloc eval --preset all`` or ``tagloc simulate``)::

    PYTHONPATH=$PWD nice python benchmarks/odometry_stride.py SESSION [SESSION ...] [--window 1.0]
    PYTHONPATH=$PWD nice python benchmarks/odometry_stride.py SESSION [SESSION ...] --localiser
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from tagloc.core.geometry import planar_from_T, planar_T, wrap_angle
from tagloc.core.rig import vest_planar
from tagloc.io.session import SessionReader
from tagloc.pipeline.run import single_threaded
from tagloc.vision.image import as_gray
from tagloc.vision.odometry import FloorOdometry, OdometryConfig, OdometryStep


def _steps(session: SessionReader, config: OdometryConfig) -> tuple[list[OdometryStep], int, int, float]:
    """The odometry's steps over the session: (steps, frames skipped, frames, CPU s per frame)."""
    odo = FloorOdometry(session.rig[0], config)
    steps: list[OdometryStep] = []
    skipped = n = 0
    cpu = 0.0
    # Timed as the localiser runs: BLAS's idle threads spin, and on a busy machine count in its time.
    with single_threaded():
        for fr in session.frames():
            if fr.image is None:
                continue
            gray = as_gray(fr.image)
            n += 1
            c0 = time.process_time()
            if odo.wants(fr.timestamp):
                step = odo.measure(gray, fr.timestamp)
                if step is not None:
                    steps.append(step)
            else:
                odo.hold(gray, fr.timestamp)
                skipped += 1
            cpu += time.process_time() - c0
    return steps, skipped, n, cpu / max(n, 1)


def _window_errors(steps: list[OdometryStep], truth: dict[float, np.ndarray], window: float) -> np.ndarray:
    """Errors (N, 3) (forward m, sideways m, turn rad) of the steps chained over consecutive windows of
    at most ``window`` s, or of one longer step (a chain ends where a step does not start at the
    previous one's end)."""
    errs = []
    i = 0
    while i < len(steps):
        pose = np.zeros(3)
        j = i
        # A chain holds its first step even when that step alone is longer than ``window`` (a gap
        # bridged, or a window under a frame): the loop went round without end on such a step.
        while j < len(steps) and (j == i or steps[j].t1 - steps[i].t0 <= window + 1e-6):
            if j > i and abs(steps[j].t0 - steps[j - 1].t1) > 1e-9:
                break
            c, s = math.cos(pose[2]), math.sin(pose[2])
            d = steps[j].delta
            pose = pose + np.array([c * d[0] - s * d[1], s * d[0] + c * d[1], d[2]])
            j += 1
        T0, T1 = truth[round(steps[i].t0, 6)], truth[round(steps[j - 1].t1, 6)]
        true = np.array(planar_from_T(np.linalg.inv(T0) @ T1))
        e = pose - true
        e[2] = wrap_angle(e[2])
        errs.append(e)
        i = j
    return np.array(errs)


def _vest_truth(path: Path, session: SessionReader, stamps: dict[int, float]) -> dict[float, np.ndarray]:
    """The vest's true planar pose, as a (4, 4) ``planar_T``, at each frame time (by the time rounded
    to the microsecond): the ground truth's camera pose carried through the nominal rig to the vest
    point and projected onto the floor (:func:`tagloc.core.rig.vest_planar`), which is what the
    odometry measures and the localiser reports. The tilted body frame's own origin, on the floor
    under the tilted torso, moves with the torso's lean as the vest point does not (1.3 m up, a
    6-degree lean into a turn is 14 cm): against it, 1 s windows read up to twice their error."""
    rc = session.rig[0]
    T_camera_body = np.linalg.inv(rc.T_body_camera)
    truth = {}
    with (path / "groundtruth_frames.jsonl").open() as f:
        for line in f:
            rec = json.loads(line)
            if rec["index"] in stamps:
                vest = vest_planar(np.array(rec["T_world_camera"]) @ T_camera_body, rc.vest_point)
                truth[round(stamps[rec["index"]], 6)] = planar_T(*vest)
    return truth


def localiser_errors(path: Path, stride: bool) -> tuple[float, float, int]:
    """(sum of squared position errors m^2, sum of squared heading errors rad^2, frames) of the
    localiser over a session, ``LocaliserConfig.odometry_stride`` = ``stride``."""
    from tagloc.eval.metrics import trajectory_errors
    from tagloc.pipeline.localiser import LocaliserConfig
    from tagloc.pipeline.run import run_session

    session = SessionReader(path)
    log = run_session(session, LocaliserConfig(odometry_stride=stride))
    v = log.valid
    e = trajectory_errors(log.stamps[v], log.poses[v], log.covs[v], *session.groundtruth())
    return float(np.sum(e.position**2)), float(np.sum(e.yaw**2)), len(e.position)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sessions", nargs="+", type=Path, help="session directories with groundtruth_frames.jsonl")
    ap.add_argument("--window", type=float, default=1.0, help="chain length, s (default 1.0)")
    ap.add_argument("--config", default="{}", help="OdometryConfig overrides as JSON (angles in radians)")
    ap.add_argument("--localiser", action="store_true", help="the whole localiser, odometry_stride off and on")
    args = ap.parse_args(argv)
    from odometry_accuracy import odometry_config

    from tagloc.cli import checks

    base = odometry_config(args.config)  # a bad --config refused before any walk
    checks.number(args.window, "--window", 0.0, lo_open=True)
    cv2.setNumThreads(1)
    if args.localiser:
        print(f"{'walk':10s} {'RMSE cm off -> on':>18s} {'heading deg off -> on':>22s}")
        total = np.zeros((2, 3))
        for path in tqdm(args.sessions, desc="sessions", unit="walk", leave=False):
            r = np.array([localiser_errors(path, stride) for stride in (False, True)])
            total += r
            rm, hd = 100 * np.sqrt(r[:, 0] / r[:, 2]), np.degrees(np.sqrt(r[:, 1] / r[:, 2]))
            tqdm.write(f"{path.name:10s} {rm[0]:8.2f} -> {rm[1]:5.2f} {hd[0]:12.2f} -> {hd[1]:5.2f}")
        rm, hd = 100 * np.sqrt(total[:, 0] / total[:, 2]), np.degrees(np.sqrt(total[:, 1] / total[:, 2]))
        print(f"{'all':10s} {rm[0]:8.2f} -> {rm[1]:5.2f} {hd[0]:12.2f} -> {hd[1]:5.2f}")
        return
    print(f"{'walk':10s} {'stride':>6s} {'skipped %':>9s} {'ms/frame':>8s}  {'window RMS fwd / lat mm, turn deg':>34s}")
    for path in tqdm(args.sessions, desc="sessions", unit="walk", leave=False):
        session = SessionReader(path)
        stamps = {fr.index: fr.timestamp for fr in session.frames(with_images=False)}
        truth = _vest_truth(path, session, stamps)
        for stride in (1, OdometryConfig().max_stride):
            steps, skipped, n, cpu = _steps(session, dataclasses.replace(base, max_stride=stride))
            e = _window_errors(steps, truth, args.window)
            rms = np.sqrt(np.mean(e**2, axis=0))
            tqdm.write(
                f"{path.name:10s} {stride:6d} {100 * skipped / max(n, 1):9.1f} {1e3 * cpu:8.2f}"
                f"  {1e3 * rms[0]:10.1f} / {1e3 * rms[1]:5.1f}, {math.degrees(rms[2]):5.2f}  ({len(e)} windows)"
            )


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("odometry_stride.py", main))
