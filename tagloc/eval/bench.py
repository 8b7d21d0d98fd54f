"""``tagloc bench``: what each per-frame stage costs and how well it works, on simulated frames.

Every view is rendered once by the physical simulator (:func:`tagloc.sim.simulate.render_view`, default
Pi v1 camera at 1296x972, fixed seeds) and every measurement runs on that same image, single-threaded
(OpenCV and BLAS on one thread each, :func:`tagloc.pipeline.run.single_threaded`). The scene is one
hand-made floor (:class:`tagloc.sim.floor.Floor`, textured, with painted lines, stains and dark
distractor squares) holding, 16 m apart so that no view sees two:

* single stickers (mapped), looked at from a chosen 3-D distance: the camera's height is drawn in
  the vest range (1.1-1.5 m, lower when the distance demands it), the sticker is put at a random
  place in the middle of the image and the pitch follows, at a random heading;
* clusters of 3 stickers laid out inside the view of the default rig (1.3 m, 55 deg); in every other
  cluster one of the three is a distractor sticker that is not in the map (decoded, never a fix);
* empty floor (0 stickers).

Map IDs are consecutive, so a sticker's spatial neighbours share leading digits with it (the hard
case for identification); the identification candidates are the true ID and the K-1 nearest IDs of
the map (:func:`tagloc.eval.bench_identify.candidate_ids`), and, to count wrong IDs where the true sticker
is absent, K map IDs near it without it.

Tables (see :func:`format_tables`):

1. Stage times (median / p95, ms of the thread's CPU time) on frames with 0, 1 and 3 stickers (vest pose, walking at
   ``walk_speed_mps`` under ``lux``), end to end = :meth:`tagloc.pipeline.localiser.Localiser.process` with a
   tracker primed at the true pose; OpenCV's ArUco detector on the 1-sticker frames with the
   sticker replaced by a DICT_4X4_50 marker of the same size.
2. Read and identification rates (ID and rotation right) and wrong IDs vs blur length (physical
   motion during the exposure) and vs illuminance (natural exposure, walking speed), 1.3-2.0 m.
3. Corner error (px) and camera position error (cm, pose from the true ID/rotation) vs blur and
   distance.
4. The paper's detector against ours on the blur-sweep frames.

Rates count only stickers fully inside the image; a sticker the detector misses counts as not read
and not identified.
"""

from __future__ import annotations

import math
import os
import platform
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import cv2
import numpy as np

from tagloc.core.camera import Camera, default_camera
from tagloc.core.errors import InputError
from tagloc.core.geometry import planar_T
from tagloc.core.jsonfile import write_json
from tagloc.core.rig import Rig, default_rig, looking_forward
from tagloc.core.stickermap import StickerMap
from tagloc.core.types import IdSource, PoseFix
from tagloc.eval.bench_detect import match_detections
from tagloc.eval.bench_identify import candidate_ids
from tagloc.pipeline.localiser import LocaliserConfig
from tagloc.pipeline.run import single_threaded
from tagloc.sim.floor import Floor, FloorConfig
from tagloc.sim.simulate import render_view, true_corners
from tagloc.vision.decode import BACKENDS, decode
from tagloc.vision.detect import detect
from tagloc.vision.identify import METHODS, identify
from tagloc.vision.pose import solve_pose
from tagloc.vision.refs import ReferenceBank, build_refs

DECODERS = BACKENDS
IDENTIFIERS = METHODS
DEFAULT_DECODER = LocaliserConfig().decoder  # what the localiser runs
DEFAULT_IDENTIFIER = LocaliserConfig().identify
_STATION_SPACING_M = 16.0  # far enough apart that no view sees two stations


@dataclass
class BenchConfig:
    """What :func:`run_bench` measures.

    Attributes:
        frames: views per cell (per blur, lux, distance level and per timing group).
        seed: seed of the scene, the views and the sensor noise.
        blurs_px: blur lengths (image px at the image centre) of the blur sweep.
        lux_levels: illuminances of the lux sweep (natural exposure, walking speed).
        distances_m: camera-to-sticker distances of the distance sweep (no blur).
        near_m, far_m: distance range of the blur and lux sweeps.
        lux: illuminance of the blur, distance and timing views.
        walk_speed_mps: walking speed (lux sweep and timing views).
        candidates: identification candidates K (true one + K-1 others).
        single_stations, triple_stations: distinct single stickers / 3-sticker clusters in the scene.
        distractors_per_m2: dark distractor squares on the floor.
        jpeg_quality: round-trip every view through JPEG (None: raw frames, as a live camera gives).
        libdmtx: also measure the libdmtx and "both" decoders (slow when they fail).
        paper: also run the paper's detector.
        progress: tqdm progress bar.
    """

    frames: int = 40
    seed: int = 0
    blurs_px: tuple[float, ...] = (0.0, 1.0, 2.0, 4.0, 6.0, 8.0)
    lux_levels: tuple[float, ...] = (50.0, 100.0, 200.0, 300.0)
    distances_m: tuple[float, ...] = (1.0, 1.5, 2.0, 2.5)
    near_m: float = 1.3
    far_m: float = 2.0
    lux: float = 150.0
    walk_speed_mps: float = 1.3
    candidates: int = 5
    single_stations: int = 8
    triple_stations: int = 10
    distractors_per_m2: float = 0.2
    jpeg_quality: int | None = None
    libdmtx: bool = True
    paper: bool = True
    progress: bool = True

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise InputError(f"bench: --frames must be >= 1, got {self.frames}")
        if not 0 < self.near_m <= self.far_m:
            raise InputError(f"bench: distance range {self.near_m}-{self.far_m} m is empty")
        if any(d <= 0.3 for d in self.distances_m):
            raise InputError("bench: distances must exceed 0.3 m")
        if any(b < 0 for b in self.blurs_px) or any(lx <= 0 for lx in self.lux_levels) or self.lux <= 0:
            raise InputError("bench: blur lengths must be >= 0 and illuminances > 0")
        if not 2 <= self.candidates <= 8:
            raise InputError(f"bench: candidates {self.candidates} must be 2-8")
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            raise InputError(f"bench: JPEG quality {self.jpeg_quality} is not in 1-100")

    @classmethod
    def quick(cls, seed: int = 0, **kw) -> BenchConfig:
        """A tiny configuration for tests: 3 views per cell, two blur levels, one lux and distance level."""
        base = dict(
            frames=3,
            seed=seed,
            blurs_px=(0.0, 4.0),
            lux_levels=(100.0,),
            distances_m=(1.5,),
            single_stations=3,
            triple_stations=2,
            progress=False,
        )
        base.update(kw)
        return cls(**base)


# -- scene ------------------------------------------------------------------------------------------


@dataclass
class _Scene:
    floor: Floor  # every sticker physically on the floor (map + distractors)
    smap: StickerMap  # the localiser's map (no distractors)
    singles: list[int]  # IDs of the single stations
    triples: list[tuple[tuple[float, float, float], list[int]]]  # body pose (x, y, yaw) and its 3 IDs
    empties: list[tuple[float, float]]  # floor points far from any sticker
    bank: ReferenceBank
    rig: Rig


def _floor_point(camera: Camera, T_world_camera: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Where the rays of distorted pixels (N, 2) meet the floor: (N, 2) world xy."""
    n = camera.undistort_pixels(px)
    rays = np.c_[(n - camera.K[:2, 2]) / [camera.fx, camera.fy], np.ones(len(n))]
    w = rays @ T_world_camera[:3, :3].T
    c = T_world_camera[:3, 3]
    s = -c[2] / w[:, 2]
    return c[:2] + s[:, None] * w[:, :2]


def _build_scene(cfg: BenchConfig, rig: Rig) -> _Scene:
    rng = np.random.default_rng([cfg.seed, 1])
    cam = rig.cameras[0].camera
    first = int(rng.integers(10000, 90000))
    next_id = iter(range(first, first + 1000))
    ids, xy, yaw, mapped = [], [], [], []

    def add(sid: int, p: np.ndarray, in_map: bool) -> None:
        ids.append(sid)
        xy.append(np.asarray(p, float))
        yaw.append(rng.uniform(-math.pi, math.pi))
        mapped.append(in_map)

    singles = []
    for k in range(cfg.single_stations):
        sid = next(next_id)
        add(sid, (k * _STATION_SPACING_M, 0.0), True)
        singles.append(sid)
    triples = []
    T_bc = rig.cameras[0].T_body_camera
    for k in range(cfg.triple_stations):
        body = (k * _STATION_SPACING_M, 2 * _STATION_SPACING_M, float(rng.uniform(-math.pi, math.pi)))
        T_wc = planar_T(*body) @ T_bc
        # Three points spread over the view, well inside it so small pose changes keep them there.
        for _ in range(1000):
            px = np.c_[rng.uniform(0.22, 0.78, 3) * cam.width, rng.uniform(0.3, 0.78, 3) * cam.height]
            pts = _floor_point(cam, T_wc, px)
            d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
            if d[np.triu_indices(3, 1)].min() > 0.6:
                break
        group = []
        for j, p in enumerate(pts):
            in_map = not (j == 2 and k % 2 == 1)
            sid = next(next_id) if in_map else first + 1000 + k  # distractors: IDs beyond the map's
            add(sid, p, in_map)
            group.append(sid)
        triples.append((body, group))
    empties = [
        (k * _STATION_SPACING_M + _STATION_SPACING_M / 2, _STATION_SPACING_M) for k in range(cfg.single_stations)
    ]

    ids_a, xy_a, yaw_a, m = np.array(ids, np.int64), np.array(xy), np.array(yaw), np.array(mapped)
    on_floor = StickerMap(ids_a, xy_a, yaw_a, "bench floor")
    smap = StickerMap(ids_a[m], xy_a[m], yaw_a[m], "bench map")
    floor = Floor(on_floor, FloorConfig(cache_tiles=1024, distractors_per_m2=cfg.distractors_per_m2), seed=cfg.seed)
    bank = build_refs(smap, progress=False)
    return _Scene(floor, smap, singles, triples, empties, bank, rig)


def view_at_distance(rng: np.random.Generator, camera: Camera, target_xy: np.ndarray, distance_m: float) -> np.ndarray:
    """``T_world_camera`` seeing the floor point ``target_xy`` at ``distance_m``, at a random place in
    the middle of the image, from a vest-like height, at a random heading."""
    for _ in range(1000):
        h = min(rng.uniform(1.1, 1.5), 0.92 * distance_m)
        px = np.array([[rng.uniform(0.25, 0.75) * camera.width, rng.uniform(0.3, 0.7) * camera.height]])
        n = camera.undistort_pixels(px)[0]
        xn, yn = (n - camera.K[:2, 2]) / [camera.fx, camera.fy]
        norm_c = math.sqrt(xn * xn + yn * yn + 1.0)
        # Ray's drop below horizontal at pitch p: (yn cos p + sin p) / |c| = h / d; solve for p.
        s = h / distance_m * norm_c / math.sqrt(1.0 + yn * yn)
        if s >= 1.0:
            continue
        pitch = math.degrees(math.asin(s) - math.atan(yn))
        if not 30.0 <= pitch <= 85.0:
            continue
        heading = rng.uniform(-180.0, 180.0)
        T = looking_forward(h, pitch, heading)  # camera at (0, 0, h)
        ray = T[:3, :3] @ np.array([xn, yn, 1.0])
        hit = T[:3, 3] + ray * (h / -ray[2])
        T[:2, 3] += np.asarray(target_xy, float) - hit[:2]
        return T
    raise InputError(f"bench: no camera pose sees a sticker at {distance_m} m")


# -- accumulation -----------------------------------------------------------------------------------


def _stats(values: list[float], digits: int = 3) -> dict:
    """median and p95 (None when empty)."""
    if not values:
        return {"median": None, "p95": None, "n": 0}
    a = np.asarray(values, float)
    return {
        "median": round(float(np.median(a)), digits),
        "p95": round(float(np.percentile(a, 95)), digits),
        "n": int(len(a)),
    }


@dataclass
class _Cell:
    """Counts and samples of one sweep cell."""

    stickers: int = 0
    detected: int = 0
    decode_right: dict = field(default_factory=lambda: dict.fromkeys(DECODERS, 0))
    decode_wrong: dict = field(default_factory=lambda: dict.fromkeys(DECODERS, 0))
    id_right: dict = field(default_factory=lambda: dict.fromkeys(IDENTIFIERS, 0))
    id_wrong: dict = field(default_factory=lambda: dict.fromkeys(IDENTIFIERS, 0))
    id_absent_wrong: dict = field(default_factory=lambda: dict.fromkeys(IDENTIFIERS, 0))
    outer_err: list = field(default_factory=list)
    inner_err: list = field(default_factory=list)
    pos_err_cm: list = field(default_factory=list)
    pose_failed: int = 0
    blur_px: list = field(default_factory=list)
    exposure_ms: list = field(default_factory=list)
    paper_detected: int = 0
    paper_err: list = field(default_factory=list)
    ours_ms: list = field(default_factory=list)
    paper_ms: list = field(default_factory=list)

    def summary(self, decoders: tuple[str, ...], identifiers: tuple[str, ...], reads: bool, paper: bool) -> dict:
        n = self.stickers

        def rate(k: int) -> float | None:
            return round(k / n, 4) if n else None

        out = {
            "stickers": n,
            "detected": self.detected,
            "detection_rate": rate(self.detected),
            "blur_px_median": _stats(self.blur_px, 2)["median"],
            "exposure_ms_median": _stats(self.exposure_ms, 3)["median"],
            "outer_err_px": _stats(self.outer_err),
            "inner_err_px": _stats(self.inner_err),
            "position_err_cm": _stats(self.pos_err_cm),
            "pose_failed": self.pose_failed,
        }
        if reads:
            out["decode"] = {
                d: {"right": self.decode_right[d], "wrong": self.decode_wrong[d], "rate": rate(self.decode_right[d])}
                for d in decoders
            }
            out["identify"] = {
                m: {
                    "right": self.id_right[m],
                    "wrong": self.id_wrong[m],
                    "absent_wrong": self.id_absent_wrong[m],
                    "rate": rate(self.id_right[m]),
                }
                for m in identifiers
            }
        if paper:
            out["detectors"] = {
                "contour": {
                    "rate": rate(self.detected),
                    "outer_err_px": _stats(self.outer_err)["median"],
                    "time_ms": _stats(self.ours_ms, 2),
                },
                "paper": {
                    "rate": rate(self.paper_detected),
                    "outer_err_px": _stats(self.paper_err)["median"],
                    "time_ms": _stats(self.paper_ms, 2),
                },
            }
        return out


def _fully_visible(corners: np.ndarray | None, camera: Camera, border: float = 1.0) -> bool:
    return corners is not None and bool(
        np.all((corners >= border) & (corners <= (camera.width - 1 - border, camera.height - 1 - border)))
    )


def _timed(fn: Callable, *args, **kw) -> tuple[Any, float]:
    """``fn(*args, **kw)`` and the CPU time of this thread it took, ms: what the stage costs, with
    OpenCV on one thread, however many other processes share the machine (their time would count
    in wall time)."""
    t0 = time.thread_time()
    out = fn(*args, **kw)
    return out, (time.thread_time() - t0) * 1e3


class _Runner:
    """Runs every measurement of one view on its single rendering."""

    def __init__(self, cfg: BenchConfig, scene: _Scene):
        self.cfg, self.scene = cfg, scene
        self.rig_cam = scene.rig.cameras[0]
        self.cam = self.rig_cam.camera
        self.pool = np.asarray(scene.smap.ids, np.int64)
        self.decoders = DECODERS if cfg.libdmtx else (DEFAULT_DECODER,)

    def render(
        self,
        T_wc: np.ndarray,
        seed: int,
        lux: float,
        velocity: np.ndarray | None = None,
        blur_px: float | None = None,
        blur_dir: float = 0.0,
    ):
        return render_view(
            self.scene.floor,
            self.cam,
            T_wc,
            lux,
            velocity=velocity,
            blur_px=blur_px,
            blur_direction_deg=blur_dir,
            seed=seed,
            jpeg_quality=self.cfg.jpeg_quality,
        )

    def single_pose(self, rng: np.random.Generator, d: float) -> tuple[int, np.ndarray]:
        """A random single sticker and a camera pose ``T_wc`` looking at it from ``d`` m."""
        sc = self.scene
        sid = int(rng.choice(sc.singles))
        return sid, view_at_distance(rng, self.cam, sc.floor.stickers.xy[sc.floor.stickers.row(sid)], d)

    def measure(
        self,
        cell: _Cell,
        gray: np.ndarray,
        T_wc: np.ndarray,
        sticker_id: int,
        rng: np.random.Generator,
        reads: bool,
        paper: bool,
    ) -> None:
        """Detection, corner and pose error, and (``reads``) decoding and identification of one sticker."""
        tc = true_corners(self.scene.floor, self.cam, T_wc, sticker_id)
        if not _fully_visible(tc, self.cam):
            return
        cell.stickers += 1
        dets, ms = _timed(detect, gray, self.cam, method="contour")
        cell.ours_ms.append(ms)
        if paper:
            pdets, pms = _timed(detect, gray, self.cam, method="paper")
            cell.paper_ms.append(pms)
            pm = match_detections(pdets, [tc[:4]])
            if pm:
                cell.paper_detected += 1
                cell.paper_err.extend(pm[0].outer_err.tolist())
        m = match_detections(dets, [tc[:4]], [tc[4:]])
        if not m:
            return
        cell.detected += 1
        det, rot = dets[m[0].detection], m[0].rotation
        cell.outer_err.extend(m[0].outer_err.tolist())
        if m[0].inner_err is not None:
            cell.inner_err.extend(m[0].inner_err.tolist())
        sol = solve_pose(det, rot, self.scene.floor.stickers.T_world_sticker(sticker_id), self.rig_cam)
        if sol.poses:
            cell.pos_err_cm.append(100.0 * float(np.linalg.norm(sol.poses[0].T_world_camera[:3, 3] - T_wc[:3, 3])))
        else:
            cell.pose_failed += 1
        if not reads:
            return
        for backend in self.decoders:
            r = decode(gray, det, self.cam, backend=backend)
            if r.sticker_id is not None:
                ok = r.sticker_id == sticker_id and r.rotation == rot
                cell.decode_right[backend] += ok
                cell.decode_wrong[backend] += not ok
        k = self.cfg.candidates
        present = candidate_ids(self.pool, sticker_id, k, False, rng)
        absent = candidate_ids(self.pool, sticker_id, k, True, rng)
        for method in IDENTIFIERS:
            r = identify(gray, det, self.cam, present, self.scene.bank, method=method)
            if r.sticker_id is not None:
                ok = r.sticker_id == sticker_id and r.rotation == rot
                cell.id_right[method] += ok
                cell.id_wrong[method] += not ok
            r = identify(gray, det, self.cam, absent, self.scene.bank, method=method)
            cell.id_absent_wrong[method] += r.sticker_id is not None


# -- timing -----------------------------------------------------------------------------------------


def aruco_frame(gray: np.ndarray, corners: np.ndarray, rng: np.random.Generator, marker_px: int = 40) -> np.ndarray:
    """``gray`` with a DICT_4X4_50 marker (black square = the sticker's outer square, one white
    module of margin) pasted over the sticker whose outer corners (4, 2) are given."""
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    cells = 6  # 4x4 bits + 1-bit black border on each side
    marker = cv2.aruco.generateImageMarker(d, 7, cells * marker_px, borderBits=1)
    pad = marker_px
    img = cv2.copyMakeBorder(marker, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255).astype(np.float32)
    src = (
        np.array(
            [
                [pad, pad],
                [pad + cells * marker_px, pad],
                [pad + cells * marker_px, pad + cells * marker_px],
                [pad, pad + cells * marker_px],
            ],
            np.float32,
        )
        - 0.5
    )
    H = cv2.getPerspectiveTransform(src, corners.astype(np.float32))
    h, w = gray.shape
    # Paper and ink levels of the sticker it replaces, so the marker has the same contrast.
    mask_q = np.zeros_like(gray)
    cv2.fillConvexPoly(mask_q, np.round(corners).astype(np.int32), 255)
    vals = gray[mask_q > 0]
    ink, paper = np.percentile(vals, 5), np.percentile(vals, 95)
    warped = cv2.warpPerspective(img, H, (w, h), flags=cv2.INTER_AREA, borderValue=0.0)
    cover = cv2.warpPerspective(np.ones_like(img), H, (w, h), flags=cv2.INTER_LINEAR, borderValue=0.0)
    patch = cv2.GaussianBlur(ink + (paper - ink) * warped / 255.0, (0, 0), 0.6)
    patch += rng.normal(0.0, 2.0, patch.shape).astype(np.float32)
    out = gray.astype(np.float32) * (1.0 - cover) + patch * cover
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def _stage_times(
    runner: _Runner, gray: np.ndarray, T_wc: np.ndarray, ids: list[int], rng: np.random.Generator
) -> dict[str, float]:
    """Per-frame time of each stage called alone on this frame (ms; decode/identify/pose summed over
    the detections matched to the frame's stickers)."""
    sc, cam = runner.scene, runner.cam
    dets, t_det = _timed(detect, gray, cam)
    times = {"detect": t_det, "decode": 0.0, "identify": 0.0, "pose": 0.0}
    truth = [true_corners(sc.floor, cam, T_wc, i) for i in ids]
    m = match_detections(dets, [t[:4] for t in truth]) if ids else []
    for mt in m:
        det, sid, rot = dets[mt.detection], ids[mt.truth], mt.rotation
        times["decode"] += _timed(decode, gray, det, cam, backend=DEFAULT_DECODER)[1]
        if sid in sc.smap:
            cands = candidate_ids(runner.pool, sid, runner.cfg.candidates, False, rng)
            times["identify"] += _timed(identify, gray, det, cam, cands, sc.bank, method=DEFAULT_IDENTIFIER)[1]
            times["pose"] += _timed(solve_pose, det, rot, sc.smap.T_world_sticker(sid), runner.rig_cam)[1]
    times["matched"] = len(m)
    return times


def _end_to_end(runner: _Runner, gray: np.ndarray, body: tuple[float, float, float], T_wc: np.ndarray) -> float:
    """CPU time (ms, this thread) of :meth:`Localiser.process` on this frame, in steady state.

    One localiser serves every frame, as on the vest (its one-off set-up, such as the odometry's
    remap tables, is not a per-frame cost). Before each timed frame the tracker is started afresh at
    the true pose and the odometry is handed the same image two and one frame periods earlier, so
    the timed call runs the odometry match as it does while walking (from the turn under way).
    """
    from tagloc.core.types import Frame
    from tagloc.pipeline.localiser import Localiser
    from tracker.tracker import Tracker

    loc = getattr(runner, "_localiser", None)
    if loc is None:
        loc = runner._localiser = Localiser(runner.scene.smap, runner.scene.rig, refs=runner.scene.bank)
        runner._clock = 0.0
    # Each timed frame a second after the last: the localiser refuses a frame not after the previous
    # one (and restarts on a reset clock), and no sticker is carried over from another view.
    runner._clock += 1.0
    t = runner._clock
    loc.tracker = Tracker(loc.config.tracker)
    prime = PoseFix(T_wc, np.asarray(body, float), np.diag([1e-4, 1e-4, 1e-4]), 0.0)
    loc.tracker.update([prime], int(runner.scene.smap.ids[0]), IdSource.DECODED, t - 1.0 / 30.0)
    odo = loc.floor_odometry(0)
    if odo is not None:
        odo.reset()
        odo.measure(gray, t - 2.0 / 30.0)
        odo.measure(gray, t - 1.0 / 30.0)
    result, ms = _timed(loc.process, Frame(0, t, gray))
    if result.skipped:
        raise RuntimeError(f"bench: the localiser refused the timed frame ({result.skipped})")
    return ms


# -- the bench --------------------------------------------------------------------------------------


def _environment() -> dict:
    return {
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "opencv": cv2.__version__,
        "numpy": np.__version__,
        "machine": platform.machine(),
    }


def run_bench(config: BenchConfig | None = None) -> dict:
    """Render the bench's views, measure every stage on them and return plain data (JSON-ready).

    Keys: ``config``, ``environment`` (load average at start and end), ``timing`` (per frame group:
    stage times and end to end, ms; ``aruco``; ``ratio``), ``blur``, ``lux``, ``distance``
    (lists of cells, see :class:`_Cell`), ``detectors`` (paper vs ours per blur), ``targets``
    (name, value, goal, pass), ``wall_s``.
    """
    from tqdm import tqdm

    cfg = config or BenchConfig()
    t_start = time.perf_counter()
    env_start = _environment()
    # One thread each for OpenCV and BLAS, as the localiser runs its frames: BLAS's default threads
    # spin while they wait, and on a busy machine that spinning was counted in the stages' CPU time.
    with single_threaded():
        rig = default_rig(camera=default_camera())
        scene = _build_scene(cfg, rig)
        runner = _Runner(cfg, scene)
        n = cfg.frames
        total = n * (len(cfg.blurs_px) + len(cfg.lux_levels) + len(cfg.distances_m) + 3) + 1
        bar = tqdm(total=total, desc="bench", unit="view", disable=not cfg.progress)

        # Warm-up view (imports, lazily built caches, first-call costs); not counted.
        rng = np.random.default_rng([cfg.seed, 99])
        sid, T = runner.single_pose(rng, 1.5)
        runner.measure(_Cell(), runner.render(T, cfg.seed, cfg.lux, blur_px=6.0).image, T, sid, rng, True, cfg.paper)
        bar.update(1)

        blur_cells = _blur_sweep(cfg, runner, bar)
        lux_cells = _lux_sweep(cfg, runner, bar)
        dist_cells = _distance_sweep(cfg, runner, bar)
        timing = _timing(cfg, runner, bar)
        bar.close()
    result = {
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()},
        "environment": {"start": env_start, "end_load_average": _environment()["load_average"]},
        "timing": timing,
        "blur": blur_cells,
        "lux": lux_cells,
        "distance": dist_cells,
        "detectors": [{"blur_px": c["blur_px"], **c["detectors"]} for c in blur_cells if "detectors" in c],
        "wall_s": round(time.perf_counter() - t_start, 1),
    }
    result["targets"] = _targets(result)
    return result


def _blur_sweep(cfg: BenchConfig, runner: _Runner, bar: Any) -> list[dict]:
    """One cell per blur length: views 1.3-2.0 m away, blurred along a random direction."""
    cells = []
    for b in cfg.blurs_px:
        cell, rng = _Cell(), np.random.default_rng([cfg.seed, 2, int(round(b * 10))])
        for _i in range(cfg.frames):
            sid, T = runner.single_pose(rng, rng.uniform(cfg.near_m, cfg.far_m))
            res = runner.render(T, int(rng.integers(2**31)), cfg.lux, blur_px=b, blur_dir=rng.uniform(0, 180))
            cell.blur_px.append(res.blur_px)
            cell.exposure_ms.append(res.exposure_s * 1e3)
            runner.measure(cell, res.image, T, sid, rng, True, cfg.paper)
            bar.update(1)
        cells.append({"blur_px": b, **cell.summary(runner.decoders, IDENTIFIERS, True, cfg.paper)})
    return cells


def _lux_sweep(cfg: BenchConfig, runner: _Runner, bar: Any) -> list[dict]:
    """One cell per illuminance: natural exposure, walking towards the view at ``walk_speed_mps``."""
    cells = []
    for lx in cfg.lux_levels:
        cell, rng = _Cell(), np.random.default_rng([cfg.seed, 3, int(round(lx))])
        for _i in range(cfg.frames):
            sid, T = runner.single_pose(rng, rng.uniform(cfg.near_m, cfg.far_m))
            heading = T[:3, 2].copy()
            heading[2] = 0.0
            v = cfg.walk_speed_mps * heading / np.linalg.norm(heading)
            res = runner.render(T, int(rng.integers(2**31)), lx, velocity=v)
            cell.blur_px.append(res.blur_px)
            cell.exposure_ms.append(res.exposure_s * 1e3)
            runner.measure(cell, res.image, T, sid, rng, True, False)
            bar.update(1)
        cells.append({"lux": lx, **cell.summary(runner.decoders, IDENTIFIERS, True, False)})
    return cells


def _distance_sweep(cfg: BenchConfig, runner: _Runner, bar: Any) -> list[dict]:
    """One cell per distance: sharp views (no motion) at ``lux``."""
    cells = []
    for d in cfg.distances_m:
        cell, rng = _Cell(), np.random.default_rng([cfg.seed, 4, int(round(d * 100))])
        for _i in range(cfg.frames):
            sid, T = runner.single_pose(rng, d)
            res = runner.render(T, int(rng.integers(2**31)), cfg.lux)
            runner.measure(cell, res.image, T, sid, rng, False, False)
            bar.update(1)
        cells.append({"distance_m": d, **cell.summary(runner.decoders, IDENTIFIERS, False, False)})
    return cells


def _timing(cfg: BenchConfig, runner: _Runner, bar: Any) -> dict:
    """Stage and end-to-end times on 0-, 1- and 3-sticker frames, and ArUco on the 1-sticker frames."""
    sc, cam = runner.scene, runner.cam
    T_bc = runner.rig_cam.T_body_camera
    groups: dict[str, dict[str, list]] = {}
    aruco_ms, aruco_found = [], 0
    aruco = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), cv2.aruco.DetectorParameters()
    )

    def walk(body: tuple[float, float, float]) -> np.ndarray:
        return cfg.walk_speed_mps * np.array([math.cos(body[2]), math.sin(body[2]), 0.0])

    for name in ("0 stickers", "1 sticker", "3 stickers"):
        rng = np.random.default_rng([cfg.seed, 5, len(groups)])
        acc = groups.setdefault(name, {k: [] for k in ("detect", "decode", "identify", "pose", "end_to_end")})
        acc["stickers_seen"] = []
        for i in range(cfg.frames):
            ids: list[int] = []
            if name == "0 stickers":
                x, y = sc.empties[i % len(sc.empties)]
                body = (x + rng.uniform(-2, 2), y + rng.uniform(-2, 2), rng.uniform(-math.pi, math.pi))
            elif name == "1 sticker":
                sid = int(sc.singles[i % len(sc.singles)])
                # A vest pose that puts the sticker somewhere in the lower two thirds of the view.
                for _ in range(1000):
                    a = rng.uniform(-math.pi, math.pi)
                    fwd, side = rng.uniform(0.6, 1.7), rng.uniform(-0.5, 0.5)
                    sxy = sc.floor.stickers.xy[sc.floor.stickers.row(sid)]
                    body = (
                        sxy[0] - fwd * math.cos(a) + side * math.sin(a),
                        sxy[1] - fwd * math.sin(a) - side * math.cos(a),
                        a,
                    )
                    if _fully_visible(true_corners(sc.floor, cam, planar_T(*body) @ T_bc, sid), cam, 5.0):
                        break
                ids = [sid]
            else:
                b0, ids = sc.triples[i % len(sc.triples)]
                body = (
                    b0[0] + rng.uniform(-0.05, 0.05),
                    b0[1] + rng.uniform(-0.05, 0.05),
                    b0[2] + math.radians(rng.uniform(-3, 3)),
                )
            T_wc = planar_T(*body) @ T_bc
            res = runner.render(T_wc, int(rng.integers(2**31)), cfg.lux, velocity=walk(body))
            gray = res.image
            visible = [s for s in ids if _fully_visible(true_corners(sc.floor, cam, T_wc, s), cam)]
            st = _stage_times(runner, gray, T_wc, visible, rng)
            for k in ("detect", "decode", "identify", "pose"):
                acc[k].append(st[k])
            acc["end_to_end"].append(_end_to_end(runner, gray, body, T_wc))
            acc["stickers_seen"].append(len(visible))
            if name == "1 sticker" and visible:
                af = aruco_frame(gray, true_corners(sc.floor, cam, T_wc, visible[0])[:4], rng)
                (corners, marker_ids, _), ms = _timed(aruco.detectMarkers, af)
                aruco_ms.append(ms)
                aruco_found += marker_ids is not None and 7 in np.ravel(marker_ids)
            bar.update(1)
    rows = []
    for name, acc in groups.items():
        seen = acc.pop("stickers_seen")
        rows.append(
            {
                "frames": name,
                "n": len(seen),
                "stickers_visible_mean": round(float(np.mean(seen)), 2),
                **{k: _stats(v, 2) for k, v in acc.items()},
            }
        )
    ar = {
        "time_ms": _stats(aruco_ms, 2),
        "detected": aruco_found,
        "frames": len(aruco_ms),
        "dictionary": "DICT_4X4_50",
        "parameters": "default",
    }
    one = next(r for r in rows if r["frames"] == "1 sticker")
    ratio = None
    if ar["time_ms"]["median"] and one["end_to_end"]["median"] is not None:
        ratio = round(one["end_to_end"]["median"] / ar["time_ms"]["median"], 3)
    ratio_detect = None
    if ar["time_ms"]["median"] and one["detect"]["median"] is not None:
        ratio_detect = round(one["detect"]["median"] / ar["time_ms"]["median"], 3)
    return {
        "rows": rows,
        "aruco": ar,
        "ratio_end_to_end_vs_aruco": ratio,
        "ratio_detect_vs_aruco": ratio_detect,
        "conditions": {
            "lux": cfg.lux,
            "walk_speed_mps": cfg.walk_speed_mps,
            "rig": "default (1.3 m, 55 deg)",
            "identify": f"{DEFAULT_IDENTIFIER}, {cfg.candidates} candidates",
            "decode": DEFAULT_DECODER,
        },
    }


# -- targets ----------------------------------------------------------------------------------------


def _pooled_rate(cells: list[dict], pick) -> float | None:
    right = sum(pick(c)["right"] for c in cells)
    n = sum(c["stickers"] for c in cells)
    return right / n if n else None


def _targets(r: dict) -> list[dict]:
    out = []

    def add(name: str, value, goal: str, ok) -> None:
        out.append({"target": name, "value": value, "goal": goal, "pass": None if ok is None else bool(ok)})

    rows = {row["frames"]: row for row in r["timing"]["rows"]}
    one, zero = rows.get("1 sticker"), rows.get("0 stickers")
    ratio = r["timing"]["ratio_end_to_end_vs_aruco"]
    add(
        "1-sticker frame vs ArUco (end to end / ArUco, median)",
        ratio,
        "<= 0.5",
        None if ratio is None else ratio <= 0.5,
    )
    e1 = one["end_to_end"]["median"] if one else None
    add("1-sticker frame end to end, median ms", e1, "< 15", None if e1 is None else e1 < 15)
    e0 = zero["end_to_end"]["median"] if zero else None
    add("0-sticker frame end to end, median ms", e0, "< 6", None if e0 is None else e0 < 6)

    sweep = r["blur"] + r["lux"]
    wrong = sum(c["decode"][d]["wrong"] for c in sweep for d in c["decode"]) + sum(
        c["identify"][m]["wrong"] + c["identify"][m]["absent_wrong"] for c in sweep for m in c["identify"]
    )
    add("wrong IDs, all decoders/identifiers, blur and lux sweeps (incl. true ID absent)", wrong, "0", wrong == 0)

    def cells(lo: float, hi: float) -> list[dict]:
        return [c for c in r["blur"] if lo <= c["blur_px"] <= hi and c["stickers"]]

    def rate_target(name: str, cs: list[dict], pick, goal: float) -> None:
        v = _pooled_rate(cs, pick) if cs else None
        add(name, None if v is None else round(v, 4), f">= {goal:g}", None if v is None else v >= goal)

    rate_target(
        "decode rate (default decoder), blur <= 2 px, pooled", cells(0, 2), lambda c: c["decode"][DEFAULT_DECODER], 0.99
    )
    rate_target("decode rate (default decoder), blur 4 px", cells(4, 4), lambda c: c["decode"][DEFAULT_DECODER], 0.70)
    rate_target(
        f"identification rate ({DEFAULT_IDENTIFIER}, 5 candidates), blur 4 px",
        cells(4, 4),
        lambda c: c["identify"][DEFAULT_IDENTIFIER],
        0.95,
    )
    rate_target(
        f"identification rate ({DEFAULT_IDENTIFIER}, 5 candidates), blur 8 px",
        cells(8, 8),
        lambda c: c["identify"][DEFAULT_IDENTIFIER],
        0.80,
    )
    idw = sum(c["identify"][m]["wrong"] + c["identify"][m]["absent_wrong"] for c in r["blur"] for m in c["identify"])
    add("identification wrong IDs, blur sweep", idw, "0", idw == 0)

    def corner(b: float, goal: float) -> None:
        c = next((c for c in r["blur"] if c["blur_px"] == b), None)
        v = c["outer_err_px"]["median"] if c else None
        add(f"outer corner error median px, blur {b:g} px", v, f"<= {goal:g}", None if v is None else v <= goal)

    corner(0.0, 0.2)
    corner(6.0, 0.5)
    c = next((c for c in r["distance"] if c["distance_m"] == 1.5), None)
    v = c["position_err_cm"]["median"] if c else None
    add("camera position error median cm, 1.5 m, no blur", v, "< 1", None if v is None else v < 1.0)
    return out


# -- tables -----------------------------------------------------------------------------------------


def _fmt(v, spec: str = ".2f") -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    return format(float(v), spec)


def _pct(right: int, n: int) -> str:
    return "-" if not n else f"{100.0 * right / n:.1f}"


def _table(title: str, headers: list[str], rows: list[list[str]]) -> str:
    """Aligned text table (first column left-aligned, the rest right-aligned)."""
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(headers)]

    def line(cells: list[str]) -> str:
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))

    sep = "  ".join("-" * w for w in widths)
    return "\n".join([title, line(headers), sep, *(line(r) for r in rows)])


def format_tables(result: dict) -> str:
    """The bench's result (from :func:`run_bench`) as aligned text tables with units."""
    env = result["environment"]
    cfg = result["config"]
    out = [
        f"tagloc bench: {cfg['frames']} views per cell, seed {cfg['seed']}, 1296x972 Pi v1 camera, "
        f"single-threaded OpenCV {env['start']['opencv']}; load average at start "
        f"{'/'.join(map(str, env['start']['load_average']))}, at end {'/'.join(map(str, env['end_load_average']))} "
        f"({env['start']['cpus']} CPUs, shared); wall {result['wall_s']} s"
    ]
    out += _timing_tables(result)
    out += _rate_tables(result)
    out += _geometry_tables(result)
    out += _detector_tables(result)
    out += _target_tables(result)
    return "\n".join(out)


def _timing_tables(result: dict) -> list[str]:
    """Table 1: stage times per frame group, and the ratios to ArUco."""
    out: list[str] = []
    tm = result["timing"]
    cond = tm["conditions"]
    rows = []
    for r in tm["rows"]:
        row = [f"{r['frames']} (n={r['n']})"]
        for k in ("detect", "decode", "identify", "pose", "end_to_end"):
            row.append(f"{_fmt(r[k]['median'])} / {_fmt(r[k]['p95'])}")
        rows.append(row)
    ar = tm["aruco"]
    rows.append(
        [
            f"ArUco {ar['dictionary']} (n={ar['frames']}, found {ar['detected']})",
            f"{_fmt(ar['time_ms']['median'])} / {_fmt(ar['time_ms']['p95'])}",
            "",
            "",
            "",
            "",
        ]
    )
    out.append("")
    out.append(
        _table(
            f"1. Stage CPU time per frame (this thread), ms, median / p95 ({cond['lux']:g} lux, walking "
            f"{cond['walk_speed_mps']:g} m/s, {cond['rig']}; decode {cond['decode']}, identify "
            f"{cond['identify']} (run on every sticker), pose per sticker; end to end = "
            "Localiser.process, tracker primed)",
            ["frames", "detect ms", "decode ms", "identify ms", "pose ms", "end to end ms"],
            rows,
        )
    )
    out.append(
        f"ratio 1-sticker end to end / ArUco: {_fmt(tm['ratio_end_to_end_vs_aruco'], '.3f')}; "
        f"detect only / ArUco: {_fmt(tm['ratio_detect_vs_aruco'], '.3f')}"
    )
    return out


def _reads_table(title: str, cells: list[dict], key: str, unit: str) -> str:
    """Rates of one sweep (``cells`` keyed by ``key``) as a table."""
    decs = list(cells[0]["decode"]) if cells else []
    ids = list(cells[0]["identify"]) if cells else []
    headers = [unit, "frame blur px (median)", "exposure ms", "stickers", "detected %"]
    headers += [f"read {d}{' (default)' if d == DEFAULT_DECODER else ''} %" for d in decs]
    headers += [f"id {m}{' (default)' if m == DEFAULT_IDENTIFIER else ''} %" for m in ids]
    headers += ["wrong IDs read/id/absent"]
    rows = []
    for c in cells:
        n = c["stickers"]
        row = [
            _fmt(c[key], "g"),
            _fmt(c["blur_px_median"]),
            _fmt(c["exposure_ms_median"]),
            str(n),
            _pct(c["detected"], n),
        ]
        row += [_pct(c["decode"][d]["right"], n) for d in decs]
        row += [_pct(c["identify"][m]["right"], n) for m in ids]
        wr = sum(c["decode"][d]["wrong"] for d in decs)
        wi = sum(c["identify"][m]["wrong"] for m in ids)
        wa = sum(c["identify"][m]["absent_wrong"] for m in ids)
        row.append(f"{wr}/{wi}/{wa}")
        rows.append(row)
    return _table(title, headers, rows)


def _rate_tables(result: dict) -> list[str]:
    """Tables 2a and 2b: read and identification rates vs blur and vs illuminance."""
    cfg = result["config"]
    out: list[str] = []
    out.append("")
    out.append(
        _reads_table(
            f"2a. Read and identification rate vs blur ({cfg['near_m']:g}-{cfg['far_m']:g} m, "
            f"{cfg['lux']:g} lux; % of fully visible stickers, ID and rotation right; "
            f"{cfg['candidates']} candidates; absent = true ID not among them)",
            result["blur"],
            "blur_px",
            "blur px",
        )
    )
    out.append("")
    out.append(
        _reads_table(
            f"2b. Read and identification rate vs illuminance (natural exposure, walking "
            f"{cfg['walk_speed_mps']:g} m/s, {cfg['near_m']:g}-{cfg['far_m']:g} m)",
            result["lux"],
            "lux",
            "lux",
        )
    )
    return out


def _geo_table(title: str, cells: list[dict], key: str, unit: str) -> str:
    """Corner and position errors of one sweep (``cells`` keyed by ``key``) as a table."""
    rows = []
    for c in cells:
        rows.append(
            [
                _fmt(c[key], "g"),
                str(c["stickers"]),
                _pct(c["detected"], c["stickers"]),
                _fmt(c["outer_err_px"]["median"], ".3f"),
                _fmt(c["outer_err_px"]["p95"], ".3f"),
                _fmt(c["inner_err_px"]["median"], ".3f"),
                _fmt(c["position_err_cm"]["median"], ".2f"),
                _fmt(c["position_err_cm"]["p95"], ".2f"),
            ]
        )
    return _table(
        title,
        [
            unit,
            "stickers",
            "detected %",
            "outer err px (median)",
            "outer err px (p95)",
            "inner err px (median)",
            "position err cm (median)",
            "position err cm (p95)",
        ],
        rows,
    )


def _geometry_tables(result: dict) -> list[str]:
    """Tables 3a and 3b: corner and camera position errors vs blur and vs distance."""
    cfg = result["config"]
    out: list[str] = []
    out.append("")
    out.append(
        _geo_table(
            "3a. Corner and camera position error vs blur (pose from true ID/rotation)",
            result["blur"],
            "blur_px",
            "blur px",
        )
    )
    out.append("")
    out.append(
        _geo_table(
            f"3b. Corner and camera position error vs distance (no blur, {cfg['lux']:g} lux)",
            result["distance"],
            "distance_m",
            "distance m",
        )
    )
    return out


def _detector_tables(result: dict) -> list[str]:
    """Table 4: the paper's detector against ours (empty without it)."""
    out: list[str] = []
    if result["detectors"]:
        rows = []
        for d in result["detectors"]:
            o, p = d["contour"], d["paper"]
            rows.append(
                [
                    _fmt(d["blur_px"], "g"),
                    _fmt(None if o["rate"] is None else 100 * o["rate"], ".1f"),
                    _fmt(None if p["rate"] is None else 100 * p["rate"], ".1f"),
                    _fmt(o["outer_err_px"], ".3f"),
                    _fmt(p["outer_err_px"], ".3f"),
                    f"{_fmt(o['time_ms']['median'])} / {_fmt(o['time_ms']['p95'])}",
                    f"{_fmt(p['time_ms']['median'])} / {_fmt(p['time_ms']['p95'])}",
                ]
            )
        out.append("")
        out.append(
            _table(
                "4. Paper's detector vs ours on the blur-sweep frames",
                [
                    "blur px",
                    "ours detected %",
                    "paper detected %",
                    "ours err px (median)",
                    "paper err px (median)",
                    "ours ms med / p95",
                    "paper ms med / p95",
                ],
                rows,
            )
        )
    return out


def _target_tables(result: dict) -> list[str]:
    """The targets with PASS/MISS."""
    rows = [
        [
            t["target"],
            _fmt(t["value"], ".4g") if not isinstance(t["value"], int) else str(t["value"]),
            t["goal"],
            "-" if t["pass"] is None else ("PASS" if t["pass"] else "MISS"),
        ]
        for t in result["targets"]
    ]
    return ["", _table("Targets", ["target", "measured", "goal", "result"], rows)]


def bench_command(
    frames: int | None = None,
    seed: int = 0,
    json_path: str | os.PathLike | None = None,
    quick: bool = False,
    jpeg_quality: int | None = None,
    libdmtx: bool = True,
    paper: bool = True,
    progress: bool = True,
) -> int:
    """``tagloc bench``: run the bench, print the tables, optionally write the JSON; returns 0."""
    from pathlib import Path

    kw = dict(seed=seed, jpeg_quality=jpeg_quality, libdmtx=libdmtx, paper=paper, progress=progress)
    if frames is not None:
        kw["frames"] = frames
    cfg = BenchConfig.quick(**kw) if quick else BenchConfig(**kw)
    result = run_bench(cfg)
    print(format_tables(result))
    if json_path is not None:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)  # as every output: "out/" need not exist
        write_json(Path(json_path), result)  # standard JSON: a figure that is not a number as null
    return 0
