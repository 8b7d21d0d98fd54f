"""``tagloc rig fit``: where the camera sits on the vest, from a recorded walk over mapped stickers.

Body frame (as the localiser reports it): origin at the vest's reference point projected vertically
onto the floor, +z up, +x the horizontal direction the operator faces, which on a straight
stretch of walking is the walking direction. The camera's mount is written
``T_body_camera = [Rz(yaw) Ry(pitch) Rx(roll) R0 | (x, y, height)]``: ``R0`` is a level camera
looking along +x (image right = -y, image down = -z), pitch turns the optical axis down,
roll turns the image about the optical axis (positive: clockwise as the camera sees it), yaw
turns the optical axis left of the walking direction. :func:`mount_T` and :func:`mount_angles`
convert between the two; with roll 0 it is :func:`tagloc.core.rig.looking_forward`.

Each decoded, unambiguous sticker gives the camera's pose in the world (``solve_pose``'s
``T_world_camera``, which does not depend on the rig). Then:

* **height, pitch, roll** follow from the camera's height and its rotation's ZYX angles
  (the floor is level, so they need no walking direction);
* **yaw** is the camera's ZYX heading minus the walking direction, over straight stretches: runs
  of fixes whose heading stays steady, that advance along a line (direction: its principal axis,
  signed by the travel).

The torso's gait (bob, sway, nod, swing) is zero-mean over strides and averages out; leaning into
turns and with braking does not, which is why the angles are taken on straight stretches when
there are enough of them. Each value is a robust mean (``scipy.optimize.least_squares`` with a
soft-L1 loss); its standard deviation counts each pass over a sticker once (the frames of one pass
share that sticker's errors). The camera's x, y on the vest are not observable from a walk (they
define where the body point is) and are kept from the prior rig.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from tagloc.core.camera import default_camera, save_calibration
from tagloc.core.errors import InputError
from tagloc.core.geometry import make_T, wrap_angle
from tagloc.core.rig import Rig, RigCamera, load_rig, save_rig
from tagloc.eval.mapobs import frames_text
from tagloc.io.session import SessionReader
from tagloc.vision.decode import decode
from tagloc.vision.detect import detect
from tagloc.vision.pose import solve_pose

#: A level camera looking along body +x: columns are the camera's x (right), y (down), z (optical axis).
R0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def mount_T(
    height_m: float, pitch_deg: float, roll_deg: float = 0.0, yaw_deg: float = 0.0, x_m: float = 0.0, y_m: float = 0.0
) -> np.ndarray:
    """``T_body_camera`` (4, 4) of a camera at ``height_m`` with the module's pitch/roll/yaw (degrees)."""
    R = Rotation.from_euler("ZYX", [yaw_deg, pitch_deg, roll_deg], degrees=True).as_matrix() @ R0
    return make_T(R, (x_m, y_m, height_m))


def mount_angles(T: np.ndarray) -> tuple[float, float, float, float]:
    """(height m, pitch deg, roll deg, yaw deg) of ``T_body_camera`` or ``T_world_camera`` (yaw: heading)."""
    yaw, pitch, roll = Rotation.from_matrix(np.asarray(T)[:3, :3] @ R0.T).as_euler("ZYX", degrees=True)
    return float(T[2, 3]), float(pitch), float(roll), float(yaw)


@dataclass(frozen=True)
class RigFitConfig:
    """Choices of :func:`fit_rig`.

    Attributes:
        camera: which rig camera's frames to use.
        decoder: Data Matrix backend (as ``tagloc replay --decoder``).
        step: use every ``step``-th frame.
        max_gap_s: fixes further apart in time do not belong to one straight stretch.
        heading_tol_deg: a straight stretch's camera headings stay within this of its median
            (the torso's swing is +-2.5 degrees at half the step rate; a turn leaves it quickly).
        min_straight_m: a straight stretch advances at least this far (over 2 m a 2 cm sway
            error changes the direction by under 0.6 degree, and stretches average).
        max_line_rms_m: a straight stretch's fixes lie this close to a line (RMS): rejects arcs.
        min_speed_mps: slower stretches are shuffling, not walking in the facing direction.
        pass_gap_s: a sticker seen again after this long is a new pass.
        independent_s: fixes closer in time than this share errors (one sticker's pass, the
            torso's slow pitch and roll drift, correlated over 1-2 s in standing-sway studies),
            so each such block of time counts as one independent sample in the sigmas.
        min_passes: warn below this many sticker passes for height, pitch and roll.
        min_straight_total_m: warn below this much straight walking for the yaw.
    """

    camera: int = 0
    decoder: str = "zxing"
    step: int = 1
    max_gap_s: float = 1.0
    heading_tol_deg: float = 6.0
    min_straight_m: float = 2.0
    max_line_rms_m: float = 0.06
    min_speed_mps: float = 0.4
    pass_gap_s: float = 0.5
    independent_s: float = 1.5
    min_passes: int = 8
    min_straight_total_m: float = 6.0


@dataclass
class CameraFix:
    """One decoded sticker's camera pose: time (s), sticker ID, ``T_world_camera`` (4, 4)."""

    t: float
    sticker_id: int
    T_world_camera: np.ndarray


@dataclass
class Estimate:
    """A fitted value and its one-sigma uncertainty (units in the name of the field holding it)."""

    value: float
    sigma: float
    samples: int


@dataclass
class RigFit:
    """What :func:`fit_rig` found.

    Attributes:
        height_m, pitch_deg, roll_deg, yaw_deg: the mount (see the module notes), with sigmas.
        T_body_camera: (4, 4) the fitted mount (x, y kept from the prior rig).
        fixes: camera poses used; passes: distinct sticker passes among them.
        stretches: straight stretches found, each (t_start, t_end, length_m, yaw_deg).
        warnings: what the walk did not constrain well.
        frames: the camera's frames looked at (every ``step``-th); skipped: why each of them that
            could not be used was (unreadable, the wrong size), "frame N: ..." each.
    """

    height_m: Estimate
    pitch_deg: Estimate
    roll_deg: Estimate
    yaw_deg: Estimate
    T_body_camera: np.ndarray
    fixes: int
    passes: int
    stretches: list[tuple[float, float, float, float]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    frames: int = 0
    skipped: list[str] = field(default_factory=list)


#: Rolling shutter: corrected solves after the first (measured on a rendered 8 s walk with 30 ms
#: read-out: mean pitch error 2.6 degrees uncorrected, 0.26 / 0.10 / 0.02 after 1 / 2 / 3 passes;
#: roll and yaw 2.7-2.8 uncorrected, within 0.16 after 3).
RS_ITERATIONS = 3


def camera_fixes(
    session: SessionReader,
    rig_camera: RigCamera,
    cfg: RigFitConfig,
    progress: bool = True,
    looked: list[int] | None = None,
    skipped: list[str] | None = None,
) -> list:
    """Decoded, unambiguous camera poses of ``cfg.camera`` over the session, in time order.

    A frame that cannot be used (unreadable, or not an image of the camera's size, which
    :func:`detect` refuses) is skipped, as the localiser skips it: ``skipped`` (if given) gets
    why ("frame N: ..."), and ``looked`` the index of every frame of the camera looked at.

    With a rolling-shutter camera (``rig_camera.readout_s`` > 0) each pose holds when its
    sticker's rows were read (``PoseSolution.row_time_s`` after the frame's time) and is solved
    again with the rows straightened to that time (``solve_pose(body_twist=...)``), the motion taken
    from the first pass's neighbouring fixes (:func:`_twists`).
    """
    seen = []
    frames = session.frames()
    for k, frame in enumerate(tqdm(frames, total=len(session), desc="rig fit", unit="frame", disable=not progress)):
        if k % cfg.step or frame.camera != cfg.camera:
            continue
        if looked is not None:
            looked.append(frame.index)
        cam = rig_camera.camera
        why = frame.error or f"frame {frame.index}: unreadable"
        try:
            dets = None if frame.image is None else detect(frame.image, cam)
        except InputError as exc:  # not an image of this camera (its size, its type): the frame's fault
            dets, why = None, f"frame {frame.index}: {exc}"
        if dets is None:
            if skipped is not None:
                skipped.append(why)
            continue
        for det in dets:
            res = decode(frame.image, det, cam, backend=cfg.decoder)
            if res.sticker_id is None or res.sticker_id not in session.map:
                continue
            T_ws = session.map.T_world_sticker(res.sticker_id)
            sol = solve_pose(det, res.rotation, T_ws, rig_camera)
            if sol.poses and not sol.ambiguous:
                # A rolling-shutter camera's pose holds when the sticker's rows were read.
                fix = CameraFix(frame.timestamp + sol.row_time_s, int(res.sticker_id), sol.poses[0].T_world_camera)
                seen.append((fix, det, res.rotation, T_ws))
    if rig_camera.readout_s <= 0 or not seen:
        return [f for f, *_ in seen]
    fixes = [f for f, *_ in seen]
    for _ in range(RS_ITERATIONS):
        # Each pass takes the motion from the previous pass's (better) poses.
        twists = _twists(fixes, rig_camera.T_body_camera)
        fixes = []
        for (fix, det, rotation, T_ws), twist in zip(seen, twists):
            sol = solve_pose(det, rotation, T_ws, rig_camera, body_twist=twist)
            pose = sol.poses[0].T_world_camera if sol.poses else fix.T_world_camera
            fixes.append(CameraFix(fix.t, fix.sticker_id, pose))
    return fixes


def _twists(fixes: list[CameraFix], T_body_camera: np.ndarray, window_s: float = 0.4) -> list[np.ndarray | None]:
    """Body motion (vx, vy, yaw rate) at each fix from the camera poses within ``window_s``: line
    fits of position and heading against time, turned into the body frame with the prior mount's
    yaw (a few degrees of error in it change the correction by a few per cent). None where the
    neighbours span too little time to tell."""
    t = np.array([f.t for f in fixes])
    xy = np.array([f.T_world_camera[:2, 3] for f in fixes])
    heading = np.unwrap(np.radians([mount_angles(f.T_world_camera)[3] for f in fixes]))
    mount_yaw = math.radians(mount_angles(T_body_camera)[3])
    out: list[np.ndarray | None] = []
    for i in range(len(fixes)):
        near = np.flatnonzero(np.abs(t - t[i]) <= window_s)
        if np.ptp(t[near]) < 0.1:
            out.append(None)
            continue
        v = np.polyfit(t[near], xy[near], 1)[0]
        rate = float(np.polyfit(t[near], heading[near], 1)[0])
        yaw = heading[i] - mount_yaw
        c, sn = math.cos(yaw), math.sin(yaw)
        out.append(np.array([c * v[0] + sn * v[1], -sn * v[0] + c * v[1], rate]))
    return out


def _passes(fixes: list[CameraFix], gap_s: float) -> np.ndarray:
    """(N,) pass number of each fix: the same sticker seen again within ``gap_s`` is the same pass."""
    last: dict[int, tuple[float, int]] = {}
    labels, n = np.zeros(len(fixes), int), 0
    for i, f in enumerate(fixes):
        prev = last.get(f.sticker_id)
        if prev is None or f.t - prev[0] > gap_s:
            prev = (f.t, n)
            n += 1
        labels[i] = prev[1]
        last[f.sticker_id] = (f.t, prev[1])
    return labels


def robust_mean(values: np.ndarray, groups: np.ndarray, angular: bool = False) -> Estimate:
    """Soft-L1 mean of ``values`` (radians wrapped if ``angular``); sigma from the MAD over the
    number of distinct ``groups`` (independent samples)."""
    v = np.asarray(values, float)
    if len(v) == 0:
        return Estimate(math.nan, math.inf, 0)
    centre0 = float(np.median(v)) if not angular else math.atan2(np.sin(v).mean(), np.cos(v).mean())

    def resid(c: np.ndarray) -> np.ndarray:
        r = v - c[0]
        return wrap_angle(r) if angular else r

    mad = 1.4826 * float(np.median(np.abs(resid(np.array([centre0])))))
    scale = max(mad, 1e-9)
    sol = least_squares(resid, [centre0], loss="soft_l1", f_scale=scale)
    centre = float(wrap_angle(sol.x[0])) if angular else float(sol.x[0])
    n_eff = max(len(np.unique(groups)), 1)
    return Estimate(centre, scale / math.sqrt(n_eff) if len(v) > 1 else math.inf, len(v))


def straight_stretches(
    t: np.ndarray, xy: np.ndarray, heading: np.ndarray, cfg: RigFitConfig
) -> list[tuple[np.ndarray, float, float]]:
    """Runs of fixes walking straight: (indices, walking direction rad, length m) each."""
    tol = math.radians(cfg.heading_tol_deg)
    out = []
    i, n = 0, len(t)
    while i < n:
        j = i + 1
        while j < n and t[j] - t[j - 1] <= cfg.max_gap_s:
            ref = math.atan2(np.sin(heading[i : j + 1]).mean(), np.cos(heading[i : j + 1]).mean())
            if abs(wrap_angle(heading[j] - ref)) > tol:
                break
            j += 1
        idx = np.arange(i, j)
        i = j
        if len(idx) < 3:
            continue
        p = xy[idx]
        travel = p[-1] - p[0]
        length = float(np.hypot(*travel))
        duration = float(t[idx[-1]] - t[idx[0]])
        if length < cfg.min_straight_m or duration <= 0 or length / duration < cfg.min_speed_mps:
            continue
        centred = p - p.mean(axis=0)
        _, s, vt = np.linalg.svd(centred, full_matrices=False)
        if s[1] / math.sqrt(len(p)) > cfg.max_line_rms_m:
            continue
        axis = vt[0] if vt[0] @ travel > 0 else -vt[0]
        out.append((idx, math.atan2(axis[1], axis[0]), length))
    return out


def fit_rig_fixes(fixes: list[CameraFix], prior: np.ndarray, cfg: RigFitConfig | None = None) -> RigFit:
    """Fit the mount to camera poses (see the module notes); ``prior`` (4, 4) gives x, y (and the
    yaw when the walk has no straight stretch)."""
    cfg = cfg or RigFitConfig()
    if not fixes:
        raise InputError("no decoded sticker in the session: cannot fit the rig (is the map right?)")
    fixes = sorted(fixes, key=lambda f: f.t)
    t = np.array([f.t for f in fixes])
    T = np.array([f.T_world_camera for f in fixes])
    angles = np.array([mount_angles(Ti) for Ti in T])  # height, pitch, roll, heading
    n_pass = len(np.unique(_passes(fixes, cfg.pass_gap_s)))
    groups = np.floor((t - t[0]) / cfg.independent_s).astype(int)
    heading = np.radians(angles[:, 3])
    runs = straight_stretches(t, T[:, :2, 3], heading, cfg)
    warnings = []
    straight = np.concatenate([r[0] for r in runs]) if runs else np.zeros(0, int)
    on_straights = len(np.unique(groups[straight])) >= cfg.min_passes
    use = straight if on_straights else np.arange(len(fixes))
    # Warn on the fallback itself: a walk with every fix on a straight stretch (the best case)
    # also uses all of them.
    if not on_straights:
        warnings.append(
            "height, pitch and roll from all fixes (too few on straight stretches): leaning in turns may bias them"
        )
    if n_pass < cfg.min_passes:
        warnings.append(f"only {n_pass} sticker passes: walk over at least {cfg.min_passes} stickers")
    height = robust_mean(angles[use, 0], groups[use])
    pitch = robust_mean(np.radians(angles[use, 1]), groups[use], angular=True)
    roll = robust_mean(np.radians(angles[use, 2]), groups[use], angular=True)
    total = sum(r[2] for r in runs)
    _, _, _, prior_yaw = mount_angles(prior)
    if runs:
        offsets = np.concatenate([wrap_angle(heading[idx] - d) for idx, d, _ in runs])
        run_of = np.concatenate([np.full(len(idx), k) for k, (idx, _, _) in enumerate(runs)])
        per_run = np.array(
            [
                math.atan2(np.sin(offsets[run_of == k]).mean(), np.cos(offsets[run_of == k]).mean())
                for k in range(len(runs))
            ]
        )
        lengths = np.array([r[2] for r in runs])
        # Each stretch's direction is worth its length: fit the common offset weighted by it.
        sol = least_squares(
            lambda c: np.sqrt(lengths) * wrap_angle(per_run - c[0]),
            [float(np.median(per_run))],
            loss="soft_l1",
            f_scale=math.radians(1.0),
        )
        yaw_value = float(wrap_angle(sol.x[0]))
        spread = float(np.sqrt(np.sum(lengths * wrap_angle(per_run - yaw_value) ** 2) / lengths.sum()))
        within = robust_mean(offsets, groups[straight], angular=True).sigma
        # Between-stretch scatter over the stretches, or the within-stretch scatter if only one.
        sigma = max(spread / math.sqrt(len(runs)) if len(runs) > 1 else 0.0, within)
        yaw = Estimate(yaw_value, sigma, len(offsets))
        stretches = [(float(t[idx[0]]), float(t[idx[-1]]), L, math.degrees(v)) for (idx, _, L), v in zip(runs, per_run)]
    else:
        yaw = Estimate(math.radians(prior_yaw), math.inf, 0)
        stretches = []
        warnings.append("no straight stretch of walking: yaw not constrained, kept from the prior rig")
    if runs and total < cfg.min_straight_total_m:
        warnings.append(
            f"only {total:.1f} m of straight walking: yaw poorly constrained (walk {cfg.min_straight_total_m:g} m+)"
        )
    pitch_deg = Estimate(math.degrees(pitch.value), math.degrees(pitch.sigma), pitch.samples)
    if abs(pitch_deg.value) > 80:
        warnings.append("the camera looks almost straight down: its yaw and roll are poorly defined")
    fit = RigFit(
        height,
        pitch_deg,
        Estimate(math.degrees(roll.value), math.degrees(roll.sigma), roll.samples),
        Estimate(math.degrees(yaw.value), math.degrees(yaw.sigma), yaw.samples),
        mount_T(
            height.value, pitch_deg.value, math.degrees(roll.value), math.degrees(yaw.value), prior[0, 3], prior[1, 3]
        ),
        len(fixes),
        n_pass,
        stretches,
        warnings,
    )
    # Beyond these sigmas the mount would cost the localiser more than its own fix noise does
    # (1 degree of tilt moves a floor point seen 2 m away by 3.5 cm).
    for name, est, limit in (
        ("height", fit.height_m, 0.01),
        ("pitch", fit.pitch_deg, 1.0),
        ("roll", fit.roll_deg, 1.0),
        ("yaw", fit.yaw_deg, 1.0),
    ):
        if runs or name != "yaw":
            if not est.sigma <= limit:
                unit = "m" if name == "height" else "deg"
                warnings.append(f"{name} uncertain: sigma {est.sigma:.3g} {unit} > {limit:g} {unit}")
    return fit


def fit_rig(
    session_dir: str | Path,
    out: str | Path,
    prior_rig: str | Path | None = None,
    cfg: RigFitConfig | None = None,
    progress: bool = True,
) -> RigFit:
    """Fit camera ``cfg.camera``'s mount from the session's walk and write ``out`` (rig.json).

    The other cameras of the prior rig (``prior_rig``, else the session's rig) are written unchanged;
    the file gains a ``"fit"`` record of the values, sigmas and warnings.
    """
    out = Path(out)
    cfg = cfg or RigFitConfig()
    if not out.parent.exists():
        raise InputError(f"{out}: directory {out.parent} does not exist")
    session = SessionReader(session_dir)
    rig = load_rig(prior_rig, session.camera) if prior_rig else session.rig
    if not 0 <= cfg.camera < len(rig):
        raise InputError(f"camera {cfg.camera} is not in the rig ({len(rig)} cameras)")
    rc = rig[cfg.camera]
    looked: list[int] = []
    skipped: list[str] = []
    fixes = camera_fixes(session, rc, cfg, progress, looked, skipped)
    if looked and len(skipped) == len(looked):
        # Every frame bad is the frames' fault, not the map's ("no decoded sticker" would blame it).
        raise InputError(f"{session.path}: none of its {len(looked)} frames could be used ({skipped[0]})")
    fit = fit_rig_fixes(fixes, rc.T_body_camera, cfg)
    fit.frames, fit.skipped = len(looked), skipped
    cams = list(rig.cameras)
    # The vest point defaults to the camera's height (tagloc.core.rig): a one-camera rig whose vest
    # height was that default follows the fitted height; a stated one is kept.
    follows = len(rig) == 1 and abs(rc.vest_height_m - rc.T_body_camera[2, 3]) < 1e-9
    vest_h = fit.height_m.value if follows else rc.vest_height_m
    cams[cfg.camera] = replace(rc, T_body_camera=fit.T_body_camera, vest_height_m=vest_h)  # read-out kept
    # The calibration is written next to the rig only when absent: never overwrite the user's file.
    save_rig(Rig(cams), out, write_calibrations=False)
    for c in cams:
        if not (out.parent / c.calibration_file).exists():
            save_calibration(c.camera, out.parent / c.calibration_file)
    doc = json.loads(out.read_text(encoding="utf-8"))
    doc["fit"] = {
        "session": str(session_dir),
        "camera": cfg.camera,
        **{
            k: {kk: _finite(vv) for kk, vv in asdict(getattr(fit, k)).items()}
            for k in ("height_m", "pitch_deg", "roll_deg", "yaw_deg")
        },
        "fixes": fit.fixes,
        "passes": fit.passes,
        "frames": fit.frames,
        "frames_skipped": len(fit.skipped),
        "straight_m": round(sum(s[2] for s in fit.stretches), 3),
        "warnings": fit.warnings,
    }
    out.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return fit


def _finite(v: float | int) -> float | int | None:
    """JSON has no inf/NaN: an unconstrained sigma is written as null."""
    return v if isinstance(v, int) or math.isfinite(v) else None


def format_fit(fit: RigFit) -> str:
    """The fit as a table with uncertainties, the stretches used and the warnings."""
    lines = [
        f"{fit.fixes} camera poses from {fit.passes} sticker passes, {len(fit.stretches)} straight stretches "
        f"({sum(s[2] for s in fit.stretches):.1f} m)",
        *([frames_text(fit.frames, fit.skipped, "unreadable or the wrong size")] if fit.skipped else []),
        f"{'':<8}{'value':>10}{'1-sigma':>10}",
        f"{'height':<8}{fit.height_m.value:>9.4f}m{fit.height_m.sigma:>9.4f}m",
    ]
    for name in ("pitch", "roll", "yaw"):
        e = getattr(fit, f"{name}_deg")
        lines.append(f"{name:<8}{e.value:>9.3f}d{e.sigma:>9.3f}d")
    lines.append("(pitch: optical axis below horizontal; roll: image turned clockwise; yaw: left of walking direction)")
    lines += [f"warning: {w}" for w in fit.warnings]
    return "\n".join(lines)


def check_rig_file(path: str | Path) -> str:
    """Each camera's mount in ``rig.json`` as height, pitch, roll and yaw, and whether the odometry
    takes it to see the wearer's legs (for ``tagloc rig show``)."""
    rig = load_rig(path, calibration=default_camera())  # only the mounts are shown
    rows = [f"{'camera':<10}{'height m':>10}{'pitch':>9}{'roll':>9}{'yaw':>9}{'x m':>8}{'y m':>8}"]
    for c in rig.cameras:
        h, p, r, y = mount_angles(c.T_body_camera)
        rows.append(
            f"{c.name:<10}{h:>10.4f}{p:>9.3f}{r:>9.3f}{y:>9.3f}{c.T_body_camera[0, 3]:>8.3f}{c.T_body_camera[1, 3]:>8.3f}"
        )
    rows += [line for line in (_legs_line(c) for c in rig.cameras) if line]
    return "\n".join(rows)


def _legs_line(c: RigCamera) -> str | None:
    """What ``tagloc rig show`` says about the wearer's legs in camera ``c``'s view, if anything."""
    from tagloc.vision.odometry import OdometryConfig, nearest_floor_ahead

    reach = OdometryConfig().legs_reach_m
    out = f"the floor odometry leaves out the floor up to {reach:.2f} m ahead of the vest point"
    if c.legs_in_view is not None:
        return f"{c.name}: legs_in_view {'true' if c.legs_in_view else 'false'}" + (
            f": {out}" if c.legs_in_view else ""
        )
    near = nearest_floor_ahead(c)
    if near is None or near >= reach:
        return None
    return (
        f"{c.name}: sees the floor from {near:.2f} m ahead of the vest point (with the Pi camera v1's field of view),"
        f' where the wearer\'s feet step, so {out} (legs_in_view not stated; "legs_in_view": false if no feet'
        " ever appear in its frames)"
    )
