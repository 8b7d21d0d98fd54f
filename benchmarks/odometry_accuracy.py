"""Floor odometry against ground truth on simulated sessions: bias, drift, cost, and the step covariance.

Run (from the repository root, on sessions made by ``tagloc eval --preset all`` or ``tagloc simulate``)::

    PYTHONPATH=$PWD python benchmarks/odometry_accuracy.py SESSION [SESSION ...] [--config '{"lean_correction": false}']
    PYTHONPATH=$PWD python benchmarks/odometry_accuracy.py SESSION ... --calibrate
    PYTHONPATH=$PWD python benchmarks/odometry_accuracy.py SESSION ... --by-residual
    PYTHONPATH=$PWD python benchmarks/odometry_accuracy.py SESSION ... --by-rho
    PYTHONPATH=$PWD python benchmarks/odometry_accuracy.py SESSION ... --in-localiser --windows
    PYTHONPATH=$PWD python benchmarks/odometry_accuracy.py SESSION ... --in-localiser --bridged

``--reference apparent`` compares with the motion the nominal bird's-eye patch appears to make given
the true (tilted) camera: the vest's motion plus the tilt change's apparent motion, which the
tracker models as its tilt offset (so the step covariance should state only the rest).

Each session's frames go through :class:`tagloc.vision.odometry.FloorOdometry` alone (no tracker),
and each step is compared with the true motion of the vest (the ground truth's camera pose carried
through the nominal rig to the vest point, :func:`tagloc.core.rig.vest_planar`), which is what the
odometry measures. Per walk: share of steps measured, per-step RMS error (forward, sideways, turn),
the turn's scale error (slope of the turn error regressed on the true turn: -6 % means turns come
out 6 % short), the summed turn error over the walk, the summed forward error against the distance
walked, and the mean CPU time per ``measure`` call (process time: robust to other load).

``--by-residual`` adds the steps binned by the floor flow's median reprojection error (see
:class:`tagloc.vision.floor_flow.FloorFlow`), for the steps the flow measured and the patch's steps
where its fit was refused: RMS error, RMS stated sigma, and the 3-DoF NEES against each step's
covariance (3 if consistent).

``--by-rho`` adds the steps binned by the ECC correlation of the patch's match
(:attr:`tagloc.vision.odometry.OdometryStep.rho`; the bins straddle ``weak_ecc`` and ``min_ecc``):
RMS error, RMS error over the stated sigma per axis (1 if the sigmas hold), and the largest.

``--in-localiser`` measures the steps the localiser itself fuses (the whole pipeline runs: the
odometry's lean and pitch then come from the tracker's prediction, as in a replay) instead of the
odometry alone; every table then describes those steps (the ms column times the localiser's
``measure`` calls alone). ``--windows`` adds the steps summed over
windows of 15, 30 and 60 consecutive steps (the gaps between stickers that odometry bridges)
against the sum of their stated covariances: RMS error, RMS stated sigma and the mean 3-DoF NEES
(3 if the stated covariance holds over such a gap; below it, the tracker's covariance grows faster
in a gap than its error does).

``--bridged`` (with ``--in-localiser``) adds the steps that bridge bursts of dropped frames
(longer than ``BRIDGE_S``, the tracker's ``gap_s``: 3 or more frames lost at 30 fps), apart for
steps the flow refined and those whose flow fit was refused: count, the mean 3-DoF NEES of the
sound ones, and each gross one (NEES beyond ``GROSS_NEES``, the 0.999 gate's 16.27) with its error.

``--calibrate`` fits the step covariance as :class:`tagloc.vision.odometry.OdometryConfig` describes:
the errors are carried to the patch centre (where they are independent), summed over windows of 15,
30, 45 and 60 frames, and the standing sigmas are those for which the variance of the sums over
windows slower than 0.3 m/s equals the stated one; the per-metre sigmas, the same over windows
faster than 0.9 m/s, with the standing part subtracted.
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

from tagloc.core.geometry import wrap_angle
from tagloc.core.rig import vest_planar
from tagloc.io.session import SessionReader
from tagloc.vision.image import as_gray
from tagloc.vision.odometry import FloorOdometry, OdometryConfig

WINDOWS = (15, 30, 45, 60)  # frames: the 0.5-2 s gaps between sticker passes that odometry bridges
SLOW_MPS, FAST_MPS = 0.3, 0.9  # window mean speeds of the standing and walking classes


def _relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(dx, dy, dyaw) of planar pose ``b`` in the frame of ``a``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    d = b[:2] - a[:2]
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], wrap_angle(b[2] - a[2])])


def _apparent(odo: FloorOdometry, T_world_camera: np.ndarray) -> np.ndarray:
    """The planar pose the nominal patch appears at: its 5 x 5 grid of floor points, seen through the
    nominal rig, traced from the true camera to the floor, rigidly fitted (x, y, yaw in the world)."""
    rc, p = odo.rig_camera, odo.patch
    g = np.linspace(0.0, odo.config.patch_px - 1.0, 5)
    cols, rows = np.meshgrid(g, g)
    q = p.origin + np.stack([cols.ravel(), rows.ravel()], axis=1) @ p.A.T
    T_cb = np.linalg.inv(rc.T_body_camera)
    pc = np.column_stack([q, np.zeros(len(q))]) @ T_cb[:3, :3].T + T_cb[:3, 3]
    rays = np.column_stack([pc[:, :2] / pc[:, 2:], np.ones(len(q))]) @ T_world_camera[:3, :3].T
    c = T_world_camera[:3, 3]
    w = c[:2] + (-c[2] / rays[:, 2])[:, None] * rays[:, :2]
    qm, wm = q.mean(axis=0), w.mean(axis=0)
    H = (q - qm).T @ (w - wm)
    yaw = math.atan2(H[0, 1] - H[1, 0], H[0, 0] + H[1, 1])
    t = wm - np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]) @ qm
    return np.array([t[0], t[1], yaw])


def _groundtruth(path: Path) -> dict[int, np.ndarray]:
    """The simulator's true camera pose (4, 4) ``T_world_camera`` of each frame of session ``path``,
    by frame index."""
    gt = {}
    with (path / "groundtruth_frames.jsonl").open() as f:
        for line in f:
            rec = json.loads(line)
            gt[rec["index"]] = np.array(rec["T_world_camera"])
    return gt


def _nees(e: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """The 3-DoF NEES (N,) of errors ``e`` (N, 3) against their covariances ``cov`` (N, 3, 3)."""
    return np.einsum("ni,ni->n", e, np.linalg.solve(cov, e[:, :, None])[:, :, 0])


def _errors(r: dict) -> np.ndarray:
    """Measured less true step (N, 3) of a walk's result ``r``, the turn wrapped (NaN rows where refused)."""
    e = r["meas"] - r["true"]
    e[:, 2] = wrap_angle(e[:, 2])
    return e


def run_session(path: Path, config: OdometryConfig, reference: str = "vest") -> dict:
    """Steps of one session: true (N, 3), measured (N, 3; NaN where refused), patch-centre motion
    (N,), frame times (N,), the odometry, and the mean cost per frame (s)."""
    from tagloc.pipeline.run import single_threaded

    session = SessionReader(path)
    rc = session.rig.cameras[0]
    odo = FloorOdometry(rc, config)
    T_camera_body = np.linalg.inv(rc.T_body_camera)
    gt = _groundtruth(path)
    true, meas, t1, covs, flow, rho = [], [], [], [], [], []
    prev = None
    cost = 0.0
    n = 0
    # Timed as the localiser runs: BLAS's idle threads spin, and on a busy machine count in its time.
    with single_threaded():
        for fr in session.frames():
            gray = as_gray(fr.image)
            flow_steps = odo.flow_steps
            t0 = time.process_time()
            step = odo.measure(gray, fr.timestamp)
            cost += time.process_time() - t0
            n += 1
            if reference == "vest":
                vest = vest_planar(gt[fr.index] @ T_camera_body, rc.vest_point)
            else:
                vest = _apparent(odo, gt[fr.index])
            if prev is not None and fr.index == prev[0] + 1:
                true.append(_relative(prev[1], vest))
                meas.append(step.delta if step is not None else np.full(3, np.nan))
                covs.append(step.cov if step is not None else np.full((3, 3), np.nan))
                rho.append(step.rho if step is not None else np.nan)
                residual = odo.last_flow_residual
                flow.append((np.nan if residual is None else residual, odo.flow_steps > flow_steps))
                t1.append(fr.timestamp)
            prev = (fr.index, vest)
    true, meas = np.array(true), np.array(meas)
    return {
        "true": true,
        "meas": meas,
        "cov": np.array(covs).reshape(-1, 3, 3),
        "flow_residual": np.array([f[0] for f in flow], float),
        "flow_used": np.array([f[1] for f in flow], bool),
        "rho": np.array(rho, float),
        "t": np.array(t1),
        "odo": odo,
        "cost_s": cost / max(n, 1),
    }


def run_session_in_localiser(path: Path, config: OdometryConfig) -> dict:
    """As :func:`run_session`, for the steps :class:`tagloc.pipeline.localiser.Localiser` fuses into its
    tracker (the default configuration with ``config`` as its odometry's), camera 0's."""
    from tagloc.pipeline.localiser import Localiser, LocaliserConfig
    from tagloc.pipeline.run import iterate_results

    cv2.setNumThreads(1)
    session = SessionReader(path)
    rc = session.rig.cameras[0]
    T_camera_body = np.linalg.inv(rc.T_body_camera)
    gt = {i: vest_planar(T @ T_camera_body, rc.vest_point) for i, T in _groundtruth(path).items()}
    loc = Localiser(
        session.map,
        session.rig,
        dataclasses.replace(LocaliserConfig(), odometry_config=config),
        map_path=session.map_path,
    )
    steps = []
    fuse = loc.tracker.update_odometry

    def recording(step, camera=None):
        """The tracker's own update, with the step and the flow's verdict on it noted."""
        odo = loc.floor_odometry(0)
        steps.append((step, odo.last_flow_residual, odo.flow_steps))
        return fuse(step, camera)

    loc.tracker.update_odometry = recording
    # Only the odometry's ``measure`` calls timed (the localiser's other work and the JPEG reads
    # were once counted in: 10.6 ms a frame against 2.8 for measure on a 3 s walk).
    spent = []
    odo = loc.floor_odometry(0)
    if odo is not None:
        measure = odo.measure

        def timed(*args, **kwargs):
            t0 = time.process_time()
            try:
                return measure(*args, **kwargs)
            finally:
                spent.append(time.process_time() - t0)

        odo.measure = timed
    frame_of = {}
    for res in iterate_results(session, loc):
        frame_of[round(res.timestamp, 9)] = res.index
    true, meas, covs, residual, used, t1, dt, rho = [], [], [], [], [], [], [], []
    flow_before = 0
    for step, res_px, flow_steps in steps:
        i0, i1 = frame_of.get(round(step.t0, 9)), frame_of.get(round(step.t1, 9))
        flowed, flow_before = flow_steps > flow_before, flow_steps
        if i0 is None or i1 is None or i0 not in gt or i1 not in gt:
            continue
        true.append(_relative(gt[i0], gt[i1]))
        meas.append(np.asarray(step.delta, float))
        covs.append(np.asarray(step.cov, float))
        residual.append(np.nan if res_px is None else res_px)
        used.append(flowed)
        rho.append(step.rho)
        t1.append(step.t1)
        dt.append(step.t1 - step.t0)
    return {
        "true": np.array(true).reshape(-1, 3),
        "meas": np.array(meas).reshape(-1, 3),
        "cov": np.array(covs).reshape(-1, 3, 3),
        "flow_residual": np.array(residual, float),
        "flow_used": np.array(used, bool),
        "rho": np.array(rho, float),
        "t": np.array(t1),
        "dt": np.array(dt),
        "odo": loc.floor_odometry(0),
        "cost_s": sum(spent) / max(len(spent), 1),
    }


def window_table(results: list[dict]) -> str:
    """The steps of each walk summed over windows of consecutive measured steps against the sum of
    their stated covariances: RMS error (forward, sideways mm, turn deg), RMS stated sigma and the
    mean 3-DoF NEES (3 if the stated covariance holds over the window)."""
    lines = [f"{'steps':>5s} {'windows':>7s}  {'rms fwd/lat mm, yaw deg':>24s}  {'stated sigma':>20s}  {'NEES':>5s}"]
    for w in (15, 30, 60):
        sums, covs = [], []
        for r in results:
            ok = np.all(np.isfinite(r["meas"]), axis=1)
            e = _errors(r)
            for k in range(0, len(e) - w + 1, w):
                if ok[k : k + w].all():
                    sums.append(e[k : k + w].sum(axis=0))
                    covs.append(r["cov"][k : k + w].sum(axis=0))
        if not sums:
            continue
        sums, covs = np.array(sums), np.array(covs)
        nees = _nees(sums, covs)
        rms = np.sqrt(np.mean(sums**2, axis=0))
        s = np.sqrt(np.mean(np.diagonal(covs, axis1=1, axis2=2), axis=0))
        lines.append(
            f"{w:5d} {len(sums):7d}  {1e3 * rms[0]:7.1f} {1e3 * rms[1]:6.1f} {math.degrees(rms[2]):6.2f}"
            f"   {1e3 * s[0]:6.1f} {1e3 * s[1]:6.1f} {math.degrees(s[2]):5.2f}  {np.mean(nees):5.2f}"
        )
    return "\n".join(lines)


def _patch_motion(odo: FloorOdometry, delta: np.ndarray) -> np.ndarray:
    """How far the patch centre moved (m) in each step ``delta`` (N, 3) (see ``covariance``)."""
    cx, cy = odo.patch.centre
    co, si = np.cos(delta[:, 2]), np.sin(delta[:, 2])
    return np.hypot(delta[:, 0] + (co - 1) * cx - si * cy, delta[:, 1] + si * cx + (co - 1) * cy)


def summary_row(name: str, r: dict) -> str:
    """One table row of a session's step statistics."""
    ok = np.all(np.isfinite(r["meas"]), axis=1)
    tr = r["true"][ok]
    e = _errors(r)[ok]
    A = np.column_stack([tr[:, 2], np.ones(len(tr))])
    slope = np.linalg.lstsq(A, e[:, 2], rcond=None)[0][0]
    rms = np.sqrt(np.mean(e**2, axis=0))
    return (
        f"{name:10s} {100 * ok.mean():5.1f}  {1e3 * rms[0]:6.2f} {1e3 * rms[1]:6.2f} {math.degrees(rms[2]):6.3f}"
        f"  {100 * slope:+6.2f}  {math.degrees(e[:, 2].sum()):+7.2f} / {math.degrees(np.abs(tr[:, 2]).sum()):4.0f}"
        f"  {100 * e[:, 0].sum():+6.1f} / {tr[:, 0].sum():5.1f}  {1e3 * r['cost_s']:5.2f}"
    )


RESIDUAL_BINS = (0.0, 1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 4.0, 6.0, math.inf)  # px
BRIDGE_S = 0.12  # s: a step over a burst of 3 or more dropped frames at 30 fps (a stride's 67 ms is no gap)
GROSS_NEES = 16.27  # chi-square, 3 DoF, at 0.999 (the tracker's odometry gate)


def residual_table(results: list[dict]) -> str:
    """The steps of all ``results`` binned by the floor flow's median reprojection error, apart for
    steps the flow measured and the patch's steps where its fit was refused: count, RMS error
    (forward, sideways mm, turn deg), RMS stated sigma, and the mean and median 3-DoF NEES against
    the step's covariance (3 if consistent)."""
    keep = [np.all(np.isfinite(r["meas"]), axis=1) & np.isfinite(r["flow_residual"]) for r in results]
    e = np.vstack([_errors(r)[k] for r, k in zip(results, keep)])
    cov = np.concatenate([r["cov"][k] for r, k in zip(results, keep)])
    res = np.concatenate([r["flow_residual"][k] for r, k in zip(results, keep)])
    used = np.concatenate([r["flow_used"][k] for r, k in zip(results, keep)])
    nees = _nees(e, cov)
    sig = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    lines = [
        f"{'step':8s} {'residual px':>11s} {'steps':>6s}  {'rms fwd/lat mm, yaw deg':>24s}"
        f"  {'stated sigma':>20s}  {'NEES mean / median':>18s}"
    ]
    for name, which in (("flow", used), ("patch", ~used)):
        for lo, hi in zip(RESIDUAL_BINS[:-1], RESIDUAL_BINS[1:]):
            m = which & (res >= lo) & (res < hi)
            if m.sum() < 3:
                continue
            rms = np.sqrt(np.mean(e[m] ** 2, axis=0))
            s = np.sqrt(np.mean(sig[m] ** 2, axis=0))
            lines.append(
                f"{name:8s} {f'{lo:g}-{hi:g}':>11s} {int(m.sum()):6d}  {1e3 * rms[0]:7.1f} {1e3 * rms[1]:6.1f}"
                f" {math.degrees(rms[2]):6.2f}   {1e3 * s[0]:6.1f} {1e3 * s[1]:6.1f} {math.degrees(s[2]):5.2f}"
                f"  {np.mean(nees[m]):8.2f} / {np.median(nees[m]):5.2f}"
            )
    return "\n".join(lines)


RHO_BINS = (0.0, 0.2, 0.25, 0.3, 0.4, 0.6, 1.0)  # ECC correlation; weak_ecc 0.2, min_ecc 0.3


def rho_table(results: list[dict]) -> str:
    """The patch-matched steps of all ``results`` binned by their ECC correlation: count, RMS error
    (forward, sideways mm, turn deg), RMS of error / stated sigma per axis (1 if the sigmas hold,
    below it they are stated on the safe side) and the largest |error / sigma|."""
    keep = [np.all(np.isfinite(r["meas"]), axis=1) & np.isfinite(r["rho"]) for r in results]
    e = np.vstack([_errors(r)[k] for r, k in zip(results, keep)])
    sig = np.sqrt(np.concatenate([np.diagonal(r["cov"][k], axis1=1, axis2=2) for r, k in zip(results, keep)]))
    rho = np.concatenate([r["rho"][k] for r, k in zip(results, keep)])
    lines = [
        f"{'ECC rho':>9s} {'steps':>6s}  {'rms fwd/lat mm, yaw deg':>24s}  {'rms err/sigma':>18s}  {'max |err/sigma|':>18s}"
    ]
    for lo, hi in zip(RHO_BINS[:-1], RHO_BINS[1:]):
        m = (rho >= lo) & ((rho < hi) if hi < 1.0 else (rho <= hi))
        if not m.any():
            continue
        rms = np.sqrt(np.mean(e[m] ** 2, axis=0))
        z = np.abs(e[m] / sig[m])
        zr, zm = np.sqrt(np.mean(z**2, axis=0)), z.max(axis=0)
        lines.append(
            f"{f'{lo:g}-{hi:g}':>9s} {int(m.sum()):6d}  {1e3 * rms[0]:7.2f} {1e3 * rms[1]:6.2f} {math.degrees(rms[2]):7.3f}"
            f"   {zr[0]:5.2f} {zr[1]:5.2f} {zr[2]:5.2f}   {zm[0]:5.1f} {zm[1]:5.1f} {zm[2]:5.1f}"
        )
    return "\n".join(lines)


def bridged_table(results: list[dict], names: list[str]) -> str:
    """The steps of ``results`` (from :func:`run_session_in_localiser`, walks ``names``) that bridge
    bursts of dropped frames, apart for steps the flow refined and those whose flow fit was refused: count,
    the mean 3-DoF NEES of the sound ones (3 if their covariance is exact), and each gross one."""
    rows, gross = {"flow refined": [], "flow refused": []}, []
    for name, r in zip(names, results):
        e = _errors(r)
        bridged = np.flatnonzero((r["dt"] > BRIDGE_S) & np.all(np.isfinite(r["meas"]), axis=1))
        for k, nees in zip(bridged, _nees(e[bridged], r["cov"][bridged])):
            rows["flow refined" if r["flow_used"][k] else "flow refused"].append(float(nees))
            if nees > GROSS_NEES:
                gross.append((name, r, k, e[k], float(nees)))
    lines = [f"{'bridged steps':14s} {'steps':>6s} {'gross':>6s} {'NEES of the sound ones':>23s}"]
    for label, nees in rows.items():
        sound = [v for v in nees if v <= GROSS_NEES]
        mean = f"{np.mean(sound):.2f}" if sound else "-"
        lines.append(f"{label:14s} {len(nees):6d} {len(nees) - len(sound):6d} {mean:>23s}")
    for name, r, k, ek, nees in gross:
        lines.append(
            f"  gross: {name} t {r['t'][k]:.2f} s, {1e3 * r['dt'][k]:.0f} ms: error {1e3 * math.hypot(ek[0], ek[1]):.0f} mm,"
            f" {math.degrees(ek[2]):.1f} deg (NEES {nees:.0f}, flow residual {r['flow_residual'][k]:.1f} px)"
        )
    return "\n".join(lines)


HEADER = (
    f"{'walk':10s} {'ok %':>5s}  {'rms fwd':>6s} {'lat mm':>6s} {'yaw deg':>6s}  {'turn %':>6s}"
    f"  {'sum yaw err / turned deg':>24s}  {'sum fwd err cm / m':>18s}  {'ms':>5s}"
)


def calibrate(results: list[dict]) -> dict[str, float]:
    """Step sigmas fitted on windows of summed patch-centre errors (see the module docstring)."""
    sums, dsq, n_steps, speed = [], [], [], []
    for r in results:
        odo = r["odo"]
        cx, cy = odo.patch.centre
        G_inv = np.linalg.inv(np.array([[1.0, 0.0, cy], [0.0, 1.0, -cx], [0.0, 0.0, 1.0]]))
        ok = np.all(np.isfinite(r["meas"]), axis=1)
        e = _errors(r)
        ep = e @ G_inv.T  # patch-centre forward, sideways and turn errors
        d = _patch_motion(odo, np.where(ok[:, None], r["meas"], r["true"]))
        for w in WINDOWS:
            for k in range(0, len(e) - w + 1, w):
                sl = slice(k, k + w)
                if not ok[sl].all():
                    continue
                sums.append(ep[sl].sum(axis=0))
                dsq.append(float(np.sum(d[sl] ** 2)))
                n_steps.append(w)
                speed.append(float(np.sum(np.hypot(r["true"][sl, 0], r["true"][sl, 1]))) / (w / 30.0))
    sums, dsq, n_steps, speed = map(np.array, (sums, dsq, n_steps, speed))
    slow, fast = speed < SLOW_MPS, speed > FAST_MPS
    print(f"windows: {slow.sum()} standing (< {SLOW_MPS} m/s), {fast.sum()} walking (> {FAST_MPS} m/s)")
    # Without such windows the sums below are 0 / 0: NaN sigmas and a RuntimeWarning, once.
    if not slow.any():
        print(f"no window slower than {SLOW_MPS} m/s: no sigma fitted (the per-metre ones need the standing ones)")
        return {}
    names = ("forward", "lateral", "yaw")
    s0 = np.sqrt(np.sum(sums[slow] ** 2, axis=0) / np.sum(n_steps[slow]))
    fitted = {f"sigma_{n}": float(v) for n, v in zip(names, s0)}
    if not fast.any():
        print(f"no window faster than {FAST_MPS} m/s: no per-metre sigma fitted")
        return fitted
    per_m2 = (np.sum(sums[fast] ** 2, axis=0) - s0**2 * np.sum(n_steps[fast])) / np.sum(dsq[fast])
    s1 = np.sqrt(np.maximum(per_m2, 0.0))
    return fitted | {f"sigma_{n}_per_m": float(v) for n, v in zip(names, s1)}


def odometry_config(text: str, option: str = "--config") -> OdometryConfig:
    """The :class:`OdometryConfig` with the JSON object ``text``'s overrides, a one-line error naming
    ``option`` for text that is no JSON object or names no field (before, a bug report's line)."""
    from eval_variants import json_object  # (benchmarks/ is on the path of a script run from it)

    from tagloc.core.errors import InputError

    overrides = json_object(text, option, "OdometryConfig fields")
    fields = {f.name for f in dataclasses.fields(OdometryConfig)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise InputError(f"{option}: no OdometryConfig field {', '.join(map(repr, unknown))}")
    return OdometryConfig(**overrides)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sessions", nargs="+", type=Path, help="session directories with groundtruth_frames.jsonl")
    ap.add_argument("--config", default="{}", help="OdometryConfig overrides as JSON (angles in radians)")
    ap.add_argument("--calibrate", action="store_true", help="fit the step sigmas on these sessions")
    ap.add_argument(
        "--by-residual",
        action="store_true",
        help="also bin the steps by the floor flow's median reprojection error (error and NEES)",
    )
    ap.add_argument(
        "--by-rho",
        action="store_true",
        help="also bin the patch-matched steps by ECC correlation (error against the stated sigma)",
    )
    ap.add_argument(
        "--reference",
        choices=("vest", "apparent"),
        default="vest",
        help="compare with the vest's true motion, or with the motion the nominal patch appears to make"
        " (the vest's plus the tilt's apparent motion, which the tracker's tilt offset takes)",
    )
    ap.add_argument(
        "--in-localiser",
        action="store_true",
        help="the steps the whole localiser fuses (lean and pitch from its tracker), not the odometry alone",
    )
    ap.add_argument(
        "--bridged",
        action="store_true",
        help="also the steps that bridge bursts of dropped frames (with --in-localiser)",
    )
    ap.add_argument(
        "--windows", action="store_true", help="also the steps summed over 15-60-step windows against their stated sums"
    )
    args = ap.parse_args(argv)
    config = odometry_config(args.config)
    if args.bridged and not args.in_localiser:
        raise SystemExit("odometry_accuracy: --bridged needs --in-localiser (the steps the localiser fuses)")
    if args.in_localiser and args.reference != "vest":
        raise SystemExit("odometry_accuracy: --in-localiser compares with the vest's motion only")
    results = []
    print(HEADER)
    for path in tqdm(args.sessions, desc="sessions", unit="walk", leave=False):
        if args.in_localiser:
            r = run_session_in_localiser(path, config)
        else:
            r = run_session(path, config, args.reference)
        results.append(r)
        tqdm.write(summary_row(path.name, r))
    if args.by_residual:
        print(residual_table(results))
    if args.by_rho:
        print(rho_table(results))
    if args.windows:
        print(window_table(results))
    if args.bridged:
        print(bridged_table(results, [str(p) for p in args.sessions]))
    if args.calibrate:
        for k, v in calibrate(results).items():
            current = getattr(config, k)
            unit = "deg" if "yaw" in k else "m"
            conv = math.degrees if "yaw" in k else float
            print(
                f"{k:22s} fitted {conv(v):.5f} {unit}{'/m' if 'per_m' in k else ''}  (configured {conv(current):.5f})"
            )


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("odometry_accuracy.py", main))
