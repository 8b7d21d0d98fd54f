"""The localiser end to end on small simulated walks: accuracy, baselines, wrong-ID safety, eval, demo, CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from tagloc.cli import main
from tagloc.core.types import Frame, IdSource, TrackState
from tagloc.eval.baselines import make_localiser
from tagloc.eval.evaluate import EvalConfig, evaluate, wrong_id_fixes
from tagloc.eval.metrics import trajectory_metrics
from tagloc.io.session import SessionReader
from tagloc.pipeline.localiser import Localiser, LocaliserConfig, load_setup
from tagloc.pipeline.run import run_session
from tagloc.sim.mapgen import GridMapConfig, grid_map
from tagloc.sim.simulate import SimConfig, simulate_session


@pytest.fixture(scope="module")
def walk(tmp_path_factory) -> Path:
    """A 6 s walk at 150 lux on a small warehouse map, with unmapped stickers and missing ones."""
    path = tmp_path_factory.mktemp("loc") / "walk"
    smap = grid_map(GridMapConfig(width_m=12, depth_m=10, spacing_min_m=1.2, spacing_max_m=1.6, seed=5))
    simulate_session(
        smap,
        path,
        SimConfig(seconds=6, lux=150, speed_mps=1.2, seed=11, unmapped=15, missing_fraction=0.1),
        progress=False,
    )
    return path


def exact_map_config() -> LocaliserConfig:
    """The default localiser told that the walk's map is exact (the simulator surveys it without
    error): with the default survey sigmas assumed instead, its stated uncertainty would be far
    wider than its errors by design, and the NEES check below would say little."""
    import dataclasses

    cfg = LocaliserConfig()
    return dataclasses.replace(cfg, pose=dataclasses.replace(cfg.pose, map_sigma_m=0.0, map_sigma_yaw=0.0))


@pytest.fixture(scope="module")
def full_log(walk):
    """tagloc's localiser over the walk, run once for the tests that read it."""
    return run_session(SessionReader(walk), exact_map_config())


def test_full_localiser_is_accurate_and_takes_no_wrong_id(walk, full_log):
    session = SessionReader(walk)
    log = full_log
    m = trajectory_metrics(log.stamps[log.valid], log.poses[log.valid], log.covs[log.valid], *session.groundtruth())
    assert log.valid.mean() > 0.7
    assert m["rmse_m"] < 0.10
    assert m["heading_rmse_deg"] < 4.0
    assert 0.1 < m["nees_mean"] < 8.0  # honest order of magnitude; eval measures it properly
    wrong, checked = wrong_id_fixes(walk, log)
    assert checked >= 10 and wrong == 0
    assert np.all(np.isfinite(log.poses)) and np.all(np.isfinite(log.covs))
    assert np.all(np.linalg.eigvalsh(log.covs) > 0)


def test_unmapped_stickers_are_read_but_never_fixes(walk, full_log):
    info = json.loads((walk / "session.json").read_text())
    unmapped = {int(u["id"]) for u in info["simulation"]["unmapped"]}
    session = SessionReader(walk)
    assert full_log.counts["unmapped_reads"] > 0
    assert not unmapped & {f["id"] for f in full_log.fixes}
    assert not unmapped & set(map(int, session.map.ids))


def test_baselines_run_on_the_same_frames(walk):
    session = SessionReader(walk)
    dec = run_session(session, localiser=make_localiser("decoded-only", session.map, session.rig))
    assert dec.fixes and all(f["source"] == "decoded" for f in dec.fixes)
    assert wrong_id_fixes(walk, dec)[0] == 0
    # Without a filter, the pose is held between fixes: its stated covariance is the last fix's.
    assert len(dec.stamps) == len(SessionReader(walk))


def test_bad_mode_is_refused(walk):
    from tagloc.core.errors import InputError

    with pytest.raises(InputError, match="mode"):
        session = SessionReader(walk)
        make_localiser("nonsense", session.map, session.rig)


def test_load_setup_from_a_session_directory(walk):
    smap, rig = load_setup(config_dir=walk)
    assert len(smap) > 10 and rig[0].camera.width == 1296


def test_eval_writes_report_and_plots(tmp_path, monkeypatch):
    threads_before = cv2.getNumThreads()
    res = evaluate(EvalConfig(sessions=1, seconds=3, out=tmp_path, modes=("full", "decoded-only"), progress=False))
    assert (tmp_path / "report.md").exists() and (tmp_path / "s00.png").exists()
    assert {r["mode"] for r in res["rows"]} == {"full", "decoded-only"}
    assert res["summary"]["full"]["wrong_id_fixes"] == 0
    assert res["summary"]["full"]["rmse_m"] < 0.3
    # Frames binned by time since the last fix: every scored frame lands in one bin, and the
    # pooled sums give back the session's RMSE.
    full = next(r for r in res["rows"] if r["mode"] == "full")
    bins = np.array(full["by_time_since_fix"])
    assert bins[:, 0].sum() == full["frames"] and bins[0, 0] > 0
    assert np.sqrt(bins[:, 1].sum() / bins[:, 0].sum()) == pytest.approx(full["rmse_m"], rel=1e-9)
    assert "since last fix" in (tmp_path / "report.md").read_text()
    # The NEES blocks pool back to the session's mean, and are worth no more samples than frames.
    blocks = np.array(full["nees_blocks"])
    assert blocks[:, 0].sum() == full["frames"]
    assert blocks[:, 1].sum() / full["frames"] == pytest.approx(full["nees_mean"], rel=1e-9)
    s_full = res["summary"]["full"]
    assert 1 <= s_full["nees_effective_samples"] <= full["frames"]
    # A 3 s walk is one 5 s block: too short for the effective bounds (the frames' own are printed).
    assert len(blocks) == 1 and s_full["nees_verdict"] == "too short"
    assert np.isnan(s_full["nees_bounds_95_effective"]).all() and np.isfinite(s_full["nees_bounds_95"]).all()
    assert "too short to say how many independent samples" in (tmp_path / "report.md").read_text()
    # Timed with OpenCV on one thread, and the caller's setting is given back.
    assert cv2.getNumThreads() == threads_before
    # Cached sessions are reused, and remade once the simulated physics change.
    import tagloc.sim.simulate
    from tagloc.eval.evaluate import make_session, scenarios

    sc = scenarios(EvalConfig(sessions=1, seconds=3))[0]
    frames = tmp_path / "sessions" / sc.name / "frames.csv"
    made = frames.stat().st_mtime_ns
    assert make_session(sc, tmp_path, False) and frames.stat().st_mtime_ns == made
    monkeypatch.setattr(tagloc.sim.simulate, "SIM_REVISION", tagloc.sim.simulate.SIM_REVISION + 1)
    make_session(sc, tmp_path, False)
    assert frames.stat().st_mtime_ns != made


def test_cli_errors_are_one_line(tmp_path, capsys):
    assert main(["replay", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope" in err[0]
    bad = tmp_path / "bad.csv"
    bad.write_text("id,x_m,y_m,yaw_deg\n1,0,0,0\n2,nan,0,0\n")
    assert main(["refs", "build", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.csv:3" in err[0]


def test_demo_runs_without_arguments_beyond_output(tmp_path):
    out = tmp_path / "demo"
    r = subprocess.run(
        [sys.executable, "-m", "tagloc", "demo", "--seconds", "2", "--quiet", "-o", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    assert "rerun " in r.stdout and (out / "demo.rrd").exists() and (out / "estimate.tum").exists()
    assert "RMSE" in r.stdout


def _first_tracked(loc, session):
    """Feed ``loc`` the session's frames until it has a pose; that frame and its result."""
    for frame in session.frames():
        res = loc.process(frame)
        if res.output.state is TrackState.TRACKING:
            return frame, res
    raise AssertionError("no pose in the whole session")


def test_one_frame_stages_observations_and_times(walk):
    session = SessionReader(walk)
    loc = Localiser(session.map, session.rig, map_path=walk / "map.csv")
    frame, res = _first_tracked(loc, session)
    assert res.frame is frame  # handed on, so a viewer need not read the image again
    fixed = [o for o in res.observations if o.accepted]
    assert fixed and all(o.identity.source is IdSource.DECODED and o.fix.poses for o in fixed)
    assert all(o.fix is None for o in res.observations if o.identity is None)
    assert {"predict", "odometry", "detect", "decode", "pose", "update", "output", "total"} <= set(res.times_ms)
    assert "identify" not in res.times_ms  # nothing was left to identify on the first fix


def test_baseline_holds_its_last_fix_over_an_unreadable_frame(walk):
    session = SessionReader(walk)
    loc = make_localiser("decoded-only", session.map, session.rig)
    frame, res = _first_tracked(loc, session)
    bad = loc.process(Frame(frame.index + 1, frame.timestamp + 0.1, None, error="corrupt"))
    assert bad.skipped == "corrupt" and bad.output.state is TrackState.TRACKING
    assert np.array_equal(bad.output.pose, res.output.pose)
    assert bad.output.since_fix == pytest.approx(0.1)
    assert loc.stats()["skipped"] == 1 and not any(k.startswith("tracker_") for k in loc.stats())


def test_region_search_between_whole_image_searches_keeps_the_track(walk, full_log):
    """Searching only round expected stickers two frames in three (the default) fixes the same
    stickers as searching every whole frame on this walk, and does search regions (in a quarter of its
    frames: at 150 lux the prior's 3 sigma often makes the regions too wide to be worth cutting out)."""
    import dataclasses

    cfg = exact_map_config()
    every = dataclasses.replace(cfg, tracking=dataclasses.replace(cfg.tracking, search_every=1))
    base = run_session(SessionReader(walk), every)
    assert full_log.counts["region_searches"] > 0.2 * len(full_log.stamps)
    assert base.counts["region_searches"] == 0
    np.testing.assert_allclose(full_log.poses[full_log.valid], base.poses[base.valid], atol=1e-9)


def test_shape_match_finds_the_corner_shift_and_the_motion():
    """A quad's corners relabelled (cyclic shift) and moved: the shift that lines them up, how far
    the centre moved, and no shape change; a distorted corner shows as the change."""
    from tagloc.pipeline.localiser import _shape_match, _shortest_side

    rng = np.random.default_rng(5)
    for _ in range(50):
        quad = np.array([[0.0, 0.0], [40.0, 0.0], [40.0, 30.0], [0.0, 30.0]]) + rng.uniform(0, 500, 2)
        sh = int(rng.integers(4))
        move = rng.normal(0, 5, 2)
        prev = np.roll(quad, -sh, axis=0) + move  # prev[j] = quad[(j + sh) % 4] moved
        shift, moved, change = _shape_match(quad, prev)
        assert shift == sh and moved == pytest.approx(np.hypot(*move)) and change < 1e-9
        assert _shortest_side(quad) == pytest.approx(30.0)
        bent = prev.copy()
        bent[0] += (3.0, 4.0)
        assert _shape_match(quad, bent)[2] == pytest.approx(5.0 * 3 / 4, rel=1e-6)


def test_a_rolling_shutter_fix_says_when_it_holds(tmp_path):
    """On a rolling-shutter camera a sticker is solved for the time its rows were read, and the fix
    in the frame's result says so (``Fix.row_time_s``: its corners' mean row's delay), as the
    tracker fuses it; fix_error.py compares each fix with the truth at that time."""
    from tagloc.core.rig import row_delay_s

    path = tmp_path / "rs"
    smap = grid_map(GridMapConfig(width_m=6, depth_m=6, spacing_min_m=1.2, spacing_max_m=1.6, seed=5))
    simulate_session(smap, path, SimConfig(seconds=1.5, lux=200, seed=3, rolling_shutter=True), progress=False)
    session = SessionReader(path)
    rc = session.rig.cameras[0]
    assert rc.readout_s > 0
    loc = Localiser(session.map, session.rig, LocaliserConfig(), map_path=session.map_path)
    row_times = []
    for frame in session.frames():
        for obs in loc.process(frame).observations:
            if obs.fix is not None and obs.fix.poses:
                rows = np.asarray(obs.detection.points, float)[:, 1]
                want = float(np.mean(row_delay_s(rows, rc.camera.height, rc.readout_s)))
                assert obs.fix.row_time_s == pytest.approx(want, abs=1e-12)
                row_times.append(obs.fix.row_time_s)
    assert row_times and max(abs(t) for t in row_times) > 1e-3  # a sticker away from the middle row


def _replayed_rmse(session: SessionReader, frames: list[Frame]) -> tuple[float, Localiser, list]:
    """RMSE (m) over the tracked frames of ``frames`` run through a fresh default localiser."""
    loc = Localiser(session.map, session.rig, exact_map_config())
    results = [loc.process(f) for f in frames]
    kept = [r for r in results if r.skipped is None and r.output.state is TrackState.TRACKING]
    m = trajectory_metrics(
        np.array([r.timestamp for r in kept]),
        np.array([r.output.pose for r in kept]),
        np.array([r.output.cov for r in kept]),
        *session.groundtruth(),
    )
    return m["rmse_m"], loc, results


def test_a_repeated_image_is_refused_as_a_dropped_frame(walk):
    """A driver re-delivering its last buffer with a new stamp: measured as a step, the copy says
    the camera stood still (one in five frames repeated took a 4 s walk from 2.3 to 8.3 cm RMSE).
    It is refused, named and counted, and the walk scores as with those frames dropped."""
    session = SessionReader(walk)
    frames = list(session.frames())
    repeated = [
        Frame(f.index, f.timestamp, frames[k - 1].image.copy()) if k % 5 == 4 else f for k, f in enumerate(frames)
    ]
    dropped = [f for k, f in enumerate(frames) if k % 5 != 4]
    rmse_rep, loc, results = _replayed_rmse(session, repeated)
    rmse_drop, _, _ = _replayed_rmse(session, dropped)
    n = sum(k % 5 == 4 for k in range(len(frames)))
    assert loc.counts["repeated_frames"] == n
    assert results[4].skipped.startswith(f"frame {frames[4].index}: the same image as camera 0's frame")
    assert abs(rmse_rep - rmse_drop) < 0.002, (rmse_rep, rmse_drop)


def test_one_array_filled_in_place_is_refused_not_measured(walk):
    """The odometry keeps the previous frame's array: a caller that fills one array in place for
    every frame would compare each frame with itself. The second hand-over is refused, with why."""
    session = SessionReader(walk)
    frames = list(session.frames())[:3]
    loc = Localiser(session.map, session.rig)
    buf = np.empty_like(frames[0].image)
    out = []
    for f in frames:
        buf[:] = f.image
        out.append(loc.process(Frame(f.index, f.timestamp, buf)))
    assert out[0].skipped is None
    assert all("each frame needs its own" in r.skipped for r in out[1:])


def test_a_frozen_camera_ends_as_a_lost_track_not_a_stale_confident_pose(walk):
    """A driver that keeps re-delivering one buffer: each repeat is skipped as a lost frame, so the
    pose published for it is carried to its time, its uncertainty grows and the track ends lost,
    as with unreadable frames (a refusal would have published the last pose, confident, forever)."""
    session = SessionReader(walk)
    frames = list(session.frames())[:60]
    loc = Localiser(session.map, session.rig, exact_map_config())
    for f in frames:
        loc.process(f)
    last = frames[-1]
    out = [loc.process(Frame(last.index + k, last.timestamp + k / 30, last.image.copy())).output for k in range(1, 301)]
    assert [o.t for o in out] == pytest.approx([last.timestamp + k / 30 for k in range(1, 301)])
    sigma = np.array([np.sqrt(np.trace(o.cov[:2, :2])) for o in out])
    assert np.all(np.diff(sigma) >= 0) and sigma[-1] > 10 * sigma[0]
    assert out[-1].state is TrackState.LOST


def test_region_search_reach_and_corner_memory_come_from_the_config():
    """A predicted sticker's search region reaches ``TrackingConfig.search_sticker_reach`` sticker
    sides (0.75) beyond its centre at its depth; the rolling-shutter corner sights of stickers not
    seen for ``LocaliserConfig.rs_corner_forget_s`` (1 s) are dropped once 64 stickers' are kept."""
    import dataclasses

    from tagloc.core.rig import default_rig
    from tagloc.core.sticker import SIZE_M
    from tagloc.core.stickermap import StickerMap
    from tagloc.core.types import Detection, Identity, PoseFix
    from tagloc.pipeline.localiser import TrackingConfig
    from tracker.candidates import project_map

    assert TrackingConfig().search_sticker_reach == 0.75 and LocaliserConfig().rs_corner_forget_s == 1.0
    rig = default_rig()
    smap = StickerMap(np.array([1, 2]), np.array([[1.2, 0.0], [30.0, 30.0]]), np.zeros(2))
    widths = {}
    for reach in (0.75, 3.0):
        loc = Localiser(smap, rig, LocaliserConfig(tracking=TrackingConfig(search_sticker_reach=reach)))
        loc.tracker.predict(0.0)
        fix = PoseFix(np.eye(4), np.zeros(3), np.diag([1e-6, 1e-6, 1e-6]), 0.1)
        assert loc.tracker.update([fix], 1, IdSource.DECODED, 0.0).accepted
        loc.tracker.predict(1 / 30)
        loc._searched[0] = (0.0, [], 0, False)
        boxes, _, crowded = loc._search_plan(0, rig[0], 1 / 30)
        assert not crowded and len(boxes) == 1
        widths[reach] = boxes[0][2] - boxes[0][0]
    depth = project_map(loc.tracker.prior()[0], smap, rig[0]).depth[0]
    assert widths[3.0] - widths[0.75] == pytest.approx(2 * 2.25 * SIZE_M * rig[0].camera.fx / depth, abs=2)

    rs = dataclasses.replace(rig[0], readout_s=0.03)
    square = np.array([[600.0, 400.0], [700.0, 400.0], [700.0, 500.0], [600.0, 500.0]])
    for forget_s, kept in ((1.0, 1), (5.0, 65)):
        loc = Localiser(smap, type(rig)([rs]), LocaliserConfig(rs_corner_forget_s=forget_s))
        for k in range(65):  # 64 stickers seen at 0-0.64 s, the 65th at 2 s
            t = 2.0 if k == 64 else 0.01 * k
            loc._corner_velocity(Detection(square), Identity(k, 0, IdSource.DECODED), rs, 0, t)
        assert len(loc._sticker_corners) == kept
