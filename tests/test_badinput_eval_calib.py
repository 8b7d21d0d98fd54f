"""Bad input to eval, rig fit, map audit/refine and the calibration, rig and JSON loaders: refused in
one line naming the file (and line), or skipped and counted; never a silent wrong figure."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from tagloc.cli import main
from tagloc.core.camera import Camera, default_camera, load_calibration, save_calibration
from tagloc.core.errors import CalibrationError, InputError
from tagloc.core.jsonfile import read_json
from tagloc.core.rig import load_rig
from tagloc.eval import evaluate as ev
from tagloc.eval.rigfit import fit_rig, format_fit
from tagloc.sim.simulate import SimConfig, simulate_session

MAP = Path(__file__).resolve().parents[1] / "maps" / "demo.csv"


@pytest.fixture(scope="module")
def walk(tmp_path_factory) -> Path:
    """A 2 s simulated walk at 10 fps (20 frames), with the simulator's per-frame truth."""
    path = tmp_path_factory.mktemp("walk") / "s"
    simulate_session(MAP, path, SimConfig(seconds=2.0, fps=10.0, seed=1), progress=False)
    return path


def copy_of(walk: Path, dest: Path) -> Path:
    shutil.copytree(walk, dest, ignore=shutil.ignore_patterns("*.npz"))
    return dest


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    return err


# --- eval --walks: per-frame truth that does not cover the session's frames -------------------


@pytest.mark.parametrize(
    ("keep", "fragment"),
    [
        (lambda lines: [], "lists 0 of the session's 20 frames"),
        (lambda lines: lines[:1], "lists 1 of the session's 20 frames"),
        (lambda lines: [lines[0].replace('"index": 0,', '"index": 100000000000000000000000,')] + lines[1:], "frame 0"),
        (lambda lines: lines + [lines[3]], "frame 3 is listed more than once"),
        (lambda lines: lines + [lines[3].replace('"index": 3,', '"index": 999,')], "lists frame 999"),
    ],
)
def test_per_frame_truth_not_matching_the_frames_is_refused_before_work(walk, tmp_path, capsys, keep, fragment):
    """An empty or partial groundtruth_frames.jsonl counted every fix of a frame it did not list as a
    wrong ID (18 of 18 on an empty file), exit 0."""
    s = copy_of(walk, tmp_path / "w")
    lines = (s / ev.GROUNDTRUTH_FRAMES).read_text().splitlines()
    assert '"index": 0,' in lines[0] and '"index": 3,' in lines[3]
    kept = keep(lines)
    (s / ev.GROUNDTRUTH_FRAMES).write_text("".join(line + "\n" for line in kept))
    assert main(["eval", "--walks", str(s), "--modes", "full", "-o", str(tmp_path / "o"), "--quiet"]) == 2
    err = one_line_error(capsys)
    assert str(s / ev.GROUNDTRUTH_FRAMES) in err and fragment in err, err
    assert not (tmp_path / "o").exists()


def test_whole_per_frame_truth_is_read_and_a_fix_it_says_nothing_of_is_not_scored(walk):
    truth = ev.read_frame_truth(walk)
    assert [i for i, _ in truth] == list(range(20))
    # Handed truth for only some frames, a fix elsewhere is neither right nor wrong.
    fix = {"frame": 5, "id": 1, "centre": np.zeros(2)}
    log = type("Log", (), {"fixes": [fix]})()
    assert ev.wrong_ids_in([(4, [])], log) == (0, 0)
    assert ev.wrong_ids_in([(5, [])], log) == (1, 1)


def test_a_duplicate_key_in_a_per_frame_truth_line_is_refused(walk, tmp_path):
    s = copy_of(walk, tmp_path / "w")
    lines = (s / ev.GROUNDTRUTH_FRAMES).read_text().splitlines()
    lines[2] = lines[2].replace('"index": 2,', '"index": 2, "index": 7,')
    (s / ev.GROUNDTRUTH_FRAMES).write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r":3: key \"index\" appears twice"):
        ev.read_frame_truth(s)


# --- rig fit, map audit, map refine: bad frames are skipped and counted ------------------------


def test_rig_fit_skips_and_counts_a_frame_of_the_wrong_size(walk, tmp_path):
    """One 20x20 frame aborted the whole fit with a message naming neither file nor frame."""
    s = copy_of(walk, tmp_path / "w")
    cv2.imwrite(str(s / "frames" / "000010.jpg"), np.full((20, 20), 128, np.uint8))
    fit = fit_rig(s, tmp_path / "rig.json", progress=False)
    assert fit.frames == 20 and len(fit.skipped) == 1 and fit.skipped[0].startswith("frame 10: image is 20x20")
    assert "20 frames (1 skipped: unreadable or the wrong size; the first: frame 10: " in format_fit(fit)
    assert json.loads((tmp_path / "rig.json").read_text())["fit"]["frames_skipped"] == 1


def test_rig_fit_with_every_frame_unreadable_says_so(walk, tmp_path, capsys):
    """It said "no decoded sticker in the session ... (is the map right?)"."""
    s = copy_of(walk, tmp_path / "w")
    for f in (s / "frames").glob("*.jpg"):
        f.write_bytes(b"")
    assert main(["rig", "fit", str(s), "-o", str(tmp_path / "rig.json"), "--no-progress"]) == 2
    err = one_line_error(capsys)
    assert f"{s}: none of its 20 frames could be used (frame 0: " in err and "map" not in err, err


def test_map_audit_and_refine_count_unreadable_frames_and_print_no_nan(walk, tmp_path, capsys):
    """With half the frames zero bytes, the audit said "20 frames" and the refinement "nan px"."""
    s = copy_of(walk, tmp_path / "w")
    for k in range(0, 20, 2):
        (s / "frames" / f"{k:06d}.jpg").write_bytes(b"")
    assert main(["map", "audit", str(s), "-o", str(tmp_path / "audit"), "--quiet"]) in (0, 2)
    report = (tmp_path / "audit" / "report.md").read_text()
    assert "20 frames (10 skipped: " in report and "the first: w: frame 0: " in report
    assert json.loads((tmp_path / "audit" / "audit.json").read_text())["skipped_frames"] == 10
    assert "nan" not in report.lower()
    capsys.readouterr()
    out = tmp_path / "refined.csv"
    assert main(["map", "refine", str(s), "--map", str(s / "map.csv"), "-o", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "20 frames (10 skipped: " in printed, printed
    assert "nan" not in out.with_suffix(".md").read_text().lower()


# --- duplicate keys and byte-order marks -------------------------------------------------------

ROS_DUMP = "width: 1296\nheight: 972\nK: [1285.7, 0, 647.5, 0, 1285.7, 485.5, 0, 0, 1]\nD: [0.1, -0.2, 0, 0, 0]\n"


def test_a_ros_calibration_naming_a_key_twice_is_refused(tmp_path):
    """The second K won (a focal length twice the true one: 95 cm off on replay)."""
    p = tmp_path / "camera.yaml"
    p.write_text(ROS_DUMP + "K: [2571, 0, 647.5, 0, 2571, 485.5, 0, 0, 1]\n")
    with pytest.raises(CalibrationError, match=r"line 5: key 'K' appears again \(first on line 3\)") as info:
        load_calibration(p)
    assert str(p) in str(info.value)
    p.write_text(ROS_DUMP)
    assert load_calibration(p).fx == pytest.approx(1285.7)


def test_an_opencv_calibration_naming_a_key_twice_is_refused_and_a_bom_is_read(tmp_path):
    p = tmp_path / "camera.yaml"
    save_calibration(default_camera(), p)
    text = p.read_text()
    p.write_text(text + "image_width: 640\n")
    with pytest.raises(CalibrationError, match=r"key 'image_width' appears again \(first on line 3\)"):
        load_calibration(p)
    p.write_bytes(b"\xef\xbb\xbf" + text.encode())  # an editor's byte-order mark
    assert np.allclose(load_calibration(p).K, default_camera().K)


OPENCV_YAML = """%YAML:1.0
---
image_width: 1296
image_height: 972
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ {fx}, 0., 647.5, 0., 1285.7, 485.5, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ {k1}, -0.2, 0., 0., 0. ]
"""


@pytest.mark.parametrize(
    ("fx", "k1", "name"), [("nan", "0.1", "camera_matrix"), ("1285.7", "-inf", "distortion_coefficients")]
)
def test_nan_or_inf_written_plainly_in_an_opencv_matrix_is_named(tmp_path, fx, k1, name):
    """OpenCV's parser said "readRawData can only be used to read plain sequences of numbers"."""
    p = tmp_path / "camera.yaml"
    p.write_text(OPENCV_YAML.format(fx="1285.7", k1="0.1"))
    assert load_calibration(p).fx == pytest.approx(1285.7)
    p.write_text(OPENCV_YAML.format(fx=fx, k1=k1))
    with pytest.raises(CalibrationError, match=rf"camera.yaml: {name} contains NaN or inf$"):
        load_calibration(p)
    p.write_text(OPENCV_YAML.format(fx=fx, k1=k1).replace("nan", ".nan").replace("-inf", "-.inf"))  # OpenCV's own
    with pytest.raises(CalibrationError, match=rf"camera.yaml: {name} contains NaN or inf$"):
        load_calibration(p)


def test_json_files_refuse_a_key_twice_and_take_a_bom(tmp_path):
    p = tmp_path / "session.json"
    p.write_text('{"format": "tagloc-session", "fps": 10, "fps": 1000}')
    with pytest.raises(InputError, match=r'session.json: key "fps" appears twice in one object'):
        read_json(p, InputError)
    p.write_bytes(b'\xef\xbb\xbf{"fps": 10}')
    assert read_json(p, InputError) == {"fps": 10}


# --- calibrations and rigs that cannot be right -------------------------------------------------


def test_a_distortion_that_folds_inside_the_image_is_refused(tmp_path):
    """D = [50, -900, 0, 0, 0] was accepted, and the replay ended with 0 poses."""
    p = tmp_path / "camera.yaml"
    save_calibration(Camera(default_camera().K, np.array([50.0, -900.0, 0, 0, 0])), p)
    with pytest.raises(CalibrationError, match="no lens over the 1296x972 image") as info:
        load_calibration(p)
    assert str(p) in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize(
    "camera",
    [
        default_camera(),  # folds at 1.08, outside its image
        Camera(
            np.array([[1100.0, 0, 959.5], [0, 1100.0, 539.5], [0, 0, 1]]), np.array([-0.12, 0, 0, 0, 0]), 1920, 1080
        ),
        Camera(default_camera().K, np.array([-0.28, 0.09, 0.001, -0.0015, 0.0])),
        Camera(default_camera().K, np.array([0.11, -0.23, 0.001, -0.002, 0.05, 0.1, 0, 0])),  # rational
    ],
)
def test_real_lenses_still_load(tmp_path, camera):
    p = tmp_path / "camera.yaml"
    save_calibration(camera, p)
    assert np.allclose(load_calibration(p).dist, camera.dist)


def test_a_huge_rotation_entry_in_a_rig_is_refused_without_numpy_warnings(tmp_path):
    """1e308 in T_body_camera printed numpy's "overflow encountered in matmul" and a source line."""
    save_calibration(default_camera(), tmp_path / "camera.yaml")
    T = [[1e308, -0.819, 0.574, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -0.574, -0.819, 1.3], [0, 0, 0, 1]]
    (tmp_path / "rig.json").write_text(json.dumps({"cameras": [{"name": "front", "T_body_camera": T}]}))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(CalibrationError, match=r"cameras\[0\]: T_body_camera is not a rigid transform"):
            load_rig(tmp_path / "rig.json")


def test_opencv_log_lines_are_kept_off_stderr(tmp_path):
    """A file that is not a video made FFmpeg print "moov atom not found", and a missing camera index
    OpenCV print two "[ WARN:0@0.4] global cap_v4l.cpp" lines, around tagloc's own one line."""
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"junk")
    env = {k: v for k, v in os.environ.items() if not k.startswith("OPENCV_") and k != "TAGLOC_DEBUG"}
    code = f"import tagloc.cli, cv2; cv2.VideoCapture({str(junk)!r}); cv2.VideoCapture(97); print('done')"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert res.stdout.strip() == "done" and res.stderr == "", res.stderr
