"""Images as the per-frame stages take them, and quad corner order: the one place either is decided.

Every stage takes a (H, W) uint8 greyscale image; :func:`as_gray` is the only conversion.
"""

from __future__ import annotations

import cv2
import numpy as np

from tagloc.core.errors import InputError
from tagloc.core.sticker import rotate_corners


def as_gray(image: np.ndarray) -> np.ndarray:
    """Return ``image`` as a (H, W) uint8 greyscale array.

    Accepts (H, W), (H, W, 1), BGR (H, W, 3) or BGRA (H, W, 4); uint8, uint16 (scaled down), bool,
    or float (0-1 if its maximum is at most 1, else 0-255). Raises InputError for anything else.
    """
    why = unusable(image)
    if why is not None:
        raise InputError(why)
    img = image
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.dtype == np.bool_:
        img = img.astype(np.uint8) * 255
    elif img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif np.issubdtype(img.dtype, np.floating):
        f = np.nan_to_num(img.astype(np.float32), nan=0.0, posinf=255.0, neginf=0.0)
        scale = 255.0 if f.size and float(f.max()) <= 1.0 else 1.0
        img = np.clip(f * scale + 0.5, 0, 255).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    return np.ascontiguousarray(img)


def unusable(image: object) -> str | None:
    """Why :func:`as_gray` cannot take ``image``, or None: a check of its type, shape and dtype alone
    (nothing is converted), so that a frame can be refused before any stage runs on it."""
    if not isinstance(image, np.ndarray):
        return f"image must be a numpy array, got {type(image).__name__}"
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3, 4)):
        return f"image shape {image.shape} is not (H, W), (H, W, 3) or (H, W, 4)"
    if not (
        image.dtype == np.bool_ or np.issubdtype(image.dtype, np.integer) or np.issubdtype(image.dtype, np.floating)
    ):
        return f"image dtype {image.dtype} is not an image type"
    return None


def require_gray(image: np.ndarray, stage: str) -> np.ndarray:
    """``image`` itself if it is what every stage takes, a (H, W) uint8 array; else InputError naming
    ``stage`` (convert with :func:`as_gray` first)."""
    if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype != np.uint8:
        what = f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
        raise InputError(f"{stage}: expected a (H, W) uint8 greyscale image, got {what} (see as_gray)")
    return image


def clockwise(quad: np.ndarray) -> np.ndarray:
    """Quad (4, 2) in clockwise on-screen order (positive shoelace area with y down), top-left-most first."""
    x, y = quad[:, 0], quad[:, 1]
    # rotate_corners(a, k)[i] is a[i + k]: np.roll(a, -k) without its set-up, which cost more here.
    if np.dot(x, rotate_corners(y, 1)) - np.dot(rotate_corners(x, 1), y) < 0:
        quad = quad[::-1]
    return rotate_corners(quad, int(np.argmin(quad.sum(axis=1))))
