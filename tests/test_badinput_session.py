"""Bad input to the session, map, ground-truth and sticker-ID readers: one-line refusals naming file
and line, strict ASCII numbers, bounded echo, and unreadable frames skipped, counted and named."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
import pytest

from tagloc.cli import main
from tagloc.core.camera import default_camera
from tagloc.core.errors import InputError, MapError, SessionError
from tagloc.core.rig import Rig, RigCamera, default_rig, looking_forward
from tagloc.core.stickermap import StickerMap, decimal_integer, decimal_number, load_map, shown
from tagloc.io.session import SessionInfo, SessionReader, SessionWriter, read_tum

ARABIC_ONE = "\u0661"  # Arabic-Indic digit one: int() and float() read it as 1


def _session(path: Path, n: int = 6, rig: Rig | None = None) -> Path:
    """A tiny one-camera session of ``n`` PNG frames, 0.1 s apart (``rig``: two cameras alternate)."""
    rig = rig or default_rig()
    smap = StickerMap([4, 9], [[0.0, 0.0], [1.5, 0.0]], [0.0, 1.0])
    with SessionWriter(path, smap, rig, SessionInfo(fps=10.0), image_ext=".png") as w:
        for k in range(n):
            w.write(k, 0.1 * k, np.full((8, 8), 10 * k, np.uint8), camera=k % len(rig))
    return path


def _refused(session: Path) -> str:
    """The one-line message of the SessionError opening ``session`` raises."""
    with pytest.raises(SessionError) as info:
        SessionReader(session)
    msg = str(info.value)
    assert "\n" not in msg
    return msg


def _two_camera_rig() -> Rig:
    cam = default_camera()
    return Rig(
        [
            RigCamera("front", cam, looking_forward(1.3, 55.0)),
            RigCamera("left", cam, looking_forward(1.3, 55.0, yaw_deg=90.0), "left.yaml"),
        ]
    )


# --- the shared number rule ----------------------------------------------------------------------


@pytest.mark.parametrize("text", ["1_0", ARABIC_ONE, "\uff11", "0x10", "1e", "", "+", "1.2.3", "\xa01"])
def test_only_plain_ascii_decimals_are_numbers(text):
    assert decimal_number(text) is None and decimal_integer(text) is None


def test_plain_decimals_read_as_python_reads_them():
    assert [decimal_number(t) for t in (" 1.5 ", ".5", "5.", "-1e-3", "+2E2")] == [1.5, 0.5, 5.0, -0.001, 200.0]
    assert [decimal_integer(t) for t in ("007", "+5", "-3")] == [7, 5, -3]
    assert decimal_integer("9" * 5000) == 10**30  # saturated, not int()'s ValueError
    assert decimal_integer("1.0") is None


def test_echoed_input_is_clipped():
    assert shown("abc") == "'abc'"
    assert shown("\x00" * 4096).endswith("... (4096 characters)") and len(shown("\x00" * 4096)) < 200


# --- map.csv -------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("row", "why"),
    [
        ("1,1_0,0,0", "x_m '1_0' is not a number"),
        (f"{ARABIC_ONE},1,0,0", f"id '{ARABIC_ONE}' is not a number"),
        ("1,1,0,1e300", "yaw_deg '1e300' is beyond +-1e+06 degrees"),
        ("1,1,0,-1e999", "yaw_deg '-1e999' is beyond +-1e+06 degrees"),
        ("1,1,0,inf", "yaw_deg is 'inf' (must be finite)"),
        ("9" * 5000 + ",1,0,0", f"id {'9' * 40!r}... (5000 characters) is not an integer in 0-99999"),
        ("1," + "1" * 5000 + ",0,0", f"x_m {'1' * 40!r}... (5000 characters) is beyond +-100000 m"),
    ],
)
def test_map_numbers_follow_the_strict_rule(tmp_path, row, why):
    p = tmp_path / "m.csv"
    p.write_text(f"id,x_m,y_m,yaw_deg\n{row}\n", encoding="utf-8")
    with pytest.raises(MapError) as info:
        load_map(p)
    assert str(info.value) == f"{p}:2: {why}"


def test_map_yaw_of_a_few_turns_is_fine(tmp_path):
    p = tmp_path / "m.csv"
    p.write_text("id,x_m,y_m,yaw_deg\n1,1,0,720\n2,3,0,-999999\n", encoding="utf-8")
    assert len(load_map(p)) == 2


# --- frames.csv ----------------------------------------------------------------------------------


def test_a_field_over_the_csv_limit_is_refused_naming_the_line(tmp_path):
    s = _session(tmp_path / "s")
    with (s / "frames.csv").open("a") as f:
        f.write("20," + "1" * 200_000 + "\n")
    assert _refused(s) == f"{s / 'frames.csv'}:8: not a frames.csv line (field larger than field limit (131072))"


@pytest.mark.parametrize(
    ("line", "shown_as"),
    [
        ("6,0.6_0", "'6,0.6_0'"),
        (f"{ARABIC_ONE}6,0.6", f"'{ARABIC_ONE}6,0.6'"),
        ("1_6,0.6", "'1_6,0.6'"),
        ("\x00" * 4096, f"{chr(0) * 40!r}... (4096 characters)"),
        ("9" * 5000 + ",0.6", f"{'9' * 40!r}... (5004 characters)"),
    ],
)
def test_frames_csv_numbers_follow_the_strict_rule_and_echo_is_bounded(tmp_path, line, shown_as):
    s = _session(tmp_path / "s")
    with (s / "frames.csv").open("a") as f:
        f.write(line + "\n")
    assert _refused(s) == f"{s / 'frames.csv'}:8: want 'index,timestamp_s', got {shown_as}"


def test_a_camera_of_arabic_indic_digits_is_refused(tmp_path):
    s = _session(tmp_path / "s", 4, _two_camera_rig())
    with (s / "frames.csv").open("a") as f:
        f.write(f"4,0.4,{ARABIC_ONE}\n")
    assert _refused(s) == f"{s / 'frames.csv'}:6: camera '{ARABIC_ONE}' is not a camera of the rig (0-1)"


# --- frames.csv listing far more frames than there are images ------------------------------------


def test_frames_csv_listing_far_more_frames_than_images_is_refused_up_front(tmp_path):
    s = _session(tmp_path / "s")
    (s / "frames.csv").write_text("index,timestamp_s\n" + "".join(f"{k},{k / 10:.6f}\n" for k in range(1000)))
    assert _refused(s) == (
        f"{s / 'frames.csv'}: lists 1000 frames but {s / 'frames'} holds 6 images, fewer than half"
        " (is frames.csv another recording's?)"
    )


def test_a_few_missing_frames_are_still_skipped_and_counted(tmp_path):
    s = _session(tmp_path / "s")
    for k in (1, 4):
        (s / "frames" / f"{k:06d}.png").unlink()
    r = SessionReader(s)
    assert len([f for f in r.frames() if f.image is not None]) == 4
    assert r.skipped == [(1, "frame 1: image file missing"), (4, "frame 4: image file missing")]


def test_a_recording_killed_mid_write_stays_readable(tmp_path):
    """The writer renames each image into place before its line: a kill leaves a temporary image and
    maybe half a line, never a listed frame without its image."""
    s = _session(tmp_path / "s")
    (s / "frames" / "000006.tmp.png").write_bytes(b"\x89PNG half")
    with (s / "frames.csv").open("a") as f:
        f.write("6,0.6")  # cut short: no newline
    r = SessionReader(s)
    assert len(r) == 6 and all(f.image is not None for f in r.frames()) and r.skipped == []


# --- unreadable frames ---------------------------------------------------------------------------


def test_an_empty_frame_is_named_as_empty(tmp_path):
    s = _session(tmp_path / "s")
    (s / "frames" / "000002.png").write_bytes(b"")
    r = SessionReader(s)
    list(r.frames())
    assert r.skipped == [(2, "frame 2: 000002.png: empty file (0 bytes)")]


def test_a_symlink_loop_frame_is_named_as_unreadable_not_missing(tmp_path):
    s = _session(tmp_path / "s")
    p = s / "frames" / "000003.png"
    p.unlink()
    p.symlink_to(p.name)
    r = SessionReader(s)
    list(r.frames())
    assert r.skipped == [(3, f"frame 3: 000003.png: cannot read ({os.strerror(errno.ELOOP)})")]


def test_frames_that_cannot_be_looked_at_are_skipped_counted_and_named(tmp_path, monkeypatch):
    """frames/ without permission: Path.exists() raised PermissionError out of the reader (Python
    3.11). Simulated, as root ignores permissions: each frame's stat is refused, its listing is not."""
    s = _session(tmp_path / "s")
    r = SessionReader(s)
    real_stat = os.stat
    frames_dir = str(s / "frames")

    def no_permission(path, *args, **kwargs):
        if str(path).startswith(frames_dir + os.sep):
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
        return real_stat(path, *args, **kwargs)

    monkeypatch.setattr(os, "stat", no_permission)
    got = list(r.frames())
    assert all(f.image is None for f in got) and len(r.skipped) == 6
    # Named by the first extension tried: without permission nothing tells which file is there.
    assert r.skipped[0] == (0, f"frame 0: 000000.jpg: cannot read ({os.strerror(errno.EACCES)})")


# --- a session without frames.csv ----------------------------------------------------------------


def test_without_frames_csv_one_camera_reads_with_a_warning(tmp_path, capsys):
    s = _session(tmp_path / "s")
    (s / "frames.csv").unlink()
    r = SessionReader(s)
    assert list(r.index) == list(range(6)) and r.timestamps == pytest.approx(np.arange(6) / 10.0)
    err = capsys.readouterr().err.splitlines()
    assert err == [
        f"tagloc: warning: {s / 'frames.csv'}: missing; frame times made up from the 6 image names at 10 fps"
        " (session.json's)"
    ]
    (s / "session.json").unlink()
    SessionReader(s)
    assert "at 30 fps (assumed: session.json states none)" in capsys.readouterr().err


def test_without_frames_csv_a_multi_camera_session_is_refused(tmp_path):
    s = _session(tmp_path / "s", 4, _two_camera_rig())
    (s / "frames.csv").unlink()
    assert (
        _refused(s) == f"{s / 'frames.csv'}: missing; a session of 2 cameras needs it (its frames' times and cameras)"
    )


# --- groundtruth.tum -----------------------------------------------------------------------------

POSE = "0 0 0 0 0 0 1"


@pytest.mark.parametrize(
    ("content", "why"),
    [
        (f"0.0 {POSE}\n0.1 {POSE}\n0.1 {POSE}\n", ":3: timestamp 0.100000 s is not after line 2's 0.100000 s"),
        (f"0.0 {POSE}\n# note\n0.2 {POSE}\n0.1 {POSE}\n", ":4: timestamp 0.100000 s is not after line 3's 0.200000 s"),
        ("", ": holds no pose"),
        ("# timestamp x y z qx qy qz qw\n\n", ": holds no pose"),
    ],
)
def test_groundtruth_out_of_order_or_empty_is_refused_on_open(tmp_path, content, why):
    s = _session(tmp_path / "s")
    gt = s / "groundtruth.tum"
    gt.write_text(content)
    assert _refused(s).startswith(f"{gt}{why}")


def test_groundtruth_with_a_byte_order_mark_reads(tmp_path):
    gt = tmp_path / "gt.tum"
    gt.write_bytes(f"\ufeff0.0 {POSE}\n0.1 1 2 0 0 0 0 1\n".encode())
    t, T = read_tum(gt)
    assert t.tolist() == [0.0, 0.1] and T[1, :2, 3] == pytest.approx((1, 2))


# --- sticker IDs on the command line -------------------------------------------------------------


@pytest.mark.parametrize(
    ("token", "why"),
    [
        (ARABIC_ONE, f"sticker ID '{ARABIC_ONE}' is not a number in 0-99999 or a range like 20-29"),
        (f"20-2{ARABIC_ONE}", f"sticker ID '20-2{ARABIC_ONE}' is not a number in 0-99999 or a range like 20-29"),
        ("9" * 5000, f"sticker ID {'9' * 40!r}... (5000 characters) is not a number in 0-99999 or a range like 20-29"),
        ("100000", "sticker ID 100000 in '100000' is outside 0-99999"),
    ],
)
def test_sticker_ids_follow_the_strict_rule(tmp_path, capsys, token, why):
    """The library's parser itself refuses them, so every caller of it does, not only the command."""
    from tagloc.io.printing import parse_ids

    with pytest.raises(InputError, match="sticker ID"):
        parse_ids([token])
    out = tmp_path / "sheet.pdf"
    assert main(["sticker", token, "-o", str(out)]) == 2
    assert capsys.readouterr().err.splitlines() == [f"tagloc sticker: error: {why}"]
    assert not out.exists()
