"""Identification of undecodable stickers against tracker candidates, and the reference bank cache.

Views come from tests/synth.py (an independent renderer: 8x8 super-sampling, linear light, gamma),
not from the generator the thresholds were tuned on (tagloc.eval.bench_identify), so these tests also
check that the thresholds carry over.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from synth import concrete, sticker_pose, synth_frame  # noqa: E402

from tagloc.cli import main as cli_main  # noqa: E402
from tagloc.core.camera import default_camera  # noqa: E402
from tagloc.core.errors import InputError  # noqa: E402
from tagloc.core.stickermap import load_map  # noqa: E402
from tagloc.core.types import Detection, IdSource  # noqa: E402
from tagloc.vision.identify import IdResult, identify  # noqa: E402
from tagloc.vision.psf import motion_kernel  # noqa: E402
from tagloc.vision.refs import build_refs, default_cache_path, load_or_build_refs, load_refs  # noqa: E402

CAM = default_camera()
# Consecutive IDs, as maps number them: neighbours share leading digits and Data Matrix codewords.
IDS = list(range(31200, 31240))


@pytest.fixture(scope="module")
def bank():
    return build_refs(IDS, progress=False)


@pytest.fixture(scope="module")
def floor():
    return concrete((CAM.height, CAM.width), seed=3)


def view(sid: int, rotation: int, tilt_deg: float, blur_px: float, seed: int, floor: np.ndarray):
    """A frame with one sticker ~85 px across and the detection a detector would hand over."""
    rng = np.random.default_rng(seed)
    centre = (rng.uniform(350, 950), rng.uniform(280, 700))
    dist = CAM.fx * 0.1 / 85 * np.sqrt(np.cos(np.radians(tilt_deg)))
    T = sticker_pose(CAM, centre, dist, tilt_deg, yaw_deg=rng.uniform(0, 360), tilt_dir_deg=rng.uniform(0, 360))
    f = synth_frame(
        [(sid, T)],
        CAM,
        blur_px=blur_px,
        blur_angle_deg=rng.uniform(0, 180),
        noise=2.5,
        gamma=2.2,
        exposure=rng.uniform(0.7, 1.0),
        background=floor,
        seed=seed,
    )
    sigma = 0.5 + 0.1 * blur_px  # blurred edges are located less well
    # synth gives canonical order (TL first); a detector may start at any corner: rotation r.
    outer = np.roll(f.outer[0], rotation, 0) + rng.normal(0, sigma, (4, 2))
    inner = np.roll(f.inner[0], rotation, 0) + rng.normal(0, sigma, (4, 2))
    return f.image, Detection(outer, inner)


def neighbours(sid: int, n: int, rng: np.random.Generator) -> list[int]:
    near = [i for i in IDS if i != sid and abs(i - sid) <= 10]
    return [int(i) for i in rng.choice(near, n, replace=False)]


def run_views(bank, floor, method: str, blur_px: float, present: bool, k: int = 5, seed: int = 0):
    """Identify 12 views (rotations 0-3 x tilts 20/45/70 deg); returns (right, wrong, results)."""
    rng = np.random.default_rng(seed)
    right = wrong = 0
    results = []
    for i, (r, tilt) in enumerate([(r, t) for r in range(4) for t in (20, 45, 70)]):
        sid = int(rng.choice(IDS))
        img, det = view(sid, r, tilt, blur_px, seed * 100 + i, floor)
        cands = neighbours(sid, k - 1 if present else k, rng)
        if present:
            cands.insert(int(rng.integers(k)), sid)
        res = identify(img, det, CAM, cands, bank, method=method)
        results.append(res)
        if res.sticker_id is not None:
            if res.sticker_id == sid and res.rotation == r:
                right += 1
            else:
                wrong += 1
    return right, wrong, results


@pytest.mark.parametrize("blur_px, at_least", [(0, 12), (4, 11), (8, 9)])
def test_appearance_names_the_right_sticker_and_rotation(bank, floor, blur_px, at_least):
    right, wrong, results = run_views(bank, floor, "appearance", blur_px, present=True, seed=int(blur_px) + 1)
    assert wrong == 0
    assert right >= at_least
    named = [r for r in results if r.sticker_id is not None]
    assert all(r.source is IdSource.APPEARANCE and r.score >= 0.5 and r.margin > 0.2 for r in named)


@pytest.mark.parametrize("blur_px, at_least", [(0, 12), (2, 10)])
def test_orb_names_the_right_sticker_and_rotation(bank, floor, blur_px, at_least):
    right, wrong, results = run_views(bank, floor, "orb", blur_px, present=True, seed=int(blur_px) + 11)
    assert wrong == 0
    assert right >= at_least
    assert all(r.source is IdSource.ORB for r in results if r.sticker_id is not None)


def test_auto_is_appearance(bank, floor):
    right, wrong, results = run_views(bank, floor, "auto", 4, present=True, seed=21)
    assert wrong == 0 and right >= 11
    assert {r.source for r in results if r.sticker_id is not None} == {IdSource.APPEARANCE}


@pytest.mark.parametrize("method", ["appearance", "orb"])
@pytest.mark.parametrize("blur_px", [0, 4, 8])
def test_refuses_when_the_true_sticker_is_not_a_candidate(bank, floor, method, blur_px):
    right, wrong, results = run_views(bank, floor, method, blur_px, present=False, seed=int(blur_px) + 31)
    assert right == 0 and wrong == 0
    assert all(r.sticker_id is None and r.rotation is None and r.source is IdSource.NONE for r in results)


def test_refuses_a_single_wrong_candidate(bank, floor):
    for i in range(8):
        sid = IDS[5 + i]
        img, det = view(sid, i % 4, 20 + 7 * i, [0, 2, 4, 8][i % 4], 500 + i, floor)
        for method in ("appearance", "orb"):
            res = identify(img, det, CAM, [sid + 1], bank, method=method)
            assert res.sticker_id is None, (method, i, res)
            assert res.runner_up is None
        # The same view with the right single candidate is named (ID, rotation).
        res = identify(img, det, CAM, [sid], bank)
        if i % 4 < 3:  # up to 4 px blur: always; 8 px may refuse but never be wrong
            assert (res.sticker_id, res.rotation) == (sid, i % 4)
        assert res.sticker_id in (None, sid)


def test_result_fields_and_margin_is_against_everything_else(bank, floor):
    sid = IDS[10]
    img, det = view(sid, 2, 35, 0, 77, floor)
    cands = [IDS[11], sid, IDS[9]]
    res = identify(img, det, CAM, cands, bank)
    assert isinstance(res, IdResult)
    assert (res.sticker_id, res.rotation, res.source) == (sid, 2, IdSource.APPEARANCE)
    assert res.runner_up in (IDS[11], IDS[9])
    assert 0.6 < res.score <= 1.0 and 0.3 < res.margin < res.score
    # Duplicated candidates do not create a zero margin against themselves.
    once = identify(img, det, CAM, [sid, IDS[9]], bank)
    again = identify(img, det, CAM, [sid, sid, IDS[9]], bank)
    assert again.sticker_id == sid and again.margin == pytest.approx(once.margin, abs=1e-9)
    assert once.margin >= res.margin - 1e-9  # fewer others to beat
    # A candidate missing from the bank is rendered on the fly.
    small = build_refs([IDS[11]], progress=False)
    res2 = identify(img, det, CAM, [sid, IDS[11]], small)
    assert (res2.sticker_id, res2.rotation) == (sid, 2)
    res3 = identify(img, det, CAM, [sid, IDS[11]], small, method="orb")
    assert (res3.sticker_id, res3.rotation) == (sid, 2)
    # No candidates: nothing to say.
    assert identify(img, det, CAM, [], bank).sticker_id is None


def test_blur_estimate_and_motion_hint(bank, floor):
    sid = IDS[20]
    sharp_img, det0 = view(sid, 1, 30, 0, 91, floor)
    blurred_img, det8 = view(sid, 1, 30, 8, 91, floor)  # same seed: same pose, blur only
    sharp = identify(sharp_img, det0, CAM, [sid], bank)
    blurred = identify(blurred_img, det8, CAM, [sid], bank)
    # 8 image px on an ~85 px sticker is ~6 px in the 64 px raster (perspective varies it).
    assert np.hypot(*sharp.blur_px) <= 2.0
    assert 3.5 <= np.hypot(*blurred.blur_px) <= 10.0
    hinted = identify(blurred_img, det8, CAM, [sid, IDS[21]], bank, motion_hint=blurred.blur_px)
    assert hinted.sticker_id == sid and np.allclose(hinted.blur_px, blurred.blur_px)


def test_motion_kernel():
    k = motion_kernel(np.array([6.0, 0.0]))
    assert k.dtype == np.float32 and k.shape[0] % 2 == 1
    assert k.sum() == pytest.approx(1.0, abs=1e-6)
    rows = np.nonzero(k.sum(axis=1) > 0.01)[0]
    cols = np.nonzero(k.sum(axis=0) > 0.01)[0]
    assert len(rows) == 1 and 6 <= len(cols) <= 8  # a horizontal segment ~6 px long, no width
    diag = motion_kernel(np.array([4.0, 4.0]))
    assert np.allclose(diag, diag.T) and diag.sum() == pytest.approx(1.0, abs=1e-6)
    assert motion_kernel(np.zeros(2)).shape == (1, 1)


def test_bad_arguments(bank, floor):
    img, det = view(IDS[0], 0, 30, 0, 3, floor)
    with pytest.raises(InputError):
        identify(img, det, CAM, [IDS[0]], bank, method="sift")
    with pytest.raises(InputError):
        identify(img.astype(np.float32), det, CAM, [IDS[0]], bank)
    with pytest.raises(InputError):
        identify(img, det, CAM, [123456], bank)  # not a sticker ID


# ---------------------------------------------------------------- reference bank cache


def write_map(path: Path, ids: list[int]) -> None:
    rows = ["id,x_m,y_m,yaw_deg"] + [f"{sid},{1.5 * i:.3f},0.000,{(37 * i) % 360}" for i, sid in enumerate(ids)]
    path.write_text("\n".join(rows) + "\n")


def test_cache_round_trip_and_rebuild_on_map_change(tmp_path):
    m = tmp_path / "site.csv"
    write_map(m, [5, 6, 7, 8])
    bank = load_or_build_refs(m, progress=False)
    cache = default_cache_path(m)
    assert cache == tmp_path / "site.refs.npz" and cache.exists()
    assert list(bank.ids) == [5, 6, 7, 8] and len(bank.des) > 4 * 50
    # Plain arrays only.
    with np.load(cache, allow_pickle=False) as z:
        assert all(z[k].dtype != object for k in z.files)
    loaded = load_refs(cache)
    assert loaded.key == bank.key
    np.testing.assert_array_equal(loaded.des, bank.des)
    np.testing.assert_allclose(loaded.xy, bank.xy)
    np.testing.assert_allclose(loaded.mean_template, bank.mean_template)
    np.testing.assert_array_equal(loaded.orb_mask, bank.orb_mask)
    # Unchanged map: the cache is used, not rewritten.
    stamp = cache.stat().st_mtime_ns
    again = load_or_build_refs(m, progress=False)
    assert again.key == bank.key and cache.stat().st_mtime_ns == stamp
    # Same IDs, moved sticker: content changed, so the key changes and the bank is rebuilt.
    m.write_text(m.read_text().replace("1.500,0.000", "1.600,0.000"))
    moved = load_or_build_refs(m, progress=False)
    assert moved.key != bank.key and load_refs(cache).key == moved.key
    write_map(m, [5, 6, 9])
    changed = load_or_build_refs(m, progress=False)
    assert list(changed.ids) == [5, 6, 9]
    np.testing.assert_array_equal(changed.features(9)[1], build_refs([9], progress=False).features(9)[1])
    # A corrupt cache is replaced silently; a corrupt file given to load_refs is an InputError.
    cache.write_bytes(b"not a zip")
    with pytest.raises(InputError):
        load_refs(cache)
    assert list(load_or_build_refs(m, progress=False).ids) == [5, 6, 9]


def test_cli_builds_the_bank(tmp_path, capsys):
    m = tmp_path / "demo.csv"
    write_map(m, [100, 101, 102])
    assert cli_main(["refs", "build", str(m), "--quiet"]) == 0
    assert (tmp_path / "demo.refs.npz").exists()
    assert "3 stickers" in capsys.readouterr().out
    out = tmp_path / "other.npz"
    assert cli_main(["refs", "build", str(m), "--quiet", "--force", "-o", str(out)]) == 0
    assert list(load_refs(out).ids) == [100, 101, 102]
    bad = tmp_path / "bad.csv"
    bad.write_text("id,x_m,y_m,yaw_deg\n1,0,0,0\nx,1,1,1\n")
    assert cli_main(["refs", "build", str(bad), "--quiet"]) == 2
    assert "bad.csv" in capsys.readouterr().err


def test_a_bank_file_naming_the_map_is_refused_and_the_map_kept(tmp_path, capsys):
    """``refs build site.csv -o site.csv`` had written the bank over the map (exit 0), and every
    later run refused the map as not UTF-8 text."""
    m = tmp_path / "site.csv"
    write_map(m, [5, 6])
    before = m.read_bytes()
    assert cli_main(["refs", "build", str(m), "--quiet", "-o", str(m)]) == 2
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err == f"tagloc refs: error: {m}: is the map itself; the bank would overwrite it\n"
    assert m.read_bytes() == before
    with pytest.raises(InputError, match="is the map itself"):
        load_or_build_refs(m, progress=False, cache_path=tmp_path / "." / "site.csv")
    assert m.read_bytes() == before and load_map(m).ids.tolist() == [5, 6]


def test_an_asked_for_bank_file_that_cannot_be_written_is_an_error(tmp_path, capsys, monkeypatch):
    m = tmp_path / "site.csv"
    write_map(m, [5, 6])
    out = tmp_path / "no_dir" / "x.npz"
    assert cli_main(["refs", "build", str(m), "--quiet", "-o", str(out)]) == 2
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err == f"tagloc refs: error: {out}: cannot write (no directory {out.parent})\n"

    import tagloc.vision.refs as refs

    def full_disk(bank, path):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(refs, "save_refs", full_disk)
    # The cache beside the map is a convenience: not writing it costs a rebuild next time, no more.
    assert list(load_or_build_refs(m, progress=False).ids) == [5, 6]
    with pytest.raises(InputError) as info:
        load_or_build_refs(m, progress=False, cache_path=tmp_path / "x.npz")
    assert str(info.value) == f"{tmp_path / 'x.npz'}: cannot write (No space left on device)"


def test_degenerate_detection_is_refused(bank, floor):
    img, det = view(IDS[3], 0, 30, 0, 8, floor)
    flat = Detection(np.array([[100.0, 100.0], [200.0, 100.0], [300.0, 100.0], [150.0, 100.0]]))
    assert identify(img, flat, CAM, [IDS[3]], bank).sticker_id is None
    nan = Detection(det.outer.copy(), det.inner)
    nan.outer[1, 0] = np.nan
    assert identify(img, nan, CAM, [IDS[3]], bank).sticker_id is None
    assert identify(img, det, CAM, [IDS[3]], bank).sticker_id == IDS[3]


def test_orb_against_every_sticker_of_the_map(bank, floor):
    """The paper's baseline hands all map stickers as candidates: the global-match path."""
    for i, sid in enumerate(IDS[2:8]):
        img, det = view(sid, i % 4, 25 + 8 * i, 0, 900 + i, floor)
        res = identify(img, det, CAM, IDS, bank, method="orb")
        assert (res.sticker_id, res.rotation) == (sid, i % 4)
        missing = identify(img, det, CAM, [c for c in IDS if c != sid], bank, method="orb")
        assert missing.sticker_id is None


def test_identify_bench_command_reports_rates_and_thresholds():
    """``tagloc bench-identify`` on a few sharp views: every present sticker right, no wrong answer,
    and the right answers clear the thresholds while the wrong ones do not."""
    from tagloc.eval.bench_identify import identify_bench_command

    text = identify_bench_command(methods=("appearance",), blurs_px=(0.0,), trials=4, seed=1, progress=False)
    rates, thresholds = text.split("Thresholds")
    assert "| appearance | 0 | present | 4/4 | 0 | 0 |" in rates
    assert "| appearance | 0 | absent | 0/4 | 0 | 4 |" in rates
    row = next(line for line in thresholds.splitlines() if line.startswith("| appearance"))
    assert row.endswith("| 4/4 | 0/4 |")
