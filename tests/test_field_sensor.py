"""Field physics of the camera and the map (issue 14, part B): rolling-shutter timing, the driver's
jittered and dropped frames, survey error in the map, the dimmer OV5647 sensor model, and what the
localiser does with each."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tagloc.cli.simulate import SENSOR_CHOICES
from tagloc.core.errors import InputError
from tagloc.core.stickermap import StickerMap, load_map, save_map
from tagloc.io.session import SessionReader
from tagloc.sim.render import (
    SENSOR_PRESETS,
    ExposureConfig,
    OpticsConfig,
    SensorConfig,
    electrons_per_lux_s,
    exposure_for_sensor,
    row_delay_s,
    sensor_preset,
)
from tagloc.sim.simulate import SimConfig, read_groundtruth_frames, simulate_session
from tagloc.sim.survey import FIELD_SURVEY, SurveyConfig, surveyed_map
from tagloc.sim.timing import FIELD_TIMING, TimingConfig, frame_schedule


def line_map(n: int = 9, spacing_m: float = 1.5) -> StickerMap:
    """Stickers along world +y, one every ``spacing_m``, IDs 200, 201, ..."""
    xy = np.column_stack([np.zeros(n), np.arange(n) * spacing_m])
    return StickerMap(np.arange(200, 200 + n), xy, np.radians(np.arange(n) * 41.0 % 360))


# -- rolling-shutter timing --------------------------------------------------------------------------


def test_row_delay_is_readout_over_rows():
    H, readout = 972, 0.030
    d = row_delay_s(np.arange(H), H, readout)
    assert np.diff(d) == pytest.approx(np.full(H - 1, readout / H))
    assert d[0] == pytest.approx(-d[-1])  # the frame's time is the middle row's
    assert d[-1] - d[0] == pytest.approx(readout * (H - 1) / H)


# -- camera timing -----------------------------------------------------------------------------------


def test_frame_schedule_drops_bursts_and_jitter():
    fps = 30.0
    n = 60 * 60 * 30  # an hour: enough frames for the rates to show
    s = frame_schedule(n, fps, FIELD_TIMING, seed=5)
    lost = np.setdiff1d(np.arange(n), s.index)
    assert s.dropped == len(lost)
    # Isolated drops at 4 % plus 3 bursts a minute of 5.5 frames on average: 4.9 % in all.
    expect = 1 - (1 - 0.04) * (1 - 3 / 60 / fps * 5.5)
    assert len(lost) / n == pytest.approx(expect, rel=0.05)
    assert s.bursts == pytest.approx(3 * 60, rel=0.15)
    runs = np.diff(np.flatnonzero(np.diff(np.r_[0, np.isin(np.arange(n), lost).astype(int), 0])))[::2]
    assert runs.max() <= 2 * 8  # two bursts may meet, never longer
    assert np.sum(runs >= 3) == pytest.approx(s.bursts, rel=0.1)
    err = s.stamp - s.index / fps
    assert np.abs(err).max() <= 0.002 + 1e-12 and np.abs(err).max() > 0.0019
    assert np.all(np.diff(s.stamp) > 0)
    again = frame_schedule(n, fps, FIELD_TIMING, seed=5)
    assert np.array_equal(again.index, s.index) and np.array_equal(again.stamp, s.stamp)
    assert not np.array_equal(frame_schedule(n, fps, FIELD_TIMING, seed=6).index, s.index)
    none = frame_schedule(100, fps, TimingConfig(), seed=5)
    assert np.array_equal(none.index, np.arange(100)) and np.array_equal(none.stamp, np.arange(100) / fps)


def test_timing_config_refuses_nonsense():
    with pytest.raises(InputError):
        TimingConfig(drop_fraction=1.5)
    with pytest.raises(InputError):
        TimingConfig(burst_frames=(5, 2))
    with pytest.raises(InputError, match="reorders"):
        frame_schedule(10, 30.0, TimingConfig(jitter_s=0.03), seed=1)


# -- survey error --------------------------------------------------------------------------------------


def test_surveyed_map_errors_have_the_stated_size(tmp_path):
    n = 4000
    truth = StickerMap(np.arange(n), np.column_stack([np.arange(n) * 1.5, np.zeros(n)]), np.zeros(n))
    m = surveyed_map(truth, FIELD_SURVEY, seed=3)
    assert np.array_equal(m.ids, truth.ids)
    d = m.xy - truth.xy
    assert d.std(axis=0) == pytest.approx([0.01, 0.01], rel=0.05)
    dyaw = (m.yaw - truth.yaw + np.pi) % (2 * np.pi) - np.pi
    assert np.degrees(dyaw.std()) == pytest.approx(1.5, rel=0.05)
    assert np.all(np.isnan(m.sigma_xy))  # not stated: the localiser's default applies
    assert surveyed_map(truth, SurveyConfig(), seed=3) is truth
    stated = surveyed_map(truth, SurveyConfig(0.02, 2.0, stated=True), seed=3)
    save_map(stated, tmp_path / "m.csv")
    back = load_map(tmp_path / "m.csv")
    assert back.sigma_xy == pytest.approx(np.full(n, 0.02)) and back.sigma_yaw == pytest.approx(
        np.full(n, math.radians(2.0)), abs=1e-6
    )


# -- sensor --------------------------------------------------------------------------------------------


def test_ov5647_preset_is_about_half_as_sensitive():
    assert set(SENSOR_CHOICES) == set(SENSOR_PRESETS)
    std, dim = sensor_preset("standard"), sensor_preset("ov5647")
    ratio = electrons_per_lux_s(OpticsConfig(), std) / electrons_per_lux_s(OpticsConfig(), dim)
    assert 1.9 < ratio < 3.0
    exp = exposure_for_sensor(ExposureConfig(), dim)
    assert exp.e0_lux_s == pytest.approx(ExposureConfig().e0_lux_s * ratio)
    assert exp.max_exposure_s == pytest.approx(ExposureConfig().max_exposure_s * ratio)
    assert exposure_for_sensor(ExposureConfig(), SensorConfig()) == ExposureConfig()
    # The datasheet figures: 4 x 4.3 ke- full well; 68 dB of dynamic range -> 1.7 e- per pixel, 2x binned.
    assert dim.full_well_e == pytest.approx(4 * 4300)
    assert dim.read_noise_e == pytest.approx(2 * 4300 / 10 ** (68 / 20), rel=0.02)
    with pytest.raises(InputError):
        sensor_preset("nope")


# -- sessions ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def field_session(tmp_path_factory):
    """A short seeded walk with all of part B's field conditions at small scale."""
    out = tmp_path_factory.mktemp("field") / "s"
    cfg = SimConfig(
        seconds=2.0,
        fps=30.0,
        lux=150.0,
        seed=4,
        scale=0.5,
        rolling_shutter=True,
        sensor_preset="ov5647",
        timing=TimingConfig(jitter_s=0.002, drop_fraction=0.05, bursts_per_min=40.0),
        survey=SurveyConfig(0.015, 1.5),
    )
    simulate_session(line_map(), out, cfg, progress=False)
    return out, cfg


def test_session_has_dropped_frames_jittered_stamps_and_surveyed_map(field_session):
    out, cfg = field_session
    reader = SessionReader(out)
    recs = read_groundtruth_frames(out)
    assert len(reader) == len(recs) < 60  # some of the 60 frames were lost
    assert list(reader.index) == [r["index"] for r in recs]
    assert np.all(np.diff(reader.index) >= 1) and np.any(np.diff(reader.index) > 1)
    t_true = np.array([r["t"] for r in recs])
    assert t_true == pytest.approx(reader.index / cfg.fps, abs=1e-6)
    assert np.abs(reader.timestamps - t_true).max() <= 0.002 + 1e-6
    assert np.abs(reader.timestamps - t_true).max() > 0.0
    truth, given = load_map(out / "map_true.csv"), load_map(out / "map.csv")
    assert np.array_equal(truth.ids, given.ids)
    assert np.allclose(truth.xy, line_map().xy, atol=1e-4)
    assert 0.002 < np.abs(given.xy - truth.xy).max() < 0.1
    assert max(r["exposure_s"] for r in recs) > 0.0035  # 0.3 lux s / 150 lux = 2 ms on the standard sensor


# -- the map's survey error in the fix covariance ----------------------------------------------------


def _pose_fixture():
    from tagloc.core.camera import default_camera
    from tagloc.core.geometry import invert, planar_T, transform_points
    from tagloc.core.rig import RigCamera, looking_forward
    from tagloc.core.sticker import INNER_CORNERS, OUTER_CORNERS
    from tagloc.core.types import Detection

    rc = RigCamera("front", default_camera(), looking_forward(1.3, 55.0), legs_in_view=False)
    body = planar_T(2.0, -1.0, 0.7)
    # The sticker ~1.6 m ahead of the body origin and a little to the left, at some yaw.
    c, s = math.cos(0.7), math.sin(0.7)
    T_ws = planar_T(2.0 + 1.6 * c - 0.2 * s, -1.0 + 1.6 * s + 0.2 * c, 2.1)
    T_cs = invert(body @ rc.T_body_camera) @ T_ws
    det = Detection(
        rc.camera.project(transform_points(T_cs, OUTER_CORNERS)),
        rc.camera.project(transform_points(T_cs, INNER_CORNERS)),
    )
    return rc, body, T_ws, det


def test_map_covariance_is_the_lever_of_the_sticker_pose():
    """A sticker's yaw error moves the body by distance x angle: the map part of the fix covariance
    matches the spread of fixes solved against perturbed map poses (Monte Carlo, 400 draws)."""
    from tagloc.core.geometry import planar_T
    from tagloc.vision.pose import map_covariance, solve_pose

    rc, body, T_ws, det = _pose_fixture()
    sig_m, sig_yaw = 0.015, math.radians(1.5)
    exact = solve_pose(det, 0, T_ws, rc, corner_sigma_px=0.3).poses[0]
    with_map = solve_pose(det, 0, T_ws, rc, corner_sigma_px=0.3, map_sigma=(sig_m, sig_yaw)).poses[0]
    C = map_covariance(exact.body, T_ws[:2, 3], sig_m, sig_yaw)
    assert with_map.cov - exact.cov == pytest.approx(C, abs=1e-12)
    dist = float(np.hypot(*(exact.body[:2] - T_ws[:2, 3])))
    assert dist == pytest.approx(1.6, abs=0.1)
    # Sideways of the sticker-to-body line the yaw error adds (distance x sigma_yaw)^2.
    u = (exact.body[:2] - T_ws[:2, 3]) / dist
    n = np.array([-u[1], u[0]])
    assert n @ C[:2, :2] @ n == pytest.approx(sig_m**2 + (dist * sig_yaw) ** 2, rel=1e-9)
    assert u @ C[:2, :2] @ u == pytest.approx(sig_m**2, rel=1e-9)

    rng = np.random.default_rng(9)
    x0, y0, a0 = T_ws[0, 3], T_ws[1, 3], math.atan2(T_ws[1, 0], T_ws[0, 0])
    bodies = []
    for _ in range(400):
        dx, dy = rng.normal(0, sig_m, 2)
        wrong = planar_T(x0 + dx, y0 + dy, a0 + rng.normal(0, sig_yaw))
        bodies.append(solve_pose(det, 0, wrong, rc, corner_sigma_px=0.3).poses[0].body)
    d = np.array(bodies) - exact.body
    emp = d.T @ d / len(d)
    for i in range(3):
        assert emp[i, i] == pytest.approx(C[i, i], rel=0.2)
    assert emp[0, 2] / math.sqrt(emp[0, 0] * emp[2, 2]) == pytest.approx(
        C[0, 2] / math.sqrt(C[0, 0] * C[2, 2]), abs=0.1
    )


def test_map_sigma_defaults_apply_where_the_map_states_none():
    from tagloc.vision.pose import PoseConfig, map_covariance, solve_pose

    rc, body, T_ws, det = _pose_fixture()
    cfg = PoseConfig()
    exact = solve_pose(det, 0, T_ws, rc, corner_sigma_px=0.3).poses[0]
    default = solve_pose(det, 0, T_ws, rc, corner_sigma_px=0.3, map_sigma=(math.nan, math.nan)).poses[0]
    C = map_covariance(exact.body, T_ws[:2, 3], cfg.map_sigma_m, cfg.map_sigma_yaw)
    assert default.cov - exact.cov == pytest.approx(C, abs=1e-12)
    stated_zero = solve_pose(det, 0, T_ws, rc, corner_sigma_px=0.3, map_sigma=(0.0, 0.0)).poses[0]
    assert stated_zero.cov == pytest.approx(exact.cov, abs=1e-15)
    stated = solve_pose(det, 0, T_ws, rc, corner_sigma_px=0.3, map_sigma=(0.01, 0.02)).poses[0]
    assert stated.cov - exact.cov == pytest.approx(map_covariance(exact.body, T_ws[:2, 3], 0.01, 0.02))


def _fixes_of(tr, sticker_xy, truth, map_error, survey, t0, n, rng, sticker_id=7):
    """Feed ``n`` frames of fixes of one sticker whose map pose is off by ``map_error`` (dx, dy, dyaw)."""
    from tagloc.core.geometry import map_error_jacobian
    from tagloc.core.types import IdSource, PoseFix, SurveyPrior

    J = map_error_jacobian(truth[:2], sticker_xy)
    R = np.diag([0.002**2, 0.002**2, math.radians(0.1) ** 2])  # corner noise only
    for k in range(n):
        t = t0 + k / 30
        z = truth + J @ map_error + rng.multivariate_normal(np.zeros(3), R)
        tr.predict(t)
        tr.update([PoseFix(np.eye(4), z, R, 0.2)], sticker_id, IdSource.DECODED, t, SurveyPrior(sticker_xy, *survey))


def test_fixes_of_a_mis_surveyed_sticker_do_not_average_its_survey_error_away():
    """Standing still, 90 frames of fixes of one sticker surveyed 2 cm and 1.5 degrees off, 1.2 m
    away: each fix is 3.6 cm off the truth the same way. Averaged as independent, 90 fixes would
    claim ~2 mm; with the sticker's survey error as a state the tracker keeps the survey's share
    (its position sigma stays >= 2 cm) and the error stays inside it."""
    from tracker.tracker import Tracker

    rng = np.random.default_rng(5)
    truth = np.array([0.0, 0.0, 0.3])
    sticker_xy = np.array([1.2, 0.1])
    survey = (0.015, math.radians(1.5))
    e = np.array([0.02, -0.01, math.radians(1.5)])
    tr = Tracker()
    _fixes_of(tr, sticker_xy, truth, e, survey, 0.0, 90, rng)
    out = tr.output()
    err = out.pose[:2] - truth[:2]
    assert np.hypot(*err) > 0.025  # the map's error is in every fix: it cannot be averaged out
    sd = math.sqrt(np.linalg.eigvalsh(out.cov[:2, :2])[-1])
    assert sd > 0.02
    assert err @ np.linalg.solve(out.cov[:2, :2], err) < 9.21  # chi2(2) 99 %


def test_map_error_slots_are_reused_and_the_filter_stays_finite():
    from tracker.ekf import MAP_SLOTS
    from tracker.tracker import Tracker

    rng = np.random.default_rng(6)
    tr = Tracker()
    truth = np.zeros(3)
    sd = []
    for j in range(MAP_SLOTS + 3):
        xy = np.array([1.0 + 0.1 * j, -0.5 + 0.2 * j])
        _fixes_of(tr, xy, truth, np.zeros(3), (0.01, math.radians(1.0)), j * 0.5, 10, rng, sticker_id=100 + j)
        sd.append(math.sqrt(tr.output().cov[0, 0]))
    slots = tr.filter.slots
    assert len(slots) == MAP_SLOTS and set(slots) == {100 + j for j in range(3, MAP_SLOTS + 3)}
    assert np.all(np.isfinite(tr.filter.P)) and np.linalg.eigvalsh(tr.filter.P)[0] > 0
    # Several stickers' survey errors are independent: together they pin the vest down better than one.
    # (Standing 0.5 s per sticker with an unknown speed, the motion model's noise grows it back later.)
    assert sd[2] < 0.8 * sd[0]


# -- rolling-shutter correction of a fix -----------------------------------------------------------


class _MovingSticker:
    """One sticker 0.62 m ahead of a camera 1.3 m up, pitched 55 deg, read out in 30 ms while the
    camera moves at ``v`` m/s along world x and turns at ``w`` (3,) rad/s about world axes
    (render_view's uniform motion)."""

    def __init__(self, v: float, w: np.ndarray):
        from tagloc.core.camera import default_camera
        from tagloc.core.rig import RigCamera, looking_forward
        from tagloc.sim.simulate import camera_pose_looking_at

        self.v, self.w = v, np.asarray(w, float)
        self.cam = default_camera()
        self.rc = RigCamera("front", self.cam, looking_forward(1.3, 55.0), readout_s=0.030, legs_in_view=False)
        self.T_wc = camera_pose_looking_at((1.0, 0.0), 1.3, 55.0, 0.0)
        self.smap = StickerMap(np.array([4242]), np.array([[0.62, 0.05]]), np.array([0.5]))
        self.T_ws = self.smap.T_world_sticker(4242)

    def pose_at(self, t: float) -> np.ndarray:
        """The camera's pose t s after the frame's time."""
        from scipy.spatial.transform import Rotation

        T = self.T_wc.copy()
        T[:3, 3] += t * np.array([self.v, 0.0, 0.0])
        T[:3, :3] = Rotation.from_rotvec(t * self.w).as_matrix() @ self.T_wc[:3, :3]
        return T

    def sticker_at(self, t: float):
        """The sticker's detection in a frame whose middle row is read t s after the frame's time,
        and the rotation that puts its canonical top-left first."""
        from tagloc.core.geometry import invert, transform_points
        from tagloc.core.sticker import OUTER_CORNERS
        from tagloc.sim.simulate import render_view
        from tagloc.vision.detect import detect

        res = render_view(
            self.smap,
            self.cam,
            self.pose_at(t),
            300.0,
            velocity=np.array([self.v, 0.0, 0.0]),
            angular_velocity=self.w,
            exposure=ExposureConfig(rolling_shutter=True, readout_s=0.030),
            seed=2,
        )
        dets = detect(res.image, self.cam)
        assert len(dets) == 1
        tl = self.cam.project(transform_points(invert(self.pose_at(t)) @ self.T_ws, OUTER_CORNERS[:1]))[0]
        return dets[0], int(np.argmin(np.hypot(*(dets[0].outer - tl).T)))

    def truth(self, row_time_s: float) -> np.ndarray:
        """The body's true (x, y, yaw) at ``row_time_s`` after the frame's time."""
        from tagloc.core.geometry import invert
        from tagloc.core.rig import vest_planar

        return vest_planar(self.pose_at(row_time_s) @ invert(self.rc.T_body_camera), self.rc.vest_point)


@pytest.mark.parametrize("turn", [0.0, 1.5])
def test_rolling_shutter_frame_gives_the_right_pose(turn):
    """A rendered rolling-shutter frame (30 ms read-out) of a camera walking at 1.5 m/s, turning at
    ``turn`` rad/s. The fix holds when the sticker's rows were read (``row_time_s``: their mean
    row's delay, ~8 ms late low in the image). Straightened with the body's motion, or with the
    corners' own motion since the previous frame (rendered 1/30 s earlier), it is that instant's
    pose within three of its sigmas; without, the sticker's shear puts it over 1 cm off, and the
    fix says so (``PoseConfig.unknown_twist_sigma``)."""
    from tagloc.core.geometry import wrap_angle
    from tagloc.core.rig import row_delay_s
    from tagloc.core.sticker import rotate_corners
    from tagloc.vision.pose import PoseConfig, solve_pose

    scene = _MovingSticker(1.5, np.array([0.0, 0.0, turn]))
    cam, rc, T_ws, v, sticker_at = scene.cam, scene.rc, scene.T_ws, scene.v, scene.sticker_at

    det, rot = sticker_at(0.0)
    prev, prev_rot = sticker_at(-1 / 30)
    assert det.outer[:, 1].mean() > 0.7 * cam.height  # low in the image: exposed late

    def err(sol):
        fix = sol.poses[0]
        truth = scene.truth(sol.row_time_s)
        e_mm = 1000 * float(np.hypot(*(fix.body[:2] - truth[:2])))
        sig_mm = 1000 * math.sqrt(np.linalg.eigvalsh(fix.cov[:2, :2])[-1])
        return (
            e_mm,
            sig_mm,
            abs(math.degrees(wrap_angle(fix.body[2] - truth[2]))),
            math.degrees(math.sqrt(fix.cov[2, 2])),
        )

    plain = solve_pose(det, rot, T_ws, rc)
    # Not straightened (no motion known), the shear is stated as the fix's error: within three of
    # its sigmas, which without that term (the corner noise alone) it is far outside.
    e_mm, sig_mm, e_deg, sig_deg = err(plain)
    assert e_mm < 3 * sig_mm and e_deg < 3 * sig_deg, (e_mm, sig_mm, e_deg, sig_deg)
    # (The camera here does not pitch or roll: the torso's rates are left out of every check but the first.)
    level = PoseConfig(tilt_rate_sigma=0.0)
    bare = solve_pose(det, rot, T_ws, rc, config=PoseConfig(unknown_twist_sigma=(0.0, 0.0, 0.0), tilt_rate_sigma=0.0))
    assert err(bare)[0] > 3 * err(bare)[1]
    rows = rotate_corners(det.points, rot)[:, 1]
    assert plain.row_time_s == pytest.approx(np.mean(row_delay_s(rows, cam.height, 0.030)))
    assert plain.row_time_s > 0.005
    by_twist = solve_pose(det, rot, T_ws, rc, body_twist=np.array([v, 0.0, turn]))
    velocity = (rotate_corners(det.points, rot) - rotate_corners(prev.points, prev_rot)) * 30.0
    by_corners = solve_pose(det, rot, T_ws, rc, corner_velocity=velocity)
    for sol in (by_twist, by_corners):
        e_mm, sig_mm, e_deg, sig_deg = err(sol)
        # The body is the vest point (the camera's mount), as certain as the camera centre. (The
        # corners' motion is their mean velocity over the last frame interval: in the 1.5 rad/s turn
        # measured 16 mm and 0.22 deg off, against 8 mm and 0.11 deg from the exact body motion.)
        assert e_mm < 3 * sig_mm and e_deg < 3 * sig_deg, (e_mm, sig_mm, e_deg, sig_deg)
        assert err(plain)[0] > 10.0
        assert err(plain)[0] > 2.5 * e_mm
    # Straightened with an estimate of the motion (the tracker's extrapolation a second after its
    # last fix: 0.6 m/s and 1.2 rad/s sigmas, here a sigma off in each), the fix states the shear
    # that estimate leaves; taken as exact, the estimate's error was outside three of its sigmas.
    estimate = np.array([v - 0.6, 0.0, turn - 1.2])
    guessed = solve_pose(det, rot, T_ws, rc, body_twist=estimate, body_twist_sigma=np.array([0.6, 0.0, 1.2]))
    e_mm, sig_mm, e_deg, sig_deg = err(guessed)
    assert e_mm < 3 * sig_mm and e_deg < 3 * sig_deg, (e_mm, sig_mm, e_deg, sig_deg)
    as_exact = solve_pose(det, rot, T_ws, rc, body_twist=estimate, config=level)
    assert err(as_exact)[0] > 3 * err(as_exact)[1], err(as_exact)
    # The switch that turns the term off (PoseConfig.estimated_twist_term) gives the exact reading.
    off = PoseConfig(estimated_twist_term=False, tilt_rate_sigma=0.0)
    switched = solve_pose(
        det, rot, T_ws, rc, body_twist=estimate, body_twist_sigma=np.array([0.6, 0.0, 1.2]), config=off
    )
    np.testing.assert_allclose(switched.poses[0].cov, as_exact.poses[0].cov, rtol=1e-12)
    # At the frame's time instead, the twist carries the sticker ~8 ms back: still right for this
    # uniform motion (the walk's gait is what makes that extrapolation fail, see tagloc.vision.pose).
    at_frame = solve_pose(
        det, rot, T_ws, rc, body_twist=np.array([v, 0.0, turn]), config=PoseConfig(at_sticker_rows=False)
    )
    assert at_frame.row_time_s == 0.0
    e_mm, sig_mm, _, _ = err(at_frame)
    assert e_mm < 3 * sig_mm


def test_a_fix_straightened_by_the_planar_twist_states_the_torsos_pitch_it_cannot_see():
    """A camera 1.3 m up walking at 1.3 m/s while the torso pitches at 20 deg/s (twice
    ``TRUNK_TILT_RATE_SIGMA``: a nod, a turn's onset), 30 ms read-out, a sticker 0.6 m ahead low in
    the image. Straightened by the body's planar twist (all the floor odometry measures), the
    pitch stretches the sticker along its rows and the solve takes it for a tilt: the fix is some
    6 cm off. Its covariance carries the torso's pitch and roll rates, so that error is within
    three of its sigmas; without that term it is four sigmas out. Straightened by the corners' own
    motion since the previous frame (which holds the pitch), the fix is 2 mm off."""
    from tagloc.core.sticker import rotate_corners
    from tagloc.vision.pose import PoseConfig, solve_pose
    from tagloc.vision.torso_tilt import TRUNK_TILT_RATE_SIGMA

    # Pitch: about the body's left axis (world y, heading along world x).
    scene = _MovingSticker(1.3, np.array([0.0, 2 * TRUNK_TILT_RATE_SIGMA, 0.0]))
    rc, T_ws, v, sticker_at = scene.rc, scene.T_ws, scene.v, scene.sticker_at

    def err(sol) -> tuple[float, float]:
        """(position error, its largest stated sigma) in mm."""
        fix = sol.poses[0]
        e = 1000 * float(np.hypot(*(fix.body[:2] - scene.truth(sol.row_time_s)[:2])))
        return e, 1000 * math.sqrt(np.linalg.eigvalsh(fix.cov[:2, :2])[-1])

    det, rot = sticker_at(0.0)
    planar = np.array([v, 0.0, 0.0])
    stated = err(solve_pose(det, rot, T_ws, rc, body_twist=planar))
    blind = err(solve_pose(det, rot, T_ws, rc, body_twist=planar, config=PoseConfig(tilt_rate_sigma=0.0)))
    assert 40.0 < stated[0] < 3 * stated[1], stated  # measured 45 mm at a stated 24 mm
    assert blind[0] > 3 * blind[1], blind  # 45 mm at a stated 11 mm
    prev, prev_rot = sticker_at(-1 / 30)
    velocity = (rotate_corners(det.points, rot) - rotate_corners(prev.points, prev_rot)) * 30.0
    by_corners = err(solve_pose(det, rot, T_ws, rc, corner_velocity=velocity))
    assert by_corners[0] < min(10.0, 3 * by_corners[1]), by_corners


def test_solve_pose_refuses_a_short_corner_velocity():
    from tagloc.core.camera import default_camera
    from tagloc.core.rig import RigCamera, looking_forward
    from tagloc.core.types import Detection
    from tagloc.vision.pose import solve_pose

    rc = RigCamera("front", default_camera(), looking_forward(1.3, 55.0), readout_s=0.030, legs_in_view=False)
    det = Detection(np.array([[600.0, 700.0], [700.0, 700.0], [700.0, 800.0], [600.0, 800.0]]))
    with pytest.raises(InputError, match="corner_velocity"):
        solve_pose(det, 0, np.eye(4), rc, corner_velocity=np.zeros((2, 2)))


def test_tracker_fuses_a_fix_at_its_sticker_rows_time():
    """Fixes of a walk at 1.5 m/s that hold 12 ms after their frames (a sticker low in a rolling-
    shutter frame): told so (``row_time_s``), the tracker's pose at the frames is unbiased; stamped
    with the frame's time, it is 1.8 cm ahead (the walk's motion over 12 ms)."""
    from tagloc.core.types import IdSource, PoseFix
    from tracker.tracker import Tracker

    v, lead = 1.5, 0.012
    R = np.diag([0.003**2, 0.003**2, math.radians(0.2) ** 2])
    rng = np.random.default_rng(4)
    bias = {}
    for told in (True, False):
        tr = Tracker()
        errs = []
        for k in range(90):
            t = k / 30
            z = np.array([v * (t + lead), 0.0, 0.0]) + rng.multivariate_normal(np.zeros(3), R)
            tr.predict(t)
            res = tr.update([PoseFix(np.eye(4), z, R, 0.2)], 7, IdSource.DECODED, t, None, lead if told else 0.0)
            assert res.accepted
            if k >= 30:
                errs.append(tr.output(t).pose[0] - v * t)
        bias[told] = float(np.mean(errs))
    assert abs(bias[True]) < 0.004, bias
    assert bias[False] == pytest.approx(v * lead, abs=0.004), bias
    assert tr.stats["late_fixes_fused"] == 0  # ahead of the frame is not late


# -- dropped and jittered frames in the tracker --------------------------------------------------------


def _wavy_walk():
    """Truth (x, y, yaw)(t) of a 1.3 m/s walk weaving +-0.5 rad (integrated at 1 ms)."""
    ts = np.arange(0.0, 21.0, 0.001)
    yaw = 0.5 * np.sin(0.4 * ts)
    x = np.concatenate([[0.0], np.cumsum(1.3 * np.cos(yaw[:-1]) * 0.001)])
    y = np.concatenate([[0.0], np.cumsum(1.3 * np.sin(yaw[:-1]) * 0.001)])

    def truth(t: float) -> np.ndarray:
        return np.array([np.interp(t, ts, x), np.interp(t, ts, y), np.interp(t, ts, yaw)])

    return truth


def _run_tracker(timing: TimingConfig, seed: int) -> dict:
    """The tracker over a 20 s walk at 30 fps as the driver delivers it: fixes (solver noise) in
    0.8 s of every 1.5 s, odometry steps between consecutive delivered frames at most 0.12 s apart
    (FloorOdometry's limit), measured over the true times, stamped with the driver's stamps."""
    from tagloc.core.types import IdSource, PoseFix
    from tagloc.vision.odometry import OdometryStep
    from tracker.tracker import Tracker

    truth = _wavy_walk()
    sched = frame_schedule(600, 30.0, timing, seed)
    rng = np.random.default_rng(seed)
    fix_cov = np.diag([0.008**2, 0.008**2, math.radians(0.4) ** 2])
    odo_cov = np.diag([0.003**2, 0.0015**2, math.radians(0.1) ** 2])
    tr = Tracker()
    err, nees = [], []
    prev = None
    for t_true, stamp in zip(sched.true_t, sched.stamp):
        tr.predict(stamp)
        if prev is not None and stamp - prev[1] <= 0.12:
            a, b = truth(prev[0]), truth(t_true)
            c, s = math.cos(a[2]), math.sin(a[2])
            d = np.array([c * (b[0] - a[0]) + s * (b[1] - a[1]), -s * (b[0] - a[0]) + c * (b[1] - a[1]), b[2] - a[2]])
            d = d + rng.multivariate_normal(np.zeros(3), odo_cov)
            tr.update_odometry(OdometryStep(prev[1], stamp, d, odo_cov, 0.5))
        if t_true % 1.5 < 0.8:
            z = truth(t_true) + rng.multivariate_normal(np.zeros(3), fix_cov)
            tr.update([PoseFix(np.eye(4), z, fix_cov, 0.3)], 300 + int(t_true // 1.5), IdSource.DECODED, stamp)
        out = tr.output(stamp)
        assert np.all(np.isfinite(out.pose)) and np.all(np.isfinite(out.cov))
        assert np.linalg.eigvalsh(out.cov).min() > 0
        assert out.t == stamp  # the pose is stamped with its frame, never a stale time
        if t_true > 2.0:
            e = out.pose[:2] - truth(stamp)[:2]
            err.append(float(np.hypot(*e)))
            nees.append(float(e @ np.linalg.solve(out.cov[:2, :2], e)))
        prev = (t_true, stamp)
    return {
        "rmse": float(np.sqrt(np.mean(np.square(err)))),
        "nees": float(np.mean(nees)),
        "stats": tr.stats,
        "sched": sched,
    }


def test_tracker_rides_out_dropped_and_jittered_frames():
    """Field timing (+-2 ms jitter, 4 % drops, bursts of 3-8 frames, here 20 a minute): every
    delivered frame gets a finite, SPD, current pose; the error stays near the clean run's and the
    covariance is not overconfident; steps across a burst are not taken as one frame's motion."""
    clean = _run_tracker(TimingConfig(), seed=11)
    field = _run_tracker(replace_timing(FIELD_TIMING, bursts_per_min=20.0), seed=11)
    assert field["sched"].bursts >= 3 and field["sched"].dropped > 40
    assert clean["rmse"] < 0.02
    assert field["rmse"] < 1.3 * clean["rmse"] + 0.003, (field["rmse"], clean["rmse"])
    assert field["nees"] < 2.6, field["nees"]  # 2 DoF; above that it would claim too much
    assert field["stats"]["rejected_decoded"] == 0
    assert field["stats"]["odometry_rejected"] <= 3
    assert field["stats"]["odometry_accepted"] < clean["stats"]["odometry_accepted"] - 50


def replace_timing(t: TimingConfig, **kw) -> TimingConfig:
    from dataclasses import replace

    return replace(t, **kw)


def _spin_after_burst(cfg, refused: bool = False, wrong_first: bool = False, at: int = 99) -> tuple[dict, float]:
    """Walk 1 m/s with fixes and odometry at 30 fps; at 3 s a spin starts (6 rad/s^2 up to 3 rad/s)
    while a burst of 8 frames is lost (``refused``: the frames arrive, but their 8 odometry steps
    are refused, as in a fast turn's smeared frames); odometry steps follow from the first frame
    after the burst (``wrong_first``: the first of them a mistracking that saw no turn). Returns the
    tracker's stats and the heading error over its stated sigma at frame ``at`` (the first after
    the burst by default)."""
    from tagloc.core.types import IdSource, PoseFix
    from tagloc.vision.odometry import OdometryStep
    from tracker.tracker import Tracker

    def truth(t: float) -> np.ndarray:
        u = max(t - 3.0, 0.0)
        yaw = 3.0 * u**2 if u < 0.5 else 0.75 + 3.0 * (u - 0.5)
        return np.array([min(t, 3.0), 0.0, yaw])

    rng = np.random.default_rng(3)
    fix_cov = np.diag([0.008**2, 0.008**2, math.radians(0.4) ** 2])
    odo_cov = np.diag([0.003**2, 0.0015**2, math.radians(0.1) ** 2])
    tr = Tracker(cfg)
    frames = [k / 30 for k in range(0, 110) if refused or not 90 < k <= 98]
    lost = {k / 30 for k in range(91, 99)}
    z_after = math.nan
    for i, t in enumerate(frames):
        tr.predict(t)
        if i:
            a, b = truth(frames[i - 1]), truth(t)
            c, s = math.cos(a[2]), math.sin(a[2])
            d = np.array([c * (b[0] - a[0]) + s * (b[1] - a[1]), -s * (b[0] - a[0]) + c * (b[1] - a[1]), b[2] - a[2]])
            if wrong_first and t == 99 / 30:
                d[2] = 0.0
            if t - frames[i - 1] <= 0.12 and t not in lost:
                tr.update_odometry(
                    OdometryStep(frames[i - 1], t, d + rng.multivariate_normal(np.zeros(3), odo_cov), odo_cov, 0.5)
                )
        if t < 3.0 and (t % 1.0) < 0.5:
            z = truth(t) + rng.multivariate_normal(np.zeros(3), fix_cov)
            tr.update([PoseFix(np.eye(4), z, fix_cov, 0.3)], 5 + int(t), IdSource.DECODED, t)
        if t == at / 30:
            out = tr.output(t)
            z_after = abs(math.remainder(out.pose[2] - truth(t)[2], 2 * math.pi)) / math.sqrt(out.cov[2, 2])
    return tr.stats, z_after


def test_gap_noise_lets_odometry_follow_a_spin_that_started_in_a_burst():
    from dataclasses import replace

    from tracker.config import TrackerConfig

    stats, z = _spin_after_burst(TrackerConfig())
    narrow, z_narrow = _spin_after_burst(replace(TrackerConfig(), gap_yaw_accel_psd=0.0))
    assert stats["frame_gaps"] == narrow["frame_gaps"] == 1
    assert z < 2.0 < 2.5 < z_narrow, (z, z_narrow)  # the heading sigma covers what the gap hid
    # (the odometry's tilt offset, which lets a lean look like motion, now also keeps the narrow
    # filter from gating these steps: none refused either way)
    assert stats["odometry_rejected"] == 0 <= narrow["odometry_rejected"]


def test_refused_odometry_steps_widen_the_heading_as_a_gap_does():
    """The same spin, its first 8 frames seen but their odometry steps refused: the heading sigma
    grows as over a burst of drops (``missed_step_noise``), so the steps after it are taken; the
    narrow model alone is far overconfident there."""
    from dataclasses import replace

    from tracker.config import TrackerConfig

    stats, z = _spin_after_burst(TrackerConfig(), refused=True)
    # The control has neither widening: the blind-turn rule (``blind_turn_max_rad``) alone also
    # keeps this spin within 2 sigma (1.97), from the first step after the refused ones.
    narrow, z_narrow = _spin_after_burst(
        replace(TrackerConfig(), missed_step_noise=False, blind_turn_max_rad=0.0), refused=True
    )
    assert stats["frame_gaps"] == narrow["frame_gaps"] == 0
    assert stats["missed_steps"] >= 5 and narrow["missed_steps"] == 0
    assert z < 2.0 < 2.5 < z_narrow, (z, z_narrow)


def test_odometry_steps_gated_in_a_row_widen_the_heading():
    """The same spin with its steps refused, and the first step after it a mistracking that saw no
    turn, fused: the filter now holds a heading 17 degrees short with a yaw rate near zero, and gates
    the right steps that follow. Two of them in a row turning the same way show that the turn went
    missing (``disagreement_noise``): the heading sigma grows by the turn they report. Without it,
    and without the turn noise of measured intervals (``turn_peak_accel``), the heading is over 4
    sigma off four frames on (at frame 99, before any evidence, both are 3.1); the turn noise alone
    leaves it 3.0 sigma off (measured)."""
    from dataclasses import replace

    from tracker.config import TrackerConfig

    stats, z = _spin_after_burst(TrackerConfig(), refused=True, wrong_first=True, at=103)
    narrow, z_narrow = _spin_after_burst(
        replace(TrackerConfig(), disagreement_noise=False, turn_peak_accel=0.0), refused=True, wrong_first=True, at=103
    )
    assert stats["odometry_disagreements"] >= 1 and narrow["odometry_disagreements"] == 0
    assert narrow["odometry_rejected"] >= 3
    assert z < 2.0 < 4.0 < z_narrow, (z, z_narrow)


def _rolling_frame(floor, rc, body: np.ndarray, v: float, w: float, seed: int = 1, **kw) -> np.ndarray:
    """A 300 lux frame of ``rc`` (30 ms rolling shutter) at the planar body pose ``body``, walking
    ``v`` m/s along its heading and turning ``w`` rad/s; ``kw`` go to ``render_view``."""
    from tagloc.sim.simulate import render_view

    yaw = math.atan2(body[1, 0], body[0, 0])
    return render_view(
        floor,
        rc.camera,
        body @ rc.T_body_camera,
        300.0,
        velocity=np.array([v * math.cos(yaw), v * math.sin(yaw), 0.0]),
        angular_velocity=np.array([0.0, 0.0, w]),
        exposure=ExposureConfig(rolling_shutter=True, readout_s=0.030),
        seed=seed,
        **kw,
    ).image


def test_odometry_patch_follows_a_rolling_shutter():
    """Two rendered 30 ms rolling-shutter frames, walking 1.4 m/s while the turn rate swings from
    +1.5 to -1.5 rad/s (the vest's twist): the frames are skewed differently, which the plain patch
    match takes for 2 cm of sideways motion and 1.4 degrees of turn; with each frame's body motion
    the step is right within 1 mm and 0.05 degree (measured: 0.1 mm, 0.013 deg)."""
    from tagloc.core.camera import default_camera
    from tagloc.core.geometry import invert, planar_from_T, planar_T
    from tagloc.core.rig import RigCamera, looking_forward
    from tagloc.sim.floor import Floor, FloorConfig
    from tagloc.vision.odometry import FloorOdometry, OdometryConfig

    cam = default_camera()
    rc = RigCamera("front", cam, looking_forward(1.3, 55.0), readout_s=0.030, legs_in_view=False)
    floor = Floor(StickerMap(np.array([1]), np.array([[50.0, 50.0]]), np.array([0.0])), FloorConfig(), seed=3)
    v, dt, wA, wB = 1.4, 1 / 30, 1.5, -1.5
    bodyA = planar_T(0.0, 0.0, 0.3)
    bodyB = planar_T(v * dt * math.cos(0.3), v * dt * math.sin(0.3), 0.3 + 0.5 * (wA + wB) * dt)
    imgs = [_rolling_frame(floor, rc, body, v, w, noise=False) for body, w in ((bodyA, wA), (bodyB, wB))]
    truth = np.array(planar_from_T(invert(bodyA) @ bodyB))
    errs = {}
    for corrected in (False, True):
        # The tilt fit is off: a rigid camera has none, and its extra freedom costs ~2 mm per step.
        odo = FloorOdometry(rc, OdometryConfig(rolling_shutter=corrected, tilt_correction=False))
        odo.measure(imgs[0], 0.0, np.array([v, 0.0, wA]))
        step = odo.measure(imgs[1], dt, np.array([v, 0.0, wB]))
        e = step.delta - truth
        errs[corrected] = (1000 * float(np.hypot(e[0], e[1])), abs(math.degrees(e[2])))
    assert errs[True][0] < 1.0 and errs[True][1] < 0.05, errs
    assert errs[False][0] > 10.0 and errs[False][1] > 1.0, errs


@pytest.mark.parametrize("frequency_hz, phase_step", [(120.0, 0.0), (100.0, 2 * math.pi / 3)])
def test_flicker_bands_are_divided_out_before_the_odometry(frequency_hz, phase_step):
    """Two rendered 30 ms rolling-shutter frames, walking 1.4 m/s under lamps with 30 % flicker: at
    120 Hz and 30 fps the bands stand still (the odometry reads the walk short, towards them), at
    100 Hz they move a third of a period a frame (it reads part of their motion). Measured: 48 and
    210 mm off; with the bands divided out (:class:`tagloc.vision.deflicker.Deflicker`), under 1 mm,
    as in steady light (0.25 mm). The patch's match alone: where it finds none (100 Hz, bands not
    divided out), the floor flow tracked from the walk's predicted step (``flow_without_patch``;
    here the true one) measures the step through the bands, 0.24 mm off."""
    from tagloc.core.camera import default_camera
    from tagloc.core.geometry import invert, planar_from_T, planar_T
    from tagloc.core.rig import RigCamera, looking_forward
    from tagloc.sim.floor import Floor, FloorConfig
    from tagloc.sim.render import Flicker
    from tagloc.vision.deflicker import Deflicker
    from tagloc.vision.odometry import FloorOdometry, OdometryConfig

    cam = default_camera()
    rc = RigCamera("front", cam, looking_forward(1.3, 55.0), readout_s=0.030, legs_in_view=False)
    floor = Floor(StickerMap(np.array([1]), np.array([[50.0, 50.0]]), np.array([0.0])), FloorConfig(), seed=3)
    v, dt, yaw = 1.4, 1 / 30, 0.3
    bodies = [planar_T(0.0, 0.0, yaw), planar_T(v * dt * math.cos(yaw), v * dt * math.sin(yaw), yaw)]
    imgs = [
        _rolling_frame(floor, rc, body, v, 0.0, seed=1 + k, flicker=Flicker(0.3, frequency_hz, 0.4 + k * phase_step))
        for k, body in enumerate(bodies)
    ]
    truth = np.array(planar_from_T(invert(bodies[0]) @ bodies[1]))
    errs = {}
    for deflicker in (False, True):
        d = Deflicker(rc.readout_s)
        frames = [d(im) for im in imgs] if deflicker else imgs
        odo = FloorOdometry(rc, OdometryConfig(flow_without_patch=False))
        odo.measure(frames[0], 0.0, np.array([v, 0.0, 0.0]))
        step = odo.measure(frames[1], dt, np.array([v, 0.0, 0.0]))
        errs[deflicker] = 1000 * float(np.hypot(*(step.delta - truth)[:2])) if step is not None else math.inf
        assert d.on == deflicker or not deflicker
    assert errs[True] < 2.0 < 20.0 < errs[False], errs


def test_cli_simulate_field_flags(tmp_path, capsys):
    from tagloc.cli import main

    save_map(line_map(), tmp_path / "m.csv")
    base = ["simulate", "--map", str(tmp_path / "m.csv"), "--seconds", "0.5", "--fps", "10", "--scale", "0.25"]
    rc = main(
        base
        + ["--quiet", "--rolling-shutter", "--readout-ms", "25", "--jitter-ms", "2", "--drop-fraction", "0.3"]
        + ["--survey-sigma-cm", "1", "--survey-sigma-deg", "1.5", "--survey-stated", "--sensor", "ov5647"]
        + ["--flicker", "30", "--mains-hz", "60", "--shadow", "--legs", "-o", str(tmp_path / "f")]
    )
    assert rc == 0, capsys.readouterr().err
    reader = SessionReader(tmp_path / "f")
    assert reader.rig[0].readout_s == pytest.approx(0.025)
    sim = json.loads((tmp_path / "f" / "session.json").read_text())["simulation"]["config"]
    assert sim["flicker"] == pytest.approx(0.3) and sim["mains_hz"] == 60
    assert sim["shadow"] is True and sim["lamps"]["height_m"] == pytest.approx(9.0)
    assert sim["legs"] is True and reader.rig[0].legs_in_view  # the forward camera sees them
    capsys.readouterr()
    # A replay says the lamps flicker (every frame's bands divided out).
    assert main(["replay", str(tmp_path / "f"), "--quiet"]) == 0
    n = len(SessionReader(tmp_path / "f"))
    assert f"lamp flicker: divided out of {n} of {n} frames" in capsys.readouterr().out
    assert np.isfinite(reader.map.sigma_xy).all() and (tmp_path / "f" / "map_true.csv").exists()
    assert 0 < len(reader) <= 5
    for bad, word in (
        (["--drop-fraction", "1.5"], "--drop-fraction"),
        (["--jitter-ms", "80"], "jitter"),
        (["--flicker", "150"], "--flicker"),
    ):
        rc = main(base + ["--quiet", *bad, "-o", str(tmp_path / "x")])
        err = capsys.readouterr().err
        assert rc == 2 and word in err and err.count("\n") == 1, err


@pytest.mark.parametrize("pitch_deg, roll_deg, left", [(0.5, 0.0, 0.4), (0.0, 0.5, 0.6), (-0.35, 0.35, 0.4)])
def test_odometry_step_is_not_fooled_by_the_vest_tilting(pitch_deg, roll_deg, left):
    """Walking 4.5 cm between two frames while the vest pitches or rolls by half a degree about the
    camera (a brisk nod or sway; a lean building up): the bird's-eye patch through the nominal rig
    moves as if the floor had slid 1.9 m per radian of pitch, 1.3 m per radian of roll (1-1.7 cm
    here); fitting the tilt change from the patch's perspective (0.3 deg prior) removes most of it,
    less of a pure roll, which the patch's perspective tells from a sideways slide less well; the
    floor flow (the default) removes nearly all of it."""
    from scipy.spatial.transform import Rotation

    from tagloc.core.camera import default_camera
    from tagloc.core.geometry import planar_T
    from tagloc.core.rig import RigCamera, looking_forward
    from tagloc.sim.floor import Floor, FloorConfig
    from tagloc.sim.simulate import render_view
    from tagloc.vision.odometry import FloorOdometry, OdometryConfig

    cam = default_camera()
    rc = RigCamera("front", cam, looking_forward(1.3, 55.0), legs_in_view=False)
    floor = Floor(StickerMap(np.array([1]), np.array([[50.0, 50.0]]), np.array([0.0])), FloorConfig(), seed=4)
    c = rc.T_body_camera[:3, 3]
    tilt = np.eye(4)
    tilt[:3, :3] = Rotation.from_euler("xy", [roll_deg, pitch_deg], degrees=True).as_matrix()
    tilt[:3, 3] = c - tilt[:3, :3] @ c  # about the camera (the vest point)
    bodyA, step = planar_T(2.0, 1.0, 0.4), np.array([0.045, 0.0, 0.0])
    bodyB = bodyA @ planar_T(*step)
    imgs = [
        render_view(floor, cam, body @ T @ rc.T_body_camera, 300.0, seed=k, noise=False).image
        for k, (body, T) in enumerate(((bodyA, np.eye(4)), (bodyB, tilt)))
    ]
    errs = {}
    for name, cfg in (
        ("none", OdometryConfig(tilt_correction=False, flow=False)),
        ("fit", OdometryConfig(tilt_filter=False, flow=False)),
        ("filtered", OdometryConfig(flow=False)),
        ("flow", OdometryConfig()),
    ):
        odo = FloorOdometry(rc, cfg)
        odo.measure(imgs[0], 0.0)
        odo.anchor_tilt_angles(0.0, 0.0, 0.0)  # a sticker fix in the first frame saw it upright
        got = odo.measure(imgs[1], 1 / 30)
        errs[name] = 1000 * float(np.hypot(*(got.delta[:2] - step[:2])))
    # Measured (the patch sampled from the frame's half-resolution level, ``patch_from_half``):
    # none 14.4-16.5 mm; fit 2.2-4.3; filtered (anchored upright in the first frame) 4.5-6.4;
    # the floor flow, which fits the tilt change at the camera's own pixel scale (and the same
    # filter): 0.9-2.3 mm. Sampled from the frame itself, these noise-free pairs came out sharper
    # (filtered 0.7-3.8, flow 0.35-0.75 mm), but the rendered walks' steps did not (see
    # ``OdometryConfig.patch_from_half``).
    assert errs["none"] > 8.0 and errs["fit"] < left * errs["none"], errs
    assert errs["filtered"] < left * errs["none"], errs
    assert errs["flow"] < 0.2 * errs["none"] and errs["flow"] < 2.5, errs


def test_corner_velocity_comes_from_the_same_sticker_in_the_previous_frame():
    """A rolling-shutter sticker's corners move by their motion since the previous frame's sight of it;
    none when that sight is too old, or not where and what the sticker is now (a wrong name)."""
    from tagloc.core.camera import default_camera
    from tagloc.core.rig import Rig, RigCamera, looking_forward
    from tagloc.core.types import Detection, Identity, IdSource
    from tagloc.pipeline.localiser import Localiser

    rc = RigCamera("front", default_camera(), looking_forward(1.3, 55.0), readout_s=0.030, legs_in_view=False)
    loc = Localiser(line_map(), Rig([rc]))
    quad = np.array([[600.0, 700.0], [700.0, 700.0], [700.0, 800.0], [600.0, 800.0]])
    ident = Identity(100, 1, IdSource.DECODED)

    def sight(offset, t):
        return loc._corner_velocity(Detection(quad + offset), ident, rc, 0, t)

    assert sight(np.zeros(2), 0.0) is None  # first sight
    v = sight(np.array([12.0, -3.0]), 1 / 30)
    assert v.shape == (4, 2) and np.allclose(v, [360.0, -90.0])
    assert sight(np.array([24.0, -6.0]), 1 / 30 + 0.08) is None  # 80 ms since: too old
    assert sight(np.array([600.0, 0.0]), 1 / 30 + 0.11) is None  # six sides away: not the same sticker
    # Without a rolling shutter there is nothing to straighten.
    gs = RigCamera("front", default_camera(), looking_forward(1.3, 55.0), legs_in_view=False)
    still = Localiser(line_map(), Rig([gs]))
    assert still._corner_velocity(Detection(quad), ident, gs, 0, 0.0) is None
    assert still._corner_velocity(Detection(quad + 5.0), ident, gs, 0, 1 / 30) is None
