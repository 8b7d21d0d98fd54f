"""tagloc rig fit: the camera mount from a walk (simulated walks with a rig perturbed by known amounts)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tagloc.cli import main
from tagloc.core.camera import default_camera
from tagloc.core.errors import InputError
from tagloc.core.geometry import invert, make_T
from tagloc.core.rig import Rig, RigCamera, default_rig, load_rig, looking_forward, save_rig
from tagloc.core.stickermap import load_map
from tagloc.eval.rigfit import CameraFix, RigFitConfig, fit_rig_fixes, mount_angles, mount_T
from tagloc.sim.simulate import SimConfig, simulate_session
from tagloc.sim.walk import WalkConfig, plan_walk

MAP = Path(__file__).resolve().parents[1] / "maps" / "demo.csv"
TRUE = dict(height_m=1.22, pitch_deg=58.0, roll_deg=2.0, yaw_deg=3.0)
# Per-fix noise of solve_pose's camera pose on full-resolution simulated frames, measured against
# the simulator's true camera poses (20 s walk, seed 1): height 4 mm, angles 0.2-0.45 degree RMS.
FIX_HEIGHT_SIGMA_M = 0.004
FIX_ANGLE_SIGMA_DEG = 0.4


def test_mount_parameterisation():
    T = mount_T(1.22, 58.0, 2.0, 3.0, 0.1, -0.05)
    assert mount_angles(T) == pytest.approx((1.22, 58.0, 2.0, 3.0))
    assert T[:2, 3] == pytest.approx([0.1, -0.05])
    assert mount_T(1.3, 55.0, 0.0, 7.0) == pytest.approx(looking_forward(1.3, 55.0, 7.0))
    # Positive roll turns the image clockwise as the camera sees it: the camera's x axis dips down.
    assert mount_T(1.3, 0.0, 10.0)[2, 0] < 0


def walk_fixes(seed: int, seconds: float, T_body_camera: np.ndarray, fps: float = 15.0) -> list[CameraFix]:
    """Camera poses of the simulator's walk (gait and vest motion included) at frames where a mapped
    sticker's centre is in the image, with solve_pose's measured noise added."""
    smap = load_map(MAP)
    cam = default_camera()
    walk = plan_walk(smap, WalkConfig(seconds=seconds, seed=seed))
    ts = np.arange(0.0, seconds, 1.0 / fps)
    rng = np.random.default_rng(seed)
    pts = np.c_[smap.xy, np.zeros(len(smap)), np.ones(len(smap))]
    out = []
    for t, T in zip(ts, walk.T_world_camera(ts, T_body_camera)):
        pc = (invert(T) @ pts.T).T[:, :3]
        ahead = np.flatnonzero(pc[:, 2] > 0.2)
        if not len(ahead):
            continue
        uv = cam.project(pc[ahead])
        inside = ahead[(uv[:, 0] > 20) & (uv[:, 0] < cam.width - 20) & (uv[:, 1] > 20) & (uv[:, 1] < cam.height - 20)]
        if not len(inside):
            continue
        noisy = T.copy()
        rot = Rotation.from_rotvec(rng.normal(0.0, np.radians(FIX_ANGLE_SIGMA_DEG), 3)).as_matrix()
        noisy[:3, :3] = rot @ T[:3, :3]
        noisy[:3, 3] += rng.normal(0.0, FIX_HEIGHT_SIGMA_M, 3)
        out.append(CameraFix(float(t), int(smap.ids[inside[0]]), noisy))
    return out


@pytest.mark.parametrize("seed", [1, 4])
def test_recovers_a_perturbed_rig_from_a_minute_of_walking(seed):
    fixes = walk_fixes(seed, 60.0, mount_T(**TRUE))
    fit = fit_rig_fixes(fixes, looking_forward(1.3, 55.0))
    assert fit.height_m.value == pytest.approx(TRUE["height_m"], abs=0.01)
    assert fit.pitch_deg.value == pytest.approx(TRUE["pitch_deg"], abs=0.5)
    assert fit.roll_deg.value == pytest.approx(TRUE["roll_deg"], abs=0.5)
    assert fit.yaw_deg.value == pytest.approx(TRUE["yaw_deg"], abs=0.5)
    assert fit.stretches and fit.warnings == []
    # The stated sigmas are honest: the errors are within 3 of them and the sigmas are small.
    for name in ("pitch_deg", "roll_deg", "yaw_deg"):
        est = getattr(fit, name)
        assert abs(est.value - TRUE[name]) < 3 * est.sigma and est.sigma < 1.0
    assert mount_angles(fit.T_body_camera) == pytest.approx(
        (fit.height_m.value, fit.pitch_deg.value, fit.roll_deg.value, fit.yaw_deg.value)
    )


def test_warns_when_the_walk_constrains_little():
    fixes = walk_fixes(1, 60.0, mount_T(**TRUE))
    few = [f for f in fixes if f.t < 1.0]  # about 1.3 m of walking
    prior = looking_forward(1.3, 55.0, 5.0)
    fit = fit_rig_fixes(few, prior)
    text = " ".join(fit.warnings)
    assert "sticker passes" in text and "yaw not constrained" in text
    assert fit.yaw_deg.value == pytest.approx(5.0) and fit.yaw_deg.sigma == np.inf
    # Fixes standing still on one spot: no walking direction at all.
    still = [CameraFix(0.1 * k, 7, mount_T(**TRUE)) for k in range(30)]
    assert "no straight stretch" in " ".join(fit_rig_fixes(still, prior).warnings)
    with pytest.raises(InputError, match="no decoded sticker"):
        fit_rig_fixes([], prior)


def test_no_fallback_warning_when_every_fix_is_on_a_straight_stretch():
    """Every fix on a straight stretch is the best case, not the fallback to all fixes: no warning.
    Standing still (no stretch) does take the fallback and says so."""
    true = mount_T(1.21, 48.0, 3.0, -4.0)
    fixes, t = [], 0.0
    for leg in range(4):  # four 8 m legs up and down an aisle, 15 fixes/s, a 2 s turn between them
        sign = 1.0 if leg % 2 == 0 else -1.0
        R = np.diag([sign, sign, 1.0])
        for k in range(90):
            x = (0.0 if sign > 0 else 8.0) + sign * 1.33 * k / 15.0
            fixes.append(CameraFix(t, k // 8 + 100 * leg, make_T(R, (x, 2.0, 0.0)) @ true))
            t += 1 / 15.0
        t += 2.0
    fit = fit_rig_fixes(fixes, looking_forward(1.3, 55.0))
    assert len(fit.stretches) == 4 and all(any(a <= f.t <= b for a, b, *_ in fit.stretches) for f in fixes)
    assert fit.warnings == []
    assert fit.height_m.value == pytest.approx(1.21, abs=1e-6)
    still = [CameraFix(0.1 * k, k // 5, true) for k in range(100)]
    assert any("from all fixes" in w for w in fit_rig_fixes(still, looking_forward(1.3, 55.0)).warnings)


def test_cli_on_a_rendered_walk(tmp_path, capsys):
    rig_path = tmp_path / "true" / "rig.json"
    rig_path.parent.mkdir()
    save_rig(Rig([RigCamera("front", default_camera(), mount_T(**TRUE))]), rig_path)
    session = tmp_path / "walk"
    cfg = SimConfig(seconds=4.0, fps=10.0, seed=1, scale=0.5, rig=rig_path, walk=WalkConfig(stop_every_s=0.0))
    simulate_session(MAP, session, cfg, progress=False)
    nominal = tmp_path / "nominal" / "rig.json"
    nominal.parent.mkdir()
    save_rig(default_rig(), nominal)
    out = tmp_path / "fitted" / "rig.json"
    out.parent.mkdir()
    assert main(["rig", "fit", str(session), "-o", str(out), "--rig", str(nominal), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "height" in printed and "warning:" in printed  # four seconds do not constrain everything
    doc = json.loads(out.read_text())
    assert doc["fit"]["fixes"] >= 3 and doc["fit"]["warnings"]
    fitted = load_rig(out)  # the calibration was written next to it
    h, pitch, _, _ = mount_angles(fitted[0].T_body_camera)
    # Eight fixes of a short half-resolution walk whose torso leans as it starts and turns: the fit
    # must say how unsure it is (warnings, sigmas), and the truth must lie within 3 stated sigmas,
    # which stay small enough (2 cm, 3 degrees) for the fit to be of use.
    fit = doc["fit"]
    sh, sp = fit["height_m"]["sigma"], fit["pitch_deg"]["sigma"]
    assert 0 < sh < 0.02 and 0 < sp < 3.0
    assert abs(h - TRUE["height_m"]) < 3 * sh and abs(pitch - TRUE["pitch_deg"]) < 3 * sp
    assert main(["rig", "show", str(out)]) == 0
    assert "front" in capsys.readouterr().out
    assert main(["rig", "fit", str(tmp_path / "none"), "-o", str(out)]) == 2


def test_config_defaults_are_sane():
    cfg = RigFitConfig()
    assert cfg.min_straight_m > 0 and cfg.heading_tol_deg > 2.5  # wider than the torso's swing


def test_rolling_shutter_fixes_are_corrected(tmp_path):
    from dataclasses import replace

    from tagloc.eval.rigfit import camera_fixes
    from tagloc.io.session import SessionReader
    from tagloc.sim.simulate import simulate_walk

    rig_path = tmp_path / "true" / "rig.json"
    rig_path.parent.mkdir()
    save_rig(Rig([RigCamera("front", default_camera(), mount_T(**TRUE))]), rig_path)
    cfg = SimConfig(
        seconds=3.0, fps=10.0, seed=1, scale=0.5, rig=rig_path, rolling_shutter=True, walk=WalkConfig(stop_every_s=0.0)
    )
    simulate_session(MAP, tmp_path / "rs", cfg, progress=False)
    session = SessionReader(tmp_path / "rs")
    # A rolling-shutter fix holds when its sticker's rows were read, not at its frame's time.
    walk, T_body_camera = simulate_walk(load_map(MAP), cfg), cfg.build_rig()[0].T_body_camera
    rc = session.rig[0]
    assert rc.readout_s > 0

    def pitch_bias(rig_camera) -> float:
        fixes = camera_fixes(session, rig_camera, RigFitConfig(), progress=False)
        assert len(fixes) >= 5
        return float(
            np.mean(
                [
                    mount_angles(f.T_world_camera)[1] - mount_angles(walk.T_world_camera(f.t, T_body_camera))[1]
                    for f in fixes
                ]
            )
        )

    raw, corrected = pitch_bias(replace(rc, readout_s=0.0)), pitch_bias(rc)
    # Walking forward under a top-to-bottom read-out tilts the solved camera by degrees; corrected, far less.
    assert abs(raw) > 1.0 and abs(corrected) < 0.4 * abs(raw)


def test_output_naming_an_input_is_refused_before_reading(tmp_path, capsys):
    """``-o`` naming the session's own rig.json (the rig its frames were recorded with) or the
    prior ``--rig`` wrote the fit over it. Refused in one line before any frame is read; the file is
    as it was."""
    session = tmp_path / "walk"
    session.mkdir()
    prior = tmp_path / "prior.json"
    for p in (session / "rig.json", prior):
        save_rig(default_rig(), p)
    before = {p: p.read_bytes() for p in (session / "rig.json", prior)}
    for out, extra in ((session / "rig.json", []), (prior, ["--rig", str(prior)]), (session / "frames" / "r.json", [])):
        assert main(["rig", "fit", str(session), "-o", str(out), *extra, "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert err == f"tagloc rig: error: {out}: -o names one of the inputs it would overwrite\n"
    assert {p: p.read_bytes() for p in before} == before
