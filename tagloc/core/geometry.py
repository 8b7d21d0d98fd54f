"""Rigid transforms on 4x4 homogeneous matrices, named ``T_parent_child``.

``T_a_b`` maps points expressed in frame b into frame a: ``p_a = T_a_b @ p_b``. Rotations go
through :mod:`scipy.spatial.transform`; nothing here re-implements what scipy or OpenCV does.
Angles are radians.
"""

from __future__ import annotations

import math

import cv2
import numpy as np


def wrap_angle(a: float | np.ndarray) -> float | np.ndarray:
    """Wrap an angle (rad) to [-pi, pi)."""
    return (
        (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi
        if isinstance(a, np.ndarray)
        else ((a + math.pi) % (2 * math.pi) - math.pi)
    )


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build a 4x4 transform from a 3x3 rotation and a translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, float).ravel()
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    R = T[:3, :3]
    return make_T(R.T, -R.T @ T[:3, 3])


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply ``T`` (4x4) to points (N, 3); returns (N, 3)."""
    points = np.asarray(points, float)
    return points @ T[:3, :3].T + T[:3, 3]


def planar_T(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    """Transform of a frame at (x, y, z) rotated by ``yaw`` about world +z."""
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = (x, y, z)
    return T


def planar_from_T(T: np.ndarray) -> tuple[float, float, float]:
    """(x, y, yaw) of a frame: position on the floor and heading of its +x axis about +z."""
    return float(T[0, 3]), float(T[1, 3]), math.atan2(T[1, 0], T[0, 0])


def T_from_rvec_tvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """4x4 transform from an OpenCV (rvec, tvec) pair, as returned by solvePnP."""
    R, _ = cv2.Rodrigues(np.asarray(rvec, float).reshape(3, 1))
    return make_T(R, np.asarray(tvec, float).ravel())


def T_to_tum(T: np.ndarray) -> tuple[float, float, float, float, float, float, float]:
    """(x, y, z, qx, qy, qz, qw) of a 4x4 transform, as a TUM line stores it."""
    from scipy.spatial.transform import Rotation  # here, not at the top: 0.2-0.6 s of start-up

    q = Rotation.from_matrix(T[:3, :3]).as_quat()  # scipy order: x, y, z, w
    return (*map(float, T[:3, 3]), *map(float, q))


def T_from_tum(values: np.ndarray) -> np.ndarray:
    """4x4 transform from (x, y, z, qx, qy, qz, qw) (7,); or (N, 4, 4) transforms from rows (N, 7)."""
    from scipy.spatial.transform import Rotation

    values = np.asarray(values, float)
    if values.ndim == 1:
        return make_T(Rotation.from_quat(values[3:7]).as_matrix(), values[:3])
    T = np.zeros((len(values), 4, 4))
    T[:, :3, :3] = Rotation.from_quat(values[:, 3:7]).as_matrix().reshape(-1, 3, 3)
    T[:, :3, 3] = values[:, :3]
    T[:, 3, 3] = 1.0
    return T


def interpolate_groundtruth(
    gt_stamps: np.ndarray, gt_T: np.ndarray, stamps: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Ground truth (x, y, yaw) (K, 3) at those ``stamps`` (N,) inside its span, and the (N,) bool mask of them."""
    gt_stamps = np.asarray(gt_stamps, float).ravel()
    gt_T = np.asarray(gt_T, float).reshape(-1, 4, 4)
    stamps = np.asarray(stamps, float).ravel()
    if len(gt_stamps) == 0:
        return np.zeros((0, 3)), np.zeros(len(stamps), bool)
    order = np.argsort(gt_stamps, kind="stable")
    gt_stamps, gt_T = gt_stamps[order], gt_T[order]
    # Slerp needs strictly increasing times: keep the first of any repeated stamp.
    keep = np.concatenate([[True], np.diff(gt_stamps) > 0])
    gt_stamps, gt_T = gt_stamps[keep], gt_T[keep]
    inside = (stamps >= gt_stamps[0]) & (stamps <= gt_stamps[-1])
    t = stamps[inside]
    if len(gt_stamps) == 1:
        R = np.repeat(gt_T[:1, :3, :3], len(t), axis=0)
        xy = np.repeat(gt_T[:1, :2, 3], len(t), axis=0)
    else:
        from scipy.spatial.transform import Rotation, Slerp

        R = Slerp(gt_stamps, Rotation.from_matrix(gt_T[:, :3, :3]))(t).as_matrix().reshape(-1, 3, 3)
        xy = np.column_stack([np.interp(t, gt_stamps, gt_T[:, 0, 3]), np.interp(t, gt_stamps, gt_T[:, 1, 3])])
    yaw = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    return np.column_stack([xy, yaw]).reshape(-1, 3), inside


def map_error_jacobian(body_xy: np.ndarray, sticker_xy: np.ndarray) -> np.ndarray:
    """(3, 3) d fix (x, y, yaw) / d map error (dx, dy, dyaw) of the sticker the fix came from.

    A fix is the sticker's map pose composed with the measured sticker-to-body transform, so a map
    pose off by (dx, dy, da) moves the fix by (dx, dy) plus the turn ``da`` about the sticker's
    centre: ``[[1, 0, -ry], [0, 1, rx], [0, 0, 1]]`` with ``r = body - sticker`` (m).
    """
    rx, ry = float(body_xy[0] - sticker_xy[0]), float(body_xy[1] - sticker_xy[1])
    return np.array([[1.0, 0.0, -ry], [0.0, 1.0, rx], [0.0, 0.0, 1.0]])
