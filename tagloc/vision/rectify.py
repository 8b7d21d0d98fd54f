"""Frontal raster of a detected sticker, lens distortion accounted for.

The raster follows :mod:`tagloc.core.sticker`'s convention (pixel centres half a pixel in from the
outer edges) but in *detection* order: its top-left is ``detection.outer[0]``, and it goes
clockwise from there, so a sticker seen with rotation r appears rotated in the raster.

How the distortion is handled: the homography is fitted in undistorted (ideal) pixels, where the
floor plane really is a homography of the sticker. A 5x5 grid of raster points is mapped through it
and re-distorted; if one homography straight to the distorted image fits that grid to within
``RectifyConfig.max_residual_px`` (distortion is locally almost projective over a ~100 px sticker),
a single ``cv2.warpPerspective`` does the job; otherwise a coarse grid (every 10 raster px) is
re-distorted exactly, interpolated to every pixel and sampled with ``cv2.remap``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from tagloc.core.camera import Camera
from tagloc.core.errors import InputError
from tagloc.core.sticker import FRAME_M, SIZE_M
from tagloc.core.types import Detection
from tagloc.vision.image import require_gray

#: Default raster side: 200 px puts the sticker's 0.5 mm design grid on whole pixels
#: (module = 7 px, frame = 16 px, quadrant = 84 px).
DEFAULT_SIZE_PX = 200


@dataclass
class RectifyConfig:
    """Options of :func:`rectify`.

    Attributes:
        max_residual_px: largest error (distorted image pixels) tolerated from approximating the
            distorted mapping by one homography before falling back to an exact per-pixel remap.
        interpolation: OpenCV interpolation flag for sampling the image.
    """

    max_residual_px: float = 0.05
    interpolation: int = cv2.INTER_LINEAR


def raster_corners(size_px: int, inner: bool = True) -> np.ndarray:
    """Raster (col, row) of the outer (then inner) corners, clockwise from top-left: (4 or 8, 2)."""
    lo, hi = -0.5, size_px - 0.5
    outer = np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]])
    if not inner:
        return outer
    d = FRAME_M / SIZE_M * size_px
    return np.vstack([outer, outer + np.array([[d, d], [-d, d], [-d, -d], [d, -d]])])


def ideal_homography(detection: Detection, camera: Camera, size_px: int) -> np.ndarray:
    """(3, 3) homography from raster (col, row) to undistorted pixels, from all detected corners."""
    img = camera.undistort_pixels(detection.points)
    src = raster_corners(size_px, inner=detection.inner is not None)
    if len(src) == 4:
        return cv2.getPerspectiveTransform(src.astype(np.float32), img.astype(np.float32))
    H, _ = cv2.findHomography(src, img, 0)
    if H is None:
        raise InputError("rectify: detection corners are degenerate (no homography)")
    return H


def distort_points(ideal: np.ndarray, camera: Camera) -> np.ndarray:
    """Undistorted pixels (N, 2) -> distorted pixels (N, 2) of the same camera."""
    rays = cv2.undistortPoints(ideal.reshape(-1, 1, 2), camera.K, None)  # K^-1 only: no distortion
    pts3 = cv2.convertPointsToHomogeneous(rays).reshape(-1, 3)
    return camera.project(pts3)


_STEP = 10  # raster px between exactly re-distorted points when the homography shortcut is too coarse


@lru_cache(maxsize=8)
def _coarse_index(size_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Left coarse-grid index (size,) and fraction (size,) of each raster pixel centre.

    Used for separable bilinear interpolation in full float precision (cv2.remap would quantise
    positions to 1/32 of a coarse cell, ~0.07 image px here).
    """
    n = int(np.ceil(size_px / _STEP)) + 1
    u = (np.arange(size_px) + 0.5) / _STEP  # pixel centre in coarse-grid units
    j = np.minimum(np.floor(u).astype(int), n - 2)
    return j, u - j


def distorted_mapping(
    detection: Detection, camera: Camera, size_px: int, config: RectifyConfig | None = None
) -> tuple[np.ndarray | None, np.ndarray | None, float]:
    """How to sample the image for the raster.

    Returns ``(H, None, residual)`` when one homography raster -> distorted pixels is accurate to
    ``config.max_residual_px``, else ``(None, maps, residual)`` with ``maps`` (size, size, 2)
    float32 distorted pixel positions of every raster pixel (bilinear between exact points 10 px
    apart). ``residual`` is the homography's
    largest error on the check grid (px).
    """
    config = config or RectifyConfig()
    H = ideal_homography(detection, camera, size_px)
    if not np.any(camera.dist):
        return H, None, 0.0
    g = np.linspace(-0.5, size_px - 0.5, 5)
    grid = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    dist_pts = distort_points(cv2.perspectiveTransform(grid.reshape(-1, 1, 2), H).reshape(-1, 2), camera)
    Hd, _ = cv2.findHomography(grid, dist_pts, 0)
    if Hd is not None:
        resid = cv2.perspectiveTransform(grid.reshape(-1, 1, 2), Hd).reshape(-1, 2) - dist_pts
        err = float(np.max(np.linalg.norm(resid, axis=1)))
        if err <= config.max_residual_px:
            return Hd, None, err
    else:
        err = float("inf")
    # Exact re-distortion on a coarse grid (every _STEP raster px, edges included), bilinearly
    # interpolated to every pixel: the distortion is smooth at that scale and this is ~30x cheaper
    # than re-distorting all size_px^2 pixels.
    n = int(np.ceil(size_px / _STEP)) + 1
    g = -0.5 + _STEP * np.arange(n, dtype=float)
    coarse = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    dist_c = distort_points(cv2.perspectiveTransform(coarse.reshape(-1, 1, 2), H).reshape(-1, 2), camera)
    dist_c = dist_c.reshape(n, n, 2)
    j, f = _coarse_index(size_px)
    rows = dist_c[j] * (1 - f)[:, None, None] + dist_c[j + 1] * f[:, None, None]  # (size, n, 2)
    maps = rows[:, j] * (1 - f)[None, :, None] + rows[:, j + 1] * f[None, :, None]  # (size, size, 2)
    return None, maps.astype(np.float32), err


def rectify(
    gray: np.ndarray,
    detection: Detection,
    camera: Camera,
    size_px: int = DEFAULT_SIZE_PX,
    config: RectifyConfig | None = None,
) -> np.ndarray:
    """Frontal ``(size_px, size_px)`` uint8 raster of the sticker's outer square.

    Args:
        gray: (H, W) uint8 distorted image.
        detection: the sticker's corners (distorted pixels, clockwise on screen).
        camera: intrinsics and distortion of ``gray``.
        size_px: raster side; 200 gives 7 px per Data Matrix module.
    Returns:
        The raster with ``detection.outer[0]`` at its top-left, going clockwise.
    """
    config = config or RectifyConfig()
    require_gray(gray, "rectify")
    H, maps, _ = distorted_mapping(detection, camera, size_px, config)
    if H is not None:
        return cv2.warpPerspective(
            gray,
            H,
            (size_px, size_px),
            flags=config.interpolation | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE,
        )
    return cv2.remap(gray, maps, None, config.interpolation, borderMode=cv2.BORDER_REPLICATE)
