"""Small simulated sessions and videos for the live/replay tests (imported by those tests).

The simulator (:mod:`tagloc.sim.simulate`) walks the default rig (Pi camera 1.3 m up, pitched 55
degrees down) over three rows of stickers 0.5 m apart, so every frame sees stickers.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from tagloc.core.stickermap import StickerMap
from tagloc.eval.metrics import interpolate_groundtruth
from tagloc.io.session import read_tum
from tagloc.sim.simulate import SimConfig, simulate_session


def line_map() -> StickerMap:
    """Three rows of stickers 0.5 m apart along x (y = 0, +-1.5 m), IDs 100..., 200..., 300..."""
    xs = np.arange(-1.0, 6.01, 0.5)
    ids = [100 + k for k in range(len(xs))] + [200 + k for k in range(len(xs))] + [300 + k for k in range(len(xs))]
    xy = np.vstack([np.c_[xs, np.zeros_like(xs)], np.c_[xs, np.full_like(xs, 1.5)], np.c_[xs, np.full_like(xs, -1.5)]])
    yaw = np.radians(np.resize([0.0, 90.0, 35.0, 180.0, -60.0], len(ids)))
    return StickerMap(np.array(ids), xy, yaw)


def make_session(path: Path, n_frames: int = 20, fps: float = 10.0, corrupt: tuple[int, ...] = ()) -> Path:
    """Simulate a walk of ``n_frames`` frames into ``path``; frames in ``corrupt`` are then overwritten with garbage."""
    simulate_session(
        line_map(), path, SimConfig(seconds=n_frames / fps, fps=fps, lux=200.0, speed_mps=0.8, seed=3), progress=False
    )
    for k in corrupt:
        (path / "frames" / f"{k:06d}.jpg").write_bytes(b"not a jpeg")
    return path


def truth_xy(session: Path, stamps: np.ndarray) -> np.ndarray:
    """Ground-truth body (x, y) (N, 2) at ``stamps`` (all inside the walk)."""
    gt, inside = interpolate_groundtruth(*read_tum(session / "groundtruth.tum"), np.asarray(stamps, float))
    assert inside.all()
    return gt[:, :2]


def write_video(session: Path, path: Path, fps: float = 10.0) -> Path:
    """The session's readable frames as an MJPG .avi (what a vest camera recording looks like)."""
    images = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in sorted((session / "frames").glob("*.jpg"))]
    images = [im for im in images if im is not None]
    h, w = images[0].shape
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert vw.isOpened()
    for im in images:
        vw.write(cv2.cvtColor(im, cv2.COLOR_GRAY2BGR))
    vw.release()
    return path
