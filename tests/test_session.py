"""Session directories: crash-safe writing, tolerant reading, TUM trajectories."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tagloc.core.errors import SessionError
from tagloc.core.geometry import make_T
from tagloc.core.rig import default_rig
from tagloc.core.stickermap import StickerMap
from tagloc.io.session import SessionInfo, SessionReader, SessionWriter, read_image, read_tum, write_tum

N = 6


def _images(rng, n=N, shape=(48, 64)) -> list[np.ndarray]:
    # Smooth content so JPEG is close; noise would make the JPEG check meaningless.
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    return [
        np.clip(100 + 60 * np.sin(xx / 7.0 + k) * np.cos(yy / 9.0) + rng.normal(0, 2, shape), 0, 255).astype(np.uint8)
        for k in range(n)
    ]


def _write_session(path, images, ext=".png", stamps=None) -> np.ndarray:
    smap = StickerMap([4, 9], [[0.0, 0.0], [1.5, 0.0]], [0.0, 1.0])
    stamps = np.round(np.cumsum(np.full(len(images), 1 / 30)) + 100.0, 6) if stamps is None else stamps
    with SessionWriter(path, smap, default_rig(), SessionInfo(source="test", fps=30.0), image_ext=ext) as w:
        for i, (t, img) in enumerate(zip(stamps, images)):
            w.write(i, float(t), img)
    return stamps


def _session_with(tmp_path, rng, name: str, content: str) -> Path:
    """A two-frame session whose file ``name`` holds ``content``: that file's path."""
    _write_session(tmp_path / "s", _images(rng, 2))
    p = tmp_path / "s" / name
    p.write_text(content)
    return p


def _refused_on_open(session: Path, message: str) -> None:
    """Opening ``session`` raises a SessionError saying exactly ``message``."""
    with pytest.raises(SessionError) as info:
        SessionReader(session)
    assert str(info.value) == message


def test_png_round_trip_exact(tmp_path, rng):
    images = _images(rng)
    stamps = _write_session(tmp_path / "s", images)
    r = SessionReader(tmp_path / "s")
    assert len(r) == N and r.info.source == "test" and r.info.fps == 30.0
    frames = list(r.frames())
    assert [f.index for f in frames] == list(range(N))
    assert np.array([f.timestamp for f in frames]) == pytest.approx(stamps, abs=1e-9)
    for f, img in zip(frames, images):
        assert f.error is None and np.array_equal(f.image, img)
    assert r.skipped == [] and list(r.map.ids) == [4, 9]
    assert r.camera.K == pytest.approx(default_rig()[0].camera.K)


def test_jpeg_round_trip_close(tmp_path, rng):
    images = _images(rng)
    _write_session(tmp_path / "s", images, ext=".jpg")
    for f, img in zip(SessionReader(tmp_path / "s").frames(), images):
        assert f.image.shape == img.shape
        assert np.abs(f.image.astype(float) - img).mean() < 3.0


def test_missing_session_json_still_readable(tmp_path, rng):
    _write_session(tmp_path / "s", _images(rng, 3))
    (tmp_path / "s" / "session.json").unlink()
    r = SessionReader(tmp_path / "s")
    assert r.info.source == "unknown" and len(list(r.frames())) == 3 and r.skipped == []


@pytest.mark.parametrize(
    ("doc", "why"),
    [
        (
            '{"format": "tagloc-session", "version": 99}',
            "version 99 is newer than this tagloc reads (1); update tagloc",
        ),
        ('{"format": "tagloc-session", "version": "one"}', 'version must be a whole number from 1, got "one"'),
        ('{"format": "tagloc-session", "version": true}', "version must be a whole number from 1, got true"),
        ('{"format": "rosbag", "version": 1}', 'format is "rosbag", want "tagloc-session"'),
        (
            '{"version": 1, "fps": ' + "1" * 5000 + "}",
            "not usable JSON (Exceeds the limit (4300 digits) for integer string conversion)",
        ),
    ],
)
def test_bad_session_json_refused_naming_it(tmp_path, rng, doc, why):
    p = _session_with(tmp_path, rng, "session.json", doc)
    _refused_on_open(tmp_path / "s", f"{p}: {why}")


def test_session_json_without_format_or_version_read_as_version_1(tmp_path, rng):
    # tagloc has written both keys since its first session format, so such a file is hand-made.
    _write_session(tmp_path / "s", _images(rng, 2))
    (tmp_path / "s" / "session.json").write_text('{"fps": 25, "source": "by hand"}')
    r = SessionReader(tmp_path / "s")
    assert (r.info.source, r.info.fps, len(r)) == ("by hand", 25.0, 2)


def test_corrupt_and_missing_frames_skipped(tmp_path, rng):
    _write_session(tmp_path / "s", _images(rng), ext=".jpg")
    frames_dir = tmp_path / "s" / "frames"
    (frames_dir / "000002.jpg").write_bytes(b"\x00garbage, not a JPEG" * 10)
    (frames_dir / "000004.jpg").unlink()
    r = SessionReader(tmp_path / "s")
    frames = list(r.frames())
    assert len(frames) == N  # every listed frame is yielded, unreadable ones without an image
    bad = {f.index for f in frames if f.image is None}
    assert bad == {2, 4}
    assert [i for i, _ in r.skipped] == [2, 4]
    assert "corrupt" in r.skipped[0][1] and "missing" in r.skipped[1][1]
    assert all(f.image.shape == (48, 64) for f in frames if f.index not in bad)


@pytest.mark.parametrize("keep", ["4,", "4"])
def test_frames_csv_cut_mid_line(tmp_path, rng, keep):
    _write_session(tmp_path / "s", _images(rng))
    csv_path = tmp_path / "s" / "frames.csv"
    lines = csv_path.read_text().splitlines(keepends=True)
    assert lines[5].startswith("4,")
    # A crash while writing line 6 (frame 4) leaves only its first characters.
    csv_path.write_text("".join(lines[:5]) + keep)
    r = SessionReader(tmp_path / "s")
    assert list(r.index) == [0, 1, 2, 3]
    assert len([f for f in r.frames() if f.image is not None]) == 4


@pytest.mark.parametrize("sj", [True, False])
def test_frames_csv_malformed_last_line_refused_unless_cut_short(tmp_path, rng, sj):
    _write_session(tmp_path / "s", _images(rng))
    if not sj:
        (tmp_path / "s" / "session.json").unlink()
    csv_path = tmp_path / "s" / "frames.csv"
    lines = csv_path.read_text().splitlines(keepends=True)
    # Newline-terminated, so written whole: not a write cut short, whatever session.json says.
    csv_path.write_text("".join(lines[:5]) + "4,abc\n")
    _refused_on_open(tmp_path / "s", f"{csv_path}:6: want 'index,timestamp_s', got '4,abc'")
    # Unterminated: a recording cut short (dropped) only when session.json says tagloc wrote it.
    csv_path.write_text("".join(lines[:5]) + "4,abc")
    if sj:
        assert list(SessionReader(tmp_path / "s").index) == [0, 1, 2, 3]
    else:
        _refused_on_open(tmp_path / "s", f"{csv_path}:6: want 'index,timestamp_s', got '4,abc'")
        # A hand-made file's unterminated last line is read like any other.
        csv_path.write_text("".join(lines[:5]) + "4,200.5")
        assert list(SessionReader(tmp_path / "s").index) == [0, 1, 2, 3, 4]


def test_frames_csv_saved_by_a_spreadsheet_reads_as_written(tmp_path, rng):
    """A byte-order mark and CRLF line ends (a spreadsheet's "CSV UTF-8"): the session reads as before.
    The mark had made the header a malformed frame line, the session refused."""
    stamps = _write_session(tmp_path / "s", _images(rng))
    csv_path = tmp_path / "s" / "frames.csv"
    csv_path.write_bytes(b"\xef\xbb\xbf" + csv_path.read_bytes().replace(b"\n", b"\r\n"))
    r = SessionReader(tmp_path / "s")
    assert list(r.index) == list(range(N)) and np.array_equal(r.timestamps, stamps)
    # Without a header, the mark is not part of the first index either.
    csv_path.write_bytes(b"\xef\xbb\xbf" + b"".join(csv_path.read_bytes().splitlines(keepends=True)[1:]))
    assert list(SessionReader(tmp_path / "s").index) == list(range(N))


@pytest.mark.parametrize(
    "content, line, why",
    [
        ("index,timestamp_s\n0,100.0\n1,100.1,0,0.003\n", 3, "want 'index,timestamp_s', got '1,100.1,0,0.003'"),
        ("index,timestamp_ms\n0,0.0\n1,33.3\n", 1, "header is 'index,timestamp_ms', want "),
        ("index,timestamp_s,exposure_s\n0,100.0,0\n", 1, "header is 'index,timestamp_s,exposure_s', want "),
    ],
)
def test_frames_csv_with_columns_the_format_has_not_is_refused(tmp_path, rng, content, line, why):
    """A column beyond index, timestamp and camera (read, then ignored) and a header naming other
    columns (a time in ms read as seconds) were accepted; each is refused naming its line."""
    csv_path = _session_with(tmp_path, rng, "frames.csv", content)
    with pytest.raises(SessionError) as info:
        SessionReader(tmp_path / "s")
    assert str(info.value).startswith(f"{csv_path}:{line}: {why}")
    # The format's own headers, in any case and spacing, still read.
    for header in ("index,timestamp_s", "Index, Timestamp_s ,camera"):
        csv_path.write_text(f"{header}\n0,100.0\n1,100.1\n")
        assert list(SessionReader(tmp_path / "s").index) == [0, 1]


@pytest.mark.parametrize("content", ["", "index,timestamp_s\n", "index,timestamp_s\n\n", "index,timestamp_s\n0,1."])
def test_frames_csv_listing_no_frames_refused(tmp_path, rng, content):
    csv_path = _session_with(tmp_path, rng, "frames.csv", content)
    _refused_on_open(tmp_path / "s", f"{csv_path}: lists no frames")


def test_images_without_frames_csv_must_be_named_by_index(tmp_path, rng):
    _write_session(tmp_path / "s", _images(rng, 2))
    (tmp_path / "s" / "frames.csv").unlink()
    assert list(SessionReader(tmp_path / "s").index) == [0, 1]  # the documented fallback
    for f in (tmp_path / "s" / "frames").glob("*.png"):
        f.rename(f.with_name("img" + f.name))
    _refused_on_open(
        tmp_path / "s", f"{tmp_path / 's'}: missing frames.csv and no image in frames/ is named by its index"
    )


def test_digits_that_are_not_ascii_are_refused_in_one_line_not_an_internal_error(tmp_path, rng):
    """'\u00b2' (superscript two) is a digit to str.isdigit() but not to int()."""
    csv_path = _session_with(tmp_path, rng, "frames.csv", "index,timestamp_s,camera\n0,0.0,0\n1,0.1,\u00b2\n")
    _refused_on_open(tmp_path / "s", f"{csv_path}:3: camera '\u00b2' is not a camera of the rig (0-0)")
    csv_path.unlink()
    for f in (tmp_path / "s" / "frames").glob("*.png"):
        f.rename(f.with_name("\u00b2" + f.name[1:]))
    _refused_on_open(
        tmp_path / "s", f"{tmp_path / 's'}: missing frames.csv and no image in frames/ is named by its index"
    )


def test_writer_refuses_existing_session(tmp_path, rng):
    _write_session(tmp_path / "s", _images(rng, 2))
    with pytest.raises(SessionError, match="already holds a session"):
        _write_session(tmp_path / "s", _images(rng, 2))


def test_reader_refuses_non_sessions(tmp_path):
    with pytest.raises(SessionError, match="not a session directory"):
        SessionReader(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SessionError, match="missing map.csv"):
        SessionReader(tmp_path / "empty")


def test_tum_round_trip(tmp_path):
    rot = Rotation.random(20, random_state=3)
    rng = np.random.default_rng(3)
    poses = [make_T(R, t) for R, t in zip(rot.as_matrix(), rng.uniform(-50, 50, (20, 3)))]
    stamps = 1000.0 + np.sort(rng.uniform(0, 60, 20))
    write_tum(tmp_path / "gt.tum", stamps, poses)
    t2, T2 = read_tum(tmp_path / "gt.tum")
    assert t2 == pytest.approx(stamps, abs=1e-6)
    assert T2.shape == (20, 4, 4)
    assert T2[:, :3, 3] == pytest.approx(np.array(poses)[:, :3, 3], abs=1e-6)
    assert T2[:, :3, :3] == pytest.approx(np.array(poses)[:, :3, :3], abs=1e-5)


def test_tum_comments_and_errors(tmp_path):
    p = tmp_path / "x.tum"
    p.write_text("# timestamp x y z qx qy qz qw\n\n1.0 1 2 3 0 0 0 1\n")
    t, T = read_tum(p)
    assert t.tolist() == [1.0] and T[0, :3, 3] == pytest.approx((1, 2, 3))
    p.write_text("1.0 1 2 3 0 0 0 1\n2.0 1 2 3 0 0 1\n")
    with pytest.raises(SessionError, match=f"{p}:2: want 8"):
        read_tum(p)
    p.write_text("1.0 1 2 3 0 0 0 1\n2.0 1 x 3 0 0 0 1\n")
    with pytest.raises(SessionError, match=f"{p}:2: not a TUM line"):
        read_tum(p)


@pytest.mark.parametrize(
    ("line", "why"),
    [
        ("2.0 1 2 NaN 0 0 0 1", "z is 'NaN' (must be finite)"),
        ("inf 1 2 3 0 0 0 1", "timestamp is 'inf' (must be finite)"),
        ("2.0 1 2 3 0 0 0 1 4", "want 8 numbers (timestamp x y z qx qy qz qw), got 9"),
    ],
)
def test_tum_line_errors_say_what_is_wrong(tmp_path, line, why):
    p = tmp_path / "x.tum"
    p.write_text(f"1.0 1 2 3 0 0 0 1\n{line}\n")
    with pytest.raises(SessionError) as info:
        read_tum(p)
    assert str(info.value) == f"{p}:2: {why}"


def test_bad_groundtruth_refused_when_the_session_is_opened(tmp_path, rng):
    p = _session_with(tmp_path, rng, "groundtruth.tum", "0.0 0 0 0 0 0 0 1\n0.1 nan 0 0 0 0 0 1\n")
    # Before any frame is read, not when groundtruth() is asked.
    _refused_on_open(tmp_path / "s", f"{p}:2: x is 'nan' (must be finite)")


def test_groundtruth_in_session(tmp_path, rng):
    _write_session(tmp_path / "s", _images(rng, 2))
    assert SessionReader(tmp_path / "s").groundtruth() is None
    write_tum(tmp_path / "s" / "groundtruth.tum", np.array([0.5]), [np.eye(4)])
    t, T = SessionReader(tmp_path / "s").groundtruth()
    assert t.tolist() == [0.5] and T[0] == pytest.approx(np.eye(4))


def test_a_frame_that_is_a_device_or_huge_is_skipped_not_read(tmp_path, monkeypatch):
    """A frame symlinked to /dev/zero would be read without end (the process killed for memory)."""
    from tagloc.io import session as session_io

    dev = tmp_path / "000001.jpg"
    dev.symlink_to("/dev/zero")
    assert read_image(dev) == (None, "000001.jpg: not a regular file")
    big = tmp_path / "000002.jpg"
    big.write_bytes(b"\xff" * 2000)
    monkeypatch.setattr(session_io, "MAX_FRAME_BYTES", 1000)
    img, why = read_image(big)
    assert img is None and "more than any frame" in why


def _png_declaring(width: int, height: int) -> bytes:
    """A small PNG whose header declares ``width`` x ``height`` pixels (its data is a few bytes)."""
    import struct
    import zlib

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(bytes(1000))) + chunk(b"IEND", b"")
    )


def test_a_frame_declaring_more_pixels_than_opencv_allows_is_skipped_not_an_error(tmp_path):
    """OpenCV raises for such a file instead of returning None; the frame is corrupt like any other."""
    bomb = tmp_path / "000003.png"
    bomb.write_bytes(_png_declaring(60000, 60000))
    img, why = read_image(bomb)
    assert img is None and why == "000003.png is corrupt or unreadable"


@pytest.mark.parametrize("orientation", [3, 6])
def test_jpeg_exif_orientation_not_applied(tmp_path, rng, orientation):
    from synth import with_exif_orientation

    # A camera's JPEG may carry an EXIF orientation tag; the calibration is of the sensor's layout,
    # so the frame is read as stored (turned, it gave no pose, or was refused as the wrong size).
    images = _images(rng, 1)
    _write_session(tmp_path / "s", images, ext=".jpg")
    path = tmp_path / "s" / "frames" / "000000.jpg"
    plain = read_image(path)[0]
    path.write_bytes(with_exif_orientation(path.read_bytes(), orientation))
    img, err = read_image(path)
    assert err is None and np.array_equal(img, plain)


def test_a_corrupt_huge_stamp_is_named_in_a_short_line(tmp_path):
    """A non-increasing 1e300 s stamp was printed to the microsecond: a 650-character 'one line'."""
    from tagloc.core.types import seconds_text

    assert seconds_text(1.5) == "1.500000" and seconds_text(1800000000.0737195) == "1800000000.073720"
    assert seconds_text(1e300) == "1e+300" and len(seconds_text(-3.2e15)) < 12
