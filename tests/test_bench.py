"""tagloc bench: a tiny smoke run (structure and sane numbers, no timing assertions) and its helpers."""

from __future__ import annotations

import json
import math
import shutil

import cv2
import numpy as np
import pytest

from tagloc.core.camera import default_camera
from tagloc.core.errors import InputError
from tagloc.core.stickermap import StickerMap
from tagloc.eval.bench import BenchConfig, aruco_frame, format_tables, run_bench, view_at_distance
from tagloc.sim.simulate import camera_pose_looking_at, render_view, true_corners


@pytest.fixture(scope="module")
def quick() -> dict:
    return run_bench(BenchConfig.quick(seed=3))


def test_result_structure_and_json(quick):
    assert {"config", "environment", "timing", "blur", "lux", "distance", "detectors", "targets"} <= set(quick)
    assert [r["frames"] for r in quick["timing"]["rows"]] == ["0 stickers", "1 sticker", "3 stickers"]
    assert [c["blur_px"] for c in quick["blur"]] == [0.0, 4.0]
    assert [c["lux"] for c in quick["lux"]] == [100.0]
    assert [c["distance_m"] for c in quick["distance"]] == [1.5]
    assert len(quick["environment"]["start"]["load_average"]) == 3
    json.loads(json.dumps(quick))  # plain data only


def test_timing_groups_hold_what_they_say(quick):
    rows = {r["frames"]: r for r in quick["timing"]["rows"]}
    # The frames hold what their group says (all stickers fully visible).
    assert rows["0 stickers"]["stickers_visible_mean"] == 0
    assert rows["1 sticker"]["stickers_visible_mean"] == 1
    assert rows["3 stickers"]["stickers_visible_mean"] == 3
    assert rows["0 stickers"]["decode"]["median"] == 0.0 and rows["0 stickers"]["pose"]["median"] == 0.0
    assert all(r["n"] == 3 for r in rows.values())
    ar = quick["timing"]["aruco"]
    assert ar["frames"] == 3 and ar["detected"] == 3  # the pasted marker is a valid ArUco marker


def test_reads_are_right_and_never_wrong(quick):
    b0 = quick["blur"][0]
    assert b0["stickers"] == 3 and b0["detected"] == 3
    assert b0["decode"]["zxing"]["rate"] == 1.0
    assert b0["identify"]["auto"]["rate"] == 1.0
    for c in quick["blur"] + quick["lux"]:
        assert all(v["wrong"] == 0 for v in c["decode"].values())
        assert all(v["wrong"] == 0 and v["absent_wrong"] == 0 for v in c["identify"].values())
    # Stronger blur lengthens what the frame shows.
    assert quick["blur"][1]["blur_px_median"] > 3.5 > quick["blur"][0]["blur_px_median"]


def test_geometry_errors_are_small(quick):
    b0 = quick["blur"][0]
    assert 0 < b0["outer_err_px"]["median"] < 1.0
    d = quick["distance"][0]
    assert d["detected"] == d["stickers"] == 3
    assert 0 < d["position_err_cm"]["median"] < 3.0


def test_targets_and_tables(quick):
    names = [t["target"] for t in quick["targets"]]
    assert any("ArUco" in n for n in names) and any("wrong IDs" in n for n in names)
    wrong = next(t for t in quick["targets"] if t["target"].startswith("wrong IDs"))
    assert wrong["value"] == 0 and wrong["pass"] is True
    text = format_tables(quick)
    for title in ("1. Stage CPU time", "2a.", "2b.", "3a.", "3b.", "4. Paper", "Targets"):
        assert title in text
    assert "PASS" in text and "load average" in text
    # Aligned: every line of a table has the width of its header line.
    lines = text.splitlines()
    k = next(i for i, line in enumerate(lines) if line.startswith("blur px  stickers"))
    assert len({len(line.rstrip()) for line in lines[k : k + 4]}) <= 2


def test_view_at_distance_is_exact():
    cam = default_camera()
    rng = np.random.default_rng(5)
    for d in (1.0, 1.5, 2.5):
        T = view_at_distance(rng, cam, np.array([3.0, -2.0]), d)
        assert np.linalg.norm(T[:3, 3] - [3.0, -2.0, 0.0]) == pytest.approx(d, abs=1e-6)
        assert 0.5 < T[2, 3] <= 1.5
        smap = StickerMap(np.array([42]), np.array([[3.0, -2.0]]), np.array([0.3]))
        px = true_corners(smap, cam, T, 42)
        assert px is not None and np.all(px > 0) and np.all(px < (cam.width, cam.height))


def test_aruco_frame_is_detected_where_the_sticker_was():
    cam = default_camera()
    smap = StickerMap(np.array([7]), np.array([[0.0, 0.0]]), np.array([0.4]))
    T = camera_pose_looking_at((0.0, 0.0), 1.3, 55.0, 20.0)
    gray = render_view(smap, cam, T, 150.0, seed=1).image
    corners = true_corners(smap, cam, T, 7)[:4]
    out = aruco_frame(gray, corners, np.random.default_rng(0))
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    found, ids, _ = det.detectMarkers(out)
    assert ids is not None and 7 in ids.ravel()
    c = found[list(ids.ravel()).index(7)].reshape(4, 2)
    # Same square, whatever the starting corner.
    err = min(np.abs(np.roll(c, -r, axis=0) - corners).max() for r in range(4))
    assert err < 1.5
    assert math.isclose(float(out[:50].mean()), float(gray[:50].mean()), abs_tol=0.01)  # rest untouched


def test_bad_options_are_refused(tmp_path):
    with pytest.raises(InputError):
        BenchConfig(frames=0)
    with pytest.raises(InputError):
        BenchConfig(near_m=2.0, far_m=1.0)
    # Refused before any work: a file where the JSON's directory should be (a missing one is made).
    (tmp_path / "f").write_text("")
    from tagloc.cli import main

    assert main(["bench", "--quick", "--json", str(tmp_path / "f" / "b.json")]) == 2


BENCHMARKS = sorted((__import__("pathlib").Path(__file__).resolve().parent.parent / "benchmarks").glob("*.py"))


@pytest.mark.parametrize("script", BENCHMARKS, ids=lambda p: p.name)
def test_every_benchmark_script_ends_its_run_through_the_one_line_error_guard(script):
    """A benchmark given a path that is no session prints one line, as the tagloc commands do."""
    assert script.read_text().rstrip().endswith(f'raise SystemExit(run_guarded("{script.name}", main))')


@pytest.mark.parametrize("script", BENCHMARKS, ids=lambda p: p.name)
def test_every_benchmark_script_answers_help_with_its_usage(script):
    """``--help`` prints the usage and exits at once: it never starts the benchmark's work."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.startswith("usage: "), (r.stdout[:200], r.stderr[-300:])


@pytest.mark.parametrize(
    "name",
    ["fix_error.py", "covariance_growth.py", "odometry_accuracy.py", "survey_sensitivity.py", "coverage_misses.py"],
)
def test_a_benchmark_given_no_session_says_so_in_one_line(name, tmp_path):
    import subprocess
    import sys

    script = next(p for p in BENCHMARKS if p.name == name)
    r = subprocess.run(
        [sys.executable, str(script), str(tmp_path / "nope")], capture_output=True, text=True, timeout=120
    )
    lines = [ln for ln in r.stderr.splitlines() if ln.strip() and "it/s" not in ln and "walk/s" not in ln]
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert lines[-1] == f"{name}: error: {tmp_path / 'nope'}: not a session directory"


def test_the_survey_sensitivity_map_scales_each_stickers_error_and_states_its_sigmas(monkeypatch):
    """Factor 0 is the true map, 1 the survey, 0.5 half way (a yaw error across +-180 deg wrapped)."""
    import math
    import sys

    import numpy as np

    from tagloc.core.stickermap import StickerMap

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop("survey_sensitivity", None)
    from survey_sensitivity import scaled_map

    true = StickerMap([1, 2], [[0.0, 0.0], [2.0, 1.0]], [math.radians(179.0), 0.5])
    # Listed in another order; sticker 1's yaw error is +2 deg across the wrap, sticker 2's -1 deg.
    surveyed = StickerMap([2, 1], [[2.02, 0.99], [-0.01, 0.03]], [0.5 - math.radians(1.0), math.radians(-179.0)])
    for f in (0.0, 0.5, 1.0):
        m = scaled_map(true, surveyed, f, 0.015, 1.5)
        assert m.ids.tolist() == [1, 2]
        assert np.allclose(m.xy, [[-0.01 * f, 0.03 * f], [2.0 + 0.02 * f, 1.0 - 0.01 * f]], atol=1e-12)
        assert np.allclose(np.degrees(m.yaw), [179.0 + 2.0 * f, math.degrees(0.5) - 1.0 * f], atol=1e-9)
        assert np.allclose(m.sigma_xy, 0.015 * f) and np.allclose(np.degrees(m.sigma_yaw), 1.5 * f)


@pytest.mark.parametrize(
    "args, named",
    [
        (["--conditions", "clean,nosuch"], "--conditions: unknown nosuch"),
        (["--conditions", "clean", "--variants", "default,nosuch"], "--variants: unknown nosuch"),
        (["--conditions", "clean", "--seeds", "0"], "--seeds must be a number >= 1"),
    ],
)
def test_field_sensor_refuses_an_unknown_name_before_simulating_any_walk(monkeypatch, tmp_path, args, named):
    """A misspelt condition or variant was a KeyError ("internal error") once the walks before it
    had been simulated and replayed; it is now a user's error, before any work."""
    import sys

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop("field_sensor", None)
    import field_sensor

    made = []
    monkeypatch.setattr(field_sensor, "make", lambda *a: made.append(a))
    with pytest.raises(InputError) as err:
        field_sensor.main([*args, "-o", str(tmp_path / "fs")])
    assert str(err.value).startswith(named) and made == []


def test_field_sensor_states_a_rig_off_as_its_condition_says(monkeypatch, tmp_path):
    """``rig-fit`` and ``stature`` walks are rendered with the nominal rig and state it off: the
    camera turned by STATED_RIG_TURN_DEG about the body's z, y and x axes, or raised; its position
    on the vest unchanged. ``gait-x2`` walks twice the default gait."""
    import sys

    from scipy.spatial.transform import Rotation

    from tagloc.core.rig import looking_forward

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop("field_sensor", None)
    import field_sensor

    T = looking_forward(1.3, 55.0)
    configs = []

    def fake(smap, path, cfg, progress):
        configs.append(cfg)
        path.mkdir(parents=True)
        rig = {"vest_height_m": 1.3, "cameras": [{"name": "front", "T_body_camera": T.tolist()}]}
        (path / "rig.json").write_text(json.dumps(rig))

    monkeypatch.setattr(field_sensor, "simulate_session", fake)
    monkeypatch.setattr(field_sensor, "walk_map", lambda seed: None)
    for cond in ("rig-fit", "stature", "gait-x2"):
        path = field_sensor.make(tmp_path / cond, 100, 1.0, cond)
        stated = np.array(json.loads((path / "rig.json").read_text())["cameras"][0]["T_body_camera"])
        turn = field_sensor.STATED_RIG_TURN_DEG.get(cond, (0.0, 0.0, 0.0))
        R = Rotation.from_euler("ZYX", turn, degrees=True).as_matrix()
        assert np.allclose(stated[:3, :3], R @ T[:3, :3], atol=1e-12)
        raise_m = field_sensor.STATED_RIG_RAISE_M.get(cond, 0.0)
        assert np.allclose(stated[:3, 3], T[:3, 3] + [0.0, 0.0, raise_m])
    assert configs[2].walk.torso_yaw_deg == pytest.approx(5.0) and configs[0].walk.torso_yaw_deg == pytest.approx(2.5)


@pytest.mark.parametrize(
    "script, args, named",
    [
        ("replay_cost", ["--repeat", "0"], "--repeat must be a number >= 1"),
        ("replay_cost", ["--core", "100000"], "--core 100000: not a CPU"),
        ("load_shedding", ["--repeat", "0"], "--repeat must be a number >= 1"),
        ("load_shedding", ["--slowdown", "1,0"], "--slowdown must be a number > 0"),
        ("load_shedding", ["--slowdown", "x"], "--slowdown: 'x' is not a number"),
    ],
)
def test_the_speed_benchmarks_refuse_bad_run_options_before_any_work(monkeypatch, tmp_path, script, args, named):
    """``--repeat 0`` printed the table's header and then an IndexError as an internal error, a
    --core the process may not use OSError's bare "Invalid argument", ``--slowdown 0`` a
    ZeroDivisionError; each is now the user's one-line error, given before the session is read."""
    _refused_before_any_work(monkeypatch, tmp_path, script, args, named)


def _refused_before_any_work(monkeypatch, tmp_path, script: str, args: list[str], named: str) -> None:
    """``benchmarks/<script>.py``'s main, given ``args`` and a session that does not exist (none for
    bench_candidates, which takes none), raises the InputError that starts with ``named``."""
    import importlib
    import sys

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop(script, None)
    mod = importlib.import_module(script)
    session = [] if script == "bench_candidates" else [str(tmp_path / "no-session")]
    with pytest.raises(InputError) as err:
        mod.main([*session, *args])
    assert str(err.value).startswith(named)


def test_odometry_stride_compares_the_steps_with_the_vest_points_motion(monkeypatch, tmp_path):
    """The odometry measures the vest point's motion (the camera's, carried through the nominal rig):
    a torso that rolls 6 degrees about its feet moves the vest point 1.3 m up by 13.6 cm sideways
    while the tilted body frame's origin on the floor stays put. The script compared the chained
    steps with that origin's motion, so a step that read the vest's motion exactly came out 13.6 cm
    off; against the vest point it is exact."""
    import json
    import math
    import sys
    import types

    from tagloc.core.geometry import planar_T
    from tagloc.core.rig import default_rig
    from tagloc.vision.odometry import OdometryStep

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop("odometry_stride", None)
    import odometry_stride

    rig = default_rig()
    roll = math.radians(6.0)
    c, s = math.cos(roll), math.sin(roll)
    T_world_body = [planar_T(2.0, 1.0, 0.3), planar_T(2.0, 1.0, 0.3) @ np.array(
        [[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]]
    )]  # fmt: skip
    with (tmp_path / "groundtruth_frames.jsonl").open("w") as f:
        for k, T in enumerate(T_world_body):
            f.write(json.dumps({"index": k, "T_world_camera": (T @ rig[0].T_body_camera).tolist()}) + "\n")
    truth = odometry_stride._vest_truth(tmp_path, types.SimpleNamespace(rig=rig), {0: 0.0, 1: 1 / 30})
    sideways = -1.3 * s  # +roll tips the body's left (+y) up: the vest point goes right
    step = OdometryStep(0.0, 1 / 30, np.array([0.0, sideways, 0.0]), np.eye(3) * 1e-6, 1.0)
    err = odometry_stride._window_errors([step], truth, 1.0)
    assert err.shape == (1, 3) and np.allclose(err, 0.0, atol=1e-9)


def test_the_bench_measures_with_one_blas_thread_and_gives_the_settings_back(monkeypatch):
    """The bench set OpenCV to one thread but left BLAS on its default threads, whose spinning on a
    busy machine counted in the stages' CPU time (the least-squares decode's p95 several times its
    one-thread figure); it now measures as the localiser runs, and the process's settings come back."""
    import threadpoolctl

    import tagloc.eval.bench as bench

    def blas_threads() -> set[int]:
        return {i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"}

    before, seen = (blas_threads(), cv2.getNumThreads()), []

    def scene(cfg, rig):
        seen.append((blas_threads(), cv2.getNumThreads()))
        raise KeyboardInterrupt  # stop here: the rest is the bench's work

    monkeypatch.setattr(bench, "_build_scene", scene)
    with pytest.raises(KeyboardInterrupt):
        bench.run_bench(BenchConfig.quick())
    assert seen == [({1}, 1)]
    assert (blas_threads(), cv2.getNumThreads()) == before


def test_the_soak_runs_the_localiser_tagloc_live_runs(monkeypatch, tmp_path):
    """The soak wrapped the localiser in an object offering ``process`` alone, built with the
    library's defaults: the live loop found no deferred work (every frame decoded and measured in
    full before publishing) and no ``behind`` to shed load by, so it soaked another configuration
    than ``tagloc live``'s. Now it is live's localiser, only its ``process`` timed."""
    import argparse
    import shutil
    import sys

    from tagloc.apps.live import LiveConfig, run_live

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop("soak", None)
    import soak

    root = BENCHMARKS[0].parent.parent
    shutil.copytree(root / "logs" / "walk2s", tmp_path / "walk_2s_30fps")
    shutil.copy(root / "maps" / "demo.refs.npz", tmp_path / "walk_2s_30fps" / "map.refs.npz")
    source, loc, done = soak.prepare(argparse.Namespace(work=tmp_path, sim_seconds=2.0, fps=30.0))
    assert loc.config.defer_lsq and loc.config.defer_odometry
    calls = []
    deferred = loc.deferred_work
    monkeypatch.setattr(loc, "deferred_work", lambda go_on=None: calls.append(1) or deferred(go_on))
    summary = run_live(LiveConfig(source="soak-loop", max_frames=12, pace=False), localiser=loc, source=source)
    assert summary.frames == 12 and len(done) == 12 and len(calls) == 12 and loc.counts["frames"] == 12


@pytest.mark.parametrize(
    "script, args, named",
    [
        ("odometry_accuracy", ["--config", "x"], "--config: not JSON"),
        ("odometry_accuracy", ["--config", '{"no_such_field": 1}'], "--config: no OdometryConfig field"),
        ("odometry_accuracy", ["--config", "[1]"], "--config: want a JSON object"),
        ("odometry_stride", ["--config", '{"no_such_field": 1}'], "--config: no OdometryConfig field"),
        ("bench_candidates", ["--n", "0"], "--n must be a number >= 9"),
        ("bench_candidates", ["--calls", "0"], "--calls must be a number >= 1"),
        ("eval_variants", ["--variant", 'x={"tracker": 1}'], "--variant x: 'tracker' is a group of settings"),
        ("eval_variants", ["--variant", 'x={"nosuch": 1}'], "--variant x: no setting 'nosuch'"),
        ("eval_variants", ["--variant", "x=[1]"], "--variant x: want a JSON object"),
        ("blind_spans", ["--variant", "x=[1]"], "--variant x: want a JSON object"),
        ("blind_spans", ["--durations", "1,x"], "--durations: 'x' is not a number"),
        ("blind_spans", ["--durations", "1,0"], "--durations must be a number > 0"),
        ("bridges", ["--variant", "x=[1]"], "--variant x: want a JSON object"),
    ],
)
def test_bad_option_values_are_the_users_one_line_error_before_any_work(monkeypatch, tmp_path, script, args, named):
    """A bad --config was a JSONDecodeError or TypeError, ``--n 0`` or ``--calls 0`` a ValueError or
    IndexError, and a variant giving a group of settings one value an AttributeError in the first
    replay after the default's: each reported as a bug ("internal error ... please report it"). Each is
    now an InputError naming the option (exit 2), raised before any session is read."""
    _refused_before_any_work(monkeypatch, tmp_path, script, args, named)


def _blas_and_cv_threads() -> tuple[set[int], int]:
    import threadpoolctl

    return {i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"}, cv2.getNumThreads()


@pytest.mark.parametrize("script", ["odometry_accuracy", "odometry_stride", "bench_candidates"])
def test_the_odometry_and_tracker_timings_run_on_one_blas_thread(monkeypatch, script):
    """odometry_accuracy's and odometry_stride's process time per ``measure`` and bench_candidates'
    timings ran with BLAS on its default threads, whose spinning on a busy machine counts in the
    time; they now measure inside ``single_threaded()`` as ``tagloc bench`` does, settings given back."""
    import importlib
    import sys

    from tagloc.io.session import SessionReader
    from tagloc.vision.odometry import FloorOdometry, OdometryConfig

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop(script, None)
    mod = importlib.import_module(script)
    before, seen = _blas_and_cv_threads(), []

    def timed(*args, **kwargs):
        seen.append(_blas_and_cv_threads())
        raise KeyboardInterrupt  # stop here: the rest is the benchmark's work

    walk = BENCHMARKS[0].parent.parent / "logs" / "walk2s"
    with pytest.raises(KeyboardInterrupt):
        if script == "bench_candidates":
            monkeypatch.setattr(mod.Tracker, "predict", timed)
            mod.main(["--n", "9", "--calls", "2"])
        else:
            monkeypatch.setattr(FloorOdometry, "measure", timed)
            if script == "odometry_accuracy":
                mod.run_session(walk, OdometryConfig())
            else:
                mod._steps(SessionReader(walk), OdometryConfig(max_stride=1))
    assert seen == [({1}, 1)]
    assert _blas_and_cv_threads() == before


def test_odometry_accuracy_in_the_localiser_times_the_measure_calls_alone(monkeypatch):
    """``--in-localiser``'s ms column, documented as the CPU time per ``measure`` call, was the whole
    localiser's time and the JPEG reads per frame. On a clock that runs only where the test advances
    it (3 ms in each measure call, 10 ms more in the rest of each frame) it is now the 3 ms."""
    import sys
    import types

    from tagloc.pipeline.localiser import Localiser
    from tagloc.vision.odometry import FloorOdometry, OdometryConfig

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop("odometry_accuracy", None)
    import odometry_accuracy

    clock = [0.0]
    monkeypatch.setattr(odometry_accuracy, "time", types.SimpleNamespace(process_time=lambda: clock[0]))
    measure, process = FloorOdometry.measure, Localiser.process

    def measured(self, *args, **kwargs):
        clock[0] += 0.003
        return measure(self, *args, **kwargs)

    def processed(self, frame):
        clock[0] += 0.010
        return process(self, frame)

    monkeypatch.setattr(FloorOdometry, "measure", measured)
    monkeypatch.setattr(Localiser, "process", processed)
    walk = BENCHMARKS[0].parent.parent / "logs" / "walk2s"
    r = odometry_accuracy.run_session_in_localiser(walk, OdometryConfig())
    assert len(r["true"]) > 30
    assert r["cost_s"] == pytest.approx(0.003, abs=1e-9)


def test_odometry_accuracy_bins_the_steps_by_ecc_correlation_against_their_stated_sigmas(monkeypatch):
    """``--by-rho``: each patch-matched step lands in its correlation's bin with its RMS error and its
    error over the stated sigma; refused steps (NaN) and flow-only steps (rho NaN) are left out."""
    import math
    import sys

    import numpy as np

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop("odometry_accuracy", None)
    from odometry_accuracy import rho_table

    true = np.zeros((5, 3))
    meas = np.array([[0.001, 0.0, 0.0], [-0.001, 0.0, 0.0], [0.0, 0.004, 0.0], [0.5, 0.5, 0.5], [np.nan] * 3])
    cov = np.tile(np.diag([0.002**2, 0.002**2, 0.01**2]), (5, 1, 1))
    rho = np.array([0.22, 0.24, 0.35, np.nan, 0.5])
    rows = {
        ln.split()[0]: ln.split()
        for ln in rho_table([{"true": true, "meas": meas, "cov": cov, "rho": rho}]).splitlines()[1:]
    }
    assert set(rows) == {"0.2-0.25", "0.3-0.4"}
    low, mid = rows["0.2-0.25"], rows["0.3-0.4"]
    assert int(low[1]) == 2 and float(low[2]) == pytest.approx(1.0) and float(low[5]) == pytest.approx(0.5)
    assert float(low[8]) == pytest.approx(0.5)
    assert int(mid[1]) == 1 and float(mid[3]) == pytest.approx(4.0) and float(mid[6]) == pytest.approx(2.0)
    assert float(mid[4]) == pytest.approx(0.0) and math.isfinite(float(mid[7]))


@pytest.mark.parametrize(
    "speeds, fitted, said",
    [
        ((1.3,), set(), "no window slower than 0.3 m/s: no sigma fitted"),
        ((0.1,), {"sigma_forward", "sigma_lateral", "sigma_yaw"}, "no window faster than 0.9 m/s"),
        ((0.1, 1.3), {f"sigma_{n}{m}" for n in ("forward", "lateral", "yaw") for m in ("", "_per_m")}, "8 walking"),
    ],
)
def test_odometry_calibration_says_when_it_has_no_window_to_fit_on(monkeypatch, capsys, speeds, fitted, said):
    """A short walk with no window slower than 0.3 m/s printed NaN sigmas with a RuntimeWarning; the
    calibration now says there was no such window and fits only what it has windows for."""
    import sys
    import types
    import warnings

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop("odometry_accuracy", None)
    import odometry_accuracy

    rng = np.random.default_rng(4)
    results = []
    for v in speeds:  # 60 steps at 30 fps straight ahead: 8 windows (4 of 15 frames, 2 of 30, 1 of 45, 1 of 60)
        true = np.tile([v / 30.0, 0.0, 0.0], (60, 1))
        odo = types.SimpleNamespace(patch=types.SimpleNamespace(centre=(0.6, 0.0)))
        results.append({"true": true, "meas": true + rng.normal(0.0, 1e-3, true.shape), "odo": odo})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = odometry_accuracy.calibrate(results)
    assert set(got) == fitted and all(math.isfinite(v) for v in got.values())
    assert said in capsys.readouterr().out


def test_load_shedding_shows_the_true_median_of_an_even_count_of_runs(monkeypatch):
    """With ``--repeat 2`` or 4 the "median" shown was the upper of the two middle runs."""
    import sys

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop("load_shedding", None)
    from load_shedding import _spread

    assert _spread([4.0, 1.0, 3.0, 2.0]) == "2.50 (1.00-4.00)"
    assert _spread([181, 180], "{:g}") == "180.5 (180-181)"
    assert _spread([7.0, 5.0, 6.0]) == "6.00 (5.00-7.00)"


def test_load_shedding_counts_the_runs_that_went_wrong(monkeypatch):
    """A run over 10 cm RMS, or with no pose at all, is counted: the median over runs hid them."""
    import sys

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop("load_shedding", None)
    from load_shedding import _over

    runs = [{"rmse_cm": v} for v in (3.7, 31.4, 10.0, float("nan"), 4.1)]
    assert _over(runs) == "2/5"
    assert _over(runs[:1]) == "0/1"


@pytest.mark.parametrize("script", BENCHMARKS, ids=lambda p: p.name)
def test_every_benchmark_says_to_run_it_with_an_interpreter_that_exists(script):
    """bench_candidates.py said to run it with /opt/venv/bin/python, which is nowhere; a script names
    ``python`` (the README's ``PYTHONPATH=$PWD python benchmarks/...``) or a path that exists."""
    import re
    from pathlib import Path

    for path in re.findall(r"(?<![\w$}])(/[\w./-]*/bin/python[\d.]*)", script.read_text()):
        assert Path(path).exists(), path


def test_odometry_stride_chains_a_step_longer_than_the_window_alone(monkeypatch):
    """A step longer than ``--window`` (a bridged gap, or a window under a frame: ``--window 0.01``)
    sent the chaining round without end; it is now a chain of its own, and ``--window 0`` is refused."""
    import sys

    from tagloc.core.geometry import planar_T
    from tagloc.vision.odometry import OdometryStep

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop("odometry_stride", None)
    import odometry_stride

    class Bounded(list):
        """The steps, refusing to be asked their length without end (the old loop's symptom)."""

        asked = 0

        def __len__(self) -> int:
            Bounded.asked += 1
            if Bounded.asked > 1000:
                raise RuntimeError("the chaining never ends")
            return super().__len__()

    times = [0.0, 1 / 30, 2 / 30, 0.5]  # two frame steps, then a 0.43 s bridged gap
    steps = Bounded(
        OdometryStep(t0, t1, np.array([0.04, 0.0, 0.0]), np.eye(3) * 1e-6, 1.0) for t0, t1 in zip(times, times[1:])
    )
    truth = {round(t, 6): planar_T(0.04 * k, 0.0, 0.0) for k, t in enumerate(times)}
    assert len(odometry_stride._window_errors(steps, truth, 0.01)) == 3  # each step alone
    err = odometry_stride._window_errors(steps, truth, 0.1)  # the two frame steps, then the gap
    assert err.shape == (2, 3) and np.allclose(err, 0.0, atol=1e-12)
    with pytest.raises(InputError, match="--window must be a number > 0"):
        odometry_stride.main(["no-session", "--window", "0"])


def test_bridges_counts_the_bridged_bursts_of_a_walk(monkeypatch, tmp_path):
    """benchmarks/bridges.py on a 2 s straight walk (seed 5, the demo map), 3 frames dropped after
    every frame from the fifth: the odometry bridges the gaps, none beyond the bound, and the
    published pose after each stays within the tracker's gate level. Every count is of bridges;
    likewise with the odometry striding (a bridge then may start before the burst's frame)."""
    import dataclasses
    import sys
    from pathlib import Path

    from tagloc.core.stickermap import load_map
    from tagloc.pipeline.localiser import LocaliserConfig
    from tagloc.sim.simulate import SimConfig, simulate_session

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop("bridges", None)
    import bridges

    root = Path(__file__).resolve().parent.parent
    walk = tmp_path / "walk"
    simulate_session(load_map(root / "maps" / "demo.csv"), walk, SimConfig(seconds=2, seed=5), progress=False)
    variants = {"default": LocaliserConfig(), "stride": dataclasses.replace(LocaliserConfig(), odometry_stride=True)}
    rows = bridges._session_rows((str(walk), [3], 5, variants))
    for row in rows:
        assert 45 <= row["bridges"] <= 51  # of the 51 gaps that end inside the walk (51 measured)
        assert row["wrong"] == row["fused"] == row["right_refused"] == 0
        assert 0.0 < row["after_max"] < bridges.CHI2_3_999 and row["after_over"] == 0
        # Scored against the truth over the step's own frames: with the odometry striding, 19 of
        # the 51 bridges start a frame before the one the burst follows (scored over that frame's
        # interval instead, the forward RMS was 26 mm against 9 mm; 11 mm now).
        assert row["right_rms"][0] < 0.015, row


def test_coverage_misses_accounts_for_every_frame_of_the_bundled_walk():
    """Every frame the ground truth covers falls in exactly one column; the bundled walk starts on a
    sticker, so nothing comes before one, and its poses are all within the bar."""
    import sys

    sys.path.insert(0, str(BENCHMARKS[0].parent))
    from coverage_misses import COLUMNS, misses

    from tagloc.io.session import SessionReader

    walk = BENCHMARKS[0].parent.parent / "logs" / "walk2s"
    row = misses(walk)
    assert set(row) == set(COLUMNS)
    assert sum(row.values()) == len(SessionReader(walk))
    assert row["before sticker"] == 0 and row["over 10 cm"] == 0 and row["within"] >= 0.95 * sum(row.values())


def test_load_shedding_counts_the_runs_stated_surer_than_they_were(monkeypatch):
    """A run whose NEES is above its own bound is counted: a track gone wrong while stating itself
    sure, which the RMSE column cannot tell from one that says it is lost."""
    import sys

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop("load_shedding", None)
    from load_shedding import _overconfident

    runs = [{"nees_verdict": v} for v in ("consistent", "overconfident", "conservative", "too short", "overconfident")]
    assert _overconfident(runs) == "2/5"
    assert _overconfident(runs[:1]) == "0/1"


def test_load_shedding_judges_each_run_by_its_own_nees_bound(monkeypatch, tmp_path):
    """One live run of a bright 11 s walk (three of eval's 5 s NEES blocks) at the camera's own rate:
    its published poses are scored against the walk's truth, NEES included, and judged as tagloc
    eval judges a walk."""
    import sys

    from tagloc.sim.mapgen import GridMapConfig, grid_map
    from tagloc.sim.simulate import SimConfig, simulate_session

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop("load_shedding", None)
    from load_shedding import run_once

    smap = grid_map(GridMapConfig(width_m=12, depth_m=10, spacing_min_m=1.2, spacing_max_m=1.6, seed=2))
    simulate_session(smap, tmp_path / "walk", SimConfig(seconds=11, lux=300, speed_mps=1.2, seed=2), progress=False)
    r = run_once(tmp_path / "walk", 1.0, True)
    assert r["rmse_cm"] < 5.0
    # A bright walk the tracker follows: no wilder than the bound a consistent filter would keep.
    assert 0.0 < r["nees"] < 5.0
    assert r["nees_verdict"] in ("consistent", "conservative")
    assert r["beyond_999"] < 0.02  # a consistent filter's share is 0.1 %


def _thin_sessions(monkeypatch):
    import sys

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop("thin_sessions", None)
    import thin_sessions

    return thin_sessions


def test_thinned_sessions_keep_every_other_frame_with_its_own_index_and_time(tmp_path, monkeypatch):
    """benchmarks/thin_sessions.py: the bundled walk at half its rate replays as a session, each kept
    frame with its index and timestamp as recorded; an existing destination and a malformed source
    are refused before anything is written."""
    from tagloc.io.session import SessionReader

    thin = _thin_sessions(monkeypatch)
    walk = BENCHMARKS[0].parent.parent / "logs" / "walk2s"
    assert thin.main([str(walk), "-o", str(tmp_path / "t")]) == 0
    src, out = SessionReader(walk), SessionReader(tmp_path / "t" / "walk2s")
    assert len(src) == 60 and list(out.index) == list(src.index[::2])
    assert np.array_equal(out.timestamps, src.timestamps[::2])
    assert out.info.fps == pytest.approx(src.info.fps / 2)
    assert out.groundtruth() is not None and len(list(out.frames())) == 30
    with pytest.raises(InputError, match="already exists"):
        thin.main([str(walk), "-o", str(tmp_path / "t")])
    bad = tmp_path / "bad"
    shutil.copytree(walk, bad)
    (bad / "frames.csv").write_text("index,timestamp_ms\n0,0\n")
    with pytest.raises(InputError, match="frames.csv:1: header"):
        thin.main([str(bad), "-o", str(tmp_path / "t2")])
    assert not (tmp_path / "t2").exists()


def test_thinned_two_camera_sessions_keep_every_other_frame_of_each_camera(tmp_path, monkeypatch):
    """With two cameras, every other frame of each (not every other row, which would keep one camera)."""
    from tagloc.core.rig import save_rig
    from tagloc.eval.multicam import front_rear_rig
    from tagloc.io.session import SessionReader

    thin = _thin_sessions(monkeypatch)
    two = tmp_path / "two"
    shutil.copytree(BENCHMARKS[0].parent.parent / "logs" / "walk2s", two)
    save_rig(front_rear_rig(), two / "rig.json", write_calibrations=False)
    rows = (two / "frames.csv").read_text().splitlines()[1:13]
    lines = ["index,timestamp_s,camera"]
    for k, row in enumerate(rows):  # cameras 0, 0, 1, 1, 0, 0, 1, 1, ...: each camera's frames in pairs
        index, stamp = row.split(",")[:2]
        camera = (k // 2) % 2
        if camera:
            jpg = two / "frames" / f"{int(index):06d}.jpg"
            jpg.rename(jpg.with_name(f"{int(index):06d}_cam1.jpg"))
        lines.append(f"{index},{stamp},{camera}")
    (two / "frames.csv").write_text("\n".join(lines) + "\n")
    assert thin.thin_session(two, tmp_path / "t" / "two", 2) == 6
    out = SessionReader(tmp_path / "t" / "two")
    assert list(out.cameras) == [0, 1, 0, 1, 0, 1]
    assert list(out.index) == [int(r.split(",")[0]) for r in rows[::2]]


def test_trace_walk_follows_the_bundled_walk_frame_by_frame(tmp_path, monkeypatch):
    """benchmarks/trace_walk.py: per frame the error against the truth, its NEES, the heading's error
    and stated sd, and the counters that changed; the window selects frames by time; settings are
    taken as eval_variants takes them; a session without ground truth is refused."""
    import sys

    monkeypatch.syspath_prepend(str(BENCHMARKS[0].parent))
    sys.modules.pop("trace_walk", None)
    import trace_walk

    walk = BENCHMARKS[0].parent.parent / "logs" / "walk2s"
    rows = trace_walk.trace(walk, {})
    assert len(rows) == 60
    placed = [r for r in rows if math.isfinite(r["error_cm"])]
    assert len(placed) >= 55 and all(r["error_cm"] < 10.0 and r["heading_sd_deg"] > 0.0 for r in placed)
    assert sum(r["counts"].get("tracker_accepted_decoded", 0) for r in rows) >= 5
    fixes = sum(sum(v for k, v in r["counts"].items() if k.startswith("tracker_accepted_")) for r in rows)
    assert fixes >= 40  # most frames of the walk are placed by a fix
    window = trace_walk.trace(walk, {}, 0.5, 1.0)
    assert [r["t"] for r in window] == [r["t"] for r in rows if 0.5 <= r["t"] <= 1.0] and len(window) == 16
    assert [r["error_cm"] for r in window] == [r["error_cm"] for r in rows if 0.5 <= r["t"] <= 1.0]
    line = trace_walk.format_row(rows[-1])
    assert "t.odometry_accepted+1" in line or "t.accepted_" in line
    off = trace_walk.trace(walk, {"odometry": False}, 1.0, 2.0)
    assert all("tracker_odometry_accepted" not in r["counts"] for r in off)
    bare = tmp_path / "bare"
    shutil.copytree(walk, bare)
    (bare / "groundtruth.tum").unlink()
    with pytest.raises(InputError, match="no groundtruth.tum"):
        trace_walk.trace(bare, {})
