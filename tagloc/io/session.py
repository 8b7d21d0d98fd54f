"""The one session layout, for recorded, simulated and logged sessions alike.

A session is a directory::

    session.json       {"format": "tagloc-session", "version": 1, "source": ..., "fps": ..., "notes": ...}
    camera.yaml        calibration (OpenCV FileStorage YAML or ROS camera_info)
    rig.json           camera poses in the body frame (see tagloc.core.rig)
    map.csv            id,x_m,y_m,yaw_deg
    frames/000000.jpg  one image per frame (.jpg or .png), named by zero-padded index
    frames.csv         index,timestamp_s (one line per frame, appended as frames are written)
    groundtruth.tum    optional: "timestamp x y z qx qy qz qw" of the body frame in the world

``session.json`` may be missing. Reading streams frame by frame and skips (and counts) frames that
are missing, unreadable or corrupt; a ``frames.csv`` listing more than twice as many frames as
``frames/`` holds images is refused up front. Without ``frames.csv`` (a hand-made session of one
camera) frame times come from the image names and the fps, with a warning. Writing is crash-safe:
each image is written to a temporary name and renamed, then its line is appended and flushed to
``frames.csv``, so a kill at any moment leaves every listed frame readable.
"""

from __future__ import annotations

import csv
import json
import math
import os
import stat
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from tagloc.core.camera import Camera
from tagloc.core.errors import SessionError, warn_stderr
from tagloc.core.geometry import T_from_tum, T_to_tum
from tagloc.core.jsonfile import read_json
from tagloc.core.rig import Rig, load_rig, save_rig
from tagloc.core.stickermap import StickerMap, decimal_integer, decimal_number, load_map, save_map, shown
from tagloc.core.types import Frame, seconds_text

FORMAT = "tagloc-session"
VERSION = 1
# The session's file names: the one definition every reader and writer uses.
SESSION_JSON = "session.json"
CAMERA_FILE = "camera.yaml"
RIG_FILE = "rig.json"
MAP_FILE = "map.csv"
FRAMES_DIR = "frames"
FRAMES_CSV = "frames.csv"
GROUNDTRUTH_FILE = "groundtruth.tum"
# The files of a session directory that a run reads besides its frames (an output must not be one).
SESSION_INPUTS = (
    SESSION_JSON,
    CAMERA_FILE,
    RIG_FILE,
    MAP_FILE,
    FRAMES_CSV,
    GROUNDTRUTH_FILE,
    "groundtruth_frames.jsonl",
)
# A step between consecutive frames longer than this is reported as a clock jump (s). 5 s: longer
# than any pause of a recording camera we know of, and longer than the tracker keeps a track
# without fixes, so the track is lost across it either way.
CLOCK_JUMP_S = 5.0
# A frame file larger than this is not a camera frame: 12 MP as 8-bit RGB, uncompressed, is 36 MB.
MAX_FRAME_BYTES = 64_000_000
MAX_FPS = 1000.0  # a frame rate above this in session.json is a typo, not a camera
IMAGE_EXTENSIONS = (".jpg", ".png", ".jpeg", ".bmp", ".tif", ".tiff")
# Frame rate assumed for a session without frames.csv whose session.json states none.
FALLBACK_FPS = 30.0


@dataclass
class SessionInfo:
    """Contents of ``session.json``."""

    source: str = "unknown"
    fps: float = 30.0
    notes: str = ""
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "format": FORMAT,
            "version": VERSION,
            "source": self.source,
            "fps": self.fps,
            "notes": self.notes,
            **self.extra,
        }


#: ``frames.csv`` holds frame times to this resolution (s, its ``%.6f``), and a pose message's ``t``
#: too (``round(t, 6)``): each frame written after another must be at least one such step later.
STAMP_RESOLUTION_S = 1e-6


def after_last(stamp: float, last: float) -> float:
    """``stamp`` (s), or the microsecond after ``last`` (s; -inf: none yet) when ``frames.csv`` would
    not hold it after ``last``: within its microsecond, or before. Rounded as frames.csv and a pose
    message round them: counted in microseconds, t / 1e-6 is rounded twice, and at epoch times
    (7e-7 s apart) a frame 0.3 us after the last went on unmoved into the same microsecond."""
    if not math.isfinite(last):
        return stamp
    last = round(last, 6)
    return stamp if round(stamp, 6) > last else round(last + STAMP_RESOLUTION_S, 6)


def tum_line(t: float, T: np.ndarray) -> str:
    """One TUM line ``timestamp x y z qx qy qz qw`` (newline included) for the 4x4 pose ``T`` at ``t`` (s).

    The one number format of every TUM file tagloc writes; "+ 0.0" prints -0.0 as 0.0 so that equal
    poses always print equal.
    """
    return f"{t + 0.0:.6f} " + " ".join(f"{v + 0.0:.6f}" for v in T_to_tum(T)) + "\n"


def write_tum(path: str | Path, stamps: np.ndarray, poses: list[np.ndarray] | np.ndarray) -> None:
    """Write 4x4 poses with timestamps as a TUM trajectory file."""
    with Path(path).open("w", encoding="utf-8") as f:
        for t, T in zip(stamps, poses):
            f.write(tum_line(float(t), T))


TUM_COLUMNS = ("timestamp", "x", "y", "z", "qx", "qy", "qz", "qw")


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM file: timestamps (N,) and poses (N, 4, 4). Lines starting with # are comments."""
    return tum_poses(read_tum_table(path))


def tum_poses(table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (N,) and poses (N, 4, 4) of a table from :func:`read_tum_table`."""
    # All rotations in one call: one at a time, a 20 s walk's ground truth took 0.1 s of start-up.
    return table[:, 0], T_from_tum(table[:, 1:]) if len(table) else np.zeros((0, 4, 4))


def read_tum_table(path: str | Path) -> np.ndarray:
    """A TUM file's numbers (N, 8), checked line by line; :class:`SessionError` naming file and line.

    Refused besides a malformed line: a file with no pose, and a timestamp not after the one before
    (repeated or backwards: interpolating in such a trajectory scores against the wrong pose). A
    byte-order mark is accepted, as in every text file tagloc reads. Checking needs no rotation maths
    (scipy), so a session can be checked up front cheaply.
    """
    path = Path(path)
    rows: list[list[float]] = []
    last_line = 0
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except OSError as exc:
        raise SessionError(f"{path}: cannot read ({exc.strerror})") from exc
    except UnicodeDecodeError as exc:
        raise SessionError(f"{path}: not a text file (byte {exc.start} is not UTF-8)") from None
    for n, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise SessionError(f"{path}:{n}: not a TUM line (timestamp x y z qx qy qz qw)") from None
        if len(values) != 8:
            raise SessionError(f"{path}:{n}: want 8 numbers (timestamp x y z qx qy qz qw), got {len(values)}")
        bad = next((k for k, v in enumerate(values) if not math.isfinite(v)), None)
        if bad is not None:
            raise SessionError(f"{path}:{n}: {TUM_COLUMNS[bad]} is {parts[bad][:20]!r} (must be finite)")
        if abs(math.hypot(*values[4:]) - 1.0) > 0.01:
            raise SessionError(f"{path}:{n}: quaternion qx qy qz qw is not of unit length")
        if max(abs(v) for v in values[1:4]) > 1e6:
            raise SessionError(f"{path}:{n}: position beyond 1000 km")
        if rows and not values[0] > rows[-1][0]:
            raise SessionError(
                f"{path}:{n}: timestamp {seconds_text(values[0])} s is not after line {last_line}'s"
                f" {seconds_text(rows[-1][0])} s (a trajectory's times must increase)"
            )
        rows.append(values)
        last_line = n
    if not rows:
        raise SessionError(f"{path}: holds no pose (want lines 'timestamp x y z qx qy qz qw')")
    return np.array(rows, float).reshape(-1, 8)


def read_image(path: Path) -> tuple[np.ndarray | None, str | None]:
    """A greyscale image file, or (None, why not). A JPEG cut short is refused, not half-decoded.

    libjpeg decodes a truncated JPEG with only a warning (the missing rows come out grey), so the
    end-of-image marker is checked first: inside a JPEG's entropy-coded data a 0xFF byte is always
    stuffed or a restart marker, so FF D9 near the end appears only when the file is complete.
    """
    try:
        st = path.stat()
        # A device or pipe in the frames (a symlink to /dev/zero) would be read without end.
        if not stat.S_ISREG(st.st_mode):
            return None, f"{path.name}: not a regular file"
        if st.st_size == 0:
            return None, f"{path.name}: empty file (0 bytes)"
        if st.st_size > MAX_FRAME_BYTES:
            return None, f"{path.name}: {st.st_size / 1e6:.0f} MB, more than any frame ({MAX_FRAME_BYTES / 1e6:.0f} MB)"
        data = path.read_bytes()
    except OSError as exc:
        return None, f"{path.name}: cannot read ({exc.strerror})"
    if path.suffix.lower() in (".jpg", ".jpeg") and b"\xff\xd9" not in data[-64:]:
        return None, f"{path.name} is corrupt: JPEG cut short (no end-of-image marker)"
    img = decode_grey(data)
    if img is None:
        return None, f"{path.name} is corrupt or unreadable"
    return img, None


def decode_grey(data: bytes) -> np.ndarray | None:
    """An encoded image (JPEG, PNG, ...) as (H, W) uint8 grey, or None when it cannot be decoded: OpenCV
    raises, rather than returning None, for some files (one declaring more pixels than it allows).

    The pixels are kept as stored, as the sensor read them: an EXIF orientation tag is ignored. The
    calibration, the rig's mount and the rolling shutter's row times are all of the sensor's own
    layout; OpenCV's default turns a frame tagged 3 by 180 deg (a session of them gave no pose) and
    one tagged 6 or 8 by 90 deg (every frame refused as the wrong size)."""
    if not data:
        return None
    try:
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    except cv2.error:
        return None


#: frames.csv's columns; the camera only with several cameras (a session without it reads as camera 0).
FRAMES_COLUMNS = ("index", "timestamp_s", "camera")


def _check_frames_header(row: list[str], where: str) -> None:
    """Refuse a frames.csv header naming other columns than the format's: one such as
    ``index,timestamp_ms`` had its numbers read as seconds without a word."""
    names = tuple(c.strip().lower() for c in row)
    if names and names not in (FRAMES_COLUMNS[:2], FRAMES_COLUMNS):
        raise SessionError(
            f"{where}: header is {shown(','.join(row))}, want 'index,timestamp_s' or 'index,timestamp_s,camera'"
        )


def frames_csv_header(multi_camera: bool) -> str:
    """frames.csv's header line: the camera column only for a rig of several cameras (a one-camera
    session keeps the original two columns, byte for byte)."""
    return ",".join(FRAMES_COLUMNS if multi_camera else FRAMES_COLUMNS[:2]) + "\n"


def frames_csv_line(index: int, timestamp: float, camera: int, multi_camera: bool) -> str:
    """One frames.csv line: timestamps to the microsecond, the format's resolution."""
    return f"{index},{timestamp:.6f},{camera}\n" if multi_camera else f"{index},{timestamp:.6f}\n"


def frame_stem(index: int, camera: int = 0) -> str:
    """File name (no extension) of a frame: ``000123`` for camera 0, ``000123_cam1`` for camera 1."""
    return f"{index:06d}" if camera == 0 else f"{index:06d}_cam{camera}"


class SessionReader:
    """Read a session directory lazily (frames are loaded one at a time)."""

    def __init__(self, path: str | Path, calibration: Camera | None = None):
        self.path = Path(path)
        if not self.path.is_dir():
            raise SessionError(f"{self.path}: not a session directory")
        self.warnings: list[str] = []  # one line each: what was odd but usable (clock jumps)
        self.info = self._read_info()
        self.map_path = self._need(MAP_FILE)  # beside it the map's reference cache (tagloc.vision.refs)
        self.map: StickerMap = load_map(self.map_path)
        self.rig: Rig = (
            load_rig(self._need(RIG_FILE), calibration)
            if (self.path / RIG_FILE).exists()
            else self._rig_from_camera(calibration)
        )
        self.cameras = np.zeros(0, np.int64)  # rig camera of each frame (frames.csv's camera column)
        self.index, self.timestamps = self._read_frames_csv()
        self._check_clock()
        # Checked now, though only used after the run: a bad file must not cost a whole replay first.
        gt = self.path / GROUNDTRUTH_FILE
        self._groundtruth = read_tum_table(gt) if gt.exists() else None
        self.skipped: list[tuple[int, str]] = []

    def _need(self, name: str) -> Path:
        p = self.path / name
        if not p.exists():
            raise SessionError(f"{self.path}: missing {name}")
        return p

    def _rig_from_camera(self, calibration: Camera | None) -> Rig:
        from tagloc.core.camera import load_calibration
        from tagloc.core.rig import default_rig

        return default_rig(camera=calibration or load_calibration(self._need(CAMERA_FILE)))

    def _read_info(self) -> SessionInfo:
        p = self.path / SESSION_JSON
        if not p.exists():
            return SessionInfo(source="unknown", fps=0.0)
        doc = read_json(p, SessionError)
        if not isinstance(doc, dict):
            raise SessionError(f"{p}: not a JSON object")
        # Every tagloc writes both keys, so a file without them was made by hand: read as version 1.
        fmt = doc.get("format", FORMAT)
        if fmt != FORMAT:
            raise SessionError(f"{p}: format is {json.dumps(fmt)[:40]}, want {json.dumps(FORMAT)}")
        version = doc.get("version", VERSION)
        if isinstance(version, bool) or not isinstance(version, int) or version < 1:
            raise SessionError(f"{p}: version must be a whole number from 1, got {json.dumps(version)[:40]}")
        if version > VERSION:
            raise SessionError(
                f"{p}: version {json.dumps(version)[:40]} is newer than this tagloc reads ({VERSION}); update tagloc"
            )
        fps = doc.get("fps", 0.0)
        if fps is None:
            fps = 0.0
        if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not 0.0 <= fps <= MAX_FPS:
            raise SessionError(f"{p}: fps must be a number from 0 to {MAX_FPS:g}, got {json.dumps(fps)[:40]}")
        extra = {k: v for k, v in doc.items() if k not in ("format", "version", "source", "fps", "notes")}
        return SessionInfo(str(doc.get("source", "unknown")), float(fps), str(doc.get("notes", "")), extra)

    def _check_clock(self) -> None:
        """Refuse frames.csv with a repeated index or a timestamp that goes backwards; note forward jumps."""
        p = self.path / FRAMES_CSV
        if len(self.index) != len(np.unique(self.index)):
            _, first, counts = np.unique(self.index, return_index=True, return_counts=True)
            dup = int(self.index[np.sort(first[counts > 1])[0]])
            raise SessionError(f"{p}: frame index {dup} appears more than once")
        steps = np.diff(self.timestamps)
        back = np.flatnonzero(steps <= 0)
        if len(back):
            k = int(back[0]) + 1
            raise SessionError(
                f"{p}: frame {int(self.index[k])}: timestamp {seconds_text(self.timestamps[k])} s is not after the"
                f" previous frame's {seconds_text(self.timestamps[k - 1])} s (sort frames.csv by time, or fix the clock)"
            )
        for k in np.flatnonzero(steps > CLOCK_JUMP_S)[:5]:
            self.warnings.append(
                f"{p}: frame {int(self.index[k + 1])}: timestamp jumps {steps[k]:.4g} s forward "
                "(the track will be lost and found again)"
            )

    def _image_count(self) -> int | None:
        """How many images ``frames/`` holds (a temporary one a killed recorder left is none), read
        in one listing; None when it cannot be listed (each frame then says why it is unreadable)."""
        try:
            with os.scandir(self.path / FRAMES_DIR) as entries:
                return sum(
                    1
                    for e in entries
                    if os.path.splitext(e.name)[1].lower() in IMAGE_EXTENSIONS and ".tmp." not in e.name
                )
        except (FileNotFoundError, NotADirectoryError):
            return 0
        except OSError:
            return None

    def _check_images_listed(self, listed: int) -> None:
        """Refuse a frames.csv listing ``listed`` frames when frames/ holds fewer than half as many
        images: it is not these images' list (one of 2,000,000 frames beside 20 images took minutes
        to find each missing). Checked on the line count, before the lines are parsed, which took
        seconds for such a file. A recording cut short is not refused: each image is written before
        its line, so it lists no frame without one. A few missing frames are skipped and counted as
        they come."""
        have = self._image_count()
        if have is not None and 2 * have < listed:
            raise SessionError(
                f"{self.path / FRAMES_CSV}: lists {listed} frames but {self.path / FRAMES_DIR} holds"
                f" {have} images, fewer than half (is frames.csv another recording's?)"
            )

    def _frames_from_images(self) -> tuple[np.ndarray, np.ndarray]:
        """The frames of a session without frames.csv: the images named by their index, at the session's
        fps (``FALLBACK_FPS`` when it states none). Kept for hand-made one-camera sessions, with a
        warning, as their times are made up; a session of several cameras is refused, as its image
        names do not give the order of its frames in time."""
        p = self.path / FRAMES_CSV
        if len(self.rig) > 1:
            raise SessionError(
                f"{p}: missing; a session of {len(self.rig)} cameras needs it (its frames' times and cameras)"
            )
        try:
            # Listed with scandir, not glob: glob takes an unreadable directory for an empty one.
            with os.scandir(self.path / FRAMES_DIR) as entries:
                files = sorted(Path(e.path) for e in entries if os.path.splitext(e.name)[1].lower() in IMAGE_EXTENSIONS)
        except FileNotFoundError:
            files = []
        except OSError as exc:
            raise SessionError(f"{self.path / FRAMES_DIR}: cannot read ({exc.strerror})") from None
        if not files:
            raise SessionError(f"{self.path}: missing frames.csv and no images in frames/")
        fps = self.info.fps or FALLBACK_FPS
        named = [f for f in files if f.stem.isascii() and f.stem.isdigit()]
        idx = np.array([int(f.stem) for f in named], np.int64)
        if not len(idx):
            raise SessionError(f"{self.path}: missing frames.csv and no image in frames/ is named by its index")
        fps_from = "session.json's" if self.info.fps else "assumed: session.json states none"
        ignored = f"; {len(files) - len(named)} images not named by an index ignored" if len(named) < len(files) else ""
        warn_stderr(
            f"{p}: missing; frame times made up from the {len(idx)} image names at {fps:g} fps ({fps_from}){ignored}"
        )
        self.cameras = np.zeros(len(idx), np.int64)
        return idx, idx / fps

    def _read_frames_csv(self) -> tuple[np.ndarray, np.ndarray]:
        p = self.path / FRAMES_CSV
        if not p.exists():
            return self._frames_from_images()
        index, stamps, cams = [], [], []
        try:
            # -sig: a spreadsheet's byte-order mark (a frames.csv sorted there, as a refusal advises) is
            # fine, as in a map; it made the header line a malformed frame line.
            lines = p.read_text(encoding="utf-8-sig", errors="replace").splitlines(keepends=True)
        except OSError as exc:
            raise SessionError(f"{p}: cannot read ({exc.strerror})") from exc
        if lines and not lines[-1].endswith("\n") and (self.path / SESSION_JSON).exists():
            # tagloc ends every line with a newline: an unterminated last line is a write cut short by a
            # crash, and its number may be cut too ("12.5" -> "1"), so it is not trusted. Any other
            # line, the last one included, is the recording's own and must parse.
            lines = lines[:-1]
        listed = sum(1 for line in lines if line.strip())
        header = bool(lines) and lines[0].strip().lower().startswith("index")
        self._check_images_listed(listed - header)
        rows = csv.reader(lines)
        try:
            for row in rows:
                n = rows.line_num
                if not row or (n == 1 and row[0].strip().lower() == "index"):
                    _check_frames_header(row, f"{p}:{n}")
                    continue
                # Plain ASCII decimals only (the map's rule): int() and float() took "1_0" and "\u0661".
                i = decimal_integer(row[0])
                t = decimal_number(row[1]) if len(row) > 1 else None
                # A column beyond the camera is no part of the format: what it holds would be ignored.
                if i is None or t is None or not 0 <= i < 10**9 or len(row) > len(FRAMES_COLUMNS):
                    raise SessionError(f"{p}:{n}: want 'index,timestamp_s', got {shown(','.join(row))}")
                if not math.isfinite(t):
                    raise SessionError(f"{p}:{n}: timestamp is not finite")
                cam: int | None = 0
                if len(row) > 2:
                    cam_text = row[2].strip()
                    cam = decimal_integer(cam_text) if cam_text.isdigit() else None  # no sign
                    if cam is None or cam >= len(self.rig):
                        raise SessionError(
                            f"{p}:{n}: camera {shown(cam_text)} is not a camera of the rig (0-{len(self.rig) - 1})"
                        )
                index.append(i)
                stamps.append(t)
                cams.append(cam)
        except csv.Error as exc:
            # A field past the csv module's limit (a block of zeros a power cut left) or the like.
            raise SessionError(f"{p}:{rows.line_num}: not a frames.csv line ({exc})") from None
        if not index:
            raise SessionError(f"{p}: lists no frames")
        self.cameras = np.array(cams, np.int64)
        return np.array(index, np.int64), np.array(stamps, float)

    def __len__(self) -> int:
        return len(self.index)

    @property
    def camera(self) -> Camera:
        """The first camera's calibration."""
        return self.rig.cameras[0].camera

    def frame_path(self, index: int, camera: int = 0) -> Path | None:
        """Path of frame ``index``'s image (of rig camera ``camera``), whatever its extension, or None.

        A path that cannot be looked at (frames/ unreadable, a symlink loop) is returned, not taken
        for missing: reading it then says why it is unreadable, and the frame is skipped and counted
        like any unreadable frame (Path.exists() raised for the first and hid the second)."""
        stem = self.path / FRAMES_DIR / frame_stem(index, camera)
        for ext in IMAGE_EXTENSIONS:
            p = stem.with_suffix(ext)
            try:
                os.stat(p)
            except (FileNotFoundError, NotADirectoryError):
                continue
            except OSError:
                pass  # there, or maybe there, but unreadable: read_image names the reason
            return p
        return None

    def frames(self, with_images: bool = True) -> Iterator[Frame]:
        """Yield every frame in order; unreadable frames come with ``image=None`` and ``error`` set."""
        for i, t, c in zip(self.index, self.timestamps, self.cameras):
            c = int(c)
            if not with_images:
                yield Frame(int(i), float(t), None, c)
                continue
            p = self.frame_path(int(i), c)
            if p is None:
                err = f"frame {i}: image file missing"
                img = None
            else:
                img, err = read_image(p)
                err = None if err is None else f"frame {i}: {err}"
            if err:
                self.skipped.append((int(i), err))
            yield Frame(int(i), float(t), img, c, err)

    def groundtruth(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(timestamps (N,), T_world_body (N, 4, 4)) when the session has ground truth, else None."""
        return None if self._groundtruth is None else tum_poses(self._groundtruth)


class SessionWriter:
    """Write a session as frames arrive; safe to kill at any moment."""

    def __init__(
        self,
        path: str | Path,
        smap: StickerMap,
        rig: Rig,
        info: SessionInfo,
        jpeg_quality: int = 90,
        image_ext: str = ".jpg",
    ):
        self.path = Path(path)
        frames = self.path / FRAMES_DIR
        try:
            frames.mkdir(parents=True, exist_ok=True)
            if (self.path / FRAMES_CSV).exists() and any(frames.iterdir()):
                raise SessionError(f"{self.path}: already holds a session; choose a new directory")
            for stale in frames.glob("*.tmp.*"):
                stale.unlink()  # an image a killed recorder was writing (never listed in frames.csv)
            (self.path / SESSION_JSON).write_text(json.dumps(info.to_json(), indent=2) + "\n", encoding="utf-8")
            save_map(smap, self.path / MAP_FILE)
            save_rig(rig, self.path / RIG_FILE)
            self._csv = (self.path / FRAMES_CSV).open("w", encoding="utf-8", buffering=1)
        except OSError as exc:
            raise SessionError(f"{exc.filename or self.path}: cannot write ({exc.strerror})") from None
        self.jpeg_quality = int(jpeg_quality)
        self.image_ext = image_ext
        # One camera: the original two columns, so such sessions stay byte-identical.
        self.multi_camera = len(rig) > 1
        self._csv.write(frames_csv_header(self.multi_camera))
        self._csv.flush()
        self.count = 0

    def write(self, index: int, timestamp: float, image: np.ndarray, camera: int = 0) -> None:
        """Write one frame of rig camera ``camera``: image first (atomic rename), then its frames.csv
        line, flushed. ``index`` is unique over the session (all cameras)."""
        if camera and not self.multi_camera:
            raise SessionError(f"{self.path}: frame {index} from camera {camera}, but the rig has one camera")
        final = self.path / FRAMES_DIR / f"{frame_stem(index, camera)}{self.image_ext}"
        tmp = final.with_name(final.stem + ".tmp" + self.image_ext)
        params = [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality] if self.image_ext == ".jpg" else []
        if not cv2.imwrite(str(tmp), image, params):
            raise SessionError(f"{tmp}: cannot write frame")
        os.replace(tmp, final)
        self._csv.write(frames_csv_line(index, timestamp, camera, self.multi_camera))
        self._csv.flush()
        self.count += 1

    def write_encoded(self, index: int, timestamp: float, data: bytes, ext: str = ".jpg", camera: int = 0) -> None:
        """Write one frame already encoded (e.g. a camera's JPEG, kept byte for byte), crash-safe like :meth:`write`."""
        if camera and not self.multi_camera:
            raise SessionError(f"{self.path}: frame {index} from camera {camera}, but the rig has one camera")
        final = self.path / FRAMES_DIR / f"{frame_stem(index, camera)}{ext}"
        tmp = final.with_name(final.stem + ".tmp" + ext)
        tmp.write_bytes(data)
        os.replace(tmp, final)
        self._csv.write(frames_csv_line(index, timestamp, camera, self.multi_camera))
        self._csv.flush()
        self.count += 1

    def update_info(self, info: SessionInfo) -> None:
        """Rewrite ``session.json`` with ``info`` (atomic rename: a kill leaves the old or the new)."""
        tmp = self.path / (SESSION_JSON + ".tmp")
        try:
            tmp.write_text(json.dumps(info.to_json(), indent=2) + "\n", encoding="utf-8")
            os.replace(tmp, self.path / SESSION_JSON)
        except OSError as exc:
            raise SessionError(f"{exc.filename or self.path}: cannot write ({exc.strerror})") from None

    def close(self) -> None:
        if not self._csv.closed:
            self._csv.flush()
            os.fsync(self._csv.fileno())
            self._csv.close()

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
