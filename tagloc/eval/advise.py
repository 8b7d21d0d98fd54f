"""``tagloc advise``: the exposure/gain trade-off at a light level and walking speed, measured on simulated frames.

For each exposure time the same views are rendered by tagloc's own image formation
(:func:`tagloc.sim.simulate.render_view`: photons from the floor's illuminance, motion blur from
the camera's walking velocity over the exposure, shot and read noise, the auto gain that brings the
image to the AE target, capped at the sensor's maximum), then run through the localiser's own
stages: detection, decoding, and identification among the true sticker and its nearest
neighbours in the map (the tracker's candidate set). Longer exposure: less noise, more blur; the
table shows where the balance lies for this light and speed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from tagloc.core.camera import Camera, default_camera
from tagloc.core.errors import InputError
from tagloc.eval.bench_detect import match_detections
from tagloc.sim.mapgen import GridMapConfig, grid_map
from tagloc.sim.render import SensorConfig
from tagloc.sim.simulate import camera_pose_looking_at, render_view, true_corners
from tagloc.vision.decode import decode
from tagloc.vision.detect import detect
from tagloc.vision.identify import identify
from tagloc.vision.refs import build_refs


@dataclass(frozen=True)
class AdviseConfig:
    """What to simulate.

    Attributes:
        lux: illuminance on the floor.
        speed_mps: walking speed (the camera moves this fast along its heading during the exposure).
        exposures_ms: exposure times to compare.
        frames: views per exposure (the same views for every exposure).
        height_m, pitch_deg: camera mount (the default rig's).
        candidates: identification candidates per sticker: the true one and its nearest neighbours
            in the map (the tracker's default K).
        jpeg_quality: frames go through JPEG as recorded sessions do.
        seed: views, floor and noise.
        scale: image resolution factor (0.5: half-size camera, faster).
    """

    lux: float = 100.0
    speed_mps: float = 1.3
    exposures_ms: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0, 8.0)
    frames: int = 24
    height_m: float = 1.3
    pitch_deg: float = 55.0
    candidates: int = 5
    jpeg_quality: int = 85
    seed: int = 1
    scale: float = 1.0

    def __post_init__(self) -> None:
        if not self.lux > 0 or not self.speed_mps >= 0 or self.frames < 1:
            raise InputError("advise needs lux > 0, speed >= 0 and at least one frame")
        if not self.exposures_ms or any(not e > 0 for e in self.exposures_ms):
            raise InputError("exposure times must be positive milliseconds")


@dataclass
class AdviseRow:
    """Measured at one exposure.

    Attributes:
        exposure_ms, gain: the setting (gain: what auto gain chose, capped at the sensor's maximum).
        blur_px: mean blur length over the exposure.
        snr: signal-to-noise ratio of the mean floor signal (shot, read and dark noise).
        brightness: mean signal relative to the AE target (below 1: gain capped, a dark image).
        stickers: stickers fully in view, over all frames.
        detected, read, identified, wrong: fractions of them detected, decoded, decoded or
            identified (the fixes the tracker gets), and given a wrong ID.
    """

    exposure_ms: float
    gain: float
    blur_px: float
    snr: float
    brightness: float
    stickers: int
    detected: float
    read: float
    identified: float
    wrong: float


def _views(cfg: AdviseConfig, smap, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """(T_world_camera, velocity) per view: looking at a sticker from a random heading and offset."""
    out = []
    for _ in range(cfg.frames):
        sid = int(rng.choice(smap.ids))
        xy = smap.xy[smap.row(sid)] + rng.uniform(-0.4, 0.4, 2)
        yaw = rng.uniform(0, 360)
        T = camera_pose_looking_at(xy, cfg.height_m, cfg.pitch_deg, yaw)
        a = math.radians(yaw)
        out.append((T, cfg.speed_mps * np.array([math.cos(a), math.sin(a), 0.0])))
    return out


def advise(cfg: AdviseConfig | None = None, progress: bool = True) -> list[AdviseRow]:
    """Measure every exposure of ``cfg`` on the same simulated views (see the module notes)."""
    cfg = cfg or AdviseConfig()
    camera: Camera = default_camera().scaled(cfg.scale) if cfg.scale != 1 else default_camera()
    smap = grid_map(GridMapConfig(width_m=12.0, depth_m=9.0, seed=cfg.seed))
    bank = build_refs(smap, progress=False)
    rng = np.random.default_rng(cfg.seed)
    views = _views(cfg, smap, rng)
    sensor = SensorConfig()
    rows = []
    total = len(cfg.exposures_ms) * len(views)
    with tqdm(total=total, desc="advise", unit="frame", disable=not progress) as bar:
        for exp_ms in cfg.exposures_ms:
            t = exp_ms * 1e-3
            n = det = read = ident = wrong = 0
            blur, snr, bright, gain = [], [], [], []
            for k, (T, v) in enumerate(views):
                res = render_view(
                    smap,
                    camera,
                    T,
                    cfg.lux,
                    velocity=v,
                    exposure_s=t,
                    seed=cfg.seed * 1000 + k,
                    jpeg_quality=cfg.jpeg_quality,
                )
                blur.append(res.blur_px)
                gain.append(res.gain)
                s = res.mean_signal_e
                snr.append(s / math.sqrt(s + sensor.read_noise_e**2))
                bright.append(res.gain * s / (0.16 * sensor.full_well_e))
                truths = [(int(i), c) for i in smap.ids if (c := true_corners(smap, camera, T, int(i))) is not None]
                truths = [(i, c) for i, c in truths if _inside(c[:4], camera)]
                dets = detect(res.image, camera)
                matches = {m.truth: m for m in match_detections(dets, [c[:4] for _, c in truths])}
                for j, (sid, _) in enumerate(truths):
                    n += 1
                    m = matches.get(j)
                    if m is None:
                        continue
                    det += 1
                    d = dets[m.detection]
                    r = decode(res.image, d, camera)
                    if r.sticker_id is not None:
                        read += r.sticker_id == sid
                        ident += r.sticker_id == sid
                        wrong += r.sticker_id != sid
                        continue
                    near = np.argsort(np.hypot(*(smap.xy - smap.xy[smap.row(sid)]).T))[: cfg.candidates]
                    cands = [int(smap.ids[i]) for i in near]
                    idr = identify(res.image, d, camera, cands, bank)
                    if idr.sticker_id is not None:
                        ident += idr.sticker_id == sid
                        wrong += idr.sticker_id != sid
                bar.update(1)
            f = 1.0 / max(n, 1)
            rows.append(
                AdviseRow(
                    exp_ms,
                    float(np.mean(gain)),
                    float(np.mean(blur)),
                    float(np.mean(snr)),
                    float(np.mean(bright)),
                    n,
                    det * f,
                    read * f,
                    ident * f,
                    wrong * f,
                )
            )
    return rows


def _inside(corners: np.ndarray, camera: Camera, margin: float = 4.0) -> bool:
    return bool(
        np.all(corners[:, 0] >= margin)
        and np.all(corners[:, 0] <= camera.width - 1 - margin)
        and np.all(corners[:, 1] >= margin)
        and np.all(corners[:, 1] <= camera.height - 1 - margin)
    )


def best_row(rows: list[AdviseRow]) -> AdviseRow | None:
    """The exposure giving the most fixes (decoded or identified) among those that gave no wrong ID
    (a wrong sticker ID is the worst failure: no number of right fixes buys one); the shorter one on
    a tie; None when none gives a fix without a wrong ID (the shortest would win the tie at 0 %,
    where more light is the answer)."""
    clean = [r for r in rows if r.wrong == 0 and r.identified > 0]
    return max(clean, key=lambda r: (round(r.identified, 3), -r.exposure_ms)) if clean else None


def format_advice(rows: list[AdviseRow], cfg: AdviseConfig) -> str:
    """The trade-off table and the recommendation."""
    lines = [
        f"{cfg.lux:g} lux, walking {cfg.speed_mps:g} m/s, {cfg.frames} simulated views per setting "
        f"(camera {cfg.height_m:g} m up, {cfg.pitch_deg:g} deg down)",
        f"{'exposure':>9}{'gain':>7}{'blur px':>9}{'SNR':>7}{'bright':>8}{'stickers':>9}"
        f"{'detected':>9}{'read':>7}{'fixes':>7}{'wrong':>7}",
    ]
    for r in rows:
        lines.append(
            f"{r.exposure_ms:>7.2f}ms{r.gain:>7.1f}{r.blur_px:>9.1f}{r.snr:>7.1f}{r.brightness:>8.2f}{r.stickers:>9d}"
            f"{r.detected:>9.0%}{r.read:>7.0%}{r.identified:>7.0%}{r.wrong:>7.0%}"
        )
    b = best_row(rows)
    lines.append(
        "read: decoded; fixes: decoded or identified among the true sticker and its nearest map neighbours; "
        "bright: mean signal / AE target (below 1: gain capped)"
    )
    if b is None and any(r.identified > 0 for r in rows):
        lines.append(
            "no recommendation: every exposure that gives a fix also gave a wrong sticker ID; check the map "
            "(stickers closer than the map says, repeated IDs) before choosing one"
        )
    elif b is None:
        longest = max(r.exposure_ms for r in rows)
        lines.append(
            f"no recommendation: no exposure tried (up to {longest:g} ms) gives a fix; more light, a slower"
            " walk or longer --exposures"
        )
    else:
        lines.append(
            f"recommended: --exposure-ms {b.exposure_ms:g} (gain about {b.gain:.1f}): {b.identified:.0%} of stickers"
            " in view give a fix"
        )
    return "\n".join(lines)
