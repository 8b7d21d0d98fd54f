"""``tagloc eval``: tagloc and the paper's two baselines over a set of simulated walks.

Two presets of walks:

* ``standard`` (the default): ``sessions`` scenarios drawing their conditions from the ranges the
  tracker issue names (illuminance 50-300 lux, speed 0.8-1.6 m/s, sticker spacing 1.2-2.0 m,
  camera pitch 45-70 degrees), every other one with missing and unmapped stickers.
* ``field``: a fixed, seeded set of walks (:data:`FIELD_WALKS`) with the field conditions of issue
  14 on: the torso's lean (always simulated), rolling shutter, camera timing (jitter, isolated and
  burst drops), a map with survey error, missing and unmapped stickers, a 90 s walk with stops,
  turns and returns along the same aisles, and a walk with the less sensitive OV5647 sensor.

Each scenario makes its own map and session with the simulator (cached by scenario), then runs the
localiser modes on the same frames (:func:`score_session`, which :mod:`tagloc.eval.walks` also runs
on sessions one already has). Wrong-ID fixes are counted against the simulator's per-frame ground
truth of which sticker is where in the image. Coverage counts a frame without a pose as a
miss: ``within_10cm_all`` is the share of all delivered frames with a pose within 10 cm.
"""

from __future__ import annotations

import json
import math
import textwrap
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from tagloc.core.errors import InputError
from tagloc.core.jsonfile import DuplicateKey, unique_keys, write_json
from tagloc.core.stickermap import StickerMap
from tagloc.eval.baselines import MODES, make_localiser
from tagloc.eval.consistency import NEES_BLOCK_S, bounds_text, nees_blocks, nees_test
from tagloc.eval.metrics import (
    NEES_999_2DOF,
    TrajectoryErrors,
    error_metrics,
    frames_in_span,
    gt_covers,
    trajectory_errors,
)
from tagloc.io.session import FRAMES_CSV, FRAMES_DIR, SessionReader
from tagloc.pipeline.run import RunLog, run_session

if TYPE_CHECKING:  # the simulator is imported only by the commands that render walks
    from tagloc.sim.simulate import SimConfig


@dataclass
class Scenario:
    """The conditions of one simulated walk."""

    name: str
    seed: int
    lux: float
    speed: float
    spacing: float
    pitch_deg: float
    seconds: float
    missing_fraction: float = 0.0
    unmapped: int = 0
    rolling_shutter: bool = False
    jitter_ms: float = 0.0
    drop_fraction: float = 0.0
    bursts_per_min: float = 0.0
    survey_cm: float = 0.0
    survey_deg: float = 0.0
    sensor: str = "standard"
    map_width_m: float = 24.0
    stop_every_s: float = 12.0
    turn_probability: float = 0.2
    scale: float = 1.0  # the camera's resolution factor (1: 1296 x 972)
    gait_scale: float = 1.0  # the walker's gait motions times this (1: the simulator's walker)

    def conditions(self) -> str:
        """The walk's conditions, short, for the table."""
        parts = [f"{self.lux:.0f} lx {self.speed} m/s {self.spacing} m {self.pitch_deg} deg", f"{self.seconds:g} s"]
        if self.rolling_shutter:
            parts.append("rolling shutter")
        if self.jitter_ms:
            parts.append(f"jitter {self.jitter_ms:g} ms")
        if self.drop_fraction or self.bursts_per_min:
            parts.append(f"drops {100 * self.drop_fraction:g}% + {self.bursts_per_min:g} bursts/min")
        if self.survey_cm or self.survey_deg:
            parts.append(f"survey {self.survey_cm:g} cm {self.survey_deg:g} deg")
        if self.missing_fraction or self.unmapped:
            parts.append(f"{100 * self.missing_fraction:g}% missing, {self.unmapped} unmapped")
        if self.sensor != "standard":
            parts.append(f"sensor {self.sensor}")
        if self.scale != 1:
            parts.append(f"resolution x{self.scale:g}")
        if self.gait_scale != 1:
            parts.append(f"gait x{self.gait_scale:g}")
        return ", ".join(parts)


# The field conditions (issue 14), on in every field walk: a 20-30 ms read-out (Pi camera), +-2 ms
# timestamp jitter, 3-5 % isolated drops and bursts of 3-8 frames, survey error of 1-2 cm and 1-2
# degrees per sticker.
_FIELD = dict(
    rolling_shutter=True, jitter_ms=2.0, drop_fraction=0.04, bursts_per_min=2.0, survey_cm=1.5, survey_deg=1.5
)

#: The field preset: fixed walks (seeds and conditions), each with all field conditions on.
FIELD_WALKS: tuple[Scenario, ...] = (
    Scenario("f00", 2000, 150, 1.3, 1.5, 55.0, 20.0, **_FIELD),
    Scenario("f01", 2001, 60, 1.6, 1.8, 48.0, 20.0, missing_fraction=0.1, unmapped=20, **_FIELD),
    Scenario("f02", 2002, 250, 0.9, 1.3, 65.0, 20.0, **_FIELD),
    # The long walk: a narrow map (three aisles) and few turns off a line, so the walker goes to the
    # end of an aisle, turns round and comes back along it, with a stop every ~10 s.
    Scenario(
        "f03-long",
        2003,
        120,
        1.2,
        1.5,
        55.0,
        90.0,
        missing_fraction=0.1,
        unmapped=20,
        map_width_m=9.0,
        stop_every_s=10.0,
        turn_probability=0.05,
        **_FIELD,
    ),
    Scenario("f04-dim", 2004, 80, 1.3, 1.5, 55.0, 20.0, sensor="ov5647", **_FIELD),
)

#: ``EvalConfig.seed`` s other than 1 moves every field walk's seed by this much times (s - 1):
#: larger than the preset's own seed spread, so no two seeds share a walk.
FIELD_SEED_STEP = 100

#: The resolution factors ``EvalConfig.scale`` accepts (0.1: 130 x 97 px; 2: 2592 x 1944, the Pi
#: camera v1's full sensor).
SCALE_RANGE = (0.1, 2.0)

PRESETS = ("standard", "field")
#: One camera against front + rear on the same walks (:mod:`tagloc.eval.multicam`); not part of "all".
TWO_CAMERA = "two-camera"


@dataclass
class EvalConfig:
    """What ``tagloc eval`` runs.

    Attributes:
        sessions: number of scenarios; conditions are drawn from ``seed``.
        seconds: length of each walk, s.
        out: directory for sessions (cached by scenario), report and plots.
        modes: localiser modes to run ("full", the baselines, "full-live"; see
            :data:`tagloc.eval.baselines.EVAL_MODES`).
        hard: add sessions' pathologies: stickers missing from the floor, stickers not in the map.
        preset: "standard" (``sessions`` walks of ``seconds`` drawn from ``seed``) or "field" (the
            fixed :data:`FIELD_WALKS`; ``sessions``, ``seconds`` and ``hard`` do not apply; a
            ``seed`` other than 1 gives held-out walks with the same conditions, each walk's seed
            moved by :data:`FIELD_SEED_STEP` times ``seed - 1``).
        scale: every walk's camera at this resolution factor (0.5: 648 x 486), the walks otherwise
            as the preset has them.
        gait_scale: every walker's gait motions (bobbing, sway, torso twist and roll, pitch wobble;
            :meth:`tagloc.sim.walk.WalkConfig.with_gait_scale`) times this, the walks otherwise as
            the preset has them: the same figures for a walker who swings more or less than the
            simulator's (:data:`GAIT_SCALE_RANGE`).
    """

    sessions: int = 6
    seconds: float = 20.0
    seed: int = 1
    out: Path = Path("out/eval")
    modes: tuple[str, ...] = MODES
    hard: bool = True
    progress: bool = True
    preset: str = "standard"
    scale: float = 1.0
    gait_scale: float = 1.0


def scenarios(cfg: EvalConfig) -> list[Scenario]:
    """The preset's scenarios (see :func:`_preset_scenarios`), at ``cfg.scale``."""
    lo, hi = SCALE_RANGE
    if not lo <= cfg.scale <= hi:
        raise InputError(f"the resolution factor must be {lo:g}-{hi:g}, got {cfg.scale:g}")
    from tagloc.sim.walk import GAIT_SCALE_RANGE

    glo, ghi = GAIT_SCALE_RANGE
    if not glo <= cfg.gait_scale <= ghi:
        raise InputError(f"the gait's scale must be {glo:g}-{ghi:g}, got {cfg.gait_scale:g}")
    out = _preset_scenarios(cfg)
    return [replace(sc, scale=cfg.scale, gait_scale=cfg.gait_scale) for sc in out]


def _preset_scenarios(cfg: EvalConfig) -> list[Scenario]:
    """The preset's scenarios: the field walks (held-out ones for a ``cfg.seed`` other than 1), or
    (standard) conditions spread over the ranges (stratified, then jittered with ``cfg.seed``)."""
    if cfg.seed < 0:
        raise InputError(f"the seed must be 0 or more, got {cfg.seed}")  # numpy's generators refuse it
    if cfg.preset == "field":
        if cfg.seed == 1:
            return list(FIELD_WALKS)
        # Held-out walks: each field walk's conditions with a fresh seed (walk, map, survey error,
        # noise and timing all follow it), so figures can be checked on walks nothing was tried on.
        off = FIELD_SEED_STEP * (cfg.seed - 1)
        return [replace(sc, seed=sc.seed + off) for sc in FIELD_WALKS]
    if cfg.preset != "standard":
        raise InputError(f"eval: unknown preset {cfg.preset!r} (one of {', '.join(PRESETS)}, all)")
    rng = np.random.default_rng(cfg.seed)
    n = cfg.sessions
    out = []
    # Stratify each range so even a few sessions cover it, and shuffle the pairings.
    strata = [rng.permutation(n) for _ in range(4)]
    for i in range(n):
        u = [(strata[k][i] + rng.uniform()) / n for k in range(4)]
        hard = cfg.hard and i % 2 == 1
        out.append(
            Scenario(
                name=f"s{i:02d}",
                seed=int(cfg.seed * 1000 + i),
                lux=round(50 + 250 * u[0]),
                speed=round(0.8 + 0.8 * u[1], 2),
                spacing=round(1.2 + 0.8 * u[2], 2),
                pitch_deg=round(45 + 25 * u[3], 1),
                seconds=cfg.seconds,
                missing_fraction=0.1 if hard else 0.0,
                unmapped=20 if hard else 0,
            )
        )
    return out


def make_session(sc: Scenario, root: Path, progress: bool) -> Path:
    """Simulate a scenario's session (reused when already made with the same conditions)."""
    from tagloc.sim.simulate import SIM_REVISION, simulate_session

    path = root / "sessions" / sc.name
    stamp = path / "scenario.json"
    made = {**asdict(sc), "simulator": SIM_REVISION}
    for key in ("scale", "gait_scale"):
        if made[key] == 1:
            del made[key]  # as stamped before the factor existed: those walks stay cached
    if stamp.exists() and json.loads(stamp.read_text()) == made and (path / FRAMES_CSV).exists():
        return path
    if path.exists():
        import shutil

        shutil.rmtree(path)
    smap, config = scenario_map_and_config(sc)
    simulate_session(smap, path, config, progress=progress)
    stamp.write_text(json.dumps(made))
    return path


def scenario_map_and_config(sc: Scenario) -> tuple[StickerMap, SimConfig]:
    """The map and simulator configuration a scenario's session is rendered from (see
    :func:`make_session`; :class:`tagloc.sim.simulate.SimScene` re-renders single frames of it)."""
    from tagloc.sim.mapgen import GridMapConfig, grid_map
    from tagloc.sim.simulate import SimConfig
    from tagloc.sim.walk import WalkConfig

    smap = grid_map(
        GridMapConfig(
            width_m=sc.map_width_m,
            depth_m=14.0,
            spacing_min_m=sc.spacing * 0.92,
            spacing_max_m=sc.spacing * 1.08,
            seed=sc.seed,
        )
    )
    config = SimConfig(
        seconds=sc.seconds,
        lux=sc.lux,
        speed_mps=sc.speed,
        seed=sc.seed,
        pitch_deg=sc.pitch_deg,
        missing_fraction=sc.missing_fraction,
        unmapped=sc.unmapped,
        rolling_shutter=sc.rolling_shutter,
        scale=sc.scale,
        walk=WalkConfig(stop_every_s=sc.stop_every_s, turn_probability=sc.turn_probability).with_gait_scale(
            sc.gait_scale
        ),
        **_sensor_conditions(sc),
    )
    return smap, config


def _sensor_conditions(sc: Scenario) -> dict:
    """SimConfig fields for the scenario's camera timing, survey error and sensor (none if off)."""
    out: dict = {}
    if sc.jitter_ms or sc.drop_fraction or sc.bursts_per_min:
        from tagloc.sim.timing import TimingConfig

        out["timing"] = TimingConfig(
            jitter_s=sc.jitter_ms / 1e3, drop_fraction=sc.drop_fraction, bursts_per_min=sc.bursts_per_min
        )
    if sc.survey_cm or sc.survey_deg:
        from tagloc.sim.survey import SurveyConfig

        out["survey"] = SurveyConfig(sigma_m=sc.survey_cm / 100, sigma_deg=sc.survey_deg)
    if sc.sensor != "standard":
        out["sensor_preset"] = sc.sensor
    return out


@dataclass
class VisibleSticker:
    """One sticker of a frame's per-frame truth: its ID, image centre (px, the corners' mean), and
    whether it is mapped and wholly inside the image."""

    id: int
    centre: np.ndarray
    in_map: bool
    inside: bool


def read_frame_truth(session: Path, frames: np.ndarray | None = None) -> list[tuple[int, list[VisibleSticker]]] | None:
    """The per-frame truth of ``groundtruth_frames.jsonl`` as (frame index, its visible stickers) in
    file order, or None for a session without it. What is scored is checked, before any work
    (``tagloc eval --walks`` takes such files from other simulators): a line that is not a JSON
    object with an integer ``index`` and ``visible`` stickers each with an integer ``id`` and four
    finite ``corners`` is refused naming the file and line, and so is a file that does not list
    exactly the session's frames (``frames``: their indices; None: read from the session when
    ``session`` is one, see :func:`_check_truth_covers`)."""
    path = session / GROUNDTRUTH_FRAMES
    if not path.exists():
        return None
    out = []
    try:
        # -sig: a byte-order mark (the file saved by an editor) is not part of the first line.
        with path.open(encoding="utf-8-sig") as f:
            for n, line in enumerate(f, 1):
                if line.strip():
                    out.append(_frame_truth_line(line, f"{path}:{n}"))
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not UTF-8 text") from None
    if frames is None and ((session / FRAMES_CSV).exists() or (session / FRAMES_DIR).is_dir()):
        frames = SessionReader(session).index
    if frames is not None:
        _check_truth_covers(path, out, frames)
    return out


def _check_truth_covers(path: Path, truth: list[tuple[int, list[VisibleSticker]]], frames: np.ndarray) -> None:
    """Refuse per-frame truth that does not list each of the session's ``frames`` once and nothing
    else: a fix in a frame it does not list would be counted as a wrong ID (no sticker there by the
    truth), and one listing other frames is another session's (the simulator writes a record for
    every frame it writes, and only for those). Python sets, not numpy: an index may be any integer."""
    listed: set[int] = set()
    for index, _ in truth:
        if index in listed:
            raise InputError(f"{path}: frame {str(index)[:24]} is listed more than once")
        listed.add(index)
    want = {int(i) for i in np.asarray(frames).ravel()}
    missing = sorted(want - listed)
    if missing:
        more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
        raise InputError(
            f"{path}: lists {len(listed & want)} of the session's {len(want)} frames (none for frame {missing[0]}"
            f"{more}): every fix in a frame it does not list would count as a wrong ID; use the file the"
            " simulator wrote with these frames"
        )
    extra = sorted(listed - want)
    if extra:
        more = f" and {len(extra) - 1} more" if len(extra) > 1 else ""
        raise InputError(
            f"{path}: lists frame {str(extra[0])[:24]}{more} that frames.csv does not: is it another session's?"
        )


def _frame_truth_line(line: str, where: str) -> tuple[int, list[VisibleSticker]]:
    try:
        rec = json.loads(line, object_pairs_hook=unique_keys)
    except DuplicateKey as exc:
        raise InputError(f"{where}: {exc}") from None
    except (ValueError, RecursionError):
        raise InputError(f"{where}: not a JSON object (a line cut short?)") from None
    index = rec.get("index") if isinstance(rec, dict) else None
    if isinstance(index, bool) or not isinstance(index, int):
        raise InputError(f"{where}: want a JSON object with an integer 'index'")
    visible = rec.get("visible", [])
    if not isinstance(visible, list):
        raise InputError(f"{where}: 'visible' is not a list")
    stickers = []
    for v in visible:
        sid = v.get("id") if isinstance(v, dict) else None
        try:
            corners = np.asarray(v.get("corners") if isinstance(v, dict) else None, float)
        except (TypeError, ValueError, OverflowError):
            corners = np.zeros(0)
        if (
            isinstance(sid, bool)
            or not isinstance(sid, int)
            or corners.shape != (4, 2)
            or not np.isfinite(corners).all()
        ):
            raise InputError(f"{where}: a visible sticker wants an integer 'id' and four finite [u, v] 'corners'")
        stickers.append(VisibleSticker(sid, corners.mean(axis=0), bool(v.get("in_map")), bool(v.get("inside"))))
    return index, stickers


def wrong_id_fixes(session: Path, log: RunLog, radius_px: float = 40.0) -> tuple[int, int]:
    """(wrong, checked): accepted fixes whose ID is not the sticker the simulator put there."""
    frames = read_frame_truth(session)
    return (0, 0) if frames is None else wrong_ids_in(frames, log, radius_px)


def wrong_ids_in(
    frames: list[tuple[int, list[VisibleSticker]]], log: RunLog, radius_px: float = 40.0
) -> tuple[int, int]:
    """:func:`wrong_id_fixes` against per-frame truth already read (:func:`read_frame_truth`). A fix
    in a frame the truth does not list is not checked (neither right nor wrong: the truth says
    nothing of it), so ``checked`` is then below the fixes; :func:`read_frame_truth` refuses such a
    file for a session's own frames."""
    truth = {index: [(v.id, v.centre) for v in visible] for index, visible in frames}
    wrong = checked = 0
    for fix in log.fixes:
        if fix["frame"] not in truth:
            continue
        near = [sid for sid, c in truth[fix["frame"]] if np.hypot(*(c - fix["centre"])) < radius_px]
        wrong += fix["id"] not in near
        checked += 1
    return wrong, checked


#: The simulator's per-frame truth of which sticker is where in each image.
GROUNDTRUTH_FRAMES = "groundtruth_frames.jsonl"
#: A wrong ID places its fix by about the distance between the sticker seen and the one named, so
#: a fix further than this share of the map's median nearest-neighbour spacing from the truth
#: counts as a wrong ID by pose; the floor keeps a dense map's bound well above a right fix's error
#: (a few centimetres, a survey error of 2 cm and 2 degrees at 1.5 m included: about 7 cm).
WRONG_ID_SPACING_SHARE = 0.5
WRONG_ID_MIN_M = 0.25


def frames_before_sticker(frames: list[tuple[int, list[VisibleSticker]]] | None) -> int | None:
    """Frames before the first in which a mapped sticker lies wholly in the image, by the
    simulator's per-frame truth (:func:`read_frame_truth`; None for a session without it). No
    localiser has a pose for them without one given from outside: the map is its only reference."""
    if frames is None:
        return None
    n = 0
    for _, visible in frames:
        if any(v.in_map and v.inside for v in visible):
            break
        n += 1
    return n


def wrong_id_distance(smap: StickerMap) -> float:
    """The distance (m) from the truth beyond which :func:`wrong_id_fixes_by_pose` calls a fix's ID
    wrong: ``WRONG_ID_SPACING_SHARE`` of the map's median nearest-neighbour spacing, at least
    ``WRONG_ID_MIN_M``."""
    from scipy.spatial import KDTree

    xy = np.asarray(smap.xy, float)
    if len(xy) < 2:
        return WRONG_ID_MIN_M
    d = KDTree(xy).query(xy, k=2)[0][:, 1]
    return max(WRONG_ID_MIN_M, WRONG_ID_SPACING_SHARE * float(np.median(d)))


def wrong_id_fixes_by_pose(log: RunLog, gt: tuple[np.ndarray, np.ndarray], distance_m: float) -> int:
    """Accepted fixes none of whose body poses (``bodies`` of the fix record) lies within
    ``distance_m`` of the ground truth at the fix's time (linearly interpolated; fixes outside the
    ground truth's time span are not counted): for sessions without the simulator's per-frame
    truth, such as recorded walks scored against a motion-capture trajectory."""
    stamps, T = gt
    if not len(stamps):
        return 0
    gx, gy = T[:, 0, 3], T[:, 1, 3]
    wrong = 0
    for fix in log.fixes:
        t = fix["t"]
        if not gt_covers(np.array([t]), stamps)[0] or not fix.get("bodies"):
            continue
        truth = np.array([np.interp(t, stamps, gx), np.interp(t, stamps, gy)])
        near = min(float(np.hypot(*(np.asarray(b[:2]) - truth))) for b in fix["bodies"])
        wrong += near > distance_m
    return wrong


GAP_BINS_S = (0.0, 1e-6, 0.2, 0.5, 1.0, 2.0, 5.0, math.inf)


def by_time_since_fix(log: RunLog, e: TrajectoryErrors) -> list[list[float]]:
    """Per bin of time since the last accepted fix (``GAP_BINS_S``; the first bin is frames with a
    fix): [frames, sum of squared position error (m^2), sum of position NEES] of the run's scored
    errors ``e``. Sums, so that sessions pool."""
    fix_t = np.unique([f["t"] for f in log.fixes])
    t = e.stamps
    since = np.full(len(t), np.inf)
    if len(fix_t):
        k = np.searchsorted(fix_t, t + 1e-9, side="right") - 1
        since = np.where(k >= 0, t - fix_t[np.clip(k, 0, None)], np.inf)
    b = np.digitize(since, GAP_BINS_S[1:])
    return [
        [int(np.sum(b == i)), float(np.sum(e.position[b == i] ** 2)), float(np.sum(e.nees[b == i]))]
        for i in range(len(GAP_BINS_S) - 1)
    ]


def score_session(
    path: Path, mode: str, progress: bool
) -> tuple[dict, SessionReader, RunLog, tuple[np.ndarray, np.ndarray]]:
    """Run ``mode`` over the session at ``path`` and score it against its ground truth: (the row's
    figures, the session, the run, the ground truth (stamps, T_world_body)). Wrong-ID fixes are
    counted against the simulator's per-frame truth of which sticker is where in the image when the
    session has it, else by pose (:func:`wrong_id_fixes_by_pose`); ``wrong_id_check`` says which."""
    session = SessionReader(path)
    gt = session.groundtruth()
    if gt is None:
        raise InputError(f"{path}: no groundtruth.tum to score against")
    # (run_session runs the frames on one thread each for BLAS and OpenCV: real time means one core
    # of the vest's computer, and the report's per-frame timings are taken inside it.)
    # Read (and checked against the session's frames) before the run: a bad file costs no run.
    truth = read_frame_truth(Path(path), session.index)  # read once: wrong IDs and the frames before a sticker
    loc = make_localiser(mode, session.map, session.rig, map_path=session.path / "map.csv")
    log = run_session(session, localiser=loc, progress=progress)
    log.require_frames(path)  # nothing localised: no figures to report as if something had been
    v = log.valid  # (a skipped frame has none: a frame without a pose, a miss)
    e = trajectory_errors(log.stamps[v], log.poses[v], log.covs[v], *gt)
    m = error_metrics(e)
    in_gt = frames_in_span(log.stamps, gt[0])
    if truth is not None:
        wrong, check = wrong_ids_in(truth, log)[0], "frames"
    else:
        wrong, check = wrong_id_fixes_by_pose(log, gt, wrong_id_distance(session.map)), "pose"
    by_source: dict[str, int] = {}
    for fx in log.fixes:
        by_source[fx["source"]] = by_source.get(fx["source"], 0) + 1
    row = {
        "mode": mode,
        **m,
        "wrong_id_fixes": wrong,
        "wrong_id_check": check,
        "fixes": len(log.fixes),
        "fixes_by_source": by_source,
        "rejected_fixes": len(log.rejected),
        "coverage": float(np.mean(v)) if len(v) else 0.0,
        "frames_run": int(len(log.valid)),
        # A frame without a pose is a miss: the share of the frames the ground truth covers with a
        # pose within 10 cm of it.
        "frames_all": in_gt,
        "frames_before_sticker": frames_before_sticker(truth),
        "within_10cm_all": m["within_10cm"] * m["frames"] / max(in_gt, 1),
        "frame_ms_median": float(np.median(log.frame_ms)) if len(log.frame_ms) else math.nan,
        "tracker_ms_median": float(np.median(log.tracker_ms)) if len(log.tracker_ms) else math.nan,
        "tracker_ms_p95": float(np.percentile(log.tracker_ms, 95)) if len(log.tracker_ms) else math.nan,
        "odometry_ms_median": float(np.median(log.odometry_ms)) if len(log.odometry_ms) else math.nan,
        # What tracking adds to a frame over the per-frame stage: the filter, candidate
        # selection and the floor odometry that feeds it, summed frame by frame.
        "tracking_ms_median": float(np.median(log.tracker_ms + log.odometry_ms)) if len(log.tracker_ms) else math.nan,
        "tracking_ms_p95": float(np.percentile(log.tracker_ms + log.odometry_ms, 95))
        if len(log.tracker_ms)
        else math.nan,
        "by_time_since_fix": by_time_since_fix(log, e),
        "nees_blocks": nees_blocks(e.stamps, e.nees).tolist(),
        "counts": log.counts,
    }
    test = nees_test(np.array(row["nees_blocks"], float))  # the walk judged by its own bounds
    row |= {"nees_bounds_95_effective": list(test.bounds_effective), "nees_verdict": test.verdict}
    return row, session, log, gt


def evaluate(cfg: EvalConfig, walks: list[Scenario] | None = None) -> dict:
    """Run every scenario (the preset's, or ``walks``) and mode; write ``report.md``,
    ``results.json`` and PNG plots under ``cfg.out``."""
    from tqdm import tqdm

    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    plots = []
    for sc in tqdm(scenarios(cfg) if walks is None else walks, desc="eval", unit="session", disable=not cfg.progress):
        path = make_session(sc, out, cfg.progress)
        for mode in cfg.modes:
            row, session, log, gt = score_session(path, mode, cfg.progress)
            rows.append({"session": sc.name, **asdict(sc), **row})
            if mode == "full":
                plots.append(plot_run(session, log, gt, out / f"{sc.name}.png", title=f"{sc.name} ({sc.conditions()})"))
    return write_results(rows, plots, out)


def write_results(rows: list[dict], plots: list[Path], out: Path) -> dict:
    """Pool ``rows`` (:func:`summarise`) and write ``results.json`` and ``report.md`` (with ``plots``)
    into ``out``: {"rows", "summary", "report" (the report's path)}."""
    summary = summarise(rows)
    write_json(out / "results.json", {"rows": rows, "summary": summary})
    (out / "report.md").write_text(report_markdown(rows, summary, plots, out), encoding="utf-8")
    return {"rows": rows, "summary": summary, "report": str(out / "report.md")}


def _pooled(rows: list[dict], key: str, squared: bool = False) -> float:
    """``key`` pooled over ``rows`` by scored frames (RMS when ``squared``); a walk with none scored
    has no figures (NaN) and no weight; NaN when no walk has any."""
    scored = [r for r in rows if r["frames"] > 0]
    if not scored:
        return math.nan
    w = np.array([r["frames"] for r in scored], float)
    w = w / w.sum()
    v = np.array([r[key] for r in scored], float)
    return float(np.sqrt(np.sum(w * v**2))) if squared else float(np.sum(w * v))


def summarise(rows: list[dict]) -> dict:
    """Overall figures per mode (errors pooled by frame over all sessions)."""
    summary = {}
    for mode in dict.fromkeys(r["mode"] for r in rows):
        rs = [r for r in rows if r["mode"] == mode]
        # The walk with the largest RMSE among those with a scored frame ({}: none had one).
        worst = max((r for r in rs if r["frames"] > 0), key=lambda r: r["rmse_m"], default={})
        summary[mode] = {
            "rmse_m": _pooled(rs, "rmse_m", squared=True),
            "within_10cm": _pooled(rs, "within_10cm"),
            "within_25cm": _pooled(rs, "within_25cm"),
            "heading_rmse_deg": _pooled(rs, "heading_rmse_deg", squared=True),
            "nees_mean": _pooled(rs, "nees_mean"),
            # (rows scored before the figure existed have none: then neither has the pool)
            "beyond_999": _pooled(rs, "beyond_999") if all("beyond_999" in r for r in rs) else math.nan,
            **_nees_summary(rs),
            "wrong_id_fixes": int(sum(r["wrong_id_fixes"] for r in rs)),
            "fixes": int(sum(r["fixes"] for r in rs)),
            "rejected_fixes": int(sum(r["rejected_fixes"] for r in rs)),
            "coverage": float(
                np.sum([r["coverage"] * r["frames_run"] for r in rs]) / max(sum(r["frames_run"] for r in rs), 1)
            ),
            "within_10cm_all": float(
                np.sum([r["within_10cm_all"] * r["frames_all"] for r in rs]) / max(sum(r["frames_all"] for r in rs), 1)
            ),
            # The most of all frames any localiser could place: none before a sticker is in view.
            "within_10cm_reachable": _reachable(rs),
            # (not nanmax: a mode no walk of which had a scored frame has no worst walk, and no warning)
            "worst_rmse_m": worst.get("rmse_m", math.nan),
            "worst_walk": worst.get("session"),
            "tracker_ms_median": float(np.median([r["tracker_ms_median"] for r in rs])),
            "tracker_ms_p95": float(np.median([r["tracker_ms_p95"] for r in rs])),
            "odometry_ms_median": float(np.median([r["odometry_ms_median"] for r in rs])),
            "tracking_ms_median": float(np.median([r["tracking_ms_median"] for r in rs])),
            "tracking_ms_p95": float(np.median([r["tracking_ms_p95"] for r in rs])),
            "frame_ms_median": float(np.median([r["frame_ms_median"] for r in rs])),
            "by_time_since_fix": np.sum([r["by_time_since_fix"] for r in rs], axis=0).tolist(),
        }
    return summary


def _reachable(rows: list[dict]) -> float:
    """The share of the rows' frames after a mapped sticker first lies wholly in view (NaN when a
    row does not know when that was)."""
    before = [r.get("frames_before_sticker") for r in rows]
    if any(b is None for b in before):
        return math.nan
    total = sum(r["frames_all"] for r in rows)
    return 1.0 - sum(before) / total if total else math.nan


def _nees_summary(rows: list[dict]) -> dict:
    """Pooled NEES test of the rows (see :mod:`tagloc.eval.consistency`): bounds for independent frames and
    for the effective number of independent samples, and the verdict."""
    blocks = [b for r in rows for b in r.get("nees_blocks", [])]
    test = nees_test(np.array(blocks, float).reshape(-1, 3))
    return {
        "nees_bounds_95": list(test.bounds_independent),
        "nees_effective_samples": test.effective_samples,
        "nees_bounds_95_effective": list(test.bounds_effective),
        "nees_verdict": test.verdict,
    }


def run_presets(cfg: EvalConfig, preset: str) -> str:
    """Evaluate ``preset`` ("standard", "field" or "all": both, into ``cfg.out``/standard and
    ``cfg.out``/field) and return the text to print: each preset's table and notes, then (for all)
    both presets' summaries. "two-camera" runs :func:`tagloc.eval.multicam.run_two_camera` into
    ``cfg.out`` (its own table; ``modes``, ``sessions``, ``seconds`` and ``seed`` do not apply)."""
    if preset == TWO_CAMERA:
        from tagloc.eval.multicam import TWO_CAMERA_WALKS, run_two_camera

        return run_two_camera(replace(TWO_CAMERA_WALKS, out=Path(cfg.out), progress=cfg.progress))
    presets = PRESETS if preset == "all" else (preset,)
    parts, summaries = [], []
    for p in presets:
        out = Path(cfg.out) / p if preset == "all" else Path(cfg.out)
        res = evaluate(replace(cfg, preset=p, out=out))
        parts += [f"## {p}", "", format_table(res["rows"], res["summary"]), "", format_notes(res["summary"])]
        parts += ["", f"report: {res['report']}", ""]
        summaries.append(format_summary(p, res["summary"]))
    if len(presets) > 1:
        parts += ["## Summary", ""] + ["\n\n".join(summaries)]
    return "\n".join(parts)


def format_table(rows: list[dict], summary: dict) -> str:
    """The terminal/Markdown table of per-session and overall figures."""
    head = (
        "| session | mode | conditions | RMSE cm | median cm | p95 cm | max cm | heading deg | <10 cm | <25 cm |"
        " fixes (by source) | rejected | wrong IDs | NEES [95% bounds (effective)] verdict | covered |"
        " <10 cm of all frames |"
    )
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        src = " ".join(f"{k[:3]}:{v}" for k, v in sorted(r["fixes_by_source"].items())) or "-"
        lines.append(
            f"| {r['session']} | {r['mode']} | {_conditions(r)} |"
            f" {100 * r['rmse_m']:.1f} | {100 * r['median_m']:.1f} | {100 * r['p95_m']:.1f} | {100 * r['max_m']:.1f} |"
            f" {r['heading_rmse_deg']:.2f} | {100 * r['within_10cm']:.0f}% | {100 * r['within_25cm']:.0f}% |"
            f" {r['fixes']} ({src}) | {r['rejected_fixes']} | {r['wrong_id_fixes']} | {_nees_cell(r)} |"
            f" {100 * r['coverage']:.0f}% | {100 * r['within_10cm_all']:.1f}% |"
        )
    for mode, s in summary.items():
        lines.append(
            f"| **all** | {mode} | | **{100 * s['rmse_m']:.1f}** | | | | {s['heading_rmse_deg']:.2f} |"
            f" {_percent(s['within_10cm'])} | {_percent(s['within_25cm'])} | {s['fixes']} | {s['rejected_fixes']} |"
            f" **{s['wrong_id_fixes']}** | {_nees_cell(s)} | {100 * s['coverage']:.0f}% |"
            f" {100 * s['within_10cm_all']:.1f}% |"
        )
    return "\n".join(lines)


def _nees_cell(r: dict) -> str:
    """Mean NEES with its effective-sample bounds and verdict (a row from before them: the mean alone)."""
    verdict = r.get("nees_verdict")
    if verdict is None or verdict == "no data":
        return f"{r['nees_mean']:.2f}"
    if verdict == "too short":
        return f"{r['nees_mean']:.2f} (one {NEES_BLOCK_S:g} s block: too short)"
    return f"{r['nees_mean']:.2f} {bounds_text(r['nees_bounds_95_effective'])} {verdict}{_beyond_text(r)}"


def _beyond_text(r: dict) -> str:
    """ ", x.x% beyond 99.9%": the share of frames whose NEES exceeds chi-square's 99.9 % point (0.1 %
    for a consistent filter); empty for a row without the figure."""
    share = r.get("beyond_999", math.nan)
    return "" if math.isnan(share) else f", {_share(share)} beyond 99.9%"


def _share(share: float) -> str:
    """A share with one decimal of a percent, "-" for NaN."""
    return "-" if math.isnan(share) else f"{100 * share:.1f}%"


def _percent(share: float) -> str:
    """A share of scored frames as a whole percentage, "-" where no frame was scored (NaN)."""
    return "-" if math.isnan(share) else f"{100 * share:.0f}%"


def _conditions(row: dict) -> str:
    """A row's conditions: its own (a scored session's), else its scenario's."""
    return row.get("conditions") or Scenario(**_scenario_fields(row)).conditions()


def _scenario_fields(row: dict) -> dict:
    """The :class:`Scenario` fields of a result row."""
    return {f: row[f] for f in Scenario.__dataclass_fields__ if f in row}


def format_summary(preset: str, summary: dict) -> str:
    """One preset's overall figures per mode, against issue 14's targets, as Markdown lines."""
    lines = [
        f"### {preset}",
        "",
        "| mode | RMSE cm | worst walk cm | <10 cm of all frames | (reachable) | heading deg | NEES |"
        " 95% bounds (effective) | verdict | frames beyond 99.9% | wrong IDs |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for mode, s in summary.items():
        # Two decimals: a bound of 98.97 % must not print as the 99 % goal.
        reach = s.get("within_10cm_reachable", math.nan)
        bounds = "-" if s["nees_verdict"] == "no data" else bounds_text(s["nees_bounds_95_effective"])
        worst = f"{100 * s['worst_rmse_m']:.2f}" + (f" ({s['worst_walk']})" if s.get("worst_walk") else "")
        lines.append(
            f"| {mode} | {100 * s['rmse_m']:.2f} | {worst} | {100 * s['within_10cm_all']:.1f}% |"
            f" {'-' if math.isnan(reach) else f'{100 * reach:.2f}%'} |"
            f" {s['heading_rmse_deg']:.2f} | {s['nees_mean']:.2f} | {bounds} |"
            f" {s['nees_verdict']} |"
            f" {_share(s.get('beyond_999', math.nan))} |"
            f" {s['wrong_id_fixes']} |"
        )
    return "\n".join(lines)


def format_notes(summary: dict) -> str:
    """Consistency (NEES against its bounds) and timing per mode, as Markdown lines."""
    parts = ["## Consistency", ""]
    for mode, s in summary.items():
        lo, hi = s["nees_bounds_95"]
        if s["nees_verdict"] == "no data":
            parts.append(f"- {mode}: no frame with a pose inside the ground truth's time span, so no NEES to test")
            continue
        effective = (
            f"95% bounds {bounds_text(s['nees_bounds_95_effective'])} for the {s['nees_effective_samples']:.0f}"
            " independent samples the frames are worth (batch means)"
            if s["nees_verdict"] != "too short"
            else f"one {NEES_BLOCK_S:g} s block, too short to say how many independent samples the frames are worth"
        )
        parts.append(
            f"- {mode}: mean position NEES {s['nees_mean']:.2f} (2 DoF), **{s['nees_verdict']}**: {effective};"
            f" [{lo:.2f}, {hi:.2f}] if every frame were independent, which they are"
            f" not (below the bounds: conservative; above: overconfident)"
        )
        share = s.get("beyond_999", math.nan)
        if not math.isnan(share):
            # The mean over a walk can hide a stretch stated surer than it was: frame by frame too.
            parts.append(
                f"  - frames whose NEES is beyond chi-square's 99.9% point ({NEES_999_2DOF:.1f}):"
                f" {100 * share:.2f}% (0.1% for a consistent filter)"
            )
    full = summary.get("full")
    if full is not None and full.get("by_time_since_fix"):
        parts += [
            "",
            "Position error and NEES of `full` by time since the last accepted fix (all sessions pooled):",
            "",
            "| since last fix | frames | RMSE cm | NEES |",
            "|---|---|---|---|",
        ]
        for i, (n, sq, ne) in enumerate(full["by_time_since_fix"]):
            lo, hi = GAP_BINS_S[i], GAP_BINS_S[i + 1]
            label = (
                "fix in this frame"
                if i == 0
                else (f"> {lo:g} s" if math.isinf(hi) else f"{lo if lo >= 1e-3 else 0:g}-{hi:g} s")
            )
            if n:
                parts.append(f"| {label} | {int(n)} | {100 * math.sqrt(sq / n):.1f} | {ne / n:.2f} |")
    parts += ["", "## Timing (per frame)", ""]
    for mode, s in summary.items():
        parts.append(
            f"- {mode} (each figure the median over the walks of each walk's own):"
            f" median frame {s['frame_ms_median']:.1f} ms, of which tracker {s['tracker_ms_median']:.2f} ms"
            f" (p95 {s['tracker_ms_p95']:.2f} ms) and floor odometry {s['odometry_ms_median']:.2f} ms;"
            f" tracking in all (tracker + odometry, per frame) {s['tracking_ms_median']:.2f} ms"
            f" (p95 {s['tracking_ms_p95']:.2f} ms; target: at most 2 ms over the per-frame stage)"
        )
    return "\n".join(parts)


def report_markdown(rows: list[dict], summary: dict, plots: list[Path], out: Path) -> str:
    """The Markdown report: conditions, the table, timing, and the plots."""
    parts = [
        "# tagloc eval",
        "",
        "Modes: `full` = tagloc (EKF + candidate identification); `decoded-only` = the paper's"
        " decoded fixes without a filter; `orb-all` = the paper's ORB identification against every reference.",
        "Errors are horizontal position errors of the body (the vest point on the floor) against the simulator's"
        " ground truth, over the frames where the mode had a pose (`covered`; the last column counts a frame"
        " without a pose as a miss). NEES is the mean normalised position error (2 DoF; its 95%"
        " bounds depend on how many independent samples the correlated frames are worth, see"
        " `tagloc/eval/consistency.py`).",
        "",
        format_table(rows, summary),
    ]
    parts += ["", format_notes(summary)]
    parts += ["", "## Plots", ""]
    parts += [f"![{p.stem}]({p.relative_to(out)})" for p in plots if p is not None]
    return "\n".join(parts) + "\n"


def plot_run(
    session: SessionReader, log: RunLog, gt: tuple[np.ndarray, np.ndarray] | None, path: Path, title: str = ""
) -> Path | None:
    """Trajectory over the map, and error over time with the 2-sigma band, as one PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from tagloc.eval.metrics import trajectory_errors

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(13, 5), gridspec_kw={"width_ratios": [1.3, 1]})
    ax0.scatter(session.map.xy[:, 0], session.map.xy[:, 1], s=6, c="0.6", marker="s", label="stickers")
    v = log.valid
    if gt is not None:
        gx = np.array([T[0, 3] for T in gt[1]])
        gy = np.array([T[1, 3] for T in gt[1]])
        ax0.plot(gx, gy, "k-", lw=1.2, label="ground truth")
    ax0.plot(log.poses[v, 0], log.poses[v, 1], "-", c="tab:blue", lw=1, label="tagloc")
    fx = np.array([log.poses[np.searchsorted(log.stamps, f["t"])][:2] for f in log.fixes]) if log.fixes else None
    if fx is not None and len(fx):
        ax0.plot(fx[:, 0], fx[:, 1], ".", c="tab:green", ms=4, label="after a fix")
    if gt is not None and v.any():
        ax0.set_xlim(min(gx.min(), log.poses[v, 0].min()) - 1.5, max(gx.max(), log.poses[v, 0].max()) + 1.5)
        ax0.set_ylim(min(gy.min(), log.poses[v, 1].min()) - 1.5, max(gy.max(), log.poses[v, 1].max()) + 1.5)
    ax0.set_aspect("equal")
    ax0.set_xlabel("x (m)")
    ax0.set_ylabel("y (m)")
    ax0.legend(loc="best", fontsize=8)
    ax0.set_title(textwrap.fill(title, 70), fontsize=9)  # a field walk's conditions run long
    e = trajectory_errors(log.stamps[v], log.poses[v], log.covs[v], *gt) if gt is not None and v.any() else None
    if e is not None and len(e.position):  # (no estimate inside the ground truth's span: no error plot)
        covs = log.covs[v][e.inside]
        sig = np.sqrt(np.maximum(np.linalg.eigvalsh(covs[:, :2, :2])[:, 1], 0))
        ax1.fill_between(e.stamps, 0, 100 * 2 * sig, color="tab:blue", alpha=0.2, label="2 sigma (major axis)")
        ax1.plot(e.stamps, 100 * e.position, c="tab:red", lw=1, label="position error")
        for f in log.fixes:
            ax1.axvline(f["t"], c="tab:green", lw=0.3, alpha=0.5)
        ax1.set_ylim(0, max(30.0, float(np.percentile(100 * e.position, 99)) * 1.2))
        ax1.legend(loc="upper right", fontsize=8)
        ax1.set_title("error and stated uncertainty (green: fixes)", fontsize=9)
    else:
        ax1.set_title("no estimate inside the ground truth's time span", fontsize=9)
    ax1.set_xlabel("time (s)")
    ax1.set_ylabel("cm")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
