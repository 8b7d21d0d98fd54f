"""Small synthetic sessions and videos for the live/replay/sink tests (imported by those tests).

The default rig (Pi camera 1.3 m up, pitched 55 degrees down) walks along a line of stickers 0.5 m
apart, so every frame sees one to three stickers at 60-100 px.
"""

from __future__ import annotations

import hashlib
import math
import os
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np

from synth import synth_frame
from tagloc.camera import Camera
from tagloc.geometry import invert, planar_T, transform_points
from tagloc.rig import default_rig
from tagloc.session import SessionInfo, SessionWriter, write_tum
from tagloc.stickermap import StickerMap


def line_map() -> StickerMap:
    """Stickers every 0.5 m along y = 0 (IDs 100...), plus two side rows out of view."""
    xs = np.arange(-0.5, 5.01, 0.5)
    ids = [100 + k for k in range(len(xs))] + [200 + k for k in range(len(xs))] + [300 + k for k in range(len(xs))]
    xy = np.vstack([np.c_[xs, np.zeros_like(xs)], np.c_[xs, np.full_like(xs, 1.5)], np.c_[xs, np.full_like(xs, -1.5)]])
    yaw = np.radians(np.resize([0.0, 90.0, 35.0, 180.0, -60.0], len(ids)))
    return StickerMap(np.array(ids), xy, yaw)


def walk_pose(t: float) -> tuple[float, float, float]:
    """Body (x, y, yaw) at time t: 0.5 m/s along +x, a gentle sway."""
    return 0.5 * t, 0.03 * math.sin(2.0 * t), 0.05 * math.sin(1.3 * t)


def _in_view(camera: Camera, T_world_camera: np.ndarray, point: np.ndarray, margin_px: float = 60.0) -> bool:
    """Whether a floor point projects into the image (with a margin): only those stickers need rendering."""
    p = transform_points(invert(T_world_camera), point[None])[0]
    if p[2] <= 0.1:
        return False
    u, v = camera.project(p[None])[0]
    return -margin_px < u < camera.width + margin_px and -margin_px < v < camera.height + margin_px


def make_session(path: Path, n_frames: int = 30, fps: float = 10.0, corrupt: tuple[int, ...] = ()) -> Path:
    """Render a session (with groundtruth.tum) into ``path``; frames in ``corrupt`` are written as garbage."""
    smap, rig = line_map(), default_rig()
    rc = rig[0]
    stickers = [(int(i), smap.T_world_sticker(int(i))) for i in smap.ids]
    stamps, poses = [], []
    with SessionWriter(path, smap, rig, SessionInfo(source="test synth", fps=fps)) as w:
        for k in range(n_frames):
            t = k / fps
            T_wb = planar_T(*walk_pose(t))
            T_wc = T_wb @ rc.T_body_camera
            near = [(i, T) for i, T in stickers if _in_view(rc.camera, T_wc, T[:3, 3])]
            img = synth_frame(near, rc.camera, T_wc, noise=2.0, seed=k).image
            w.write(k, t, img)
            stamps.append(t)
            poses.append(T_wb)
    for k in corrupt:
        (path / "frames" / f"{k:06d}.jpg").write_bytes(b"not a jpeg")
    write_tum(path / "groundtruth.tum", np.array(stamps), poses)
    return path


def cached_session(cache_dir: Path, n_frames: int, fps: float) -> Path:
    """A session made by :func:`make_session`, rendered once and reused (keyed by the rendering code).

    ``cache_dir`` is pytest's cache (``request.config.cache.mkdir``); copy the session before
    changing it.
    """
    here = Path(__file__).resolve().parent
    key = hashlib.sha1((here / "synth.py").read_bytes() + Path(__file__).read_bytes()
                       + f"{n_frames},{fps}".encode()).hexdigest()[:16]
    final = Path(cache_dir) / key
    if not (final / "groundtruth.tum").exists():
        tmp = Path(tempfile.mkdtemp(dir=cache_dir))
        make_session(tmp / "s", n_frames, fps)
        try:
            os.replace(tmp / "s", final)
        except OSError:  # another process made it first
            shutil.rmtree(tmp / "s")
        tmp.rmdir()
    return final


def write_video(session: Path, path: Path, fps: float = 10.0) -> Path:
    """The session's frames as an MJPG .avi (what a vest camera recording looks like)."""
    images = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in sorted((session / "frames").glob("*.jpg"))]
    images = [im for im in images if im is not None]
    first = images[0]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (first.shape[1], first.shape[0]))
    assert vw.isOpened()
    for im in images:
        vw.write(cv2.cvtColor(im, cv2.COLOR_GRAY2BGR))
    vw.release()
    return path

