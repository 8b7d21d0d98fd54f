"""Rolling-shutter fixes measured: the corrections on true corners, and the localiser's own fixes.

Run: ``python benchmarks/rolling_shutter_fixes.py [--seeds 3] [--seconds 15] [--corner-noise-px 0.11]
[--variants default,rs-fix-frame-time,rs-fix-body-twist,no-rs-correction] [-o out/rolling_shutter_fixes]
[--json out/rolling_shutter_fixes.json]``.

The walks are ``benchmarks/field_sensor.py``'s "rolling" ones (30 ms read-out, 150 lux, 1.3 m/s, pitch
55 deg on a 24 x 14 m grid map, seed 100 + s): the same sessions, cached in the output directory
(``-o out/field_sensor`` shares that benchmark's). The walk's truth is the walk itself, rebuilt with
:func:`tagloc.sim.simulate.simulate_walk` from the same map and settings (checked against the session's
``groundtruth_frames.jsonl``). Two tables, each pooled over the seeds:

1. **True corners** (no images): at every frame time k / fps, each mapped sticker wholly in the image in
   that frame and the one before has its 8 corners (outer then inner) projected through the walk's
   rolling-shutter camera, each with the camera's pose at its own row's time (three fixed-point steps
   from the frame time's projection), plus Gaussian noise (``--corner-noise-px`` RMS per corner, seeded
   by frame and sticker, so a sticker's previous sight is the same noisy corners). The camera pose is
   solved by ``cv2.solvePnP`` (IPPE) on the corners straightened to their mean row's time by: nothing;
   the body's true planar motion (vest point velocity and yaw rate, through
   :func:`tagloc.vision.pose.rolling_shutter_shift`: the localiser's fallback); the corners' own image
   motion since the previous frame (their backward difference: the localiser's default); the camera's
   exact instantaneous twist (central differences of its true pose). Both twists act on the corners'
   true points in the camera. Errors against the true camera pose at the corners' mean row time.
2. **The localiser's accepted fixes**: each session replayed by :class:`tagloc.pipeline.localiser.Localiser`
   on its map (exact: these walks have no survey error, so the error is the camera model's own) with
   each variant of ``field_sensor.py``; each accepted fix's camera pose (its best solution) against the
   true camera pose at the fix's own time, the frame's true time plus the sticker rows' time
   (:attr:`tagloc.vision.pose.PoseSolution.row_time_s`, which the localiser does not keep: re-solved).

Each table gives the camera position error's RMS (cm), its RMS over the errors under 20 cm (how the
README's first true-corner figures were taken) and its median, the rotation angle's RMS (deg), and how
many position errors are over 20 cm.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
from field_sensor import make, sim_config, variants, walk_map  # this script's folder: field_sensor.py's walks
from scipy.spatial.transform import Rotation

from tagloc.core.geometry import T_from_rvec_tvec, invert, transform_points, wrap_angle
from tagloc.core.rig import RigCamera, row_delay_s
from tagloc.core.sticker import ALL_CORNERS
from tagloc.core.stickermap import StickerMap
from tagloc.io.session import SessionReader
from tagloc.pipeline.localiser import Localiser
from tagloc.pipeline.run import iterate_results
from tagloc.sim.simulate import read_groundtruth_frames, simulate_walk, true_corners
from tagloc.sim.walk import Walk
from tagloc.vision.pose import rolling_shutter_shift, solve_pose

METHODS = ("uncorrected", "planar body motion", "corners' own motion", "exact camera twist")
VARIANTS = {
    "default": "sticker rows' time, corners' own motion",
    "rs-fix-body-twist": "sticker rows' time, planar body motion",
    "rs-fix-frame-time": "frame's time, planar body motion",
    "no-rs-correction": "no correction (nor of the odometry)",
}
GROSS_M = 0.20  # m, the "over 20 cm" column
_H = 1e-4  # s, central differences of the true motion
_NEAR_M = 3.0  # stickers this near the camera (horizontally) are tried for the view


def camera_poses(walk: Walk, rc: RigCamera, times) -> np.ndarray:
    """The camera's true poses (N, 4, 4) at ``times`` (s)."""
    return walk.T_world_camera(np.atleast_1d(np.asarray(times, float)), rc.T_body_camera)


def exact_twist(walk: Walk, rc: RigCamera, t: float) -> tuple[np.ndarray, np.ndarray]:
    """The camera's true (v m/s, w rad/s) in its own frame at ``t``."""
    Ta, Tb, Tc = camera_poses(walk, rc, [t - _H, t + _H, t])
    v = Tc[:3, :3].T @ (Tb[:3, 3] - Ta[:3, 3]) / (2 * _H)
    w = Rotation.from_matrix(Ta[:3, :3].T @ Tb[:3, :3]).as_rotvec() / (2 * _H)
    return v, w


def planar_twist(walk: Walk, rc: RigCamera, t: float) -> np.ndarray:
    """The body's true planar motion (vx, vy, yaw rate) in the body frame at ``t``: the ground truth's
    (vest point on the floor, heading) rates."""
    a, b, c = walk.groundtruth(np.array([t - _H, t + _H, t]), rc.vest_point)
    vx, vy = (b[:2] - a[:2]) / (2 * _H)
    co, si = math.cos(c[2]), math.sin(c[2])
    return np.array([co * vx + si * vy, -si * vx + co * vy, wrap_angle(b[2] - a[2]) / (2 * _H)])


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(camera position error m, rotation angle rad) of an estimated camera pose."""
    angle = Rotation.from_matrix(T_est[:3, :3].T @ T_true[:3, :3]).magnitude()
    return float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])), float(angle)


def rolling_corners(walk: Walk, smap: StickerMap, rc: RigCamera, sticker_id: int, t: float) -> np.ndarray | None:
    """Sticker ``sticker_id``'s 8 corners (px, outer then inner) in the rolling-shutter frame of time ``t``,
    each seen from the camera's pose at its own row's time; None unless all are in the image."""
    cam = rc.camera
    px = true_corners(smap, cam, camera_poses(walk, rc, t)[0], sticker_id)
    if px is None:
        return None
    pts = transform_points(smap.T_world_sticker(sticker_id), ALL_CORNERS)
    for _ in range(3):
        T = camera_poses(walk, rc, t + row_delay_s(np.clip(px[:, 1], 0, cam.height - 1), cam.height, rc.readout_s))
        X = np.einsum("nji,nj->ni", T[:, :3, :3], pts - T[:, :3, 3])  # each corner in its own row's camera
        if np.any(X[:, 2] <= 0):
            return None
        px = cam.project(X)
    if np.any(px < 0) or np.any(px > (cam.width - 1, cam.height - 1)):
        return None
    # Far outside the view the distortion polynomial folds points back into the image: the corners must
    # undistort to where the pinhole puts them.
    ideal = X[:, :2] / X[:, 2:] @ cam.K[:2, :2].T + cam.K[:2, 2]
    if not np.allclose(cam.undistort_pixels(px), ideal, atol=1.0):
        return None
    return px


def straightened(
    walk: Walk, rc: RigCamera, T_world_sticker: np.ndarray, t: float, img: np.ndarray, prev: np.ndarray, fps: float
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The true camera pose at the corners' mean row's time, and the corners ``img`` (seen in the frame of
    time ``t``; ``prev``: the frame before) moved to that time by each method."""
    cam = rc.camera
    d = row_delay_s(img[:, 1], cam.height, rc.readout_s)
    at = float(d.mean())
    dd = (d - at)[:, None]
    T_true = camera_poses(walk, rc, t + at)[0]
    X = transform_points(invert(T_true) @ T_world_sticker, ALL_CORNERS)  # the corners in the camera then
    v, w = exact_twist(walk, rc, t + at)
    return T_true, {
        "uncorrected": img,
        "planar body motion": img + rolling_shutter_shift(X, img, rc, planar_twist(walk, rc, t + at), at),
        "corners' own motion": img - dd * (img - prev) * fps,
        "exact camera twist": img + cam.project(X) - cam.project(X - dd * (v + np.cross(w, X))),
    }


def true_corner_errors(
    walk: Walk, smap: StickerMap, rc: RigCamera, seconds: float, fps: float, noise_px: float, seed: int
) -> dict[str, list[tuple[float, float]]]:
    """Per method, the (position m, rotation rad) errors of every sticker sight with a previous sight."""
    import cv2

    out: dict[str, list[tuple[float, float]]] = {m: [] for m in METHODS}
    prev: dict[int, np.ndarray] = {}
    for k in range(int(math.floor(seconds * fps + 1e-9))):
        t = k / fps
        T_mid = camera_poses(walk, rc, t)[0]
        seen = {}
        for row in smap.within(T_mid[0, 3], T_mid[1, 3], _NEAR_M):
            sid = int(smap.ids[row])
            px = rolling_corners(walk, smap, rc, sid, t)
            if px is None:
                continue
            rng = np.random.default_rng([seed, k, sid])
            seen[sid] = img = px + rng.normal(0.0, noise_px / math.sqrt(2.0), px.shape)
            if sid not in prev:
                continue
            T_ws = smap.T_world_sticker(sid)
            T_true, by_method = straightened(walk, rc, T_ws, t, img, prev[sid], fps)
            for method, pts in by_method.items():
                _, rvec, tvec = cv2.solvePnP(
                    ALL_CORNERS, pts.reshape(-1, 1, 2), rc.camera.K, rc.camera.dist, flags=cv2.SOLVEPNP_IPPE
                )
                out[method].append(pose_error(T_ws @ invert(T_from_rvec_tvec(rvec, tvec)), T_true))
        prev = seen
    return out


def fix_errors(path: Path, walk: Walk, config) -> tuple[list[tuple[float, float]], int]:
    """The (position m, rotation rad) errors of the localiser's accepted fixes over session ``path``, and
    how many of them were ambiguous (two solutions; the best one is measured)."""
    session = SessionReader(path)
    loc = Localiser(session.map, session.rig, config, map_path=session.map_path)
    true_t = {g["index"]: g["t"] for g in read_groundtruth_frames(path)}
    errors, ambiguous = [], 0
    for res in iterate_results(session, loc):
        for obs in res.observations:
            fix = obs.fix
            if fix is None or not fix.accepted or not fix.poses:
                continue
            rc = session.rig[obs.camera]
            T_ws = session.map.T_world_sticker(obs.identity.sticker_id)
            row_time = solve_pose(obs.detection, obs.identity.rotation, T_ws, rc, config=config.pose).row_time_s
            T_true = camera_poses(walk, rc, true_t[res.index] + row_time)[0]
            errors.append(pose_error(fix.poses[0].T_world_camera, T_true))
            ambiguous += fix.ambiguous
    return errors, ambiguous


def summary(errors: list[tuple[float, float]]) -> dict:
    """RMS and median of the camera position errors (all, and those under ``GROSS_M``), RMS of the
    rotation errors, and how many are over ``GROSS_M``."""
    e = np.array(errors, float).reshape(-1, 2)
    small = e[e[:, 0] < GROSS_M, 0]

    def rms(a: np.ndarray) -> float:
        return float(np.sqrt(np.mean(a**2))) if len(a) else math.nan

    return {
        "n": len(e),
        "position_rms_cm": 100 * rms(e[:, 0]),
        "position_rms_under_20cm_cm": 100 * rms(small),
        "position_median_cm": 100 * float(np.median(e[:, 0])) if len(e) else math.nan,
        "rotation_rms_deg": math.degrees(rms(e[:, 1])),
        "over_20cm": int(len(e) - len(small)),
    }


def print_table(title: str, rows: dict[str, dict], label: dict[str, str] | None = None) -> None:
    label = label or {}
    width = max(len(label.get(k, k)) for k in rows)
    print(f"\n{title}")
    print(
        f"{'':{width}s} {'n':>6s} {'pos RMS cm':>10s} {'<20cm RMS':>10s} {'pos med cm':>10s} {'rot RMS deg':>11s}"
        f" {'over 20 cm':>10s}"
    )
    for k, s in rows.items():
        print(
            f"{label.get(k, k):{width}s} {s['n']:6d} {s['position_rms_cm']:10.2f}"
            f" {s['position_rms_under_20cm_cm']:10.2f} {s['position_median_cm']:10.2f}"
            f" {s['rotation_rms_deg']:11.3f} {s['over_20cm']:10d}",
            flush=True,
        )


def check_truth(path: Path, walk: Walk, rc: RigCamera) -> None:
    """The rebuilt walk must be the session's: its camera poses against ``groundtruth_frames.jsonl``."""
    gt = read_groundtruth_frames(path)
    T = camera_poses(walk, rc, [g["t"] for g in gt])
    worst = float(np.max(np.abs(T - np.array([g["T_world_camera"] for g in gt])))) if gt else math.inf
    if not worst < 1e-5:
        raise SystemExit(f"{path}: the rebuilt walk is not the session's (camera poses {worst:.2g} off)")


def main() -> None:
    import cv2

    cv2.setNumThreads(1)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--corner-noise-px", type=float, default=0.11, help="RMS per corner (px) on the true corners")
    ap.add_argument("--variants", default=",".join(VARIANTS), help="the localiser's, from field_sensor.py")
    ap.add_argument("-o", "--out", type=Path, default=Path("out/rolling_shutter_fixes"))
    ap.add_argument("--json", type=Path, help="also write the figures as JSON")
    args = ap.parse_args()
    vs = variants()
    names = args.variants.split(",")
    t0 = time.perf_counter()
    corners: dict[str, list] = {m: [] for m in METHODS}
    fixes: dict[str, list] = {v: [] for v in names}
    ambiguous = dict.fromkeys(names, 0)
    for s in range(args.seeds):
        seed = 100 + s
        cfg = sim_config(seed, args.seconds, "rolling")
        path = make(args.out / f"rolling-{s}", seed, args.seconds, "rolling")
        smap, rc = walk_map(seed), cfg.build_rig()[0]
        walk = simulate_walk(smap, cfg)
        check_truth(path, walk, rc)
        for m, e in true_corner_errors(walk, smap, rc, args.seconds, cfg.fps, args.corner_noise_px, seed).items():
            corners[m] += e
        for v in names:
            e, amb = fix_errors(path, walk, vs[v])
            fixes[v] += e
            ambiguous[v] += amb
        print(f"seed {seed}: done at {time.perf_counter() - t0:.0f} s", flush=True)
    result = {
        "seeds": [100 + s for s in range(args.seeds)],
        "seconds": args.seconds,
        "corner_noise_px": args.corner_noise_px,
        "true_corners": {m: summary(e) for m, e in corners.items()},
        "fixes": {v: summary(e) | {"ambiguous": ambiguous[v]} for v, e in fixes.items()},
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    print_table(
        f"True corners ({args.corner_noise_px:g} px noise), camera pose at the corners' mean row time",
        result["true_corners"],
    )
    print_table("The localiser's accepted fixes, camera pose at the fix's own time", result["fixes"], VARIANTS)
    print(f"\n{result['wall_s']:.0f} s")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("rolling_shutter_fixes.py", main))
