"""tagloc eval --walks: sessions one already has, scored as the presets are (the bundled 2 s walk)."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from tagloc.cli import main
from tagloc.core.errors import InputError
from tagloc.eval.evaluate import GROUNDTRUTH_FRAMES, wrong_id_fixes_by_pose
from tagloc.eval.walks import find_sessions, walk_names
from tagloc.pipeline.run import RunLog

REPO = Path(__file__).resolve().parent.parent
WALK = REPO / "logs" / "walk2s"


def recorded_copy(dest: Path) -> Path:
    """The bundled walk as a site recording would be: no simulator's per-frame truth."""
    shutil.copytree(WALK, dest, ignore=shutil.ignore_patterns("*.npz"))
    (dest / GROUNDTRUTH_FRAMES).unlink()
    return dest


def rows_of(out: Path) -> list[dict]:
    return json.loads((out / "results.json").read_text())["rows"]


def test_walks_are_scored_as_a_preset_and_wrong_ids_by_pose_agree_with_the_frames_truth(tmp_path, capsys):
    rec = recorded_copy(tmp_path / "site" / "walk-a")
    assert main(["eval", "--walks", str(WALK), str(rec), "--modes", "full", "-o", str(tmp_path / "o"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "Wrong IDs checked by the simulator's per-frame truth and by pose" in out and "### 2 walks" in out
    sim, site = rows_of(tmp_path / "o")
    assert (sim["wrong_id_check"], site["wrong_id_check"]) == ("frames", "pose")
    # The same frames and localiser: the same figures, and no fix placed at the wrong sticker.
    assert site["rmse_m"] == pytest.approx(sim["rmse_m"], abs=1e-12) and site["fixes"] == sim["fixes"] > 50
    assert sim["wrong_id_fixes"] == site["wrong_id_fixes"] == 0
    assert sim["rmse_m"] < 0.03 and site["conditions"].startswith("tagloc simulate: 2 s")
    assert {p.name for p in (tmp_path / "o").glob("*.png")} == {"walk2s.png", "walk-a.png"}


def test_fixes_placed_at_the_wrong_sticker_are_counted_by_pose(tmp_path, capsys):
    """Two stickers seen on the walk with their IDs swapped in the map: every accepted fix of either
    names the sticker that is not there, and the check by pose counts each one."""
    rec = recorded_copy(tmp_path / "swapped")
    rows = list(csv.DictReader((rec / "map.csv").open()))
    a, b = (next(r for r in rows if r["id"] == k) for k in ("35581", "40418"))
    a["id"], b["id"] = b["id"], a["id"]
    with (rec / "map.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    assert main(["eval", "--walks", str(rec), "--modes", "full", "-o", str(tmp_path / "o"), "--quiet"]) == 0
    (row,) = rows_of(tmp_path / "o")
    swapped = row["fixes_by_source"]
    assert row["fixes"] > 10 and row["wrong_id_fixes"] == sum(swapped.values()) == row["fixes"], row
    assert row["rmse_m"] > 1.0


def _log(fixes: list[dict]) -> RunLog:
    z = np.zeros(0)
    return RunLog(z, np.zeros((0, 3)), np.zeros((0, 3, 3)), z.astype(bool), fixes, [], {}, z, z, z)


def test_wrong_id_by_pose_counts_a_fix_none_of_whose_poses_is_near_the_truth():
    stamps = np.array([0.0, 1.0])
    T = np.repeat(np.eye(4)[None], 2, axis=0)
    T[1, 0, 3] = 1.0  # walking along x at 1 m/s
    fixes = [
        {"t": 0.5, "bodies": [[0.52, 0.01, 0.0]]},  # 2 cm off: right
        {"t": 0.5, "bodies": [[2.0, 0.0, 0.0]]},  # 1.5 m off: the sticker next along
        {"t": 0.5, "bodies": [[2.0, 0.0, 0.0], [0.5, 0.03, 0.0]]},  # IPPE's other solution is right
        {"t": 3.0, "bodies": [[9.0, 9.0, 0.0]]},  # outside the ground truth's span: not judged
        {"t": 0.5, "bodies": []},
    ]
    assert wrong_id_fixes_by_pose(_log(fixes), (stamps, T), 0.5) == 1
    assert wrong_id_fixes_by_pose(_log(fixes), (stamps, T), 2.0) == 0


def test_sessions_are_found_below_a_directory_and_named_apart(tmp_path):
    a = recorded_copy(tmp_path / "eval" / "field" / "sessions" / "s00")
    b = recorded_copy(tmp_path / "eval" / "standard" / "sessions" / "s00")
    (tmp_path / "eval" / "notes").mkdir()
    found = find_sessions([tmp_path / "eval"])
    assert found == [a, b]
    assert walk_names(found) == ["field/sessions/s00", "standard/sessions/s00"]
    assert walk_names([a, WALK]) == ["s00", "walk2s"]


@pytest.mark.parametrize(
    ("make", "fragment"),
    [
        (lambda p: p / "missing", "no such directory"),
        (lambda p: (p / "empty").mkdir() or p / "empty", "neither a session"),
        (lambda p: (p / "f.txt").write_text("x") and p / "f.txt", "not a directory"),
    ],
)
def test_a_path_without_sessions_is_refused(tmp_path, make, fragment):
    with pytest.raises(InputError, match=fragment):
        find_sessions([make(tmp_path)])


def test_walks_without_ground_truth_or_with_the_report_inside_are_refused_before_work(tmp_path, capsys):
    rec = recorded_copy(tmp_path / "w")
    cases = [
        (["--walks", str(rec), str(rec)], "named twice"),
        (["--walks", str(rec), "-o", str(rec / "report")], "inside the session"),
        (["--walks", str(rec), "--preset", "field"], "--preset does not apply"),
        (["--walks", str(rec), "--seed", "2", "--scale", "0.5"], "--seed, --scale do not apply"),
    ]
    for extra, fragment in cases:
        assert main(["eval", *extra, "--modes", "full", "--quiet"]) == 2
        err = capsys.readouterr().err
        assert fragment in err and len(err.strip().splitlines()) == 1, err
    (rec / "groundtruth.tum").unlink()
    assert main(["eval", "--walks", str(rec), "--modes", "full", "-o", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "no groundtruth.tum" in err and str(rec) in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("edit", "line", "fragment"),
    [
        (lambda lines: lines[:-1] + [lines[-1][:-200]], -1, "not a JSON object"),  # a write cut short
        (lambda lines: lines[:2] + [lines[2].replace('"index": 2,', '"index": "2",')] + lines[3:], 3, "'index'"),
        (
            lambda lines: lines[:4] + [lines[4].replace('"corners": [[', '"corners": [[NaN, 1], [', 1)] + lines[5:],
            5,
            "'corners'",
        ),
    ],
)
def test_a_malformed_per_frame_truth_is_refused_before_work(tmp_path, capsys, edit, line, fragment):
    """groundtruth_frames.jsonl (another simulator's, say) was read only after the walk's localisation,
    and a bad line stopped eval with an internal error naming neither file nor line."""
    walk = tmp_path / "w"
    shutil.copytree(WALK, walk, ignore=shutil.ignore_patterns("*.npz"))
    lines = (walk / GROUNDTRUTH_FRAMES).read_text().splitlines()
    assert '"index": 2,' in lines[2] and '"corners": [[' in lines[4]
    (walk / GROUNDTRUTH_FRAMES).write_text("\n".join(edit(lines)) + "\n")
    n = line if line > 0 else len(lines)
    assert main(["eval", "--walks", str(walk), "--modes", "full", "-o", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"{walk / GROUNDTRUTH_FRAMES}:{n}: " in err and fragment in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "o").exists()


def test_ground_truth_that_covers_no_frame_is_refused_and_a_plot_survives_it(tmp_path, capsys):
    """A ground truth from another clock (1000 s later) cannot score the walk: refused in one line
    before any work. Scored anyway (a preset's own path), the row has no error and the plot no error
    panel, rather than an internal error."""
    from tagloc.eval.evaluate import plot_run, score_session

    rec = recorded_copy(tmp_path / "late")
    lines = (rec / "groundtruth.tum").read_text().splitlines()
    shifted = [
        ln if ln.startswith("#") else " ".join([f"{float(ln.split()[0]) + 1000:.6f}", *ln.split()[1:]]) for ln in lines
    ]
    (rec / "groundtruth.tum").write_text("\n".join(shifted) + "\n")
    assert main(["eval", "--walks", str(rec), "--modes", "full", "-o", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "does not cover any frame" in err and len(err.strip().splitlines()) == 1, err
    row, session, log, gt = score_session(rec, "full", progress=False)
    assert row["frames"] == 0 and np.isnan(row["rmse_m"])
    png = plot_run(session, log, gt, tmp_path / "late.png")
    assert png is not None and png.stat().st_size > 0


def test_pooling_weights_by_frame_and_a_walk_with_nothing_scored_does_not_blank_it():
    """Found by a review: one walk without a scored frame had made the pooled RMSE, heading and NEES
    NaN, and coverage was a plain mean of walks (a 90 s walk counting as a 20 s one)."""
    import math

    from tagloc.eval.evaluate import summarise
    from tagloc.eval.metrics import frames_in_span

    def row(frames, rmse, coverage, frames_run):
        nan = math.nan
        return {
            "mode": "full",
            "frames": frames,
            "rmse_m": rmse if frames else nan,
            "within_10cm": 1.0 if frames else nan,
            "within_25cm": 1.0 if frames else nan,
            "heading_rmse_deg": 0.5 if frames else nan,
            "nees_mean": 2.0 if frames else nan,
            "nees_blocks": [[frames, 2.0 * frames, 8.0 * frames]] if frames else [],
            "wrong_id_fixes": 0,
            "fixes": 1,
            "rejected_fixes": 0,
            "coverage": coverage,
            "frames_run": frames_run,
            "frames_all": frames_run,
            "within_10cm_all": coverage,
            "by_time_since_fix": [[0, 0.0, 0.0]],
            **{k: 1.0 for k in ("tracker_ms_median", "tracker_ms_p95", "odometry_ms_median")},
            **{k: 1.0 for k in ("tracking_ms_median", "tracking_ms_p95", "frame_ms_median")},
        }

    rows = [row(2700, 0.03, 1.0, 2700), row(600, 0.01, 1.0, 600), row(0, 0.0, 0.0, 600)]
    s = summarise(rows)["full"]
    assert s["rmse_m"] == pytest.approx(math.sqrt((2700 * 0.03**2 + 600 * 0.01**2) / 3300))
    assert s["heading_rmse_deg"] == pytest.approx(0.5) and s["nees_mean"] == pytest.approx(2.0)
    assert s["coverage"] == pytest.approx(3300 / 3900)  # by frame, not (1 + 1 + 0) / 3
    # A jittered last frame just past the ground truth's end is no miss: it is not counted at all.
    assert frames_in_span(np.array([0.0, 0.5, 1.0, 1.0003]), np.array([0.0, 1.0])) == 3


def test_a_walk_none_of_whose_frames_could_be_read_is_refused(tmp_path, capsys):
    """Found by a review: a walk whose every image was unreadable was scored as a walk the localiser
    never placed (a row of NaN, a RuntimeWarning, exit 0); tagloc replay refuses such a run."""
    walk = recorded_copy(tmp_path / "w")
    for jpg in (walk / "frames").glob("*.jpg"):
        jpg.write_bytes(b"not a jpeg")
    assert main(["eval", "--walks", str(walk), "--modes", "full", "-o", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "none of its" in err and str(walk) in err and len(err.strip().splitlines()) == 1, err


def test_a_mode_that_never_placed_the_walker_reports_no_figures_without_a_warning(recwarn):
    """Found by a review: a walk the localiser never placed (frames readable, no pose) made the
    summary warn "All-NaN axis encountered" on stderr, print "nan%" in the pooled row beside the
    walk's 0%, and state NEES bounds "[none: one block] for the 0 independent samples"."""
    import math

    from tagloc.eval.evaluate import format_notes, format_summary, format_table, summarise

    nan = math.nan
    row = {
        "session": "w",
        "conditions": "site walk",
        "mode": "full",
        "frames": 0,
        "outside_gt": 0,
        **dict.fromkeys(["rmse_m", "median_m", "p95_m", "max_m", "heading_rmse_deg", "nees_mean"], nan),
        "within_10cm": 0.0,
        "within_25cm": 0.0,
        "nees_blocks": [],
        "wrong_id_fixes": 0,
        "fixes": 0,
        "fixes_by_source": {},
        "rejected_fixes": 0,
        "coverage": 0.0,
        "frames_run": 120,
        "frames_all": 120,
        "within_10cm_all": 0.0,
        "frames_before_sticker": None,
        **dict.fromkeys(["frame_ms_median", "tracker_ms_median", "tracker_ms_p95", "odometry_ms_median"], 1.0),
        **dict.fromkeys(["tracking_ms_median", "tracking_ms_p95"], 1.0),
        "by_time_since_fix": [[0, 0.0, 0.0]] * 7,
    }
    summary = summarise([row])
    assert math.isnan(summary["full"]["worst_rmse_m"]) and summary["full"]["within_10cm_all"] == 0.0
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]
    table, notes = format_table([row], summary), format_notes(summary)
    assert "nan%" not in table and "| **all** | full | | **nan** | | | | nan | - | - |" in table, table
    assert "no frame with a pose" in notes and "0 independent samples" not in notes, notes
    assert "| nan | - | no data |" in format_summary("1 walk", summary)


def test_a_simulated_walks_row_names_the_field_conditions_it_was_rendered_with(tmp_path, capsys):
    """Found by a review: a walk rendered with --rolling-shutter --jitter-ms 2 --drop-fraction 0.04
    --survey-sigma-cm 1.5 --survey-sigma-deg 1.5 had the conditions of a clear-weather one in its row
    (the session's notes: seconds, lux, speed and seed only)."""
    walk = tmp_path / "field"
    shutil.copytree(WALK, walk, ignore=shutil.ignore_patterns("*.npz"))
    info = json.loads((walk / "session.json").read_text())
    info["simulation"]["config"] |= {
        "rolling_shutter": True,
        "timing": {"jitter_s": 0.002, "drop_fraction": 0.04, "bursts_per_min": 2.0},
        "survey": {"sigma_m": 0.015, "sigma_deg": 1.5, "stated": False},
        "missing_fraction": 0.1,
        "unmapped": 20,
        "sensor_preset": "ov5647",
    }
    (walk / "session.json").write_text(json.dumps(info))
    assert main(["eval", "--walks", str(WALK), str(walk), "--modes", "full", "-o", str(tmp_path / "o"), "--quiet"]) == 0
    plain, field = (r["conditions"] for r in rows_of(tmp_path / "o"))
    assert plain == "tagloc simulate: 2 s at 120 lux, 1.3 m/s, seed 4"
    assert field == (
        "tagloc simulate: 2 s at 120 lux, 1.3 m/s, seed 4, rolling shutter, jitter +-2 ms, drops 4% + 2 bursts/min,"
        " survey 1.5 cm 1.5 deg, 10% missing, 20 unmapped, sensor ov5647"
    )
    assert field in capsys.readouterr().out
    # Today's simulator names them in the notes itself: each is named once.
    from tagloc.eval.walks import session_conditions

    notes = "tagloc simulate: 2 s at 120 lux, 1.3 m/s, seed 4, rolling shutter 30 ms, jitter +-2 ms, sensor ov5647"
    both = session_conditions(notes, info)
    assert both.startswith(notes) and both.count("rolling shutter") == both.count("jitter") == 1
    assert both.endswith("drops 4% + 2 bursts/min, survey 1.5 cm 1.5 deg, 10% missing, 20 unmapped")


def test_a_frame_the_localiser_skipped_counts_as_a_frame_without_a_pose(tmp_path):
    """Found by a review: a frame that could not be read kept the filter's prediction in the run's
    log, and eval scored it as a pose of that frame (covered, within 10 cm), though a replay does not
    publish it: with 10 of a walk's frames corrupt, coverage and the share within 10 cm of all frames
    both read 100 %."""
    walk = recorded_copy(tmp_path / "w")
    jpgs = sorted((walk / "frames").glob("*.jpg"))
    for jpg in jpgs[30:40]:
        jpg.write_bytes(b"not a jpeg")
    assert main(["eval", "--walks", str(walk), "--modes", "full", "-o", str(tmp_path / "o"), "--quiet"]) == 0
    (row,) = rows_of(tmp_path / "o")
    n = len(jpgs)
    assert row["counts"]["skipped_frames"] == 10 and row["frames_run"] == row["frames_all"] == n
    assert row["coverage"] == pytest.approx((n - 10) / n, abs=1e-9)
    assert row["frames"] == n - 10 and row["within_10cm_all"] == pytest.approx((n - 10) / n, abs=1e-9)


def test_each_walks_row_gives_its_nees_bounds_and_verdict(tmp_path, capsys):
    """Found by a review: a walk's row gave its mean NEES alone, so whether a walk was overconfident
    by its own effective-sample bounds (the README's "no walk overconfident") could not be read from
    tagloc eval's output. The bundled 2 s walk is one 5 s block: too short to judge."""
    from tagloc.eval.evaluate import format_table, summarise

    assert main(["eval", "--walks", str(WALK), "--modes", "full", "-o", str(tmp_path / "o"), "--quiet"]) == 0
    (row,) = rows_of(tmp_path / "o")
    assert row["nees_verdict"] == "too short"
    assert f"| {row['nees_mean']:.2f} (one 5 s block: too short) |" in capsys.readouterr().out
    # A walk of three blocks whose errors are twice what it states: overconfident by its own bounds.
    row |= {
        "nees_blocks": [[150, 600.0, 3000.0], [150, 570.0, 2800.0], [150, 630.0, 3200.0]],
        "nees_mean": 4.0,
        "nees_bounds_95_effective": [1.5, 2.6],
        "nees_verdict": "overconfident",
        "beyond_999": 0.05,
    }
    table = format_table([row], summarise([row]))
    # With the share of its frames beyond chi-square's 99.9 % point (0.1 % if consistent).
    assert "| 4.00 [1.50, 2.60] overconfident, 5.0% beyond 99.9% |" in table, table


def test_results_json_is_standard_json_with_null_for_figures_it_cannot_give(tmp_path):
    """Found by a review: results.json held Python's NaN token (a walk too short for NEES bounds,
    one with nothing scored), which strict JSON parsers (JavaScript's JSON.parse, serde_json) refuse."""

    def refuse(token):
        raise ValueError(f"not JSON: {token}")

    assert main(["eval", "--walks", str(WALK), "--modes", "full", "-o", str(tmp_path / "o"), "--quiet"]) == 0
    doc = json.loads((tmp_path / "o" / "results.json").read_text(), parse_constant=refuse)
    assert doc["summary"]["full"]["nees_verdict"] == "too short"
    assert doc["summary"]["full"]["nees_bounds_95_effective"] == [None, None]
    assert 0 < doc["rows"][0]["rmse_m"] < 0.03


def test_the_two_camera_and_variant_scoring_leaves_skipped_frames_out_too(tmp_path):
    """multicam.score_run (the two-camera preset, benchmarks/eval_variants.py) scored a skipped
    frame's prediction as a pose, as eval's rows did."""
    from tagloc.eval.multicam import score_run
    from tagloc.io.session import SessionReader
    from tagloc.pipeline.run import run_session

    walk = recorded_copy(tmp_path / "w")
    jpgs = sorted((walk / "frames").glob("*.jpg"))
    for jpg in jpgs[30:40]:
        jpg.write_bytes(b"not a jpeg")
    session = SessionReader(walk)
    log = run_session(session)
    assert log.skipped == 10 and log.valid.sum() == len(jpgs) - 10
    assert score_run(session, log)["coverage"] == pytest.approx((len(jpgs) - 10) / len(jpgs), abs=1e-9)
