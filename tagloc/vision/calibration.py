"""Camera intrinsics from views of the ChArUco board, all on OpenCV.

Per view, ``cv2.aruco.CharucoDetector`` finds the markers and the identified chessboard corners.
From all usable views a well-spread subset is kept (farthest-point sampling over where the board
sits in the image, how large it appears and how it is tilted: many near-identical frames of a video
add no information but bias the fit to one region), then ``cv2.calibrateCameraExtended`` fits
K and the distortion and gives each parameter's standard deviation. Views whose own reprojection
error is far above the rest (a blurred or misdetected frame) are dropped and the fit repeated once.

The fit is refused when no view is tilted: a board parallel to the image plane is imaged as an
affine copy of itself, whose size says focal length over distance and nothing about either (the
degenerate case of Zhang's method, which needs planes of different orientations). OpenCV then
still returns a focal length, anywhere along that ridge, with a standard deviation that claims
hundredths of a pixel (its covariance is a pseudo-inverse, which drops the unobservable direction).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from tagloc.core.camera import Camera
from tagloc.core.charuco import DEFAULT_BOARD, BoardSpec, make_board
from tagloc.core.errors import CalibrationError
from tagloc.vision.image import as_gray

#: Names of calibrateCameraExtended's stdDeviationsIntrinsics entries, in order.
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")


@dataclass(frozen=True)
class CalibrationConfig:
    """How views are chosen and the model fitted.

    Attributes:
        min_corners: a view needs this many identified corners (6: the homography of a plane has
            8 unknowns; fewer corners pin almost nothing and are usually a misdetection).
        max_views: keep at most this many views (beyond about 30 well-spread views the
            intrinsics' uncertainty hardly shrinks while the fit's time grows with every view).
        min_views: refuse to calibrate from fewer (the 9 parameters need several distinct tilts).
        outlier_factor: drop views whose RMS error exceeds this many times the median view's
            (and 1 px) and refit once.
        rational: fit the 8-coefficient rational model (wide-angle lenses) instead of 5.
        fix_k3: hold k3 at zero (for narrow lenses whose k3 is not observable).
        min_tilt_deg: refuse the fit when no view used has the board tilted this much from
            parallel to the image (see the module notes). Measured on 12 rendered views through
            the Pi camera v1 at 648x486 and 1296x972 (3 seeds per bound on the tilt): with the
            most tilted view at 0.4-1.9 degrees fx was 0.4-49 % off with a stated sigma of
            0.005-0.011 px; at 2.1-2.5 degrees 0.02-3.7 % off, the sigma still 0.01 px in 7 of 8
            sets; at 2.7-3.7 degrees within 1.6 % (the sigma honest at 648 wide, collapsed in 4 of
            6 sets at 1296 wide, up to 3.2 degrees, but those within 0.3 %); from 4.3 degrees
            within 1 % with honest sigmas. 3 refuses every set that was percents off with a
            hundredth-pixel sigma; just above it the report warns (apps.calibrate.WEAK_TILT_DEG).
    """

    min_corners: int = 6
    max_views: int = 30
    min_views: int = 5
    outlier_factor: float = 3.0
    rational: bool = False
    fix_k3: bool = False
    min_tilt_deg: float = 3.0


@dataclass
class BoardView:
    """The board as found in one image.

    Attributes:
        index: the image's index in the source (frame number or file order).
        corners: (N, 2) float32 identified chessboard corners, distorted pixels.
        ids: (N,) int corner IDs on the board.
        object_points: (N, 3) float32 the corners on the board, metres, z = 0.
    """

    index: int
    corners: np.ndarray
    ids: np.ndarray
    object_points: np.ndarray


@dataclass
class CalibrationResult:
    """A fitted camera and how well the views support it.

    Attributes:
        camera: the fitted intrinsics.
        rms_px: overall RMS reprojection error, pixels.
        std: one-sigma standard deviation of each fitted parameter (px for fx..cy, unitless for
            the distortion), by :data:`INTRINSIC_NAMES` name.
        view_rms_px: (V,) RMS error of each view used.
        views: the views used, in fit order.
        detected: how many images showed the board well enough to use.
        images: how many images were read.
        dropped_outliers: indices of views dropped for a high error.
        unreadable: images that could not be read (skipped).
        view_tilt: (V,) each view's board tilt, radians: the angle between the board's normal and
            the optical axis in the fitted pose (0 for a board parallel to the image).
    """

    camera: Camera
    rms_px: float
    std: dict[str, float]
    view_rms_px: np.ndarray
    views: list[BoardView]
    detected: int
    images: int
    dropped_outliers: list[int] = field(default_factory=list)
    unreadable: int = 0
    view_tilt: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def corners(self) -> np.ndarray:
        """(N, 2) every corner used in the fit, pixels."""
        return np.vstack([v.corners for v in self.views]) if self.views else np.zeros((0, 2))


class BoardDetector:
    """Finds the board of ``spec`` in images."""

    def __init__(self, spec: BoardSpec = DEFAULT_BOARD) -> None:
        self.spec = spec
        self.board = make_board(spec)
        self._detector = cv2.aruco.CharucoDetector(self.board)

    def detect(self, image: np.ndarray, index: int = 0, min_corners: int = 6) -> BoardView | None:
        """The board's identified corners in ``image``, or None when too few or all on one line."""
        corners, ids, _, _ = self._detector.detectBoard(as_gray(image))
        if ids is None or len(ids) < min_corners:
            return None
        if self.board.checkCharucoCornersCollinear(ids):
            return None
        obj, img = self.board.matchImagePoints(corners, ids)
        return BoardView(
            index, img.reshape(-1, 2).astype(np.float32), ids.ravel(), obj.reshape(-1, 3).astype(np.float32)
        )


def _descriptor(view: BoardView, size: tuple[int, int]) -> np.ndarray:
    """Where the board is (centroid, fraction of the image), its apparent size and its tilt.

    Tilt: the perspective row of the board-to-image homography times the board's extent, i.e.
    how much the image scale changes across the board (0 for a fronto-parallel board).
    """
    w, h = size
    pts = view.corners.astype(np.float64)
    centre = pts.mean(axis=0) / np.array([w, h])
    area = cv2.contourArea(cv2.convexHull(pts.astype(np.float32)))
    scale = np.sqrt(max(area, 1.0) / (w * h))
    H, _ = cv2.findHomography(view.object_points[:, :2].astype(np.float64), pts)
    if H is None:
        return np.array([*centre, scale, 0.0, 0.0])
    extent = float(np.ptp(view.object_points[:, :2], axis=0).max())
    tilt = H[2, :2] / H[2, 2] * extent
    return np.array([*centre, scale, *np.clip(tilt, -1.0, 1.0)])


def select_views(views: list[BoardView], size: tuple[int, int], max_views: int) -> list[BoardView]:
    """A well-spread subset of at most ``max_views`` views.

    Farthest-point sampling over :func:`_descriptor`: start from the view with the most corners,
    then repeatedly add the view farthest from all chosen ones (ties: more corners first).
    """
    if len(views) <= max_views:
        return list(views)
    desc = np.array([_descriptor(v, size) for v in views])
    counts = np.array([len(v.ids) for v in views], float)
    chosen = [int(np.argmax(counts))]
    dmin = np.linalg.norm(desc - desc[chosen[0]], axis=1)
    while len(chosen) < max_views:
        # A small bonus for more corners only breaks near-ties between equally distant views.
        k = int(np.argmax(dmin + 1e-3 * counts / counts.max()))
        chosen.append(k)
        dmin = np.minimum(dmin, np.linalg.norm(desc - desc[k], axis=1))
    return [views[k] for k in sorted(chosen)]


def _flags(cfg: CalibrationConfig) -> int:
    flags = 0
    if cfg.rational:
        flags |= cv2.CALIB_RATIONAL_MODEL
    if cfg.fix_k3:
        flags |= cv2.CALIB_FIX_K3
    return flags


def _fit(views: list[BoardView], size: tuple[int, int], cfg: CalibrationConfig) -> tuple:
    obj = [v.object_points.reshape(-1, 1, 3) for v in views]
    img = [v.corners.reshape(-1, 1, 2) for v in views]
    w, h = size
    # Start from a plausible pinhole (focal about the image width) so the first iterations converge.
    K0 = np.array([[float(w), 0.0, (w - 1) / 2], [0.0, float(w), (h - 1) / 2], [0.0, 0.0, 1.0]])
    n_dist = 8 if cfg.rational else 5
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    try:
        rms, K, dist, rvecs, _, std_in, _, per_view = cv2.calibrateCameraExtended(
            obj, img, size, K0, np.zeros(n_dist), flags=_flags(cfg) | cv2.CALIB_USE_INTRINSIC_GUESS, criteria=criteria
        )
    except cv2.error as exc:
        raise CalibrationError(f"OpenCV could not calibrate from {len(views)} views: {exc.err}") from exc
    return float(rms), K, dist.ravel()[:n_dist], std_in.ravel(), per_view.ravel(), _tilts(rvecs)


def _tilts(rvecs) -> np.ndarray:
    """(V,) angle between each view's board normal (its z axis) and the optical axis, radians."""
    normal_z = np.array([cv2.Rodrigues(np.asarray(r, float))[0][2, 2] for r in rvecs])
    return np.arccos(np.clip(np.abs(normal_z), 0.0, 1.0))


def calibrate_views(
    views: list[BoardView], size: tuple[int, int], images: int, cfg: CalibrationConfig = CalibrationConfig()
) -> CalibrationResult:
    """Fit the camera to ``views`` of images of ``size`` (width, height); see the module notes."""
    detected = len(views)
    if detected < cfg.min_views:
        raise CalibrationError(
            f"the board was found in {detected} of {images} images; need at least {cfg.min_views} "
            "(show the whole board, in focus, at several tilts and across the image)"
        )
    chosen = select_views(views, size, cfg.max_views)
    rms, K, dist, std_in, per_view, tilt = _fit(chosen, size, cfg)
    limit = max(cfg.outlier_factor * float(np.median(per_view)), 1.0)
    bad = per_view > limit
    dropped: list[int] = []
    if bad.any() and (~bad).sum() >= cfg.min_views:
        dropped = [v.index for v, b in zip(chosen, bad) if b]
        chosen = [v for v, b in zip(chosen, bad) if not b]
        rms, K, dist, std_in, per_view, tilt = _fit(chosen, size, cfg)
    # The most tilted view decides: one is enough (11 views within 0.3 degrees of parallel and one
    # tilted 30 degrees gave fx within 0.1 % and an honest sigma; without it, 30 % off).
    if tilt.max() < math.radians(cfg.min_tilt_deg):
        raise CalibrationError(
            f"the board is nearly parallel to the image in all {len(chosen)} views used (tilted at most "
            f"{math.degrees(tilt.max()):.1f} degrees, need {cfg.min_tilt_deg:g}): the focal length cannot be told from "
            "the distance; tilt the board 20-45 degrees, towards and away and to either side, in several views"
        )
    names = INTRINSIC_NAMES[: 4 + len(dist)]
    std = {n: float(s) for n, s in zip(names, std_in)}
    if cfg.fix_k3:
        std.pop("k3", None)
    camera = Camera(K, dist, size[0], size[1])
    return CalibrationResult(camera, rms, std, per_view, chosen, detected, images, dropped, view_tilt=tilt)
