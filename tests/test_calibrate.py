"""tagloc calibrate: the printed board, board detection, view selection and intrinsics from synthetic views."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tagloc.apps.calibrate import calibrate_camera, coverage, format_report
from tagloc.cli import main
from tagloc.core.camera import Camera, load_calibration
from tagloc.core.charuco import BoardSpec, make_board
from tagloc.core.errors import CalibrationError, InputError
from tagloc.io.calibration_board import write_board
from tagloc.sim.board import board_poses, render_board_view
from tagloc.vision.calibration import BoardDetector, CalibrationConfig, calibrate_views, select_views

# A webcam-like camera with strong barrel distortion and a principal point off the centre.
CAM = Camera(
    np.array([[700.0, 0.0, 322.3], [0.0, 701.4, 238.7], [0.0, 0.0, 1.0]]),
    np.array([-0.28, 0.09, 0.001, -0.0015, 0.0]),
    640,
    480,
)


@pytest.fixture(scope="module")
def image_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("calib")
    for i, T in enumerate(board_poses(CAM, 24, seed=3)):
        cv2.imwrite(str(d / f"{i:03d}.png"), render_board_view(CAM, T, rng=np.random.default_rng(i)))
    (d / "zz_corrupt.png").write_bytes(b"not an image")
    return d


def test_board_spec_checks():
    with pytest.raises(InputError, match="dictionary"):
        BoardSpec(dictionary="7x7_1000")
    with pytest.raises(InputError, match="marker"):
        BoardSpec(marker_m=0.03)
    with pytest.raises(InputError, match="markers"):
        BoardSpec(squares_x=20, squares_y=12, dictionary="4x4_50")


def test_board_sheet_true_scale(tmp_path):
    png = write_board(tmp_path / "board.png", dpi=100)
    img = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    assert img.shape[1] == 1169 and abs(img.shape[0] - 827) <= 1  # A4 landscape at 100 dpi (rounding)
    # The printed board's black outer squares span 220 mm = 866 px at 100 dpi.
    cols = np.where((img < 60).mean(axis=0) > 0.2)[0]
    assert cols[-1] - cols[0] + 1 == pytest.approx(220 / 25.4 * 100, abs=2)
    assert write_board(tmp_path / "board.pdf").read_bytes().startswith(b"%PDF")
    with pytest.raises(InputError, match="does not fit"):
        write_board(tmp_path / "big.pdf", BoardSpec(square_m=0.05, marker_m=0.035))
    with pytest.raises(InputError, match="format"):
        write_board(tmp_path / "board.jpg")


def test_detects_the_printed_board_with_true_corners():
    T = board_poses(CAM, 1, seed=5)[0]
    view = BoardDetector().detect(render_board_view(CAM, T))
    assert view is not None and len(view.ids) > 50
    board = make_board()
    obj = board.getChessboardCorners()[view.ids]
    truth, _ = cv2.projectPoints(obj, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], CAM.K, CAM.dist)
    err = np.linalg.norm(view.corners - truth.reshape(-1, 2), axis=1)
    assert np.median(err) < 0.1 and err.max() < 0.5
    assert BoardDetector().detect(np.full((480, 640), 128, np.uint8)) is None


def test_select_views_prefers_spread():
    det = BoardDetector()
    poses = board_poses(CAM, 12, seed=9)
    views = [det.detect(render_board_view(CAM, T), i) for i, T in enumerate(poses)]
    views = [v for v in views if v is not None]
    # Ten copies of one view and the distinct ones: a spread subset takes at most one copy.
    dup = views[:1] * 10 + views[1:]
    chosen = select_views(dup, CAM.size, len(views))
    assert sum(v is views[0] for v in chosen) == 1
    assert len(chosen) == len(views)


def test_calibration_recovers_the_camera(image_dir, tmp_path):
    out = tmp_path / "camera.yaml"
    result = calibrate_camera(str(image_dir), out, config=CalibrationConfig(max_views=20), progress=False)
    cam = load_calibration(out)
    assert cam.size == (640, 480)
    assert cam.fx == pytest.approx(CAM.fx, rel=0.005)
    assert cam.fy == pytest.approx(CAM.fy, rel=0.005)
    assert abs(cam.K[0, 2] - CAM.K[0, 2]) < 2 and abs(cam.K[1, 2] - CAM.K[1, 2]) < 2
    assert cam.dist[0] == pytest.approx(CAM.dist[0], abs=0.01)
    # The distortion is recovered where it was measured: undistorting a corner-ish pixel agrees.
    px = np.array([[40.0, 30.0], [600.0, 450.0]])
    assert np.abs(cam.undistort_pixels(px) - CAM.undistort_pixels(px)).max() < 1.0
    assert result.rms_px < 0.2 and result.unreadable == 1 and len(result.views) == 20
    assert 0 < result.std["fx"] < 2 and coverage(result) > 0.7
    assert (tmp_path / "camera_coverage.png").stat().st_size > 0
    report = format_report(result)
    assert "RMS reprojection error" in report and "board tilt" in report and "warning" not in report
    assert np.degrees(result.view_tilt.max()) > 20


def test_too_few_views_is_a_clear_error(tmp_path):
    det = BoardDetector()
    views = [det.detect(render_board_view(CAM, T), i) for i, T in enumerate(board_poses(CAM, 3, seed=1))]
    with pytest.raises(CalibrationError, match="found in 3 of 10 images"):
        calibrate_views([v for v in views if v], CAM.size, 10)


def _views_tilted_at_most(tilt_deg: float, n: int = 8, seed: int = 3, folder=None) -> list:
    """The board's views in ``n`` renders tilted up to ``tilt_deg`` (also written to ``folder``)."""
    det, views = BoardDetector(), []
    for i, T in enumerate(board_poses(CAM, n, seed=seed, max_tilt_deg=tilt_deg)):
        img = render_board_view(CAM, T, rng=np.random.default_rng(i))
        if folder is not None:
            cv2.imwrite(str(folder / f"{i:03d}.png"), img)
        views.append(det.detect(img, i))
    return [v for v in views if v is not None]


def test_views_of_a_board_parallel_to_the_image_are_refused(tmp_path, capsys):
    """Boards all parallel to the image (tilted at most 0.5 degrees) leave the focal length
    unobservable: OpenCV returned fx 20 % off with a sigma of 0.01 px. Refused, in one line naming
    the source and saying how to hold the board; nothing is written."""
    src = tmp_path / "flat"
    src.mkdir()
    views = _views_tilted_at_most(0.5, folder=src)
    with pytest.raises(CalibrationError) as info:
        calibrate_views(views, CAM.size, len(views))
    msg = str(info.value)
    assert "nearly parallel to the image" in msg and "tilted at most 0." in msg
    assert "tilt the board 20-45 degrees" in msg and "\n" not in msg
    out = tmp_path / "camera.yaml"
    assert main(["calibrate", "camera", str(src), "-o", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"tagloc calibrate: error: {src}: the board is nearly parallel") and err.count("\n") == 1
    assert not out.exists()


def test_weakly_tilted_views_are_fitted_with_a_warning():
    """Views tilted up to 5 degrees pin the focal length (fx 0.1 % off, sigma 3 px on the reviewer's
    648x486 set), but weakly: the report says so and how to do better."""
    result = calibrate_views(_views_tilted_at_most(5.0), CAM.size, 8)
    assert 3.0 <= np.degrees(result.view_tilt.max()) < 10.0
    assert abs(result.camera.fx - CAM.fx) < 3 * result.std["fx"]
    report = format_report(result)
    assert "warning: the board is tilted at most" in report and "tilt the board 20-45 degrees" in report


def test_cli(image_dir, tmp_path, capsys):
    assert main(["calibrate", "board", "-o", str(tmp_path / "b.svg")]) == 0
    assert (tmp_path / "b.svg").exists()
    assert main(["calibrate", "camera", str(tmp_path / "missing"), "-o", str(tmp_path / "c.yaml")]) == 2
    assert "not a folder, video file or camera index" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["calibrate", "board", "-o", str(tmp_path / "b.pdf"), "--squares", "5"])


def test_video_source_is_read_with_a_step(tmp_path):
    from tagloc.apps.calibrate import SourceConfig, _frames

    path = tmp_path / "board.avi"
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (640, 480), False)
    for i, T in enumerate(board_poses(CAM, 6, seed=2)):
        out.write(render_board_view(CAM, T, rng=np.random.default_rng(i)))
    out.release()
    got = list(_frames(str(path), SourceConfig(step=2)))
    assert [i for i, _, _ in got] == [0, 2, 4]
    assert all(img is not None and img.shape[:2] == (480, 640) for _, img, _ in got)
    assert BoardDetector().detect(got[0][1]) is not None


def test_board_photos_are_read_as_stored_whatever_their_exif_orientation(tmp_path):
    """A folder of photos is read in the sensor's layout, as the frames the calibration serves: a
    photo tagged to be shown turned (EXIF orientation 6) stays 640 x 480 with its board where it is."""
    from synth import with_exif_orientation

    from tagloc.apps.calibrate import SourceConfig, _frames

    view = render_board_view(CAM, board_poses(CAM, 1, seed=3)[0], rng=np.random.default_rng(3))
    ok, jpeg = cv2.imencode(".jpg", view, [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    (tmp_path / "a.jpg").write_bytes(with_exif_orientation(jpeg.tobytes(), 6))
    ((_, img, name),) = list(_frames(str(tmp_path), SourceConfig()))
    assert name == "a.jpg" and img.shape == (480, 640)
    assert BoardDetector().detect(img) is not None


def test_outputs_are_never_images_of_the_folder_read(image_dir, tmp_path, capsys):
    """``-o`` in the folder of calibration images put the coverage PNG there, and the next run read
    it as a view and stopped ("image size 800x660 differs"); ``--coverage`` naming a view wrote over
    it. Both refused before any image is read, nothing written; a YAML in the folder is not a view."""
    views = tmp_path / "views"
    views.mkdir()
    for name in ("000.png", "001.png"):
        (views / name).write_bytes((image_dir / name).read_bytes())
    before = {p.name: p.read_bytes() for p in views.iterdir()}
    err = "tagloc calibrate: error: {}: {} is an image in the folder of calibration images {}"
    out = views / "camera.yaml"
    assert main(["calibrate", "camera", str(views), "-o", str(out), "--no-progress"]) == 2
    assert capsys.readouterr().err.startswith(
        err.format(views / "camera_coverage.png", "the coverage PNG (beside -o; --coverage puts it elsewhere)", views)
    )
    cov = views / "000.png"
    assert main(["calibrate", "camera", str(views), "-o", str(tmp_path / "c.yaml"), "--coverage", str(cov)]) == 2
    assert capsys.readouterr().err.startswith(err.format(cov, "--coverage", views))
    assert {p.name: p.read_bytes() for p in views.iterdir()} == before
    with pytest.raises(InputError, match="-o and --coverage name the same file"):
        calibrate_camera(str(views), tmp_path / "c.png", coverage_png=tmp_path / "c.png", progress=False)
