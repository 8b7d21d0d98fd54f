"""Camera and body pose from one identified sticker, with a covariance from the corner noise.

IPPE_SQUARE on the four outer corners gives the two planar-pose candidates; each is refined by
Levenberg-Marquardt on every corner the detector found (outer + inner black-frame corners). The
covariance of the 6-DoF pose is sigma^2 (J^T J)^-1 with J the reprojection Jacobian from
``cv2.projectPoints``, plus the pose's response to an error all corners share (the outline seen
larger or smaller, ``PoseConfig.outline_scale_px``), propagated to the body's planar (x, y, yaw) by
a central-difference Jacobian.
The body's planar pose is the vest point projected vertically onto the floor and the horizontal
heading of the body's +x axis (:func:`tagloc.core.rig.vest_planar`), not the body origin carried
through the tilted torso: every degree of torso tilt would swing that origin, 1.3 m down the
torso's axis, by 2.3 cm. The vest point sits at the camera's mount, so its position is about as
well determined as the camera centre's (~1 cm at 1.4 m and 0.3 px: worse than a point on the floor
near the sticker, but it is where the operator is, whatever the torso's tilt).
When the second IPPE solution explains the corners about as well as the first (within a chi-square
margin of the corner noise), both are returned, best first, and the solution is flagged ambiguous.

The map is a measurement too: a sticker surveyed ``e`` off in position moves the fix by ``e``, and
one ``a`` off in yaw turns the whole fix about the sticker's centre, moving the body by ``a`` times
its distance from the sticker (1.5 m and 1 degree: 2.6 cm) and its heading by ``a``. A fix used on
its own (the paper's baselines) carries that in its covariance (``map_sigma``:
:func:`map_covariance`). tagloc's tracker instead estimates each sticker's survey error as a state
(:mod:`tracker.ekf`), because the error is the same in every frame that sees the sticker: the
localiser then solves without it and hands the tracker the sticker's survey sigmas.

A rolling-shutter camera (``RigCamera.readout_s`` > 0) exposes each row at its own time, so a
moving camera sees each corner from a slightly different pose: the sticker is skewed and, lower
in the image, seen later than the frame's time (the middle row's). The pose is solved for the
time the sticker itself was read, its corners' mean row's (``PoseSolution.row_time_s`` after the
frame's time; ``PoseConfig.at_sticker_rows``), and the tracker fuses it at that time. Given the
body's motion (``body_twist``: from the floor odometry's last step or the tracker's prediction),
the solver first solves as usual, then moves each corner to where it would have been seen at that
time (:func:`rolling_shutter_shift`: the corner's point in the camera, moved back by the camera's
velocity over its row's delay, projected) and solves again on the corrected corners.

Why the sticker's own time and not the frame's: the correction extrapolates the corners with one
twist over each row's delay. To the frame's middle row that is up to half the read-out (15 ms at
30 ms), and a walking torso's pitch and roll rates change within that (the gait's nod, heel
strikes), which a first-order shift cannot follow; to the sticker's mean row it is only the
sticker's own spread of rows (a 10 cm sticker at 1-2 m spans 60-120 of 972 rows: +-1-2 ms).
Measured on the simulator's true corners of the field walk f02 (30 ms read-out, the walk's exact
instantaneous twist): camera position RMS 12.5 cm uncorrected, 2.46 cm corrected to the frame's
time, 0.06 cm corrected to the sticker's time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from tagloc.core.errors import InputError
from tagloc.core.geometry import T_from_rvec_tvec, invert, map_error_jacobian, wrap_angle
from tagloc.core.rig import RigCamera, row_delay_s, vest_planar
from tagloc.core.sticker import ALL_CORNERS, OUTER_CORNERS, rotate_corners
from tagloc.core.types import Detection, PoseFix
from tagloc.vision.torso_tilt import TRUNK_TILT_RATE_SIGMA


@dataclass
class PoseConfig:
    """Options of :func:`solve_pose`.

    Attributes:
        use_inner: refine with the inner frame corners when the detector gives them.
        min_sigma_px: floor of the corner noise estimated from the residual (pixels).
        sigma_4pt_px: corner noise assumed with only the 4 outer corners (2 residual dof are too few
            to estimate it).
        ambiguity_chi2: keep the second IPPE solution when its sum of squared residuals exceeds
            the best one's by less than this many sigma^2.
        max_reprojection_px: solutions with a larger RMS reprojection error are dropped.
        outline_scale_px: standard deviation (px) of an error every corner of one sticker shares:
            each moved along its direction from the corners' centre, so that the outline is seen
            a little larger or smaller. Blur, gamma-encoded shading, JPEG and the lens model's
            residual move the located edges of all four sides alike, and a focal length known to
            a few tenths of a percent scales the outline the same way; corners moved so fit with
            no residual (the camera a little nearer or further), so the corner noise estimated
            from the residual cannot contain it. Its effect on range grows with the distance
            squared (a quarter of a pixel on each corner of a 33 px sticker 3 m away is 1 % of the range).
            Against the simulator's true corners the shared outward error was 0.03 px on
            stickers 75-100 px across and 0.23 px under 40 px; 0.25 px covers the smallest for
            every size, since which cause dominates on a given camera is not known (on large
            stickers the term is small anyway). Without it, fixes 2-3 m away were 1.2-3.6 cm
            short of the truth against a stated 1-2 cm and a walk with the camera pitched 45 deg
            ended overconfident (see the README's Field physics). 0: no such term.
        map_sigma_m, map_sigma_yaw: survey standard deviation of a sticker's centre (per axis, m)
            and yaw (rad) where the map does not state one. Stickers are stuck down by hand and
            measured with tape or a laser: 1.5 cm and 1.5 degrees, the middle of the 1-2 cm and 1-2
            degrees such surveys achieve (a total-station survey states its own, smaller, sigmas in
            the map). Too small a value makes a mis-surveyed sticker's fixes fail the gate pass
            after pass, or pass it and pull the track overconfidently; too large one only leans on
            odometry a little more.
        at_sticker_rows: with a rolling-shutter camera, solve the pose for the time the sticker's
            rows were read (:attr:`PoseSolution.row_time_s`) instead of the frame's time (see the
            module docstring); False: the frame's time, the correction spanning half the read-out.
        unknown_twist_sigma: (vx m/s, vy m/s, yaw rate rad/s) of the body's motion when nothing
            measured it (no ``body_twist``, no ``corner_velocity``: a rolling-shutter camera's
            first frame after a blind spell, before the tracker knows a velocity). The sticker is
            then solved sheared by whatever motion there was: a 10 cm sticker read over 3 ms while
            the camera moves 4 mm is sheared by 4 %, which the solve takes for a tilt of a degree
            or two, and the vest point 1.3 m below moves 3-6 cm. Its covariance gets the pose's
            response to each component at this sigma (the solve repeated with the corners
            straightened for it). 1 m/s forward: the root mean square of a walking speed anywhere
            in 0-2 m/s (1.15) rounded to the tracker's own start-up sigma; 0.3 m/s sideways (sway
            and sidesteps); 1 rad/s of turn (the tracker's start-up sigma, a walking turn's
            rate). Zeros: no such term (the fix's covariance is its corner noise alone).
        estimated_twist_term: likewise for a ``body_twist`` that is an estimate with sigmas
            (``body_twist_sigma``: the tracker's prediction when no odometry step measured the
            motion): the shear those sigmas leave. False: such a twist is taken as exact.
        tilt_rate_sigma: the torso's pitch and roll rates (rad/s, standard deviation of each)
            while a rolling-shutter frame is read, when the corners are straightened by the
            body's planar twist (measured, estimated or unknown) rather than by their own image
            velocity: a planar twist has no pitch or roll, and a sticker read while the camera
            pitches is stretched or squeezed along its rows, which the solve takes for a tilt
            (the vest point 1.3 m below moves with it). The fix's covariance gets the pose's response to
            each rate at this sigma. Default: the trunk's tilt rate
            (:data:`tagloc.vision.torso_tilt.TRUNK_TILT_RATE_SIGMA`). Without it, the 15 fps
            walk's fixes of a sticker read at rows 680-800 of 972 while the torso pitched at
            16-25 deg/s (a turn's onset) were 6-10 cm off at a stated 1.1-1.2 cm; solved with the
            corners' true image velocities instead, 0.2-0.9 cm. 0: no such term.
    """

    use_inner: bool = True
    min_sigma_px: float = 0.3
    sigma_4pt_px: float = 0.5
    ambiguity_chi2: float = 16.0
    max_reprojection_px: float = 5.0
    outline_scale_px: float = 0.25
    map_sigma_m: float = 0.015
    map_sigma_yaw: float = math.radians(1.5)
    at_sticker_rows: bool = True
    unknown_twist_sigma: tuple[float, float, float] = (1.0, 0.3, 1.0)
    estimated_twist_term: bool = True
    tilt_rate_sigma: float = TRUNK_TILT_RATE_SIGMA

    def survey_sigmas(self, sigma_m: float, sigma_yaw: float) -> tuple[float, float]:
        """A sticker's survey sigmas (m per axis, rad of yaw): the map's where it states them, else
        (NaN) ``map_sigma_m`` / ``map_sigma_yaw``."""
        return (
            float(sigma_m) if math.isfinite(sigma_m) else self.map_sigma_m,
            float(sigma_yaw) if math.isfinite(sigma_yaw) else self.map_sigma_yaw,
        )


@dataclass
class PoseSolution:
    """Result of :func:`solve_pose`: 0-2 fixes, best first; ``ambiguous`` when 2 are plausible."""

    poses: list[PoseFix]
    ambiguous: bool
    sigma_px: float = 0.0  # corner noise used for the covariances
    # When the poses hold, in seconds after the frame's time: a rolling-shutter camera's sticker is
    # solved at its corners' mean row's time (PoseConfig.at_sticker_rows); 0 otherwise.
    row_time_s: float = 0.0


def _body_from_rt(
    r: np.ndarray, t: np.ndarray, T_world_sticker: np.ndarray, T_camera_body: np.ndarray, vest_point: np.ndarray
) -> np.ndarray:
    """Body (x, y, yaw) (vest point on the floor, heading) for sticker-in-camera pose (rvec ``r``, tvec ``t``)."""
    T_world_camera = T_world_sticker @ invert(T_from_rvec_tvec(r, t))
    return vest_planar(T_world_camera @ T_camera_body, vest_point)


def _row_times(img: np.ndarray, rig_camera: RigCamera, at_sticker_rows: bool) -> tuple[np.ndarray, float]:
    """Each corner's row delay (N,) s after the frame's time (zeros for a global shutter) and the
    time the pose is solved for: the corners' mean delay with ``at_sticker_rows`` on a
    rolling-shutter camera, else 0 (the frame's time)."""
    if rig_camera.readout_s <= 0:
        return np.zeros(len(img)), 0.0
    delays = row_delay_s(img[:, 1], rig_camera.camera.height, rig_camera.readout_s)
    return delays, float(np.mean(delays)) if at_sticker_rows else 0.0


def _twist_sigma(
    rig_camera: RigCamera,
    body_twist: np.ndarray | None,
    corner_velocity: np.ndarray | None,
    body_twist_sigma: np.ndarray | None,
    config: PoseConfig,
) -> tuple[float, float, float] | None:
    """The sigmas (vx, vy, yaw rate) of the motion a rolling-shutter frame was read under that the
    straightening did not know (:func:`_unknown_motion_cov`): ``config.unknown_twist_sigma`` with
    nothing given, ``body_twist_sigma`` with an estimated ``body_twist``; None with a global shutter,
    the corners' own velocity or an exact twist."""
    if rig_camera.readout_s <= 0 or corner_velocity is not None:
        return None
    if body_twist is None:
        return config.unknown_twist_sigma
    if body_twist_sigma is None or not config.estimated_twist_term:
        return None
    sd = np.asarray(body_twist_sigma, float).ravel()
    if sd.shape != (3,) or not np.all(np.isfinite(sd)) or np.any(sd < 0):
        raise InputError(f"solve_pose: body_twist_sigma {sd} is not three finite sigmas >= 0")
    return (float(sd[0]), float(sd[1]), float(sd[2]))


def _unknown_motion_cov(
    J: np.ndarray,
    Jb: np.ndarray,
    points_camera: np.ndarray,
    img: np.ndarray,
    rig_camera: RigCamera,
    row_time: float,
    sigmas: tuple[float, float, float] | None,
    tilt_rate_sigma: float,
) -> np.ndarray:
    """(3, 3) covariance of the body pose (x, y, yaw) from the motion a rolling-shutter frame was
    read under that the straightening did not know, to first order: the body's planar twist when
    it is unknown (``PoseConfig.unknown_twist_sigma``) or only estimated (``sigmas`` the
    estimate's; None: measured, no such part), and the torso's pitch and roll rates, which a
    planar twist never holds (``tilt_rate_sigma``, rad/s, each; a rotation of the camera about its
    own centre). For each component at its sigma: the corners' shear (``points_camera`` (N, 3) the
    solved corners in the camera), the least-squares pose's response to it through the
    reprojection Jacobian ``J`` (2N, 6), and the body's through ``Jb`` (3, 6); the components
    independent."""
    R_bc = rig_camera.T_body_camera[:3, :3]
    motions = []  # the camera's (v, w) for each component at its sigma
    for k, sigma in enumerate(sigmas or ()):
        if sigma > 0:
            twist = np.zeros(3)
            twist[k] = sigma
            motions.append(camera_twist(rig_camera, twist))
    if tilt_rate_sigma > 0:
        for axis in (0, 1):  # roll about the body's +x (forward), pitch about its +y (left)
            w_body = np.zeros(3)
            w_body[axis] = tilt_rate_sigma
            motions.append((np.zeros(3), R_bc.T @ w_body))
    fit = np.linalg.pinv(J)  # (6, 2N): pose change per corner displacement
    cov = np.zeros((3, 3))
    for v, w in motions:
        # The corners seen are the straight ones minus the shift that would straighten them.
        d = Jb @ (fit @ -_camera_motion_shift(points_camera, img, rig_camera, v, w, row_time).ravel())
        cov += np.outer(d, d)
    return cov


def _rodrigues_batch(r: np.ndarray) -> np.ndarray:
    """(k, 3, 3) rotation matrices of k rotation vectors ``r`` (k, 3): cv2.Rodrigues's formula
    (cos I + (1 - cos) n n^T + sin [n]x), one numpy pass instead of a call per vector."""
    theta = np.sqrt(np.einsum("ki,ki->k", r, r))
    n = r / np.where(theta > 0, theta, 1.0)[:, None]
    c, s = np.cos(theta)[:, None, None], np.sin(theta)[:, None, None]
    nx = np.zeros((len(r), 3, 3))
    nx[:, 0, 1], nx[:, 0, 2], nx[:, 1, 2] = -n[:, 2], n[:, 1], -n[:, 0]
    nx[:, 1, 0], nx[:, 2, 0], nx[:, 2, 1] = n[:, 2], -n[:, 1], n[:, 0]
    return c * np.eye(3) + (1.0 - c) * n[:, :, None] * n[:, None, :] + s * nx


def _body_jacobian(
    rvec: np.ndarray,
    tvec: np.ndarray,
    T_world_sticker: np.ndarray,
    T_camera_body: np.ndarray,
    vest_point: np.ndarray,
    h: float = 1e-6,
) -> np.ndarray:
    """(3, 6) d body(x, y, yaw) / d (rvec, tvec), central differences (all 12 evaluations of
    :func:`_body_from_rt` at once: it was 12 calls of a dozen small numpy operations each)."""
    x = np.concatenate([rvec.ravel(), tvec.ravel()]) + np.concatenate([h * np.eye(6), -h * np.eye(6)])  # (12, 6)
    R = _rodrigues_batch(x[:, :3])  # R_camera_sticker
    # T_world_body = T_world_sticker inv(T_camera_sticker) T_camera_body, so the vest point (c in the
    # camera) lands at R_ws R^T (c - t) + t_ws and the body's x axis along R_ws R^T R_cb[:, 0].
    R_wc = T_world_sticker[:3, :3] @ R.transpose(0, 2, 1)
    c = T_camera_body[:3, :3] @ np.asarray(vest_point, float) + T_camera_body[:3, 3]
    p = np.einsum("kij,kj->ki", R_wc, c - x[:, 3:]) + T_world_sticker[:3, 3]
    ax = R_wc @ T_camera_body[:3, 0]
    body = np.column_stack([p[:, 0], p[:, 1], np.arctan2(ax[:, 1], ax[:, 0])])
    diff = body[:6] - body[6:]
    diff[:, 2] = wrap_angle(diff[:, 2])
    return (diff / (2 * h)).T


def map_covariance(body: np.ndarray, sticker_xy: np.ndarray, sigma_m: float, sigma_yaw: float) -> np.ndarray:
    """(3, 3) covariance of a fix's body (x, y, yaw) from its sticker's survey error.

    The fix is the sticker's map pose composed with the measured sticker-to-body transform, so an
    error (dx, dy, da) of the map pose moves the body by (dx, dy) plus the turn ``da`` about the
    sticker's centre: ``J = [[1, 0, -ry], [0, 1, rx], [0, 0, 1]]`` with ``r = body - sticker``
    (m), and the covariance is ``J diag(sigma_m^2, sigma_m^2, sigma_yaw^2) J^T``.
    """
    J = map_error_jacobian(body[:2], sticker_xy)
    return (J * np.array([sigma_m**2, sigma_m**2, sigma_yaw**2])) @ J.T


def camera_twist(rig_camera: RigCamera, body_twist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(v (3,), w (3,)): the camera's linear (m/s) and angular (rad/s) velocity in its own frame for
    the body moving at ``body_twist`` = (vx, vy, yaw rate) in the body frame (m/s, m/s, rad/s)."""
    vx, vy, w = (float(a) for a in np.asarray(body_twist, float).ravel()[:3])
    R_bc, r = rig_camera.T_body_camera[:3, :3], rig_camera.T_body_camera[:3, 3]
    v_body = np.array([vx - w * r[1], vy + w * r[0], 0.0])  # the camera's point of the body
    return R_bc.T @ v_body, R_bc.T @ np.array([0.0, 0.0, w])


def rolling_shutter_shift(
    points_camera: np.ndarray,
    observed_px: np.ndarray,
    rig_camera: RigCamera,
    body_twist: np.ndarray,
    at_s: float = 0.0,
) -> np.ndarray:
    """(N, 2) pixel shifts that move corners seen at their own rows' times to the time ``at_s`` (s)
    after the frame's time.

    ``points_camera`` (N, 3): the corners' points in the camera frame at that time (from a first
    solve); ``observed_px`` (N, 2): where they were seen (their rows give their delays).
    A static point moves in the camera frame as dX/dt = -(v + w x X); over a row's delay ``d``
    from ``at_s`` (a few ms) that is first order: X(d) = X - d (v + w x X).
    """
    v, w = camera_twist(rig_camera, body_twist)
    return _camera_motion_shift(points_camera, observed_px, rig_camera, v, w, at_s)


def _camera_motion_shift(
    points_camera: np.ndarray,
    observed_px: np.ndarray,
    rig_camera: RigCamera,
    v: np.ndarray,
    w: np.ndarray,
    at_s: float,
) -> np.ndarray:
    """:func:`rolling_shutter_shift` for the camera's own linear ``v`` (m/s) and angular ``w``
    (rad/s) velocity (3,) in its frame."""
    cam = rig_camera.camera
    X = np.asarray(points_camera, float)
    d = row_delay_s(np.asarray(observed_px, float)[:, 1], cam.height, rig_camera.readout_s) - at_s
    X_seen = X - d[:, None] * (v + np.cross(w, X))
    return cam.project(X) - cam.project(X_seen)


def _pose_cov(J: np.ndarray, img: np.ndarray, sigma_px: float, outline_px: float) -> np.ndarray:
    """(6, 6) covariance of the pose (rvec, tvec) fitted to corners ``img`` (N, 2) px with
    reprojection Jacobian ``J`` (2N, 6): independent corner noise ``sigma_px``, plus an error of
    ``outline_px`` every corner shares, each moved along its direction from the corners' centre
    (the outline seen larger or smaller, see ``PoseConfig.outline_scale_px``)."""
    JtJ_inv = np.linalg.pinv(J.T @ J)
    cov = sigma_px**2 * JtJ_inv
    if outline_px > 0:
        u = img - img.mean(axis=0)
        u = u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
        d = JtJ_inv @ (J.T @ u.ravel())  # the least-squares pose's response to that displacement
        cov = cov + outline_px**2 * np.outer(d, d)
    return cov


def _ippe_solutions(outer: np.ndarray, img: np.ndarray, obj: np.ndarray, use8: bool, K: np.ndarray, dist: np.ndarray):
    """Distinct IPPE solutions refined on all points, best first: (SSR px^2, rvec, tvec, J (2N, 6))."""
    n_sol, rvecs, tvecs, _ = cv2.solvePnPGeneric(
        OUTER_CORNERS, outer.reshape(-1, 1, 2), K, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE
    )
    cands = []
    for rvec, tvec in zip(rvecs[:n_sol], tvecs[:n_sol]):
        rvec, tvec = rvec.reshape(3, 1).copy(), tvec.reshape(3, 1).copy()
        if use8:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img.reshape(-1, 1, 2), K, dist, rvec, tvec)
        if tvec[2, 0] <= 0:  # sticker behind the camera
            continue
        proj, jac = cv2.projectPoints(obj, rvec, tvec, K, dist)
        res = proj.reshape(-1, 2) - img
        cands.append((float(np.sum(res**2)), rvec, tvec, jac[:, :6]))
    cands.sort(key=lambda c: c[0])
    # LM can pull the worse IPPE solution onto the better one: keep distinct poses only.
    uniq = []
    for c in cands:
        if all(np.linalg.norm(c[1] - u[1]) > 1e-4 or np.linalg.norm(c[2] - u[2]) > 1e-6 for u in uniq):
            uniq.append(c)
    return uniq


def solve_pose(
    detection: Detection,
    rotation: int,
    T_world_sticker: np.ndarray,
    rig_camera: RigCamera,
    corner_sigma_px: float | None = None,
    config: PoseConfig | None = None,
    map_sigma: tuple[float, float] | None = None,
    body_twist: np.ndarray | None = None,
    corner_velocity: np.ndarray | None = None,
    body_twist_sigma: np.ndarray | None = None,
) -> PoseSolution:
    """Pose of the camera and the body from one sticker.

    Args:
        detection: corners in distorted pixels (outer, optional inner), clockwise on screen.
        rotation: r (0-3), the canonical top-left corner is ``detection.outer[r]``.
        T_world_sticker: (4, 4) the sticker's pose in the world (from the map).
        rig_camera: the camera that saw it (intrinsics and ``T_body_camera``).
        corner_sigma_px: corner noise (px) if known (else the detection's own, if it states one);
            else estimated from the 8-point residual
            (floored at ``config.min_sigma_px``) or ``config.sigma_4pt_px`` with 4 points.
        map_sigma: the sticker's survey (sigma per axis m, sigma yaw rad) from the map, NaN where
            the map states none (then ``config.map_sigma_m`` / ``config.map_sigma_yaw``); None:
            ``T_world_sticker`` is exact (no map part).
        body_twist: the body's motion (vx, vy, yaw rate) in the body frame (m/s, m/s, rad/s), for
            a rolling-shutter camera (``rig_camera.readout_s`` > 0): the corners are moved to the
            pose's time (``row_time_s``) before the final solve (see the module docstring). None:
            no correction.
        corner_velocity: instead of ``body_twist``, the corners' own image velocities (N, 2) px/s,
            canonical order (rotated as the corners are; outer then inner), e.g. their motion since
            the previous frame: each corner is moved by its velocity over its row's delay from
            the pose's time, and the pose solved once.
        body_twist_sigma: (3,) standard deviations of ``body_twist``'s components when it is an
            estimate (the tracker's prediction, seconds after its last fix): the covariance gets
            the pose's response to each at its sigma, as for an unknown motion
            (``PoseConfig.unknown_twist_sigma``). None: ``body_twist`` is taken as exact.
    Returns:
        :class:`PoseSolution` with PoseFix(T_world_camera, body (x, y, yaw), cov (3, 3), RMS px);
        body (x, y) is the vest point's vertical projection, yaw the heading of the body's +x axis;
        ``cov`` has the corner noise and the map's survey error (:func:`map_covariance`); the
        poses hold ``row_time_s`` after the frame's time (a rolling shutter's sticker rows).
    """
    config = config or PoseConfig()
    if rotation not in (0, 1, 2, 3):
        raise InputError(f"solve_pose: rotation {rotation!r} is not 0-3")
    cam = rig_camera.camera
    K, dist = cam.K, cam.dist
    outer = rotate_corners(np.asarray(detection.outer, float), rotation)
    use8 = config.use_inner and detection.inner is not None
    img = rotate_corners(np.asarray(detection.points, float), rotation) if use8 else outer
    obj = ALL_CORNERS if use8 else OUTER_CORNERS

    delays, row_time = _row_times(img, rig_camera, config.at_sticker_rows)
    # The shear of a motion the frame was read under that nothing measured (none given, or only
    # an estimate of it) is an error of the fix.
    twist_sigma = _twist_sigma(rig_camera, body_twist, corner_velocity, body_twist_sigma, config)
    if corner_velocity is not None and rig_camera.readout_s > 0:
        vel = np.asarray(corner_velocity, float)
        if vel.shape[0] < len(img) or not np.all(np.isfinite(vel)):
            raise InputError(f"solve_pose: corner_velocity {vel.shape} does not cover the {len(img)} corners")
        img = img - (delays - row_time)[:, None] * vel[: len(img)]
        outer = img[:4]
        body_twist = None
    uniq = _ippe_solutions(outer, img, obj, use8, K, dist)
    if uniq and body_twist is not None and rig_camera.readout_s > 0:
        R = cv2.Rodrigues(uniq[0][1])[0]
        shift = rolling_shutter_shift(obj @ R.T + uniq[0][2].ravel(), img, rig_camera, body_twist, row_time)
        img = img + shift
        outer = img[:4]
        uniq = _ippe_solutions(outer, img, obj, use8, K, dist)
    if not uniq:
        return PoseSolution([], False, row_time_s=row_time)

    n = len(obj)
    dof = 2 * n - 6
    if corner_sigma_px is None:
        corner_sigma_px = detection.corner_sigma_px
    if corner_sigma_px is not None:
        sigma = float(corner_sigma_px)
    elif use8:
        sigma = max(float(np.sqrt(uniq[0][0] / dof)), config.min_sigma_px)
    else:
        sigma = config.sigma_4pt_px
    keep = [uniq[0]]
    if len(uniq) > 1 and uniq[1][0] - uniq[0][0] < config.ambiguity_chi2 * sigma**2:
        keep.append(uniq[1])

    sig_m, sig_yaw = config.survey_sigmas(*map_sigma) if map_sigma is not None else (0.0, 0.0)
    T_camera_body = invert(rig_camera.T_body_camera)
    poses = []
    for ssr, rvec, tvec, J in keep:
        rms = float(np.sqrt(ssr / n))
        if rms > config.max_reprojection_px:
            continue
        cov6 = _pose_cov(J, img, sigma, config.outline_scale_px)
        Jb = _body_jacobian(rvec, tvec, T_world_sticker, T_camera_body, rig_camera.vest_point)
        cov = Jb @ cov6 @ Jb.T
        cov = (cov + cov.T) / 2
        T_world_camera = T_world_sticker @ invert(T_from_rvec_tvec(rvec, tvec))
        body = vest_planar(T_world_camera @ T_camera_body, rig_camera.vest_point)
        if sig_m > 0 or sig_yaw > 0:
            cov = cov + map_covariance(body, T_world_sticker[:2, 3], sig_m, sig_yaw)
        if rig_camera.readout_s > 0 and corner_velocity is None:
            # Straightened by a planar twist or not at all: what that left out is an error.
            points = obj @ cv2.Rodrigues(rvec)[0].T + np.asarray(tvec, float).ravel()
            cov = cov + _unknown_motion_cov(
                J, Jb, points, img, rig_camera, row_time, twist_sigma, config.tilt_rate_sigma
            )
        poses.append(PoseFix(T_world_camera, body, cov, rms))
    return PoseSolution(poses, len(poses) > 1, sigma, row_time)
