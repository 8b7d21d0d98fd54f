"""The wearer's legs in the simulator, and the floor the odometry leaves to them."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tagloc.core.stickermap import load_map
from tagloc.sim.legs import Legs
from tagloc.sim.simulate import SimConfig, simulate_walk
from tagloc.sim.walk import WalkConfig

DEMO_MAP = Path(__file__).resolve().parents[1] / "maps" / "demo.csv"


@pytest.fixture(scope="module")
def walk():
    cfg = SimConfig(seconds=8.0, seed=4, speed_mps=1.3, walk=WalkConfig(stop_every_s=0.0))
    return simulate_walk(load_map(DEMO_MAP), cfg)


def test_feet_alternate_and_stand_still_in_stance(walk):
    """Footprints alternate left and right of the walking line by the step width; consecutive ones
    are a step length apart along the walk (speed over cadence, within 20 %: the two are taken at
    the two strikes); a foot in stance does not move, and each foot is in stance for its fraction
    of the gait cycle."""
    legs = Legs(walk)
    cfg = legs.config
    falls = legs._falls
    assert len(falls) >= 15  # 10 s of walk (it runs 1 s beyond each end) at ~1.8 steps a second
    straight = 0
    for (k0, t0, h0, yaw0), (k1, t1, h1, yaw1) in zip(falls, falls[1:]):
        assert k1 == k0 + 1
        if abs(math.remainder(yaw1 - yaw0, 2 * math.pi)) > math.radians(5):
            continue  # in a bend the step's length leans into the across direction
        straight += 1
        fwd, left = np.array([math.cos(yaw0), math.sin(yaw0)]), np.array([-math.sin(yaw0), math.cos(yaw0)])
        side = 1.0 if k0 % 2 == 0 else -1.0
        # The next footprint is on the other side, a step width across (the path bends a little).
        assert float((h1 - h0) @ left) * side == pytest.approx(-cfg.step_width_m, abs=0.04)
        cadence = 1.0 / (t1 - t0)
        step = float(walk.speed(0.5 * (t0 + t1))) / cadence
        assert float((h1 - h0) @ fwd) == pytest.approx(step, rel=0.2)
    assert straight >= 12
    planted = 0
    ts = np.arange(2.0, 7.0, 0.01)
    for side in (1.0, -1.0):
        heels = np.array([legs.feet(t)[side][0] for t in ts])
        lifts = np.array([legs.feet(t)[side][2] for t in ts])
        still = np.hypot(*np.diff(heels, axis=0).T) < 1e-9
        planted += still.sum()
        # Planted: no lift. Stance is 60 % of the cycle (a little less counted on sampled steps).
        assert np.all(lifts[1:][still] == 0.0)
        assert 0.5 < still.mean() < 0.65
    assert planted > 0


def test_a_standing_walker_keeps_both_feet_down():
    """In a stop the phase stops: from the stop's start on (the walker has braked to it), both feet
    stay where they are, on the floor."""
    w = simulate_walk(load_map(DEMO_MAP), SimConfig(seconds=20.0, seed=2))
    (t0, t1), *_ = w.stops  # 18.6-19.6 s
    legs = Legs(w)
    a, b = legs.feet(t0 + 0.05), legs.feet(t1 - 0.05)
    for side in (1.0, -1.0):
        assert np.hypot(*(a[side][0] - b[side][0])) < 1e-3
        assert a[side][2] < 1e-4 and b[side][2] < 1e-4  # on the floor (the spline's speed is ~1e-7 m/s)


def test_legs_are_painted_where_the_camera_looks_down_only(walk):
    """At 65 degrees the lower image shows the legs at some time of the step (dark pixels where the
    floor alone is bright); the upper image never; at 30 degrees (looking far ahead) the frame is
    the same with and without them."""
    from tagloc.core.camera import default_camera
    from tagloc.core.rig import looking_forward
    from tagloc.sim.floor import Floor, FloorConfig
    from tagloc.sim.render import Renderer

    cam = default_camera()
    floor = Floor(load_map(DEMO_MAP), FloorConfig(), seed=1)
    legs = Legs(walk)
    changed_low, changed_high = 0.0, 0.0
    for pitch in (65.0, 30.0):
        T_body_camera = looking_forward(1.3, pitch)
        for t in (3.0, 3.13, 3.26):
            T = walk.T_world_camera(t, T_body_camera)
            r = Renderer(floor, cam)
            r._ensure_mosaic(T[None])
            rows = r.visible_rows(T[None])
            roi = (0, 0, *r.canvas_size)
            bare = r._render_roi(T, roi, rows)
            painted = bare.copy()
            legs.paint(painted, T, r.K_canvas, t)
            diff = np.abs(painted.astype(int) - bare.astype(int)) > 20
            h = diff.shape[0]
            if pitch == 65.0:
                changed_low += diff[h // 2 :].mean()
                changed_high += diff[: h // 4].mean()
            else:
                assert not diff.any()
    assert changed_low > 0.05  # a few per cent of the lower half, summed over three instants
    assert changed_high == 0.0


def test_odometry_leaves_the_legs_floor_out():
    """For a camera that sees the legs (its rig says so, or, not stated, it sees the floor within
    the reach), the patch's near edge starts ``legs_reach_m`` ahead of the vest point and no flow
    point sees the zone; for one that does not, or with the zone set to 0, the patch is the largest
    square nearest the camera, as before."""
    from dataclasses import replace

    from tagloc.core.camera import default_camera
    from tagloc.core.rig import RigCamera, floor_under_pixels, looking_forward
    from tagloc.vision.odometry import FloorOdometry, OdometryConfig, floor_patch

    plain = RigCamera("front", default_camera(), looking_forward(1.3, 65.0), legs_in_view=False)
    legs = replace(plain, legs_in_view=True)
    cfg = OdometryConfig()
    # Not stated, a forward camera that sees the floor within the reach is taken to see the legs.
    assert floor_patch(replace(plain, legs_in_view=None), cfg).x_near == floor_patch(legs, cfg).x_near
    shallow = RigCamera("front", default_camera(), looking_forward(1.3, 40.0))
    assert floor_patch(shallow, cfg).x_near == floor_patch(replace(shallow, legs_in_view=False), cfg).x_near
    near = floor_patch(plain, cfg).x_near
    assert near < 0.3  # at 65 degrees the image's bottom edge sees the floor 0.1 m ahead
    assert floor_patch(legs, replace(cfg, legs_reach_m=0.0)).x_near == near
    assert floor_patch(legs, cfg).x_near == pytest.approx(legs.vest_point[0] + cfg.legs_reach_m, abs=1e-9)
    all_pts = FloorOdometry(plain, cfg)._flow._px
    kept = FloorOdometry(legs, cfg)._flow._px
    assert 0 < len(kept) < len(all_pts)
    gone = np.array([pt for pt in all_pts.tolist() if pt not in kept.tolist()])
    f_gone = floor_under_pixels(legs, gone) - legs.vest_point[:2]
    f_kept = floor_under_pixels(legs, kept) - legs.vest_point[:2]
    zone = (cfg.legs_reach_m, cfg.legs_half_width_m)
    assert np.all((f_gone[:, 0] < zone[0]) & (np.abs(f_gone[:, 1]) < zone[1]))
    assert not np.any((f_kept[:, 0] < zone[0]) & (np.abs(f_kept[:, 1]) < zone[1]))


def test_rig_json_carries_legs_in_view(tmp_path):
    """``legs_in_view`` is written when stated (true or false) and read back; absent, it stays None
    (decided from the mount); anything but a boolean is refused with the file and camera named."""
    import json

    from tagloc.core.errors import CalibrationError
    from tagloc.core.rig import default_rig, load_rig, save_rig

    rig = default_rig()
    save_rig(rig, tmp_path / "rig.json")
    assert "legs_in_view" not in (tmp_path / "rig.json").read_text()
    assert load_rig(tmp_path / "rig.json").cameras[0].legs_in_view is None
    for stated in (True, False):
        rig.cameras[0].legs_in_view = stated
        save_rig(rig, tmp_path / "rig.json")
        assert load_rig(tmp_path / "rig.json").cameras[0].legs_in_view is stated
    doc = json.loads((tmp_path / "rig.json").read_text())
    doc["cameras"][0]["legs_in_view"] = "yes"
    (tmp_path / "rig.json").write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match=r"rig.json: cameras\[0\]: legs_in_view"):
        load_rig(tmp_path / "rig.json")


def test_rig_show_points_out_a_camera_that_sees_the_feet(tmp_path, capsys):
    """``tagloc rig show`` says of a camera that sees the floor where the feet step (65 degrees at
    1.3 m: from 0.13 m ahead) and states nothing that the odometry leaves that floor out, shows a
    stated value, and says nothing for a camera looking further ahead (40 degrees: from 0.77 m)."""
    from tagloc.cli import main
    from tagloc.core.rig import default_rig, save_rig
    from tagloc.vision.odometry import nearest_floor_ahead, sees_legs

    steep, shallow = default_rig(1.3, 65.0), default_rig(1.3, 40.0)
    assert nearest_floor_ahead(steep.cameras[0]) == pytest.approx(0.13, abs=0.01)
    assert nearest_floor_ahead(shallow.cameras[0]) == pytest.approx(0.77, abs=0.01)
    assert sees_legs(steep.cameras[0]) and not sees_legs(shallow.cameras[0])
    said = {}
    for name, rig in (("steep", steep), ("shallow", shallow)):
        save_rig(rig, tmp_path / f"{name}.json")
        assert main(["rig", "show", str(tmp_path / f"{name}.json")]) == 0
        said[name] = capsys.readouterr().out
    assert "0.13 m ahead" in said["steep"] and "legs_in_view not stated" in said["steep"]
    assert "legs_in_view" not in said["shallow"]
    for stated in (True, False):
        steep.cameras[0].legs_in_view = stated
        save_rig(steep, tmp_path / "steep.json")
        assert main(["rig", "show", str(tmp_path / "steep.json")]) == 0
        assert f"legs_in_view {str(stated).lower()}" in capsys.readouterr().out
