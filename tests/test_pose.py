"""Pose from one sticker: exactness, accuracy under corner noise, honest covariance, ambiguity."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from tagloc.core.camera import default_camera
from tagloc.core.geometry import invert, planar_from_T, planar_T, transform_points, wrap_angle
from tagloc.core.rig import RigCamera, looking_forward
from tagloc.core.sticker import INNER_CORNERS, OUTER_CORNERS
from tagloc.core.types import Detection
from tagloc.vision.pose import PoseConfig, solve_pose


def rig_camera(height=1.3, pitch=55.0) -> RigCamera:
    return RigCamera("front", default_camera(), looking_forward(height, pitch))


def scene(rng: np.random.Generator, rc: RigCamera, distance: float | None = None, lateral: float = 0.0):
    """(T_world_body, T_world_sticker) with the sticker ``distance`` m from the camera (random yaws)."""
    body = planar_T(rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-np.pi, np.pi))
    T_wc = body @ rc.T_body_camera
    cam_pos = T_wc[:3, 3]
    axis = T_wc[:3, 2]
    fwd = axis[:2] / np.linalg.norm(axis[:2]) if np.linalg.norm(axis[:2]) > 1e-9 else body[:2, 0]
    left = np.array([-fwd[1], fwd[0]])
    if distance is None:  # where the optical axis meets the floor
        p = cam_pos - axis * cam_pos[2] / axis[2]
        xy = p[:2] + lateral * left
    else:
        ground = math.sqrt(distance**2 - cam_pos[2] ** 2)
        xy = cam_pos[:2] + ground * fwd + lateral * left
    return body, planar_T(xy[0], xy[1], rng.uniform(-np.pi, np.pi))


def corners(rc: RigCamera, T_world_body, T_world_sticker, rotation: int, sigma: float, rng) -> Detection:
    """Detection with canonical TL at ``outer[rotation]`` and Gaussian corner noise ``sigma`` px."""
    T_cs = invert(T_world_body @ rc.T_body_camera) @ T_world_sticker
    outer = rc.camera.project(transform_points(T_cs, OUTER_CORNERS)) + rng.normal(0, sigma, (4, 2))
    inner = rc.camera.project(transform_points(T_cs, INNER_CORNERS)) + rng.normal(0, sigma, (4, 2))
    return Detection(np.roll(outer, rotation, 0), np.roll(inner, rotation, 0))


def pose_error(fix, T_world_body, rc):
    cam_err = np.linalg.norm(fix.T_world_camera[:3, 3] - (T_world_body @ rc.T_body_camera)[:3, 3])
    truth = np.array(planar_from_T(T_world_body))
    d = fix.body - truth
    d[2] = wrap_angle(d[2])
    return cam_err, d


@pytest.mark.parametrize("rotation", [0, 1, 2, 3])
def test_exact_corners_recover_pose(rotation):
    rng = np.random.default_rng(rotation)
    rc = rig_camera()
    body, sticker = scene(rng, rc, 1.6, 0.2)
    for use_inner in (False, True):
        sol = solve_pose(
            corners(rc, body, sticker, rotation, 0.0, rng),
            rotation,
            sticker,
            rc,
            config=PoseConfig(use_inner=use_inner),
        )
        cam_err, d = pose_error(sol.poses[0], body, rc)
        assert cam_err < 1e-6 and np.all(np.abs(d) < 1e-6), (cam_err, d)
        assert sol.poses[0].reprojection_px < 1e-6
        assert np.allclose(sol.poses[0].T_world_camera, body @ rc.T_body_camera, atol=1e-6)


def test_wrong_rotation_gives_wrong_pose():
    """The rotation really selects the corner correspondence (a wrong one is off by ~90 deg)."""
    rng = np.random.default_rng(9)
    rc = rig_camera()
    body, sticker = scene(rng, rc, 1.6)
    det = corners(rc, body, sticker, 1, 0.0, rng)
    _, d = pose_error(solve_pose(det, 2, sticker, rc).poses[0], body, rc)
    assert abs(d[2]) > 1.0


def test_noise_accuracy_4_vs_8_points():
    """0.5 px corner noise at 1.5 m: median camera position error < 3 cm, lower with 8 points."""
    rng = np.random.default_rng(1)
    rc = rig_camera()
    errs = {False: [], True: []}
    for _ in range(150):
        body, sticker = scene(rng, rc, 1.5, rng.uniform(-0.4, 0.4))
        det = corners(rc, body, sticker, int(rng.integers(4)), 0.5, rng)
        for use_inner in (False, True):
            sol = solve_pose(det, _rot(det, rc, body, sticker), sticker, rc, config=PoseConfig(use_inner=use_inner))
            errs[use_inner].append(pose_error(sol.poses[0], body, rc)[0])
    m4, m8 = np.median(errs[False]), np.median(errs[True])
    assert m4 < 0.03, m4
    assert m8 < 0.8 * m4, (m4, m8)


def _rot(det, rc, body, sticker) -> int:
    """Rotation of a detection built by :func:`corners` (index of the canonical TL corner)."""
    T_cs = invert(body @ rc.T_body_camera) @ sticker
    tl = rc.camera.project(transform_points(T_cs, OUTER_CORNERS[:1]))[0]
    return int(np.argmin(np.linalg.norm(det.outer - tl, axis=1)))


def test_realistic_noise_under_1cm():
    """0.15 px noise, 1.5 m, all 8 corners: median camera position error under 1 cm."""
    rng = np.random.default_rng(2)
    rc = rig_camera()
    errs = []
    for _ in range(100):
        body, sticker = scene(rng, rc, 1.5, rng.uniform(-0.4, 0.4))
        r = int(rng.integers(4))
        sol = solve_pose(corners(rc, body, sticker, r, 0.15, rng), r, sticker, rc)
        errs.append(pose_error(sol.poses[0], body, rc)[0])
    assert np.median(errs) < 0.01, np.median(errs)


def mean_nees(
    rng: np.random.Generator,
    distances: tuple[float, float],
    noise: float,
    corner_sigma_px: float | None,
    config: PoseConfig,
    shared: float = 0.0,
    n: int = 300,
) -> float:
    """Mean NEES of the body (x, y, yaw) over ``n`` stickers at ``distances`` (m) with independent
    corner noise ``noise`` px and, when ``shared``, every corner also moved by one shared error of
    that sigma (px) along its direction from the corners' centre (the outline larger or smaller)."""
    rc = rig_camera()
    nees = []
    for _ in range(n):
        body, sticker = scene(rng, rc, rng.uniform(*distances), rng.uniform(-0.4, 0.4))
        r = int(rng.integers(4))
        det = corners(rc, body, sticker, r, noise, rng)
        if shared:
            pts = np.vstack([det.outer, det.inner])
            u = pts - pts.mean(axis=0)
            pts = pts + rng.normal(0.0, shared) * u / np.linalg.norm(u, axis=1, keepdims=True)
            det = Detection(pts[:4], pts[4:])
        sol = solve_pose(det, r, sticker, rc, corner_sigma_px=corner_sigma_px, config=config)
        _, d = pose_error(sol.poses[0], body, rc)
        nees.append(d @ np.linalg.solve(sol.poses[0].cov, d))
    return float(np.mean(nees))


@pytest.mark.parametrize("estimated", [False, True])
def test_covariance_is_honest(estimated):
    """NEES of body (x, y, yaw) averages ~3 over noisy trials (given or estimated sigma)."""
    sigma, n = 0.4, 300
    # Independent corner noise only: no error shared by the corners (outline_scale_px 0).
    config = PoseConfig(min_sigma_px=0.05, outline_scale_px=0.0)
    mean = mean_nees(np.random.default_rng(3), (1.3, 2.0), sigma, None if estimated else sigma, config, n=n)
    if estimated:
        # sigma from 10 residual dof: the NEES is then ~3 F(3, 10)-distributed, mean 3 * 10/8.
        assert 2.5 < mean < 5.0, mean
    else:
        lo, hi = chi2.ppf([0.005, 0.995], 3 * n) / n
        assert lo < mean < hi, (mean, lo, hi)
    # and not a constant: closer stickers give tighter covariances
    assert np.isfinite(mean)


@pytest.mark.parametrize("stated", [True, False])
def test_outline_scale_error_is_in_the_covariance(stated):
    """Corners all moved along their directions from the sticker's centre by one shared error (the
    outline seen larger or smaller) fit with no residual, as a change of range: the covariance
    carries it through ``outline_scale_px`` (NEES ~3), and without that term the far fixes it
    moves are overconfident."""
    shared, noise, n = 0.25, 0.1, 300
    config = PoseConfig(min_sigma_px=0.05, outline_scale_px=shared if stated else 0.0)
    mean = mean_nees(np.random.default_rng(11), (2.0, 3.5), noise, noise, config, shared=shared, n=n)
    lo, hi = chi2.ppf([0.005, 0.995], 3 * n) / n
    if stated:
        assert lo < mean < hi, (mean, lo, hi)
    else:
        assert mean > 2 * hi, mean


def test_covariance_grows_with_distance():
    """The vest point is the camera's mount, so its (x, y) is as certain as the camera centre: best
    at middle distances (a sticker nearly under the camera trades its tilt for its position), then
    growing with distance; the heading's variance grows with distance throughout."""
    rng = np.random.default_rng(4)
    rc = rig_camera()
    traces, yaws = [], []
    for dist in (1.8, 3.5):
        body, sticker = scene(rng, rc, dist)
        sol = solve_pose(corners(rc, body, sticker, 0, 0.0, rng), 0, sticker, rc, corner_sigma_px=0.3)
        traces.append(np.trace(sol.poses[0].cov[:2, :2]))
        yaws.append(sol.poses[0].cov[2, 2])
    assert traces[1] > 2 * traces[0]
    assert yaws[1] > 2 * yaws[0]


def test_head_on_is_ambiguous_oblique_is_not():
    """Looking straight down at a sticker under the camera both IPPE poses fit: flagged ambiguous."""
    rng = np.random.default_rng(5)
    down = rig_camera(1.3, 90.0)
    body, sticker = scene(rng, down)
    sol = solve_pose(corners(down, body, sticker, 0, 0.3, rng), 0, sticker, down, corner_sigma_px=0.3)
    assert sol.ambiguous and len(sol.poses) == 2
    assert sol.poses[0].reprojection_px <= sol.poses[1].reprojection_px
    rc = rig_camera()
    amb = 0
    for _ in range(20):
        body, sticker = scene(rng, rc, 1.5, rng.uniform(-0.3, 0.3))
        sol = solve_pose(corners(rc, body, sticker, 0, 0.15, rng), 0, sticker, rc)
        amb += sol.ambiguous
        cam_err, _ = pose_error(sol.poses[0], body, rc)
        assert cam_err < 0.05
    assert amb <= 2


def test_bad_rotation_raises():
    from tagloc.core.errors import InputError

    rng = np.random.default_rng(6)
    rc = rig_camera()
    body, sticker = scene(rng, rc, 1.5)
    with pytest.raises(InputError):
        solve_pose(corners(rc, body, sticker, 0, 0.0, rng), 4, sticker, rc)


def test_detection_states_its_own_corner_noise():
    """A coarse detector's stated corner noise (the paper's method) sets the covariance; an explicit
    argument still wins."""
    rng = np.random.default_rng(11)
    rc = rig_camera()
    body, sticker = scene(rng, rc, distance=1.5)
    det = corners(rc, body, sticker, 0, 0.0, rng)
    four = Detection(outer=det.outer, inner=None)
    # The corner noise alone (the outline's shared error does not scale with it).
    plain = PoseConfig(outline_scale_px=0.0)
    base = solve_pose(four, 0, sticker, rc, config=plain).poses[0].cov
    coarse = Detection(outer=det.outer, inner=None, corner_sigma_px=2.0)
    sol = solve_pose(coarse, 0, sticker, rc, config=plain)
    assert sol.sigma_px == 2.0
    assert np.allclose(sol.poses[0].cov, base * (2.0 / PoseConfig().sigma_4pt_px) ** 2, rtol=1e-6)
    assert solve_pose(coarse, 0, sticker, rc, corner_sigma_px=0.5).sigma_px == 0.5


@pytest.mark.parametrize("x_m", [0.0, 0.15])
def test_tilted_torso_reports_the_vest_point_projected_vertically(x_m):
    """A torso leaning 8 deg (roll) and 5 deg (pitch) about its vest point: the fix's (x, y) is the
    vest point's vertical projection and its yaw the heading of the body's +x axis; the old
    definition (the body origin carried through the tilt) was 1.3 m sin(tilt) off."""
    rng = np.random.default_rng(21)
    rc = RigCamera("front", default_camera(), looking_forward(1.3, 55.0, x_m=x_m))
    vest = rc.vest_point
    assert np.allclose(vest, [0.0, 0.0, 1.3])
    upright, sticker = scene(rng, rc, 1.6, 0.1)
    tilt = np.eye(4)
    tilt[:3, :3] = Rotation.from_euler("xyz", [math.radians(8.0), math.radians(5.0), 0.0]).as_matrix()
    # Rotate the torso about the vest point: T_world_body = upright @ T(vest) @ tilt @ T(-vest).
    to_vest, back = np.eye(4), np.eye(4)
    to_vest[:3, 3], back[:3, 3] = vest, -vest
    T_world_body = upright @ to_vest @ tilt @ back
    sol = solve_pose(corners(rc, T_world_body, sticker, 0, 0.0, rng), 0, sticker, rc)
    fix = sol.poses[0]
    p_vest = T_world_body[:3, :3] @ vest + T_world_body[:3, 3]
    heading = math.atan2(T_world_body[1, 0], T_world_body[0, 0])
    assert np.allclose(fix.body[:2], p_vest[:2], atol=1e-6)
    assert abs(wrap_angle(fix.body[2] - heading)) < 1e-6
    # The vest point did not move under the tilt: the upright pose's (x, y).
    assert np.allclose(fix.body[:2], upright[:2, 3], atol=1e-6)
    old = planar_from_T(T_world_body)
    assert np.hypot(old[0] - fix.body[0], old[1] - fix.body[1]) > 0.1
    # Its covariance is the camera centre's (about a centimetre at 1.6 m), not the floor point's.
    sigma = np.sqrt(np.linalg.eigvalsh(fix.cov[:2, :2]))
    assert 0.001 < sigma.max() < 0.05


def test_batched_body_jacobian_matches_one_difference_at_a_time():
    """The covariance's Jacobian, all 12 evaluations in one pass, equals the column-by-column central
    differences of _body_from_rt (cv2.Rodrigues per evaluation), small and large rotations alike."""
    from tagloc.core.geometry import T_from_rvec_tvec
    from tagloc.vision.pose import _body_from_rt, _body_jacobian

    rng = np.random.default_rng(5)
    h = 1e-6
    for k in range(30):
        rvec = rng.normal(size=(3, 1)) * (0.01 if k % 3 == 0 else 1.5)
        tvec = rng.normal(size=(3, 1)) + [[0.0], [0.0], [2.0]]
        T_ws = T_from_rvec_tvec(rng.normal(size=3), rng.normal(size=3))
        T_cb = T_from_rvec_tvec(rng.normal(size=3), rng.normal(size=3))
        vp = rng.normal(size=3)
        x0 = np.concatenate([rvec.ravel(), tvec.ravel()])
        ref = np.empty((3, 6))
        for i in range(6):
            d = np.zeros(6)
            d[i] = h
            diff = _body_from_rt(*np.split(x0 + d, 2), T_ws, T_cb, vp) - _body_from_rt(
                *np.split(x0 - d, 2), T_ws, T_cb, vp
            )
            diff[2] = wrap_angle(diff[2])
            ref[:, i] = diff / (2 * h)
        np.testing.assert_allclose(_body_jacobian(rvec, tvec, T_ws, T_cb, vp), ref, rtol=1e-6, atol=1e-8)
