"""The camera rig on the operator's vest: each camera's calibration and pose in the body frame.

Body frame: rigid with the torso (the vest), +x forward, +y left, +z up when the operator stands
upright; its origin is on the floor under the vest's reference point, the point of the torso where
the rig is mounted, ``vest_point = (0, 0, vest_height_m)`` in the body frame. ``rig.json``::

    {"vest_height_m": 1.3,
     "cameras": [{"name": "front", "calibration": "camera.yaml",
                  "T_body_camera": [[...4 rows of 4...]]}]}

``T_body_camera`` (row-major, metres) maps points from the OpenCV camera frame (x right, y down,
z along the optical axis) into the body frame. ``calibration`` is relative to the rig file.
``vest_height_m`` is optional (default: the cameras' mean height).

The operator's reported pose is **not** the body origin carried through the tilted torso: it is
the vest point projected vertically onto the floor, (x, y), with the heading of the body's +x axis
projected onto the floor. A torso leaning by a degree would swing the origin, 1.3 m down the torso's
own z axis, by 2.3 cm; the vest point does not move when the torso tilts about it, so tilt measured
by a sticker fix does not move (x, y) (see :func:`vest_planar`).
An optional ``"readout_s"`` gives a rolling-shutter camera's read-out time, first row to last
(seconds; 0 or absent: global shutter): row ``v`` is exposed ``(v - (H - 1) / 2) * readout_s / H``
after the frame's timestamp, which belongs to the middle row. ``"legs_in_view"`` (true or false)
says whether the camera sees the wearer's own feet and legs (pitched steeply down from the chest, it
sees the leading foot once per step): the floor odometry then leaves out the floor they can cover
(:class:`tagloc.vision.odometry.OdometryConfig` ``legs_reach_m``). Absent, it is decided from the
mount: a forward camera that sees the floor within that reach of the vest point sees the feet
(:func:`tagloc.vision.odometry.legs_zone`). An optional ``"stamp_offset_s"`` (seconds, within +-1)
is what to add to a live camera's timestamps to get the frame's time, when the driver's own stamp
is known to sit elsewhere than :func:`tagloc.io.capture.frame_time` assumes (measured, say);
absent, that conversion applies. Replays take their recorded stamps as frame times.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from tagloc.core.camera import Camera, default_camera, load_calibration, save_calibration
from tagloc.core.errors import CalibrationError
from tagloc.core.geometry import make_T
from tagloc.core.jsonfile import read_json


@dataclass
class RigCamera:
    """One camera of the rig: a name, its intrinsics, ``T_body_camera`` (4, 4) and its rolling-shutter
    read-out ``readout_s`` (s, first row to last; 0: global shutter)."""

    name: str
    camera: Camera
    T_body_camera: np.ndarray
    calibration_file: str = "camera.yaml"
    readout_s: float = 0.0
    vest_height_m: float | None = None  # height of the vest point in the body frame; None: the camera's
    # The camera sees the wearer's feet and legs; None: decided from the mount (see the module docstring).
    legs_in_view: bool | None = None
    # Seconds from a live source's stamp to the frame's time; None: the source's own rule
    # (tagloc.io.capture.frame_time).
    stamp_offset_s: float | None = None

    def __post_init__(self) -> None:
        if self.vest_height_m is None:
            self.vest_height_m = float(np.asarray(self.T_body_camera)[2, 3])

    @property
    def vest_point(self) -> np.ndarray:
        """(3,) the vest's reference point in the body frame, m: ``(0, 0, vest_height_m)``."""
        return np.array([0.0, 0.0, float(self.vest_height_m)])


@dataclass
class Rig:
    """All cameras worn by the operator."""

    cameras: list[RigCamera]

    def __post_init__(self) -> None:
        # One torso, one vest point: cameras made one by one each default to their own height.
        if len({c.vest_height_m for c in self.cameras}) > 1:
            _shared_height(self.cameras, None)

    def __getitem__(self, index: int) -> RigCamera:
        return self.cameras[index]

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def vest_point(self) -> np.ndarray:
        """(3,) the vest's reference point in the body frame (m), shared by all cameras."""
        return self.cameras[0].vest_point


def vest_planar(T_world_body: np.ndarray, vest_point: np.ndarray) -> np.ndarray:
    """The reported pose (x, y, yaw) of a (possibly tilted) body pose ``T_world_body`` (4, 4).

    (x, y): the vest point ``vest_point`` (3,) (body frame, m) carried into the world and projected
    vertically onto the floor; yaw: the horizontal direction of the body's +x axis (rad).
    """
    T = np.asarray(T_world_body, float)
    p = T[:3, :3] @ np.asarray(vest_point, float) + T[:3, 3]
    return np.array([p[0], p[1], math.atan2(T[1, 0], T[0, 0])])


def torso_tilt(T_world_camera: np.ndarray, T_body_camera: np.ndarray) -> tuple[float, float]:
    """The torso's (pitch, roll) off the rig's nominal pose (rad), given a camera's measured pose.

    ``T_world_camera`` (4, 4) is where the camera is; ``T_body_camera`` (4, 4) where the rig puts it
    on an upright body. The tilt is the rotation ``R`` in the body's heading frame (the horizontal
    direction of the body's +x, as in :func:`vest_planar`) with ``R_world_camera = R_heading R
    R_body_camera``; pitch turns about the body's y axis (> 0 tips +x, the front, down), roll about
    its x axis (> 0 tips +y, the left, up).
    """
    Rb = np.asarray(T_world_camera, float)[:3, :3] @ np.asarray(T_body_camera, float)[:3, :3].T
    yaw = math.atan2(Rb[1, 0], Rb[0, 0])
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ Rb
    return math.atan2(R[0, 2], R[2, 2]), math.atan2(-R[1, 2], R[2, 2])


def floor_under_pixels(rig_camera: RigCamera, px: np.ndarray, min_depression: float = 0.0) -> np.ndarray:
    """Body-frame floor points (N, 2) m under distorted pixels ``px`` (N, 2) of ``rig_camera`` at its
    nominal mount; NaN where the ray dips less than ``min_depression`` (rad) below the horizon."""
    cam = rig_camera.camera
    n = cv2.undistortPoints(np.asarray(px).reshape(-1, 1, 2).astype(np.float64), cam.K, cam.dist).reshape(-1, 2)
    rays = np.column_stack([n, np.ones(len(n))]) @ rig_camera.T_body_camera[:3, :3].T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    c = rig_camera.T_body_camera[:3, 3]
    out = np.full((len(n), 2), np.nan)
    down = rays[:, 2] < -math.sin(min_depression)
    s = -c[2] / rays[down, 2]
    out[down] = c[:2] + s[:, None] * rays[down, :2]
    return out


def _shared_height(cameras: list[RigCamera], height: float | None) -> list[RigCamera]:
    """The cameras with one vest height: ``height``, or the cameras' mean height."""
    h = float(np.mean([c.T_body_camera[2, 3] for c in cameras])) if height is None else float(height)
    for c in cameras:
        c.vest_height_m = h
    return cameras


def row_delay_s(rows: np.ndarray | float, height: int, readout_s: float) -> np.ndarray | float:
    """Rolling shutter: when row ``rows`` (0 = top, may be fractional) is exposed, relative to the frame time (s).

    The sensor reads one row every ``readout_s / height`` seconds, top row first; the frame's time
    is the middle row's (``(height - 1) / 2``), so rows above it are exposed earlier (negative).
    """
    return (np.asarray(rows, float) - 0.5 * (height - 1)) * (readout_s / height)


def looking_forward(
    height_m: float = 1.3, pitch_deg: float = 55.0, yaw_deg: float = 0.0, x_m: float = 0.0, y_m: float = 0.0
) -> np.ndarray:
    """``T_body_camera`` of a camera at ``height_m`` looking along body yaw, pitched down by ``pitch_deg``."""
    p, a = math.radians(pitch_deg), math.radians(yaw_deg)
    fwd = np.array([math.cos(p) * math.cos(a), math.cos(p) * math.sin(a), -math.sin(p)])  # optical axis
    right = np.array([math.sin(a), -math.cos(a), 0.0])
    down = np.cross(fwd, right)
    return make_T(np.column_stack([right, down, fwd]), (x_m, y_m, height_m))


def default_rig(height_m: float = 1.3, pitch_deg: float = 55.0, camera: Camera | None = None) -> Rig:
    """One forward camera ``height_m`` up, pitched ``pitch_deg`` below horizontal (default Pi camera);
    the vest point is the camera's mounting point."""
    return Rig([RigCamera("front", camera or default_camera(), looking_forward(height_m, pitch_deg))])


# Bounds of a worn camera's position in the body frame (m): the vest height's own range (0-3 m) and
# a torso's reach (a camera on the chest, back or shoulder is well inside 1 m of the body axis).
MAX_CAMERA_HEIGHT_M = 3.0
MAX_CAMERA_REACH_M = 1.0
# How far from orthonormal (|R R^T - I|, elementwise) a written rotation may be: a hand-written
# rig.json rounds its entries to 3 decimals (up to 5e-4 each, up to 1.8e-3 on R R^T; the
# README's 0.819, 0.574 for 55 degrees give 2.4e-4); a wrong matrix (a scale, a shear, a typo) is
# far beyond. Such a rotation is replaced by the nearest rotation matrix, a fraction of a degree away.
RIGID_TOL = 5e-3


def _check_T(value: object, where: str) -> np.ndarray:
    try:
        T = np.asarray(value, float)
    except (TypeError, ValueError, OverflowError):
        raise CalibrationError(f"{where}: T_body_camera is not a 4x4 matrix of numbers") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise CalibrationError(f"{where}: T_body_camera must be a finite 4x4 matrix")
    R = T[:3, :3]
    if np.max(np.abs(R)) > 1 + RIGID_TOL:
        # Refused before R R^T: an entry of 1e308 overflowed there, numpy's warning printed over the
        # refusal. (The translation is bounded below, with the camera's position in the message.)
        raise CalibrationError(
            f"{where}: T_body_camera is not a rigid transform (its rotation holds {np.max(np.abs(R)):.4g};"
            " a rotation's entries are within +-1)"
        )
    if (
        not np.allclose(R @ R.T, np.eye(3), atol=RIGID_TOL)
        or np.linalg.det(R) < 0
        or not np.allclose(T[3], [0, 0, 0, 1])
    ):
        raise CalibrationError(f"{where}: T_body_camera is not a rigid transform")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-9, rtol=0.0):
        # A rotation written to a few decimals: the nearest rotation (polar decomposition), so that
        # everything downstream, which inverts it as its transpose, sees a rigid transform.
        u, _, vt = np.linalg.svd(R)
        T = T.copy()
        T[:3, :3] = u @ vt
    # The body frame stands on the floor under the wearer: a worn camera is above the floor and
    # within reach of the torso (metres off, every pose would be as far off, without a word).
    if not 0.0 < T[2, 3] < MAX_CAMERA_HEIGHT_M or np.hypot(T[0, 3], T[1, 3]) > MAX_CAMERA_REACH_M:
        raise CalibrationError(
            f"{where}: T_body_camera puts the camera at ({T[0, 3]:.4g}, {T[1, 3]:.4g}, {T[2, 3]:.4g}) m; a worn "
            f"camera is 0-{MAX_CAMERA_HEIGHT_M:g} m above the floor and within {MAX_CAMERA_REACH_M:g} m of the body axis"
        )
    return T


def load_rig(path: str | Path, calibration: Camera | None = None) -> Rig:
    """Load ``rig.json``; each camera's calibration is read relative to the rig file.

    ``calibration`` overrides the file named in the rig (for ``--calibration`` on the CLI).
    """
    path = Path(path)
    doc = read_json(path, CalibrationError, "rig")
    cams = doc.get("cameras") if isinstance(doc, dict) else None
    if not isinstance(cams, list) or not cams:
        raise CalibrationError(f'{path}: needs a non-empty "cameras" list')
    out = []
    for i, entry in enumerate(cams):
        where = f"{path}: cameras[{i}]"
        if not isinstance(entry, dict) or "T_body_camera" not in entry:
            raise CalibrationError(f"{where}: needs T_body_camera")
        name = str(entry.get("name", f"cam{i}"))
        calib_file = entry.get("calibration", "camera.yaml")
        if not isinstance(calib_file, str) or not calib_file or "\0" in calib_file:
            raise CalibrationError(f"{where}: calibration must be a file name")
        cam = calibration if calibration is not None else load_calibration(path.parent / calib_file)
        readout = entry.get("readout_s", 0.0)
        if isinstance(readout, bool) or not isinstance(readout, (int, float)) or not 0.0 <= readout < 1.0:
            raise CalibrationError(f"{where}: readout_s {readout!r} must be a number of seconds in [0, 1)")
        legs = entry.get("legs_in_view")
        if legs is not None and not isinstance(legs, bool):
            raise CalibrationError(f"{where}: legs_in_view must be true or false, got {legs!r}")
        offset = entry.get("stamp_offset_s")
        if offset is not None and (
            isinstance(offset, bool) or not isinstance(offset, (int, float)) or not abs(float(offset)) < 1.0
        ):
            raise CalibrationError(f"{where}: stamp_offset_s {offset!r} must be a number of seconds within +-1")
        rc = RigCamera(name, cam, _check_T(entry["T_body_camera"], where), calib_file, float(readout))
        rc.legs_in_view = legs
        rc.stamp_offset_s = None if offset is None else float(offset)
        out.append(rc)
    height = doc.get("vest_height_m")
    if height is not None and (
        isinstance(height, bool)
        or not isinstance(height, (int, float))
        or not 0.0 < float(height) < MAX_CAMERA_HEIGHT_M
    ):
        raise CalibrationError(
            f"{path}: vest_height_m must be a height in metres (0-{MAX_CAMERA_HEIGHT_M:g}), got {height!r}"
        )
    return Rig(_shared_height(out, height))


def local_calibration_names(rig: Rig) -> list[str]:
    """A plain file name per camera for its calibration beside a written ``rig.json``: the rig's own
    name's last part (``cams/front.yaml`` -> ``front.yaml``), or ``camera<k>.yaml`` where two
    cameras' would be the same."""
    names = [Path(c.calibration_file).name or f"camera{k}.yaml" for k, c in enumerate(rig.cameras)]
    if len(set(names)) < len(names):
        names = [f"camera{k}.yaml" for k in range(len(names))]
    return names


def save_rig(rig: Rig, path: str | Path, write_calibrations: bool = True) -> None:
    """Write ``rig.json``; by default with each camera's calibration written beside it, under a plain
    file name (:func:`local_calibration_names`) that ``rig.json`` then names: a rig loaded from
    elsewhere may name its calibrations by an absolute path or a folder, and a copy of it (a
    recording's) must neither write over those files nor depend on them. Without
    ``write_calibrations`` the rig's own names are kept (a rig written beside its calibrations)."""
    path = Path(path)
    names = local_calibration_names(rig) if write_calibrations else [c.calibration_file for c in rig.cameras]
    doc = {
        "vest_height_m": round(float(rig.vest_point[2]), 6),
        "cameras": [
            {"name": c.name, "calibration": name, "T_body_camera": np.round(c.T_body_camera, 12).tolist()}
            | ({"readout_s": c.readout_s} if c.readout_s > 0 else {})
            | ({"legs_in_view": bool(c.legs_in_view)} if c.legs_in_view is not None else {})
            | ({"stamp_offset_s": c.stamp_offset_s} if c.stamp_offset_s is not None else {})
            for c, name in zip(rig.cameras, names)
        ],
    }
    path.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    if write_calibrations:
        for c, name in zip(rig.cameras, names):
            save_calibration(c.camera, path.parent / name)
