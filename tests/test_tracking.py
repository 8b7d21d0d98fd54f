"""Sticker tracking: a decoded sticker's identity carried to the next frame without decoding it again."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tagloc.core.types import Detection, Identity, IdSource
from tagloc.pipeline.localiser import LocaliserConfig, Tracked, TrackingConfig, match_tracked, match_tracks

CFG = TrackingConfig()
SQUARE = np.array([[100.0, 100.0], [160.0, 100.0], [160.0, 160.0], [100.0, 160.0]])  # clockwise, y down


def only(sid):
    """The tracker's candidates for any detection: just ``sid``."""
    return lambda det: [sid]


def _tracked(outer=SQUARE, sid=7, rotation=1, age=0, t=0.0, camera=0) -> Tracked:
    return Tracked(outer, Identity(sid, rotation, IdSource.DECODED), camera, t, age)


def test_a_sticker_that_moved_keeps_its_identity_and_rotation():
    moved = Detection(SQUARE + [30.0, -25.0])  # half a side: a brisk step at 30 fps
    (ident,) = match_tracked([moved], [_tracked()], 0, 1 / 30, CFG, only(7))
    assert ident is not None and ident.sticker_id == 7 and ident.rotation == 1 and ident.source is IdSource.DECODED


@pytest.mark.parametrize("shift", [1, 2, 3])
def test_rotation_follows_the_canonical_corner_when_the_corner_order_starts_elsewhere(shift):
    # The detector starts its clockwise corners at the top-left-most one, which changes as the
    # sticker turns in the image: the canonical corner (outer[1] before) must stay the same point.
    cur = np.roll(SQUARE, shift, axis=0)  # cur[(j + shift) % 4] == SQUARE[j]
    (ident,) = match_tracked([Detection(cur + 20.0)], [_tracked()], 0, 1 / 30, CFG, only(7))
    assert ident is not None
    np.testing.assert_allclose(cur[ident.rotation], SQUARE[1])


def test_a_detection_far_from_or_unlike_the_tracked_sticker_is_decoded():
    far = Detection(SQUARE + [1.2 * 60, 0.0])  # beyond a side away
    assert match_tracked([far], [_tracked()], 0, 1 / 30, CFG, only(7)) == [None]
    bigger = Detection((SQUARE - SQUARE.mean(0)) * 1.5 + SQUARE.mean(0))  # not the same sticker's image
    assert match_tracked([bigger], [_tracked()], 0, 1 / 30, CFG, only(7)) == [None]


def test_the_prediction_must_find_that_sticker_the_most_likely_here():
    det = [Detection(SQUARE + 5.0)]
    # A neighbour inside the gate too (a dense floor, a wide covariance): the tracked one still leads.
    assert match_tracked(det, [_tracked()], 0, 1 / 30, CFG, lambda d: [7, 9])[0] is not None
    assert match_tracked(det, [_tracked()], 0, 1 / 30, CFG, lambda d: [9, 7]) == [None]  # 9 is likelier here
    assert match_tracked(det, [_tracked()], 0, 1 / 30, CFG, lambda d: [9]) == [None]  # 7 is not predicted here
    assert match_tracked(det, [_tracked()], 0, 1 / 30, CFG, lambda d: []) == [None]  # tracker not tracking
    assert match_tracked(det, [_tracked()], 0, 1 / 30, CFG, only(7))[0] is not None


def test_the_predicted_image_motion_carries_a_sticker_through_a_fast_turn():
    # Turning at 1.5 rad/s sweeps the image by ~60 px a frame: 1.5 sides of this 60 px sticker.
    det = [Detection(SQUARE + [90.0, 4.0])]
    assert match_tracked(det, [_tracked()], 0, 1 / 30, CFG, only(7)) == [None]  # too far for the bare gate
    (ident,) = match_tracked(det, [_tracked()], 0, 1 / 30, CFG, only(7), lambda tr: np.array([88.0, 0.0]))
    assert ident is not None and ident.sticker_id == 7 and ident.rotation == 1
    # A prediction that moved elsewhere, or none at all, carries nothing.
    assert match_tracked(det, [_tracked()], 0, 1 / 30, CFG, only(7), lambda tr: np.array([-88.0, 0.0])) == [None]
    assert match_tracked(det, [_tracked()], 0, 1 / 30, CFG, only(7), lambda tr: None) == [None]


def test_stale_other_camera_or_due_tracks_are_not_carried():
    det = [Detection(SQUARE + 1.0)]
    assert match_tracked(det, [_tracked(t=0.0)], 0, 0.2, CFG, only(7)) == [None]  # a gap of dropped frames
    assert match_tracked(det, [_tracked(camera=1)], 0, 1 / 30, CFG, only(7)) == [None]
    assert match_tracked(det, [_tracked(age=CFG.redecode_every - 1)], 0, 1 / 30, CFG, only(7)) == [None]
    assert match_tracked(det, [_tracked(age=CFG.redecode_every - 2)], 0, 1 / 30, CFG, only(7))[0] is not None


@pytest.mark.parametrize(("t0", "t1"), [("0.3", "0.4"), ("1000000.2", "1000000.3"), ("1800000000.1", "1800000000.2")])
def test_a_track_one_max_gap_back_is_carried_whatever_the_clocks_origin(t0, t1):
    # At 10 fps the previous frame is max_gap_s (0.1 s) back. Read from frames.csv, the difference of
    # two such stamps is 0.1 s give or take the floats' rounding, which depends on where the clock
    # started: of 60 frames at 10 fps, 32 on a clock from 0, 12 from 1e6 s and 24 from 1.8e9 s were
    # more than 0.1 s apart, their tracks not carried, so one walk decoded differently on each clock.
    det = [Detection(SQUARE + 1.0)]
    (ident,) = match_tracked(det, [_tracked(t=float(t0))], 0, float(t1), CFG, only(7))
    assert ident is not None and ident.sticker_id == 7
    assert match_tracked(det, [_tracked(t=float(t0))], 0, float(t1) + 3e-6, CFG, only(7)) == [None]  # longer: not


def test_a_track_due_for_re_decoding_is_matched_as_due():
    det = [Detection(np.roll(SQUARE, 1, axis=0) + 1.0)]
    (m,) = match_tracks(det, [_tracked(age=CFG.redecode_every - 1)], 0, 1 / 30, CFG, only(7))
    assert m is not None and m.due and m.identity.sticker_id == 7 and m.identity.rotation == 2
    (m,) = match_tracks(det, [_tracked(age=CFG.redecode_every - 2)], 0, 1 / 30, CFG, only(7))
    assert m is not None and not m.due
    assert match_tracks(det, [_tracked(age=CFG.redecode_every - 1)], 0, 1 / 30, CFG, only(9)) == [None]


def test_ambiguous_matches_carry_nothing():
    # Two tracked stickers on the same spot (cannot tell which) and two detections on one tracked one.
    two = [_tracked(sid=7), _tracked(outer=SQUARE + 2.0, sid=8)]
    assert match_tracked([Detection(SQUARE + 1.0)], two, 0, 1 / 30, CFG, only(7)) == [None]
    dets = [Detection(SQUARE + 1.0), Detection(SQUARE - 1.0)]
    assert match_tracked(dets, [_tracked()], 0, 1 / 30, CFG, only(7)) == [None, None]


def test_a_missed_sticker_does_not_pass_its_name_to_the_sticker_beside_it():
    """Tracked sticker A is missed this frame; U, seen beside it in the previous frame but not named,
    is now where A is predicted (within a side): U could be either, so it is decoded, not named A.
    Without U's previous sight (nothing to compete) the carry stands, as before."""
    a_prev = SQUARE + [400.0, 200.0]
    u_prev = a_prev + [61.0, 0.0]  # a sticker laid next to A (1.02 sides to its right)
    u_now = u_prev + [-3.0, 0.0]
    # The tracker predicts A's image 3 px to the right; U's sight ends up 55 px (0.92 sides) from A's.
    motion = lambda tr: np.array([3.0, 0.0])  # noqa: E731
    kw = dict(config=CFG, candidates=only(7), image_motion=motion)
    assert match_tracked([Detection(u_now)], [_tracked(a_prev)], 0, 1 / 30, **kw)[0] is not None
    assert match_tracks([Detection(u_now)], [_tracked(a_prev)], 0, 1 / 30, **kw, others=[u_prev]) == [None]
    # Both seen, moved alike: A keeps its name (U is 1.02 sides off A's prediction), U is decoded.
    both = [Detection(a_prev + [3.0, 0.0]), Detection(u_prev + [3.0, 0.0])]
    (a, u) = match_tracks(both, [_tracked(a_prev)], 0, 1 / 30, **kw, others=[u_prev])
    assert a is not None and a.identity.sticker_id == 7 and u is None


@pytest.mark.parametrize("spacing", [(1.2, 1.6), (0.7, 0.9)], ids=["sparse", "dense"])
def test_tracking_saves_decodes_without_changing_fixes_or_taking_a_wrong_id(tmp_path, spacing):
    from tagloc.eval.evaluate import wrong_id_fixes
    from tagloc.eval.metrics import trajectory_metrics
    from tagloc.io.session import SessionReader
    from tagloc.pipeline.run import run_session
    from tagloc.sim.mapgen import GridMapConfig, grid_map
    from tagloc.sim.simulate import SimConfig, simulate_session

    smap = grid_map(GridMapConfig(width_m=12, depth_m=10, spacing_min_m=spacing[0], spacing_max_m=spacing[1], seed=5))
    path = tmp_path / "walk"
    simulate_session(smap, path, SimConfig(seconds=3, lux=150, speed_mps=1.3, seed=4, unmapped=15), progress=False)
    logs = {}
    for on in (False, True):
        session = SessionReader(path)
        # Tracking alone: the expected-ID check would name some of the decodes counted here.
        log = run_session(session, LocaliserConfig(sticker_tracking=on, check_expected=False))
        m = trajectory_metrics(log.stamps[log.valid], log.poses[log.valid], log.covs[log.valid], *session.groundtruth())
        wrong, checked = wrong_id_fixes(path, log)
        logs[on] = (log, m, wrong, checked)
    (off, m_off, wrong_off, _), (on, m_on, wrong_on, checked_on) = logs[False], logs[True]
    assert wrong_on == 0 and wrong_off == 0 and checked_on >= 20
    assert on.counts["tracked"] >= 0.5 * off.counts["decoded"]  # most decodes are carried
    # Nearly all: measured 3 of 92 (sparse) and 9 of 127 (dense, where neighbours share the
    # tracker's gate; 17 of 127 when the tracked sticker had to be the only candidate).
    assert on.counts["decoded"] <= 0.1 * off.counts["decoded"]
    assert on.counts["reverified"] >= 1  # stickers due a re-decode were re-checked instead
    assert on.counts["tracked"] - on.counts["reverified"] <= 3 * (on.counts["decoded"] + on.counts["reverified"])
    assert on.counts["decoded"] + on.counts["tracked"] >= off.counts["decoded"]
    assert len(on.fixes) >= len(off.fixes) - 2
    assert m_on["rmse_m"] <= m_off["rmse_m"] + 0.01


def _blank_square_frames(with_sticker: bool, n: int):
    """``n`` frames of a camera 1.3 m up, pitched 55 deg down, over a framed square with nothing
    printed in it (a label on the floor: detected as a sticker, fails every decoding stage), with
    mapped sticker 77 in view as well (``with_sticker``: the tracker then has a fix from the first
    frame); each frame a pixel's noise apart (see Localiser._check_repeat). (map, rig, frames)."""
    from synth import floor_view, synth_frame

    from tagloc.core.camera import default_camera
    from tagloc.core.geometry import make_T
    from tagloc.core.rig import Rig, RigCamera
    from tagloc.core.stickermap import StickerMap
    from tagloc.core.types import Frame

    cam = default_camera()
    T_wc = floor_view(cam)
    smap = StickerMap(np.array([77]), np.array([[1.2, 0.0]]), np.zeros(1))
    stickers = [(77, make_T(np.eye(3), (1.2, 0.0, 0.0)))] if with_sticker else []
    img = synth_frame(stickers, cam, T_wc, seed=3).image
    cv2.rectangle(img, (250, 600), (330, 680), 30, cv2.FILLED)
    cv2.rectangle(img, (257, 607), (323, 673), 210, cv2.FILLED)
    frames = []
    for i in range(n):
        frame = img.copy()
        frame[0, i] ^= 1
        frames.append(Frame(i, i / 30, frame))
    return smap, Rig([RigCamera("front", cam, T_wc)]), frames


@pytest.mark.parametrize("with_sticker", [True, False])
def test_a_blank_square_that_failed_decoding_skips_least_squares_until_its_retry(with_sticker):
    # In the frames after it failed, the costly least-squares stage is left out for the blank square
    # until its retry is due, while the tracker is tracking; before the first fix (no sticker in
    # view) nothing else can place the operator, and the stage runs every frame. It never gives an
    # identity.
    from tagloc.pipeline.localiser import Localiser

    smap, rig, frames = _blank_square_frames(with_sticker, 2 * TrackingConfig().lsq_retry_every)
    loc = Localiser(smap, rig, LocaliserConfig(odometry=False))
    every = loc.config.tracking.lsq_retry_every
    skipped = []
    for frame in frames:
        res = loc.process(frame)
        blanks = [o for o in res.observations if o.identity is None]
        assert len(blanks) == 1 and len(res.observations) == 1 + with_sticker
        skipped.append(loc.counts["lsq_skipped"])
    assert (loc.tracker.state.value == "tracking") == with_sticker
    # Frame 0 runs it; then, tracking, it is left out every frame but each ``every``-th.
    steps = np.diff([0, *skipped])
    assert steps.tolist() == (([0] + [1] * (every - 1)) * 2 if with_sticker else [0] * 2 * every)


def test_the_tracker_predicts_a_stickers_image_motion_from_its_pose():
    """``Tracker.sticker_pixels`` projects a mapped sticker's centre through the pose (the motion that
    ``Localiser._image_motion`` takes between two frames): checked against OpenCV's projection of
    the same point, before and after a 4 deg turn and a 3 cm step."""
    from tagloc.core.camera import default_camera
    from tagloc.core.geometry import planar_T
    from tagloc.core.rig import RigCamera, looking_forward
    from tagloc.core.types import PoseFix
    from tagloc.sim.mapgen import GridMapConfig, grid_map
    from tracker.tracker import Tracker

    smap = grid_map(GridMapConfig(width_m=8, depth_m=8, spacing_min_m=0.7, spacing_max_m=0.9, seed=2))
    rc = RigCamera("front", default_camera(), looking_forward(1.3, 55.0))
    start = np.array([3.0, 3.0, 0.4])
    moved = start + [0.03, 0.0, np.radians(4.0)]

    def projected(pose, sid):
        T_cw = np.linalg.inv(planar_T(*pose) @ rc.T_body_camera)
        p_w = np.array([*smap.xy[smap.row(sid)], 0.0])
        pix, _ = cv2.projectPoints(
            (T_cw[:3, :3] @ p_w + T_cw[:3, 3]).reshape(1, 1, 3), np.zeros(3), np.zeros(3), rc.camera.K, rc.camera.dist
        )
        return pix.reshape(2)

    pixels = []
    for pose in (start, moved):
        tr = Tracker()
        tr.update([PoseFix(np.eye(4), pose, np.diag([1e-4, 1e-4, 1e-4]), 0.4)], int(smap.ids[0]), IdSource.DECODED, 0.0)
        seen = {}
        for sid in (int(i) for i in smap.ids):
            pix = tr.sticker_pixels(smap, rc, [sid]).get(sid)
            if pix is not None and 0 <= pix[0] < rc.camera.width and 0 <= pix[1] < rc.camera.height:
                seen[sid] = pix
        pixels.append(seen)
    both = sorted(set(pixels[0]) & set(pixels[1]))
    assert len(both) >= 3
    for sid in both:
        np.testing.assert_allclose(pixels[0][sid], projected(start, sid), atol=1e-6)
        np.testing.assert_allclose(
            pixels[1][sid] - pixels[0][sid], projected(moved, sid) - projected(start, sid), atol=1e-6
        )
    assert max(np.linalg.norm(pixels[1][s] - pixels[0][s]) for s in both) > 40.0  # a motion worth predicting
    assert Tracker().sticker_pixels(smap, rc, both) == {}  # not tracking: nothing predicted


def test_the_expected_id_check_never_names_a_sticker_the_map_has_wrong(tmp_path, monkeypatch):
    """A floor where every other mapped sticker is in fact its decade neighbour (an ID differing only
    in its last data codeword, the closest match there is): where blur stops zxing, the tracker
    expects the mapped ID there and its module check (``LocaliserConfig.check_expected``) runs, but
    it never names the neighbour as the mapped sticker; no wrong ID is accepted, and the check
    names the stickers the map has right."""
    import dataclasses

    import tagloc.vision.decode as decode_mod
    from tagloc.core.stickermap import save_map
    from tagloc.eval.evaluate import wrong_id_fixes
    from tagloc.io.session import SessionReader
    from tagloc.pipeline.run import run_session
    from tagloc.sim.mapgen import GridMapConfig, grid_map
    from tagloc.sim.simulate import SimConfig, simulate_session

    floor = grid_map(GridMapConfig(width_m=12, depth_m=10, spacing_min_m=1.2, spacing_max_m=1.6, seed=5))
    path = tmp_path / "walk"
    simulate_session(floor, path, SimConfig(seconds=6, lux=60, speed_mps=1.4, seed=4), progress=False)
    ids = floor.ids.copy()
    swapped = {int(i) - int(i) % 10 + (int(i) % 10 + 1) % 10: int(i) for i in ids[::2]}
    assert not set(swapped) & set(map(int, ids))
    ids[::2] = list(swapped)
    save_map(dataclasses.replace(floor, ids=ids), path / "map.csv")

    checks = []
    real = decode_mod._check_expected

    def spy(rect, sticker_ids, config, result, grid):
        named = real(rect, sticker_ids, config, result, grid)
        checks.append((sticker_ids[0] if sticker_ids else None, named))
        return named

    monkeypatch.setattr(decode_mod, "_check_expected", spy)
    session = SessionReader(path)
    log = run_session(session, LocaliserConfig())
    on_swapped = [named for sid, named in checks if sid in swapped]
    assert len(on_swapped) >= 15 and not any(on_swapped), on_swapped  # measured: 27 checks
    assert sum(named for sid, named in checks if sid is not None and sid not in swapped) >= 5
    assert log.counts["unmapped_reads"] >= 5  # the neighbours, read for what they are
    assert wrong_id_fixes(path, log)[0] == 0
