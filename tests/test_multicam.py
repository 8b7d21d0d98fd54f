"""Several cameras: the simulator renders every rig camera into one session; sessions carry a camera column."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tagloc.cli import main
from tagloc.core.errors import SessionError
from tagloc.core.rig import default_rig
from tagloc.core.stickermap import load_map
from tagloc.eval import multicam
from tagloc.eval.multicam import MultiCamConfig, camera_subset, front_rear_rig, run_two_camera, sticker_in_view
from tagloc.io.session import SessionInfo, SessionReader, SessionWriter
from tagloc.pipeline.localiser import Localiser, LocaliserConfig
from tagloc.pipeline.run import run_session
from tagloc.sim.simulate import SimConfig, read_groundtruth_frames, simulate_session
from tagloc.vision.odometry import floor_patch

MAP = Path(__file__).resolve().parents[1] / "maps" / "demo.csv"


@pytest.fixture(scope="module")
def two_cam(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("multicam") / "walk"
    simulate_session(
        MAP, path, SimConfig(seconds=1.0, fps=10.0, seed=1, scale=0.5, rig=front_rear_rig()), progress=False
    )
    return path


def test_every_camera_is_rendered_into_one_session(two_cam):
    lines = (two_cam / "frames.csv").read_text().splitlines()
    assert lines[0] == "index,timestamp_s,camera" and len(lines) == 21
    session = SessionReader(two_cam)
    assert len(session.rig) == 2 and list(session.cameras) == [0, 1] * 10
    assert np.all(np.diff(session.timestamps) > 0)  # the rear camera exposes half a frame later
    assert (two_cam / "frames" / "000001_cam1.jpg").exists() and (two_cam / "frames" / "000000.jpg").exists()
    frames = list(session.frames())
    assert [f.camera for f in frames] == [0, 1] * 10 and all(f.image is not None for f in frames)
    gt = read_groundtruth_frames(two_cam)
    assert [r["camera"] for r in gt] == [0, 1] * 10
    # The two cameras look opposite ways: their optical axes point apart horizontally.
    ax0, ax1 = (np.array(gt[k]["T_world_camera"])[:2, 2] for k in (0, 1))
    assert ax0 @ ax1 < 0
    assert 0.0 <= sticker_in_view(two_cam, 2) <= 1.0
    info = json.loads((two_cam / "session.json").read_text())
    assert info["simulation"]["config"]["rig"] == "given"


def test_the_localiser_takes_both_cameras(two_cam):
    log = run_session(SessionReader(two_cam))
    assert len(log.stamps) == 20 and np.all(np.diff(log.stamps) > 0)
    # Each camera's floor-odometry step spans its own previous frame, with the other camera's frame
    # in between: every step is matched to its camera's clone (before per-camera clones: none was).
    c = log.counts
    assert c["odometry_steps"] >= 5 and c["tracker_odometry_unmatched"] == 0
    assert c["tracker_odometry_accepted"] >= 0.8 * (c["odometry_steps"] - c["tracker_odometry_ignored"])


def test_camera_subset_keeps_one_cameras_frames(two_cam):
    session = SessionReader(two_cam)
    front = camera_subset(session, [0])
    assert list(front.cameras) == [0] * 10 and list(front.index) == list(session.index[::2])
    assert [f.camera for f in front.frames(with_images=False)] == [0] * 10
    assert len(session) == 20  # the original is untouched
    # The front camera alone sees a sticker at no more frame times than both together.
    assert sticker_in_view(two_cam, 2, [0]) <= sticker_in_view(two_cam, 2)


def test_two_camera_eval_table(tmp_path, monkeypatch, capsys):
    cfg = MultiCamConfig(map_path=MAP, out=tmp_path, seeds=(1,), seconds=2.0, fps=10.0, scale=0.5, progress=False)
    text = run_two_camera(cfg)
    res = json.loads((tmp_path / "results.json").read_text())
    rows = {r["rig"]: r for r in res["rows"]}
    assert set(rows) == {"front", "front+rear"} and all(r["walk"] == "s1" for r in rows.values())
    assert rows["front"]["frames"] == 20 and rows["front+rear"]["frames"] == 40
    assert rows["front+rear"]["sticker_in_view"] >= rows["front"]["sticker_in_view"]
    assert rows["front+rear"]["fixes"] >= rows["front"]["fixes"]
    for r in rows.values():
        assert r["odometry_unmatched"] == 0
        assert 0.0 < r["rmse_m"] < 0.5 and np.isfinite(r["nees_mean"]) and 0.0 <= r["coverage"] <= 1.0
    assert set(res["summary"]) == {"front", "front+rear"}
    lines = text.splitlines()
    assert any(line.startswith("| s1 | front |") for line in lines)
    assert any(line.startswith("| s1 | front+rear |") for line in lines)
    assert (tmp_path / "two_camera.png").stat().st_size > 1000 and (tmp_path / "report.md").exists()
    # A second run reuses the walk (same conditions) and gives the same table; so does the CLI preset.
    assert run_two_camera(cfg) == text
    monkeypatch.setattr(multicam, "TWO_CAMERA_WALKS", cfg)
    assert main(["eval", "--preset", "two-camera", "--quiet", "-o", str(tmp_path)]) == 0
    assert capsys.readouterr().out.strip() == text


def test_camera_column_checked_and_single_camera_layout_kept(tmp_path):
    smap = load_map(MAP)
    with SessionWriter(tmp_path / "one", smap, default_rig(), SessionInfo("test", 10.0)) as w:
        w.write(0, 0.0, np.zeros((972, 1296), np.uint8))
        with pytest.raises(SessionError, match="one camera"):
            w.write(1, 0.1, np.zeros((972, 1296), np.uint8), camera=1)
    assert (tmp_path / "one" / "frames.csv").read_text() == "index,timestamp_s\n0,0.000000\n"
    (tmp_path / "one" / "frames.csv").write_text("index,timestamp_s,camera\n0,0.000000,1\n")
    with pytest.raises(SessionError, match=r"frames.csv:2: camera '1' is not a camera of the rig"):
        SessionReader(tmp_path / "one")


def test_odometry_from_chosen_cameras_only(two_cam):
    session = SessionReader(two_cam)
    loc = Localiser(session.map, session.rig, LocaliserConfig(odometry_cameras=(0,)))
    both = run_session(session).counts["odometry_steps"]
    front = run_session(session, localiser=loc).counts
    assert loc.floor_odometry(1) is None and loc.floor_odometry(0) is not None
    assert 0 < front["odometry_steps"] <= min(9, both)
    assert front["odometry_unavailable"] == 0 and front["tracker_odometry_unmatched"] == 0


def test_a_rear_camera_matches_its_nearest_floor():
    """The odometry patch of a camera looking back mirrors the front camera's about the camera: the
    nearest full square, not the farthest (seen coarser, and swung more by the torso's lean)."""
    front, rear = (replace(c, legs_in_view=False) for c in front_rear_rig().cameras)  # no legs in view
    pf, pr = floor_patch(front), floor_patch(rear)
    x_front, x_rear = front.T_body_camera[0, 3], rear.T_body_camera[0, 3]
    assert pr.side == pytest.approx(pf.side, abs=1e-3)
    assert x_rear - pr.x_far == pytest.approx(pf.x_near - x_front, abs=0.02)


def test_sticker_tracks_survive_the_other_cameras_frames(tmp_path):
    # Each camera's decoded stickers are carried into its own next frame, with the other camera's
    # frame in between (a review found every two-camera track wiped by the other camera's frame:
    # no sticker carried, every one decoded again, the floor flow never skipped). 15 fps per camera:
    # a camera's frames within TrackingConfig.max_gap_s of each other.
    path = tmp_path / "walk"
    simulate_session(
        MAP, path, SimConfig(seconds=2.0, fps=15.0, seed=1, scale=0.5, rig=front_rear_rig()), progress=False
    )
    session = SessionReader(path)
    both = run_session(session).counts
    front = run_session(camera_subset(session, [0])).counts
    assert front["tracked"] > 0
    assert both["tracked"] >= front["tracked"]


def test_one_calibration_is_not_given_to_cameras_that_have_their_own(tmp_path):
    # --calibration replaced every rig camera's calibration: a half-resolution rear camera then had
    # every frame refused as the wrong size (a review), one of the same size would be solved
    # through the front camera's lens.
    from tagloc.core.camera import default_camera, save_calibration
    from tagloc.core.errors import InputError
    from tagloc.core.rig import save_rig
    from tagloc.pipeline.localiser import load_setup

    rig = front_rear_rig()
    rig.cameras[1].camera = default_camera().scaled(0.5)
    save_rig(rig, tmp_path / "rig.json")
    save_calibration(default_camera(), tmp_path / "front.yaml")
    with pytest.raises(InputError, match="camera0.yaml, camera1.yaml"):
        load_setup(MAP, tmp_path / "front.yaml", tmp_path / "rig.json")
    _, loaded = load_setup(MAP, None, tmp_path / "rig.json")
    assert loaded[1].camera.size == (648, 486)
    # A one-camera rig (or cameras sharing one file) still takes it.
    (tmp_path / "one").mkdir()
    save_rig(default_rig(), tmp_path / "one" / "rig.json")
    assert len(load_setup(MAP, tmp_path / "front.yaml", tmp_path / "one" / "rig.json")[1]) == 1


def test_one_calibration_is_given_again_to_a_recording_of_cameras_that_shared_it(tmp_path):
    # Two cameras of one model sharing one calibration: live takes --calibration, and its recording
    # names the calibrations camera0.yaml and camera1.yaml apart (one file each, the same contents).
    # Replaying that recording with the same --calibration was refused as cameras with their own
    # (a review); cameras whose files differ still are.
    from tagloc.core.camera import default_camera, save_calibration
    from tagloc.core.errors import InputError
    from tagloc.core.rig import save_rig
    from tagloc.io.session import SessionInfo, SessionWriter
    from tagloc.pipeline.localiser import load_setup

    rig = front_rear_rig()
    for c in rig.cameras:
        c.calibration_file = "camera.yaml"
    save_rig(rig, tmp_path / "rig.json", write_calibrations=False)
    save_calibration(default_camera(), tmp_path / "cam.yaml")
    smap, live_rig = load_setup(MAP, tmp_path / "cam.yaml", tmp_path / "rig.json")
    with SessionWriter(tmp_path / "rec", smap, live_rig, SessionInfo(source="0", fps=30.0)):
        pass
    assert "camera1.yaml" in (tmp_path / "rec" / "rig.json").read_text()
    _, again = load_setup(MAP, tmp_path / "cam.yaml", tmp_path / "rec" / "rig.json")
    assert len(again) == 2 and all(c.camera.size == default_camera().size for c in again)
    save_calibration(default_camera().scaled(0.5), tmp_path / "rec" / "camera1.yaml")
    with pytest.raises(InputError, match="camera0.yaml, camera1.yaml"):
        load_setup(MAP, tmp_path / "cam.yaml", tmp_path / "rec" / "rig.json")
