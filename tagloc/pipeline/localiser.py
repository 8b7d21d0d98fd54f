"""The localiser: one frame in, observations and a tracked pose out.

The frame flows one way: detect -> decode, or identify against the tracker's candidates ->
pose -> tracker. Sources and sinks live elsewhere (:mod:`tagloc.io.capture`, :mod:`tagloc.io.sinks`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from tagloc.core.camera import load_calibration
from tagloc.core.errors import CalibrationError, InputError
from tagloc.core.rig import Rig, default_rig, load_rig
from tagloc.core.stickermap import StickerMap, load_map
from tagloc.core.types import Frame, FrameResult, IdSource, Observation, TrackerOutput, TrackState
from tagloc.io.session import CAMERA_FILE, MAP_FILE, RIG_FILE
from tagloc.vision.decode import decode
from tagloc.vision.detect import detect
from tagloc.vision.odometry import FloorOdometry, OdometryConfig
from tagloc.vision.pose import PoseConfig, SurveyPasses, solve_pose
from tracker.candidates import select_candidates
from tracker.tracker import Tracker, TrackerConfig

MODES = ("full", "decoded-only", "orb-all")


@dataclass
class LocaliserConfig:
    """Choices of the per-frame stage and the tracker.

    Attributes:
        mode: "full" (tagloc), or a baseline from the paper: "decoded-only" (decoded fixes, no
            filter: the last fix is held) or "orb-all" (ORB against every reference in the
            map when decoding fails, no prediction, no filter).
        detector: "contour" (ours) or "paper" (ORB + k-means, for comparison).
        decoder: Data Matrix backend: "zxing", "libdmtx" or "both".
        identify: identification when decoding fails: "auto", "orb", "appearance" or "off".
        candidates: K, the most candidates handed to identification.
        tracker: the EKF's configuration.
        odometry: measure the body's motion between frames from the floor texture and feed it to
            the tracker ("full" mode only); ``odometry_config`` tunes it.
        pose: the pose solver's options (corner noise, the map's default survey sigmas).
        rolling_shutter: for a rig camera with a rolling shutter (``readout_s`` in rig.json),
            move each sticker's corners to the frame's time with the body's motion (this frame's
            odometry step, else the tracker's prediction) before solving its pose.
    """

    mode: str = "full"
    detector: str = "contour"
    decoder: str = "zxing"
    identify: str = "auto"
    candidates: int = 5
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    odometry: bool = True
    odometry_config: OdometryConfig = field(default_factory=OdometryConfig)
    pose: PoseConfig = field(default_factory=PoseConfig)
    rolling_shutter: bool = True


def load_setup(
    map_path: str | Path | None = None,
    calibration: str | Path | None = None,
    rig_path: str | Path | None = None,
    config_dir: str | Path | None = None,
) -> tuple[StickerMap, Rig]:
    """Load the map and rig from explicit files, or all from a session-like ``config_dir``.

    Explicit files override the directory's. Without a rig, the default rig is used with the given
    calibration. The map is validated before anything else happens.
    """
    cdir = Path(config_dir) if config_dir is not None else None
    if cdir is not None and not cdir.is_dir():
        raise InputError(f"{cdir}: --config must be a directory holding camera.yaml, rig.json, map.csv")
    map_path = map_path or (cdir / MAP_FILE if cdir else None)
    if map_path is None:
        raise InputError("no map: give --map FILE or --config DIR")
    smap = load_map(map_path)
    camera = load_calibration(calibration) if calibration else None
    rig_path = rig_path or (cdir / RIG_FILE if cdir and (cdir / RIG_FILE).exists() else None)
    if rig_path is not None:
        rig = load_rig(rig_path, camera)
    else:
        if camera is None and cdir is not None and (cdir / CAMERA_FILE).exists():
            camera = load_calibration(cdir / CAMERA_FILE)
        rig = default_rig(camera=camera)
    return smap, rig


class Localiser:
    """Per-frame vision plus the tracker, for one operator."""

    def __init__(
        self,
        smap: StickerMap,
        rig: Rig,
        config: LocaliserConfig | None = None,
        refs=None,
        map_path: str | Path | None = None,
    ):
        self.map = smap
        self.rig = rig
        self.config = config or LocaliserConfig()
        if self.config.mode not in MODES:
            raise InputError(f"unknown localiser mode {self.config.mode!r} (want one of {', '.join(MODES)})")
        self.tracker = Tracker(self.config.tracker)
        self._passes = SurveyPasses()  # repeated fixes of a sticker share its survey error
        self._step = None  # this frame's odometry step, for the rolling-shutter correction
        self._held: TrackerOutput | None = None  # the baselines' last fix
        self._refs = refs
        self._map_path = map_path
        self._odometry: dict[int, FloorOdometry | None] = {}  # per rig camera; None: camera sees too little floor
        self.counts = {
            "frames": 0,
            "skipped": 0,
            "detections": 0,
            "decoded": 0,
            "identified": 0,
            "rejected_reads": 0,
            "unmapped_reads": 0,
            "odometry_steps": 0,
            "odometry_unavailable": 0,
        }

    @property
    def refs(self):
        """The ORB/appearance reference bank, built or loaded on first need."""
        if self._refs is None:
            from tagloc.vision.refs import build_refs, load_or_build_refs

            if self._map_path is not None:
                self._refs = load_or_build_refs(self._map_path, progress=False)
            else:
                self._refs = build_refs(self.map, progress=False)
        return self._refs

    def process(self, frame: Frame) -> FrameResult:
        """Run one frame through the pipeline and return what was seen and the pose after it."""
        t0 = time.perf_counter()
        t = frame.timestamp
        self.counts["frames"] += 1
        times: dict[str, float] = {}
        self.tracker.predict(t)
        times["tracker"] = (time.perf_counter() - t0) * 1e3
        if frame.image is None:
            self.counts["skipped"] += 1
            return FrameResult(frame.index, t, [], self.tracker.output(t), {}, frame.error or "unreadable")
        gray = frame.image if frame.image.ndim == 2 else cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY)
        rig_cam = self.rig[frame.camera]
        cam = rig_cam.camera
        if self.config.odometry and self.config.mode == "full":
            # Before the fixes: the step covers the interval the tracker just predicted over.
            ts = time.perf_counter()
            self._odometry_step(gray, frame.camera, t)
            times["odometry"] = (time.perf_counter() - ts) * 1e3

        ts = time.perf_counter()
        detections = detect(gray, cam, method=self.config.detector)
        times["detect"] = (time.perf_counter() - ts) * 1e3
        self.counts["detections"] += len(detections)
        observations = [Observation(d, frame.camera) for d in detections]

        # Decoded stickers first: their fixes sharpen the prediction the candidates come from.
        undecoded = []
        for obs in observations:
            ts = time.perf_counter()
            res = decode(gray, obs.detection, cam, backend=self.config.decoder)
            obs.times_ms["decode"] = (time.perf_counter() - ts) * 1e3
            if res.sticker_id is None:
                obs.rejected_read = res.rejected
                self.counts["rejected_reads"] += res.rejected is not None
                undecoded.append(obs)
                continue
            if res.sticker_id not in self.map:
                # A real sticker that is not in our map: never a fix, and not worth identifying.
                obs.rejected_read = f"decoded {res.sticker_id}, not in the map"
                obs.sticker_id = res.sticker_id
                self.counts["unmapped_reads"] += 1
                continue
            obs.sticker_id, obs.rotation, obs.source = res.sticker_id, res.rotation, IdSource.DECODED
            obs.score = 1.0
            self.counts["decoded"] += 1
            self._fix(obs, rig_cam, t)

        if self.config.mode == "full" and self.config.identify != "off":
            for obs in undecoded:
                self._identify(obs, gray, rig_cam, t)
        elif self.config.mode == "orb-all":
            for obs in undecoded:
                self._identify(obs, gray, rig_cam, t, list(map(int, self.map.ids)))

        for name in ("decode", "identify", "candidates", "pose", "update"):
            vals = [o.times_ms[name] for o in observations if name in o.times_ms]
            if vals:
                times[name] = float(sum(vals))
        times["tracker"] += times.get("candidates", 0.0) + times.get("update", 0.0)
        ts = time.perf_counter()
        out = self.tracker.output(t) if self.config.mode == "full" else self._baseline_output(observations, t)
        times["tracker"] = times.get("tracker", 0.0) + (time.perf_counter() - ts) * 1e3
        times["total"] = (time.perf_counter() - t0) * 1e3
        return FrameResult(frame.index, t, observations, out, times)

    def floor_odometry(self, camera: int) -> FloorOdometry | None:
        """The floor odometry of rig camera ``camera`` (made on first use), or None if that camera
        sees too little floor for it."""
        if camera not in self._odometry:
            try:
                self._odometry[camera] = FloorOdometry(self.rig[camera], self.config.odometry_config)
            except CalibrationError:
                self._odometry[camera] = None
                self.counts["odometry_unavailable"] += 1
        return self._odometry[camera]

    def _odometry_step(self, gray: np.ndarray, camera: int, t: float) -> None:
        odo = self.floor_odometry(camera)
        step = odo.measure(gray, t) if odo is not None else None
        self._step = step
        if step is not None:
            self.counts["odometry_steps"] += 1
            self.tracker.update_odometry(step)

    def _identify(self, obs: Observation, gray: np.ndarray, rig_cam, t: float, cands: list[int] | None = None) -> None:
        from tagloc.vision.identify import IdentifyConfig, identify

        method, id_config = self.config.identify, None
        if cands is not None:
            # The paper's baseline: ORB against every reference, each scored by its own match count.
            method, id_config = "orb", IdentifyConfig(orb_global_above=len(cands) + 1)
        else:
            ts = time.perf_counter()
            prior = self.tracker.prior()
            cands = (
                []
                if prior is None
                else select_candidates(
                    prior[0], prior[1], self.map, rig_cam, obs.detection.outer.mean(axis=0), k=self.config.candidates
                )
            )
            obs.times_ms["candidates"] = (time.perf_counter() - ts) * 1e3
        if not cands:
            return
        ts = time.perf_counter()
        res = identify(gray, obs.detection, rig_cam.camera, cands, self.refs, method=method, config=id_config)
        obs.times_ms["identify"] = (time.perf_counter() - ts) * 1e3
        if res.sticker_id is None:
            return
        obs.sticker_id, obs.rotation, obs.source = res.sticker_id, res.rotation, res.source
        obs.score, obs.margin = res.score, res.margin
        self.counts["identified"] += 1
        self._fix(obs, rig_cam, t)

    def _fix(self, obs: Observation, rig_cam, t: float) -> None:
        ts = time.perf_counter()
        row = self.map.row(obs.sticker_id)
        survey = (float(self.map.sigma_xy[row]), float(self.map.sigma_yaw[row]))  # NaN: the default
        sol = solve_pose(
            obs.detection,
            obs.rotation,
            self.map.T_world_sticker(obs.sticker_id),
            rig_cam,
            config=self.config.pose,
            map_sigma=survey,
            map_scale=self._passes.scale(obs.sticker_id, t) if self.config.mode == "full" else 1.0,
            body_twist=self._body_twist(rig_cam, t),
        )
        obs.times_ms["pose"] = (time.perf_counter() - ts) * 1e3
        obs.poses, obs.ambiguous = sol.poses, sol.ambiguous
        if not sol.poses or self.config.mode != "full":
            return
        ts = time.perf_counter()
        res = self.tracker.update(sol.poses, obs.sticker_id, obs.source, t)
        obs.times_ms["update"] = (time.perf_counter() - ts) * 1e3
        obs.accepted = res.accepted
        obs.gate_reason = res.reason

    def _body_twist(self, rig_cam, t: float) -> np.ndarray | None:
        """The body's motion (vx, vy, yaw rate; body frame) for the rolling-shutter correction, or None."""
        if not (self.config.rolling_shutter and rig_cam.readout_s > 0 and self.config.mode == "full"):
            return None
        s = self._step
        if s is not None and s.t1 == t and s.t1 > s.t0:
            # The vest's own motion over the last frame interval, wobble included.
            return np.asarray(s.delta, float) / (s.t1 - s.t0)
        return self.tracker.velocity()

    def _baseline_output(self, observations: list[Observation], t: float) -> TrackerOutput:
        """The baselines' pose: this frame's best fix, else the last one held (no filter)."""
        fixes = [(o, o.poses[0]) for o in observations if o.poses]
        if fixes:
            o, p = min(fixes, key=lambda f: f[1].reprojection_px)
            o.accepted = True
            self._held = TrackerOutput(t, p.body.copy(), p.cov.copy(), TrackState.TRACKING, 0.0, o.sticker_id, o.source)
        if self._held is None:
            return TrackerOutput(t, np.zeros(3), np.diag([1e6, 1e6, np.pi**2]), TrackState.INITIALISING, float("inf"))
        h = self._held
        return TrackerOutput(t, h.pose, h.cov, h.state, t - (h.t - h.since_fix), h.last_id, h.last_source)

    def output_at(self, t: float) -> TrackerOutput:
        """The pose at time ``t`` (>= the last frame), without a frame."""
        return self.tracker.output(t) if self.config.mode == "full" else self._baseline_output([], t)
