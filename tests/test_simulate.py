"""The session simulator: walk, floor, image formation (exposure, blur, noise) and session output."""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from tagloc.cli import main
from tagloc.core.camera import Camera, default_camera, save_calibration
from tagloc.core.errors import InputError
from tagloc.core.rig import looking_forward
from tagloc.core.sticker import INNER_CORNERS, OUTER_CORNERS
from tagloc.core.stickermap import StickerMap, save_map
from tagloc.io.session import SessionReader
from tagloc.sim.floor import Floor, FloorConfig
from tagloc.sim.render import (
    ExposureConfig,
    Flicker,
    OpticsConfig,
    SensorConfig,
    choose_gain,
    electrons_per_lux_s,
    expected_blur_px,
    exposure_time,
    subframe_offsets,
)
from tagloc.sim.simulate import (
    SimConfig,
    camera_pose_looking_at,
    read_groundtruth_frames,
    render_view,
    simulate_session,
    true_corners,
)
from tagloc.sim.timing import TimingConfig, frame_schedule
from tagloc.sim.walk import WalkConfig, plan_walk


def aisle_map(rows: int = 3, length_m: float = 12.0, spacing_m: float = 1.5, aisle_m: float = 3.0) -> StickerMap:
    """Stickers along ``rows`` parallel aisles (world +y), one every ``spacing_m``; IDs 100, 101, ..."""
    ys = np.arange(0.0, length_m + 1e-9, spacing_m)
    xy = np.array([(i * aisle_m, y) for i in range(rows) for y in ys])
    yaw = np.radians(np.arange(len(xy)) * 37.0 % 360)
    return StickerMap(np.arange(100, 100 + len(xy)), xy, yaw)


def small_camera(f: float = 640.0, w: int = 320, h: int = 240, dist: tuple = (0, 0, 0, 0, 0)) -> Camera:
    return Camera(np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]]), np.array(dist, float), w, h)


def test_ground_truth_leaves_out_a_sticker_the_lens_folds_into_the_image():
    """A wide lens (k1 = -0.45, folding at 50 deg off the axis) puts a sticker 50-51 deg to the left
    onto the image's left side if the polynomial is evaluated there; it is not in view."""
    cam = Camera(default_camera().K, np.array([-0.45, 0.0, 0.0, 0.0, 0.0]), 1296, 972)
    T_wc = looking_forward(1.3, 55.0)
    ray = T_wc[:3, :3] @ np.array([-1.2, 0.2, 1.0])
    xy = (T_wc[:3, 3] - T_wc[2, 3] / ray[2] * ray)[:2]
    smap = StickerMap(np.array([7]), xy[None], np.zeros(1))
    pts = np.vstack([OUTER_CORNERS, INNER_CORNERS]) + [*xy, 0.0]
    px = cam.project((pts - T_wc[:3, 3]) @ T_wc[:3, :3])
    assert np.all((px > 0) & (px < (1295, 971)))  # where the folded polynomial puts it
    assert true_corners(smap, cam, T_wc, 7) is None


# -- physics ---------------------------------------------------------------------------------------


def test_expected_blur_matches_paper():
    # The paper: 2571 px focal length, 1 m/s at 1 m needs 1/2571 s for 1 px of blur.
    assert expected_blur_px(2571.0, 1.0, 1 / 2571, 1.0) == pytest.approx(1.0)
    assert expected_blur_px(1285.7, 1.3, 0.003, 1.6) == pytest.approx(3.134, abs=0.01)


def edge_width_10_90(profile: np.ndarray) -> float:
    """10-90 % width (px) of a falling edge in a 1-D profile, with linear interpolation."""
    hi, lo = np.median(profile[:6]), np.median(profile[-4:])
    levels = lo + (hi - lo) * np.array([0.9, 0.1])
    xs = []
    for lv in levels:
        k = int(np.argmax(profile < lv))
        xs.append(k - 1 + (profile[k - 1] - lv) / (profile[k - 1] - profile[k]))
    return xs[1] - xs[0]


@pytest.mark.parametrize("blur", [6.0, 12.0])
def test_motion_blur_matches_f_v_t_over_d(blur):
    """A camera translating parallel to the floor blurs a straight edge by f v t / D."""
    cam = small_camera()
    smap = StickerMap([7], [[0.0, 0.0]], [0.0])
    floor = Floor(smap, FloorConfig(texture=False))
    D, t_exp = 0.25, 0.004
    T = camera_pose_looking_at((0.0, 0.0), height_m=D, pitch_deg=90.0)
    v = blur * D / (cam.fx * t_exp)
    lin = dict(
        optics=OpticsConfig(psf_sigma_px=0.0, vignetting=0.0),
        noise=False,
        sensor=SensorConfig(gamma=1.0, prnu=0.0),
        exposure=ExposureConfig(px_per_subframe=0.25, max_subframes=64),
    )
    # Straight down with yaw 0, image +x is world -y: move along world y.
    res = render_view(floor, cam, T, 300.0, velocity=(0.0, v, 0.0), exposure_s=t_exp, gain=4.0, **lin)
    sharp = render_view(floor, cam, T, 300.0, exposure_s=t_exp, gain=4.0, **lin)
    assert res.blur_px == pytest.approx(blur, rel=0.02)
    assert res.subframes == min(64, math.ceil(blur / 0.25))
    corners = true_corners(floor, cam, T, 7)
    row = int(round(corners[:4, 1].mean()))
    x_edge = corners[:4, 0].min()  # the sticker's left outer edge: floor -> black frame
    x0 = int(x_edge) - 20  # the frame is 20 px wide: 14 px of black past the edge, minus half the blur
    prof = res.image[row - 3 : row + 4, x0 : x0 + 34].astype(float).mean(axis=0)
    prof_sharp = sharp.image[row - 3 : row + 4, x0 : x0 + 34].astype(float).mean(axis=0)
    w_sharp = edge_width_10_90(prof_sharp)
    assert w_sharp < 1.5
    # A box blur of length L has a 10-90 % width of 0.8 L; interpolation adds a fraction of a pixel.
    assert edge_width_10_90(prof) == pytest.approx(0.8 * expected_blur_px(cam.fx, v, t_exp, D), abs=0.8)


def test_short_motion_blur_is_rendered_at_its_length():
    """A 1 px blur (walking at 300 lux) is rendered, from two sub-frames at the middles of the
    exposure's halves, and matches a render sampled every 0.02 px; 0.25 px, under the lens's PSF, is not."""
    assert subframe_offsets(1.0, 0.004, ExposureConfig()) == pytest.approx([-0.001, 0.001])
    assert subframe_offsets(0.25, 0.004, ExposureConfig()) == pytest.approx([0.0])
    assert subframe_offsets(3.0, 0.006, ExposureConfig()) == pytest.approx(np.arange(-2.5, 3) * 0.001)
    assert len(subframe_offsets(30.0, 0.006, ExposureConfig())) == 16
    cam = small_camera()
    floor = Floor(StickerMap([7], [[0.0, 0.0]], [0.3]), FloorConfig(texture=False))
    T = camera_pose_looking_at((0.0, 0.0), height_m=0.5, pitch_deg=90.0)  # a 128 px sticker
    # Linear, noise-free, fine ADC: white paper at ~170 DN, so that only the blur differs.
    lin = dict(noise=False, sensor=SensorConfig(gamma=1.0, adc_bits=16), exposure_s=0.004, gain=20.0)
    sharp = render_view(floor, cam, T, 300.0, **lin).image.astype(float)
    fine = ExposureConfig(px_per_subframe=0.02, max_subframes=100)
    res = render_view(floor, cam, T, 300.0, blur_px=1.0, blur_direction_deg=30.0, **lin)
    ref = render_view(floor, cam, T, 300.0, blur_px=1.0, blur_direction_deg=30.0, exposure=fine, **lin)
    assert res.blur_px == pytest.approx(1.0, abs=0.01) and res.subframes == 2 and ref.subframes == 50
    img, ref_img = res.image.astype(float), ref.image.astype(float)
    changed = np.abs(ref_img - sharp) > 1  # the pixels the blur changes: the sticker's edges

    def rms(d):
        return float(np.sqrt((d[changed] ** 2).mean()))

    # Measured: the blur changes those pixels by 4.7 DN RMS; the render is 1.1 DN off the reference
    # (one sub-frame, the sharp image, was 4.7 DN off).
    assert rms(ref_img - sharp) == pytest.approx(4.7, abs=1.0)
    assert rms(img - sharp) > 0.75 * rms(ref_img - sharp)
    assert rms(img - ref_img) < 0.3 * rms(ref_img - sharp)
    under = render_view(floor, cam, T, 300.0, blur_px=0.25, blur_direction_deg=30.0, **lin)
    assert under.subframes == 1 and np.array_equal(under.image.astype(float), sharp)


def test_exposure_policy_and_gain():
    cfg = ExposureConfig()
    luxes = [10, 20, 50, 100, 300, 1000]
    times = [exposure_time(lx, cfg, 1 / 30) for lx in luxes]
    assert times[luxes.index(300)] == pytest.approx(0.001)
    assert times[luxes.index(100)] == pytest.approx(0.003)
    assert times[luxes.index(50)] == pytest.approx(0.006)
    assert all(a >= b for a, b in zip(times, times[1:]))
    assert max(times) == pytest.approx(cfg.max_exposure_s)
    assert exposure_time(5, replace(cfg, max_exposure_s=1.0), 1 / 30) == pytest.approx(1 / 30)  # frame interval cap
    with pytest.raises(InputError):
        exposure_time(0.0, cfg)
    # Photometry: e- per pixel per lux s = T / (4 N^2) * photons * pitch^2 * QE.
    assert electrons_per_lux_s(OpticsConfig(), SensorConfig()) == pytest.approx(
        0.9 / (4 * 2.9**2) * 1e16 * 2.8e-6**2 * 0.25, rel=1e-9
    )
    assert choose_gain(1e6, SensorConfig(), cfg) == 1.0
    assert choose_gain(1.0, SensorConfig(), cfg) == SensorConfig().max_gain

    # Renders: below the exposure cap the signal is constant (lux * t is), above it gain takes over.
    cam = small_camera()
    floor = Floor(StickerMap([1], [[0.0, 0.0]], [0.0]), FloorConfig(texture=False))
    T = camera_pose_looking_at((0.0, 0.0), 1.3, 55.0)
    low_target = replace(cfg, target_mean=0.02)  # keeps the gain below its cap in bright light
    out = {lx: render_view(floor, cam, T, lx, noise=False, exposure=low_target) for lx in (10, 20, 50, 100, 300)}
    # (Equal up to the dark current, which grows with the exposure time.)
    assert out[300].gain == pytest.approx(out[50].gain, rel=5e-3)
    assert out[300].mean_signal_e == pytest.approx(out[50].mean_signal_e, rel=5e-3)
    assert out[20].exposure_s == out[10].exposure_s == cfg.max_exposure_s
    assert out[10].gain > out[20].gain > out[50].gain * 1.2
    assert out[10].mean_signal_e == pytest.approx(out[20].mean_signal_e / 2, rel=1e-2)
    # The AE reaches its target: mean image level ~ target_mean of full scale through the gamma curve.
    assert out[50].image.mean() == pytest.approx(255 * 0.02 ** (1 / 2.2), rel=0.1)
    # Noise: darker light at capped exposure -> lower SNR on a uniform floor.
    noisy = {lx: render_view(floor, cam, T, lx, exposure=low_target, seed=3).image[80:160, 100:220] for lx in (5, 100)}
    snr = {lx: im.mean() / im.std() for lx, im in noisy.items()}
    assert snr[5] < 0.7 * snr[100]


def test_flicker_bands_a_rolling_shutter_and_a_full_period_averages_it_out():
    """30 % flicker at 100 Hz on a uniform floor: with a 30 ms rolling shutter and a 1 ms exposure,
    each row's signal (linearised, against steady light) follows the flicker at that row's time,
    three periods down the frame; a global shutter scales the whole frame by the flicker at the
    frame's time; a 10 ms exposure (one period) sees steady light."""
    from tagloc.core.rig import row_delay_s
    from tagloc.sim.render import Renderer

    cam = small_camera()
    floor = Floor(StickerMap([1], [[0.0, 0.0]], [0.0]), FloorConfig(texture=False))
    T = camera_pose_looking_at((0.0, 0.0), 1.3, 55.0)
    flicker = Flicker(0.3, 100.0, 0.7)
    t_mid = 0.0123

    def rows_linear(rolling: bool, exposure_s: float, fl: Flicker | None) -> np.ndarray:
        exp = ExposureConfig(rolling_shutter=rolling, readout_s=0.030, bands=8, target_mean=0.05)
        r = Renderer(floor, cam, sensor=SensorConfig(noise=False, prnu=0.0), exposure=exp, flicker=fl)
        img = r.render(
            lambda ts: np.repeat(T[None], len(ts), 0), t_mid, 300.0, np.random.default_rng(0), exposure_s=exposure_s
        ).image
        return ((img[:, 40:280].astype(float) + 0.0) / 255.0) ** 2.2

    rows = np.arange(cam.height)
    for rolling in (True, False):
        ratio = (rows_linear(rolling, 0.001, flicker) / rows_linear(rolling, 0.001, None)).mean(axis=1)
        want = flicker.mean_over(t_mid + row_delay_s(rows, cam.height, 0.030 if rolling else 0.0), 0.001)
        # Rows near the horizon are dark (vignetting, far floor): compare where the signal is.
        ok = rows > 20
        assert np.abs(ratio[ok] - want[ok]).max() < 0.03, np.abs(ratio[ok] - want[ok]).max()
        assert (np.ptp(ratio[ok]) > 0.5) == rolling  # bands (+-30 %) only with the rolling shutter
    steady = rows_linear(True, 0.010, flicker) / rows_linear(True, 0.010, None)
    assert np.abs(steady[rows > 20].mean(axis=1) - 1.0).max() < 0.02


# -- walk -----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def long_walk():
    smap = aisle_map()
    return smap, plan_walk(smap, WalkConfig(seconds=60.0, seed=4, stop_every_s=10.0))


def test_walk_speed_stops_turns_and_smoothness(long_walk):
    smap, walk = long_walk
    t = np.arange(0.0, 60.0, 0.005)
    v = walk.speed(t)
    moving = v > 0.3
    assert 1.1 < np.median(v[moving]) < 1.45
    assert np.percentile(v, 99) < 1.75
    assert len(walk.stops) >= 3
    assert all(1.0 <= b - a <= 2.0 for a, b in walk.stops)
    for a, b in walk.stops:  # standing still through the stop
        if 0 < a and b < 60:
            assert walk.speed(np.linspace(a, b, 20)).max() < 0.05
    # Turning on the spot: standing while the heading turns fast.
    yaw_rate = np.gradient(walk.planar(t)[:, 2], t)
    assert np.any((v < 0.15) & (np.abs(yaw_rate) > math.radians(45)))
    # C1 positions and smooth heading: bounded acceleration and yaw acceleration, no jumps.
    acc = np.gradient(walk.spline(t, 1)[:, :2], t, axis=0)
    assert np.max(np.hypot(*acc.T)) < 6.0
    assert np.max(np.abs(np.diff(walk.planar(t)[:, :2], axis=0))) < 2.0 * 0.005
    assert np.max(np.abs(np.gradient(yaw_rate, t))) < 15.0
    # The walk follows the sticker lines.
    # The walk follows the sticker lines: the aisles (x = 0, 3, 6) and, to change aisle, their ends.
    p = walk.planar(t)[:, :2]
    d = np.minimum(np.min(np.abs(p[:, :1] - [0.0, 3.0, 6.0]), axis=1), np.min(np.abs(p[:, 1:] - [0.0, 12.0]), axis=1))
    assert np.percentile(d, 90) < 0.45
    # Ground truth body frame is on the floor, upright.
    T = walk.T_world_body(t[::100], np.array([0.0, 0.0, 1.3]))
    assert np.allclose(T[:, 2, 3], 0.0) and np.allclose(T[:, 2, 2], 1.0)


def test_walk_vest_bobbing_at_step_frequency():
    smap = aisle_map(rows=1, length_m=40.0)
    cfg = WalkConfig(seconds=30.0, seed=2, stop_every_s=0.0, speed_variation=0.05)
    walk = plan_walk(smap, cfg)
    from tagloc.core.rig import looking_forward

    T_bc = looking_forward(1.3, 55.0)
    fs = 100.0
    t_all = np.arange(0.0, 30.0, 1 / fs)
    # The longest stretch of steady walking (the line ends make the walker turn round).
    walking = np.r_[False, walk.speed(t_all) > 1.0, False].astype(int)
    starts, ends = np.flatnonzero(np.diff(walking) == 1), np.flatnonzero(np.diff(walking) == -1)
    k = int(np.argmax(ends - starts))
    t = t_all[starts[k] + 100 : ends[k] - 100]
    assert len(t) > 8 * fs
    Tc = walk.T_world_camera(t, T_bc)
    z = Tc[:, 2, 3] - 1.3
    spec = np.abs(np.fft.rfft((z - z.mean()) * np.hanning(len(z))))
    freqs = np.fft.rfftfreq(len(z), 1 / fs)
    f_peak = freqs[np.argmax(spec)]
    assert 1.7 < f_peak < 2.1
    amplitude = math.sqrt(2) * z.std()
    assert 0.02 <= amplitude <= 0.03
    # Lateral sway (in the body frame) at half the step frequency.
    lateral = np.einsum("ni,ni->n", Tc[:, :3, 3] - walk.T_world_path(t)[:, :3, 3], walk.T_world_path(t)[:, :3, 1])
    spec = np.abs(np.fft.rfft((lateral - lateral.mean()) * np.hanning(len(t))))
    assert 0.8 < freqs[np.argmax(spec)] < 1.1
    # Pitch jitter of the camera relative to the rig's nominal pitch: about a degree.
    pitch = np.degrees(np.arcsin(-Tc[:, 2, 2])) - 55.0
    assert 0.2 < pitch.std() < 1.5


def test_gait_scale_scales_the_torso_motion_and_keeps_the_path(long_walk):
    """with_gait_scale(k) keeps the path and the lean and multiplies every gait motion of the torso
    about it by k: bobbing, sway, twist and tilt (their deviations from the path and the lean)."""
    smap, walk = long_walk
    cfg = walk.config
    t = np.arange(0.0, 60.0, 0.01)
    vp = np.array([0.0, 0.0, 1.3])
    still = plan_walk(smap, cfg.with_gait_scale(0.0))

    def torso(w):
        """The vest point's offsets from the path (m, path axes) and the vest's rotation from the
        lean alone (rotation vectors, rad)."""
        from scipy.spatial.transform import Rotation

        T = w.T_body_vest(t)
        lean = still.T_body_vest(t)[:, :3, :3]
        rel = Rotation.from_matrix(np.einsum("nji,njk->nik", lean, T[:, :3, :3])).as_rotvec()
        return T[:, :3, :3] @ vp + T[:, :3, 3] - vp, rel

    double = plan_walk(smap, cfg.with_gait_scale(2.0))
    assert np.allclose(double.planar(t), walk.planar(t)) and np.allclose(double.lean(t), walk.lean(t))
    (p1, r1), (p2, r2) = torso(walk), torso(double)
    p0 = torso(still)[0]
    # Offsets about the lean's own displacement of the vest point: twice as large (small angles).
    assert np.std(p2 - p0, axis=0) == pytest.approx(2.0 * np.std(p1 - p0, axis=0), rel=0.05)
    assert np.std(r2, axis=0) == pytest.approx(2.0 * np.std(r1, axis=0), rel=0.05)
    assert np.allclose(torso(still)[1], 0.0, atol=1e-9)
    with pytest.raises(InputError, match="gait's scale"):
        cfg.with_gait_scale(-1.0)


def test_vest_drifts_in_roll_while_standing(long_walk):
    """Standing people shift their weight sideways: the vest's roll drifts (0.35 deg RMS) with no gait."""
    smap, walk = long_walk
    standing = np.concatenate([np.linspace(a + 0.1, b - 0.1, 50) for a, b in walk.stops if 0 < a and b < 60])
    assert walk.speed(standing).max() < 0.05
    R = walk.T_body_vest(standing)[:, :3, :3]
    roll = np.degrees(np.arctan2(R[:, 2, 1], R[:, 2, 2]))
    assert 0.1 < np.sqrt(np.mean(roll**2)) < 0.8
    still = plan_walk(smap, WalkConfig(seconds=60.0, seed=4, stop_every_s=10.0, roll_drift_deg=0.0, lean=False))
    R0 = still.T_body_vest(standing)[:, :3, :3]
    assert np.allclose(np.arctan2(R0[:, 2, 1], R0[:, 2, 2]), 0.0, atol=1e-9)
    # Drawn from a stream of its own: the path is the same with or without it.
    t = np.linspace(0.0, 60.0, 500)
    assert np.allclose(still.planar(t), walk.planar(t))


def test_torso_rates_have_the_body_inertia(long_walk):
    """The vest's angular velocity is a body's: most of its power below 5 Hz (the gait, the lean and
    the slow drifts), not a white rate that grows with the walk's 10 ms integration step; a standing
    person's tilt drifts at under 1 deg/s."""
    from scipy.signal import welch
    from scipy.spatial.transform import Rotation

    _, walk = long_walk
    fs = 1000.0
    t = np.arange(1.0, 59.0, 1 / fs)
    R = walk.T_body_vest(t)[:, :3, :3]
    w = Rotation.from_matrix(np.einsum("kji,kjl->kil", R[:-1], R[1:])).as_rotvec() * fs  # body axes, rad/s
    for axis in (0, 1):  # roll and pitch rates
        f, psd = welch(w[:, axis] - w[:, axis].mean(), fs=fs, nperseg=4096)
        high = psd[f > 5.0].sum() / psd.sum()
        assert high < 0.15, (axis, high)
    standing = np.concatenate([np.linspace(a + 0.5, b - 0.1, 200) for a, b in walk.stops if 0 < a and b < 59])
    Rs = walk.T_body_vest(standing)[:, :3, :3]
    tilt = np.column_stack([np.arctan2(Rs[:, 2, 1], Rs[:, 2, 2]), -np.arcsin(np.clip(Rs[:, 2, 0], -1, 1))])
    dt = np.diff(standing)
    ok = dt < 0.05  # within one stop
    rate = np.degrees(np.abs(np.diff(tilt, axis=0)[ok]) / dt[ok, None])
    assert np.sqrt(np.mean(rate**2)) < 1.0


# -- floor ----------------------------------------------------------------------------------------


def test_floor_tiles_are_seamless_and_order_independent():
    smap = aisle_map(rows=1, length_m=3.0)
    a = Floor(smap, FloorConfig(distractors_per_m2=2.0), seed=5)
    b = Floor(smap, FloorConfig(distractors_per_m2=2.0), seed=5)
    t10 = a.tile(1, 0)
    b.tile(0, 0)
    assert np.array_equal(b.tile(1, 0), t10)
    assert not np.array_equal(Floor(smap, FloorConfig(distractors_per_m2=2.0), seed=6).tile(1, 0), t10)
    img, A = a.mosaic(0.0, 0.0, 1.999, 0.999)
    # World-anchored: another tiling of the same floor shows the same mottling and features, so
    # nothing jumps at tile borders. Only the grain and pits are drawn per tile.
    cfg = FloorConfig(distractors_per_m2=2.0, grain=0.0)
    one = Floor(smap, cfg, seed=5).mosaic(0.0, 0.0, 1.999, 0.999)[0].astype(float)
    half = Floor(smap, replace(cfg, tile_m=0.5), seed=5).mosaic(0.0, 0.0, 1.999, 0.999)[0].astype(float)
    assert np.percentile(np.abs(one - half), 99) <= 1.0
    assert one.std() > 3.0  # there is texture to compare
    # The texel affine: world (x, y) -> (col, row).
    assert np.allclose(A @ [0.001, 0.001, 1.0], [0.0, 0.0, 1.0])
    assert 0.3 < img.mean() / 255 < 0.5


def test_floor_texture_contrast_scales_the_concrete_only():
    smap = aisle_map(rows=1, length_m=3.0)
    plain = {"distractors_per_m2": 0.0, "stains_per_m2": 0.0, "line_spacing_m": 0.0}
    full = Floor(smap, FloorConfig(**plain), seed=5).tile(1, 0).astype(float)
    assert np.array_equal(Floor(smap, FloorConfig(texture_contrast=1.0, **plain), seed=5).tile(1, 0), full)
    # The texture's spread about the concrete's mean reflectance scales with the factor; the mean
    # stays (a sealed floor is as light as a worn one, only more even).
    for c in (0.5, 0.25):
        tile = Floor(smap, FloorConfig(texture_contrast=c, **plain), seed=5).tile(1, 0).astype(float)
        assert tile.std() / full.std() == pytest.approx(c, rel=0.08)
        assert tile.mean() == pytest.approx(full.mean(), rel=0.02)
    flat = Floor(smap, FloorConfig(texture_contrast=0.0, **plain), seed=5).tile(1, 0)
    assert np.ptp(flat) == 0
    with pytest.raises(InputError, match="texture contrast"):
        FloorConfig(texture_contrast=-0.1)


def test_floor_missing_and_unmapped():
    smap = aisle_map()
    floor = Floor(smap, FloorConfig(missing_fraction=0.25, unmapped=6), seed=1)
    assert len(floor.missing_ids) == round(0.25 * len(smap))
    assert (~floor.in_map).sum() == 6
    assert not set(floor.missing_ids) & set(floor.stickers.ids.tolist())
    assert not set(floor.stickers.ids[~floor.in_map].tolist()) & set(smap.ids.tolist())
    d = np.hypot(*(floor.stickers.xy[:, None] - floor.stickers.xy[None]).transpose(2, 0, 1))
    assert np.min(d + 10 * np.eye(len(d))) > 0.2


def test_floor_refuses_more_unmapped_stickers_than_fit():
    """Around one sticker (0.5 m margin) only some tens of stickers fit 0.3 m apart: asking for 300
    unmapped ones is refused, not answered with a floor holding fewer than asked for."""
    one = StickerMap(np.array([7]), np.zeros((1, 2)), np.zeros(1))
    with pytest.raises(InputError, match=r"room for only \d+ of 300 unmapped"):
        Floor(one, FloorConfig(unmapped=300, margin_m=0.5, texture=False), seed=1)
    floor = Floor(one, FloorConfig(unmapped=3, margin_m=0.5, texture=False), seed=1)
    d = np.hypot(*(floor.stickers.xy[:, None] - floor.stickers.xy[None]).transpose(2, 0, 1))
    assert (~floor.in_map).sum() == 3 and np.min(d + 10 * np.eye(len(d))) > 0.3


# -- views and sessions -----------------------------------------------------------------------------


def test_render_view_ground_truth_corners_on_dark_frame():
    """The true corners (with lens distortion) outline the sticker's black frame in the image."""
    cam = Camera(
        np.array([[643.0, 0, 323.5], [0, 643.0, 242.5], [0, 0, 1]]), np.array([0.10, -0.20, 0, 0, 0]), 648, 486
    )
    smap = StickerMap([11, 12], [[0.0, 0.0], [0.35, 0.25]], [0.3, 1.2])
    floor = Floor(smap, FloorConfig(texture=False))
    T = camera_pose_looking_at((0.1, 0.1), 0.9, 60.0, 20.0)
    img = render_view(floor, cam, T, 200.0, noise=False).image.astype(float)
    for sid in (11, 12):
        c = true_corners(floor, cam, T, sid)
        assert c is not None and np.all((c >= 0) & (c < (cam.width, cam.height)))
        band = np.zeros(img.shape, np.uint8)  # the middle line of the 8 mm black frame
        cv2.polylines(band, [np.round((c[:4] + c[4:]) / 2 * 16).astype(np.int32)], True, 1, 1, cv2.LINE_8, 4)
        ring = np.zeros(img.shape, np.uint8)
        centre = c[:4].mean(axis=0)
        cv2.fillPoly(ring, [np.round((centre + 1.4 * (c[:4] - centre)) * 16).astype(np.int32)], 1, cv2.LINE_8, 4)
        cv2.fillPoly(ring, [np.round((centre + 1.08 * (c[:4] - centre)) * 16).astype(np.int32)], 0, cv2.LINE_8, 4)
        assert img[band > 0].mean() < 0.6 * img[ring > 0].mean()
        # Just inside the inner corners is white paper, brighter than the floor.
        inner = np.zeros(img.shape, np.uint8)
        cv2.fillPoly(inner, [np.round((centre + 0.9 * (c[4:] - centre)) * 16).astype(np.int32)], 1, cv2.LINE_8, 4)
        cv2.fillPoly(inner, [np.round((centre + 0.75 * (c[4:] - centre)) * 16).astype(np.int32)], 0, cv2.LINE_8, 4)
        assert img[inner > 0].mean() > img[ring > 0].mean()


def sim_config(**kw) -> SimConfig:
    base = dict(seconds=1.5, fps=10.0, lux=200.0, seed=3, scale=0.5, jpeg_quality=92)
    base.update(kw)
    return SimConfig(**base)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    smap = aisle_map()
    out = tmp_path_factory.mktemp("sim") / "s1"
    summary = simulate_session(smap, out, sim_config(missing_fraction=0.2, unmapped=10), progress=False)
    return smap, out, summary


def test_session_round_trip(session):
    smap, out, summary = session
    reader = SessionReader(out)
    assert summary.frames == len(reader) == 15
    frames = list(reader.frames())
    assert all(f.image is not None and f.image.shape == (486, 648) for f in frames)
    assert np.allclose(reader.timestamps, np.arange(15) / 10.0)
    stamps, poses = reader.groundtruth()
    assert np.allclose(stamps, reader.timestamps, atol=1e-6)
    assert np.allclose(poses[:, 2, 3], 0.0, atol=1e-6)
    assert reader.camera.width == 648 and reader.camera.fx == pytest.approx(1285.7 / 2, rel=1e-3)
    assert sorted(reader.map.ids.tolist()) == sorted(smap.ids.tolist())
    sim = reader.info.extra["simulation"]
    assert sorted(sim["missing_ids"]) == sorted(summary.missing_ids) and len(sim["unmapped"]) == 10
    recs = read_groundtruth_frames(out)
    assert [r["index"] for r in recs] == list(range(15))
    for r, T in zip(recs, poses):
        assert np.allclose(np.array(r["T_world_body"]), T, atol=1e-5)
        Tc = np.array(r["T_world_camera"])
        assert 1.2 < Tc[2, 3] < 1.4  # rig height plus bobbing
        assert r["exposure_s"] == pytest.approx(0.3 / 200)
        for v in r["visible"]:
            assert v["id"] not in summary.missing_ids
            assert v["in_map"] == (v["id"] in smap)


def test_session_ground_truth_matches_images(session):
    smap, out, _ = session
    checked = 0
    for r in read_groundtruth_frames(out):
        img = cv2.imread(str(out / "frames" / f"{r['index']:06d}.jpg"), cv2.IMREAD_GRAYSCALE).astype(float)
        for v in r["visible"]:
            if not v["inside"] or v["distance_m"] > 1.8:
                continue
            c = np.array(v["corners"])
            centre = c.mean(axis=0)
            pts = (c + np.array(v["inner"])) / 2  # the middle line of the 8 mm black frame
            mask = np.zeros(img.shape, np.uint8)
            cv2.polylines(mask, [np.round(pts * 16).astype(np.int32)], True, 1, 1, cv2.LINE_8, 4)
            ring = np.zeros(img.shape, np.uint8)
            cv2.polylines(
                ring, [np.round((centre + 1.35 * (c - centre)) * 16).astype(np.int32)], True, 1, 2, cv2.LINE_8, 4
            )
            # Measured: 0.35-0.52 on the true corners; 0.5-0.75 with them 1 px off, 0.8-0.97 at 2 px.
            assert img[mask > 0].mean() < 0.62 * img[ring > 0].mean(), (r["index"], v["id"])
            checked += 1
    assert checked >= 3


def test_session_is_deterministic(tmp_path, session):
    smap, out, _ = session
    again = tmp_path / "again"
    simulate_session(smap, again, sim_config(missing_fraction=0.2, unmapped=10), progress=False)
    for k in (0, 7, 14):
        name = f"frames/{k:06d}.jpg"
        assert (again / name).read_bytes() == (out / name).read_bytes()
    assert (again / "groundtruth_frames.jsonl").read_text() == (out / "groundtruth_frames.jsonl").read_text()
    other = tmp_path / "other"
    simulate_session(smap, other, sim_config(missing_fraction=0.2, unmapped=10, seed=4, seconds=0.3), progress=False)
    assert (other / "frames/000000.jpg").read_bytes() != (out / "frames/000000.jpg").read_bytes()
    assert (other / "groundtruth.tum").read_text() != (out / "groundtruth.tum").read_text()[
        : len((other / "groundtruth.tum").read_text())
    ]


def test_rolling_shutter_ground_truth(tmp_path):
    """With a rolling shutter, corners are projected at their rows' times and still sit on the frame."""
    smap = aisle_map(rows=1)
    out = tmp_path / "rs"
    simulate_session(smap, out, sim_config(rolling_shutter=True, seconds=1.0, lux=300.0), progress=False)
    checked = 0
    for r in read_groundtruth_frames(out):
        img = cv2.imread(str(out / "frames" / f"{r['index']:06d}.jpg"), cv2.IMREAD_GRAYSCALE).astype(float)
        for v in r["visible"]:
            if v["inside"] and v["distance_m"] < 1.8:
                c = np.array(v["corners"])
                centre = c.mean(axis=0)
                mask = np.zeros(img.shape, np.uint8)
                mid = (c + np.array(v["inner"])) / 2
                cv2.polylines(mask, [np.round(mid * 16).astype(np.int32)], True, 1, 1, cv2.LINE_8, 4)
                ring = np.zeros(img.shape, np.uint8)
                cv2.polylines(
                    ring, [np.round((centre + 1.35 * (c - centre)) * 16).astype(np.int32)], True, 1, 2, cv2.LINE_8, 4
                )
                assert img[mask > 0].mean() < 0.62 * img[ring > 0].mean()
                checked += 1
    assert checked >= 2


def test_rig_cameras_have_their_own_jitter_and_drops(tmp_path):
    """Free-running cameras have their own drivers and queues: independent jitter and dropped frames;
    camera 0 keeps a single camera's schedule."""
    from tagloc.eval.multicam import front_rear_rig

    timing = TimingConfig(jitter_s=0.002, drop_fraction=0.25)
    out = tmp_path / "two"
    cfg = sim_config(seconds=2.0, fps=15.0, scale=0.25, rig=front_rear_rig(), timing=timing)
    simulate_session(aisle_map(rows=1), out, cfg, progress=False)
    reader = SessionReader(out)  # refuses stamps that do not increase
    recs = read_groundtruth_frames(out)
    assert [r["stamp"] for r in recs] == pytest.approx(list(reader.timestamps), abs=1e-6)
    stagger = 1 / 30.0  # 1 / (2 cameras * 15 fps)
    cams = [{r["index"] // 2: r for r in recs if r["camera"] == c} for c in (0, 1)]
    single = frame_schedule(30, 15.0, timing, 3)  # the schedule of a one-camera session
    assert sorted(cams[0]) == single.index.tolist()
    assert [cams[0][k]["stamp"] for k in sorted(cams[0])] == pytest.approx(single.stamp.tolist(), abs=1e-6)
    # Each camera loses about a quarter of its 30 frames (binomial: 7.5 +- 2.4), and not the same ones.
    lost = [set(range(30)) - set(c) for c in cams]
    assert all(3 <= len(x) <= 13 for x in lost)
    assert len(lost[0] ^ lost[1]) >= 4
    sim = reader.info.extra["simulation"]
    assert sim["dropped_frames_per_camera"] == [len(x) for x in lost]
    assert sim["dropped_frames"] == len(lost[0]) + len(lost[1])
    # Jitter: each camera's stamps within +-2 ms of its true times, and independent between the
    # cameras (the difference of two uniform +-2 ms errors has a standard deviation of 1.63 ms).
    both = sorted(set(cams[0]) & set(cams[1]))
    jit = np.array([[cams[c][k]["stamp"] - cams[c][k]["t"] for c in (0, 1)] for k in both])
    assert np.all(np.abs(jit) <= 0.002 + 1e-6)
    assert np.array([cams[1][k]["t"] - cams[0][k]["t"] for k in both]) == pytest.approx(stagger, abs=1e-6)
    assert np.std(jit[:, 1] - jit[:, 0]) == pytest.approx(0.00163, rel=0.4)


def test_delivered_frames_follow_the_stamps():
    """With jitter of half the stagger or more, two cameras' stamps can swap or meet: frames.csv is in
    stamp order and a stamp that meets the one before it (in microseconds) is put 1 us after it."""
    from tagloc.sim.simulate import _delivered
    from tagloc.sim.timing import FrameSchedule

    stagger = 1 / 60.0
    k = np.array([0, 1])
    cam0 = FrameSchedule(k, k / 30.0, k / 30.0 + 0.009, 0, 0)
    cam1 = FrameSchedule(k, k / 30.0, k / 30.0 + np.array([0.009 - stagger + 2e-7, -0.009]), 0, 0)
    shots = _delivered([cam0, cam1], stagger)
    assert [(s.camera, s.k) for s in shots] == [(0, 0), (1, 0), (1, 1), (0, 1)]
    assert [s.stamp for s in shots] == pytest.approx(
        [0.009, 0.009001, 1 / 30 + stagger - 0.009, 1 / 30 + 0.009], abs=1e-9
    )
    assert [s.t for s in shots] == pytest.approx([0.0, stagger, 1 / 30 + stagger, 1 / 30])


def test_cli_simulate(tmp_path, capsys):
    smap = aisle_map(rows=1)
    save_map(smap, tmp_path / "m.csv")
    rc = main(
        [
            "simulate",
            "--map",
            str(tmp_path / "m.csv"),
            "--seconds",
            "0.2",
            "--fps",
            "10",
            "--scale",
            "0.25",
            "--quiet",
            "--unmapped",
            "2",
            "-o",
            str(tmp_path / "cli"),
        ]
    )
    assert rc == 0
    assert len(list((tmp_path / "cli" / "frames").glob("*.jpg"))) == 2
    assert "2 frames" in capsys.readouterr().out
    rc = main(["simulate", "--map", str(tmp_path / "nope.csv"), "--quiet", "-o", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert rc == 2 and "nope.csv" in err and err.count("\n") == 1
    rc = main(
        [
            "simulate",
            "--map",
            str(tmp_path / "m.csv"),
            "--missing-fraction",
            "1.5",
            "--quiet",
            "-o",
            str(tmp_path / "y"),
        ]
    )
    assert rc == 2 and "--missing-fraction" in capsys.readouterr().err


def test_walker_leans_into_turns_and_with_acceleration(long_walk):
    """Roll atan(v omega / g) into the turn, pitch atan(a / g) with the speed change, through the
    body's pendulum lag sqrt(h_com / g); the ground truth is the vest point, moved by the lean."""
    smap, walk = long_walk
    cfg = walk.config
    assert cfg.lean_tau_s == pytest.approx(math.sqrt(0.95 / 9.81))
    t = np.arange(1.0, 59.0, 0.01)
    v = walk.speed(t)
    omega = np.gradient(walk.planar(t)[:, 2], t)
    accel = np.gradient(v, t)
    roll, pitch = walk.lean(t).T
    roll_demand, pitch_demand = -np.arctan(v * omega / 9.81), np.arctan(accel / 9.81)
    # The lean is the demand through a first-order lag of time constant tau (integrated here by hand).
    tau, dt = cfg.lean_tau_s, 0.01
    expect = np.zeros((len(t), 2))
    expect[0] = roll[0], pitch[0]
    for i in range(1, len(t)):
        expect[i] = expect[i - 1] + (np.array([roll_demand[i], pitch_demand[i]]) - expect[i - 1]) * dt / tau
    assert np.max(np.abs(expect[:, 0] - roll)) < math.radians(0.5)
    assert np.max(np.abs(expect[:, 1] - pitch)) < math.radians(0.5)
    # Into the turn: a left turn (omega > 0) tips the torso's top to the left (roll < 0 about +x).
    turning = np.abs(v * omega) > 1.0
    assert np.all(np.sign(roll[turning]) == -np.sign(omega[turning]))
    assert math.radians(5) < np.max(np.abs(roll)) < math.radians(15)
    # Braking into each stop at 0.8 m/s^2: about atan(0.8 / g) = 4.7 deg backwards at the end.
    assert np.min(pitch) == pytest.approx(-math.atan(cfg.accel_mps2 / 9.81), abs=math.radians(0.3))
    # The lean is in the torso's tilt (about the centre of mass): the vest point 0.35 m above it moves.
    R = walk.T_body_vest(t)[:, :3, :3]
    still = plan_walk(smap, WalkConfig(seconds=60.0, seed=4, stop_every_s=10.0, lean=False))
    assert np.allclose(still.planar(t), walk.planar(t)) and np.allclose(still.lean(t), 0.0)
    R0 = still.T_body_vest(t)[:, :3, :3]
    up, up0 = R[:, :, 2], R0[:, :, 2]
    k = np.argmax(np.abs(roll))
    assert np.degrees(np.arccos(np.clip(up[k] @ up0[k], -1, 1))) == pytest.approx(np.degrees(abs(roll[k])), abs=1.5)
    vest = np.array([0.0, 0.0, 1.3])
    shift = walk.groundtruth(t[k], vest)[:2] - still.groundtruth(t[k], vest)[:2]
    assert np.hypot(*shift) == pytest.approx((1.3 - 0.95) * math.sin(abs(roll[k])), rel=0.3)


def test_session_notes_name_every_condition_that_is_not_the_default():
    """``tagloc eval --walks`` prints a session's notes as its conditions: a field walk's row must say
    it was rendered with a rolling shutter, drops and a surveyed map, and a plain walk's must not."""
    from tagloc.sim.survey import SurveyConfig

    plain = SimConfig(seconds=4, lux=150, seed=3).describe()
    assert plain == "4 s at 150 lux, 1.3 m/s, seed 3"
    field = SimConfig(
        seconds=4,
        seed=3,
        rolling_shutter=True,
        timing=TimingConfig(jitter_s=0.002, drop_fraction=0.04, bursts_per_min=2.0),
        survey=SurveyConfig(0.015, 1.5, True),
        sensor_preset="ov5647",
        pitch_deg=45.0,
        calibration="site/wide.yaml",
    ).describe()
    for part in (
        "camera 1.3 m up, 45 deg down",
        "rolling shutter 30 ms",
        "jitter +-2 ms",
        "drops 4% + 2 bursts/min",
        "survey 1.5 cm 1.5 deg stated",
        "sensor ov5647",
        "lens wide.yaml",
    ):
        assert part in field, (part, field)


def test_cli_simulate_takes_the_gait_scale(tmp_path, capsys):
    """--gait-scale reaches the walk (stated in session.json's simulator settings) and is checked
    against its range before anything is written."""
    import json

    save_map(aisle_map(rows=1), tmp_path / "m.csv")
    args = ["simulate", "--map", str(tmp_path / "m.csv"), "--scale", "0.25", "--seconds", "0.2", "--quiet"]
    assert main(args + ["--gait-scale", "2", "-o", str(tmp_path / "g2")]) == 0
    walk = json.loads((tmp_path / "g2" / "session.json").read_text())["simulation"]["config"]["walk"]
    default = WalkConfig()
    assert walk["bob_m"] == pytest.approx(2 * default.bob_m) and walk["torso_yaw_deg"] == pytest.approx(5.0)
    assert walk["step_hz"] == default.step_hz and walk["lean"] is True
    capsys.readouterr()
    assert main(args + ["--gait-scale", "4", "-o", str(tmp_path / "g4")]) == 2
    err = capsys.readouterr().err
    assert "--gait-scale" in err and err.count("\n") == 1 and not (tmp_path / "g4").exists()


def test_cli_simulate_refuses_a_session_without_a_frame(tmp_path, capsys):
    """0.02 s at 30 fps exposes no frame (frame k at k / fps, k < seconds x fps): a one-line error
    before anything is written, not an internal error over an empty ground truth."""
    save_map(aisle_map(rows=1), tmp_path / "m.csv")
    args = ["simulate", "--map", str(tmp_path / "m.csv"), "--scale", "0.25", "--quiet", "-o", str(tmp_path / "s")]
    rc = main(args + ["--seconds", "0.02"])
    err = capsys.readouterr().err
    assert rc == 2 and "no frame" in err and err.count("\n") == 1
    assert not (tmp_path / "s").exists()
    with pytest.raises(InputError, match="no frame"):
        SimConfig(seconds=0.5, fps=1.0)
    assert SimConfig(seconds=1.0, fps=1.0).frame_count == 1 and SimConfig(seconds=0.2, fps=10.0).frame_count == 2


def test_rolling_shutter_read_out_fits_in_the_frame_interval(tmp_path, capsys):
    """A sensor reads one frame out before the next: a 50 ms read-out at 30 fps (33 ms frames) is
    refused; without a rolling shutter the read-out plays no part, and 30 ms at 30 fps is fine."""
    save_map(aisle_map(rows=1), tmp_path / "m.csv")
    args = ["simulate", "--map", str(tmp_path / "m.csv"), "--scale", "0.25", "--quiet", "-o", str(tmp_path / "s")]
    rc = main(args + ["--seconds", "0.1", "--rolling-shutter", "--readout-ms", "50"])
    err = capsys.readouterr().err
    assert rc == 2 and "read-out 50 ms is longer than the frame interval" in err and err.count("\n") == 1
    assert not (tmp_path / "s").exists()
    with pytest.raises(InputError, match="frame interval"):
        SimConfig(fps=60.0, rolling_shutter=True)
    SimConfig(fps=60.0, rolling_shutter=False)
    SimConfig(fps=30.0, rolling_shutter=True, exposure=ExposureConfig(readout_s=1 / 30))


def test_cli_simulate_does_not_write_over_its_inputs(tmp_path, capsys):
    """-o naming the directory of --map (or --calibration, --rig) would write the session's map.csv
    (with survey error, perturbed) and camera.yaml (scaled) over the files read: refused, untouched."""
    d = tmp_path / "site"
    d.mkdir()
    save_map(aisle_map(rows=1), d / "map.csv")
    before = (d / "map.csv").read_bytes()
    base = ["simulate", "--seconds", "0.1", "--scale", "0.25", "--quiet", "--survey-sigma-cm", "5"]
    rc = main(base + ["--map", str(d / "map.csv"), "-o", str(d)])
    err = capsys.readouterr().err
    assert rc == 2 and "holding the run's inputs" in err and err.count("\n") == 1
    assert (d / "map.csv").read_bytes() == before and not (d / "frames").exists()
    # A calibration beside the output is protected too; a new directory next to the inputs is fine.
    save_calibration(default_camera(), tmp_path / "cam.yaml")
    cal = (tmp_path / "cam.yaml").read_bytes()
    rc = main(base + ["--map", str(d / "map.csv"), "--calibration", str(tmp_path / "cam.yaml"), "-o", str(tmp_path)])
    assert rc == 2 and "holding the run's inputs" in capsys.readouterr().err
    assert (tmp_path / "cam.yaml").read_bytes() == cal
    assert main(base + ["--map", str(d / "map.csv"), "-o", str(d / "s1")]) == 0
    assert (d / "map.csv").read_bytes() == before
