"""Trajectory metrics, and `tagloc replay` on a small synthetic session (determinism, GT metrics, .rrd)."""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest_io import line_map, make_session, truth_xy

from tagloc.core.errors import SessionError
from tagloc.core.geometry import planar_T
from tagloc.eval.metrics import interpolate_groundtruth, trajectory_metrics
from tagloc.io.session import read_tum

FPS = 10.0
N = 20


def straight_gt(n: int = 11, yaw_rate: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(n) / 10.0
    return t, np.stack([planar_T(ti, 0.0, yaw_rate * ti) for ti in t])


def test_metrics_of_a_constant_offset():
    gt_t, gt_T = straight_gt()
    t = np.arange(10) / 10.0 + 0.05  # between GT samples: needs interpolation
    est = np.c_[t + 0.03, np.full_like(t, 0.04), np.full_like(t, math.radians(2.0))]
    cov = np.repeat(np.diag([0.0025, 0.0025, 1e-3])[None], len(t), axis=0)
    m = trajectory_metrics(t, est, cov, gt_t, gt_T)
    assert m["frames"] == 10 and m["outside_gt"] == 0
    for k in ("rmse_m", "median_m", "p95_m", "max_m"):
        assert m[k] == pytest.approx(0.05, abs=1e-9)
    assert m["heading_rmse_deg"] == pytest.approx(2.0, abs=1e-6)
    assert m["within_10cm"] == 1.0 and m["within_25cm"] == 1.0
    assert m["nees_mean"] == pytest.approx(1.0)  # (0.03^2 + 0.04^2) / 0.0025


def test_metrics_against_numpy_on_random_errors():
    rng = np.random.default_rng(7)
    gt_t, gt_T = straight_gt(101, yaw_rate=0.5)
    t = np.sort(rng.uniform(0.0, 10.0, 200))
    truth = np.c_[t, np.zeros_like(t), 0.5 * t]
    err = rng.normal(0.0, 0.08, (200, 2))
    dyaw = rng.normal(0.0, 0.05, 200)
    est = truth + np.c_[err, dyaw]
    sig = rng.uniform(0.03, 0.1, 200)
    cov = np.stack([np.diag([s**2, (2 * s) ** 2, 0.01]) for s in sig])
    m = trajectory_metrics(t, est, cov, gt_t, gt_T)
    d = np.hypot(err[:, 0], err[:, 1])
    assert m["rmse_m"] == pytest.approx(np.sqrt(np.mean(d**2)), rel=1e-9)
    assert m["median_m"] == pytest.approx(np.median(d), rel=1e-9)
    assert m["p95_m"] == pytest.approx(np.percentile(d, 95), rel=1e-9)
    assert m["max_m"] == pytest.approx(d.max(), rel=1e-9)
    assert m["heading_rmse_deg"] == pytest.approx(np.degrees(np.sqrt(np.mean(dyaw**2))), rel=1e-6)
    assert m["within_10cm"] == pytest.approx(np.mean(d <= 0.1)) and m["within_25cm"] == pytest.approx(
        np.mean(d <= 0.25)
    )
    nees = err[:, 0] ** 2 / sig**2 + err[:, 1] ** 2 / (2 * sig) ** 2
    assert m["nees_mean"] == pytest.approx(nees.mean(), rel=1e-9)
    assert m["beyond_999"] == pytest.approx(np.mean(nees > 13.8155), abs=1e-12)


def test_frames_stated_surer_than_they_were_are_counted_beyond_chi_squares_999_point():
    """The mean NEES over a walk can be fine while a stretch of it is stated far too sure: each
    frame's NEES is also held against chi-square's 99.9 % point for 2 DoF (13.8), which a
    consistent filter's exceeds on 0.1 % of its frames."""
    from tagloc.eval.metrics import NEES_999_2DOF

    assert NEES_999_2DOF == pytest.approx(13.8155, abs=1e-4)
    rng = np.random.default_rng(3)
    gt_t, gt_T = straight_gt(201)
    t = np.arange(20000) * 0.001
    truth = np.c_[t, np.zeros_like(t), np.zeros_like(t)]
    sd = 0.02
    err = rng.normal(0.0, sd, (len(t), 2))
    cov = np.repeat(np.diag([sd**2, sd**2, 1e-4])[None], len(t), axis=0)
    honest = trajectory_metrics(t, truth + np.c_[err, np.zeros_like(t)], cov, gt_t, gt_T)
    assert honest["beyond_999"] == pytest.approx(0.001, abs=0.0008)
    # A tenth of the walk stated five times too sure (its errors as before): beyond on most of it.
    surer = cov.copy()
    surer[:2000, :2, :2] /= 25.0
    m = trajectory_metrics(t, truth + np.c_[err, np.zeros_like(t)], surer, gt_t, gt_T)
    assert 0.05 < m["beyond_999"] < 0.1


def test_heading_interpolation_wraps_around_pi():
    t = np.array([0.0, 1.0])
    gt_T = np.stack([planar_T(0, 0, math.pi - 0.1), planar_T(0, 0, -math.pi + 0.1)])  # a 0.2 rad turn across pi
    gt, inside = interpolate_groundtruth(t, gt_T, np.array([0.5, 0.25, 2.0]))
    assert inside.tolist() == [True, True, False]
    assert abs(abs(gt[0, 2]) - math.pi) < 1e-9  # half way is pi, not 0
    m = trajectory_metrics([0.5], [[0.0, 0.0, -math.pi + 0.01]], [np.eye(3)], t, gt_T)
    assert m["heading_rmse_deg"] == pytest.approx(math.degrees(0.01), abs=1e-6)


def test_metrics_with_nothing_to_score():
    gt_t, gt_T = straight_gt()
    m = trajectory_metrics([5.0, 6.0], np.zeros((2, 3)), np.repeat(np.eye(3)[None], 2, 0), gt_t, gt_T)
    assert m["frames"] == 0 and m["outside_gt"] == 2
    assert math.isnan(m["rmse_m"]) and m["within_10cm"] == 0.0
    m = trajectory_metrics(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3)), gt_t, gt_T)
    assert m["frames"] == 0 and math.isnan(m["nees_mean"])


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    """A simulated session with frame 5 corrupted."""
    return make_session(tmp_path_factory.mktemp("replay") / "sess", N, FPS, corrupt=(5,))


def replay_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "tagloc", "replay", *args, "--quiet"], capture_output=True, text=True, timeout=180
    )


def test_replay_is_deterministic_and_scores_against_ground_truth(session, tmp_path):
    runs = []
    for k in range(2):
        out, log = tmp_path / f"est{k}.tum", tmp_path / f"frames{k}.jsonl"
        # The second run also logs to Rerun: that must not change the results either.
        rerun = ["--rerun", str(tmp_path / "r.rrd")] if k else []
        r = replay_cli(str(session), "--out", str(out), "--log", str(log), *rerun)
        assert r.returncode == 0, r.stderr
        runs.append((out.read_bytes(), log.read_bytes(), r.stdout))
    assert runs[0][0] == runs[1][0] and runs[0][1] == runs[1][1]
    stdout = runs[0][2]
    assert f"frames: {N} (1 skipped" in stdout and "error vs ground truth" in stdout
    # The frames stated surer than they were, beside the mean NEES: a share, 0.0-100.0 %.
    beyond = re.search(r", ([0-9.]+)% of frames beyond its 99.9% point", stdout)
    assert beyond is not None and 0.0 <= float(beyond.group(1)) <= 100.0, stdout

    stamps, T = read_tum(tmp_path / "est0.tum")
    assert len(stamps) >= N - 4  # a pose per frame once tracking, the unreadable frame 5 aside
    err = np.hypot(*(T[:, :2, 3] - truth_xy(session, stamps)).T)
    assert np.median(err) < 0.10
    lines = [json.loads(s) for s in (tmp_path / "frames0.jsonl").read_text().splitlines()]
    assert [d["index"] for d in lines] == list(range(N))
    assert lines[5]["skipped"] and not lines[5]["observations"]
    decoded = [o["sticker_id"] for d in lines for o in d["observations"] if o["source"] == "decoded"]
    assert set(decoded) <= set(line_map().ids.tolist()) and len(decoded) >= N // 2

    from tagloc.io.rerun_view import read_rrd

    ents = read_rrd(tmp_path / "r.rrd")
    assert ents["world/body/front/image"].frames == [k for k in range(N) if k != 5]
    assert len(ents["plots/error/position_m"].frames) >= N - 4
    assert ents["world/groundtruth/path"].static


def test_replay_metrics_match_the_library(session, tmp_path):
    from tagloc.apps.replay import ReplayConfig, replay

    res = replay(ReplayConfig(session=session, out=tmp_path / "e.tum", progress=False))
    assert res.frames == N and res.skipped == 1 and res.metrics is not None
    assert res.metrics["frames"] == res.posed
    # Scored are the poses published: the unreadable frame 5 has none (it publishes nothing).
    stamps, _ = read_tum(tmp_path / "e.tum")
    assert res.posed == len(stamps)
    assert res.metrics["rmse_m"] < 0.10 and res.metrics["within_25cm"] > 0.9
    assert sum(res.fixes.values()) >= N // 2 and res.fixes.get("decoded", 0) >= N // 4


def test_frames_of_another_size_are_skipped_and_counted_and_none_usable_is_an_error(session, tmp_path, capsys):
    """A frame whose size is not the calibration's is skipped and counted with the unreadable ones;
    a session none of whose frames can be used is an error naming it and why, not a run (exit 0)."""
    import shutil

    import cv2

    from tagloc.cli import main

    small = cv2.imencode(".jpg", np.full((48, 64), 128, np.uint8))[1].tobytes()
    one = tmp_path / "one_small"
    shutil.copytree(session, one)
    (one / "frames" / "000007.jpg").write_bytes(small)
    assert main(["replay", str(one), "--quiet"]) == 0
    out = capsys.readouterr()
    assert f"frames: {N} (2 skipped" in out.out  # frame 5 unreadable, frame 7 the wrong size

    every = tmp_path / "all_small"
    shutil.copytree(session, every)
    for f in (every / "frames").iterdir():
        f.write_bytes(small)
    assert main(["replay", str(every), "--quiet", "--out", str(tmp_path / "e.tum")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (
        f"tagloc replay: error: {every}: none of its {N} frames could be used "
        "(frame 0: image is 64x48, the calibration is for 1296x972)"
    )


def test_replay_refuses_bad_ground_truth_before_it_writes_anything(session, tmp_path):
    from tagloc.apps.replay import ReplayConfig, replay

    s = shutil.copytree(session, tmp_path / "s")
    gt = s / "groundtruth.tum"
    lines = gt.read_text().splitlines(keepends=True)
    gt.write_text("".join(lines[:9]) + "1.0 0 0 0 0 0 0 NaN\n" + "".join(lines[10:]))
    out, log = tmp_path / "e.tum", tmp_path / "frames.jsonl"
    with pytest.raises(SessionError) as info:
        replay(ReplayConfig(session=s, out=out, log=log, progress=False))
    assert str(info.value) == f"{gt}:10: qw is 'NaN' (must be finite)"
    assert not out.exists() and not log.exists()


def test_a_bags_options_given_with_a_session_are_refused_not_ignored(session, tmp_path, capsys):
    """``replay SESSION --map refined.csv`` (as ``map audit`` and ``map refine`` take --map) replayed
    the session's own map.csv without a word; --rig, --calibration and --info-topic likewise."""
    from tagloc.cli import main

    other = tmp_path / "other.csv"
    shutil.copy(session / "map.csv", other)
    out = tmp_path / "e.tum"
    args = ["replay", str(session), "--out", str(out), "--quiet"]
    assert main([*args, "--map", str(other)]) == 2
    assert capsys.readouterr().err == (
        f"tagloc replay: error: {session}: --map only with a bag (--topic); a session is replayed with its own "
        "map.csv, rig.json and camera.yaml\n"
    )
    assert main([*args, "--rig", str(session / "rig.json"), "--info-topic", "/cam/camera_info"]) == 2
    assert "--rig, --info-topic only with a bag" in capsys.readouterr().err
    assert not out.exists()
    assert main(args) == 0 and out.exists()


def test_a_dropout_in_the_ground_truth_is_not_scored_across():
    """Found by a review: an estimate equal to the truth, on a 2 m circle whose 100 Hz ground truth is
    lost for 6 s, scored 1.04 m RMSE (1.86 m max) against the chord drawn across the dropout; frames
    inside it are neither scored nor counted as frames the ground truth can score."""
    from tagloc.eval.metrics import frames_in_span

    def truth(t):
        return np.column_stack([2 * np.cos(0.5 * t), 2 * np.sin(0.5 * t), 0.5 * t + math.pi / 2])

    gt_t = np.arange(0.0, 10.0001, 0.01)
    gt_t = gt_t[(gt_t <= 2.0) | (gt_t >= 8.0)]
    gt_T = np.stack([planar_T(*p) for p in truth(gt_t)])
    est_t = np.arange(300) / 30.0
    covs = np.repeat(1e-4 * np.eye(3)[None], len(est_t), 0)
    m = trajectory_metrics(est_t, truth(est_t), covs, gt_t, gt_T)
    kept = int(np.sum((est_t <= 2.0) | (est_t >= 8.0)))
    assert m["frames"] == kept == frames_in_span(est_t, gt_t) and m["rmse_m"] < 1e-4
    # Ground truth no denser than its gaps (one pose a second) is still interpolated.
    assert trajectory_metrics([0.5], [[0.0, 0.0, 0.0]], [np.eye(3)], [0.0, 1.0], gt_T[:2])["frames"] == 1


def test_realtime_pacing_does_not_wait_out_a_clock_jump(monkeypatch):
    """``replay --realtime`` over a session whose clock jumps (accepted and reported) waited the jump
    out: an hour's jump slept an hour, one of 1e300 s stopped with an OverflowError from time.sleep.
    Now pacing starts afresh after a step beyond CLOCK_JUMP_S, as live's does. A fake clock, no timing."""
    import tagloc.pipeline.run as run
    from tagloc.core.types import Frame

    class Clock:
        now = 0.0
        slept: list[float] = []

        def monotonic(self) -> float:
            return self.now

        def sleep(self, s: float) -> None:
            self.slept.append(s)
            self.now += s

    clock = Clock()
    monkeypatch.setattr(run, "time", clock)
    stamps = [0.0, 0.1, 0.2, 3600.2, 3600.3, 1e300, 1e300 + 1e290]

    class Source:
        def frames(self):
            return (Frame(i, t, None) for i, t in enumerate(stamps))

    class Echo:
        def process(self, frame):
            return frame.timestamp

    got = list(run._results(Source(), Echo(), progress=False, realtime=True))
    assert got == stamps
    # Each frame waited for its step from the one before, the jumps not at all.
    assert clock.slept == pytest.approx([0.1, 0.1, 0.1])
    assert clock.now == pytest.approx(0.3)
