"""The vest as the map's auditor: missing, unmapped, misplaced and hard-to-read stickers from recorded walks.

From the walks' sightings (:mod:`tagloc.eval.mapobs`):

- **missing**: mapped stickers that the tracked pose put fully inside the image and within detection
  range on several passes, never identified and (almost) never detected where they should be;
- **unmapped**: decoded stickers that are not in the map, placed through the tracked pose and the
  sticker's pose in the camera, with an uncertainty, ready to add; those decoded only while the
  track was lost are listed without a position (with the wrong map nothing is ever tracked, and
  the IDs that the walks read but the map lacks are what shows it);
- **misplaced**: mapped stickers whose survey prior the joint refinement (:mod:`tagloc.eval.maprefine`)
  rejected: the rest of the walk puts them elsewhere, by the estimated offset;
- **hard to read**: stickers detected often but decoded far less often than the others (worn, dirty).

The checks of "in view" use the camera pose that the frame's nearest accepted fix measured, and
only in frames without one the body pose the tracker published through the nominal rig (the torso
leans 6-9 deg in turns, which the rig does not know); a margin in pixels covers the rest (the fix's
error, the vest's wobble where there is no fix). A sticker counts only with every corner short of
the angle where the lens's distortion polynomial folds back into the image
(:meth:`tagloc.core.camera.Camera.project_in_view`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from tagloc.core.geometry import invert, planar_from_T, planar_T, wrap_angle
from tagloc.core.jsonfile import write_json
from tagloc.core.sticker import OUTER_CORNERS
from tagloc.core.stickermap import StickerMap, save_map
from tagloc.eval.mapobs import FrameRecord, WalkLog, collect_walks, frames_text, walks_skipped
from tagloc.eval.maprefine import RefineConfig, RefineResult, refine_map, residual_text


@dataclass
class AuditConfig:
    """Thresholds of :func:`audit_walks`.

    Attributes:
        max_pose_sigma_m: frames are used for "in view" checks and for placing stickers only while
            the tracked position sigma (larger axis) is below this: a 5 cm error moves a sticker's
            projection by ~40 px at 1.5 m, within ``margin_px``.
        max_distance_m: a sticker counts as in view only up to this distance from the camera: the
            bench detects 95 % of stickers at 2.5 m and fewer beyond.
        margin_px: the projected outer corners must be this far inside the image: the vest's wobble
            (about 2 deg of yaw and 1 deg of pitch RMS) moves the view by ~40 px against the nominal
            rig, which frames without an accepted fix use; a fix's camera pose is within 0.45 deg
            (95th percentile, ~10 px) on simulated walks.
        match_px: a detection within this distance of a sticker's predicted centre counts as it
            (the same wobble and pose error).
        pass_gap_s: in-view frames further apart than this start a new pass.
        min_missing_passes: passes with the sticker in view needed to call it missing ("several").
        min_pass_frames: in-view frames for a pass to count (a sixth of a second at 30 fps: one
            frame at the image's edge is no chance to see it).
        max_missing_detect_fraction: a missing sticker may have had a detection near its predicted
            place in at most this share of its in-view frames (distractors, floor marks).
        hard_min_detections: frames with a detection needed before judging readability.
        hard_max_relative_rate: hard to read when the decode rate is below this share of the
            median decode rate of the stickers seen as often (the same walks' blur and light).
        min_tracked_fraction: a walk with fewer of its frames tracked (as above) than this share
            checked next to nothing of the map, and the audit says so instead of an all-clear (the
            CLI exits 2): the map is not this floor's, or the walk was off the mapped floor or
            too dark to read. A walk on the mapped floor is tracked from its first fixes on:
            simulated walks were tracked in 100 % of their frames on the 0.4 m strip and 66-97 % on
            an aisle with stickers 1.5 m apart (the 66 % walk reached its first sticker after
            3.3 s); with a map of another floor, in none. A fifth leaves room for a walk that
            starts or strays off the mapped floor.
        refine: the joint refinement that finds misplaced stickers.
    """

    max_pose_sigma_m: float = 0.05
    max_distance_m: float = 2.5
    margin_px: float = 40.0
    match_px: float = 60.0
    pass_gap_s: float = 1.0
    min_missing_passes: int = 2
    min_pass_frames: int = 5
    max_missing_detect_fraction: float = 0.1
    hard_min_detections: int = 10
    hard_max_relative_rate: float = 0.4
    min_tracked_fraction: float = 0.2
    refine: RefineConfig = field(default_factory=RefineConfig)


@dataclass
class Finding:
    """One sticker in one class of the audit.

    Attributes:
        kind: "missing", "unmapped", "misplaced" or "hard".
        sticker_id: the ID.
        x, y, yaw: map position (missing, hard), estimated position (unmapped, misplaced); m, rad.
        sigma_m, sigma_deg: uncertainty of an estimated position (per axis, m) and yaw (deg).
        offset: (dx, dy, dyaw_deg) from the map to the estimate (misplaced).
        passes, frames: passes and frames with evidence.
        detail: counts behind the verdict.
        evidence: "walk:frame" of the frames that show it (all, in order).
    """

    kind: str
    sticker_id: int
    x: float
    y: float
    yaw: float
    sigma_m: float = float("nan")
    sigma_deg: float = float("nan")
    offset: tuple[float, float, float] | None = None
    passes: int = 0
    frames: int = 0
    detail: str = ""
    evidence: list[str] = field(default_factory=list)


@dataclass
class AuditResult:
    """Everything the audit found, and the walks it used.

    ``walk_frames``, ``walk_tracked``: per walk, its frames and those tracked well enough to check
    the map against; ``unchecked``: the walks with too few of those (``min_tracked_fraction``).
    ``skipped``: why each frame the localiser skipped was (unreadable, the wrong size, a bad time),
    "walk: frame N: ..." each.
    """

    map: StickerMap
    walks: list[str]
    frames: int
    tracked_frames: int
    findings: list[Finding]
    refine: RefineResult | None
    trajectories: list[np.ndarray]  # per walk (N, 2) tracked positions used
    walk_frames: list[int] = field(default_factory=list)
    walk_tracked: list[int] = field(default_factory=list)
    min_tracked_fraction: float = AuditConfig.min_tracked_fraction
    skipped: list[str] = field(default_factory=list)

    def of(self, kind: str) -> list[Finding]:
        return [f for f in self.findings if f.kind == kind]

    @property
    def unchecked(self) -> list[str]:
        """The walks tracked in under ``min_tracked_fraction`` of their frames."""
        per = zip(self.walks, self.walk_frames, self.walk_tracked)
        return [name for name, n, k in per if k < self.min_tracked_fraction * n]

    @property
    def unplaced(self) -> list[Finding]:
        """Unmapped stickers decoded only while the track was lost: IDs without a position."""
        return [f for f in self.of("unmapped") if not math.isfinite(f.x)]

    def unchecked_text(self) -> str:
        """What the walks in ``unchecked`` were, in one sentence (empty when there are none)."""
        if not self.unchecked:
            return ""
        per = [
            f"{name} {k} of {n}"
            for name, n, k in zip(self.walks, self.walk_frames, self.walk_tracked)
            if name in self.unchecked
        ]
        return ", ".join(per) + " frames tracked"


def _tracked(fr: FrameRecord, config: AuditConfig) -> bool:
    if fr.state != "tracking" or fr.skipped:
        return False
    return float(np.sqrt(max(np.linalg.eigvalsh(fr.cov[:2, :2]).max(), 0.0))) < config.max_pose_sigma_m


def _passes(times: list[float], gap_s: float) -> list[list[int]]:
    """Split the indices of sorted ``times`` into runs no more than ``gap_s`` apart."""
    runs: list[list[int]] = []
    for k, t in enumerate(times):
        if runs and t - times[runs[-1][-1]] <= gap_s:
            runs[-1].append(k)
        else:
            runs.append([k])
    return runs


def _camera_pose(walk: WalkLog, fr: FrameRecord, smap: StickerMap) -> np.ndarray:
    """T_world_camera of the frame's camera: as its nearest accepted fix measured it, else the
    tracked body pose through the nominal mount.

    The torso leans 6-9 deg in turns, so the nominal mount can put a sticker well inside the image
    that was outside it (on two simulated 5 s walks: camera rotation error against the truth 8.8 deg
    at the 95th percentile through the mount, 0.45 deg from the nearest accepted fix). The nearest
    sticker gives the best-conditioned pose; the tracker accepted it, so it agrees with the track.
    """
    fixes = [
        s
        for s in fr.sightings
        if s.accepted is True and s.in_map and s.camera == fr.camera and s.T_camera_sticker is not None
    ]
    if fixes:
        s = min(fixes, key=lambda s: float(np.linalg.norm(s.T_camera_sticker[:3, 3])))
        return smap.T_world_sticker(int(s.sticker_id)) @ invert(s.T_camera_sticker)
    return planar_T(*fr.pose) @ walk.rig[fr.camera].T_body_camera


def _expected(walk: WalkLog, fr: FrameRecord, smap: StickerMap, config: AuditConfig) -> list[tuple[int, np.ndarray]]:
    """(map row, predicted centre px) of the stickers fully in view of the frame's camera (the one
    that took it) at its measured or tracked pose (:func:`_camera_pose`)."""
    cam = walk.rig[fr.camera].camera
    T_camera_world = invert(_camera_pose(walk, fr, smap))
    rows = smap.within(fr.pose[0], fr.pose[1], config.max_distance_m + 1.0)
    out = []
    for row in rows:
        pts = (T_camera_world @ smap.T_world_sticker(int(smap.ids[row])))[:3] @ np.vstack(
            [OUTER_CORNERS.T, np.ones((1, 4))]
        )
        if np.linalg.norm(pts.mean(axis=1)) > config.max_distance_m:
            continue
        # Far outside the field of view the distortion polynomial folds back into the image:
        # only corners short of the fold have pixels to test against the image's bounds.
        px = cam.project_in_view(pts.T)
        if px is None:
            continue
        m = config.margin_px
        if np.all(
            (px[:, 0] >= m) & (px[:, 0] <= cam.width - 1 - m) & (px[:, 1] >= m) & (px[:, 1] <= cam.height - 1 - m)
        ):
            out.append((int(row), px.mean(axis=0)))
    return out


def _sticker_in_world(walk: WalkLog, fr: FrameRecord, camera: int, T_camera_sticker: np.ndarray) -> np.ndarray:
    T = planar_T(*fr.pose) @ walk.rig[camera].T_body_camera @ T_camera_sticker
    return np.array(planar_from_T(T))


def _unmapped(walks: list[WalkLog], smap: StickerMap, config: AuditConfig) -> list[Finding]:
    samples: dict[int, list[tuple[float, str, np.ndarray, float]]] = {}
    reads: dict[int, list[str]] = {}  # every frame that decoded it, tracked or not
    for walk in walks:
        for fr in walk.frames:
            for s in fr.sightings:
                if s.decoded and not s.in_map and s.sticker_id is not None:
                    reads.setdefault(int(s.sticker_id), []).append(f"{walk.name}:{fr.index}")
            if not _tracked(fr, config):
                continue
            pos_var = float(np.linalg.eigvalsh(fr.cov[:2, :2]).max())
            for s in fr.sightings:
                if s.decoded and not s.in_map and s.T_camera_sticker is not None:
                    est = _sticker_in_world(walk, fr, s.camera, s.T_camera_sticker)
                    samples.setdefault(int(s.sticker_id), []).append((fr.t, f"{walk.name}:{fr.index}", est, pos_var))
    out = []
    for sid, rows in sorted(samples.items()):
        est = np.array([r[2] for r in rows])
        yaw = math.atan2(np.sin(est[:, 2]).mean(), np.cos(est[:, 2]).mean())
        xy = est[:, :2].mean(axis=0)
        by_walk: dict[str, list[float]] = {}
        for t, ev, _, _ in rows:
            by_walk.setdefault(ev.split(":")[0], []).append(t)
        n_pass = sum(len(_passes(sorted(ts), config.pass_gap_s)) for ts in by_walk.values())
        # Frames of one pass share the pose error and the vest's tilt: only passes are independent.
        scatter = np.var(est[:, :2], axis=0).max() if len(est) > 1 else 0.0
        sigma_m = math.sqrt(scatter / n_pass + float(np.mean([r[3] for r in rows])))
        dyaw = wrap_angle(est[:, 2] - yaw)
        sigma_deg = math.degrees(math.sqrt(float(np.mean(dyaw**2)) / n_pass + 1e-8))
        out.append(
            Finding(
                "unmapped",
                sid,
                float(xy[0]),
                float(xy[1]),
                float(yaw),
                sigma_m,
                sigma_deg,
                passes=n_pass,
                frames=len(rows),
                detail=f"decoded in {len(rows)} frames on {n_pass} passes",
                evidence=[r[1] for r in rows],
            )
        )
    # Read, but never in a tracked frame: no position to give, but the ID is not in the map (with
    # the wrong map nothing is tracked, and these IDs are what says so).
    for sid in sorted(set(reads) - set(samples)):
        out.append(
            Finding(
                "unmapped",
                sid,
                math.nan,
                math.nan,
                math.nan,
                frames=len(reads[sid]),
                detail=f"decoded in {len(reads[sid])} frames, none tracked: no position",
                evidence=reads[sid],
            )
        )
    return out


@dataclass
class _Tally:
    in_view: list[tuple[float, str, bool]] = field(default_factory=list)  # (t, evidence, detected nearby)
    identified: int = 0
    detected: int = 0
    decoded: int = 0
    gated: int = 0
    walks: set[str] = field(default_factory=set)
    frames: list[str] = field(default_factory=list)


def _tally(walks: list[WalkLog], smap: StickerMap, config: AuditConfig) -> dict[int, _Tally]:
    """Per mapped sticker: in-view frames (and whether something was detected there), sightings, reads."""
    tally: dict[int, _Tally] = {int(i): _Tally() for i in smap.ids}
    for walk in walks:
        for fr in walk.frames:
            ev = f"{walk.name}:{fr.index}"
            seen_here: set[int] = set()
            for s in fr.sightings:
                if s.sticker_id is not None and s.in_map:
                    tl = tally[int(s.sticker_id)]
                    tl.identified += 1
                    tl.decoded += s.decoded
                    tl.gated += s.accepted is False
                    tl.frames.append(ev)
                    seen_here.add(int(s.sticker_id))
            if not _tracked(fr, config):
                for sid in seen_here:
                    tally[sid].detected += 1
                continue
            unnamed = [s.centre_px for s in fr.sightings if s.sticker_id is None and s.camera == fr.camera]
            for row, centre in _expected(walk, fr, smap, config):
                sid = int(smap.ids[row])
                near = any(np.hypot(*(px - centre)) < config.match_px for px in unnamed)
                tally[sid].in_view.append((fr.t, ev, near or sid in seen_here))
                if near and sid not in seen_here:
                    tally[sid].detected += 1
            for sid in seen_here:
                tally[sid].detected += 1
    return tally


def _missing(tally: dict[int, _Tally], smap: StickerMap, config: AuditConfig) -> list[Finding]:
    out = []
    for sid, tl in tally.items():
        if tl.identified or not tl.in_view:
            continue
        by_walk: dict[str, list[tuple[float, str, bool]]] = {}
        for rec in tl.in_view:
            by_walk.setdefault(rec[1].split(":")[0], []).append(rec)
        n_pass = sum(
            sum(len(run) >= config.min_pass_frames for run in _passes([r[0] for r in recs], config.pass_gap_s))
            for recs in by_walk.values()
        )
        near = sum(r[2] for r in tl.in_view)
        if n_pass >= config.min_missing_passes and near <= config.max_missing_detect_fraction * len(tl.in_view):
            row = smap.row(sid)
            out.append(
                Finding(
                    "missing",
                    sid,
                    float(smap.xy[row, 0]),
                    float(smap.xy[row, 1]),
                    float(smap.yaw[row]),
                    passes=n_pass,
                    frames=len(tl.in_view),
                    detail=f"in view in {len(tl.in_view)} frames on {n_pass} passes, never identified,"
                    f" a detection near its place in {near}",
                    evidence=[r[1] for r in tl.in_view],
                )
            )
    return out


def _hard(tally: dict[int, _Tally], smap: StickerMap, config: AuditConfig) -> list[Finding]:
    often = {sid: tl for sid, tl in tally.items() if tl.detected >= config.hard_min_detections}
    if not often:
        return []
    rates = {sid: tl.decoded / tl.detected for sid, tl in often.items()}
    median = float(np.median(list(rates.values())))
    out = []
    for sid, tl in often.items():
        if rates[sid] < config.hard_max_relative_rate * median:
            row = smap.row(sid)
            out.append(
                Finding(
                    "hard",
                    sid,
                    float(smap.xy[row, 0]),
                    float(smap.xy[row, 1]),
                    float(smap.yaw[row]),
                    frames=tl.detected,
                    detail=f"detected in {tl.detected} frames, decoded in {tl.decoded} ({rates[sid]:.0%};"
                    f" median of the stickers seen as often {median:.0%})",
                    evidence=tl.frames,
                )
            )
    return out


def _misplaced(refined: RefineResult, tally: dict[int, _Tally]) -> list[Finding]:
    out = []
    for c in refined.changes:
        if not c.moved:
            continue
        tl = tally[c.sticker_id]
        out.append(
            Finding(
                "misplaced",
                c.sticker_id,
                float(c.refined[0]),
                float(c.refined[1]),
                float(c.refined[2]),
                c.sigma_m,
                math.degrees(c.sigma_yaw),
                offset=(
                    float(c.refined[0] - c.prior[0]),
                    float(c.refined[1] - c.prior[1]),
                    math.degrees(c.dyaw),
                ),
                frames=c.frames,
                detail=f"moved {c.offset_m * 100:.1f} cm, {math.degrees(c.dyaw):+.1f} deg from the map"
                f" (chi-square {c.prior_d2:.0f} against its survey, 3 DoF); refined from {c.frames} frames with"
                f" other stickers; {tl.gated} of its {tl.identified} fixes gated by the tracker",
                evidence=tl.frames,
            )
        )
    return out


def audit_walks(walks: list[WalkLog], smap: StickerMap, config: AuditConfig | None = None) -> AuditResult:
    """Classify the map's stickers from walks collected with ``smap``."""
    config = config or AuditConfig()
    tally = _tally(walks, smap, config)
    refined = refine_map(walks, smap, config.refine)
    findings = _missing(tally, smap, config) + _unmapped(walks, smap, config) + _misplaced(refined, tally)
    findings += _hard(tally, smap, config)
    trajectories = [np.array([fr.pose[:2] for fr in w.frames if _tracked(fr, config)]).reshape(-1, 2) for w in walks]
    n_frames = [len(w.frames) for w in walks]
    n_tracked = [len(t) for t in trajectories]
    return AuditResult(
        smap,
        [w.name for w in walks],
        sum(n_frames),
        sum(n_tracked),
        findings,
        refined,
        trajectories,
        n_frames,
        n_tracked,
        config.min_tracked_fraction,
        walks_skipped(walks)[1],
    )


KIND_TITLES = {
    "missing": "Missing (in view on several passes, never seen)",
    "unmapped": "Unmapped (decoded, not in the map)",
    "misplaced": "Misplaced (the walks put them elsewhere)",
    "hard": "Hard to read (detected often, rarely decoded)",
}
KIND_COLOURS = {"missing": "tab:red", "unmapped": "tab:blue", "misplaced": "tab:orange", "hard": "tab:purple"}


def _evidence(ev: list[str], n: int = 6) -> str:
    return ", ".join(ev[:n]) + (f" (+{len(ev) - n} more)" if len(ev) > n else "")


def audit_markdown(result: AuditResult, map_name: str) -> str:
    """The audit as a Markdown report."""
    lines = [
        f"# Map audit of {map_name}",
        "",
        f"{len(result.walks)} walks ({', '.join(result.walks)}), {frames_text(result.frames, result.skipped)},"
        f" {result.tracked_frames}"
        f" tracked well enough to check the map against; {len(result.map)} mapped stickers.",
        "",
    ]
    if result.unchecked:
        lines += [
            f"**NOT CHECKED: the tracker hardly tracked {', '.join(result.unchecked)} with this map"
            f" ({result.unchecked_text()}, under {result.min_tracked_fraction:.0%}), so nothing was"
            " checked where they walked, and empty classes below are no all-clear. Is this the map of the"
            " floor they walked? The unmapped class lists the IDs they decoded that the map lacks.**",
            "",
        ]
    lines += [
        "| class | count | IDs |",
        "|---|---|---|",
    ]
    for kind in KIND_TITLES:
        fs = result.of(kind)
        lines.append(f"| {kind} | {len(fs)} | {' '.join(str(f.sticker_id) for f in fs) or '-'} |")
    lines += ["", "![floor plan](floorplan.png)", ""]
    for kind, title in KIND_TITLES.items():
        fs = result.of(kind)
        lines += [f"## {title}: {len(fs)}", ""]
        if not fs:
            lines += ["None.", ""]
            continue
        if kind in ("unmapped", "misplaced"):
            lines += [
                "| id | x m | y m | yaw deg | sigma cm | sigma deg | offset (dx, dy cm, dyaw deg) | evidence |",
                "|---|---|---|---|---|---|---|---|",
            ]
        else:
            lines += ["| id | x m | y m | yaw deg | why | evidence |", "|---|---|---|---|---|---|"]
        for f in fs:
            pos = f"| {f.sticker_id} | {f.x:.3f} | {f.y:.3f} | {math.degrees(f.yaw):.1f} |"
            if not math.isfinite(f.x):  # decoded only while the track was lost
                lines.append(f"| {f.sticker_id} | - | - | - | - | - | - | {f.detail}; {_evidence(f.evidence)} |")
                continue
            if kind in ("unmapped", "misplaced"):
                off = (
                    ""
                    if f.offset is None
                    else f"{f.offset[0] * 100:+.1f}, {f.offset[1] * 100:+.1f}, {f.offset[2]:+.1f}"
                )
                lines.append(
                    f"{pos} {f.sigma_m * 100:.1f} | {f.sigma_deg:.1f} | {off} | {f.detail}; {_evidence(f.evidence)} |"
                )
            else:
                lines.append(f"{pos} {f.detail} | {_evidence(f.evidence)} |")
        lines.append("")
    if result.refine is not None:
        r = result.refine
        lines += [
            "## Refinement behind the misplaced class",
            "",
            f"{r.frames_used} frames with two or more decoded stickers, {r.sightings_used} sightings"
            f" ({r.sightings_dropped} dropped; {r.links_dropped} odometry links dropped),"
            f" {len(r.changes)} stickers refined, {residual_text(r)};"
            " seen but never with another sticker (not checked for placement):"
            f" {' '.join(map(str, r.seen_alone)) or 'none'}. {r.note}",
            "",
        ]
    return "\n".join(lines)


def plot_audit(result: AuditResult, path: str | Path) -> None:
    """A floor plan (PNG): the map, the tracked walks and the findings coloured by class."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    smap = result.map
    xs = np.concatenate([smap.xy[:, 0]] + [t[:, 0] for t in result.trajectories])
    ys = np.concatenate([smap.xy[:, 1]] + [t[:, 1] for t in result.trajectories])
    aspect = (np.ptp(ys) + 1.0) / (np.ptp(xs) + 1.0)  # a long aisle gets a short, wide figure
    fig, ax = plt.subplots(figsize=(11, float(np.clip(8 * aspect + 1.5, 3.0, 9.0))), dpi=120)
    ax.scatter(smap.xy[:, 0], smap.xy[:, 1], s=12, marker="s", c="0.6", label=f"mapped ({len(smap)})", zorder=2)
    for k, traj in enumerate(result.trajectories):
        ax.plot(traj[:, 0], traj[:, 1], lw=0.7, c="tab:cyan", alpha=0.7, label="walks" if k == 0 else None, zorder=1)
    markers = {"missing": "x", "unmapped": "P", "misplaced": "o", "hard": "D"}
    for kind in KIND_TITLES:
        fs = [f for f in result.of(kind) if math.isfinite(f.x)]  # the unplaced have no place to mark
        if not fs:
            continue
        xy = np.array([[f.x, f.y] for f in fs])
        ax.scatter(
            xy[:, 0],
            xy[:, 1],
            s=70,
            marker=markers[kind],
            **(
                {"facecolors": "none", "edgecolors": KIND_COLOURS[kind]}
                if kind in ("misplaced", "hard")
                else {"c": KIND_COLOURS[kind]}
            ),
            linewidths=1.8,
            label=f"{kind} ({len(fs)})",
            zorder=3,
        )
        for f in fs:
            text = str(f.sticker_id)
            if f.offset is not None:
                row = smap.row(f.sticker_id)
                ax.annotate(
                    "",
                    xy=(f.x, f.y),
                    xytext=tuple(smap.xy[row]),
                    arrowprops={"arrowstyle": "->", "color": "tab:orange"},
                )
                text += f" ({math.hypot(f.offset[0], f.offset[1]) * 100:.0f} cm)"
            ax.annotate(
                text, (f.x, f.y), xytext=(4, 4), textcoords="offset points", fontsize=7, color=KIND_COLOURS[kind]
            )
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"Map audit: {len(result.walks)} walks, {result.frames} frames")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# The files write_audit puts in the output directory (the CLI keeps them apart from the inputs).
AUDIT_FILES = ("report.md", "floorplan.png", "audit.json", "unmapped.csv")


def write_audit(result: AuditResult, out_dir: str | Path, map_name: str) -> Path:
    """Write ``report.md``, ``floorplan.png``, ``audit.json`` and ``unmapped.csv`` (map rows with
    sigma columns, ready to add: the unmapped stickers with a position) to ``out_dir``; returns the
    report's path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.md").write_text(audit_markdown(result, map_name) + "\n", encoding="utf-8")
    plot_audit(result, out / "floorplan.png")
    doc = {
        "map": map_name,
        "walks": result.walks,
        "frames": result.frames,
        "skipped_frames": len(result.skipped),
        "first_skipped": result.skipped[0] if result.skipped else None,
        "tracked_frames": result.tracked_frames,
        "walk_frames": result.walk_frames,
        "walk_tracked_frames": result.walk_tracked,
        "unchecked_walks": result.unchecked,
        "counts": {kind: len(result.of(kind)) for kind in KIND_TITLES},
        "findings": [{**asdict(f), "yaw_deg": math.degrees(f.yaw)} for f in result.findings],
    }
    write_json(out / "audit.json", doc)
    um = [f for f in result.of("unmapped") if math.isfinite(f.x)]  # rows need a position
    if um:
        save_map(
            StickerMap(
                np.array([f.sticker_id for f in um]),
                np.array([[f.x, f.y] for f in um]),
                np.array([f.yaw for f in um]),
                "unmapped",
                np.array([f.sigma_m for f in um]),
                np.radians([f.sigma_deg for f in um]),
            ),
            out / "unmapped.csv",
        )
    return out / "report.md"


def audit_sessions(
    sessions: list[str | Path],
    out_dir: str | Path,
    map_path: str | Path | None = None,
    config: AuditConfig | None = None,
    progress: bool = False,
) -> AuditResult:
    """``tagloc map audit``: localise the sessions with the map, classify its stickers, write the report."""
    smap, map_path, walks = collect_walks(sessions, map_path, progress=progress)
    result = audit_walks(walks, smap, config)
    write_audit(result, out_dir, str(map_path))
    return result
