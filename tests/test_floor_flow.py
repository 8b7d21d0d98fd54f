"""The floor flow: step, tilt change and rise from rendered frame pairs with known motion."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tagloc.core.camera import default_camera
from tagloc.core.geometry import planar_T
from tagloc.core.rig import RigCamera, looking_forward
from tagloc.sim.floor import Floor, FloorConfig
from tagloc.sim.mapgen import GridMapConfig, grid_map
from tagloc.sim.render import ExposureConfig
from tagloc.sim.simulate import render_view
from tagloc.vision.floor_flow import FloorFlow, FloorFlowConfig, _Model, flatten
from tagloc.vision.odometry import FloorOdometry, OdometryConfig

FPS = 30.0


@pytest.fixture(scope="module")
def floor() -> Floor:
    smap = grid_map(GridMapConfig(width_m=10, depth_m=10, spacing_min_m=1.6, spacing_max_m=2.0, seed=4))
    return Floor(smap, FloorConfig(), seed=11)


def _tilted(rc: RigCamera, pitch: float, roll: float, rise: float = 0.0) -> np.ndarray:
    """T_body_camera of ``rc`` with the torso tilted (pitch, roll; rad) about the vest point and raised."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("yx", [pitch, roll]).as_matrix()  # Ry(pitch) @ Rx(roll)
    pv = rc.vest_point
    T[:3, 3] = pv - T[:3, :3] @ pv + (0.0, 0.0, rise)
    return T @ rc.T_body_camera


def _rolling_frame(
    floor: Floor, rc: RigCamera, P: np.ndarray, velocity: np.ndarray, turn_rate: float, seed: int
) -> np.ndarray:
    """A noise-free, briefly exposed frame of rolling-shutter camera ``rc`` (its ``readout_s``) on the
    body pose ``P`` (4, 4), the body moving at ``velocity`` (2,) m/s (world) and turning at
    ``turn_rate`` rad/s during the read-out."""
    exposure = ExposureConfig(rolling_shutter=True, readout_s=rc.readout_s)
    return render_view(
        floor,
        rc.camera,
        P @ rc.T_body_camera,
        lux=200,
        exposure_s=2e-3,
        seed=seed,
        noise=False,
        velocity=np.array([velocity[0], velocity[1], 0.0]),
        angular_velocity=np.array([0.0, 0.0, turn_rate]),
        exposure=exposure,
    ).image


def test_step_tilt_change_and_rise_of_a_rendered_pair(floor):
    """A body step of (4.3 cm, 0.6 cm, 1.2 deg) with the torso pitching 0.4 deg forward, rolling 0.3 deg and
    rising 6 mm (the gait's nod, sway and bobbing in one frame interval, larger than typical), tracked
    from a guess 3.6 mm and 0.1 deg off (as the patch's step typically is). On this low-contrast
    concrete (texture 6 grey levels RMS, sensor noise as large) the points land ~1 px from the model
    and the fit finds the step within 3 mm and 0.05 deg, the tilt change within 0.1 deg and the
    rise within 2 mm; noise-free, within a tenth of that (the model is exact)."""
    rc = RigCamera("front", default_camera(), looking_forward(1.3, 55.0))
    step = np.array([0.043, 0.006, math.radians(1.2)])
    d_pitch, d_roll, rise = math.radians(0.4), math.radians(-0.3), 0.006
    P0 = planar_T(4.0, 4.0, 0.3)
    P1 = P0 @ planar_T(*step)
    flow = FloorFlow(rc)
    guess = step + np.array([0.003, -0.002, math.radians(0.1)])
    T1 = P1 @ _tilted(rc, d_pitch, d_roll, rise)
    for noise, tol in ((False, 0.1), (True, 1.0)):
        g0 = render_view(floor, rc.camera, P0 @ rc.T_body_camera, lux=200, seed=1, noise=noise).image
        g1 = render_view(floor, rc.camera, T1, lux=200, seed=2, noise=noise).image
        fit = flow.refine(g0, g1, guess, 1.0 / FPS)
        assert fit is not None
        assert fit.points >= 60
        assert fit.residual_px < 1.5 * tol  # 0.12 and 0.92 px measured
        # measured noise-free: 0.1-0.4 mm, 0.004-0.006 deg (where Lucas-Kanade's 0.01 px stop leaves
        # it), tilt 0.01 deg, rise 0.1 mm; with noise 1.1 / 2.1 mm, 0.03 deg, tilt 0.06 deg, rise 1.2 mm.
        assert np.allclose(fit.delta[:2], step[:2], atol=3e-3 * tol)
        assert math.degrees(abs(fit.delta[2] - step[2])) < (0.05 if noise else 0.008)
        assert math.degrees(abs(fit.d_pitch - d_pitch)) < 0.1 * tol
        assert math.degrees(abs(fit.d_roll - d_roll)) < 0.1 * tol
        assert fit.dz == pytest.approx(rise, abs=2e-3 * tol)


def test_one_scale_for_all_points_projects_as_the_per_point_scales():
    """A global shutter's fit hands the projection one scale (1,) for all points instead of one
    per point (N,) (the rows' trigonometry then works per row): the same numbers, bit for bit."""
    rc = RigCamera("front", default_camera(), looking_forward(1.3, 55.0))
    rng = np.random.default_rng(2)
    X = np.column_stack([rng.uniform(0.6, 3.0, 60), rng.uniform(-1.2, 1.2, 60), np.zeros(60)])
    M0 = rc.T_body_camera[:3, :3]
    model = _Model(X, rc.T_body_camera[:3, 3] - rc.vest_point, rc.vest_point, M0)
    x = np.array([0.043, 0.006, math.radians(1.2), math.radians(0.1), math.radians(-0.05), 0.001])
    rows = x + np.vstack([np.zeros(6), np.diag(np.full(6, 1e-5))])
    for s in (1.0, 1.02):
        assert np.array_equal(model.project(rows, np.full(1, s)), model.project(rows, np.full(len(X), s)))


def test_fit_stops_once_converged_where_the_full_iterations_would_end(monkeypatch):
    """The six-parameter fit stops once a Gauss-Newton step moves nothing by more than
    ``fit_tolerance_m`` / ``fit_tolerance_rad``. Given the exact pixels of a known motion (a typical
    step, tilt change and rise, tracked from a guess a few millimetres off), it stops after two
    steps instead of three and lands where all ``fit_iterations`` do (tolerances 0: never early),
    within a micrometre and a microradian of the motion."""
    rc = RigCamera("front", default_camera(), looking_forward(1.3, 55.0))
    truth = np.array([0.043, 0.006, math.radians(1.2), math.radians(0.1), math.radians(-0.05), 0.001])
    guess = truth[:3] + np.array([0.003, -0.002, math.radians(0.1)])
    cam = rc.camera
    fit_once = FloorFlow._fit

    def exact_fit(self, gray0, gray1, problem, flat):
        model = _Model(problem.X, problem.lever, self._vp, problem.M0)
        seen = np.column_stack([model.project(truth[None], np.ones(len(problem.X)))[0], np.ones(len(problem.X))])
        px = cv2.projectPoints(seen, np.zeros(3), np.zeros(3), cam.K, cam.dist)[0]
        ok = np.ones((len(px), 1), np.uint8)
        monkeypatch.setattr(self, "_track", lambda *a, **k: (px.astype(np.float32), ok))
        return fit_once(self, gray0, gray1, problem, flat)

    monkeypatch.setattr(FloorFlow, "_fit", exact_fit)
    solves = []
    lstsq = np.linalg.lstsq
    monkeypatch.setattr(np.linalg, "lstsq", lambda *a, **k: solves.append(1) or lstsq(*a, **k))
    blank = np.zeros((cam.height, cam.width), np.uint8)
    fits = {}
    for name, cfg in (
        ("early", FloorFlowConfig()),
        ("full", FloorFlowConfig(fit_tolerance_m=0.0, fit_tolerance_rad=0.0)),
    ):
        solves.clear()
        fits[name] = (FloorFlow(rc, cfg).refine(blank, blank, guess, 1.0 / FPS), len(solves))
    (early, n_early), (full, n_full) = fits["early"], fits["full"]
    assert (n_early, n_full) == (2, FloorFlowConfig().fit_iterations)
    for fit in (early, full):
        got = np.array([*fit.delta, fit.d_pitch, fit.d_roll, fit.dz])
        assert np.abs(got - truth).max() < 1e-6
        assert fit.residual_px < 1e-3


def test_rolling_shutter_pair_is_measured_row_by_row(floor):
    """A rolling-shutter camera (30 ms read-out) walking 1.3 m/s while turning 60 deg/s: each row is seen
    at its own time (noise-free frames, short exposure: the timing model is under test). With the
    read-out in the model, the step comes out within 2 mm and 0.05 deg (measured 1.6 mm, 0.036 deg:
    the renderer moves the camera in a straight line during the read-out, the model at a constant
    body twist); taken as a global shutter, the turn is 2.4 times as far off (0.087 deg)."""
    readout = 0.03
    rc = RigCamera("front", default_camera(), looking_forward(1.3, 55.0), readout_s=readout)
    v_body, w = 1.3, math.radians(60.0)
    dt = 1.0 / FPS
    heading = np.array([math.cos(0.3), math.sin(0.3)])
    frames, poses = [], []
    for k in range(2):
        P = planar_T(4.0, 4.0, 0.3 + w * k * dt)
        P[:2, 3] += heading * v_body * k * dt
        poses.append(P)
        frames.append(_rolling_frame(floor, rc, P, heading * v_body, w, seed=3 + k))
    d = np.linalg.inv(poses[0]) @ poses[1]
    truth = np.array([d[0, 3], d[1, 3], w * dt])
    guess = truth + np.array([0.004, 0.003, math.radians(0.1)])
    errors = {}
    for rolling in (True, False):
        fit = FloorFlow(rc, rolling_shutter=rolling).refine(frames[0], frames[1], guess, dt)
        assert fit is not None
        errors[rolling] = (float(np.hypot(*(fit.delta[:2] - truth[:2]))), math.degrees(abs(fit.delta[2] - truth[2])))
    assert errors[True][0] < 0.002
    assert errors[True][1] < 0.05
    assert errors[False][1] > 2 * errors[True][1]
    # 60 deg/s is a fast turn: kept because the frames are sharp (median error 0.2 px, against
    # fast_turn_max_residual_px), refused when no fast turn may keep its fit.
    strict = FloorFlow(rc, FloorFlowConfig(fast_turn_max_residual_px=0.0))
    assert strict.refine(frames[0], frames[1], guess, dt) is None


def test_rolling_shutter_turn_follows_the_torsos_twist_acceleration(floor):
    """A rolling-shutter camera (30 ms read-out) on a torso twisting 5 deg either way at 1 Hz while
    walking 1.3 m/s, three frames at the twist's turning point (rate through zero, angular
    acceleration 200 deg/s^2): a point read d after its frame's time turned, between its two
    sightings, by the interval's turn plus the rate's change times d. With the previous fit's rate
    (``rs_acceleration``) the second pair's turn comes out within 0.02 deg (4e-5 measured);
    at constant velocity it is read as if earlier, 0.079 deg off (the rows that set the turn are
    the far floor's, read early)."""
    readout = 0.03
    rc = RigCamera("front", default_camera(), looking_forward(1.3, 55.0), readout_s=readout)
    amp, freq, v = math.radians(5.0), 1.0, 1.3
    dt = 1.0 / FPS
    t = 0.25 + (np.arange(3) - 1) * dt  # sin(2 pi f t) peaks at t = 0.25 s: the turn reverses

    def yaw(t):
        return amp * np.sin(2 * math.pi * freq * t)

    def rate(t):
        return amp * 2 * math.pi * freq * np.cos(2 * math.pi * freq * t)

    poses, frames = [], []
    for k, tk in enumerate(t):
        P = planar_T(3.0 + v * tk, 4.0, float(yaw(tk)))
        poses.append(P)
        frames.append(_rolling_frame(floor, rc, P, np.array([v, 0.0]), float(rate(tk)), seed=21 + k))
    truth = []
    for a, b in zip(poses[:-1], poses[1:]):
        d = np.linalg.inv(a) @ b
        truth.append([d[0, 3], d[1, 3], math.atan2(d[1, 0], d[0, 0])])
    errors = {}
    for accelerated in (True, False):
        flow = FloorFlow(rc, FloorFlowConfig(rs_acceleration=accelerated))
        fits = [flow.refine(frames[k], frames[k + 1], np.asarray(truth[k]), dt) for k in range(2)]
        assert all(f is not None for f in fits)
        errors[accelerated] = math.degrees(abs(fits[1].delta[2] - truth[1][2]))
    assert errors[True] < 0.02
    assert errors[False] > 0.04
    assert errors[False] > 3 * errors[True]


def test_fits_far_off_are_refused(floor):
    """The flow needs the patch's step as its start: from a guess 4 cm off, the points do not find
    their texture and the fit's median reprojection error (8.7 px measured) refuses it. A fit that
    ends further from the patch's step than ``max_disagreement_m`` is refused too (a gross
    mistracking). A blank floor is not the flow's to refuse: the patch's match refuses it first
    (``test_textureless_or_noise_floor_is_refused``)."""
    rc = RigCamera("front", default_camera(), looking_forward(1.3, 55.0))
    P0 = planar_T(4.0, 4.0, 0.3)
    step = np.array([0.04, 0.0, 0.0])
    g0 = render_view(floor, rc.camera, P0 @ rc.T_body_camera, lux=200, seed=1).image
    g1 = render_view(floor, rc.camera, P0 @ planar_T(*step) @ rc.T_body_camera, lux=200, seed=2).image
    dt = 1.0 / FPS
    assert FloorFlow(rc).refine(g0, g1, step + np.array([0.0, 0.04, 0.0]), dt) is None
    near = step + np.array([0.004, 0.003, 0.0])
    fit = FloorFlow(rc).refine(g0, g1, near, dt)
    assert fit is not None and np.allclose(fit.delta[:2], step[:2], atol=0.003)
    # The same fit, with the gate tighter than its distance from the guess (5 mm).
    assert FloorFlow(rc, FloorFlowConfig(max_disagreement_m=0.002)).refine(g0, g1, near, dt) is None


def test_odometry_uses_the_flow_for_the_tilt_change(floor):
    """Through :class:`FloorOdometry`: a walk whose torso nods 0.3 deg per frame forward then back, the
    tilt anchored upright by a fix at the start (noise-free frames: the models are under test). With
    the flow, every step is refined and keeps its length within 1.5 mm (0.7 measured); with the patch
    alone (the homography's tilt fit) the nod leaks into the steps (4.1 mm measured). With sensor
    noise the flow's steps are 1.3 mm RMS off and the patch's 2.1."""
    rc = RigCamera("front", default_camera(), looking_forward(1.3, 60.0))
    fwd = 0.04
    nod = [0.0, 0.3, 0.6, 0.3, 0.0, -0.3, -0.6, -0.3, 0.0, 0.3]
    imgs = []
    for k, p in enumerate(nod):
        P = planar_T(4.0 + fwd * k * math.cos(0.3), 4.0 + fwd * k * math.sin(0.3), 0.3)
        imgs.append(
            render_view(floor, rc.camera, P @ _tilted(rc, math.radians(p), 0.0), lux=200, seed=k, noise=False).image
        )
    errs = {}
    for flow in (True, False):
        odo = FloorOdometry(rc, OdometryConfig(flow=flow))
        steps, residuals = [], []
        for k, img in enumerate(imgs):
            if k == 0:
                odo.anchor_tilt_angles(0.0, 0.0, 0.0)  # a sticker fix saw the torso upright
            steps.append(odo.measure(img, k / FPS))
            residuals.append(odo.last_flow_residual)
        d = np.array([s.delta for s in steps[1:] if s is not None])
        assert len(d) == len(imgs) - 1
        errs[flow] = float(np.max(np.abs(d[:, 0] - fwd)))
        if flow:
            assert odo.flow_steps == len(imgs) - 1 and odo.flow_refused == 0
            # Each step's fit reports how well the frames fitted (noise-free: 0.05-0.10 px
            # measured), the first frame none.
            assert residuals[0] is None and all(0.0 <= r < 0.3 for r in residuals[1:])
        else:
            assert odo.flow_steps == 0 and residuals == [None] * len(imgs)
    assert errs[True] < 0.0015
    assert errs[False] > 2 * errs[True]


def _tracks_as_one_call(flow, g0, g1, p0, guess, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Assert that ``flow._track`` gives the points and status of one ``calcOpticalFlowPyrLK`` call
    with the flow's levels on the frames at ``scale`` (1: full resolution; 0.5: the half frames,
    one level fewer), scaled back; return that call's points (N, 1, 2) at full resolution and
    which of them tracked (N,) bool."""
    import cv2

    cfg = flow.config
    a, b = (g0, g1) if scale == 1.0 else (cv2.pyrDown(g0), cv2.pyrDown(g1))
    want, want_status, _ = cv2.calcOpticalFlowPyrLK(
        a,
        b,
        (p0 * scale).astype(np.float32),
        (guess * scale).astype(np.float32),
        winSize=(cfg.window_px, cfg.window_px),
        maxLevel=cfg.levels - (0 if scale == 1.0 else 1),
        criteria=flow._criteria,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    want = want / scale
    got, status = flow._track(g0, g1, p0, guess)
    ok = want_status.ravel() == 1
    assert ok.sum() >= 60
    np.testing.assert_array_equal(status.ravel(), want_status.ravel())
    np.testing.assert_allclose(got.reshape(-1, 2)[ok], want.reshape(-1, 2)[ok], atol=1e-3)
    return want, ok


def test_tracking_ends_at_half_resolution_for_the_reference_camera(floor):
    """With ``finest_scale`` 2 (the default) the reference camera's points are tracked down to its
    half-resolution level only: they equal one ``calcOpticalFlowPyrLK`` call on the half frames,
    scaled back, with that call's status; from guesses up to 8 px off they land where the floor
    under them went (projected through the true poses), unbiased and no less precisely than with
    the full-resolution pass. A camera with pixels twice as large keeps its own full resolution
    (its half level would be a quarter of the reference's)."""
    import cv2

    rc = RigCamera("front", default_camera(), looking_forward(1.3, 55.0))
    cam = rc.camera
    P0 = planar_T(4.0, 4.0, 0.3)
    T0, T1 = P0 @ rc.T_body_camera, P0 @ planar_T(0.04, 0.002, 0.01) @ rc.T_body_camera
    g0, g1 = (render_view(floor, cam, T, lux=200, seed=k).image for k, T in enumerate((T0, T1)))
    half = FloorFlow(rc, FloorFlowConfig(flatten_px=0))
    full = FloorFlow(rc, FloorFlowConfig(flatten_px=0, finest_scale=0.0))
    assert half._half_only and not full._half_only
    p0 = half._px.reshape(-1, 1, 2)
    # Where the floor under each point went: its ray to the floor, seen from the moved camera.
    n = cv2.undistortPoints(p0.astype(np.float64), cam.K, cam.dist).reshape(-1, 2)
    rays = np.column_stack([n, np.ones(len(n))]) @ T0[:3, :3].T
    down = rays[:, 2] < -0.2
    X = T0[:3, 3] + (-T0[2, 3] / rays[down, 2])[:, None] * rays[down]
    true = cv2.projectPoints((X - T1[:3, 3]) @ T1[:3, :3], np.zeros(3), np.zeros(3), cam.K, cam.dist)[0]
    p0 = p0[down]
    guess = (true + np.random.default_rng(4).uniform(-8.0, 8.0, true.shape)).astype(np.float32)
    want, ok = _tracks_as_one_call(half, g0, g1, p0, guess, scale=0.5)
    got, _ = half._track(g0, g1, p0, guess)
    got_full, status_full = full._track(g0, g1, p0, guess)
    both = ok & (status_full.ravel() == 1)
    d_half = (got - true).reshape(-1, 2)[both]
    d_full = (got_full - true).reshape(-1, 2)[both]
    # Measured: mean offset (0.07, 0.10) px, RMS 1.38 px at half resolution, 1.49 px with the full pass.
    assert np.all(np.abs(d_half.mean(axis=0)) < 0.3)
    assert np.sqrt(np.mean(d_half**2)) < 1.1 * np.sqrt(np.mean(d_full**2))
    half_cam = RigCamera("front", default_camera().scaled(0.5), looking_forward(1.3, 55.0))
    assert not FloorFlow(half_cam, FloorFlowConfig())._half_only


def test_tracking_on_the_kept_half_frame_equals_one_pyramid_call(floor):
    """The flow tracks its coarse levels on each frame's half-resolution level, built once per frame
    (OpenCV's Python binding takes no pyramid made before); the points must be those of one
    ``calcOpticalFlowPyrLK`` call with the same levels, from guesses up to 8 px off (the frames as
    they are: with ``flatten_px`` the coarse levels are tracked on flattened frames instead)."""
    rc = RigCamera("front", default_camera(), looking_forward(1.3, 55.0))
    P0 = planar_T(4.0, 4.0, 0.3)
    frames = [
        render_view(
            floor, rc.camera, P0 @ planar_T(0.04 * k, 0.002 * k, 0.01 * k) @ rc.T_body_camera, lux=200, seed=k
        ).image
        for k in range(3)
    ]
    flow = FloorFlow(rc, FloorFlowConfig(flatten_px=0, finest_scale=0.0))
    p0 = flow._px.reshape(-1, 1, 2)
    rng = np.random.default_rng(3)
    moved = 0
    for g0, g1 in zip(frames[:-1], frames[1:]):
        guess = (p0 + rng.uniform(-8.0, 8.0, p0.shape)).astype(np.float32)
        want, ok = _tracks_as_one_call(flow, g0, g1, p0, guess, scale=1.0)
        moved += int(np.sum(np.linalg.norm((want - p0).reshape(-1, 2)[ok], axis=1) > 10.0))
    assert moved > 50  # the step moved the points far enough that the coarse levels mattered
    assert len(flow._halves) == 2  # each frame's half level built once and kept for the next pair


def test_rolling_shutter_patch_takes_the_trackers_twist(floor):
    """A rolling-shutter camera (30 ms read-out) at 1.2 m/s entering a turn, its turn rate growing by
    40 deg/s every frame (the field walk f01's turn entries grew by about 15 deg/s a frame, to 150
    deg/s), patch alone (no flow, as where the flow refuses a smeared fast turn), noise-free frames. Each frame's patch is sampled with the
    twist the tracker gives for it (``rs_twist_from_tracker``). With each frame's true twist the
    steps come out within 4 mm (2.9 measured); with the twist a frame late, 7.9 mm; with the
    odometry's own last step (the option off: the tracker's twist only until the odometry has a
    step of its own), 11.5 mm. The turn is read within 0.2-0.23 deg in all three: the read-out's
    skew shows in the step's position."""
    readout = 0.03
    rc = RigCamera("front", default_camera(), looking_forward(1.3, 55.0), readout_s=readout)
    v_body, accel = 1.2, math.radians(40.0) * FPS  # turn rate + 40 deg/s per frame
    dt = 1.0 / FPS
    # The walk integrated finely: heading 0.3 + accel t^2 / 2, position along it at v_body.
    fine = np.linspace(0.0, 4 * dt, 4001)
    yaw = 0.3 + 0.5 * accel * fine**2
    xy = 4.0 + np.concatenate(
        [
            [[0.0, 0.0]],
            np.cumsum(v_body * np.diff(fine)[:, None] * np.column_stack([np.cos(yaw[1:]), np.sin(yaw[1:])]), axis=0),
        ]
    )
    frames, poses, twists = [], [], []
    for k in range(5):
        j = 1000 * k
        P = planar_T(xy[j, 0], xy[j, 1], yaw[j])
        poses.append(P)
        twists.append(np.array([v_body, 0.0, accel * fine[j]]))
        frames.append(
            _rolling_frame(
                floor, rc, P, np.array([math.cos(yaw[j]), math.sin(yaw[j])]) * v_body, accel * fine[j], 5 + k
            )
        )
    truth = []
    for a, b in zip(poses[:-1], poses[1:]):
        d = np.linalg.inv(a) @ b
        truth.append([d[0, 3], d[1, 3], math.atan2(d[1, 0], d[0, 0])])
    truth = np.array(truth)

    def steps(from_tracker: bool, lag: int) -> np.ndarray:
        # (An upright torso: the lean model, which would roll the patch into the turn, is off.)
        odo = FloorOdometry(rc, OdometryConfig(flow=False, lean_correction=False, rs_twist_from_tracker=from_tracker))
        out = [odo.measure(f, k * dt, twists[max(k - lag, 0)]) for k, f in enumerate(frames)]
        return np.array([s.delta for s in out[1:]])

    def worst(d: np.ndarray) -> tuple[float, float]:
        return float(np.hypot(*(d[:, :2] - truth[:, :2]).T).max()), math.degrees(
            float(np.abs(d[:, 2] - truth[:, 2]).max())
        )

    right, late, own = worst(steps(True, 0)), worst(steps(True, 1)), worst(steps(False, 0))
    assert right[0] < 0.004 and right[1] < 0.3
    assert late[0] > 2 * right[0]
    assert own[0] > 3 * right[0]


def test_a_coarser_camera_starts_its_pyramid_lower_and_trusts_its_tilts_less():
    """At half the reference resolution the pixels are twice as large: the flow runs one pyramid
    level fewer (its coarsest level sees the floor at the reference's scale) and the tilt filter's
    angular sigmas are doubled; the reference camera and a finer one keep the configured values."""
    from tagloc.core.camera import default_camera, pixel_scale
    from tagloc.core.rig import RigCamera, looking_forward
    from tagloc.vision.floor_flow import FloorFlow, FloorFlowConfig
    from tagloc.vision.odometry import FloorOdometry, OdometryConfig

    cfg = OdometryConfig()
    for factor, scale, levels in ((1.0, 1.0, 2), (0.5, 2.0, 1), (2.0, 1.0, 2)):
        cam = default_camera().scaled(factor) if factor != 1.0 else default_camera()
        rc = RigCamera("front", cam, looking_forward(1.3, 55.0))
        assert pixel_scale(cam) == pytest.approx(scale, rel=1e-3)
        assert FloorFlow(rc, FloorFlowConfig())._levels == levels
        torso = FloorOdometry(rc, cfg)._torso
        assert torso.anchor_sigma == pytest.approx(cfg.tilt_anchor_sigma * scale, rel=1e-3)
        assert torso.fit_sigma == pytest.approx(cfg.tilt_fit_sigma * scale, rel=1e-3)


def test_flatten_divides_out_smooth_shading_and_keeps_texture():
    """A textured frame under a 40 % ramp of shading and a soft shadow 25 % deep (penumbra 120 px):
    divided by its local mean, it matches the unshaded frame divided alike within 3 grey levels
    (measured 1-2; the texture itself spans +-40), away from the borders."""
    rng = np.random.default_rng(5)
    import cv2

    H, W = 240, 320
    tex = cv2.GaussianBlur(rng.normal(0.0, 1.0, (H, W)).astype(np.float32), (0, 0), 1.5)
    base = 100.0 * (1.0 + 0.12 * tex / tex.std())
    y, x = np.mgrid[0:H, 0:W]
    shade = (0.8 + 0.4 * x / W) * (1.0 - 0.25 / (1.0 + np.exp(-(y - H / 2) / 30.0)))
    plain = np.clip(base + 0.5, 0, 255).astype(np.uint8)
    shaded = np.clip(base * shade + 0.5, 0, 255).astype(np.uint8)
    a, b = flatten(plain, 21).astype(float), flatten(shaded, 21).astype(float)
    inner = np.s_[20:-20, 20:-20]
    assert np.abs(a - b)[inner].max() <= 3.0
    assert a[inner].std() > 5.0  # the texture is still there


def test_shadow_fixed_to_the_body_does_not_shorten_the_step(floor):
    """The operator 0.7 m past a row of low lamps (4.5 m up, 4 m apart), the camera pitched 65
    degrees down, walking 3 cm a frame (0.9 m/s): the body's shadow lies in the lower part of the
    view and moves with it. Noise-free, so that only the shading differs: Lucas-Kanade on the
    frames as they are reads the 30 mm step 2.1 mm short (measured), divided by the local mean
    (``flatten_px``) 0.07 mm; without the shadow both 0.13 mm."""
    from tagloc.sim.lamps import LampConfig, Lamps

    rc = RigCamera("front", default_camera(), looking_forward(1.3, 65.0))
    lamps = Lamps(LampConfig(spacing_m=4.0, height_m=4.5), seed=0)
    P0 = planar_T(lamps.offset[0] + 8.7, lamps.offset[1] + 8.3, 0.0)
    step = np.array([0.03, 0.0, 0.0])
    frames = []
    for k, P in enumerate((P0, P0 @ planar_T(*step))):
        body = np.r_[P[:2, 3] - lamps.config.axis_behind_m * P[:2, 0], 0.0]
        frames.append(
            render_view(
                floor, rc.camera, P @ rc.T_body_camera, lux=250, seed=10 + k, noise=False, lamps=lamps, body=body
            ).image
        )
    err = {}
    for fp in (0, FloorFlowConfig().flatten_px):
        fit = FloorFlow(rc, FloorFlowConfig(flatten_px=fp)).refine(*frames, step + [0.003, -0.002, 0.001], 1 / FPS)
        assert fit is not None
        err[fp] = 1000.0 * (fit.delta[0] - step[0])
    assert err[0] < -1.5 and abs(err[FloorFlowConfig().flatten_px]) < 0.5, err


@pytest.mark.parametrize("readout_s, rel", [(0.0, 0.1), (0.03, 0.4)])
def test_the_flow_fits_actual_sigma_grows_with_the_change_and_the_read_out(readout_s, rel):
    """What the tilt filter's stated variance takes a flow fit's error to be: the floor sigma for
    no change, growing by the change times 0.1 (global shutter) or 0.4 (30 ms read-out)."""
    from tagloc.vision.floor_flow import FlowStep

    rc = RigCamera("front", default_camera(), looking_forward(1.3, 55.0), readout_s=readout_s, legs_in_view=False)
    odo = FloorOdometry(rc, OdometryConfig())
    floor = FloorFlowConfig().tilt_sigma
    still = FlowStep(np.zeros(3), 0.0, 0.0, 0.0, 1.0, 80)
    assert odo._flow_tilt_sigmas(still) == pytest.approx((floor, floor))
    d = math.radians(0.6)
    moving = FlowStep(np.zeros(3), d, -d / 2, 0.0, 1.0, 80)
    sp, sr = odo._flow_tilt_sigmas(moving)
    assert sp == pytest.approx(math.hypot(floor, rel * d))
    assert sr == pytest.approx(math.hypot(floor, rel * d / 2))


def test_the_patch_fits_tilt_change_is_stated_by_its_actual_error_and_weighed_by_its_design(monkeypatch):
    """Where the flow is refused, the patch's homography fit of the tilt change goes to the tilt
    filter weighed by ``tilt_fit_sigma`` (the design) while the stated variance takes its actual
    error, which grows with the change (``tilt_fit_sigma_rel``): a fitted 1 deg change leaves the
    estimate where the design puts it and the stated spread wider than the design's."""
    rc = RigCamera("front", default_camera(), looking_forward(1.3, 55.0), legs_in_view=False)
    # (No rate bound: the stated variance's process increment is then the filter's own.)
    cfg = OdometryConfig(flow=False, lean_correction=False, tilt_rate_sigma=math.inf)
    odo = FloorOdometry(rc, cfg)
    ref = FloorOdometry(rc, dataclasses.replace(cfg, tilt_fit_sigma_rel=0.0))
    fit = (math.radians(1.0), math.radians(-0.5))
    for o in (odo, ref):
        monkeypatch.setattr(o, "_tilt_fit", lambda *a, **k: fit)
        o.anchor_tilt_angles(0.0, 0.0, 0.0)
        o._untilted_step(None, None, None, np.zeros(3), 0.0, 1 / 30)
    a, b = odo._torso.pitch, ref._torso.pitch
    assert a.value == b.value and a.var == b.var  # the same weights
    assert b.var_true == pytest.approx(b.var)  # stated as the design: the design's variance
    # Actual sigma hypot(0.3 deg, 1 x 1 deg) = 1.04 deg, against the design's 0.3.
    assert a.var_true > 2.0 * b.var_true
    assert odo._torso.roll.var_true > ref._torso.roll.var_true
