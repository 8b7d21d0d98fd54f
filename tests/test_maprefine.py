"""Map refinement's pieces without rendering: odometry links, the apparent pose, the anchoring bound, the site survey."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tagloc.core.errors import InputError
from tagloc.core.geometry import invert, planar_T
from tagloc.core.rig import default_rig, vest_planar
from tagloc.core.stickermap import StickerMap
from tagloc.eval.mapbench import SITE_SURVEY, anchoring_bound, site_map, strip_site, without
from tagloc.eval.mapobs import FrameRecord
from tagloc.eval.maprefine import _compose, _links, apparent_poses, patch_rays
from tagloc.sim.survey import SurveyConfig, surveyed_map
from tagloc.vision.odometry import OdometryStep


def _view(T_world_camera: np.ndarray) -> np.ndarray:
    """(6,) rvec, tvec of T_camera_world."""
    T = invert(T_world_camera)
    return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])


def _apparent(rig_cam, T_world_camera: np.ndarray) -> np.ndarray:
    q, rays = patch_rays(rig_cam, 5)
    return apparent_poses(_view(T_world_camera)[None], q[None], rays[None])[0]


def test_apparent_pose_is_the_body_pose_at_the_nominal_mount():
    rc = replace(default_rig().cameras[0], legs_in_view=False)  # no legs in these views
    for body in ([0.0, 0.0, 0.0], [3.2, -1.5, 0.7], [-2.0, 4.0, -2.9]):
        T_world_camera = planar_T(*body) @ rc.T_body_camera
        np.testing.assert_allclose(_apparent(rc, T_world_camera), body, atol=1e-9)


def test_apparent_pose_moves_with_the_lean():
    """Pitching the torso forward by a small angle looks like floor motion through the fixed bird's-eye
    view: apart from the vest point's own motion, about 1.9 m per radian for the default rig (README,
    issue 14), and no turn."""
    rc = replace(default_rig().cameras[0], legs_in_view=False)  # no legs in these views
    a = math.radians(1.0)
    # Lean forward about the body's y axis through the floor point under the vest (the body origin).
    lean = np.eye(4)
    lean[:3, :3] = Rotation.from_euler("y", a).as_matrix()
    moved = _apparent(rc, lean @ rc.T_body_camera)
    assert abs(moved[2]) < 1e-6 and abs(moved[1]) < 1e-6
    vest = vest_planar(lean, rc.vest_point)
    assert vest[0] == pytest.approx(rc.vest_point[2] * math.sin(a))
    assert 1.7 < abs(moved[0] - vest[0]) / a < 2.1


def test_compose_planar_motions_and_their_covariance():
    d, cov = _compose(np.array([1.0, 0.0, math.pi / 2]), np.zeros((3, 3)), np.array([1.0, 0.0, 0.0]), np.eye(3) * 1e-4)
    np.testing.assert_allclose(d, [1.0, 1.0, math.pi / 2], atol=1e-12)
    # The second step's forward error is sideways in the first frame after a left quarter turn.
    np.testing.assert_allclose(cov, np.eye(3) * 1e-4, atol=1e-15)
    _, cov = _compose(np.zeros(3), np.diag([0.0, 0.0, 1e-4]), np.array([2.0, 0.0, 0.0]), np.zeros((3, 3)))
    assert cov[1, 1] == pytest.approx(4e-4)  # a heading error swings the end point through the lever
    assert cov[1, 2] == pytest.approx(2e-4)


def _frames(n: int, steps: dict[int, bool]) -> list[FrameRecord]:
    out = []
    for k in range(n):
        t = k / 30
        step = None
        if steps.get(k, True) and k > 0:
            step = OdometryStep((k - 1) / 30, t, np.array([0.04, 0.0, 0.01]), np.eye(3) * 1e-6, 0.9)
        out.append(FrameRecord(k, t, np.zeros(3), np.eye(3), "tracking", step=step))
    return out


def test_links_compose_the_steps_between_views_and_stop_at_a_missing_step():
    frames = _frames(10, {6: False})  # frame 6 has no step
    views = {0: 0, 3: 1, 5: 2, 8: 3, 9: 4}
    links = _links(frames, views, max_link_s=2.0)
    assert [(a, b) for a, b, _, _ in links] == [(0, 1), (1, 2), (3, 4)]  # 5 -> 8 crosses frame 6
    d, cov = links[0][2], links[0][3]
    assert d[2] == pytest.approx(0.03) and d[0] == pytest.approx(0.12, abs=1e-3)
    assert cov[0, 0] > 3e-6  # three steps' noise, plus the turn's swing
    assert _links(frames, {0: 0, 5: 1}, max_link_s=0.1) == []  # longer than the horizon


def test_anchoring_bound_of_a_perfect_shape_is_the_prior_fit():
    truth = strip_site(2, 10, 0.5)
    prior = surveyed_map(truth, SurveyConfig(0.01, 1.0, stated=True, seed=3), seed=0)
    ids = [int(i) for i in truth.ids]
    b = anchoring_bound(truth, prior, truth, ids)
    assert b.shape_rms_m < 1e-9  # the truth's shape is exact
    # Three rigid degrees of freedom over N stickers: sigma (per axis) * sqrt(3 / N) in position,
    # a little less for what the yaw priors add on the rotation.
    assert b.expected_rms_m == pytest.approx(0.01 * math.sqrt(3 / len(ids)), rel=0.1)
    assert b.expected_rms_m < 0.01 * math.sqrt(3 / len(ids))
    # The oracle's error is one rigid motion: far below the survey's own scatter.
    assert np.sqrt(np.mean(b.oracle_m**2)) < 0.5 * np.sqrt(np.mean(np.sum((prior.xy - truth.xy) ** 2, axis=1)))


def test_site_survey_is_one_survey_for_every_session():
    site = strip_site()
    floor_a = without(site, 1047)
    floor_b = without(site, 1066)
    a = surveyed_map(floor_a, SITE_SURVEY, seed=1)
    b = surveyed_map(floor_b, SITE_SURVEY, seed=2)
    for sid in (1000, 1029, 1079):
        np.testing.assert_array_equal(a.xy[a.row(sid)], b.xy[b.row(sid)])
    # The moved sticker is 15 cm (plus its survey error) from the truth.
    moved = site_map(site)
    off = np.hypot(*(moved.xy[moved.row(1029)] - site.xy[site.row(1029)]))
    assert 0.10 < off < 0.20
    assert 1066 not in moved and np.isfinite(moved.sigma_xy).all()
    # Without a site seed the draws are the session's, as before.
    old = surveyed_map(site, SurveyConfig(0.01, 1.0), seed=4)
    rng = np.random.default_rng([4, 37])
    np.testing.assert_allclose(old.xy - site.xy, rng.standard_normal((len(site), 2)) * 0.01)
    with pytest.raises(InputError, match="not in the map"):
        surveyed_map(StickerMap(np.array([1]), np.zeros((1, 2)), np.zeros(1)), SITE_SURVEY, seed=0)


def test_a_view_starts_from_the_stickers_that_agree_with_the_map_not_a_turned_one():
    """A view that sees a sticker laid 180 deg round since the survey, best fitted of its three, starts
    from the pose the other two give: started from the turned one (the best fit), the camera was 180
    deg off and the solve of the review's walk diverged (200 evaluations, then a singular factor)."""
    from pathlib import Path

    from tagloc.core.sticker import OUTER_CORNERS
    from tagloc.eval.mapobs import Sighting, WalkLog
    from tagloc.eval.maprefine import RefineConfig, _build

    rig = default_rig()
    T_wc = rig[0].T_body_camera  # body at the origin

    def floor(x_n: float) -> np.ndarray:
        ray = T_wc[:3, :3] @ np.array([x_n, 0.15, 1.0])
        c = T_wc[:3, 3]
        return (c - c[2] / ray[2] * ray)[:2]

    truth = StickerMap(np.array([1, 2, 3]), np.array([floor(-0.2), floor(0.0), floor(0.2)]), np.radians([180.0, 0, 0]))
    smap = StickerMap(truth.ids, truth.xy, np.zeros(3))  # the survey: sticker 1 at yaw 0
    sightings = []
    for sid, rms in ((1, 0.1), (2, 0.3), (3, 0.3)):
        T_cs = invert(T_wc) @ truth.T_world_sticker(sid)
        pts = T_cs[:3] @ np.vstack([OUTER_CORNERS.T, np.ones((1, 4))])
        s = Sighting(0, np.zeros(2), sid, "decoded", in_map=True, accepted=True)
        s.corners, s.T_camera_sticker, s.reprojection_px = rig[0].camera.project(pts.T), T_cs, rms
        sightings.append(s)
    fr = FrameRecord(0, 0.0, np.zeros(3), np.eye(3) * 1e-4, "tracking", sightings)
    prob = _build([WalkLog(Path("synthetic"), rig, [fr])], smap, RefineConfig(), set())
    T_cw = invert(T_wc)
    assert np.allclose(prob.x0_views[0, 3:], T_cw[:3, 3], atol=1e-6)
    assert np.allclose(prob.x0_views[0, :3], Rotation.from_matrix(T_cw[:3, :3]).as_rotvec(), atol=1e-6)
