"""Simulated sessions: an operator walking over a sticker map, filmed by the vest camera.

:func:`simulate_session` writes the standard session layout (see :mod:`tagloc.io.session`) plus
``groundtruth_frames.jsonl``, one JSON object per frame::

    {"index": 12, "t": 0.4, "stamp": 0.4012, "T_world_body": 4x4, "T_world_camera": 4x4, "exposure_s": 0.003,
     "gain": 12.1, "blur_px": 3.4, "subframes": 4, "mean_signal_e": 95.2,
     "visible": [{"id": 4242, "in_map": true, "corners": [[u, v] x 4], "inner": [[u, v] x 4],
                  "inside": true, "distance_m": 1.52}, ...]}

``T_world_body`` is the ground-truth body pose (also in ``groundtruth.tum``): the rig's vest point
projected vertically onto the floor (z = 0) with the horizontal heading of the torso's +x axis, so it
moves with the torso's sway, twist and lean (see :mod:`tagloc.sim.walk`). ``T_world_camera`` is the
true camera pose at the frame's time, torso motion included. ``corners``/``inner`` are the sticker's outer and inner frame corners in
distorted pixels, canonical order (top-left first, clockwise on the sticker); ``inside`` says all
eight are in the image. Stickers in the map but left off the floor never appear; stickers on the
floor but not in the map appear with ``in_map: false``. Frame ``k`` is exposed around ``t = k / fps``
(with a rolling shutter: the middle row; corners are then projected at their own rows' times,
:func:`tagloc.sim.render.row_delay_s`). ``stamp`` is the timestamp written to ``frames.csv``: ``t``
plus the driver's jitter; dropped frames have no record, no image and no ``frames.csv`` line, and
``groundtruth.tum`` holds the delivered frames at their true times ``t`` (see
:mod:`tagloc.sim.timing`). The cameras of a rig run free: each has its own jitter, drops and bursts
(camera 0 those of a one-camera session), and ``frames.csv`` and the records follow the stamps.
With survey error (:mod:`tagloc.sim.survey`) the session's ``map.csv`` is the surveyed map and
``map_true.csv`` the stickers' true poses, which the frames show.

:func:`render_view` renders one frame from a given camera pose (with an optional straight motion
that makes a chosen blur length), for tests and benchmarks of the other stages.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from tagloc.core.camera import Camera, default_camera, load_calibration
from tagloc.core.errors import InputError
from tagloc.core.geometry import make_T, planar_T
from tagloc.core.rig import Rig, RigCamera, default_rig, load_rig, looking_forward
from tagloc.core.sticker import INNER_CORNERS, OUTER_CORNERS
from tagloc.core.stickermap import StickerMap, load_map, save_map
from tagloc.io.session import GROUNDTRUTH_FILE, SessionInfo, SessionWriter, after_last, write_tum
from tagloc.sim.floor import Floor, FloorConfig
from tagloc.sim.lamps import LampConfig, Lamps
from tagloc.sim.legs import Legs, LegsConfig
from tagloc.sim.render import (
    ExposureConfig,
    Flicker,
    OpticsConfig,
    Renderer,
    RenderResult,
    SensorConfig,
    exposure_for_sensor,
    exposure_time,
    row_delay_s,
    sensor_preset,
)
from tagloc.sim.survey import SurveyConfig, surveyed_map
from tagloc.sim.timing import TimingConfig, frame_schedule
from tagloc.sim.walk import Walk, WalkConfig, plan_walk

#: Renderer seed offset of each further camera of the rig (its own sensor's fixed pattern).
CAMERA_SEED_STEP = 7919

# Bumped whenever the simulated physics change, so that sessions cached by ``tagloc eval`` are made
# again (2: slow roll drift of the vest; 3: lean into turns and with acceleration, torso rotations
# about the centre of mass, ground truth at the vest point's vertical projection; 4: the tilt drift
# and the walking speed's variation have the body's inertia, so their rates are not white noise;
# 5: the frames are the same, but the session's rig states ``legs_in_view``, which a rig made
# before would have decided from its mount; 6: each camera of a rig has its own jitter and dropped
# frames, and motion blur is rendered from 0.3 px up, one sub-frame per 0.5 px, where blur up to
# 1.5 px was rendered sharp and longer blur with one per 1.5 px).
SIM_REVISION = 6


@dataclass
class SimConfig:
    """Everything a simulated session depends on. Same config (and map), same bytes.

    Attributes:
        seconds, fps: length of the session (s) and frame rate.
        lux: illuminance on the floor.
        speed_mps: nominal walking speed.
        seed: random seed of walk, floor, and noise.
        pitch_deg, height_m: camera pitch below horizontal and height (default rig only).
        rolling_shutter: expose rows at staggered times (``exposure.readout_s`` from top to bottom).
        jpeg_quality: JPEG quality of the written frames.
        distractors_per_m2: dark squares (8-15 cm) on the floor per square metre.
        missing_fraction: share of the map's stickers that are not on the floor.
        unmapped: number of stickers on the floor whose IDs are not in the map.
        scale: image resolution factor (0.5: half-size frames and intrinsics, for fast tests).
        calibration: true camera (Camera or a calibration file); default: Pi camera v1.
        rig: rig (Rig or rig.json); default: one camera at ``height_m`` pitched ``pitch_deg``.
            Every camera is rendered (see :func:`simulate_session`).
        walk, floor, optics, sensor, exposure: detailed models; the fields above override their
            seconds/speed/seed, distractors/missing/unmapped and rolling_shutter.
        sensor_preset: a named sensor model (:func:`tagloc.sim.render.sensor_preset`) instead of
            ``sensor``; the auto exposure is scaled to its sensitivity
            (:func:`tagloc.sim.render.exposure_for_sensor`).
        timing: jittered timestamps and dropped frames (:mod:`tagloc.sim.timing`).
        survey: survey error of the map written to the session (:mod:`tagloc.sim.survey`); the
            floor keeps the true poses.
        flicker: the lamps' percent flicker as a fraction (:class:`tagloc.sim.render.Flicker`; 0:
            steady light), at twice ``mains_hz``; the mains phase at time 0 is drawn from ``seed``.
        shadow: the operator's own shadow under a grid of overhead lamps (``lamps``,
            :mod:`tagloc.sim.lamps`), on top of the floor's illumination pattern; the grid's offset
            is drawn from ``seed``.
        legs: the wearer's legs and feet in the camera's view (``legs_config``,
            :mod:`tagloc.sim.legs`), stepping with the walk's gait; the session's rig marks its
            forward-looking cameras ``legs_in_view`` then, and every camera not so without them.
    """

    seconds: float = 20.0
    fps: float = 30.0
    lux: float = 100.0
    speed_mps: float = 1.3
    seed: int = 1
    pitch_deg: float = 55.0
    height_m: float = 1.3
    rolling_shutter: bool = False
    jpeg_quality: int = 85
    distractors_per_m2: float = 0.05
    missing_fraction: float = 0.0
    unmapped: int = 0
    scale: float = 1.0
    calibration: Camera | str | Path | None = None
    rig: Rig | str | Path | None = None
    walk: WalkConfig = field(default_factory=WalkConfig)
    floor: FloorConfig = field(default_factory=FloorConfig)
    optics: OpticsConfig = field(default_factory=OpticsConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    exposure: ExposureConfig = field(default_factory=ExposureConfig)
    sensor_preset: str | None = None
    timing: TimingConfig = field(default_factory=TimingConfig)
    survey: SurveyConfig = field(default_factory=SurveyConfig)
    flicker: float = 0.0
    mains_hz: float = 50.0
    shadow: bool = False
    lamps: LampConfig = field(default_factory=LampConfig)
    legs: bool = False
    legs_config: LegsConfig = field(default_factory=LegsConfig)

    def __post_init__(self) -> None:
        if not self.seconds > 0 or not self.fps > 0 or not self.lux > 0 or not self.speed_mps > 0:
            raise InputError("seconds, fps, lux and speed must be positive")
        if self.frame_count < 1:
            # Frame k is exposed at k / fps, k < seconds * fps: a shorter session has none to write.
            raise InputError(f"{self.seconds:g} s at {self.fps:g} fps holds no frame (want seconds x fps >= 1)")
        if not 0 < self.scale <= 4:
            raise InputError(f"scale {self.scale} must be in (0, 4]")
        if not self.exposure.readout_s >= 0:
            raise InputError(f"rolling-shutter read-out {self.exposure.readout_s} s must be >= 0")
        if self.rolling_shutter and self.exposure.readout_s > 1.0 / self.fps + 1e-12:
            # A sensor reads a frame's last row before the next frame's first: rows of two frames
            # are never read out at once (the Pi camera: 20-30 ms at up to 30-40 fps).
            raise InputError(
                f"rolling-shutter read-out {self.exposure.readout_s * 1e3:g} ms is longer than the frame"
                f" interval {1e3 / self.fps:g} ms at {self.fps:g} fps"
            )
        if not 0 <= self.flicker <= 1:
            raise InputError(f"flicker {self.flicker} must be a fraction in [0, 1]")
        if not self.mains_hz > 0:
            raise InputError(f"mains frequency {self.mains_hz} Hz must be positive")
        if not 1 <= self.jpeg_quality <= 100:
            raise InputError(f"JPEG quality {self.jpeg_quality} is not in 1-100")

    def describe(self) -> str:
        """The session's conditions in one line (its ``session.json`` notes, the condition column
        ``tagloc eval --walks`` prints): length, light, speed and seed, then every condition that is
        not the plain default, so that a walk's row names what it was rendered with."""
        parts = [f"{self.seconds:g} s at {self.lux:g} lux, {self.speed_mps:g} m/s, seed {self.seed}"]
        return ", ".join(parts + self._camera_conditions() + self._field_conditions())

    def _camera_conditions(self) -> list[str]:
        """The mount, lens, frame rate and resolution, where not the default."""
        parts = []
        if self.rig is not None:
            parts.append(f"rig {Path(self.rig).name if isinstance(self.rig, (str, Path)) else 'given'}")
        elif (self.pitch_deg, self.height_m) != (55.0, 1.3):
            parts.append(f"camera {self.height_m:g} m up, {self.pitch_deg:g} deg down")
        if self.calibration is not None:
            cal = self.calibration
            parts.append(f"lens {Path(cal).name if isinstance(cal, (str, Path)) else f'{cal.width}x{cal.height}'}")
        if self.fps != 30.0:
            parts.append(f"{self.fps:g} fps")
        if self.scale != 1.0:
            parts.append(f"resolution x{self.scale:g}")
        if self.jpeg_quality != 85:
            parts.append(f"JPEG {self.jpeg_quality}")
        return parts

    def _field_conditions(self) -> list[str]:
        """Shutter, timing, survey, floor, sensor and light conditions that are on."""
        t, sv = self.timing, self.survey
        named = [
            (self.rolling_shutter, f"rolling shutter {1e3 * self.exposure.readout_s:g} ms"),
            (t.jitter_s, f"jitter +-{1e3 * t.jitter_s:g} ms"),
            (
                t.drop_fraction or t.bursts_per_min,
                f"drops {100 * t.drop_fraction:g}% + {t.bursts_per_min:g} bursts/min",
            ),
            (
                sv.sigma_m or sv.sigma_deg,
                f"survey {100 * sv.sigma_m:g} cm {sv.sigma_deg:g} deg{' stated' if sv.stated else ''}",
            ),
            (
                self.missing_fraction or self.unmapped,
                f"{100 * self.missing_fraction:g}% missing, {self.unmapped} unmapped",
            ),
            (self.sensor_preset not in (None, "standard"), f"sensor {self.sensor_preset}"),
            (self.flicker, f"flicker {100 * self.flicker:g}% at {self.mains_hz:g} Hz mains"),
            (self.floor.texture_contrast != 1.0, f"floor texture x{self.floor.texture_contrast:g}"),
            (self.shadow, "shadow"),
            (self.legs, "legs"),
        ]
        return [text for on, text in named if on]

    @property
    def frame_count(self) -> int:
        """Frames the sensor exposes in the session (at ``k / fps`` for ``k`` below it), before any drop."""
        return int(math.floor(self.seconds * self.fps + 1e-9))

    def walk_config(self) -> WalkConfig:
        """The walk model with this config's seconds, speed and seed."""
        return replace(self.walk, seconds=self.seconds, speed_mps=self.speed_mps, seed=self.seed)

    def floor_config(self) -> FloorConfig:
        """The floor model with this config's distractors and missing/unmapped stickers."""
        return replace(
            self.floor,
            distractors_per_m2=self.distractors_per_m2,
            missing_fraction=self.missing_fraction,
            unmapped=self.unmapped,
        )

    def sensor_config(self) -> SensorConfig:
        """The sensor model: the named preset if one is given, else ``sensor``."""
        return sensor_preset(self.sensor_preset) if self.sensor_preset else self.sensor

    def exposure_config(self) -> ExposureConfig:
        """The exposure model with this config's shutter type, scaled to the sensor's sensitivity."""
        return exposure_for_sensor(replace(self.exposure, rolling_shutter=self.rolling_shutter), self.sensor_config())

    def light_flicker(self) -> Flicker | None:
        """The lamps' flicker (None: steady light), its mains phase drawn from ``seed``."""
        if self.flicker == 0:
            return None
        phase = float(np.random.default_rng([self.seed, 29]).uniform(0.0, 2.0 * math.pi))
        return Flicker(self.flicker, 2.0 * self.mains_hz, phase)

    def lamp_grid(self) -> Lamps | None:
        """The lamps that cast the operator's shadow (None: no shadow)."""
        return Lamps(self.lamps, seed=self.seed) if self.shadow else None

    def build_rig(self) -> Rig:
        """The rig to simulate (every camera), each camera scaled by ``scale``."""
        cam = self.calibration
        if isinstance(cam, (str, Path)):
            cam = load_calibration(cam)
        if self.rig is None:
            rig = default_rig(self.height_m, self.pitch_deg, cam or default_camera())
        else:
            rig = self.rig if isinstance(self.rig, Rig) else load_rig(self.rig, cam)
        # A rolling-shutter camera says so in the session's rig.json (its read-out), as a real one would.
        readout = self.exposure.readout_s if self.rolling_shutter else 0.0
        return Rig(
            [
                RigCamera(
                    rc.name,
                    rc.camera.scaled(self.scale) if self.scale != 1 else rc.camera,
                    rc.T_body_camera.copy(),
                    rc.calibration_file,
                    readout,
                    vest_height_m=rc.vest_height_m,
                )
                for rc in rig.cameras
            ]
        )

    def to_json(self) -> dict:
        """Plain-data description for ``session.json`` (files by name; objects summarised)."""
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in ("calibration", "rig"):
                out[f.name] = str(v) if isinstance(v, (str, Path)) else (None if v is None else "given")
            elif hasattr(v, "__dataclass_fields__"):
                out[f.name] = asdict(v)
            else:
                out[f.name] = v
        return out


@dataclass
class SimSummary:
    """What :func:`simulate_session` produced.

    Attributes:
        path: session directory.
        frames: frames written.
        wall_s: rendering time, s.
        exposure_s, gain, blur_px: means over the frames.
        max_subframes: most sub-frames used by one frame.
        missing_ids: map IDs not on the floor; unmapped_ids: floor IDs not in the map.
    """

    path: Path
    frames: int
    wall_s: float
    exposure_s: float
    gain: float
    blur_px: float
    max_subframes: int
    missing_ids: list[int]
    unmapped_ids: list[int]


def simulate_walk(smap: StickerMap, config: SimConfig) -> Walk:
    """The walk of a simulated session (see :mod:`tagloc.sim.walk`)."""
    return plan_walk(smap, config.walk_config())


def _project_corners(camera: Camera, T_world_camera: np.ndarray, pts_world: np.ndarray) -> np.ndarray | None:
    """Distorted pixels (N, 2) of world points, or None if any is behind or far outside the view
    (beyond where the distortion polynomial folds back into the image: :meth:`Camera.project_in_view`)."""
    pc = pts_world @ np.linalg.inv(T_world_camera)[:3, :3].T + np.linalg.inv(T_world_camera)[:3, 3]
    return camera.project_in_view(pc)


def visible_stickers(floor: Floor, renderer: Renderer, pose_at, t: float, readout_s: float = 0.0) -> list[dict]:
    """Ground truth of the floor stickers in view at ``t``: see the module docstring.

    With ``readout_s`` > 0 (rolling shutter) each corner is projected with the pose at its own row's
    time (two fixed-point iterations).
    """
    cam = renderer.camera
    T_mid = pose_at(np.array([t]))[0]
    out = []
    for row in renderer.visible_rows(T_mid[None]):
        T_ws = floor.stickers.T_world_sticker(int(floor.stickers.ids[row]))
        pts = np.vstack([OUTER_CORNERS, INNER_CORNERS]) @ T_ws[:3, :3].T + T_ws[:3, 3]
        px = _project_corners(cam, T_mid, pts)
        if px is None:
            continue
        if readout_s > 0:
            for _ in range(2):
                tc = t + row_delay_s(np.clip(px[:, 1], 0, cam.height - 1), cam.height, readout_s)
                poses = pose_at(tc)
                new = [_project_corners(cam, T, p[None]) for T, p in zip(poses, pts)]
                if any(n is None for n in new):
                    break
                px = np.vstack(new)
        lo, hi = px.min(axis=0), px.max(axis=0)
        if hi[0] < -0.5 or hi[1] < -0.5 or lo[0] > cam.width - 0.5 or lo[1] > cam.height - 0.5:
            continue
        inside = bool(np.all((px >= 0) & (px <= (cam.width - 1, cam.height - 1))))
        dist = float(np.linalg.norm(T_ws[:3, 3] - T_mid[:3, 3]))
        out.append(
            {
                "id": int(floor.stickers.ids[row]),
                "in_map": bool(floor.in_map[row]),
                "corners": np.round(px[:4], 3).tolist(),
                "inner": np.round(px[4:], 3).tolist(),
                "inside": inside,
                "distance_m": round(dist, 4),
            }
        )
    return out


def _resolve_map(smap: StickerMap | str | Path) -> StickerMap:
    return smap if isinstance(smap, StickerMap) else load_map(smap)


@dataclass
class SimScene:
    """What a simulated session is rendered from: the rig, the walk, the floor, one renderer per rig
    camera (its own sensor and auto exposure) and each camera's frame schedule (jitter, drops)."""

    config: SimConfig
    rig: Rig
    walk: Walk
    floor: Floor
    renderers: list[Renderer]
    schedules: list

    @classmethod
    def build(cls, smap: StickerMap, config: SimConfig) -> SimScene:
        """The scene :func:`simulate_session` renders ``smap`` under ``config`` from (no frame rendered)."""
        rig = config.build_rig()
        # The session's rig says what its cameras see: the simulated vest's legs or none (an
        # installer looks at the frames too).
        for rc in rig.cameras:
            rc.legs_in_view = bool(config.legs and float(rc.T_body_camera[0, 2]) > 0.0)
        walk = simulate_walk(smap, config)
        floor = Floor(smap, config.floor_config(), seed=config.seed)
        lamps = config.lamp_grid()
        legs = Legs(walk, rig.vest_point, config.legs_config) if config.legs else None
        # Each camera has its own sensor (fixed-pattern noise seed) and its own auto exposure.
        renderers = [
            Renderer(
                floor,
                rc.camera,
                config.optics,
                config.sensor_config(),
                config.exposure_config(),
                seed=config.seed + CAMERA_SEED_STEP * c,
                flicker=config.light_flicker(),
                lamps=lamps,
                legs=legs,
            )
            for c, rc in enumerate(rig.cameras)
        ]
        # Free-running cameras have their own drivers and queues: each its own jitter, drops and bursts.
        schedules = [
            frame_schedule(config.frame_count, config.fps, config.timing, config.seed, camera=c)
            for c in range(len(rig))
        ]
        return cls(config, rig, walk, floor, renderers, schedules)

    @property
    def stagger(self) -> float:
        """Seconds between the rig cameras' exposures: free-running cameras are never simultaneous,
        camera c is exposed c / (cameras * fps) after camera 0."""
        return 1.0 / (len(self.rig) * self.config.fps)

    def pose_at(self, camera: int) -> Callable[[np.ndarray], np.ndarray]:
        """Rig camera ``camera``'s true pose T_world_camera ((N, 4, 4)) at times (N,) s."""
        T_body_camera = self.rig.cameras[camera].T_body_camera
        return lambda ts: self.walk.T_world_camera(np.asarray(ts, float), T_body_camera)

    def render_frame(self, k: int, camera: int = 0) -> tuple[float, np.ndarray, np.ndarray]:
        """Frame ``k`` of rig camera ``camera`` as :func:`simulate_session` renders it (before JPEG),
        without rendering the frames before it: (true mid-exposure time s, (H, W) uint8 image,
        T_world_body (4, 4)). The same walk, light, noise draws and seeds; the renderer cuts its floor
        mosaic afresh, which can move a few pixels by a few grey levels from a session's frame drawn
        on a mosaic cut for earlier frames (frames 504 and 506 of the field walk f01 come out
        identical). Raises InputError for a frame the camera's driver dropped or that the session
        does not hold."""
        sc = self.schedules[camera]
        rows = np.flatnonzero(sc.index == k)
        if not len(rows):
            raise InputError(f"simulate: camera {camera} delivers no frame {k}")
        t = float(sc.true_t[rows[0]]) + camera * self.stagger
        shot = _Shot(float(sc.stamp[rows[0]]) + camera * self.stagger, t, camera, int(k))
        res, T_world_body = _render_shot(self, shot)
        return t, res.image, T_world_body


def _render_shot(scene: SimScene, shot: _Shot) -> tuple[RenderResult, np.ndarray]:
    """Render ``shot`` with its camera's renderer: the result and the body pose T_world_body (4, 4)."""
    config, rig = scene.config, scene.rig
    renderer = scene.renderers[shot.camera]
    k, t, camera = shot.k, shot.t, shot.camera
    seed = [config.seed, 23, k] if camera == 0 else [config.seed, 23, k, camera]
    vest_point = rig.vest_point
    T_world_body = scene.walk.T_world_body(t, vest_point)
    body = renderer.lamps.axis(T_world_body, vest_point) if renderer.lamps is not None else None
    res = renderer.render(
        scene.pose_at(camera),
        t,
        config.lux,
        np.random.default_rng(seed),
        frame_interval_s=1.0 / config.fps,
        body=body,
    )
    return res, T_world_body


def simulate_session(
    smap: StickerMap | str | Path, out_dir: str | Path, config: SimConfig | None = None, progress: bool = True
) -> SimSummary:
    """Simulate a walk over ``smap`` and write it as a session with ground truth to ``out_dir``."""
    from tqdm import tqdm

    config = config or SimConfig()
    smap = _resolve_map(smap)
    scene = SimScene.build(smap, config)
    rig, walk, floor, schedules = scene.rig, scene.walk, scene.floor, scene.schedules
    n_cams = len(rig)
    exp_cfg = config.exposure_config()
    shots = _delivered(schedules, scene.stagger)
    # Ground truth at the frames' true times; frames.csv gets the drivers' jittered stamps.
    gt_stamps = np.sort(np.array([shot.t for shot in shots], float))
    given_map = surveyed_map(smap, config.survey, config.seed)
    out = Path(out_dir)
    unmapped = [int(i) for i in floor.stickers.ids[~floor.in_map]]
    sim_info = {
        "simulation": {
            "config": config.to_json(),
            "missing_ids": [int(i) for i in floor.missing_ids],
            "unmapped": [
                {
                    "id": int(floor.stickers.ids[k]),
                    "x_m": round(float(floor.stickers.xy[k, 0]), 4),
                    "y_m": round(float(floor.stickers.xy[k, 1]), 4),
                    "yaw_deg": round(math.degrees(float(floor.stickers.yaw[k])), 3),
                }
                for k in np.flatnonzero(~floor.in_map)
            ],
            "groundtruth_frames": "groundtruth_frames.jsonl",
            "dropped_frames": sum(sc.dropped for sc in schedules),
            "drop_bursts": sum(sc.bursts for sc in schedules),
        }
    }
    if n_cams > 1:
        sim_info["simulation"] |= {
            "dropped_frames_per_camera": [sc.dropped for sc in schedules],
            "drop_bursts_per_camera": [sc.bursts for sc in schedules],
        }
    info = SessionInfo(
        source="simulated",
        fps=config.fps,
        notes=f"tagloc simulate: {config.describe()}",
        extra=sim_info,
    )
    readout = exp_cfg.readout_s if exp_cfg.rolling_shutter else 0.0
    poses = [scene.pose_at(c) for c in range(n_cams)]
    t_wall = time.perf_counter()
    stats = []
    with SessionWriter(out, given_map, rig, info, jpeg_quality=config.jpeg_quality) as writer:
        if given_map is not smap:
            save_map(smap, out / "map_true.csv")
        write_tum(out / GROUNDTRUTH_FILE, gt_stamps, walk.T_world_body(gt_stamps, rig.vest_point))
        with (out / "groundtruth_frames.jsonl").open("w", encoding="utf-8") as gt:
            for shot in tqdm(shots, desc="simulate", unit="frame", disable=not progress):
                rec, stat = _simulate_frame(writer, scene, poses[shot.camera], shot, readout)
                gt.write(json.dumps(rec) + "\n")
                gt.flush()
                stats.append(stat)
    s = np.array(stats).reshape(-1, 4)
    n = len(shots)
    return SimSummary(
        out,
        n,
        time.perf_counter() - t_wall,
        float(s[:, 0].mean()) if n else 0.0,
        float(s[:, 1].mean()) if n else 0.0,
        float(s[:, 2].mean()) if n else 0.0,
        int(s[:, 3].max()) if n else 0,
        [int(i) for i in floor.missing_ids],
        unmapped,
    )


@dataclass(frozen=True, order=True)
class _Shot:
    """One delivered frame: its driver's stamp, true (middle-row) time, rig camera and frame number
    (ordered by stamp first)."""

    stamp: float
    t: float
    camera: int
    k: int


def _delivered(schedules: list, stagger: float) -> list[_Shot]:
    """The frames the cameras' drivers deliver (camera c's ``schedules[c]``, exposed ``c * stagger``
    after camera 0's), in the order of their stamps, as a recorder merging the cameras' queues writes them.

    The cameras' jitter is independent, so with jitter of half the stagger or more two cameras'
    stamps can swap (against the true times) or meet: a stamp that would not come after the one
    before it once rounded to frames.csv's microseconds is put one microsecond after it, the
    resolution the recorder's clock has there (frames.csv's stamps must increase), by the recorders'
    own rule, :func:`~tagloc.io.session.after_last`.
    """
    shots = sorted(
        _Shot(float(sc.stamp[j]) + c * stagger, float(sc.true_t[j]) + c * stagger, c, int(sc.index[j]))
        for c, sc in enumerate(schedules)
        for j in range(len(sc.index))
    )
    out: list[_Shot] = []
    for shot in shots:
        if out:
            shot = replace(shot, stamp=after_last(shot.stamp, out[-1].stamp))
        out.append(shot)
    return out


def _simulate_frame(writer: SessionWriter, scene: SimScene, pose_at, shot: _Shot, readout: float) -> tuple[dict, tuple]:
    """Render and write the delivered frame ``shot`` of ``scene`` (``pose_at``: its camera's pose at
    any time); its ground-truth record.

    One camera: index = the schedule's frame number (sessions as before). Several: index = frame
    number * cameras + camera, unique over the session, and each record names its camera.
    """
    k, t, camera = shot.k, shot.t, shot.camera
    n_cams = len(scene.rig)
    index = k if n_cams == 1 else k * n_cams + camera
    res, T_world_body = _render_shot(scene, shot)
    stamp = shot.stamp
    writer.write(index, stamp, res.image, camera)
    rec = {"index": index} | ({"camera": camera} if n_cams > 1 else {})
    rec |= {
        "t": round(t, 6),
        "stamp": round(stamp, 6),
        "T_world_body": np.round(T_world_body, 6).tolist(),
        "T_world_camera": np.round(pose_at(np.array([t]))[0], 6).tolist(),
        "exposure_s": round(res.exposure_s, 7),
        "gain": round(res.gain, 4),
        "blur_px": round(res.blur_px, 3),
        "subframes": res.subframes,
        "mean_signal_e": round(res.mean_signal_e, 2),
        "visible": visible_stickers(scene.floor, scene.renderers[camera], pose_at, t, readout),
    }
    return rec, (res.exposure_s, res.gain, res.blur_px, res.subframes)


def read_groundtruth_frames(session_dir: str | Path) -> list[dict]:
    """The records of a session's ``groundtruth_frames.jsonl`` (empty list if it has none)."""
    p = Path(session_dir) / "groundtruth_frames.jsonl"
    if not p.exists():
        return []
    out = []
    with p.open(encoding="utf-8-sig") as f:
        for n, line in enumerate(f, 1):
            if line.strip():
                try:
                    out.append(json.loads(line))
                except json.JSONDecodeError:
                    raise InputError(f"{p}:{n}: not a JSON object") from None
    return out


# -- single views --------------------------------------------------------------------------------


def camera_pose_looking_at(
    target_xy: tuple[float, float] | np.ndarray,
    height_m: float = 1.3,
    pitch_deg: float = 55.0,
    yaw_deg: float = 0.0,
    roll_deg: float = 0.0,
) -> np.ndarray:
    """``T_world_camera`` of a camera ``height_m`` above the floor, heading ``yaw_deg`` (from world +x),
    pitched ``pitch_deg`` below horizontal (90: straight down) and rolled ``roll_deg`` about its axis,
    whose optical axis meets the floor at ``target_xy``."""
    p, a = math.radians(pitch_deg), math.radians(yaw_deg)
    back = height_m / math.tan(p) if abs(math.cos(p)) > 1e-9 else 0.0
    x, y = float(target_xy[0]) - back * math.cos(a), float(target_xy[1]) - back * math.sin(a)
    r = math.radians(roll_deg)
    roll = make_T(np.array([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1]]), np.zeros(3))
    return planar_T(x, y, 0.0) @ looking_forward(height_m, pitch_deg, yaw_deg) @ roll


def render_view(
    scene: StickerMap | Floor,
    camera: Camera,
    T_world_camera: np.ndarray,
    lux: float = 150.0,
    *,
    velocity: np.ndarray | None = None,
    angular_velocity: np.ndarray | None = None,
    blur_px: float | None = None,
    blur_direction_deg: float = 0.0,
    exposure_s: float | None = None,
    gain: float | None = None,
    seed: int = 0,
    noise: bool = True,
    jpeg_quality: int | None = None,
    floor_config: FloorConfig | None = None,
    optics: OpticsConfig | None = None,
    sensor: SensorConfig | None = None,
    exposure: ExposureConfig | None = None,
    flicker: Flicker | None = None,
    lamps: Lamps | None = None,
    body: np.ndarray | None = None,
) -> RenderResult:
    """Render one frame of ``camera`` at ``T_world_camera`` (pose at mid-exposure), same physics as sessions.

    Motion during the exposure (straight and uniform): ``velocity`` (3,) world m/s of the camera
    centre and ``angular_velocity`` (3,) rad/s about world axes through the camera centre, or
    ``blur_px``: a velocity parallel to the image plane, along image direction
    ``blur_direction_deg`` (0: image +x, 90: image +y), that blurs the floor at the image centre
    by that many pixels. ``scene`` is a map (a floor is made with ``floor_config`` and ``seed``;
    pass a :class:`Floor` to reuse its tile cache across calls). ``noise=False`` gives the
    noise-free image; ``jpeg_quality`` round-trips it through JPEG. ``flicker``: the lamps', the
    frame at time 0 of its phase. ``lamps`` and ``body`` (3,): the operator's shadow, the body's
    axis standing at ``body`` (x, y, yaw; m, rad)
    """
    import cv2

    floor = scene if isinstance(scene, Floor) else Floor(scene, floor_config or FloorConfig(), seed=seed)
    sensor = replace(sensor or SensorConfig(), noise=noise)
    exp_cfg = exposure or ExposureConfig()
    renderer = Renderer(floor, camera, optics, sensor, exp_cfg, seed=seed, flicker=flicker, lamps=lamps)
    T0 = np.asarray(T_world_camera, float)
    t_exp = exposure_s if exposure_s is not None else exposure_time(lux, exp_cfg)
    v = np.zeros(3) if velocity is None else np.asarray(velocity, float)
    w = np.zeros(3) if angular_velocity is None else np.asarray(angular_velocity, float)
    if blur_px is not None and blur_px > 0:
        # Depth of the floor point on the optical axis sets the speed that gives blur_px there.
        axis = T0[:3, 2]
        if axis[2] >= -1e-6:
            raise InputError("blur_px needs a camera looking down at the floor")
        depth = -T0[2, 3] / axis[2]
        b = math.radians(blur_direction_deg)
        direction = math.cos(b) * T0[:3, 0] + math.sin(b) * T0[:3, 1]
        # Moving the camera one way moves the image the other way; blur length is what matters.
        v = v + direction * blur_px * depth / (camera.fx * t_exp)

    def pose_at(ts: np.ndarray) -> np.ndarray:
        from scipy.spatial.transform import Rotation

        ts = np.asarray(ts, float)
        out = np.repeat(T0[None], len(ts), axis=0)
        out[:, :3, 3] += ts[:, None] * v
        if np.any(w):
            R = Rotation.from_rotvec(ts[:, None] * w).as_matrix()
            out[:, :3, :3] = R @ T0[:3, :3]
        return out

    res = renderer.render(pose_at, 0.0, lux, np.random.default_rng([seed, 29]), exposure_s=t_exp, gain=gain, body=body)
    if jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", res.image, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        res.image = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return res


def true_corners(
    scene: Floor | StickerMap, camera: Camera, T_world_camera: np.ndarray, sticker_id: int
) -> np.ndarray | None:
    """Outer then inner corners (8, 2) of ``sticker_id`` in distorted pixels (canonical order), or None
    if it is behind the camera or far outside the view."""
    stickers = scene.stickers if isinstance(scene, Floor) else scene
    T_ws = stickers.T_world_sticker(sticker_id)
    pts = np.vstack([OUTER_CORNERS, INNER_CORNERS]) @ T_ws[:3, :3].T + T_ws[:3, 3]
    return _project_corners(camera, np.asarray(T_world_camera, float), pts)


__all__ = [
    "SIM_REVISION",
    "SimConfig",
    "SimSummary",
    "simulate_walk",
    "simulate_session",
    "visible_stickers",
    "render_view",
    "camera_pose_looking_at",
    "true_corners",
    "read_groundtruth_frames",
]
