"""The linear motion-blur kernel, shared by decoding's PSF and identification's blurred templates."""

from __future__ import annotations

import numpy as np

#: Points sampled per pixel of blur length: dense enough that the bilinear splats merge into a line.
SAMPLES_PER_PX = 8
#: Shorter blurs (px) are no blur: the kernel is the identity.
MIN_LENGTH_PX = 0.25


def motion_kernel(blur: np.ndarray) -> np.ndarray:
    """Linear motion-blur kernel (odd square, float32, sums to 1) for a blur vector (2,) (dx, dy) px.

    The segment from -blur/2 to +blur/2 is sampled densely and each sample splatted bilinearly,
    so the kernel has the segment's exact length and no width across it. Point-symmetric, so
    filtering with it (correlation) is convolving with it.
    """
    b = np.asarray(blur, float).reshape(2)
    length = float(np.hypot(*b))
    if length < MIN_LENGTH_PX:
        return np.ones((1, 1), np.float32)
    half = int(np.ceil(length)) // 2 + 1  # the splats reach at most ceil(length)/2 + 1 from the centre
    n = 2 * half + 1
    t = np.linspace(-0.5, 0.5, max(2, int(np.ceil(length * SAMPLES_PER_PX))))
    x, y = half + t * b[0], half + t * b[1]
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    k = np.zeros((n, n))
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(k, (y0 + dy, x0 + dx), w)
    return (k / k.sum()).astype(np.float32)
