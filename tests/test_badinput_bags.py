"""Bad input in ROS bags: a pose_json that is no JSON object, a wild image stamp, a recording that
was killed, a calibration of another size, and bag outputs that cannot be written."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from tagloc.core.errors import SessionError
from tagloc.io.fleet import FleetState, MessageError, parse_message
from tagloc.io.rosbag import (
    STRING_TYPE,
    BagSession,
    BagWriter,
    _RawImage,
    bag_to_session,
    judge_stamps,
    read_pose_messages,
)
from tagloc.io.session import SessionReader

REPO = Path(__file__).resolve().parent.parent
WALK = REPO / "logs" / "walk2s"  # a 2 s session made by `tagloc simulate`
TOPIC = "/cam/image/compressed"
WILD = 2**31 - 1.0  # a header stamp far in the future (the last second ROS 2 can hold)


def _image_bag(path: Path, stamps: list[float], info: bool = False) -> Path:
    """A rosbag2 (MCAP) of walk2s's first frames as JPEG CompressedImages with these header stamps,
    received 1/30 s apart from 100 s on (and a CameraInfo of walk2s's calibration with ``info``)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from tagloc.io.rosbag import camera_info

    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    session = SessionReader(WALK)
    frames = list(session.frames())[: len(stamps)]
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection(TOPIC, "sensor_msgs/msg/CompressedImage", typestore=store)
        cinfo = w.add_connection("/cam/camera_info", "sensor_msgs/msg/CameraInfo", typestore=store) if info else None
        for k, (f, t) in enumerate(zip(frames, stamps)):
            stamp = T["builtin_interfaces/msg/Time"](*divmod(round(t * 1e9), 10**9))
            header = T["std_msgs/msg/Header"](stamp, "cam")
            msg = T["sensor_msgs/msg/CompressedImage"](header, "jpeg", cv2.imencode(".jpg", f.image)[1].ravel())
            received = round((100 + k / 30) * 1e9)
            w.write(conn, received, store.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))
            if cinfo is not None:
                ci = camera_info(T, header, session.camera)
                w.write(cinfo, received, store.serialize_cdr(ci, "sensor_msgs/msg/CameraInfo"))
    return path


# --- 1: a pose_json that is JSON but no object -----------------------------------------------------


@pytest.mark.parametrize("doc", [[1, 2], 5, None, True, 2.5])
def test_a_decoded_document_that_is_no_object_is_a_message_error(doc):
    with pytest.raises(MessageError, match="not a JSON object"):
        parse_message(doc)


def test_a_bags_pose_json_that_is_no_object_is_counted_invalid(tmp_path):
    """`monitor --from-bag` stopped with an internal TypeError on a pose_json of [1, 2]."""
    rig = SessionReader(WALK).rig
    bag = tmp_path / "v1"
    w = BagWriter(bag, "v1", rig)
    for k, text in enumerate(["[1, 2]", "5", "null", "true"]):
        w._write(w._json, 10.0 + k, w._types[STRING_TYPE](data=text))
    w.close()
    msgs = list(read_pose_messages(bag))
    assert [m.doc for m in msgs] == ["[1, 2]", "5", "null", "true"]  # passed on as the text
    state = FleetState()
    for m in msgs:
        assert state.handle(m.doc, m.t_bag) is None
    assert state.received == 4 and state.invalid == 4 and "not a JSON object" in state.last_error


# --- 6: a wild image stamp ------------------------------------------------------------------------


def _raw(stamps: list[float | None]) -> list[_RawImage]:
    return [_RawImage(k, 100 + k / 10, t, object(), "sensor_msgs/msg/CompressedImage") for k, t in enumerate(stamps)]


def test_a_lone_stamp_far_ahead_is_wild_and_gets_a_time_between_its_neighbours():
    stamps = [0.0, 0.1, 0.2, WILD, 0.4, 0.5, 0.6]
    got = list(judge_stamps(_raw(stamps), TOPIC))
    assert [g.wild is not None for g in got] == [False, False, False, True, False, False, False]
    assert "frame 3" in got[3].wild and "2147483647" in got[3].wild and "frame 4's 0.400000 s" in got[3].wild
    assert 0.2 < got[3].t < 0.4  # the localiser takes it (skipped) and the frames after it
    assert [g.t for g in got if g.wild is None] == [0.0, 0.1, 0.2, 0.4, 0.5, 0.6]


@pytest.mark.parametrize(
    "stamps",
    [
        [100.0, 100.1, 100.1, 100.05, 100.2],  # jitter: the later frame is the one refused, as before
        [5.0, 5.1, 5.2, 5.3, 5.4, 5.5, 5.6, 1.0, 1.1, 1.2, 1.3],  # a clock that was reset: left to the localiser
        [0.0, 0.1, 0.2, 0.3, 0.4],  # in order
    ],
)
def test_stamps_that_are_no_lone_outlier_pass_as_they_are(stamps):
    got = list(judge_stamps(_raw(stamps), TOPIC))
    assert [g.wild for g in got] == [None] * len(stamps) and [g.t for g in got] == stamps


def test_the_first_frame_and_a_short_run_can_be_wild():
    got = list(judge_stamps(_raw([WILD, 0.1, 0.2, 0.3]), TOPIC))
    assert [g.wild is not None for g in got] == [True, False, False, False] and got[0].t < 0.1
    got = list(judge_stamps(_raw([0.0, 0.1, 50.0, 50.1, 0.2, 0.3, None, 0.5]), TOPIC))
    assert [g.wild is not None for g in got] == [False, False, True, True, False, False, False, False]
    assert 0.3 < got[6].t < 0.5  # a corrupt message: its receive time on the frames' clock (not the wild one's)


def test_a_conversion_skips_and_names_the_wild_frame_not_the_rest(tmp_path):
    """`session from-bag` of a bag with one image stamped 2^31-1 s wrote the frames before it and
    skipped every one after it, naming none."""
    stamps = [100 + k / 30 for k in range(8)]
    stamps[3] = WILD
    bag = _image_bag(tmp_path / "wild", stamps)
    warned: list[str] = []
    n, skipped = bag_to_session(bag, TOPIC, tmp_path / "s", WALK / "map.csv", WALK / "rig.json", warn=warned.append)
    assert (n, skipped) == (7, 1)
    assert list(SessionReader(tmp_path / "s").index) == [0, 1, 2, 4, 5, 6, 7]
    assert len(warned) == 1 and "1 frame skipped: frame 3: " in warned[0] and "2147483647" in warned[0]


def test_a_replay_skips_the_wild_frame_without_a_clock_reset(tmp_path):
    """A replay took the wild stamp, refused the next 4 frames, then restarted on a "reset" clock and
    published every later pose 2^31 s late."""
    from tagloc.pipeline.localiser import Localiser

    stamps = [100 + k / 30 for k in range(10)]
    stamps[3] = WILD
    src = BagSession(_image_bag(tmp_path / "wild", stamps, info=True), TOPIC, WALK / "map.csv")
    loc = Localiser(src.map, src.rig)
    results = [loc.process(f) for f in src.frames()]
    assert [r.skipped is not None for r in results] == [k == 3 for k in range(10)]
    assert "a wild stamp" in results[3].skipped and src.skipped == [(3, results[3].skipped)]
    assert loc.counts["clock_resets"] == 0 and loc.counts["refused_timestamps"] == 0
    assert max(r.timestamp for r in results) < 101


# --- 7: a recording that was killed ---------------------------------------------------------------


def test_a_bag_without_metadata_is_named_an_interrupted_recording(tmp_path):
    bag = _image_bag(tmp_path / "killed", [100.0, 100.1])
    (bag / "metadata.yaml").unlink()  # as a kill -9 leaves it: rosbag2 writes it on close
    with pytest.raises(SessionError, match=r"killed.mcap but no metadata.yaml: the recording was likely interrupted"):
        BagSession(bag, TOPIC, WALK / "map.csv", calibration=WALK / "camera.yaml")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SessionError, match=r"not a rosbag2 directory \(no metadata.yaml\)$"):
        BagSession(tmp_path / "empty", TOPIC, WALK / "map.csv")


def test_a_cut_mcap_file_is_named_an_interrupted_recording(tmp_path):
    bag = _image_bag(tmp_path / "cut", [100.0, 100.1])
    mcap = bag / "cut.mcap"
    mcap.write_bytes(mcap.read_bytes()[:-100])
    with pytest.raises(SessionError, match="cannot read bag .*likely interrupted") as exc:
        BagSession(bag, TOPIC, WALK / "map.csv", calibration=WALK / "camera.yaml")
    assert "\n" not in str(exc.value)


# --- 8: bag outputs checked before work starts ----------------------------------------------------


def test_bag_outputs_are_checked_before_any_work(tmp_path, capsys):
    from tagloc.cli import main

    (tmp_path / "taken").mkdir()
    (tmp_path / "file").write_text("x")
    cases = [
        (["replay", str(WALK), "--bag", str(tmp_path / "taken"), "--quiet"], "--bag: already exists"),
        (["replay", str(WALK), "--bag", str(tmp_path / "file" / "b.bag2"), "--quiet"], "is a file, not a directory"),
        (
            ["live", "--camera", str(WALK), "--config", str(WALK), "--record-bag", str(tmp_path / "taken")],
            "--record-bag",
        ),
    ]
    for argv, message in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1
    assert sorted(os.listdir(tmp_path)) == ["file", "taken"]


# --- 14: a calibration of another size ------------------------------------------------------------


def test_a_conversion_refuses_a_calibration_of_another_size(tmp_path):
    """`session from-bag` wrote all frames with a 1298x972 calibration for 1296x972 images; every
    reader then refused every frame."""
    bag = _image_bag(tmp_path / "b", [100.0, 100.1, 100.2])
    cal = tmp_path / "cam1298.yaml"
    cal.write_text((WALK / "camera.yaml").read_text().replace("image_width: 1296", "image_width: 1298"))
    with pytest.raises(SessionError) as exc:
        bag_to_session(bag, TOPIC, tmp_path / "s", WALK / "map.csv", calibration=cal)
    msg = str(exc.value)
    assert str(bag) in msg and TOPIC in msg and str(cal) in msg and "1296x972" in msg and "1298x972" in msg
    assert not (tmp_path / "s").exists()
    # The rig's calibration file is named when it is the one used (no CameraInfo in the bag).
    rigdir = tmp_path / "rig"
    rigdir.mkdir()
    (rigdir / "rig.json").write_text((WALK / "rig.json").read_text())
    (rigdir / "camera.yaml").write_text(cal.read_text())
    with pytest.raises(SessionError, match=r"calibration .*rig/camera.yaml is for 1298x972"):
        bag_to_session(bag, TOPIC, tmp_path / "s2", WALK / "map.csv", rig_path=rigdir / "rig.json")


def test_a_frame_of_another_size_is_skipped_and_named(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    frames = list(SessionReader(WALK).frames())[:3]
    images = [frames[0].image, np.full((20, 20), 128, np.uint8), frames[2].image]
    bag = tmp_path / "b"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection(TOPIC, "sensor_msgs/msg/CompressedImage", typestore=store)
        for k, img in enumerate(images):
            header = T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](100 + k, 0), "cam")
            msg = T["sensor_msgs/msg/CompressedImage"](header, "jpeg", cv2.imencode(".jpg", img)[1].ravel())
            w.write(conn, (100 + k) * 10**9, store.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))
    warned: list[str] = []
    n, skipped = bag_to_session(bag, TOPIC, tmp_path / "s", WALK / "map.csv", WALK / "rig.json", warn=warned.append)
    assert (n, skipped) == (2, 1) and "frame 1: image is 20x20, the calibration is for 1296x972" in warned[0]
