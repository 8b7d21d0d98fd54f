"""How often a burst of dropped frames is bridged wrongly, and what the wrong bridges do to the pose.

A camera driver loses single frames and bursts of 3-8. The floor odometry bridges a gap up to
``OdometryConfig.bridge_max_dt`` with one match between the frames either side of it, started from
the walk predicted through the gap (:meth:`tagloc.vision.odometry.FloorOdometry._bridge`). Such a
match has no frame in between to check it, and in a fast turn it can settle on a wrong alignment
with a correlation as high as a right one's.

Each session is replayed once; after every frame from ``--start`` on, a copy of the localiser is
handed, for each burst length of ``--drops``, the frame that many frames later, as if those
between were lost. Where the copy's odometry bridged the gap, its step is compared with the true
step (the simulator's camera poses, ``groundtruth_frames.jsonl``, carried to the vest point
through the rig), and the published pose after it with the truth. Per session and variant:

- bridges: gaps bridged; wrong: bridged steps beyond the 99 % chi-square bound (3 DoF, 11.34) of
  their own stated covariance; fused: of those, the ones the tracker accepted;
- right refused: bridges within the bound that the tracker refused; right RMS: the error of the
  bridges within the bound (forward and sideways mm, turn deg);
- after: the published pose's 3-DoF NEES (x, y, yaw) at the frame after the gap: its maximum and
  how many exceed the 99.9 % bound (16.27; an honest filter once in a thousand);
- every gap: the same pose after every gap, bridged or not (a bridge the odometry or the tracker
  refused leaves the gap to the walking model): its position error (RMS and maximum, mm) and how
  many exceed 16.27. A check that refuses bridges shows its cost here.

Each ``--variant NAME=JSON`` (dotted settings, as ``benchmarks/eval_variants.py`` takes them) runs
the same gaps. Run from the repository root on simulated sessions, e.g.::

    tagloc simulate --map maps/demo.csv --seconds 4 --seed 1 -o out/b1 --quiet
    PYTHONPATH=$PWD python benchmarks/bridges.py out/b1 out/b2 out/b3 --jobs 2 \\
        --variant 'no-mask={"odometry_config.bridge_overlap_mask": false}'

A 4 s walk takes about 10 s per variant here (every frame's copy runs each burst).
"""

from __future__ import annotations

import argparse
import copy
import json
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from eval_variants import variant_configs  # (benchmarks/ is on the path of a script run from it)
from odometry_accuracy import _groundtruth, _nees, _relative

from tagloc.core.geometry import planar_from_T, wrap_angle
from tagloc.core.rig import vest_planar
from tagloc.io.session import SessionReader
from tagloc.pipeline.localiser import Localiser, LocaliserConfig
from tagloc.pipeline.run import single_threaded

#: 99 % point of chi-square with 3 DoF: a bridged step beyond it is counted wrong.
CHI2_3_99 = 11.345
#: 99.9 % point of chi-square with 3 DoF: the tracker's own gate level, for the published pose.
CHI2_3_999 = 16.266


def _pose_nees(out, truth: np.ndarray) -> float:
    """3-DoF NEES of a published pose ``out`` (TrackerOutput) against the true (x, y, yaw)."""
    e = np.asarray(out.pose, float) - truth
    e[2] = wrap_angle(e[2])
    return float(_nees(e[None], np.asarray(out.cov, float)[None])[0])


def _session_rows(args: tuple[str, list[int], int, dict[str, LocaliserConfig]]) -> list[dict]:
    path, drops, start, variants = args
    session = SessionReader(Path(path))
    rc = session.rig.cameras[0]
    T_camera_body = np.linalg.inv(rc.T_body_camera)
    true_step = {i: vest_planar(T @ T_camera_body, rc.vest_point) for i, T in _groundtruth(Path(path)).items()}
    gt_t, gt_T = session.groundtruth()
    frames = [f for f in session.frames() if f.image is not None]
    index_at = {float(f.timestamp): f.index for f in frames}
    rows = []
    for name, cfg in variants.items():
        row = {"walk": path, "variant": name, "bridges": 0, "wrong": 0, "fused": 0, "right_refused": 0}
        after, right, gaps, gap_nees = [], [], [], []
        loc = Localiser(session.map, session.rig, cfg, map_path=session.map_path)
        with single_threaded():
            for k, f in enumerate(frames):
                loc.process(f)
                if k < start:
                    continue
                for drop in drops:
                    if k + drop + 1 >= len(frames):
                        continue
                    g = frames[k + drop + 1]
                    trial = copy.deepcopy(loc)
                    odo = trial.floor_odometry(g.camera)
                    bridged, fused = odo.bridged, trial.tracker.stats["odometry_accepted"]
                    out = trial.process(g).output
                    step = trial._step
                    j = int(np.argmin(np.abs(gt_t - out.t)))
                    placed = out.state.value != "initialising" and abs(gt_t[j] - out.t) < 1e-3
                    if placed:
                        # Every gap, bridged or not: what the published pose after it is worth.
                        truth = np.array(planar_from_T(gt_T[j]))
                        gaps.append(np.hypot(*(np.asarray(out.pose[:2], float) - truth[:2])))
                        gap_nees.append(_pose_nees(out, truth))
                    # The step's own frames: it starts at the odometry's last measured frame, which is
                    # not ``f`` when the odometry skipped ``f`` (a variant with odometry_stride).
                    i0 = None if step is None else index_at.get(float(step.t0))
                    if odo.bridged == bridged or i0 not in true_step or g.index not in true_step:
                        continue
                    e = np.asarray(step.delta, float) - _relative(true_step[i0], true_step[g.index])
                    e[2] = wrap_angle(e[2])
                    wrong = float(_nees(e[None], np.asarray(step.cov, float)[None])[0]) > CHI2_3_99
                    accepted = trial.tracker.stats["odometry_accepted"] > fused
                    row["bridges"] += 1
                    row["wrong"] += wrong
                    row["fused"] += wrong and accepted
                    row["right_refused"] += not wrong and not accepted
                    if not wrong:
                        right.append(e)
                    if placed:
                        after.append(gap_nees[-1])
        rms = np.sqrt(np.mean(np.square(right), axis=0)) if right else np.full(3, np.nan)
        row["right_rms"] = [float(rms[0]), float(rms[1]), float(np.degrees(rms[2]))]  # m, m, deg
        row["after_max"] = float(max(after, default=0.0))
        row["after_over"] = int(sum(a > CHI2_3_999 for a in after))
        row["gaps"] = len(gaps)
        row["gap_rms"] = float(np.sqrt(np.mean(np.square(gaps)))) if gaps else float("nan")  # m
        row["gap_max"] = float(max(gaps, default=float("nan")))  # m
        row["gap_over"] = int(sum(a > CHI2_3_999 for a in gap_nees))
        rows.append(row)
    return rows


def summarise(rows: list[dict]) -> str:
    """The table: one row per (walk, variant)."""
    w = max(7, *(len(r["variant"]) for r in rows))
    lines = [
        f"{'walk':<24}  {'variant':<{w}}  bridges  wrong  fused  right refused  "
        "right RMS fwd/lat mm, deg  after: max NEES  > 16.27  every gap: RMS / max mm  > 16.27",
        f"{'-' * 24}  {'-' * w}  -------  -----  -----  -------------  "
        "-------------------------  ---------------  -------  ---------------------  -------",
    ]
    for r in rows:
        fwd, lat, turn = r["right_rms"]
        lines.append(
            f"{Path(r['walk']).name[:24]:<24}  {r['variant']:<{w}}  {r['bridges']:7d}  {r['wrong']:5d}  "
            f"{r['fused']:5d}  {r['right_refused']:13d}  {1000 * fwd:8.1f} {1000 * lat:6.1f} {turn:9.2f}  "
            f"{r['after_max']:15.1f}  {r['after_over']:7d}  {1000 * r['gap_rms']:10.1f} {1000 * r['gap_max']:10.1f}"
            f"  {r['gap_over']:7d}"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Bridge bursts of dropped frames at every place of each session; print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sessions", nargs="+", help="simulated session directories (groundtruth_frames.jsonl)")
    ap.add_argument("--drops", default="3,6,9", help="frames dropped per burst (comma-separated)")
    ap.add_argument("--start", type=int, default=5, help="first frame a burst follows (frames before: start-up)")
    ap.add_argument("--jobs", type=int, default=1, help="sessions replayed in parallel")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME=JSON", help="settings to compare")
    ap.add_argument("--json", type=Path, help="write the rows here")
    a = ap.parse_args(argv)
    try:
        drops = [int(x) for x in a.drops.split(",")]
    except ValueError:
        ap.error(f"--drops {a.drops!r}: want whole numbers of frames, comma-separated")
    if min(drops) < 1 or a.start < 0:
        ap.error("--drops must be at least 1 frame, --start not negative")
    variants = variant_configs(a.variant)
    for s in a.sessions:
        if not (Path(s) / "groundtruth_frames.jsonl").is_file():
            ap.error(f"{s}: no groundtruth_frames.jsonl (a session from tagloc simulate)")
        cameras = len(SessionReader(Path(s)).rig.cameras)
        if cameras != 1:
            ap.error(f"{s}: the rig has {cameras} cameras; bursts are dropped from one camera's frames")
    jobs = [(s, drops, a.start, variants) for s in a.sessions]
    with ProcessPoolExecutor(max_workers=max(1, a.jobs)) as pool:
        rows = [r for part in pool.map(_session_rows, jobs) for r in part]
    print(summarise(rows))
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("bridges.py", main))
