"""Refine a sticker map from recorded walks: a joint least-squares estimate of stickers and camera poses.

Unknowns: the 6-DoF pose of the camera in every frame that saw two or more stickers, or that saw
one and is linked by the floor odometry to another such frame, and every sticker those frames saw,
as (x, y, yaw) on the floor. Measurements: every sticker corner the detector placed (outer, and
inner when found), as undistorted pixels against the pinhole projection, weighted by the corner
noise; the odometry links; and each sticker's survey prior from the map (its own
``sigma_m``/``sigma_deg``, or a default where the map does not state them), which anchors the map's
frame so that it does not move. The problem is solved by ``scipy.optimize.least_squares`` with a
sparse Jacobian pattern (a corner's residual depends on one camera and one sticker, a link's on two
cameras).

An odometry link joins two consecutive frames of a walk's camera that saw stickers, with every
frame between them measured by the floor odometry (at most ``max_link_s`` apart): the steps are
composed into one planar motion with its covariance (first-order propagation). The odometry sees
the floor through the rig's nominal camera mount, so a torso that leans shows up as floor motion
(issue 14: 1.9 m per radian of pitch); the link therefore compares the measured motion with the
*apparent* motion of the two camera poses: the rigid planar motion between the floor patches that
the nominal bird's-eye view of each pose shows. Composing the steps telescopes, so only the two end
poses matter, and both are measured by their stickers' corners in all six degrees of freedom.

A sticker whose estimate disagrees with its own prior beyond the chi-square bound (it was moved,
or surveyed badly) loses its prior, the worst first, and the problem is solved again: a 15 cm move
would otherwise pull every other sticker by 15 cm / N. Sightings that the solution cannot explain
(RMS reprojection above a bound: a wrong corner) are dropped the same way, and so are odometry
links whose residual, judged against its own covariance at the solution (Baarda's test: a link
that alone ties a group of frames to the rest has most of its error absorbed, and shows a small
residual), exceeds the same chi-square bound: the odometry across a turn can be off by several
sigma, and on a walk ending in a turn such links put three stickers 3-4 cm off. Not caught: two
walks over the same turn carry the same odometry error, each link agrees with its twin, none fails,
and those stickers stay 4 cm off with 1 cm sigmas (see the README's Map maintenance).

The stated uncertainty of each refined sticker is its marginal covariance, from the Gauss-Newton
information with the camera poses eliminated (Schur complement), with each residual class (corners,
links, priors) weighted down by its own variance factor, its chi-square over its redundancy, where
that exceeds 1: pooled, the thousands of corners (whose 0.5 px is generous) would hide links
noisier than stated. Stickers not refined are left exactly as they were, sigma columns included.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix, diags
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

from tagloc.core.errors import InputError
from tagloc.core.geometry import planar_from_T, wrap_angle
from tagloc.core.rig import RigCamera
from tagloc.core.sticker import ALL_CORNERS
from tagloc.core.stickermap import StickerMap, save_map
from tagloc.eval.mapobs import FrameRecord, Sighting, WalkLog, collect_walks, frames_text, walks_skipped
from tagloc.vision.odometry import OdometryConfig, floor_patch

# Solves at most: each but the last drops one sighting, link or prior. The walks measured needed
# at most 9 (a 5 s walk ending in a turn: 8 links dropped; the refinement benchmark 7, the sparse
# one 8). The bound keeps odometry that states too small a covariance throughout from being
# dropped one link per solve for ever: stated 10 times too small on that walk, 19 links went in
# 20 solves, and the stickers came out as with honest odometry (0.19 against 0.20 cm RMS).
MAX_ROUNDS = 20
# A residual class's variance factor (chi-square over redundancy) is estimated only from this much
# redundancy: one 3-DoF measurement's worth. Below it (no links, every prior rejected) the class
# keeps its stated sigma.
MIN_REDUNDANCY = 3.0
# A link's residual is tested only in directions where it keeps at least this share of its own
# redundancy: where the solution absorbed more of it, the residual says nothing (and dividing by
# almost nothing would blow up rounding).
MIN_LINK_REDUNDANCY = 0.01
# Links whose shares are computed together (3 rows each against the cameras' LU): 86 links are a
# (258, 6V) block, 8 MB at the benchmark's 691 frames.
LINK_CHUNK = 86


@dataclass
class RefineConfig:
    """Choices of :func:`refine_map`.

    Attributes:
        corner_sigma_px: corner noise assumed for the weights (px). ``tagloc bench`` measures the
            outer corners' error at 0.17-0.32 px median and 0.4-1.0 px p95 up to 6 px of blur: 0.5 px
            covers the typical corner; the covariance is rescaled by the residuals if it was optimistic.
        default_sigma_m: survey sigma per axis (m) of stickers whose map row states none: centimetre
            surveys (tape or total station on a busy floor) are the realistic case.
        default_sigma_deg: survey yaw sigma (degrees) where none is stated: a sticker laid by hand
            against a line is within a few degrees.
        moved_chi2: a prior whose residual's squared Mahalanobis distance (3 DoF) exceeds this is
            dropped as a moved sticker: 16.27 is the 99.9 % point, so an honest map loses about one
            prior in a thousand. An odometry link is dropped at the same bound (its residual against
            its own covariance at the solution), so honest odometry loses one link in a thousand.
        max_moved_fraction: at most this share of the refined stickers may lose their prior (with
            more, the map is not a prior worth anchoring to and the result says so).
        max_sighting_rms_px: sightings whose corners the solution misses by more than this RMS (px)
            are dropped and the problem solved again (a corner on the wrong edge, a wrong ID).
        use_identified: also use stickers identified by appearance/ORB whose fix the tracker
            accepted (default: decoded stickers only, whose identity does not depend on the map).
        odometry: link frames by the floor odometry (see the module docstring).
        max_link_s: longest run of odometry steps composed into one link, s: the odometry's noise
            was calibrated over the 0.5-2 s it bridges between stickers, and a link longer than
            that is worth little next to the corners at either end.
        link_points: floor points per side of the patch grid that defines a pose's apparent motion
            (5 x 5 spans the square; the rigid fit barely changes with more).
    """

    corner_sigma_px: float = 0.5
    default_sigma_m: float = 0.02
    default_sigma_deg: float = 2.0
    moved_chi2: float = 16.27
    max_moved_fraction: float = 0.3
    max_sighting_rms_px: float = 2.0
    use_identified: bool = False
    odometry: bool = True
    max_link_s: float = 2.0
    link_points: int = 5

    def __post_init__(self) -> None:
        for name in ("corner_sigma_px", "default_sigma_m", "default_sigma_deg", "max_sighting_rms_px", "max_link_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"refine: {name} must be a positive number, got {value!r}")


@dataclass
class StickerChange:
    """What the refinement did to one sticker.

    Attributes:
        sticker_id: the ID.
        sightings, frames: corner sets and frames it was refined from.
        prior: (3,) map (x, y, yaw) before; refined: (3,) after (m, m, rad).
        sigma_m: per-axis position sigma after (the larger principal axis), m; sigma_yaw: rad.
        moved: its prior was rejected (the sticker is not where the map says).
        prior_d2: squared Mahalanobis distance of the change under the prior (3 DoF).
    """

    sticker_id: int
    sightings: int
    frames: int
    prior: np.ndarray
    refined: np.ndarray
    sigma_m: float
    sigma_yaw: float
    moved: bool
    prior_d2: float

    @property
    def offset_m(self) -> float:
        return float(np.hypot(*(self.refined[:2] - self.prior[:2])))

    @property
    def dyaw(self) -> float:
        return float(wrap_angle(self.refined[2] - self.prior[2]))


@dataclass
class RefineResult:
    """The refined map and what changed.

    Attributes:
        refined: the whole map, refined stickers updated with sigma columns, the rest unchanged.
        changes: one entry per refined sticker, in map order.
        seen_alone: stickers identified but never together with another one (not refinable).
        frames_used, sightings_used, sightings_dropped: problem size; odometry_links: links used
            (frames_linked: of the frames used, those that saw a single sticker, there by a link).
        rms_px: RMS corner residual after the solve; chi2_dof: chi-square per degree of freedom
            (corners, links and priors pooled) with ``corner_sigma_px``.
        links_dropped: odometry links dropped as inconsistent with the rest.
        variance_factors: per residual class ("corners", "links", "priors"), its chi-square over
            its redundancy: 1 when its stated noise is right (NaN: too little redundancy to say).
        solve_s: wall time of the solves, s; evaluations: residual evaluations in all.
        note: why nothing was refined, or a warning (too many moved stickers).
    """

    refined: StickerMap
    changes: list[StickerChange] = field(default_factory=list)
    seen_alone: list[int] = field(default_factory=list)
    frames_used: int = 0
    sightings_used: int = 0
    sightings_dropped: int = 0
    odometry_links: int = 0
    frames_linked: int = 0
    rms_px: float = float("nan")
    chi2_dof: float = float("nan")
    solve_s: float = 0.0
    evaluations: int = 0
    note: str = ""
    links_dropped: int = 0
    variance_factors: dict[str, float] = field(default_factory=dict)


def _usable(s: Sighting, config: RefineConfig) -> bool:
    if not s.in_map or s.corners is None or s.T_camera_sticker is None:
        return False
    return s.decoded or (config.use_identified and s.accepted is True)


@dataclass
class _Problem:
    """The least-squares problem's index tables (P corner points, V views = camera poses, S stickers,
    L odometry links)."""

    ids: np.ndarray  # (S,) sticker IDs refined
    rows: np.ndarray  # (S,) their rows in the map
    view_sighting: list[list[Sighting]]  # per view, its sightings
    pt_view: np.ndarray  # (P,) view of each corner point
    pt_sticker: np.ndarray  # (P,) sticker (0..S-1) of each point
    pt_sighting: np.ndarray  # (P,) global sighting number of each point
    obj: np.ndarray  # (P, 2) corner in the sticker frame, m
    meas: np.ndarray  # (P, 2) undistorted pixel
    fx: np.ndarray  # (P,), fy, cx, cy of the point's camera
    fy: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    x0_views: np.ndarray  # (V, 6) OpenCV rvec, tvec of T_camera_world
    n_sightings: int
    link_views: np.ndarray  # (L, 2) views joined by each odometry link
    link_delta: np.ndarray  # (L, 3) composed odometry (dx, dy, dyaw): later apparent pose in the earlier's frame
    link_whiten: np.ndarray  # (L, 3, 3) inverse Cholesky factor of each link's covariance
    patch_q: np.ndarray  # (V, M, 2) nominal floor patch points, body frame, m (defines the apparent pose)
    patch_rays: np.ndarray  # (V, M, 3) those points' rays in the camera through the nominal mount
    single_linked: int  # views that saw one sticker only (there by a link)
    link_keys: list[tuple[int, int, int, int]]  # (walk, camera, earlier frame, later frame) of each link
    view_keys: list[tuple[int, int, int]]  # (walk, camera, frame) of each view


def _compose(a: np.ndarray, cov_a: np.ndarray, b: np.ndarray, cov_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Planar motion ``a`` then ``b`` (each (dx, dy, dyaw), ``b`` in ``a``'s end frame) and the
    first-order covariance of the result (independent errors)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    out = np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2]])
    Ja = np.array([[1.0, 0.0, -s * b[0] - c * b[1]], [0.0, 1.0, c * b[0] - s * b[1]], [0.0, 0.0, 1.0]])
    Jb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return out, Ja @ cov_a @ Ja.T + Jb @ cov_b @ Jb.T


def _links(
    frames: list[FrameRecord], is_view: dict[int, int], max_link_s: float
) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """Odometry links (view a, view b, delta, cov) along one camera's ``frames`` (in order) between
    consecutive frames that are candidate views (``is_view``: frame position -> view number), every
    frame between them having a step from its predecessor."""
    out = []
    last, acc, cov, t_last = None, np.zeros(3), np.zeros((3, 3)), 0.0
    for k, fr in enumerate(frames):
        step = fr.step
        ok = last is not None and step is not None and k > 0 and abs(step.t0 - frames[k - 1].t) < 1e-6
        if ok:
            acc, cov = _compose(acc, cov, np.asarray(step.delta, float), np.asarray(step.cov, float))
        else:
            last = None
        if k in is_view:
            if last is not None and fr.t - t_last <= max_link_s:
                out.append((last, is_view[k], acc.copy(), cov.copy()))
            last, acc, cov, t_last = is_view[k], np.zeros(3), np.zeros((3, 3)), fr.t
    return out


def apparent_poses(views: np.ndarray, patch_q: np.ndarray, patch_rays: np.ndarray) -> np.ndarray:
    """(V, 3) the apparent body pose (x, y, yaw) of each camera pose, as the floor odometry sees it.

    ``views`` (V, 6): rvec, tvec of T_camera_world; ``patch_q`` (V, M, 2): floor points of the
    odometry's patch in the body frame (m); ``patch_rays`` (V, M, 3): the rays to them from the camera
    at its nominal mount. The odometry takes the image to show the floor through that mount; the
    apparent pose is the rigid planar motion taking the patch points to where the actual camera
    pose's rays meet the floor (exactly the body pose when the camera sits at its nominal mount).
    """
    R_wc = Rotation.from_rotvec(views[:, :3]).inv().as_matrix()  # (V, 3, 3)
    centre = -np.einsum("vij,vj->vi", R_wc, views[:, 3:])  # camera centre in the world
    rays = np.einsum("vij,vmj->vmi", R_wc, patch_rays)
    scale = -centre[:, None, 2] / np.where(np.abs(rays[:, :, 2]) > 1e-9, rays[:, :, 2], -1e-9)
    w = centre[:, None, :2] + scale[:, :, None] * rays[:, :, :2]
    qm, wm = patch_q.mean(axis=1), w.mean(axis=1)
    qc, wc = patch_q - qm[:, None], w - wm[:, None]
    yaw = np.arctan2(
        np.sum(qc[:, :, 0] * wc[:, :, 1] - qc[:, :, 1] * wc[:, :, 0], axis=1),
        np.sum(qc[:, :, 0] * wc[:, :, 0] + qc[:, :, 1] * wc[:, :, 1], axis=1),
    )
    c, sn = np.cos(yaw), np.sin(yaw)
    t = wm - np.column_stack([c * qm[:, 0] - sn * qm[:, 1], sn * qm[:, 0] + c * qm[:, 1]])
    return np.column_stack([t, yaw])


def patch_rays(rig_cam: RigCamera, points: int) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) grid over the odometry's floor patch (body frame, m) and (M, 3) the rays to them from
    the camera at its nominal mount (camera frame, z = 1)."""
    p = floor_patch(rig_cam, OdometryConfig())
    g = np.linspace(0.0, OdometryConfig().patch_px - 1, points)
    col, row = np.meshgrid(g, g)
    q = p.origin + np.column_stack([col.ravel(), row.ravel()]) @ p.A.T
    T_cb = np.linalg.inv(rig_cam.T_body_camera)
    pc = np.column_stack([q, np.zeros(len(q))]) @ T_cb[:3, :3].T + T_cb[:3, 3]
    return q, pc / pc[:, 2:3]


# A sighting agrees with a view's starting pose when the sticker it puts in the world is within this
# of the map's (m, rad): the survey's few centimetres and degrees, not a sticker moved or turned.
AGREE_M, AGREE_RAD = 0.05, math.radians(10.0)


def _initial_view(sights: list[Sighting], smap: StickerMap) -> np.ndarray:
    """A view's starting T_camera_world: the pose one sighting gives through the prior map, from the
    sighting whose pose puts the most of the view's other stickers where the map has them (then the
    best-fitting). The best-fitting sticker alone may be one turned or moved since the survey: a
    sticker laid 90 or 180 degrees round started its views that far off, and the solve diverged."""
    cands = []
    for s in sights:
        T_cw = s.T_camera_sticker @ np.linalg.inv(smap.T_world_sticker(s.sticker_id))
        T_wc = np.linalg.inv(T_cw)
        agree = 0
        for o in sights:
            if o is s:
                continue
            x, y, yaw = planar_from_T(T_wc @ o.T_camera_sticker)
            k = smap.row(int(o.sticker_id))
            dyaw = wrap_angle(yaw - smap.yaw[k])
            agree += bool(np.hypot(x - smap.xy[k, 0], y - smap.xy[k, 1]) <= AGREE_M and abs(dyaw) <= AGREE_RAD)
        cands.append((-agree, s.reprojection_px, len(cands), T_cw))
    return min(cands, key=lambda c: c[:3])[3]


def _build(
    walks: list[WalkLog],
    smap: StickerMap,
    config: RefineConfig,
    drop: set[tuple[int, int, int]],
    drop_links: set[tuple[int, int, int, int]] = frozenset(),
) -> _Problem:
    """Views (frame, camera) with two or more usable sightings, or one and an odometry link to
    another view, minus dropped sightings (walk, frame, slot) and dropped links (walk, camera,
    earlier frame, later frame)."""
    cands: list[tuple[WalkLog, int, list[tuple[int, Sighting]]]] = []
    cand_key: list[tuple[int, int, int]] = []  # (walk, camera, frame index) of each candidate view
    links: list[tuple[int, int, np.ndarray, np.ndarray]] = []
    for w, walk in enumerate(walks):
        per_cam: dict[int, list[FrameRecord]] = {}
        is_view: dict[int, dict[int, int]] = {}
        for fr in walk.frames:
            frames = per_cam.setdefault(fr.camera, [])
            sights = [
                (slot, s)
                for slot, s in enumerate(fr.sightings)
                if _usable(s, config) and s.camera == fr.camera and (w, fr.index, slot) not in drop
            ]
            if sights:
                is_view.setdefault(fr.camera, {})[len(frames)] = len(cands)
                cands.append((walk, fr.camera, sights))
                cand_key.append((w, fr.camera, fr.index))
            frames.append(fr)
        if config.odometry:
            for cam, frames in per_cam.items():
                links += _links(frames, is_view.get(cam, {}), config.max_link_s)
    links = [lk for lk in links if (*cand_key[lk[0]], cand_key[lk[1]][2]) not in drop_links]
    # Keep the views that tie two or more stickers together: alone, or through their links.
    n = len(cands)
    edges = np.array([(a, b) for a, b, _, _ in links], np.int64).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    stickers_of: dict[int, set[int]] = {}
    for v, (_, _, sights) in enumerate(cands):
        stickers_of.setdefault(int(comp[v]), set()).update(int(s.sticker_id) for _, s in sights)
    keep = [v for v in range(n) if len(stickers_of[int(comp[v])]) >= 2]
    renum = {v: k for k, v in enumerate(keep)}
    views = [cands[v] for v in keep]
    link_keys = [(*cand_key[a], cand_key[b][2]) for a, b, _, _ in links if a in renum and b in renum]
    links = [(renum[a], renum[b], d, c) for a, b, d, c in links if a in renum and b in renum]
    ids = sorted({int(s.sticker_id) for _, _, sights in views for _, s in sights})
    col = {sid: k for k, sid in enumerate(ids)}
    tables: dict[str, list] = {k: [] for k in ("view", "sticker", "sighting", "obj", "meas", "f")}
    x0_views, view_sighting, view_q, view_rays = [], [], [], []
    rays_of: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    n_sight = 0
    for v, (walk, cam, sights) in enumerate(views):
        camera = walk.rig[cam].camera
        T_cw = _initial_view([s for _, s in sights], smap)
        x0_views.append(np.concatenate([Rotation.from_matrix(T_cw[:3, :3]).as_rotvec(), T_cw[:3, 3]]))
        view_sighting.append([s for _, s in sights])
        key = (id(walk), cam)
        if key not in rays_of:
            rays_of[key] = patch_rays(walk.rig[cam], config.link_points)
        view_q.append(rays_of[key][0])
        view_rays.append(rays_of[key][1])
        for _, s in sights:
            m = len(s.corners)
            tables["view"].append(np.full(m, v))
            tables["sticker"].append(np.full(m, col[int(s.sticker_id)]))
            tables["sighting"].append(np.full(m, n_sight))
            tables["obj"].append(ALL_CORNERS[:m, :2])
            tables["meas"].append(camera.undistort_pixels(s.corners))
            tables["f"].append(np.tile(camera.K[[0, 1, 0, 1], [0, 1, 2, 2]], (m, 1)))
            n_sight += 1
    cat = {k: (np.concatenate(v) if v else np.zeros(0)) for k, v in tables.items()}
    f = cat["f"].reshape(-1, 4)
    M = config.link_points**2
    return _Problem(
        np.array(ids, np.int64),
        np.array([smap.row(i) for i in ids], np.int64),
        view_sighting,
        cat["view"].astype(np.int64),
        cat["sticker"].astype(np.int64),
        cat["sighting"].astype(np.int64),
        cat["obj"].reshape(-1, 2),
        cat["meas"].reshape(-1, 2),
        f[:, 0],
        f[:, 1],
        f[:, 2],
        f[:, 3],
        np.array(x0_views).reshape(-1, 6),
        n_sight,
        np.array([(a, b) for a, b, _, _ in links], np.int64).reshape(-1, 2),
        np.array([d for _, _, d, _ in links]).reshape(-1, 3),
        np.array([np.linalg.inv(np.linalg.cholesky(c + 1e-12 * np.eye(3))) for _, _, _, c in links]).reshape(-1, 3, 3),
        np.array(view_q).reshape(-1, M, 2),
        np.array(view_rays).reshape(-1, M, 3),
        sum(len({s.sticker_id for s in sights}) == 1 for sights in view_sighting),
        link_keys,
        [cand_key[v] for v in keep],
    )


class _Solver:
    """Residuals, Jacobian pattern and solve of one :class:`_Problem`."""

    def __init__(self, prob: _Problem, prior: np.ndarray, prior_sigma: np.ndarray, config: RefineConfig):
        self.p = prob
        self.prior = prior  # (S, 3)
        self.prior_w = 1.0 / prior_sigma  # (S, 3)
        self.active = np.ones(len(prob.ids), bool)
        self.w_px = 1.0 / config.corner_sigma_px
        self.V, self.S, self.L = len(prob.x0_views), len(prob.ids), len(prob.link_views)
        self.sparsity = self._sparsity()
        self.W = self._whitening()

    def _whitening(self) -> np.ndarray:
        """(V, 6, 6) per-view change of variables making each camera's own information the identity.

        A pose from one 10 cm sticker trades rotation against translation almost freely, so the
        camera blocks are badly conditioned and the trust-region's iterative (lsmr) steps crawl
        (measured: 200 iterations without converging); in whitened variables they converge in a few.
        """
        p = self.p
        W = np.empty((self.V, 6, 6))
        order = np.argsort(p.pt_view, kind="stable")
        starts = np.searchsorted(p.pt_view[order], np.arange(self.V + 1))
        for v in range(self.V):
            pts = order[starts[v] : starts[v + 1]]
            s = self.prior[p.pt_sticker[pts]]
            c, sn = np.cos(s[:, 2]), np.sin(s[:, 2])
            world = np.column_stack(
                [
                    s[:, 0] + c * p.obj[pts, 0] - sn * p.obj[pts, 1],
                    s[:, 1] + sn * p.obj[pts, 0] + c * p.obj[pts, 1],
                    np.zeros(len(pts)),
                ]
            )
            k = pts[0]
            K = np.array([[p.fx[k], 0.0, p.cx[k]], [0.0, p.fy[k], p.cy[k]], [0.0, 0.0, 1.0]])
            rvec, tvec = p.x0_views[v, :3], p.x0_views[v, 3:]
            _, jac = cv2.projectPoints(world.reshape(-1, 1, 3), rvec, tvec, K, None)
            J = jac[:, :6] * self.w_px
            lam, Q = np.linalg.eigh(J.T @ J)
            lam = np.maximum(lam, 1e-12 * lam.max())
            W[v] = Q / np.sqrt(lam)
        return W

    def views(self, y: np.ndarray) -> np.ndarray:
        """(V, 6) rvec, tvec of each view from the whitened variables."""
        z = y[: 6 * self.V].reshape(self.V, 6)
        return self.p.x0_views + np.einsum("vij,vj->vi", self.W, z)

    def initial(self, stickers: np.ndarray) -> np.ndarray:
        """The variable vector at the views' initial poses and the given (S, 3) stickers."""
        return np.concatenate([np.zeros(6 * self.V), np.asarray(stickers, float).ravel()])

    def _sparsity(self):
        p, V = self.p, self.V
        P = len(p.pt_view)
        rows, cols = [], []
        r = np.arange(2 * P)
        pt = r // 2
        for k in range(6):
            rows.append(r)
            cols.append(6 * p.pt_view[pt] + k)
        for k in range(3):
            rows.append(r)
            cols.append(6 * V + 3 * p.pt_sticker[pt] + k)
        prior_rows = 2 * P + np.arange(3 * self.S)
        rows.append(prior_rows)
        cols.append(6 * V + np.arange(3 * self.S))
        # Each link's three rows depend on the six variables of each of its two views.
        link_rows = 2 * P + 3 * self.S + np.arange(3 * self.L)
        for end in range(2):
            for k in range(6):
                rows.append(link_rows)
                cols.append(6 * np.repeat(p.link_views[:, end], 3) + k)
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        shape = (2 * P + 3 * self.S + 3 * self.L, 6 * V + 3 * self.S)
        return coo_matrix((np.ones(len(rows)), (rows, cols)), shape=shape).tocsr()

    def link_residuals(self, x: np.ndarray) -> np.ndarray:
        """(L, 3) whitened odometry residuals: the apparent motion between each link's views minus the
        composed measurement."""
        p = self.p
        if self.L == 0:
            return np.zeros((0, 3))
        a = apparent_poses(self.views(x), p.patch_q, p.patch_rays)
        pa, pb = a[p.link_views[:, 0]], a[p.link_views[:, 1]]
        c, sn = np.cos(pa[:, 2]), np.sin(pa[:, 2])
        d = pb[:, :2] - pa[:, :2]
        rel = np.column_stack([c * d[:, 0] + sn * d[:, 1], -sn * d[:, 0] + c * d[:, 1], pb[:, 2] - pa[:, 2]])
        e = rel - p.link_delta
        e[:, 2] = wrap_angle(e[:, 2])
        return np.einsum("lij,lj->li", p.link_whiten, e)

    def corner_residuals(self, x: np.ndarray) -> np.ndarray:
        """(P, 2) corner residuals in pixels (not weighted)."""
        p, V = self.p, self.V
        views = self.views(x)
        st = x[6 * V :].reshape(self.S, 3)
        R = Rotation.from_rotvec(views[:, :3]).as_matrix()[p.pt_view]  # (P, 3, 3) R_camera_world
        t = views[p.pt_view, 3:]
        s = st[p.pt_sticker]
        c, sn = np.cos(s[:, 2]), np.sin(s[:, 2])
        wx = s[:, 0] + c * p.obj[:, 0] - sn * p.obj[:, 1]
        wy = s[:, 1] + sn * p.obj[:, 0] + c * p.obj[:, 1]
        cam = R[:, :, 0] * wx[:, None] + R[:, :, 1] * wy[:, None] + t  # floor points have z = 0
        z = np.maximum(cam[:, 2], 1e-6)
        u = p.fx * cam[:, 0] / z + p.cx
        v = p.fy * cam[:, 1] / z + p.cy
        return np.column_stack([u, v]) - p.meas

    def residuals(self, x: np.ndarray) -> np.ndarray:
        st = x[6 * self.V :].reshape(self.S, 3)
        d = st - self.prior
        d[:, 2] = wrap_angle(d[:, 2])
        prior_r = d * self.prior_w * self.active[:, None]
        return np.concatenate(
            [self.corner_residuals(x).ravel() * self.w_px, prior_r.ravel(), self.link_residuals(x).ravel()]
        )

    def solve(self, x0: np.ndarray):
        # One BLAS thread: the solver's vectors are small, and threaded BLAS spinning on a busy
        # machine made it 9 times slower (measured 15 s against 1.7 s on one problem).
        with threadpool_limits(limits=1, user_api="blas"):
            return self._solve(x0)

    def _solve(self, x0: np.ndarray):
        return least_squares(
            self.residuals,
            x0,
            jac_sparsity=self.sparsity,
            method="trf",
            x_scale="jac",
            # lsmr's default tolerances give steps too inexact to meet ftol: measured 200 evaluations
            # without converging, against 6-11 with these.
            tr_options={"atol": 1e-10, "btol": 1e-10},
            max_nfev=200,
        )

    def row_classes(self) -> dict[str, slice]:
        """The rows of each residual class in :meth:`residuals`."""
        n_corner, n_prior = 2 * len(self.p.pt_view), 3 * self.S
        return {
            "corners": slice(0, n_corner),
            "priors": slice(n_corner, n_corner + n_prior),
            "links": slice(n_corner + n_prior, n_corner + n_prior + 3 * self.L),
        }

    def _blocks(self, jac):
        """The Gauss-Newton information split at the cameras: the LU of the cameras' block A,
        G = A^-1 B and the stickers' full (3S, 3S) marginal covariance (Schur complement)."""
        V = self.V
        H = (jac.T @ jac).tocsr()
        # The cameras' block is block-diagonal but for the odometry links: a sparse LU solves it.
        lu = splu(H[: 6 * V, : 6 * V].tocsc())
        B = H[: 6 * V, 6 * V :].toarray()
        G = lu.solve(B)
        schur = H[6 * V :, 6 * V :].toarray() - B.T @ G
        return lu, G, np.linalg.pinv((schur + schur.T) / 2)

    def sticker_covariance(self, jac) -> np.ndarray:
        """(S, 3, 3) marginal covariance of each sticker, cameras eliminated (Schur complement)."""
        if not self.S:
            return np.zeros((0, 3, 3))
        cov = self._blocks(jac)[2]
        return np.stack([cov[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] for k in range(self.S)])

    def link_shares(self, jac, blocks=None) -> np.ndarray:
        """(L, 3, 3) each link's share of the unknowns, J_l H^-1 J_l' (whitened): its residual's own
        covariance at the solution is I minus it. A link that alone ties a group of frames to the rest
        has a share near I: the solution absorbs most of its error (small residual, small redundancy).

        With H^-1 split at the cameras (A, B; G = A^-1 B; Sigma the stickers' covariance) and a link's
        rows touching cameras only: J A^-1 J' + (J G) Sigma (J G)'.
        """
        V = self.V
        if self.L == 0:
            return np.zeros((0, 3, 3))
        lu, G, cov = blocks if blocks is not None else self._blocks(jac)
        J = jac.tocsr()[self.row_classes()["links"], : 6 * V]
        out = np.empty((self.L, 3, 3))
        step = 3 * LINK_CHUNK
        for k in range(0, J.shape[0], step):  # A^-1 against a chunk of links at a time: bounded memory
            part = J[k : k + step]
            full = (part @ lu.solve(part.T.toarray())).reshape(-1, 3, part.shape[0] // 3, 3)
            n = part.shape[0] // 3
            out[k // 3 : k // 3 + n] = full[np.arange(n), :, np.arange(n), :]
        M = (J @ G).reshape(self.L, 3, -1)
        return out + np.einsum("lij,jk,lmk->lim", M, cov, M)

    def link_test(self, x: np.ndarray, shares: np.ndarray) -> np.ndarray:
        """(L,) each link's residual against its own covariance at the solution, e' (I - share)^-1 e:
        chi-square with 3 DoF for a link as noisy as stated (Baarda's test). Directions in which the
        link has under ``MIN_LINK_REDUNDANCY`` of its own redundancy cannot be tested and are left out."""
        e = self.link_residuals(x)
        q, U = np.linalg.eigh(np.eye(3)[None] - shares)
        proj = np.einsum("lji,lj->li", U, e)
        tested = q > MIN_LINK_REDUNDANCY
        return np.sum(np.where(tested, proj**2 / np.maximum(q, MIN_LINK_REDUNDANCY), 0.0), axis=1)

    def redundancy(self, jac, link_shares: np.ndarray | None = None, blocks=None) -> dict[str, float]:
        """Per residual class, its residuals less the share of the unknowns it determines:
        r_c = n_c - sum over its rows j of j' H^-1 j (the classes' shares add up to the unknowns).
        chi2_c / r_c is the class's variance factor (Foerstner's variance components): a class
        whose stated noise is right gives 1 whatever the other classes do. A prior's rows touch
        its sticker only (share w^2 Sigma_kk); the links' come from :meth:`link_shares`; the corners
        get the rest.
        """
        blocks = blocks if blocks is not None else self._blocks(jac)
        cov = blocks[2]
        if link_shares is None:
            link_shares = self.link_shares(jac, blocks)
        n_prior = 3 * int(self.active.sum())
        w2 = (self.prior_w * self.active[:, None]).ravel() ** 2
        out = {
            "priors": n_prior - float(np.sum(w2 * np.diag(cov))),
            "links": 3 * self.L - float(np.trace(link_shares, axis1=1, axis2=2).sum()),
        }
        n_all = 2 * len(self.p.pt_view) + n_prior + 3 * self.L
        out["corners"] = n_all - (6 * self.V + 3 * self.S) - out["priors"] - out["links"]
        return out


def _prior_sigma(smap: StickerMap, rows: np.ndarray, config: RefineConfig) -> np.ndarray:
    sxy = np.where(np.isfinite(smap.sigma_xy[rows]), smap.sigma_xy[rows], config.default_sigma_m)
    syaw = np.where(np.isfinite(smap.sigma_yaw[rows]), smap.sigma_yaw[rows], math.radians(config.default_sigma_deg))
    # A stated sigma of 0 means "exact": keep it finite so the weights stay finite (0.1 mm, 0.01 deg).
    return np.column_stack([np.maximum(sxy, 1e-4), np.maximum(sxy, 1e-4), np.maximum(syaw, math.radians(0.01))])


def refine_map(walks: list[WalkLog], smap: StickerMap, config: RefineConfig | None = None) -> RefineResult:
    """Jointly estimate the stickers seen two or more to a frame and those frames' camera poses.

    ``walks`` were collected with ``smap`` (:func:`tagloc.eval.mapobs.collect_walk`). Returns the
    refined map (unrefined stickers unchanged) and what moved.
    """
    # One BLAS thread for the solves and for the sparse LU solves of the links' tests and the
    # covariance: threaded BLAS spinning on a busy machine made one link test 20 times slower
    # (measured 2.4 s against 0.12 s for 86 links on the sparse benchmark).
    with threadpool_limits(limits=1, user_api="blas"):
        return _refine_map(walks, smap, config)


def _refine_map(walks: list[WalkLog], smap: StickerMap, config: RefineConfig | None) -> RefineResult:
    config = config or RefineConfig()
    t0 = time.perf_counter()
    result = RefineResult(_copy_map(smap))
    seen = {int(s.sticker_id) for w in walks for fr in w.frames for s in fr.sightings if _usable(s, config)}
    drop: set[tuple[int, int, int]] = set()
    drop_links: set[tuple[int, int, int, int]] = set()
    x_st: dict[int, np.ndarray] = {}
    x_views: dict[tuple[int, int, int], np.ndarray] = {}
    moved: set[int] = set()
    for round_ in range(MAX_ROUNDS):
        prob = _build(walks, smap, config, drop, drop_links)
        if len(prob.ids) == 0:
            result.note = "no frame saw two or more usable (decoded) stickers: nothing to refine"
            result.seen_alone = sorted(seen)
            return result
        prior = np.column_stack([smap.xy[prob.rows], smap.yaw[prob.rows]])
        # Each round starts where the last one ended: dropping one measurement moves little.
        for v, key in enumerate(prob.view_keys):
            if key in x_views:
                prob.x0_views[v] = x_views[key]
        solver = _Solver(prob, prior, _prior_sigma(smap, prob.rows, config), config)
        solver.active = np.array([int(i) not in moved for i in prob.ids])
        x0_st = np.array([x_st.get(int(i), prior[k]) for k, i in enumerate(prob.ids)])
        sol = solver.solve(solver.initial(x0_st))
        result.evaluations += int(sol.nfev)
        st = sol.x[6 * solver.V :].reshape(-1, 3)
        x_st = {int(i): st[k] for k, i in enumerate(prob.ids)}
        x_views = dict(zip(prob.view_keys, solver.views(sol.x)))
        res = solver.corner_residuals(sol.x)
        d = st - prior
        d[:, 2] = wrap_angle(d[:, 2])
        d2 = np.sum((d * solver.prior_w) ** 2, axis=1)
        # The split information serves the link test here and, after the last solve, the classes'
        # redundancy (_class_covariance): one LU and Schur complement per solve.
        blocks = solver._blocks(sol.jac)
        shares = solver.link_shares(sol.jac, blocks)
        worst = _worst(solver, prob, res, d2, solver.link_test(sol.x, shares), moved, config)
        if worst is None:
            break
        if round_ == MAX_ROUNDS - 1:
            result.note = (
                f"stopped after {MAX_ROUNDS} solves with measurements still inconsistent with the rest"
                " (the stated sigmas allow for it)"
            )
            break
        kind, k = worst
        if kind == "sighting":
            drop.add(_sighting_key(walks, prob, k))
        elif kind == "link":
            drop_links.add(prob.link_keys[k])
        else:
            moved.add(int(prob.ids[k]))
    if not result.note and np.any(solver.active & (d2 > config.moved_chi2)):
        result.note = (
            f"more than {config.max_moved_fraction:.0%} of the stickers disagree with their survey:"
            " the prior map is too far off to anchor to"
        )
    result.solve_s = time.perf_counter() - t0
    n_res = 2 * len(prob.pt_view) + 3 * int(solver.active.sum()) + 3 * solver.L
    dof = max(n_res - 6 * solver.V - 3 * solver.S, 1)
    result.chi2_dof = float(2 * sol.cost / dof)
    result.rms_px = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
    cov, result.variance_factors = _class_covariance(solver, sol.fun, sol.jac, shares, blocks)
    result.links_dropped = len(drop_links)
    result.frames_used = solver.V
    result.sightings_used = prob.n_sightings
    result.sightings_dropped = len(drop)
    result.odometry_links = solver.L
    result.frames_linked = prob.single_linked
    frames_of = np.zeros(len(prob.ids), np.int64)
    sightings_of = np.zeros(len(prob.ids), np.int64)
    for sights in prob.view_sighting:
        cols = np.searchsorted(prob.ids, [int(s.sticker_id) for s in sights])
        np.add.at(sightings_of, cols, 1)
        frames_of[np.unique(cols)] += 1
    refined = result.refined
    for k, (sid, row) in enumerate(zip(prob.ids, prob.rows)):
        sigma_m = float(np.sqrt(max(np.linalg.eigvalsh(cov[k, :2, :2]).max(), 0.0)))
        sigma_yaw = float(np.sqrt(max(cov[k, 2, 2], 0.0)))
        refined.xy[row] = st[k, :2]
        refined.yaw[row] = wrap_angle(float(st[k, 2]))
        refined.sigma_xy[row] = sigma_m
        refined.sigma_yaw[row] = sigma_yaw
        result.changes.append(
            StickerChange(
                int(sid),
                int(sightings_of[k]),
                int(frames_of[k]),
                prior[k].copy(),
                np.array([st[k, 0], st[k, 1], wrap_angle(float(st[k, 2]))]),
                sigma_m,
                sigma_yaw,
                int(sid) in moved,
                float(d2[k]),
            )
        )
    result.changes.sort(key=lambda c: int(smap.row(c.sticker_id)))
    result.seen_alone = sorted(seen - {int(i) for i in prob.ids})
    return _reindex(result)


def _class_covariance(
    solver: _Solver, fun: np.ndarray, jac, shares: np.ndarray, blocks=None
) -> tuple[np.ndarray, dict[str, float]]:
    """(S, 3, 3) the stickers' covariance with each residual class (corners, links, priors) weighted
    down by its own variance factor where that exceeds 1, and the factors (NaN: too little
    redundancy to estimate one).

    Each class's noise is checked against its own residuals (variance components): the corners'
    0.5 px is deliberately generous (factor about 0.08 on the simulated walks), and thousands of
    them pooled with a few hundred links would hide links noisier than stated. None is weighted up:
    a generous sigma stays generous.
    """
    redundancy = solver.redundancy(jac, shares, blocks)
    scale = np.ones(len(fun))
    factors = {}
    for name, rows in solver.row_classes().items():
        r = redundancy[name]
        factor = float(np.sum(fun[rows] ** 2)) / r if r >= MIN_REDUNDANCY else math.nan
        factors[name] = factor
        if math.isfinite(factor) and factor > 1.0:
            scale[rows] = 1.0 / math.sqrt(factor)
    return solver.sticker_covariance(diags(scale) @ jac), factors


def _worst(
    solver: _Solver,
    prob: _Problem,
    res: np.ndarray,
    d2: np.ndarray,
    link_d2: np.ndarray,
    moved: set[int],
    config: RefineConfig,
) -> tuple[str, int] | None:
    """The measurement to drop next, or None when all are consistent with the solution.

    First a sighting the solution misses by more than ``max_sighting_rms_px`` (a wrong corner set
    distorts the stickers near it), the worst first. Then, of the odometry links and the survey
    priors beyond ``moved_chi2`` (3-DoF chi-squares), the larger: a link's residual is judged
    against its own covariance at the solution, so that a link that alone ties a group of frames
    to the rest, whose error the solution mostly absorbed, shows it (on a walk ending in a turn,
    such a link put three stickers 3-4 cm off); a prior's is the change against its survey.
    Priors only while fewer than ``max_moved_fraction`` of the stickers have lost theirs.

    Returns ("sighting", k), ("link", k) or ("prior", k).
    """
    per = np.bincount(prob.pt_sighting, np.sum(res**2, axis=1), prob.n_sightings)
    npts = np.bincount(prob.pt_sighting, minlength=prob.n_sightings)
    rms = np.sqrt(per / np.maximum(npts, 1))
    if len(rms) and rms.max() > config.max_sighting_rms_px:
        return "sighting", int(np.argmax(rms))
    cands: list[tuple[float, str, int]] = []
    if len(link_d2):
        k = int(np.argmax(link_d2))
        if link_d2[k] > config.moved_chi2:
            cands.append((float(link_d2[k]), "link", k))
    prior_bad = np.flatnonzero(solver.active & (d2 > config.moved_chi2))
    if len(prior_bad) and len(moved) < config.max_moved_fraction * len(prob.ids):
        k = int(prior_bad[np.argmax(d2[prior_bad])])
        cands.append((float(d2[k]), "prior", k))
    if not cands:
        return None
    _, kind, k = max(cands)
    return kind, k


def _sighting_key(walks: list[WalkLog], prob: _Problem, k: int) -> tuple[int, int, int]:
    """(walk, frame, slot) of the problem's ``k``-th sighting."""
    n = 0
    for sights in prob.view_sighting:
        if k < n + len(sights):
            target = sights[k - n]
            break
        n += len(sights)
    for w, walk in enumerate(walks):
        for fr in walk.frames:
            for slot, s in enumerate(fr.sightings):
                if s is target:
                    return (w, fr.index, slot)
    raise InputError("internal: sighting not found")


def _copy_map(smap: StickerMap) -> StickerMap:
    return StickerMap(
        smap.ids.copy(), smap.xy.copy(), smap.yaw.copy(), smap.source, smap.sigma_xy.copy(), smap.sigma_yaw.copy()
    )


def _reindex(result: RefineResult) -> RefineResult:
    """Rebuild the refined map's spatial index after its positions changed."""
    m = result.refined
    result.refined = StickerMap(m.ids, m.xy, m.yaw, m.source, m.sigma_xy, m.sigma_yaw)
    return result


def _factors(factors: dict[str, float]) -> str:
    """The variance factors as "corners 0.08, links 1.21, priors 0.13" (n/a: too little redundancy)."""
    return ", ".join(f"{k} {v:.2f}" if math.isfinite(v) else f"{k} n/a" for k, v in factors.items()) or "n/a"


def refine_markdown(result: RefineResult, map_name: str, walks: list[str]) -> str:
    """What the refinement did, as Markdown: the problem, then every refined sticker, largest move first."""
    moved = [c for c in result.changes if c.moved]
    lines = [
        f"# Map refinement of {map_name}",
        "",
        f"From {len(walks)} walks ({', '.join(walks)}): {result.frames_used} frames with two or more decoded"
        f" stickers or one and a floor-odometry link ({result.frames_linked} such, {result.odometry_links} links),"
        f" {result.sightings_used} sightings ({result.sightings_dropped} dropped as unexplained,"
        f" {result.links_dropped} links dropped as inconsistent), {len(result.changes)} stickers refined,"
        f" {residual_text(result)}, {result.solve_s:.1f} s.",
        f"Moved (survey prior rejected): {' '.join(str(c.sticker_id) for c in moved) or 'none'}."
        f" Seen but never with another sticker, left unchanged: {' '.join(map(str, result.seen_alone)) or 'none'}.",
    ]
    if result.note:
        lines += ["", f"**Note:** {result.note}"]
    lines += [
        "",
        "| id | moved | offset cm | dx cm | dy cm | dyaw deg | sigma cm | sigma deg | frames | chi-square vs survey |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in sorted(result.changes, key=lambda c: -c.offset_m):
        d = (c.refined - c.prior)[:2] * 100
        lines.append(
            f"| {c.sticker_id} | {'yes' if c.moved else ''} | {c.offset_m * 100:.2f} | {d[0]:+.2f} | {d[1]:+.2f} |"
            f" {math.degrees(c.dyaw):+.2f} | {c.sigma_m * 100:.2f} | {math.degrees(c.sigma_yaw):.2f} | {c.frames} |"
            f" {c.prior_d2:.1f} |"
        )
    return "\n".join(lines) + "\n"


def residual_text(result: RefineResult) -> str:
    """The solve's RMS corner residual and chi-square, or that nothing was solved (no frame to refine
    from: a figure of nothing is no "nan px")."""
    if not math.isfinite(result.rms_px):
        return "nothing solved (no corner residual)"
    return (
        f"RMS corner residual {result.rms_px:.2f} px (chi-square per DoF {result.chi2_dof:.2f}; per"
        f" class, against its redundancy: {_factors(result.variance_factors)})"
    )


def default_report(out: str | Path) -> Path:
    """Where the report goes when none is named: the refined map's name with ``.md``."""
    return Path(out).with_suffix(".md")


def refine_sessions(
    sessions: list[str | Path],
    map_path: str | Path,
    out: str | Path,
    report: str | Path | None = None,
    config: RefineConfig | None = None,
    progress: bool = False,
) -> RefineResult:
    """``tagloc map refine``: localise the sessions with the map, refine it, write the refined map and
    a Markdown report of what moved (default: ``out`` with ``.md``)."""
    smap, map_path, walks = collect_walks(sessions, map_path, progress=progress)
    result = refine_map(walks, smap, config)
    frames, skipped = walks_skipped(walks)
    if skipped:
        # Said with the result (the command prints the note): frames lost are stickers not refined.
        result.note = "; ".join(filter(None, [result.note, f"of the walks' {frames_text(frames, skipped)}"]))
    out = Path(out)
    report = Path(report) if report is not None else default_report(out)
    # The CLI checked that these can be created, missing directories included: create them.
    for path in (out, report):
        path.parent.mkdir(parents=True, exist_ok=True)
    save_map(result.refined, out)
    report.write_text(refine_markdown(result, str(map_path), [w.name for w in walks]), encoding="utf-8")
    return result
