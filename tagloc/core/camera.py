"""Camera intrinsics with OpenCV's distortion model, and their calibration files.

Two file formats are read: OpenCV FileStorage YAML (what ``cv2.calibrateCamera`` users write with
``cv2.FileStorage``: ``camera_matrix``, ``distortion_coefficients``, ``image_width``,
``image_height``) and ROS ``camera_info`` YAML (``camera_calibration``'s output, or a dumped
``sensor_msgs/CameraInfo`` with ``K``/``D``/``width``/``height``). tagloc writes the OpenCV form.
Only OpenCV's pinhole distortion is read: a ROS ``distortion_model`` other than plumb_bob or
rational_polynomial (e.g. equidistant, a fisheye) is refused, as is an OpenCV file marked
``fisheye_model: 1`` (OpenCV's calibration sample run with cv2.fisheye).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import yaml

from tagloc.core.errors import CalibrationError

MAX_SIZE_PX = 100_000  # an image side beyond this is a typo, not a sensor
# Focal lengths a real lens and sensor give, in pixels: a fisheye on a small sensor has a few
# hundred, a long lens on a large one tens of thousands. Outside, the file is wrong (and the
# projection's arithmetic overflows near 0 and infinity).
MIN_FOCAL_PX, MAX_FOCAL_PX = 1.0, 1e6
# OpenCV's distortion coefficients: fitted lenses give |k| up to tens (the rational model's
# numerator and denominator terms together); 1e4 is no lens.
MAX_DISTORTION = 1e4
# ROS camera_info distortion models whose coefficients are OpenCV's pinhole model (k1, k2, p1, p2[,
# k3[, k4, k5, k6]]), the one tagloc projects with; a missing model is plumb_bob (ROS's default).
# Any other, e.g. equidistant (fisheye k1..k4 of the angle), is a different projection: its
# coefficients read as OpenCV's move a point 50 degrees off-axis by 155 px (focal length 420 px).
PINHOLE_MODELS = ("plumb_bob", "rational_polynomial")
# Points nearer than this in front of the camera (m) are not projected: the pinhole division blows
# up at the camera's plane, and nothing tagloc looks at (the floor, 1 m and more below the vest) is
# that close.
MIN_DEPTH_M = 0.05
# How far off the optical axis the search for the distortion's fold goes, as tan(angle): 10 is 84
# deg, beyond any lens tagloc models; a polynomial still growing there is taken never to fold.
FOLD_SEARCH_MAX = 10.0
# Steps of that search: 1e-3 in tan(angle) (under 0.06 deg), so the fold is found within a step.
FOLD_SEARCH_STEPS = 10_000


@dataclass
class Camera:
    """A pinhole camera with OpenCV distortion.

    Attributes:
        K: (3, 3) intrinsic matrix, pixels.
        dist: (N,) OpenCV distortion coefficients (k1, k2, p1, p2[, k3, ...]), N in 4, 5, 8, 12, 14.
        width, height: image size, pixels.
    """

    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    width: int = 1296
    height: int = 972

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, float).reshape(3, 3)
        self.dist = np.asarray(self.dist, float).ravel()
        self.width = int(self.width)
        self.height = int(self.height)

    @property
    def fx(self) -> float:
        """Horizontal focal length, px."""
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        """Vertical focal length, px."""
        return float(self.K[1, 1])

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) as OpenCV wants it."""
        return self.width, self.height

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Project camera-frame points (N, 3) (z forward, must be > 0) to distorted pixels (N, 2)."""
        pts = np.asarray(points_cam, float).reshape(-1, 1, 3)
        if len(pts) == 0:
            return np.zeros((0, 2))
        img, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist)
        return img.reshape(-1, 2)

    def fold_radius(self) -> float:
        """How far off the optical axis (as tan(angle), the normalised radius) the projection is
        faithful: where OpenCV's radial distortion stops growing with the angle, or inf if it never
        does. Beyond it the polynomial folds back towards the image centre, so :meth:`project` puts
        points far outside the field of view into the image: the default camera's k1 = 0.1,
        k2 = -0.2 fold at 1.08 (47 deg), and a point 58 deg left of the axis (the half-FOV is 27
        deg) lands at x = 762 px, right of the centre of the 1296 px image. Radial terms only: the
        tangential terms of a fitted lens are a small correction where the radial polynomial still
        grows."""
        return _fold_radius(tuple(float(d) for d in self.dist))

    def project_in_view(self, points_cam: np.ndarray, min_depth: float = MIN_DEPTH_M) -> np.ndarray | None:
        """:meth:`project` of camera-frame points (N, 3), or None when any point is nearer than
        ``min_depth`` in front of the camera (or behind it) or beyond :meth:`fold_radius`, where the
        pixel it would be given is not where the point is. Points inside the fold radius project
        faithfully, so testing their pixels against the image's bounds tells whether they are in it."""
        pts = np.asarray(points_cam, float).reshape(-1, 3)
        if np.any(pts[:, 2] < min_depth):
            return None
        if np.any(np.hypot(pts[:, 0], pts[:, 1]) >= self.fold_radius() * pts[:, 2]):
            return None
        return self.project(pts)

    def undistort_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """Map distorted pixels (N, 2) to ideal (undistorted) pixels of the same K, (N, 2)."""
        pts = np.asarray(pixels, float).reshape(-1, 1, 2)
        if len(pts) == 0 or not np.any(self.dist):
            return pts.reshape(-1, 2).copy()
        return cv2.undistortPoints(pts, self.K, self.dist, P=self.K).reshape(-1, 2)

    def scaled(self, factor: float) -> Camera:
        """The same camera at another resolution (K scaled, distortion unchanged)."""
        K = self.K.copy()
        K[:2] *= factor
        # Pixel centres: OpenCV's (0,0) is a pixel centre, so the principal point shifts by half.
        K[0, 2] = (self.K[0, 2] + 0.5) * factor - 0.5
        K[1, 2] = (self.K[1, 2] + 0.5) * factor - 0.5
        return Camera(K, self.dist.copy(), round(self.width * factor), round(self.height * factor))


@lru_cache(maxsize=64)
def _fold_radius(dist: tuple[float, ...]) -> float:
    """The first normalised radius where r * radial(r) of OpenCV's model stops increasing (or its
    rational denominator reaches 0); inf if neither happens up to ``FOLD_SEARCH_MAX``. Cached: the
    audit and the simulator ask for every sticker of every frame, with one or two lenses."""
    r = np.linspace(0.0, FOLD_SEARCH_MAX, FOLD_SEARCH_STEPS + 1)[1:]
    num, den = _radial_terms(dist, r)
    bad = den <= 0
    rd = r * num / np.where(bad, 1.0, den)
    bad[1:] |= np.diff(rd) <= 0
    bad[0] |= rd[0] <= 0
    first = int(np.argmax(bad))
    if not bad[first]:
        return math.inf
    # The last radius before the fold (the first sample, if the lens folds at once).
    return float(r[max(first - 1, 0)])


def _radial_terms(dist: tuple[float, ...] | np.ndarray, r: np.ndarray | float) -> tuple:
    """Numerator and denominator of OpenCV's radial factor at normalised radius ``r``:
    (1 + k1 r^2 + k2 r^4 + k3 r^6, 1 + k4 r^2 + k5 r^4 + k6 r^6), coefficients absent taken as 0."""
    k = np.zeros(6)
    radial = [dist[i] for i in (0, 1, 4, 5, 6, 7) if i < len(dist)]  # k1, k2, k3, k4, k5, k6
    k[: len(radial)] = radial
    r2 = r * r
    return 1 + r2 * (k[0] + r2 * (k[1] + r2 * k[2])), 1 + r2 * (k[3] + r2 * (k[4] + r2 * k[5]))


# The focal length (px) of the reference camera (default_camera) for which tagloc's pixel and
# angular defaults were set and measured; other cameras scale them by their own.
REFERENCE_FOCAL_PX = 1285.7


def pixel_scale(camera: Camera) -> float:
    """How many times larger than the reference camera's (:func:`default_camera`, the Pi camera v1
    at 1296 x 972, for which tagloc's figures were measured) ``camera``'s pixels are in angle, at
    least 1. An angle read from image positions is that much less sure at the same pixel noise,
    and an image pyramid reaches the same angular scale that many times sooner. A finer camera
    keeps the measured figures (they also hold errors that are not in pixels)."""
    return max(1.0, REFERENCE_FOCAL_PX / float(camera.K[0, 0]))


def default_camera() -> Camera:
    """Raspberry Pi camera v1 (OV5647) at 1296x972: 3.6 mm lens, 1.4 um pixels binned 2x2.

    fx = fy = 3.6 mm / 2.8 um = 1285.7 px, principal point at the image centre. The mild barrel
    distortion is typical of that lens, so that undistortion is always exercised.
    """
    f = 3.6e-3 / 2.8e-6
    K = np.array([[f, 0.0, (1296 - 1) / 2], [0.0, f, (972 - 1) / 2], [0.0, 0.0, 1.0]])
    return Camera(K, np.array([0.10, -0.20, 0.0, 0.0, 0.0]), 1296, 972)


def save_calibration(camera: Camera, path: str | Path, extra: dict | None = None) -> None:
    """Write ``camera`` as OpenCV FileStorage YAML; ``extra`` adds keys (numbers, strings, arrays)
    after the four tagloc reads, which loading ignores."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise CalibrationError(f"{path}: cannot write calibration")
    fs.write("image_width", camera.width)
    fs.write("image_height", camera.height)
    fs.write("camera_matrix", camera.K)
    fs.write("distortion_coefficients", camera.dist.reshape(1, -1))
    for key, value in (extra or {}).items():
        fs.write(key, value)
    fs.release()


def check_calibration(camera: Camera, path: Path | str) -> Camera:
    """``camera`` if tagloc can run with it, else :class:`CalibrationError` naming ``path`` (the file,
    or where a calibration came from, such as a bag's CameraInfo topic) and what is wrong."""
    K = camera.K
    for name, values in (("camera_matrix", K), ("distortion_coefficients", camera.dist)):
        if not np.all(np.isfinite(values)):
            raise CalibrationError(f"{path}: {name} contains NaN or inf")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1 or np.any(K[2, :2] != 0) or K[1, 0] != 0:
        raise CalibrationError(f"{path}: camera_matrix is not a valid intrinsic matrix: {K.tolist()}")
    if not (MIN_FOCAL_PX <= K[0, 0] <= MAX_FOCAL_PX and MIN_FOCAL_PX <= K[1, 1] <= MAX_FOCAL_PX):
        raise CalibrationError(
            f"{path}: focal length fx {K[0, 0]:g}, fy {K[1, 1]:g} px is outside {MIN_FOCAL_PX:g}-{MAX_FOCAL_PX:g} px"
        )
    if np.max(np.abs(camera.dist), initial=0.0) > MAX_DISTORTION:
        raise CalibrationError(f"{path}: a distortion coefficient is beyond +-{MAX_DISTORTION:g}")
    if not (0 < camera.width <= MAX_SIZE_PX and 0 < camera.height <= MAX_SIZE_PX):
        raise CalibrationError(
            f"{path}: image size {camera.width}x{camera.height} is not positive and at most {MAX_SIZE_PX} px a side"
        )
    cx, cy = K[0, 2], K[1, 2]
    if not (-0.5 <= cx <= camera.width - 0.5 and -0.5 <= cy <= camera.height - 0.5):
        raise CalibrationError(
            f"{path}: principal point ({cx:.1f}, {cy:.1f}) px is outside the {camera.width}x{camera.height} image"
        )
    if camera.dist.size not in (4, 5, 8, 12, 14):
        raise CalibrationError(f"{path}: {camera.dist.size} distortion coefficients (want 4, 5, 8, 12 or 14)")
    if why := fold_problem(camera):
        raise CalibrationError(f"{path}: {why}")
    return camera


def fold_problem(camera: Camera) -> str | None:
    """Why ``camera``'s distortion cannot be a lens's over its image, or None: OpenCV's radial model
    maps the off-axis radius r to r (1 + k1 r^2 + ...) / (1 + k4 r^2 + ...), which a lens makes grow
    with r all the way to the image's corners. Where it turns back first (:meth:`Camera.fold_radius`)
    it reaches a largest radius, and image points beyond that one have no ray at all (undistortion
    then puts them anywhere: ``D = [50, -900, 0, 0, 0]`` gave a replay without one pose). A fitted
    lens that folds just outside its image (the default camera's 0.1, -0.2 at 1.08, its corners at
    0.63) is fine: only the image is measured."""
    fold = camera.fold_radius()
    if not math.isfinite(fold):
        return None
    num, den = _radial_terms(camera.dist, fold)
    peak = fold * num / den
    # The image's farthest corner (pixel edges, not centres), as a distorted normalised radius.
    cx, cy = camera.K[0, 2], camera.K[1, 2]
    du = max(cx + 0.5, camera.width - 0.5 - cx) / camera.K[0, 0]
    dv = max(cy + 0.5, camera.height - 0.5 - cy) / camera.K[1, 1]
    corner = math.hypot(du, dv)
    if corner < peak:
        return None
    return (
        f"distortion_coefficients [{', '.join(f'{d:.4g}' for d in camera.dist)}] are no lens over"
        f" the {camera.width}x{camera.height} image: the model turns back {math.degrees(math.atan(fold)):.0f} deg"
        f" off the axis, reaching {peak:.3g} of the {corner:.3g} (normalised radius) the image's corners need,"
        " so part of the image has no ray (recalibrate the camera)"
    )


def _unsupported_model(what: str) -> str:
    return (
        f"{what} is not supported (tagloc reads {' and '.join(PINHOLE_MODELS)}, OpenCV's pinhole model); "
        "calibrate the camera with 'tagloc calibrate camera' (--rational for a wide lens)"
    )


def distortion_model_problem(model: object) -> str | None:
    """Why a ROS ``distortion_model`` cannot be read as OpenCV's coefficients, or None when it can.
    None (no such field) and "" (a CameraInfo message's unset string) are ROS's default, plumb_bob."""
    if model is None or model == "" or model in PINHOLE_MODELS:
        return None
    return _unsupported_model(f"distortion_model {str(model)[:40]!r}")


def _size(value: object, path: Path, name: str) -> int:
    """An image side in pixels; the message echoes what the file says, not a conversion of it."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value:
        raise CalibrationError(f"{path}: {name} must be a whole number of pixels, got {str(value)[:40]!r}")
    if not (abs(value) <= MAX_SIZE_PX and value == int(value)):
        raise CalibrationError(f"{path}: {name} must be a whole number of pixels 1 to {MAX_SIZE_PX}, got {value!r}")
    return int(value)


def _node_size(fs: cv2.FileStorage, path: Path, name: str) -> int:
    node = fs.getNode(name)
    if not (node.isInt() or node.isReal()):
        text = node.string() if node.isString() else f"a {('sequence' if node.isSeq() else 'mapping')}"
        raise CalibrationError(f"{path}: {name} must be a whole number of pixels, got {text[:40]!r}")
    return _size(node.real(), path, name)


class _DuplicateKey(yaml.YAMLError):
    """A mapping of a YAML file names a key twice (``line``, ``first``: 1-based lines); its text is
    the message's, after the file's name, for either YAML form."""

    def __init__(self, key: object, line: int, first: int) -> None:
        super().__init__(f"line {line}: key {key!r} appears again (first on line {first})")
        self.key, self.line, self.first = key, line, first


# A key at the top level of an OpenCV FileStorage YAML file: a name at column 0 followed by ":".
_TOP_KEY = re.compile(r"^([A-Za-z_][\w-]*)[ \t]*:", re.MULTILINE)
# NaN or infinity written as Python or numpy prints them (nan, inf, -inf, infinity): OpenCV reads
# only its own .nan and .inf, and says of these "readRawData can only be used to read plain sequences".
_PLAIN_NONFINITE = re.compile(r"(?<![\w.])[+-]?(nan|inf(inity)?)(?![\w.])", re.IGNORECASE)


def _top_level_blocks(text: str) -> list[tuple[str, int, str]]:
    """(key, line number, its text up to the next key) for each top-level key of an OpenCV YAML file."""
    found = list(_TOP_KEY.finditer(text))
    ends = [m.start() for m in found[1:]] + [len(text)]
    return [(m.group(1), text.count("\n", 0, m.start()) + 1, text[m.end() : e]) for m, e in zip(found, ends)]


def _check_opencv_text(path: Path, text: str) -> None:
    """Refuse what OpenCV's parser takes without a word or reports cryptically: a key given twice
    (it keeps the first, PyYAML the last: the two formats would disagree) and NaN or inf in a
    matrix written as ``nan``/``inf``."""
    blocks = _top_level_blocks(text)
    seen: dict[str, int] = {}
    for key, line, _ in blocks:
        if key in seen:
            raise CalibrationError(f"{path}: {_DuplicateKey(key, line, seen[key])}")
        seen[key] = line
    for key, _, body in blocks:
        if key in ("camera_matrix", "distortion_coefficients") and _PLAIN_NONFINITE.search(body):
            raise CalibrationError(f"{path}: {key} contains NaN or inf")


def _load_opencv(path: Path, text: str) -> Camera:
    """Read an OpenCV FileStorage calibration; ``text``: the file's text (checked first, and parsed
    instead of the file when it starts with a byte-order mark, which OpenCV's parser refuses)."""
    bom = text.startswith("\ufeff")
    text = text.removeprefix("\ufeff")
    _check_opencv_text(path, text)
    try:
        return _read_opencv(path, text if bom else None)
    except (cv2.error, SystemError) as exc:
        # FileStorage's parser reports a cut or inconsistent file as cv2.error (raised from its
        # constructor it arrives wrapped in a SystemError); keep the parser's reason only.
        err = exc if isinstance(exc, cv2.error) else (exc.__cause__ or exc.__context__ or exc)
        reason = (getattr(err, "err", None) or str(err) or type(err).__name__).strip().splitlines()[-1][:200]
        raise CalibrationError(f"{path}: not a valid OpenCV FileStorage calibration ({reason})") from None
    except (UnicodeError, ValueError, TypeError, OverflowError):
        # What the OpenCV binding makes of bytes that are not UTF-8 or of values of the wrong kind.
        raise CalibrationError(f"{path}: not a valid OpenCV FileStorage calibration (malformed values)") from None


def _read_opencv(path: Path, text: str | None = None) -> Camera:
    """The calibration in ``path``, or in ``text`` (the file's contents) when given."""
    if text is None:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    else:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    if not fs.isOpened():
        raise CalibrationError(f"{path}: not a readable OpenCV FileStorage file")
    try:
        names = {"camera_matrix", "distortion_coefficients", "image_width", "image_height"}
        missing = [n for n in sorted(names) if fs.getNode(n).empty()]
        if missing:
            raise CalibrationError(f"{path}: missing {', '.join(missing)}")
        # OpenCV's calibration sample writes fisheye_model (1 for cv2.fisheye's k1..k4); other
        # tools copy ROS's distortion_model string.
        fisheye = fs.getNode("fisheye_model")
        if not fisheye.empty() and (fisheye.isInt() or fisheye.isReal()) and fisheye.real() != 0:
            why = _unsupported_model(f"fisheye_model {fisheye.real():g} (cv2.fisheye's k1..k4)")
            raise CalibrationError(f"{path}: {why}")
        node = fs.getNode("distortion_model")
        model = None if node.empty() else node.string() if node.isString() else "(not a name)"
        if why := distortion_model_problem(model):
            raise CalibrationError(f"{path}: {why}")
        K = fs.getNode("camera_matrix").mat()
        dist = fs.getNode("distortion_coefficients").mat()
        if K is None or dist is None or K.shape != (3, 3):
            raise CalibrationError(f"{path}: camera_matrix must be a 3x3 matrix")
        w, h = _node_size(fs, path, "image_width"), _node_size(fs, path, "image_height")
        return Camera(K.astype(float), dist.astype(float).ravel(), w, h)
    finally:
        fs.release()


def _ros_matrix(node: object, path: Path, name: str) -> np.ndarray:
    data = node.get("data") if isinstance(node, dict) else node
    try:
        return np.asarray(data, float).ravel()
    except (TypeError, ValueError, OverflowError):
        raise CalibrationError(f"{path}: {name} is not a list of numbers") from None


def _load_ros(path: Path, doc: dict) -> Camera:
    if why := distortion_model_problem(doc.get("distortion_model")):
        raise CalibrationError(f"{path}: {why}")
    if "camera_matrix" in doc:  # camera_calibration's ost.yaml
        K = _ros_matrix(doc["camera_matrix"], path, "camera_matrix")
        dist = _ros_matrix(doc.get("distortion_coefficients", [0, 0, 0, 0, 0]), path, "distortion_coefficients")
        w, h = doc.get("image_width"), doc.get("image_height")
        names = ("image_width", "image_height")
    elif "K" in doc or "k" in doc:  # a dumped sensor_msgs/CameraInfo
        K = _ros_matrix(doc.get("K", doc.get("k")), path, "K")
        d = doc.get("D", doc.get("d"))
        dist = _ros_matrix([0, 0, 0, 0, 0] if d is None or (isinstance(d, list) and not d) else d, path, "D")
        w, h = doc.get("width"), doc.get("height")
        names = ("width", "height")
    else:
        raise CalibrationError(f"{path}: neither OpenCV nor ROS camera_info calibration (no camera_matrix or K)")
    if K.size != 9:
        raise CalibrationError(f"{path}: camera matrix has {K.size} values, want 9")
    if w is None or h is None:
        raise CalibrationError(f"{path}: missing image width/height")
    return Camera(K.reshape(3, 3), dist, _size(w, path, names[0]), _size(h, path, names[1]))


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader refusing a mapping that names a key twice: it keeps the last silently
    (a camera_info with a second ``K:`` had replay use it, 95 cm off), and OpenCV's parser the first."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: dict[object, int] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue  # "<<" merges another mapping: the base loader takes it apart
            key = self.construct_object(key_node, deep=deep)
            try:
                first = seen.setdefault(key, key_node.start_mark.line + 1)
            except TypeError:
                continue  # an unhashable key: the base loader refuses it
            if first != key_node.start_mark.line + 1:
                raise _DuplicateKey(key, key_node.start_mark.line + 1, first)
        return super().construct_mapping(node, deep=deep)


def load_calibration(path: str | Path) -> Camera:
    """Load a camera from OpenCV FileStorage YAML or ROS camera_info YAML (format auto-detected)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot read calibration ({exc.strerror})") from None
    except ValueError:  # e.g. a NUL byte in the name
        raise CalibrationError(f"{path!r}: not a usable file name") from None
    if text.removeprefix("\ufeff").lstrip().startswith("%YAML") or "!!opencv-matrix" in text:
        return check_calibration(_load_opencv(path, text), path)
    try:
        # A dumped message may end with "---" (the next document's separator): empty documents are fine.
        docs = [d for d in yaml.load_all(text, Loader=_UniqueKeyLoader) if d is not None]
    except _DuplicateKey as exc:
        raise CalibrationError(f"{path}: {exc}") from None
    except yaml.YAMLError as exc:
        line = getattr(getattr(exc, "problem_mark", None), "line", None)
        where = f" line {line + 1}:" if line is not None else ""
        raise CalibrationError(f"{path}:{where} not valid YAML") from None
    except (RecursionError, ValueError, OverflowError):
        raise CalibrationError(f"{path}: not a calibration YAML file") from None
    if len(docs) > 1:
        raise CalibrationError(f"{path}: {len(docs)} YAML documents, want one calibration")
    doc = docs[0] if docs else None
    if not isinstance(doc, dict):
        raise CalibrationError(f"{path}: not a calibration mapping")
    return check_calibration(_load_ros(path, doc), path)
