"""Synthetic camera frames of floor stickers with exact ground-truth corners (a test helper).

Not the simulator: the floor is a procedural concrete texture, blur is a linear motion kernel and
noise is additive Gaussian, which is enough to exercise detection and pose code with known truth.

Rendering is exact to a few hundredths of a pixel: every output pixel is 8x8 super-sampled, each
sub-sample is traced through the lens distortion (undistort) and the sticker-plane homography into
the canonical raster of :func:`tagloc.core.sticker.render_sticker`, so the sticker's edges land where
``Camera.project`` puts its corners. Intensities are composed in linear light (0-1), blurred,
gamma-encoded, then noise is added and values quantised to uint8.

Typical use::

    cam = default_camera()
    T = sticker_pose(cam, centre_px=(640, 500), distance_m=1.2, tilt_deg=40, yaw_deg=30)
    frame = synth_frame([(42, T)], cam, blur_px=4, noise=3, seed=1)
    frame.image, frame.outer[0], frame.inner[0]   # (972, 1296) uint8, (4, 2), (4, 2)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from tagloc.core.camera import Camera
from tagloc.core.geometry import invert, make_T, transform_points
from tagloc.core.sticker import INNER_CORNERS, OUTER_CORNERS, SIZE_M, render_sticker

_SUPER = 8  # sub-samples per pixel side
_RASTER = 600  # sticker raster resolution used for sampling (px per 100 mm; a multiple of 200 keeps it exact)
_PAD = 4  # raster pixels of "outside" around the sticker, so alpha ramps exactly at the edge
_PAPER = 0.85  # linear reflectances
_INK = 0.04


@dataclass
class SynthFrame:
    """A synthetic frame and its truth.

    Attributes:
        image: (H, W) uint8 greyscale.
        ids: sticker IDs, in the order given.
        outer: per sticker (4, 2) outer corners, distorted pixels, canonical order (TL, TR, BR, BL).
        inner: per sticker (4, 2) inner frame corners, same order.
        inside: per sticker, True when all 4 outer corners are at least 3 px inside the image.
        H: per sticker (3, 3) homography sticker-plane metres (x, y, 1) -> undistorted pixels.
    """

    image: np.ndarray
    ids: list[int] = field(default_factory=list)
    outer: list[np.ndarray] = field(default_factory=list)
    inner: list[np.ndarray] = field(default_factory=list)
    inside: list[bool] = field(default_factory=list)
    H: list[np.ndarray] = field(default_factory=list)


def distort_ideal(camera: Camera, pixels: np.ndarray) -> np.ndarray:
    """Map ideal (undistorted) pixels (N, 2) to distorted pixels (N, 2) of ``camera``."""
    pts = np.asarray(pixels, float).reshape(-1, 2)
    norm = np.c_[(pts[:, 0] - camera.K[0, 2]) / camera.K[0, 0], (pts[:, 1] - camera.K[1, 2]) / camera.K[1, 1]]
    return camera.project(np.c_[norm, np.ones(len(norm))])


def sticker_pose(
    camera: Camera,
    centre_px: tuple[float, float],
    distance_m: float,
    tilt_deg: float,
    yaw_deg: float = 0.0,
    tilt_dir_deg: float = 0.0,
) -> np.ndarray:
    """``T_camera_sticker`` (4, 4) putting a sticker's centre on the ray through ``centre_px``.

    ``distance_m`` is the range along that ray, ``tilt_deg`` the angle between the viewing ray and
    the sticker's normal (0 = seen face on), ``tilt_dir_deg`` the direction of that tilt about the
    ray, and ``yaw_deg`` the sticker's in-plane rotation (0: canonical top towards image top).
    """
    ideal = camera.undistort_pixels(np.array([centre_px], float))[0]
    ray = np.linalg.solve(camera.K, np.r_[ideal, 1.0])
    ray /= np.linalg.norm(ray)
    # Face-on frame: +z towards the camera, +y (canonical top) roughly towards image top.
    z = -ray
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R0 = np.column_stack([x, y, z])
    d = math.radians(tilt_dir_deg)
    axis = math.cos(d) * x + math.sin(d) * y
    R = Rotation.from_rotvec(math.radians(tilt_deg) * axis).as_matrix() @ R0
    R = R @ Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    return make_T(R, ray * distance_m)


def concrete(shape: tuple[int, int], seed: int = 0, level: float = 0.40, contrast: float = 0.05) -> np.ndarray:
    """Procedural concrete floor (H, W) float32 linear reflectance: a few octaves of smooth noise plus grit."""
    rng = np.random.default_rng(seed)
    h, w = shape
    out = np.full((h, w), level, np.float32)
    for cell, amp in ((64, 1.0), (16, 0.6), (4, 0.4), (1, 0.35)):
        small = rng.standard_normal((max(2, h // cell + 2), max(2, w // cell + 2))).astype(np.float32)
        big = cv2.resize(small, (w + 2 * cell, h + 2 * cell), interpolation=cv2.INTER_CUBIC)
        out += contrast * amp * big[cell : cell + h, cell : cell + w]
    return np.clip(out, 0.02, 0.95)


def motion_kernel(length_px: float, angle_deg: float) -> np.ndarray:
    """Centred linear motion-blur kernel (odd square, sums to 1): a segment of ``length_px`` at ``angle_deg``.

    Centred means the blurred image shows the scene at mid-exposure.
    """
    size = 2 * int(math.ceil(length_px / 2)) + 3
    k = np.zeros((size, size), np.float64)
    c = size // 2
    a = math.radians(angle_deg)
    n = max(2, int(length_px * 20))
    for s in np.linspace(-length_px / 2, length_px / 2, n):
        x, y = c + s * math.cos(a), c + s * math.sin(a)
        x0, y0 = int(math.floor(x)), int(math.floor(y))
        fx, fy = x - x0, y - y0
        k[y0, x0] += (1 - fx) * (1 - fy)
        k[y0, x0 + 1] += fx * (1 - fy)
        k[y0 + 1, x0] += (1 - fx) * fy
        k[y0 + 1, x0 + 1] += fx * fy
    return (k / k.sum()).astype(np.float32)


def _homography(camera: Camera, pose: np.ndarray, T_world_camera: np.ndarray | None) -> np.ndarray:
    pose = np.asarray(pose, float)
    if pose.shape == (3, 3):
        return pose / pose[2, 2]
    T = pose if T_world_camera is None else invert(T_world_camera) @ pose
    H = camera.K @ np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]])
    return H / H[2, 2]


def _ideal_corners(H: np.ndarray, corners: np.ndarray) -> np.ndarray:
    p = np.c_[corners[:, :2], np.ones(len(corners))] @ H.T
    return p[:, :2] / p[:, 2:]


def _paint_sticker(
    lin: np.ndarray, camera: Camera, H: np.ndarray, raster: np.ndarray, alpha_r: np.ndarray, outer_px: np.ndarray
) -> None:
    """Composite one sticker into the linear image ``lin`` in place."""
    h, w = lin.shape
    # Edges bow under distortion, so take the box of densely sampled outline points.
    t = np.linspace(0, 1, 25)[:, None]
    ring = np.vstack([(1 - t) * OUTER_CORNERS[i, :2] + t * OUTER_CORNERS[(i + 1) % 4, :2] for i in range(4)])
    outline = distort_ideal(camera, _ideal_corners(H, ring))
    x0, y0 = np.floor(outline.min(0)).astype(int) - 3
    x1, y1 = np.ceil(outline.max(0)).astype(int) + 4
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if x1 - x0 < 2 or y1 - y0 < 2:
        return
    # Sticker-raster coordinates of every pixel centre in the box; the map is smooth, so the
    # super-samples take them by bilinear up-sampling instead of tracing each one.
    gx, gy = np.meshgrid(np.arange(x0, x1, dtype=float), np.arange(y0, y1, dtype=float))
    ideal = camera.undistort_pixels(np.c_[gx.ravel(), gy.ravel()])
    plane = np.c_[ideal, np.ones(len(ideal))] @ np.linalg.inv(H).T
    plane = plane[:, :2] / plane[:, 2:]
    n = raster.shape[0] - 2 * _PAD
    col = (plane[:, 0] + SIZE_M / 2) / SIZE_M * n - 0.5 + _PAD
    row = (SIZE_M / 2 - plane[:, 1]) / SIZE_M * n - 0.5 + _PAD
    bw, bh = x1 - x0, y1 - y0
    size = (bw * _SUPER, bh * _SUPER)
    mx = cv2.resize(col.reshape(bh, bw).astype(np.float32), size, interpolation=cv2.INTER_LINEAR)
    my = cv2.resize(row.reshape(bh, bw).astype(np.float32), size, interpolation=cv2.INTER_LINEAR)
    val = cv2.remap(raster, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    alpha = cv2.remap(alpha_r, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    val = val.reshape(bh, _SUPER, bw, _SUPER).mean(axis=(1, 3))
    alpha = alpha.reshape(bh, _SUPER, bw, _SUPER).mean(axis=(1, 3))
    box = lin[y0:y1, x0:x1]
    # val is premultiplied by alpha (the raster's padding is 0).
    lin[y0:y1, x0:x1] = box * (1 - alpha) + val


def _sticker_rasters(sticker_id: int) -> tuple[np.ndarray, np.ndarray]:
    img = render_sticker(sticker_id, _RASTER).astype(np.float32) / 255.0
    lin = _INK + (_PAPER - _INK) * img
    val = cv2.copyMakeBorder(lin, _PAD, _PAD, _PAD, _PAD, cv2.BORDER_CONSTANT, value=0)
    alpha = cv2.copyMakeBorder(np.ones_like(lin), _PAD, _PAD, _PAD, _PAD, cv2.BORDER_CONSTANT, value=0)
    return val, alpha


def synth_frame(
    stickers: Sequence[tuple[int, np.ndarray]],
    camera: Camera,
    T_world_camera: np.ndarray | None = None,
    *,
    blur_px: float = 0.0,
    blur_angle_deg: float = 0.0,
    noise: float = 0.0,
    gamma: float = 1.0,
    exposure: float = 1.0,
    distractors: Sequence[tuple[float, float, float, float]] = (),
    lines: Sequence[tuple[float, float, float, float, float]] = (),
    background: np.ndarray | None = None,
    seed: int = 0,
) -> SynthFrame:
    """Render a frame of ``camera`` showing the given stickers on a concrete floor.

    Args:
        stickers: (id, pose) pairs. pose is ``T_world_sticker`` (4, 4) when ``T_world_camera`` is given,
            else ``T_camera_sticker`` (4, 4), or a (3, 3) homography from sticker-plane metres
            (x, y, 1) to undistorted pixels. In-plane rotation is part of the pose.
        camera: intrinsics and image size; lens distortion is applied.
        T_world_camera: camera pose in the world, or None (poses are then camera-relative).
        blur_px, blur_angle_deg: centred linear motion blur (length in pixels, direction).
        noise: additive Gaussian noise, standard deviation in grey levels (0-255).
        gamma: encoding exponent: stored value = 255 * (exposure * linear) ** (1 / gamma).
        exposure: scale on linear light (dim scenes < 1).
        distractors: dark squares (cx, cy, side, angle_deg) in pixels, painted before blur.
        lines: painted bright lines (x0, y0, x1, y1, width) in pixels.
        background: (H, W) linear reflectance to use instead of procedural concrete.
        seed: seeds the texture and the noise.

    Returns:
        The image and, per sticker, true outer/inner corners in distorted pixels, canonical order.
    """
    h, w = camera.height, camera.width
    lin = concrete((h, w), seed) if background is None else np.asarray(background, np.float32).copy()
    for x0, y0, x1, y1, width in lines:
        cv2.line(lin, (round(x0), round(y0)), (round(x1), round(y1)), 0.75, max(1, round(width)), cv2.LINE_AA)
    for cx, cy, side, ang in distractors:
        pts = cv2.boxPoints(((cx, cy), (side, side), ang))
        cv2.fillConvexPoly(lin, np.round(pts * 16).astype(np.int32), 0.05, cv2.LINE_AA, shift=4)
    frame = SynthFrame(image=np.zeros((h, w), np.uint8))
    for sid, pose in stickers:
        H = _homography(camera, pose, T_world_camera)
        outer = distort_ideal(camera, _ideal_corners(H, OUTER_CORNERS))
        inner = distort_ideal(camera, _ideal_corners(H, INNER_CORNERS))
        val, alpha = _sticker_rasters(int(sid))
        _paint_sticker(lin, camera, H, val, alpha, outer)
        frame.ids.append(int(sid))
        frame.outer.append(outer)
        frame.inner.append(inner)
        frame.H.append(H)
        frame.inside.append(bool(np.all((outer >= 3) & (outer <= [w - 4, h - 4]))))
    if blur_px > 0:
        lin = cv2.filter2D(lin, -1, motion_kernel(blur_px, blur_angle_deg), borderType=cv2.BORDER_REFLECT)
    enc = 255.0 * np.clip(lin * exposure, 0, 1) ** (1.0 / gamma)
    if noise > 0:
        enc = enc + np.random.default_rng(seed + 7919).normal(0.0, noise, enc.shape)
    frame.image = np.clip(np.rint(enc), 0, 255).astype(np.uint8)
    return frame


def floor_view(camera: Camera, height_m: float = 1.3, pitch_deg: float = 55.0) -> np.ndarray:
    """``T_world_camera`` of a camera ``height_m`` above the world origin looking along +x, pitched down."""
    p = math.radians(pitch_deg)
    fwd = np.array([math.cos(p), 0.0, -math.sin(p)])
    right = np.array([0.0, -1.0, 0.0])
    down = np.cross(fwd, right)
    return make_T(np.column_stack([right, down, fwd]), (0.0, 0.0, height_m))


def floor_point_at_pixel(camera: Camera, T_world_camera: np.ndarray, pixel: tuple[float, float]) -> np.ndarray:
    """World (x, y) of the floor point seen at distorted ``pixel`` (2,)."""
    ideal = camera.undistort_pixels(np.array([pixel], float))[0]
    ray_c = np.linalg.solve(camera.K, np.r_[ideal, 1.0])
    ray_w = T_world_camera[:3, :3] @ ray_c
    origin = T_world_camera[:3, 3]
    s = -origin[2] / ray_w[2]
    return (origin + s * ray_w)[:2]


def project_world(camera: Camera, T_world_camera: np.ndarray, points_w: np.ndarray) -> np.ndarray:
    """Distorted pixels (N, 2) of world points (N, 3)."""
    return camera.project(transform_points(invert(T_world_camera), points_w))


def with_exif_orientation(jpeg: bytes, orientation: int) -> bytes:
    """``jpeg`` with an APP1 Exif block holding only an orientation tag (1-8), as a phone or a camera
    driver may write: a big-endian TIFF header and one IFD with the tag as a SHORT."""
    ifd = (1).to_bytes(2, "big") + bytes.fromhex("0112 0003 00000001") + orientation.to_bytes(2, "big") + bytes(6)
    payload = b"Exif\0\0" + b"MM\0\x2a" + (8).to_bytes(4, "big") + ifd
    return jpeg[:2] + b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload + jpeg[2:]
