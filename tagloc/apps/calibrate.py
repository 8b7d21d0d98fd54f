"""``tagloc calibrate``: print the ChArUco board; calibrate a camera from a video, a folder or a live camera.

The maths is :mod:`tagloc.vision.calibration` (OpenCV); this module reads the images, writes the
calibration (OpenCV FileStorage YAML, the format :func:`tagloc.core.camera.load_calibration`
reads, plus the fit's RMS error and standard deviations as extra keys) and the coverage picture.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from tagloc.core.camera import save_calibration
from tagloc.core.charuco import DEFAULT_BOARD, BoardSpec
from tagloc.core.errors import CalibrationError, InputError
from tagloc.vision.calibration import BoardDetector, CalibrationConfig, CalibrationResult, calibrate_views

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")
#: Coverage is counted on this grid of image cells (columns, rows).
COVERAGE_GRID = (8, 6)
#: Warn when fewer of those cells hold a corner: distortion is then extrapolated, not measured.
MIN_COVERAGE = 0.7
#: Warn when no view has the board tilted this much (degrees; below
#: ``CalibrationConfig.min_tilt_deg`` the fit is refused): the focal length then rests on a weak
#: perspective. Measured on 12 rendered views, fx's sigma is 1.2-2.5 px at 1296x972 with the most
#: tilted view at 5-9 degrees (0.7 px at 11-12; 0.16-0.3 px at 648x486 at 21-42 degrees), and OpenCV's
#: stated sigma collapsed to 0.01 px in one set as tilted as 3.2 degrees.
WEAK_TILT_DEG = 10.0


@dataclass(frozen=True)
class SourceConfig:
    """Which images of the source are used.

    Attributes:
        step: use every ``step``-th frame of a video or camera (neighbouring frames are near copies).
        max_frames: stop after reading this many frames (a live camera has no end).
    """

    step: int = 5
    max_frames: int = 3000


def _frames(source: str, cfg: SourceConfig) -> Iterator[tuple[int, np.ndarray | None, str]]:
    """(index, image or None when unreadable, name) from a folder of images, a video or a camera index."""
    path = Path(source)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise InputError(f"{path}: no images ({', '.join(IMAGE_SUFFIXES)})")
        for i, f in enumerate(files[: cfg.max_frames]):
            # As stored, as the frames it calibrates are read (an EXIF orientation would turn some).
            yield i, cv2.imread(str(f), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION), f.name
        return
    if source.isascii() and source.isdigit():
        cap = cv2.VideoCapture(int(source))
        name = f"camera {source}"
    elif path.is_file():
        cap = cv2.VideoCapture(str(path))
        name = str(path)
    else:
        raise InputError(f"{source}: not a folder, video file or camera index")
    if not cap.isOpened():
        raise InputError(f"{name}: cannot open")
    try:
        for i in range(cfg.max_frames):
            ok, img = cap.read()
            if not ok:
                return
            if i % cfg.step == 0:
                yield i, img, f"{name} frame {i}"
    finally:
        cap.release()


def coverage(result: CalibrationResult) -> float:
    """Fraction of :data:`COVERAGE_GRID` image cells holding at least one corner used in the fit."""
    cols, rows = COVERAGE_GRID
    w, h = result.camera.size
    c = result.corners
    cells = set(
        zip(
            np.clip((c[:, 0] * cols / w).astype(int), 0, cols - 1),
            np.clip((c[:, 1] * rows / h).astype(int), 0, rows - 1),
        )
    )
    return len(cells) / (cols * rows)


def write_coverage_png(result: CalibrationResult, path: str | Path) -> Path:
    """Plot where the corners used fell in the image (one colour per view) over the coverage grid."""
    from matplotlib.figure import Figure

    w, h = result.camera.size
    fig = Figure(figsize=(8, 8 * h / w + 0.6))
    ax = fig.add_subplot(1, 1, 1)
    for k, v in enumerate(result.views):
        ax.plot(v.corners[:, 0], v.corners[:, 1], ".", ms=2, color=f"C{k % 10}")
    cols, rows = COVERAGE_GRID
    for i in range(1, cols):
        ax.axvline(i * w / cols, color="0.8", lw=0.5)
    for j in range(1, rows):
        ax.axhline(j * h / rows, color="0.8", lw=0.5)
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_aspect("equal")
    ax.set_title(
        f"{len(result.views)} views, {len(result.corners)} corners, {coverage(result):.0%} of cells covered, "
        f"RMS {result.rms_px:.3f} px",
        fontsize=9,
    )
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    return Path(path)


def save_result(result: CalibrationResult, path: str | Path, spec: BoardSpec) -> None:
    """Write the calibration as OpenCV FileStorage YAML, with the fit's quality as extra keys."""
    extra = {
        "avg_reprojection_error": result.rms_px,
        "std_deviations": np.array([result.std[k] for k in result.std], float).reshape(1, -1),
        "std_deviation_names": " ".join(result.std),
        "views_used": len(result.views),
        "board": spec.describe(),
    }
    save_calibration(result.camera, path, extra)


def _outputs_apart_from_source(source: str, outputs: list[tuple[str, Path]]) -> None:
    """Refuse outputs that are one file, the source video, or an image in the source folder (the
    coverage PNG beside an ``-o`` in that folder would be read as a view by the next run, and
    refused there for its size; ``--coverage`` naming a view would overwrite it)."""
    src = Path(os.path.realpath(source))
    seen: dict[Path, str] = {}
    for option, path in outputs:
        real = Path(os.path.realpath(path))
        if real in seen:
            raise InputError(f"{path}: {seen[real]} and {option} name the same file")
        seen[real] = option
        if real == src:
            raise InputError(f"{path}: {option} names the source it would overwrite")
        if src.is_dir() and real.parent == src and real.suffix.lower() in IMAGE_SUFFIXES:
            raise InputError(
                f"{path}: {option} is an image in the folder of calibration images {source}, where it would be"
                " read as a view of the board; write it elsewhere"
            )


def calibrate_camera(
    source: str,
    out: str | Path,
    spec: BoardSpec = DEFAULT_BOARD,
    config: CalibrationConfig | None = None,
    source_config: SourceConfig | None = None,
    coverage_png: str | Path | None = None,
    progress: bool = True,
) -> CalibrationResult:
    """Calibrate from ``source`` (folder of images, video file or camera index), write ``out`` (YAML)
    and the coverage PNG (default: ``out`` with ``_coverage.png``). Unreadable images are skipped and counted."""
    out = Path(out)
    config = config or CalibrationConfig()
    source_config = source_config or SourceConfig()
    if not out.parent.exists():
        raise InputError(f"{out}: directory {out.parent} does not exist")
    given = coverage_png is not None
    coverage_png = Path(coverage_png) if given else out.with_name(out.stem + "_coverage.png")
    coverage_option = "--coverage" if given else "the coverage PNG (beside -o; --coverage puts it elsewhere)"
    _outputs_apart_from_source(str(source), [("-o", out), (coverage_option, coverage_png)])
    detector = BoardDetector(spec)
    views, size, images, unreadable = [], None, 0, 0
    for index, image, name in tqdm(_frames(str(source), source_config), desc="board", unit="img", disable=not progress):
        images += 1
        if image is None:
            unreadable += 1
            continue
        shape = (image.shape[1], image.shape[0])
        if size is None:
            size = shape
        elif shape != size:
            raise InputError(
                f"{name}: image size {shape[0]}x{shape[1]} differs from the first image's {size[0]}x{size[1]}"
            )
        view = detector.detect(image, index, config.min_corners)
        if view is not None:
            views.append(view)
    if size is None:
        raise InputError(f"{source}: no readable image ({unreadable} unreadable)")
    try:
        result = calibrate_views(views, size, images, config)
    except CalibrationError as exc:
        raise CalibrationError(f"{source}: {exc}") from None
    result.unreadable = unreadable
    save_result(result, out, spec)
    write_coverage_png(result, coverage_png)
    return result


def format_report(result: CalibrationResult) -> str:
    """The fit as a person reads it: parameters with one-sigma uncertainty, views, coverage, warnings."""
    cam = result.camera
    values = {"fx": cam.K[0, 0], "fy": cam.K[1, 1], "cx": cam.K[0, 2], "cy": cam.K[1, 2]}
    names = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
    values.update({n: v for n, v in zip(names, cam.dist)})
    lines = [
        f"image {cam.width}x{cam.height}: board in {result.detected} of {result.images} images "
        f"({result.unreadable} unreadable), {len(result.views)} views used",
        f"RMS reprojection error {result.rms_px:.3f} px",
        f"{'param':<6}{'value':>14}{'1-sigma':>12}",
    ]
    for n, v in values.items():
        s = result.std.get(n, math.nan)
        lines.append(f"{n:<6}{v:>14.6g}{s:>12.3g}")
    cov = coverage(result)
    lines.append(f"coverage {cov:.0%} of {COVERAGE_GRID[0]}x{COVERAGE_GRID[1]} image cells")
    tilt = np.degrees(result.view_tilt)
    if len(tilt):
        lines.append(f"board tilt {tilt.min():.1f}-{tilt.max():.1f} degrees (median {np.median(tilt):.1f})")
    if result.dropped_outliers:
        lines.append(f"dropped views with a high error: {result.dropped_outliers}")
    if cov < MIN_COVERAGE:
        lines.append("warning: corners cover little of the image; show the board near the edges and corners too")
    if len(tilt) and tilt.max() < WEAK_TILT_DEG:
        lines.append(
            f"warning: the board is tilted at most {tilt.max():.1f} degrees: the focal length is weakly "
            "measured and its 1-sigma may be too small; tilt the board 20-45 degrees in several views"
        )
    if result.rms_px > 1.0:
        lines.append("warning: RMS error above 1 px (blur, a bent board or a wrong --square-mm?)")
    return "\n".join(lines)
