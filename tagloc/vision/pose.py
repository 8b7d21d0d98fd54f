"""Camera and body pose from one identified sticker, with a covariance from the corner noise.

IPPE_SQUARE on the four outer corners gives the two planar-pose candidates; each is refined by
Levenberg-Marquardt on every corner the detector found (outer + inner black-frame corners). The
covariance of the 6-DoF pose is sigma^2 (J^T J)^-1 with J the reprojection Jacobian from
``cv2.projectPoints``, propagated to the body's planar (x, y, yaw) by a central-difference Jacobian.
The body's planar pose is the vest point projected vertically onto the floor and the horizontal
heading of the body's +x axis (:func:`tagloc.core.rig.vest_planar`), not the body origin carried
through the tilted torso: every degree of torso tilt would swing that origin, 1.3 m down the
torso's axis, by 2.3 cm. The vest point sits at the camera's mount, so its position is about as
well determined as the camera centre's (~1 cm at 1.4 m and 0.3 px: worse than a point on the floor
near the sticker, but it is where the operator is, whatever the torso's tilt).
When the second IPPE solution explains the corners about as well as the first (within a chi-square
margin of the corner noise), both are returned, best first, and the solution is flagged ambiguous.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from tagloc.core.errors import InputError
from tagloc.core.geometry import T_from_rvec_tvec, invert, wrap_angle
from tagloc.core.rig import RigCamera, vest_planar
from tagloc.core.sticker import ALL_CORNERS, OUTER_CORNERS, rotate_corners
from tagloc.core.types import Detection, PoseFix


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
    """

    use_inner: bool = True
    min_sigma_px: float = 0.3
    sigma_4pt_px: float = 0.5
    ambiguity_chi2: float = 16.0
    max_reprojection_px: float = 5.0


@dataclass
class PoseSolution:
    """Result of :func:`solve_pose`: 0-2 fixes, best first; ``ambiguous`` when 2 are plausible."""

    poses: list[PoseFix]
    ambiguous: bool
    time_ms: float
    sigma_px: float = 0.0  # corner noise used for the covariances


def _body_from_rt(
    r: np.ndarray, t: np.ndarray, T_world_sticker: np.ndarray, T_camera_body: np.ndarray, vest_point: np.ndarray
) -> np.ndarray:
    """Body (x, y, yaw) (vest point on the floor, heading) for sticker-in-camera pose (rvec ``r``, tvec ``t``)."""
    T_world_camera = T_world_sticker @ invert(T_from_rvec_tvec(r, t))
    return vest_planar(T_world_camera @ T_camera_body, vest_point)


def _body_jacobian(
    rvec: np.ndarray,
    tvec: np.ndarray,
    T_world_sticker: np.ndarray,
    T_camera_body: np.ndarray,
    vest_point: np.ndarray,
    h: float = 1e-6,
) -> np.ndarray:
    """(3, 6) d body(x, y, yaw) / d (rvec, tvec), central differences."""
    x0 = np.concatenate([rvec.ravel(), tvec.ravel()])
    J = np.empty((3, 6))
    for i in range(6):
        d = np.zeros(6)
        d[i] = h
        bp = _body_from_rt((x0 + d)[:3], (x0 + d)[3:], T_world_sticker, T_camera_body, vest_point)
        bm = _body_from_rt((x0 - d)[:3], (x0 - d)[3:], T_world_sticker, T_camera_body, vest_point)
        diff = bp - bm
        diff[2] = wrap_angle(diff[2])
        J[:, i] = diff / (2 * h)
    return J


def solve_pose(
    detection: Detection,
    rotation: int,
    T_world_sticker: np.ndarray,
    rig_camera: RigCamera,
    corner_sigma_px: float | None = None,
    config: PoseConfig | None = None,
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
    Returns:
        :class:`PoseSolution` with PoseFix(T_world_camera, body (x, y, yaw), cov (3, 3), RMS px); body
        (x, y) is the vest point's vertical projection, yaw the heading of the body's +x axis.
    """
    config = config or PoseConfig()
    t0 = time.perf_counter()
    if rotation not in (0, 1, 2, 3):
        raise InputError(f"solve_pose: rotation {rotation!r} is not 0-3")
    cam = rig_camera.camera
    K, dist = cam.K, cam.dist
    outer = rotate_corners(np.asarray(detection.outer, float), rotation)
    use8 = config.use_inner and detection.inner is not None
    img = rotate_corners(np.asarray(detection.points, float), rotation) if use8 else outer
    obj = ALL_CORNERS if use8 else OUTER_CORNERS

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
    if not uniq:
        return PoseSolution([], False, (time.perf_counter() - t0) * 1e3)

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

    T_camera_body = invert(rig_camera.T_body_camera)
    poses = []
    for ssr, rvec, tvec, J in keep:
        rms = float(np.sqrt(ssr / n))
        if rms > config.max_reprojection_px:
            continue
        cov6 = sigma**2 * np.linalg.pinv(J.T @ J)
        Jb = _body_jacobian(rvec, tvec, T_world_sticker, T_camera_body, rig_camera.vest_point)
        cov = Jb @ cov6 @ Jb.T
        cov = (cov + cov.T) / 2
        T_world_camera = T_world_sticker @ invert(T_from_rvec_tvec(rvec, tvec))
        body = vest_planar(T_world_camera @ T_camera_body, rig_camera.vest_point)
        poses.append(PoseFix(T_world_camera, body, cov, rms))
    return PoseSolution(poses, len(poses) > 1, (time.perf_counter() - t0) * 1e3, sigma)
