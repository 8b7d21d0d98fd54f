"""Camera calibration files (OpenCV FileStorage, ROS camera_info) and rig files."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from tagloc.core.camera import Camera, default_camera, load_calibration, save_calibration
from tagloc.core.errors import CalibrationError
from tagloc.core.geometry import invert
from tagloc.core.rig import Rig, RigCamera, default_rig, load_rig, looking_forward, save_rig

K = np.array([[1010.5, 0.0, 640.25], [0.0, 1008.75, 479.5], [0.0, 0.0, 1.0]])
DIST = np.array([0.11, -0.23, 0.001, -0.002, 0.05])


def _same(cam: Camera, K_=K, dist=DIST, size=(1280, 960)) -> None:
    assert cam.K == pytest.approx(K_, abs=1e-9)
    assert cam.dist == pytest.approx(dist, abs=1e-12)
    assert (cam.width, cam.height) == size


def test_projection_stops_where_the_distortion_folds_back():
    """Far off the axis OpenCV's distortion polynomial folds back: the default camera's (k1 = 0.1,
    k2 = -0.2) stops growing at tan(angle) = 1.078 (47 deg), and a point 58 deg left of the axis
    (half-FOV 27 deg) lands right of the image's centre. project_in_view refuses it."""
    cam = default_camera()
    assert cam.fold_radius() == pytest.approx(1.078, abs=0.002)  # r(1 + 0.1 r^2 - 0.2 r^4) peaks at r^2 = 1.161
    left_58 = np.array([[-np.tan(np.radians(58)), 0.0, 1.0]])
    assert cam.project(left_58)[0, 0] == pytest.approx(762.1, abs=0.5)
    assert cam.project_in_view(left_58) is None
    # Short of the fold it is project(); behind the camera or on its plane, nothing.
    pts = np.array([[0.3, -0.2, 1.5], [-1.0, 0.1, 1.0]])
    np.testing.assert_array_equal(cam.project_in_view(pts), cam.project(pts))
    assert cam.project_in_view(np.array([[0.0, 0.0, -1.0]])) is None
    assert cam.project_in_view(np.array([[0.0, 0.0, 0.01]])) is None
    # A strong barrel lens folds at 1 / sqrt(3 |k1|); no distortion never folds.
    barrel = Camera(cam.K, np.array([-0.45, 0.0, 0.0, 0.0, 0.0]), cam.width, cam.height)
    assert barrel.fold_radius() == pytest.approx(1 / np.sqrt(1.35), abs=0.002)
    assert Camera(cam.K, np.zeros(5), cam.width, cam.height).fold_radius() == np.inf


def test_opencv_round_trip(tmp_path):
    p = tmp_path / "camera.yaml"
    save_calibration(Camera(K, DIST, 1280, 960), p)
    _same(load_calibration(p))
    cam = default_camera()
    save_calibration(cam, p)
    back = load_calibration(p)
    assert back.K == pytest.approx(cam.K) and back.dist == pytest.approx(cam.dist) and back.size == (1296, 972)


def test_file_written_by_cv2_filestorage(tmp_path):
    p = tmp_path / "calib.yml"
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 1280)
    fs.write("image_height", 960)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", DIST.reshape(-1, 1))  # column vector, as calibrateCamera returns
    fs.write("avg_reprojection_error", 0.21)
    fs.release()
    _same(load_calibration(p))


OST = """image_width: 1280
image_height: 960
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [1010.5, 0.0, 640.25, 0.0, 1008.75, 479.5, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [0.11, -0.23, 0.001, -0.002, 0.05]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [1010.5, 0, 640.25, 0, 0, 1008.75, 479.5, 0, 0, 0, 1, 0]
"""

CAMERA_INFO = """header:
  seq: 0
  stamp: {secs: 0, nsecs: 0}
  frame_id: vest_camera
height: 960
width: 1280
distortion_model: plumb_bob
D: [0.11, -0.23, 0.001, -0.002, 0.05]
K: [1010.5, 0.0, 640.25, 0.0, 1008.75, 479.5, 0.0, 0.0, 1.0]
R: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
P: [1010.5, 0.0, 640.25, 0.0, 0.0, 1008.75, 479.5, 0.0, 0.0, 0.0, 1.0, 0.0]
binning_x: 0
binning_y: 0
"""


def test_ros_camera_calibration_ost_yaml(tmp_path):
    p = tmp_path / "ost.yaml"
    p.write_text(OST)
    _same(load_calibration(p))


def test_ros_camera_info_dump(tmp_path):
    p = tmp_path / "camera_info.yaml"
    p.write_text(CAMERA_INFO)
    _same(load_calibration(p))
    p.write_text(CAMERA_INFO.replace("D:", "d:").replace("K:", "k:"))  # ROS 2 field names
    _same(load_calibration(p))


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("image_width: [1, 2\n", "not valid YAML"),
        ("- 1\n- 2\n", "not a calibration mapping"),
        ("image_width: 10\nimage_height: 10\n", "no camera_matrix or K"),
        (CAMERA_INFO.replace("K: [1010.5, 0.0, 640.25,", "K: [1010.5,"), "camera matrix has 7 values"),
        (CAMERA_INFO.replace("width: 1280\n", ""), "width/height"),
        (CAMERA_INFO.replace("K: [1010.5", "K: [-1010.5"), "not a valid intrinsic"),
        (CAMERA_INFO.replace("K: [1010.5", "K: [.nan"), "NaN or inf"),
        (CAMERA_INFO.replace("K: [1010.5", "K: [1e-300"), "focal length"),
        (CAMERA_INFO.replace("K: [1010.5", "K: [1e300"), "focal length"),
        (CAMERA_INFO.replace("D: [0.11,", "D: [1e300,"), "distortion coefficient is beyond"),
        (CAMERA_INFO.replace("D: [0.11, -0.23, 0.001, -0.002, 0.05]", "D: [0.1, 0.2, 0.3]"), "distortion"),
        (CAMERA_INFO.replace("K: [1010.5", "K: [abc"), "not a list of numbers"),
        (OST.replace("image_width: 1280", "image_width: 0"), "not positive"),
    ],
)
def test_malformed_ros_files_refused(tmp_path, text, fragment):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(CalibrationError) as info:
        load_calibration(p)
    assert str(p) in str(info.value) and fragment in str(info.value)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("model", ["plumb_bob", "rational_polynomial", None])
def test_ros_pinhole_distortion_models_read(tmp_path, model):
    p = tmp_path / "ost.yaml"
    text = OST if model is not None else OST.replace("distortion_model: plumb_bob\n", "")  # absent: plumb_bob
    if model == "rational_polynomial":
        text = text.replace("plumb_bob", model).replace(
            "cols: 5\n  data: [0.11, -0.23, 0.001, -0.002, 0.05]",
            "cols: 8\n  data: [0.11, -0.23, 0.001, -0.002, 0.05, 0.1, 0, 0]",
        )
    p.write_text(text)
    cam = load_calibration(p)
    assert cam.dist.size == (8 if model == "rational_polynomial" else 5)


def _fisheye_opencv(p):
    """What OpenCV's calibration sample writes after calibrating with cv2.fisheye."""
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 1280)
    fs.write("image_height", 960)
    fs.write("fisheye_model", 1)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", DIST[:4].reshape(-1, 1))
    fs.release()
    return p


@pytest.mark.parametrize(
    "write, fragment",
    [
        (lambda p: p.write_text(OST.replace("plumb_bob", "equidistant")), "distortion_model 'equidistant'"),
        (lambda p: p.write_text(CAMERA_INFO.replace("plumb_bob", "fisheye")), "distortion_model 'fisheye'"),
        (lambda p: p.write_text(OST.replace("plumb_bob", "[1, 2]")), "distortion_model '[1, 2]'"),
        (_fisheye_opencv, "fisheye_model 1"),
    ],
    ids=["ost-equidistant", "camera-info-fisheye", "not-a-name", "opencv-fisheye-sample"],
)
def test_calibrations_in_another_distortion_model_refused(tmp_path, write, fragment):
    """A fisheye's k1..k4 read as OpenCV's k1, k2, p1, p2 put a point 50 degrees off-axis 155 px
    from where the lens images it: such a file is refused, in one line naming it and the model."""
    p = tmp_path / "camera.yaml"
    write(p)
    with pytest.raises(CalibrationError) as info:
        load_calibration(p)
    msg = str(info.value)
    assert msg.startswith(f"{p}: {fragment}") and "is not supported" in msg and "\n" not in msg


def test_opencv_file_naming_its_distortion_model(tmp_path):
    p = tmp_path / "cv.yaml"
    for model, ok in (("plumb_bob", True), ("equidistant", False)):
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", 1280)
        fs.write("image_height", 960)
        fs.write("fisheye_model", 0)  # OpenCV's sample after cv2.calibrateCamera: fine
        fs.write("distortion_model", model)
        fs.write("camera_matrix", K)
        fs.write("distortion_coefficients", DIST)
        fs.release()
        if ok:
            _same(load_calibration(p))
        else:
            with pytest.raises(CalibrationError, match=f"{p}: distortion_model 'equidistant' is not supported"):
                load_calibration(p)


def test_bag_camera_info_in_another_distortion_model_refused():
    from types import SimpleNamespace

    from tagloc.core.errors import InputError
    from tagloc.io.rosbag import camera_from_info

    msg = SimpleNamespace(k=K.ravel(), d=DIST, width=1280, height=960, distortion_model="plumb_bob")
    _same(camera_from_info(msg))
    msg.distortion_model = ""  # a driver's unset string: ROS's default, plumb_bob
    _same(camera_from_info(msg))
    msg.distortion_model, msg.d = "equidistant", DIST[:4]
    with pytest.raises(InputError, match="CameraInfo distortion_model 'equidistant' is not supported"):
        camera_from_info(msg)


def test_malformed_opencv_files_refused(tmp_path):
    p = tmp_path / "cv.yaml"
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", K)
    fs.release()
    with pytest.raises(CalibrationError, match="missing distortion_coefficients, image_height, image_width"):
        load_calibration(p)
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 1280)
    fs.write("image_height", 960)
    fs.write("camera_matrix", np.eye(2))
    fs.write("distortion_coefficients", DIST)
    fs.release()
    with pytest.raises(CalibrationError, match=f"{p}: camera_matrix must be a 3x3"):
        load_calibration(p)
    with pytest.raises(CalibrationError, match="cannot read"):
        load_calibration(tmp_path / "absent.yaml")


# --- rig ------------------------------------------------------------------------------------------


def test_looking_forward_geometry():
    T = looking_forward(1.3, 55.0)
    assert T[:3, 3] == pytest.approx((0, 0, 1.3))
    axis = T[:3, 2]  # optical axis in the body frame: forward and down by the pitch
    assert axis == pytest.approx((np.cos(np.radians(55)), 0, -np.sin(np.radians(55))))
    assert T[:3, 0] == pytest.approx((0, -1, 0))  # image x (right) is body -y
    R = T[:3, :3]
    assert R @ R.T == pytest.approx(np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)


def test_rig_round_trip(tmp_path):
    side = Camera(K, DIST, 1280, 960)
    rig = Rig(
        [
            RigCamera("front", default_camera(), looking_forward(1.3, 55.0)),
            RigCamera("left", side, looking_forward(1.2, 60.0, yaw_deg=90.0, y_m=0.1), "left.yaml"),
        ]
    )
    rig.cameras[1].stamp_offset_s = -0.031
    save_rig(rig, tmp_path / "rig.json")
    assert (tmp_path / "camera.yaml").exists() and (tmp_path / "left.yaml").exists()
    back = load_rig(tmp_path / "rig.json")
    assert [c.name for c in back.cameras] == ["front", "left"]
    assert [c.stamp_offset_s for c in back.cameras] == [None, -0.031]
    for a, b in zip(rig.cameras, back.cameras):
        assert b.T_body_camera == pytest.approx(a.T_body_camera, abs=1e-12)
        assert b.camera.K == pytest.approx(a.camera.K) and b.camera.dist == pytest.approx(a.camera.dist)
    override = load_rig(tmp_path / "rig.json", calibration=side)
    assert all(c.camera is side for c in override.cameras)


def test_a_written_rig_keeps_its_calibrations_beside_it_under_plain_names(tmp_path):
    """A rig naming its calibrations by an absolute path or a folder (as a site's may) is written, as
    a recording's, with each calibration beside rig.json: the originals are not written over, and
    the copy stands alone. Two cameras whose files share a name get distinct ones."""
    original = tmp_path / "site" / "abs.yaml"
    original.parent.mkdir()
    original.write_text("# the site's own file, with a comment\n")
    before = original.read_bytes()
    rig = Rig(
        [
            RigCamera("front", default_camera(), looking_forward(1.3, 55.0), str(original)),
            RigCamera("left", default_camera(), looking_forward(1.2, 60.0, yaw_deg=90.0), "cams/left.yaml"),
        ]
    )
    out = tmp_path / "rec"
    out.mkdir()
    save_rig(rig, out / "rig.json")
    assert original.read_bytes() == before
    assert sorted(p.name for p in out.iterdir()) == ["abs.yaml", "left.yaml", "rig.json"]
    assert [c["calibration"] for c in json.loads((out / "rig.json").read_text())["cameras"]] == [
        "abs.yaml",
        "left.yaml",
    ]
    back = load_rig(out / "rig.json")
    assert back.cameras[0].camera.K == pytest.approx(default_camera().K)
    twins = Rig([RigCamera(n, default_camera(), looking_forward(1.3, 55.0), f"{n}/camera.yaml") for n in ("a", "b")])
    save_rig(twins, out / "twins.json")
    assert [c["calibration"] for c in json.loads((out / "twins.json").read_text())["cameras"]] == [
        "camera0.yaml",
        "camera1.yaml",
    ]


def _rig_doc(T) -> str:
    return json.dumps({"cameras": [{"name": "front", "calibration": "camera.yaml", "T_body_camera": T}]})


@pytest.mark.parametrize(
    "T, fragment",
    [
        (np.eye(3).tolist(), "finite 4x4"),
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, float("nan")]], "finite 4x4"),
        ((np.diag([2.0, 1, 1, 1])).tolist(), "not a rigid transform"),
        ((np.diag([1.0, 1, -1, 1])).tolist(), "not a rigid transform"),  # a reflection
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], "not a rigid transform"),
        ([["a", 0, 0, 0]] * 4, "not a 4x4 matrix of numbers"),
        # Rigid, but no worn camera: below the floor, 500 m up, off in space, 5 m beside the wearer.
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -1.3], [0, 0, 0, 1]], "at (0, 0, -1.3) m; a worn camera is 0-3 m"),
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 500], [0, 0, 0, 1]], "at (0, 0, 500) m"),
        ([[1, 0, 0, 1e300], [0, 1, 0, 0], [0, 0, 1, 1.3], [0, 0, 0, 1]], "within 1 m of the body axis"),
        ([[1, 0, 0, 0], [0, 1, 0, 5], [0, 0, 1, 1.3], [0, 0, 0, 1]], "at (0, 5, 1.3) m"),
    ],
)
def test_bad_T_body_camera_refused(tmp_path, T, fragment):
    save_calibration(default_camera(), tmp_path / "camera.yaml")
    p = tmp_path / "rig.json"
    p.write_text(_rig_doc(T))
    with pytest.raises(CalibrationError) as info:
        load_rig(p)
    assert f"{p}: cameras[0]" in str(info.value) and fragment in str(info.value)


def test_rig_written_to_three_decimals_loads_as_a_rotation(tmp_path):
    """The README's rig.json (55 degrees written as 0.819 and 0.574: R R^T is 2.4e-4 off the
    identity) was refused as "not a rigid transform". It loads, as the nearest rotation."""
    save_calibration(default_camera(), tmp_path / "camera.yaml")
    p = tmp_path / "rig.json"
    T = [[0, -0.819, 0.574, 0], [-1, 0, 0, 0], [0, -0.574, -0.819, 1.3], [0, 0, 0, 1]]
    p.write_text(_rig_doc(T))
    got = load_rig(p)[0].T_body_camera
    R = got[:3, :3]
    assert R @ R.T == pytest.approx(np.eye(3), abs=1e-12) and np.linalg.det(R) == pytest.approx(1.0)
    assert got == pytest.approx(np.array(T, float), abs=1e-3)
    assert got == pytest.approx(looking_forward(1.3, 55.0), abs=1e-3)
    # Exactly written rotations are kept as written.
    exact = looking_forward(1.22, 58.0, 3.0)
    p.write_text(_rig_doc(exact.tolist()))
    assert np.array_equal(load_rig(p)[0].T_body_camera, exact)
    # A scale of 1 %, not rounding, is still refused.
    p.write_text(_rig_doc((np.diag([1.01, 1.01, 1.01, 1.0]) @ exact).tolist()))
    with pytest.raises(CalibrationError, match="not a rigid transform"):
        load_rig(p)


def test_bad_rig_files_refused(tmp_path):
    p = tmp_path / "rig.json"
    p.write_text('{"cameras": [}')
    with pytest.raises(CalibrationError, match="line 1: not valid JSON"):
        load_rig(p)
    p.write_text('{"cameras": []}')
    with pytest.raises(CalibrationError, match="non-empty"):
        load_rig(p)
    p.write_text('{"cameras": [{"name": "x"}]}')
    with pytest.raises(CalibrationError, match="needs T_body_camera"):
        load_rig(p)
    p.write_text(_rig_doc(np.eye(4).tolist()))
    with pytest.raises(CalibrationError, match="camera.yaml: cannot read"):
        load_rig(p)  # the calibration it names is missing


@pytest.mark.parametrize("offset", ['"0.01"', "true", "1.5", "NaN"])
def test_a_stamp_offset_that_is_not_seconds_within_one_is_refused(tmp_path, offset):
    save_calibration(default_camera(), tmp_path / "camera.yaml")
    doc = json.loads(_rig_doc(np.eye(4).tolist()))
    doc["cameras"][0]["stamp_offset_s"] = "@"
    (tmp_path / "rig.json").write_text(json.dumps(doc).replace('"@"', offset))
    with pytest.raises(CalibrationError, match="stamp_offset_s"):
        load_rig(tmp_path / "rig.json")


def test_rig_file_with_an_integer_too_long_to_convert_refused(tmp_path):
    p = tmp_path / "rig.json"
    p.write_text('{"cameras": [], "n": ' + "9" * 5001 + "}")  # valid JSON; Python converts at most 4300 digits
    with pytest.raises(CalibrationError) as info:
        load_rig(p)
    assert str(info.value) == f"{p}: not usable JSON (Exceeds the limit (4300 digits) for integer string conversion)"


def test_default_rig_sees_floor_ahead():
    rig = default_rig()
    cam = rig[0]
    # A floor point 1.3/tan(55 deg) ahead of the body projects to the principal point.
    d = 1.3 / np.tan(np.radians(55.0))
    p_cam = (invert(cam.T_body_camera) @ np.array([d, 0, 0, 1.0]))[:3]
    uv = cam.camera.project(p_cam[None])[0]
    assert uv == pytest.approx(cam.camera.K[:2, 2], abs=1e-6)


def test_the_vest_height_has_the_camera_heights_bound(tmp_path, monkeypatch):
    """``vest_height_m`` in rig.json is bounded by the one named limit of a worn camera's height
    (``MAX_CAMERA_HEIGHT_M``, 3 m), not by a copy of its value."""
    import tagloc.core.rig as rigmod

    save_calibration(default_camera(), tmp_path / "camera.yaml")
    doc = json.loads(_rig_doc(looking_forward(1.3, 55.0).tolist()))
    doc["vest_height_m"] = 2.5
    (tmp_path / "rig.json").write_text(json.dumps(doc))
    assert load_rig(tmp_path / "rig.json").vest_point[2] == 2.5
    monkeypatch.setattr(rigmod, "MAX_CAMERA_HEIGHT_M", 2.0)
    with pytest.raises(CalibrationError, match=r"vest_height_m must be a height in metres \(0-2\)"):
        load_rig(tmp_path / "rig.json")
