"""Map audit and refinement (tagloc/eval/mapaudit.py, maprefine.py) on short simulated walks.

The floor is one aisle of stickers 0.5 m apart: three 5 s walks (seeds 1-3) go up and down it, so
each sticker is passed several times. The audited map has survey errors (2 cm radial RMS, 2 deg),
one sticker moved by 15 cm, one sticker that is not on the floor (missing) and lacks one that is
(unmapped).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tagloc.cli import main
from tagloc.core.errors import InputError
from tagloc.core.stickermap import StickerMap, load_map, save_map
from tagloc.eval.mapaudit import AuditConfig, _hard, _Tally, audit_walks
from tagloc.eval.mapbench import map_errors, survey_error_map
from tagloc.eval.mapobs import collect_walk
from tagloc.eval.maprefine import RefineConfig, refine_map
from tagloc.sim.simulate import SimConfig, simulate_session

MISSING, UNMAPPED, MOVED = 1007, 1011, 1004
MOVE = (0.09, 0.12)  # 15 cm


def full_map() -> StickerMap:
    xs = np.arange(0.0, 7.01, 0.5)
    ids = np.arange(1000, 1000 + len(xs))
    yaw = np.radians(np.resize([0.0, 90.0, 35.0, 180.0, -60.0, 120.0], len(ids)))
    return StickerMap(ids, np.c_[xs, np.zeros_like(xs)], yaw)


def subset(smap: StickerMap, drop: int) -> StickerMap:
    keep = smap.ids != drop
    return StickerMap(smap.ids[keep], smap.xy[keep], smap.yaw[keep])


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("mapaudit")
    truth = full_map()
    floor = subset(truth, MISSING)
    sessions = []
    for seed in (1, 2, 3):
        path = root / f"walk{seed}"
        simulate_session(floor, path, SimConfig(seconds=5, lux=150, speed_mps=1.0, seed=seed), progress=False)
        sessions.append(path)
    survey = survey_error_map(subset(truth, UNMAPPED), 0.02, 2.0, seed=5, moved={MOVED: MOVE})
    save_map(survey, root / "survey.csv")
    survey = load_map(root / "survey.csv")
    walks = [collect_walk(s, survey) for s in sessions]
    return {"root": root, "truth": truth, "survey": survey, "sessions": sessions, "walks": walks}


def test_refine_recovers_surveyed_and_moved_stickers(site):
    truth, survey = site["truth"], site["survey"]
    res = refine_map(site["walks"], survey)
    seen = [c.sticker_id for c in res.changes]
    assert len(seen) >= 10
    plain = [i for i in seen if i != MOVED]
    before, _ = map_errors(survey, truth, plain)
    after, after_yaw = map_errors(res.refined, truth, plain)
    rms_before, rms_after = float(np.sqrt(np.mean(before**2))), float(np.sqrt(np.mean(after**2)))
    assert rms_before > 0.012  # the survey errors are really there
    assert rms_after < 0.5 * rms_before
    assert np.degrees(np.sqrt(np.mean(after_yaw**2))) < 0.6
    moved = [c for c in res.changes if c.moved]
    assert [c.sticker_id for c in moved] == [MOVED]
    err_moved, _ = map_errors(res.refined, truth, [MOVED])
    assert err_moved[0] < 0.015
    surveyed_off, _ = map_errors(survey, truth, [MOVED])  # the 15 cm move plus its survey error
    assert moved[0].offset_m == pytest.approx(surveyed_off[0], abs=0.015)
    print(
        f"seen {len(seen)}: RMS {rms_before * 100:.2f} -> {rms_after * 100:.2f} cm; moved sticker {err_moved[0] * 100:.2f} cm"
    )
    # Stickers not refined are left exactly as they were, sigma columns included.
    rows = [survey.row(int(i)) for i in survey.ids if int(i) not in seen]
    assert np.array_equal(res.refined.xy[rows], survey.xy[rows])
    assert np.array_equal(res.refined.sigma_xy[rows], survey.sigma_xy[rows], equal_nan=True)
    # Refined stickers state a sigma, smaller than the survey's, and it is not overconfident.
    rows = [survey.row(i) for i in plain]
    assert np.all(res.refined.sigma_xy[rows] < survey.sigma_xy[rows])
    assert rms_after < 3 * float(np.sqrt(np.mean(res.refined.sigma_xy[rows] ** 2 * 2)))


def test_audit_finds_missing_unmapped_and_misplaced(site):
    res = audit_walks(site["walks"], site["survey"])
    truth = site["truth"]
    assert [f.sticker_id for f in res.of("missing")] == [MISSING]
    assert res.of("missing")[0].passes >= 2
    unmapped = res.of("unmapped")
    assert [f.sticker_id for f in unmapped] == [UNMAPPED]
    u = unmapped[0]
    true_xy = truth.xy[truth.row(UNMAPPED)]
    assert math.hypot(u.x - true_xy[0], u.y - true_xy[1]) < 0.06
    assert math.hypot(u.x - true_xy[0], u.y - true_xy[1]) < 3 * math.sqrt(2) * u.sigma_m
    assert [f.sticker_id for f in res.of("misplaced")] == [MOVED]
    assert res.of("hard") == []


def test_hard_to_read_is_relative_to_the_other_stickers():
    smap = StickerMap(np.array([1, 2, 3, 4]), np.array([[0, 0], [1, 0], [2, 0], [3, 0]]), np.zeros(4))
    tally = {1: _Tally(detected=40, decoded=36), 2: _Tally(detected=30, decoded=25), 3: _Tally(detected=50, decoded=4)}
    tally[4] = _Tally(detected=3, decoded=0)  # too few detections to judge
    hard = _hard(tally, smap, AuditConfig())
    assert [f.sticker_id for f in hard] == [3]
    # When every sticker reads badly (dark, blurred walks), none is singled out.
    tally = {k: _Tally(detected=40, decoded=4 + k) for k in (1, 2, 3)}
    assert _hard(tally, smap, AuditConfig()) == []


def test_cli_audit_and_refine_write_their_files(site, tmp_path, capsys):
    sessions = [str(p) for p in site["sessions"]]
    survey = str(site["root"] / "survey.csv")
    assert main(["map", "audit", *sessions, "--map", survey, "-o", str(tmp_path / "audit"), "--quiet"]) == 0
    for name in ("report.md", "floorplan.png", "audit.json", "unmapped.csv"):
        assert (tmp_path / "audit" / name).exists()
    added = load_map(tmp_path / "audit" / "unmapped.csv")
    assert list(added.ids) == [UNMAPPED] and np.isfinite(added.sigma_xy).all()
    out = tmp_path / "refined.csv"
    assert main(["map", "refine", *sessions, "--map", survey, "-o", str(out), "--quiet"]) == 0
    refined = load_map(out)
    assert list(refined.ids) == list(site["survey"].ids)
    assert str(MOVED) in (tmp_path / "refined.md").read_text()
    assert "1 moved" in capsys.readouterr().out


def test_bad_input_is_one_line(tmp_path, capsys):
    assert main(["map", "refine", str(tmp_path / "nope"), "--map", str(tmp_path / "m.csv"), "-o", "x.csv"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "m.csv" in err[0]
    with pytest.raises(InputError):
        RefineConfig(default_sigma_m=0.0)


def test_sightings_keep_unmapped_reads_with_their_pose(site):
    reads = [s for w in site["walks"] for fr in w.frames for s in fr.sightings if s.sticker_id == UNMAPPED]
    assert reads
    assert all(not s.in_map and s.decoded for s in reads)
    assert all(s.T_camera_sticker is not None for s in reads)
