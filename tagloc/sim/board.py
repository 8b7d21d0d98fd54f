"""Synthetic views of the ChArUco calibration board through a known camera (for testing calibration).

Each sensor pixel is traced back through the lens: ``cv2.undistortPointsIter`` turns it into a
ray of the ideal pinhole camera, the ray meets the board plane, and the board's raster is sampled
there with one ``cv2.remap``. The distortion is therefore exactly OpenCV's model, inverted to the
iteration's tolerance, and the true corners are where ``cv2.projectPoints`` puts them. The raster
is low-pass filtered to the sensor's sampling first (no aliasing), then the image gets a lens blur
and Gaussian noise, so corner localisation behaves as on a camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from tagloc.core.camera import Camera
from tagloc.core.charuco import DEFAULT_BOARD, BoardSpec, board_image
from tagloc.core.geometry import make_T

_PX_PER_MM = 8.0  # board raster resolution: finer than any sensor pixel on the board in these views
_PAPER_MARGIN_SQUARES = 1.0  # white paper around the board (ArUco needs a light quiet zone)


@dataclass(frozen=True)
class BoardSceneConfig:
    """Image formation of a board view.

    Attributes:
        paper, background: grey levels (0-255) of the white paper and of the surroundings.
        black: grey level of the printed black (toner reflects a few per cent).
        psf_sigma_px: Gaussian lens blur, pixels (as tagloc's floor renderer's 0.6 px).
        noise_sigma: Gaussian noise, grey levels.
    """

    paper: float = 215.0
    background: float = 90.0
    black: float = 25.0
    psf_sigma_px: float = 0.6
    noise_sigma: float = 2.0


@lru_cache(maxsize=4)
def _rays(key: tuple) -> np.ndarray:
    """(H, W, 2) normalised ideal image coordinates of every sensor pixel of the camera in ``key``."""
    K = np.array(key[0]).reshape(3, 3)
    dist = np.array(key[1])
    w, h = key[2], key[3]
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([uu.ravel(), vv.ravel()], axis=1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4; OpenCV 5 folded the criteria into undistortPoints
        und = cv2.undistortPointsIter(pts, K, dist, None, None, criteria)
    else:
        und = cv2.undistortPoints(pts, K, dist, criteria=criteria)
    return und.reshape(h, w, 2)


@lru_cache(maxsize=4)
def _paper(spec: BoardSpec, cfg: BoardSceneConfig) -> tuple[np.ndarray, float]:
    """The board on its paper margin as float32 grey levels, and the margin in metres."""
    board = board_image(spec, _PX_PER_MM).astype(np.float32) / 255.0
    img = cfg.black + (cfg.paper - cfg.black) * board
    pad = round(_PAPER_MARGIN_SQUARES * spec.square_m * 1000 * _PX_PER_MM)
    img = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=cfg.paper)
    return img, pad / (_PX_PER_MM * 1000.0)


def render_board_view(
    camera: Camera,
    T_camera_board: np.ndarray,
    spec: BoardSpec = DEFAULT_BOARD,
    cfg: BoardSceneConfig = BoardSceneConfig(),
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """The (H, W) uint8 image of the board at ``T_camera_board`` (board frame: x, y on the board
    from its corner, z into the board) seen by ``camera``."""
    d = _rays((tuple(camera.K.ravel()), tuple(camera.dist), camera.width, camera.height))
    R, t = T_camera_board[:3, :3], T_camera_board[:3, 3]
    # Ray s * (x, y, 1) in the camera; in the board frame p = R^T (s d - t); the plane is p_z = 0.
    dirs = np.concatenate([d, np.ones(d.shape[:2] + (1,))], axis=2) @ R  # (H, W, 3) = R^T d
    origin = -R.T @ t
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -origin[2] / dirs[..., 2]
    hit = origin[None, None, :2] + s[..., None] * dirs[..., :2]
    hit[~(s > 0)] = -1e3  # behind the camera: background
    paper, margin_m = _paper(spec, cfg)
    scale = _PX_PER_MM * 1000.0
    map_x = ((hit[..., 0] + margin_m) * scale - 0.5).astype(np.float32)
    map_y = ((hit[..., 1] + margin_m) * scale - 0.5).astype(np.float32)
    # Low-pass the raster to the sensor's sampling at this distance (raster px per sensor px / 2).
    depth = float(t[2])
    ratio = scale * depth / camera.fx
    src = cv2.GaussianBlur(paper, (0, 0), 0.5 * ratio) if ratio > 1.0 else paper
    img = cv2.remap(src, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=cfg.background)
    if cfg.psf_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), cfg.psf_sigma_px)
    if cfg.noise_sigma > 0:
        rng = rng or np.random.default_rng(0)
        img = img + rng.normal(0.0, cfg.noise_sigma, img.shape).astype(np.float32)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def _rot(ax: float, ay: float, az: float) -> np.ndarray:
    """Rotation by ``az`` about z, then ``ay`` about y, then ``ax`` about x (radians), as cv2.Rodrigues does."""
    Rx = cv2.Rodrigues(np.array([ax, 0.0, 0.0]))[0]
    Ry = cv2.Rodrigues(np.array([0.0, ay, 0.0]))[0]
    Rz = cv2.Rodrigues(np.array([0.0, 0.0, az]))[0]
    return Rx @ Ry @ Rz


def board_poses(
    camera: Camera,
    n: int,
    spec: BoardSpec = DEFAULT_BOARD,
    seed: int = 0,
    fill: float = 0.6,
    max_tilt_deg: float = 35.0,
) -> list[np.ndarray]:
    """``n`` poses ``T_camera_board`` as a person calibrating would hold the board: its centre on a
    ray through points spread over the image, at a distance where it fills about ``fill`` of the
    image width, tilted up to ``max_tilt_deg`` about both board axes and rolled up to 20 degrees."""
    rng = np.random.default_rng(seed)
    w_m, h_m = spec.size_m
    depth0 = camera.fx * w_m / (fill * camera.width)
    out = []
    for _ in range(n):
        u = rng.uniform(0.25, 0.75) * camera.width
        v = rng.uniform(0.25, 0.75) * camera.height
        depth = depth0 * rng.uniform(0.85, 1.25)
        ray = np.linalg.solve(camera.K, np.array([u, v, 1.0]))
        centre = ray * depth
        tilt = math.radians(max_tilt_deg)
        R = _rot(rng.uniform(-tilt, tilt), rng.uniform(-tilt, tilt), rng.uniform(-math.radians(20), math.radians(20)))
        # Board frame origin at its corner: put the board's centre on the chosen ray.
        t = centre - R @ np.array([w_m / 2, h_m / 2, 0.0])
        out.append(make_T(R, t))
    return out
