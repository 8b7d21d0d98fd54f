"""Which mapped stickers could the one seen at a pixel be? Candidates from the tracker's prior.

Stickers near the camera's predicted floor footprint are fetched from the map's KD-tree, their
centres projected through the predicted body pose and the rig into the (distorted) image, and each
projection's uncertainty is the body-pose covariance pushed through the projection Jacobian plus
the vest's own wobble and a pixel term. Candidates are those whose predicted pixel lies within the
Mahalanobis gate of the observed one, most likely first.

Projection Jacobian of sticker centre ``p_w`` (world, on the floor) with respect to the body pose
(x, y, yaw): ``p_b = R(yaw)^T (p_w - (x, y, 0))``, ``p_c = R_cb p_b + t_cb``, pixel ``u = pi(p_c)``::

    d p_b / d(x, y, yaw) = [[-cos, -sin,  p_b.y],
                            [ sin, -cos, -p_b.x],
                            [   0,    0,      0]]
    d u / d(x, y, yaw)   = (d u / d p_c) R_cb (d p_b / d(x, y, yaw))

``d u / d p_c`` (with distortion) is OpenCV's ``projectPoints`` Jacobian with respect to ``tvec``
at zero pose; its Jacobian with respect to ``rvec`` gives the effect of the camera tilting.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from tagloc.core.camera import Camera
from tagloc.core.geometry import invert, planar_T
from tagloc.core.rig import RigCamera
from tagloc.core.stickermap import StickerMap
from tracker.ekf import largest_eig_2x2

#: Default gate: 99.9% of a 2-D Gaussian, sqrt of the chi-square bound, about 3.72 sigma (for 2 degrees
#: of freedom the bound is closed-form: -2 ln(1 - p)).
GATE_SIGMA = math.sqrt(-2.0 * math.log(1.0 - 0.999))


@dataclass
class CandidateConfig:
    """Noise beyond the body-pose covariance when predicting where a sticker appears.

    Attributes:
        pixel_sigma: detection-centre noise, px: the mean of the four detected corners is not the
            projected centre under perspective (~1 px for a 10 cm sticker) and blur moves corners.
        tilt_sigma: camera tilt about its own axes relative to the rig as the tracker predicts it,
            rad: the gait's ~1 deg nod and roll, and the lean with speed changes, atan(a / g), which
            is not predicted (~0.4 m/s^2 RMS over a walk with stops: 2.3 deg); together 2.5 deg
            (at fx ~1290 px, ~56 px). The lean into turns is predicted (the camera is rolled by it).
        bob_sigma: camera height bob, m (2-3 cm while walking).
        max_range: farthest floor distance from the camera considered, m (the footprint of rays
            above the horizon is clipped there; a 10 cm sticker is ~30 px wide at 4 m).
        min_depth: points closer than this along the optical axis are not projected, m.
        image_margin: fraction of the image size around it where predicted stickers still count
            (a sticker predicted just outside may be the one seen just inside).
        query_margin_m: the map is searched this far (m) beyond the footprint's bounding circle:
            one sticker side (10 cm), so a sticker whose centre is just outside the floor under the
            image border, with part of it in view, is still projected.
        border_samples: points per image side where rays are cast for the footprint's polygon:
            17 (16 segments, 81 px apart along the 1296 px side): on the reference camera
            (:func:`tagloc.core.camera.default_camera`, 1.3 m up, pitched 55 deg) the floor under
            the whole border strays 0.3 mm from that polygon.
    """

    pixel_sigma: float = 3.0
    tilt_sigma: float = math.radians(2.5)
    bob_sigma: float = 0.025
    max_range: float = 4.0
    min_depth: float = 0.1
    image_margin: float = 0.25
    query_margin_m: float = 0.1
    border_samples: int = 17


@dataclass
class Footprint:
    """The floor area a camera sees, in the body frame.

    Attributes:
        polygon: (M, 2) floor points under the image border (body x, y), m, rays clipped at range.
        centre: (2,) centre of the polygon's bounding box. radius: distance to its farthest vertex.
    """

    polygon: np.ndarray
    centre: np.ndarray
    radius: float


@dataclass
class Projection:
    """Mapped sticker centres projected into one camera.

    Attributes:
        rows: (N,) map rows. ids: (N,) sticker IDs.
        pixels: (N, 2) distorted pixel positions. depth: (N,) distance along the optical axis, m.
        in_image: (N,) bool, the pixel lies inside the image.
    """

    rows: np.ndarray
    ids: np.ndarray
    pixels: np.ndarray
    depth: np.ndarray
    in_image: np.ndarray


# Footprints by the rig camera's content (pose, intrinsics, range), the last few used. By object
# identity instead, the tracker's leaned camera (a new pose whenever the predicted lean changes)
# left one entry per lean: 590 after the 90 s field walk, ~200,000 over an 8-hour shift.
_FOOTPRINTS: OrderedDict[bytes, Footprint] = OrderedDict()
_FOOTPRINTS_KEPT = 8  # rig cameras of a multi-camera rig, each nominal and leaned, with room
_FOOTPRINTS_LOCK = threading.Lock()


def _key(rc: RigCamera, cfg: CandidateConfig) -> bytes:
    c = rc.camera
    return (
        rc.T_body_camera.tobytes()
        + c.K.tobytes()
        + c.dist.tobytes()
        + np.array([c.width, c.height, cfg.max_range, cfg.border_samples], float).tobytes()
    )


_BORDER_RAYS: dict[bytes, np.ndarray] = {}


def _border_rays(cam: Camera, samples: int) -> np.ndarray:
    """(3, M) camera-frame rays (z = 1) through ``samples`` points on each side of the image border,
    cached per intrinsics: the tracker hands :func:`footprint` a new, leaned camera pose each frame
    (``Tracker.leaned_camera``), which misses the footprint's own cache, but the rays through the
    border stay the camera's."""
    key = cam.K.tobytes() + cam.dist.tobytes() + np.array([cam.width, cam.height, samples], float).tobytes()
    rays = _BORDER_RAYS.get(key)
    if rays is None:
        w, h = cam.width - 1.0, cam.height - 1.0
        s = np.linspace(0.0, 1.0, samples)
        border = np.vstack(
            [np.c_[s * w, 0 * s], np.c_[w + 0 * s, s * h], np.c_[(1 - s) * w, h + 0 * s], np.c_[0 * s, (1 - s) * h]]
        )
        norm = cv2.undistortPoints(border.reshape(-1, 1, 2), cam.K, cam.dist).reshape(-1, 2)
        rays = _BORDER_RAYS[key] = np.c_[norm, np.ones(len(norm))].T
    return rays


def footprint(rig_camera: RigCamera, config: CandidateConfig | None = None) -> Footprint:
    """Floor footprint of ``rig_camera`` in the body frame (cached per rig camera and settings)."""
    cfg = config or CandidateConfig()
    key = _key(rig_camera, cfg)
    with _FOOTPRINTS_LOCK:
        hit = _FOOTPRINTS.get(key)
        if hit is not None:
            _FOOTPRINTS.move_to_end(key)
            return hit
    rays = rig_camera.T_body_camera[:3, :3] @ _border_rays(rig_camera.camera, cfg.border_samples)  # (3, M), body
    origin = rig_camera.T_body_camera[:3, 3]
    horiz = np.hypot(rays[0], rays[1])
    # Distance along the floor to where each ray meets it; rays at or above the horizon never do.
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = np.where(rays[2] < -1e-9, origin[2] * horiz / -rays[2], np.inf)
    reach = np.minimum(reach, cfg.max_range)
    dirs = rays[:2] / np.maximum(horiz, 1e-12)
    poly = (origin[:2, None] + dirs * reach).T
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    centre = 0.5 * (lo + hi)
    fp = Footprint(poly, centre, float(np.max(np.hypot(*(poly - centre).T))))
    with _FOOTPRINTS_LOCK:
        _FOOTPRINTS[key] = fp
        while len(_FOOTPRINTS) > _FOOTPRINTS_KEPT:
            _FOOTPRINTS.popitem(last=False)
    return fp


def _query_rows(
    mean: np.ndarray,
    cov: np.ndarray | None,
    smap: StickerMap,
    fp: Footprint,
    n_sigma: float,
    margin_m: float,
) -> np.ndarray:
    """Map rows near the footprint (within ``margin_m`` m of its bounding circle), widened by
    ``n_sigma`` of the position and heading uncertainty of the body pose ``mean`` (3,), ``cov``
    (3, 3) (None: none)."""
    x, y, yaw = (float(v) for v in mean)
    c, s = math.cos(yaw), math.sin(yaw)
    cx, cy = x + c * fp.centre[0] - s * fp.centre[1], y + s * fp.centre[0] + c * fp.centre[1]
    radius = fp.radius + margin_m
    if cov is not None:
        pos_sigma = math.sqrt(max(largest_eig_2x2(cov), 0.0))
        reach = float(np.hypot(*fp.centre)) + fp.radius
        # A heading error swings the footprint about the body by at most a chord of 2 * reach.
        radius += n_sigma * pos_sigma + min(n_sigma * math.sqrt(max(cov[2, 2], 0.0)), 2.0) * reach
    return smap.within(cx, cy, radius)


def _project(
    mean: np.ndarray, smap: StickerMap, rig_camera: RigCamera, rows: np.ndarray, cfg: CandidateConfig, jacobians: bool
):
    """Project map rows' centres; returns (kept rows, pixels (N,2), depth (N,), p_b (N,3), J (2N,15) | None)."""
    T_world_body = planar_T(*mean)
    T_cam_body = invert(rig_camera.T_body_camera)
    # On the floor (z = 0); filled in rather than through np.c_, whose set-up cost more than the rest.
    p_w = np.zeros((len(rows), 3))
    p_w[:, :2] = smap.xy[rows]
    Rwb, twb = T_world_body[:3, :3], T_world_body[:3, 3]
    p_b = (p_w - twb) @ Rwb  # R^T (p_w - t)
    p_c = p_b @ T_cam_body[:3, :3].T + T_cam_body[:3, 3]
    cam = rig_camera.camera
    z = p_c[:, 2]
    keep = z > cfg.min_depth
    # Only points whose ideal projection lies near the image: distortion polynomials fold far-off
    # points back into view.
    with np.errstate(divide="ignore", invalid="ignore"):
        u = cam.fx * p_c[:, 0] / z + cam.K[0, 2]
        v = cam.fy * p_c[:, 1] / z + cam.K[1, 2]
    mx, my = cfg.image_margin * cam.width, cfg.image_margin * cam.height
    keep &= (u > -mx) & (u < cam.width + mx) & (v > -my) & (v < cam.height + my)
    rows, p_b, p_c = rows[keep], p_b[keep], p_c[keep]
    if len(rows) == 0:
        return rows, np.zeros((0, 2)), np.zeros(0), p_b, None
    pix, J = cv2.projectPoints(p_c.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist)
    return rows, pix.reshape(-1, 2), p_c[:, 2], p_b, (J if jacobians else None)


def project_map(
    mean: np.ndarray, smap: StickerMap, rig_camera: RigCamera, config: CandidateConfig | None = None
) -> Projection:
    """Every mapped sticker whose centre falls in (or near) ``rig_camera``'s view from body pose ``mean`` (3,).

    For visualisation and for spotting mapped stickers that should have been seen; ``in_image``
    flags the ones whose centre is inside the image proper.
    """
    cfg = config or CandidateConfig()
    mean = np.asarray(mean, float).ravel()
    rows = _query_rows(mean, None, smap, footprint(rig_camera, cfg), 0.0, cfg.query_margin_m)
    rows, pix, depth, _, _ = _project(mean, smap, rig_camera, rows, cfg, jacobians=False)
    cam = rig_camera.camera
    inside = (pix[:, 0] >= 0) & (pix[:, 0] <= cam.width - 1) & (pix[:, 1] >= 0) & (pix[:, 1] <= cam.height - 1)
    return Projection(rows, smap.ids[rows], pix, depth, inside)


def centre_pixels(
    mean: np.ndarray, smap: StickerMap, rig_camera: RigCamera, rows: np.ndarray, config: CandidateConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Distorted pixels (N, 2) of the centres of map ``rows`` seen from body pose ``mean`` (3,), with
    the rows kept (N,): those in front of the camera and near the image."""
    cfg = config or CandidateConfig()
    mean = np.asarray(mean, float).ravel()
    rows, pix, _, _, _ = _project(mean, smap, rig_camera, np.asarray(rows, np.int64), cfg, jacobians=False)
    return rows, pix


def predicted_pixels(
    mean: np.ndarray,
    cov: np.ndarray,
    smap: StickerMap,
    rig_camera: RigCamera,
    rows: np.ndarray,
    config: CandidateConfig | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predicted pixels of map ``rows`` with their covariances.

    Returns (kept rows (N,), pixels (N, 2), covariances (N, 2, 2) in px^2) for the rows in front of
    the camera and near the image.
    """
    cfg = config or CandidateConfig()
    mean = np.asarray(mean, float).ravel()
    rows, pix, _, p_b, J = _project(mean, smap, rig_camera, np.asarray(rows, np.int64), cfg, jacobians=True)
    if len(rows) == 0:
        return rows, pix, np.zeros((0, 2, 2))
    n = len(rows)
    J = J.reshape(n, 2, -1)
    J_rot, J_c = J[:, :, 0:3], J[:, :, 3:6]  # d pixel / d rvec, d pixel / d p_c at zero pose
    R_cb = rig_camera.T_body_camera[:3, :3].T
    c, s = math.cos(mean[2]), math.sin(mean[2])
    G = np.zeros((n, 3, 3))
    G[:, 0, 0], G[:, 0, 1], G[:, 0, 2] = -c, -s, p_b[:, 1]
    G[:, 1, 0], G[:, 1, 1], G[:, 1, 2] = s, -c, -p_b[:, 0]
    J_pose = J_c @ R_cb @ G  # (n, 2, 3)
    cov = np.asarray(cov, float)
    C = J_pose @ cov @ J_pose.transpose(0, 2, 1)
    C += cfg.tilt_sigma**2 * J_rot @ J_rot.transpose(0, 2, 1)
    up = J_c @ R_cb[:, 2]  # (n, 2): pixel motion per metre of camera height change
    C += cfg.bob_sigma**2 * up[:, :, None] * up[:, None, :]
    C += cfg.pixel_sigma**2 * np.eye(2)
    return rows, pix, C


def predicted_rows(
    mean: np.ndarray,
    cov: np.ndarray,
    smap: StickerMap,
    rig_camera: RigCamera,
    gate_sigma: float = GATE_SIGMA,
    config: CandidateConfig | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The map rows that may be in ``rig_camera``'s view from the body pose prior ``mean`` (3,),
    ``cov`` (3, 3) (the footprint widened by ``gate_sigma`` of its uncertainty), with their
    predicted pixels and covariances as :func:`predicted_pixels` gives them: (rows (N,), pixels
    (N, 2), covariances (N, 2, 2) px^2). The part of :func:`select_candidates` that does not
    depend on the observed pixel: one prior serves every sticker detected under it."""
    cfg = config or CandidateConfig()
    mean = np.asarray(mean, float).ravel()
    cov = np.asarray(cov, float)
    rows = _query_rows(mean, cov, smap, footprint(rig_camera, cfg), gate_sigma, cfg.query_margin_m)
    if len(rows) == 0:
        return rows, np.zeros((0, 2)), np.zeros((0, 2, 2))
    return predicted_pixels(mean, cov, smap, rig_camera, rows, cfg)


def gate_candidates(
    smap: StickerMap,
    predicted: tuple[np.ndarray, np.ndarray, np.ndarray],
    observed_px: np.ndarray,
    k: int = 5,
    gate_sigma: float = GATE_SIGMA,
) -> list[int]:
    """Up to ``k`` IDs of the ``predicted`` rows (see :func:`predicted_rows`) whose pixel
    distribution holds ``observed_px`` (2,) within the Mahalanobis gate ``gate_sigma``, most
    likely first."""
    rows, pix, C = predicted
    if len(rows) == 0:
        return []
    d = np.asarray(observed_px, float).ravel()[:2] - pix
    d2 = np.einsum("ni,ni->n", d, np.linalg.solve(C, d[:, :, None])[:, :, 0])
    inside = d2 <= gate_sigma**2
    if not inside.any():
        return []
    neg_log_lik = d2[inside] + np.log(np.linalg.det(C[inside]))
    order = np.argsort(neg_log_lik, kind="stable")[:k]
    return [int(i) for i in smap.ids[rows[inside][order]]]


def select_candidates(
    mean: np.ndarray,
    cov: np.ndarray,
    smap: StickerMap,
    rig_camera: RigCamera,
    observed_px: np.ndarray,
    k: int = 5,
    gate_sigma: float = GATE_SIGMA,
    config: CandidateConfig | None = None,
) -> list[int]:
    """IDs of the mapped stickers that may be the one whose centre was seen at ``observed_px``.

    Args:
        mean, cov: body pose prior (x, y, yaw) (3,) and its covariance (3, 3) (``Tracker.prior()``;
            pass its result only while TRACKING, which is when it is not None).
        observed_px: (2,) distorted pixel centre of the detected sticker.
        k: at most this many IDs. gate_sigma: Mahalanobis gate in pixel space.

    Returns:
        Up to ``k`` sticker IDs inside the gate, most likely first (Gaussian likelihood of the
        observed pixel under each sticker's predicted pixel distribution).
    """
    if mean is None or cov is None:
        return []
    return gate_candidates(
        smap, predicted_rows(mean, cov, smap, rig_camera, gate_sigma, config), observed_px, k, gate_sigma
    )
