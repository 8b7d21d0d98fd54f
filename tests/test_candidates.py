"""Tests of candidate selection: footprint, projection, pixel covariance, gating and ranking."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from tagloc.core.geometry import invert, planar_T, transform_points
from tagloc.core.rig import RigCamera, default_rig
from tagloc.core.stickermap import StickerMap
from tagloc.core.types import IdSource, PoseFix
from tracker.candidates import CandidateConfig, footprint, predicted_pixels, project_map, select_candidates
from tracker.tracker import Tracker

QUIET = CandidateConfig(pixel_sigma=0.0, tilt_sigma=0.0, bob_sigma=0.0)


def grid_map(rng, n_side=60, spacing=1.5, jitter=0.3) -> StickerMap:
    g = np.stack(np.meshgrid(np.arange(n_side), np.arange(n_side)), -1).reshape(-1, 2) * spacing
    xy = g + rng.uniform(-jitter, jitter, g.shape)
    return StickerMap(np.arange(len(xy)) + 1000, xy, rng.uniform(-np.pi, np.pi, len(xy)))


def brute_pixels(mean, smap: StickerMap, rc: RigCamera):
    """All map centres through the full 4x4 chain and Camera.project (reference, no shortcuts)."""
    T_cam_world = invert(planar_T(*mean) @ rc.T_body_camera)
    p_c = transform_points(T_cam_world, np.c_[smap.xy, np.zeros(len(smap))])
    front = p_c[:, 2] > 0.1
    pix = np.full((len(smap), 2), np.nan)
    pix[front] = rc.camera.project(p_c[front])
    return pix, front


def test_footprint_of_the_default_rig():
    rc = default_rig()[0]  # 1.3 m high, pitched 55 deg, vertical FOV +-20.7 deg
    fp = footprint(rc)
    near, far = fp.polygon[:, 0].min(), fp.polygon[:, 0].max()
    half = math.atan(486 / 1285.7)
    assert near == pytest.approx(1.3 / math.tan(math.radians(55) + half), abs=0.02)
    assert far == pytest.approx(1.3 / math.tan(math.radians(55) - half), abs=0.06)
    assert abs(fp.polygon[:, 1].max() + fp.polygon[:, 1].min()) < 1e-6  # symmetric left/right
    assert footprint(rc) is fp  # cached
    # A camera looking at the horizon is clipped at the configured range.
    from tagloc.core.rig import looking_forward

    flat = RigCamera("flat", rc.camera, looking_forward(1.3, 5.0))
    assert footprint(flat, CandidateConfig(max_range=4.0)).polygon[:, 0].max() == pytest.approx(4.0, abs=1e-6)


def test_footprint_cache_stays_small_as_the_lean_changes():
    """The tracker's leaned camera is a new object with a new pose whenever the lean changes: the
    cache keeps the last few by content (a leaned camera equal to an earlier one finds it), not
    one entry per lean for the whole shift."""
    import dataclasses

    import tracker.candidates as cand

    rc = default_rig()[0]
    fresh, alive = {}, []  # every camera kept alive, so none shares an earlier one's identity
    for k in range(200):
        roll = math.radians(0.05 * k)
        T = np.eye(4)
        T[1:3, 1:3] = [[math.cos(roll), -math.sin(roll)], [math.sin(roll), math.cos(roll)]]
        leaned = dataclasses.replace(rc, T_body_camera=T @ rc.T_body_camera)
        alive.append(leaned)
        fp = footprint(leaned)
        if k % 50 == 0:
            fresh[k] = (leaned, fp)
        assert len(cand._FOOTPRINTS) <= cand._FOOTPRINTS_KEPT
    last_leaned, last_fp = fresh[150]
    again = dataclasses.replace(last_leaned, T_body_camera=last_leaned.T_body_camera.copy())
    cand._FOOTPRINTS.clear()
    assert np.array_equal(footprint(again).polygon, last_fp.polygon)
    assert footprint(dataclasses.replace(again)) is footprint(again)  # equal content: cached


def test_tracker_candidates_reuse_one_priors_projection_and_only_that(rng):
    """Several stickers detected under one prior get what select_candidates gives each; once a fix
    moves the prior, the projection is made afresh (a reused one would gate the old pose)."""
    smap = grid_map(rng, 10, spacing=0.6)  # dense enough for several stickers in view
    rc = default_rig()[0]
    pose = np.array([3.0, 3.0, 0.2])
    pr = project_map(pose, smap, rc)
    seen = [pr.pixels[i] + np.array([2.0, -1.0]) for i in np.flatnonzero(pr.in_image)]
    assert len(seen) >= 3
    tr = Tracker()
    tr.predict(0.0)
    tr.update([PoseFix(np.eye(4), pose, np.diag([1e-4, 1e-4, 1e-4]), 0.3)], 1, IdSource.DECODED, 0.0)

    def fresh(px):
        mean, cov = tr.prior()
        return select_candidates(mean, cov, smap, tr.leaned_camera(rc), px)

    first = [tr.candidates(smap, rc, px) for px in seen]
    assert first == [fresh(px) for px in seen] and all(first)
    kept = tr._predicted
    assert [tr.candidates(smap, rc, px) for px in seen] == first and tr._predicted is kept  # reused
    nudged = pose + np.array([0.02, -0.01, 0.0])  # a second fix moves the prior
    res = tr.update([PoseFix(np.eye(4), nudged, np.diag([1e-4, 1e-4, 1e-4]), 0.3)], 2, IdSource.DECODED, 0.0)
    assert res.accepted and tr._predicted is kept  # made only when asked
    after = [tr.candidates(smap, rc, px) for px in seen]
    assert tr._predicted is not kept and after == [fresh(px) for px in seen]


def test_project_map_matches_brute_force(rng):
    smap = grid_map(rng, 20)
    rc = default_rig()[0]
    for _ in range(10):
        mean = np.array([rng.uniform(3, 25), rng.uniform(3, 25), rng.uniform(-np.pi, np.pi)])
        pr = project_map(mean, smap, rc)
        pix, front = brute_pixels(mean, smap, rc)
        cam = rc.camera
        # Visible: distorted pixel in the image and the ray inside the lens's field (beyond it the
        # distortion polynomial folds far-off points back into the image).
        corners = np.array([[0, 0], [cam.width - 1, 0], [cam.width - 1, cam.height - 1], [0, cam.height - 1]], float)
        r_max = np.hypot(*cv2.undistortPoints(corners.reshape(-1, 1, 2), cam.K, cam.dist).reshape(-1, 2).T).max()
        T_cam_world = invert(planar_T(*mean) @ rc.T_body_camera)
        p_c = transform_points(T_cam_world, np.c_[smap.xy, np.zeros(len(smap))])
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.hypot(p_c[:, 0], p_c[:, 1]) / p_c[:, 2]
        inside = (
            front
            & (r <= r_max * 1.01)
            & (pix[:, 0] >= 0)
            & (pix[:, 0] <= cam.width - 1)
            & (pix[:, 1] >= 0)
            & (pix[:, 1] <= cam.height - 1)
        )
        assert set(pr.rows[pr.in_image].tolist()) == set(np.flatnonzero(inside).tolist())
        np.testing.assert_allclose(pr.pixels, pix[pr.rows], atol=1e-6)
        np.testing.assert_array_equal(pr.ids, smap.ids[pr.rows])


def test_pixel_covariance_is_jacobian_propagation(rng):
    """With no extra noise, C = J P J^T with J from finite differences of the projection."""
    smap = grid_map(rng, 20)
    rc = default_rig()[0]
    rows = []
    while len(rows) < 2:
        mean = np.array([rng.uniform(5, 20), rng.uniform(5, 20), rng.uniform(-np.pi, np.pi)])
        rows = project_map(mean, smap, rc).rows
    P = np.array([[0.04, 0.01, 0.002], [0.01, 0.02, -0.001], [0.002, -0.001, 0.003]])
    kept, pix, C = predicted_pixels(mean, P, smap, rc, rows, QUIET)
    ref_pix, _ = brute_pixels(mean, smap, rc)
    np.testing.assert_allclose(pix, ref_pix[kept], atol=1e-6)
    eps = 1e-6
    J = np.zeros((len(kept), 2, 3))
    for j in range(3):
        d = np.zeros(3)
        d[j] = eps
        J[:, :, j] = (brute_pixels(mean + d, smap, rc)[0][kept] - brute_pixels(mean - d, smap, rc)[0][kept]) / (2 * eps)
    np.testing.assert_allclose(C, J @ P @ J.transpose(0, 2, 1), rtol=1e-4, atol=1e-6)


def test_camera_bob_term(rng):
    """bob_sigma adds the pixel motion of raising the camera, squared."""
    smap = grid_map(rng, 20)
    rc = default_rig()[0]
    rows = []
    while len(rows) < 2:
        mean = np.array([rng.uniform(5, 20), rng.uniform(5, 20), rng.uniform(-np.pi, np.pi)])
        rows = project_map(mean, smap, rc).rows
    s = 0.025
    kept, _, C = predicted_pixels(mean, np.zeros((3, 3)), smap, rc, rows, CandidateConfig(0.0, 0.0, s))
    up = RigCamera("up", rc.camera, rc.T_body_camera.copy())
    up.T_body_camera[2, 3] += 1e-6
    u = (brute_pixels(mean, smap, up)[0][kept] - brute_pixels(mean, smap, rc)[0][kept]) / 1e-6
    np.testing.assert_allclose(C, s**2 * u[:, :, None] * u[:, None, :], rtol=1e-3, atol=1e-6)


def test_true_sticker_is_among_candidates(rng):
    """Prior drawn from its own covariance; the seen sticker should be in the list, usually first."""
    smap = grid_map(rng, 40)
    rc = default_rig()[0]
    cam = rc.camera
    cov = np.diag([0.15**2, 0.15**2, math.radians(5) ** 2])
    found = first = trials = 0
    sizes = []
    while trials < 200:
        truth = np.array([rng.uniform(5, 50), rng.uniform(5, 50), rng.uniform(-np.pi, np.pi)])
        pr = project_map(truth, smap, rc)
        if not pr.in_image.any():
            continue
        k = int(rng.choice(np.flatnonzero(pr.in_image)))
        observed = pr.pixels[k] + rng.normal(0, 2.0, 2)
        prior = truth + rng.multivariate_normal(np.zeros(3), cov)
        ids = select_candidates(prior, cov, smap, rc, observed, k=5)
        trials += 1
        sizes.append(len(ids))
        found += int(pr.ids[k]) in ids
        first += bool(ids) and ids[0] == int(pr.ids[k])
        assert len(set(ids)) == len(ids) <= 5
        assert -10 <= observed[0] < cam.width + 10
    assert found / trials >= 0.97
    assert first / trials >= 0.8
    assert np.mean(sizes) < 3.0  # the gate narrows ~1000 stickers to a few


def test_no_candidates_when_nothing_fits(rng):
    smap = grid_map(rng, 10)
    rc = default_rig()[0]
    cov = np.diag([0.01, 0.01, 0.001])
    assert select_candidates(None, None, smap, rc, np.array([600.0, 500.0])) == []
    # Far from every mapped sticker.
    assert select_candidates(np.array([500.0, 500.0, 0.0]), cov, smap, rc, np.array([600.0, 500.0])) == []
    # Somewhere with stickers in view, but a pixel far from all their predictions.
    mean = np.array([7.0, 7.0, 0.3])
    while not project_map(mean, smap, rc).in_image.any():
        mean = np.array([rng.uniform(3, 10), rng.uniform(3, 10), rng.uniform(-np.pi, np.pi)])
    assert select_candidates(mean, cov, smap, rc, np.array([-4000.0, -4000.0])) == []


def test_ranking_prefers_the_nearer_prediction(rng):
    """Two stickers 0.5 m apart in view: the one predicted nearer the observed pixel comes first."""
    smap = StickerMap([1, 2], [[1.0, 0.0], [1.0, 0.5]], [0.0, 0.0])
    rc = default_rig()[0]
    mean = np.zeros(3)
    pr = project_map(mean, smap, rc)
    assert pr.in_image.all()
    cov = np.diag([0.3**2, 0.3**2, 0.05**2])
    for target in (0, 1):
        observed = pr.pixels[target] + np.array([3.0, -2.0])
        ids = select_candidates(mean, cov, smap, rc, observed)
        assert ids[0] == smap.ids[pr.rows[target]]
        assert len(ids) == 2


def test_tracker_candidates_only_while_tracking(rng):
    smap = grid_map(rng, 10)
    rc = default_rig()[0]
    pose = np.array([6.0, 6.0, 0.2])
    pr = project_map(pose, smap, rc)
    observed = pr.pixels[np.flatnonzero(pr.in_image)[0]]
    tr = Tracker()
    tr.predict(0.0)
    assert tr.candidates(smap, rc, observed) == []
    tr.update([PoseFix(np.eye(4), pose, np.diag([1e-4, 1e-4, 1e-4]), 0.3)], 1, IdSource.DECODED, 0.0)
    ids = tr.candidates(smap, rc, observed)
    assert ids and ids[0] == int(pr.ids[np.flatnonzero(pr.in_image)[0]])
    tr.predict(30.0)  # long gap: LOST, no candidates
    assert tr.candidates(smap, rc, observed) == []


def test_footprint_sampling_and_map_query_margin_come_from_the_config():
    """The footprint's rays per image side (``border_samples``, 17) and the map search's margin
    beyond its bounding circle (``query_margin_m``, one sticker side) are CandidateConfig values: a
    sticker 5 cm beyond the circle (its centre still within the image margin) is projected with the
    default margin and not without one."""
    rc = default_rig()[0]
    assert CandidateConfig().border_samples == 17 and CandidateConfig().query_margin_m == 0.1
    assert len(footprint(rc).polygon) == 4 * 17
    coarse = footprint(rc, CandidateConfig(border_samples=5))
    assert len(coarse.polygon) == 4 * 5 and coarse is not footprint(rc)  # cached apart
    fp = footprint(rc)
    x = fp.centre[0] + fp.radius + 0.05
    smap = StickerMap(np.array([7]), np.array([[x, 0.0]]), np.zeros(1))
    body = np.zeros(3)
    assert list(project_map(body, smap, rc).ids) == [7]
    assert len(project_map(body, smap, rc, CandidateConfig(query_margin_m=0.0)).ids) == 0
