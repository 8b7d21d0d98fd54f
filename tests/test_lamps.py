"""The lamp grid's light and the operator's shadow: normalised, where geometry puts it, in the frames."""

from __future__ import annotations

import numpy as np
import pytest

from tagloc.sim.lamps import LampConfig, Lamps

# One lamp within reach of everything near it: the shadow ratio is then that lamp's visible share.
LONE = LampConfig(spacing_m=200.0, height_m=9.0, reach=3.0)


def test_lamp_grid_averages_to_one_and_varies_little():
    """Under 9 m high lamps 6 m apart the floor is lit evenly: the mean is 1 (the session's lux) and
    the cos^4 sum of the lamps varies by under 2 % (measured +-1 %)."""
    lamps = Lamps(LampConfig(), seed=3)
    g = np.linspace(0.0, 30.0, 151)
    e = lamps.illuminance(np.stack(np.meshgrid(g, g), -1).reshape(-1, 2))
    assert e.mean() == pytest.approx(1.0, abs=0.005)
    assert e.min() > 0.98 and e.max() < 1.02
    # Lower lamps closer together light the floor less evenly, but still on average 1.
    low = Lamps(LampConfig(spacing_m=4.0, height_m=4.5), seed=3)
    el = low.illuminance(np.stack(np.meshgrid(g, g), -1).reshape(-1, 2))
    assert el.mean() == pytest.approx(1.0, abs=0.005) and el.max() - el.min() > e.max() - e.min()


def test_shadow_of_the_head_ends_where_the_ray_grazes_it():
    """A lamp 3 m behind the body: along the line through both, the ray to the lamp grazes the head
    (radius 0.09 m, top 1.75 m, a fraction s = 1.75 / 9 of the way up) at x = (0.09 + 3 s) / (1 - s)
    = 0.836 m ahead of the body's axis. There half the luminaire is hidden; the penumbra's half-width
    on the floor (0.3 s / (1 - s) = 7.2 cm) nearer it all is hidden, as far beyond it all visible."""
    lamps = Lamps(LONE, seed=0)
    lamp = lamps.offset + 200.0
    body = np.r_[lamp + np.array([3.0, 0.0]), 0.0]  # (x, y, yaw): facing +x, away from the lamp
    s = LONE.stature_m / LONE.height_m
    edge = (LONE.head_radius_m + 3.0 * s) / (1.0 - s)
    half = 0.5 * LONE.size_m * s / (1.0 - s)
    x = np.array([edge - half - 0.01, edge, edge + half + 0.01, 0.5, 2.5])
    share = lamps.shadow(body[:2] + np.c_[x, np.zeros_like(x)], body)
    assert share[0] == pytest.approx(0.0, abs=1e-6)
    assert share[1] == pytest.approx(0.5, abs=0.02)
    assert share[2] == pytest.approx(1.0, abs=1e-6)
    assert share[3] == pytest.approx(0.0, abs=1e-6)  # in the torso's shadow
    assert share[4] == pytest.approx(1.0, abs=1e-6)
    # Beside the body, beyond the torso's radius and penumbra, the light is whole.
    side = lamps.shadow(body[:2] + np.array([[0.6, 0.35], [0.6, -0.35]]), body)
    np.testing.assert_allclose(side, 1.0, atol=1e-6)


def test_no_body_no_shadow_and_a_point_source_casts_a_hard_one():
    lamps = Lamps(LONE, seed=0)
    pts = lamps.offset + 200.0 + np.array([[3.5, 0.0], [4.5, 0.0]])
    np.testing.assert_allclose(lamps.illuminance(pts, None), lamps.illuminance(pts))
    hard = Lamps(LampConfig(spacing_m=200.0, size_m=0.0), seed=0)
    body = np.r_[hard.offset + 200.0 + np.array([3.0, 0.0]), 0.0]
    s = LONE.stature_m / LONE.height_m
    edge = (LONE.head_radius_m + 3.0 * s) / (1.0 - s)
    share = hard.shadow(body[:2] + np.array([[edge - 0.002, 0.0], [edge + 0.002, 0.0]]), body)
    np.testing.assert_allclose(share, [0.0, 1.0], atol=1e-9)


def test_axis_stands_behind_the_vest_point_and_the_legs_beside_it():
    from tagloc.core.geometry import planar_T

    lamps = Lamps(LampConfig(axis_behind_m=0.12), seed=0)
    axis = lamps.axis(planar_T(2.0, 1.0, np.pi / 2), np.array([0.0, 0.0, 1.3]))
    np.testing.assert_allclose(axis, [2.0, 0.88, np.pi / 2], atol=1e-9)
    # Facing +y towards a lamp 3 m ahead, the legs stand 0.1 m to either side in x: the floor
    # between them is lit (its ray to the lamp passes the torso 0.3 m ahead of its axis), the floor
    # under each leg is not.
    lone = Lamps(LONE, seed=0)
    body = np.r_[lone.offset + 200.0 - np.array([0.0, 3.0]), np.pi / 2]
    share = lone.shadow(body[:2] + np.array([[0.0, 0.0], [0.1, 0.0], [-0.1, 0.0]]), body)
    np.testing.assert_allclose(share, [1.0, 0.0, 0.0], atol=1e-6)


def test_rendered_frame_darkens_ahead_of_the_body_only():
    """A frame rendered with the body's shadow under low lamps (4.5 m up, one 1.5 m behind the body)
    against the same frame without: the bottom middle of the image, the floor just ahead of the
    chest, is darker by the model's share there (within 3 %), the top corners are not."""
    from tagloc.core.camera import default_camera
    from tagloc.core.geometry import planar_T
    from tagloc.core.rig import looking_forward
    from tagloc.core.stickermap import StickerMap
    from tagloc.sim.floor import Floor, FloorConfig
    from tagloc.sim.render import SensorConfig
    from tagloc.sim.simulate import render_view

    cam = default_camera()
    lamps = Lamps(LampConfig(spacing_m=4.0, height_m=4.5), seed=2)
    body = np.r_[lamps.offset + np.array([4.0 * 5 + 1.5, 4.0 * 5]), 0.0]
    T_world_body = planar_T(body[0] + 0.12, body[1], 0.0)
    T = T_world_body @ looking_forward(1.3, 55.0)
    floor = Floor(StickerMap(np.array([1]), np.array([[80.0, 80.0]]), np.array([0.0])), FloorConfig(), seed=1)
    kw = dict(noise=False, exposure_s=0.002, gain=4.0)
    lit = render_view(floor, cam, T, 300.0, **kw).image.astype(float)
    shaded = render_view(floor, cam, T, 300.0, lamps=lamps, body=body, **kw).image.astype(float)
    H, W = lit.shape
    gamma = SensorConfig().gamma
    # The 8-bit image is the linear signal to the power 1 / gamma: compare in linear light.
    ratio = (
        shaded[H - 60 : H - 20, W // 2 - 20 : W // 2 + 20].mean()
        / lit[H - 60 : H - 20, W // 2 - 20 : W // 2 + 20].mean()
    ) ** gamma
    assert ratio < 0.9
    # The floor seen there, from the camera's pose, and the model's share at it.
    from tagloc.sim.render import Renderer

    r = Renderer(floor, cam)
    from tagloc.sim.render import _floor_hits

    xy, ok = _floor_hits(T, r._K_inv, np.array([[W / 2, H - 40.0]]) - r.canvas_origin, 8.0)
    assert ok.all()
    assert ratio == pytest.approx(float(lamps.shadow(xy, body)[0]), abs=0.03)
    for sl in (np.s_[20:60, 20:60], np.s_[20:60, W - 60 : W - 20]):
        assert (shaded[sl].mean() / lit[sl].mean()) ** gamma == pytest.approx(1.0, abs=0.01)
