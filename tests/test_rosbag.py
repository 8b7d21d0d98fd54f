"""ROS bags: write a bag from a simulated session, read it back with rosbags, replay it, convert it."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from tagloc.core.errors import InputError, SessionError
from tagloc.core.stickermap import load_map
from tagloc.core.types import Frame, FrameResult, TrackerOutput, TrackState
from tagloc.io.rosbag import (
    UNESTIMATED_VARIANCE,
    BagSession,
    BagWriter,
    bag_to_session,
    covariance_3x3,
    covariance_6x6,
    read_pose_messages,
    ros_name,
)
from tagloc.io.session import SessionReader
from tagloc.io.sinks import PoseMessage, TumSink
from tagloc.pipeline.run import run_session

REPO = Path(__file__).resolve().parent.parent
WALK = REPO / "logs" / "walk2s"  # a 2 s session made by `tagloc simulate`
IMAGE_TOPIC = "/tagloc/vest_1/front/image/compressed"


def _read_all(bag: Path) -> dict[str, list[tuple[int, object]]]:
    from rosbags.highlevel import AnyReader

    out: dict[str, list[tuple[int, object]]] = {}
    with AnyReader([bag]) as r:
        for conn, ns, raw in r.messages():
            out.setdefault(conn.topic, []).append((ns, r.deserialize(raw, conn.msgtype)))
    return out


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> dict:
    """walk2s replayed once, written to a bag with images, and its TUM and outputs kept for comparison."""
    tmp = tmp_path_factory.mktemp("bag")
    session = SessionReader(WALK)
    bag = tmp / "walk.bag2"
    writer = BagWriter(bag, "vest-1", session.rig, images=True)
    tum = TumSink(tmp / "session.tum")
    results = []

    def on_result(res):
        writer.publish(PoseMessage("vest-1", res.index, res.output))
        writer.write_frame(Frame(res.index, res.timestamp, None), res, session.frame_path(res.index).read_bytes())
        tum.write(res.output)
        results.append(res)

    run_session(session, on_result=on_result)
    writer.close()
    tum.close()
    return {"tmp": tmp, "bag": bag, "session": session, "results": results, "tum": tmp / "session.tum"}


def test_bag_counts_timestamps_and_covariance(written):
    msgs = _read_all(written["bag"])
    results = written["results"]
    posed = [r for r in results if r.output.state != TrackState.INITIALISING]
    n = len(results)
    assert n == len(written["session"]) == 60 and len(posed) > 50
    assert len(msgs["/tagloc/vest_1/pose_json"]) == n
    assert len(msgs["/tagloc/vest_1/pose"]) == len(posed) == len(msgs["/tf"])
    assert len(msgs["/tf_static"]) == 1
    assert len(msgs["/tagloc/vest_1/front/detections"]) == n
    assert len(msgs[IMAGE_TOPIC]) == len(msgs["/tagloc/vest_1/front/camera_info"]) == n
    for (ns, msg), res in zip(msgs["/tagloc/vest_1/pose"], posed):
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        assert t == pytest.approx(res.timestamp, abs=1e-9) and ns == round(res.timestamp * 1e9)
        assert msg.header.frame_id == "map"
        cov = msg.pose.covariance.reshape(6, 6)
        assert np.allclose(covariance_3x3(cov), res.output.cov, rtol=0, atol=1e-15)
        assert np.allclose(np.diag(cov)[2:5], UNESTIMATED_VARIANCE)
        assert np.allclose(cov, cov.T)
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        assert (p.x, p.y, p.z) == pytest.approx((res.output.pose[0], res.output.pose[1], 0.0))
        dyaw = 2 * np.arctan2(q.z, q.w) - res.output.pose[2]
        assert abs((dyaw + np.pi) % (2 * np.pi) - np.pi) < 1e-9 and abs(q.x) + abs(q.y) < 1e-12
    tf = msgs["/tf"][0][1].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("map", "vest_1/body")
    static = msgs["/tf_static"][0][1].transforms[0]
    assert (static.header.frame_id, static.child_frame_id) == ("vest_1/body", "vest_1/front")
    assert static.transform.translation.z == pytest.approx(written["session"].rig[0].T_body_camera[2, 3])
    # Detections: one entry per observation, corners and IDs as the localiser saw them.
    for (_, det), res in zip(msgs["/tagloc/vest_1/front/detections"], results):
        assert len(det.detections) == len(res.observations)
        for d, o in zip(det.detections, res.observations):
            assert d.sticker_id == (-1 if o.sticker_id is None else o.sticker_id)
            assert d.source == o.source.value and d.accepted == bool(o.accepted)
            assert np.allclose(d.corners_px.reshape(4, 2), o.detection.outer)
    # The JSON twin carries the full tagloc message.
    doc = json.loads(msgs["/tagloc/vest_1/pose_json"][-1][1].data)
    assert doc["vest"] == "vest-1" and doc["state"] == results[-1].output.state.value


def test_bag_metadata_reads_as_humbles_rosbag2_reads_it(written):
    # Humble's rosbag2 (metadata_io.cpp, rosbag2_transport/qos.cpp) reads every topic's
    # offered_qos_profiles with as<std::string>() and parses that string's policies as integers; a
    # list there (metadata version 9) made `ros2 bag info`/`play` stop at "yaml-cpp: bad conversion".
    import yaml

    meta = yaml.safe_load((written["bag"] / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 8 and meta["storage_identifier"] == "mcap"
    topics = {t["topic_metadata"]["name"]: t for t in meta["topics_with_message_count"]}
    for t in topics.values():
        assert isinstance(t["topic_metadata"]["offered_qos_profiles"], str)
    (latched,) = yaml.safe_load(topics["/tf_static"]["topic_metadata"]["offered_qos_profiles"])
    # rmw's enums: KEEP_LAST 1, RELIABLE 1, TRANSIENT_LOCAL 1, AUTOMATIC 1
    assert (latched["history"], latched["depth"], latched["reliability"], latched["durability"]) == (1, 1, 1, 1)
    assert latched["liveliness"] == 1 and latched["deadline"] == {"sec": 0, "nsec": 0}
    assert topics["/tf_static"]["message_count"] == 1 and topics["/tf"]["message_count"] > 50
    assert meta["message_count"] == sum(t["message_count"] for t in topics.values())


def test_replaying_the_bag_gives_the_sessions_trajectory(written):
    bag = BagSession(written["bag"], IMAGE_TOPIC, WALK / "map.csv", WALK / "rig.json")
    assert len(bag) == 60
    assert np.array_equal(bag.camera.K, written["session"].camera.K)
    assert np.array_equal(bag.camera.dist, written["session"].camera.dist)
    tum = TumSink(written["tmp"] / "bag.tum")
    run_session(bag, on_result=lambda r: tum.write(r.output))
    tum.close()
    assert (written["tmp"] / "bag.tum").read_bytes() == written["tum"].read_bytes()


def test_bag_to_session_keeps_jpeg_bytes_and_stamps(written):
    out = written["tmp"] / "converted"
    n, skipped = bag_to_session(written["bag"], IMAGE_TOPIC, out, WALK / "map.csv", WALK / "rig.json")
    assert (n, skipped) == (60, 0)
    conv = SessionReader(out)
    assert np.array_equal(conv.timestamps, written["session"].timestamps)
    for i in (0, 31, 59):
        assert conv.frame_path(i).read_bytes() == written["session"].frame_path(i).read_bytes()


def test_read_pose_messages_for_the_monitor(written):
    poses = list(read_pose_messages(written["bag"]))
    assert len(poses) == 60 and all(p.doc["vest"] == "vest-1" for p in poses)
    assert [p.t_bag for p in poses] == sorted(p.t_bag for p in poses)


def test_ros1_bag_with_raw_images(tmp_path):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    T = store.types
    session = SessionReader(WALK)
    cam = session.camera
    path = tmp_path / "cam.bag"
    frames = list(session.frames())[:5]
    with Writer(path) as w:
        img_c = w.add_connection("/cam/image_raw", "sensor_msgs/msg/Image", typestore=store)
        info_c = w.add_connection("/cam/camera_info", "sensor_msgs/msg/CameraInfo", typestore=store)
        for f in frames:
            sec, nsec = divmod(round((f.timestamp + 100.0) * 1e9), 10**9)  # a zero stamp means unset
            header = T["std_msgs/msg/Header"](
                seq=f.index, stamp=T["builtin_interfaces/msg/Time"](sec, nsec), frame_id="cam"
            )
            rgb = cv2.cvtColor(f.image, cv2.COLOR_GRAY2RGB)
            h, wd = f.image.shape
            msg = T["sensor_msgs/msg/Image"](header, h, wd, "rgb8", 0, 3 * wd, rgb.ravel())
            ns = round((f.timestamp + 100.0) * 1e9) + 1000  # received a microsecond after capture
            w.write(img_c, ns, store.serialize_ros1(msg, "sensor_msgs/msg/Image"))
            info = T["sensor_msgs/msg/CameraInfo"](
                header, cam.height, cam.width, "plumb_bob", cam.dist, cam.K.ravel(), np.eye(3).ravel(),
                np.c_[cam.K, np.zeros(3)].ravel(), 0, 0, T["sensor_msgs/msg/RegionOfInterest"](0, 0, 0, 0, False),
            )  # fmt: skip
            w.write(info_c, ns, store.serialize_ros1(info, "sensor_msgs/msg/CameraInfo"))
    bag = BagSession(path, "/cam/image_raw", WALK / "map.csv")  # no rig: default rig with the bag's CameraInfo
    assert np.array_equal(bag.camera.K, cam.K) and len(bag) == 5
    got = list(bag.frames())
    assert [f.timestamp for f in got] == pytest.approx([f.timestamp + 100.0 for f in frames], abs=1e-9)
    for a, b in zip(got, frames):
        # rgb8 -> grey round trip of a grey image is exact up to OpenCV's fixed-point weights.
        assert np.abs(a.image.astype(int) - b.image.astype(int)).max() <= 1


def test_bad_bags_give_one_line_errors(tmp_path, written):
    with pytest.raises(SessionError, match="no such bag"):
        BagSession(tmp_path / "nothing", "/x", WALK / "map.csv")
    with pytest.raises(SessionError, match="image topics in the bag: /tagloc/vest_1/front/image/compressed"):
        BagSession(written["bag"], "/cam/image", WALK / "map.csv")
    with pytest.raises(SessionError, match="not an Image"):
        BagSession(written["bag"], "/tf", WALK / "map.csv")
    (tmp_path / "notabag").mkdir()
    with pytest.raises(SessionError, match="no metadata.yaml"):
        BagSession(tmp_path / "notabag", "/x", WALK / "map.csv")
    with pytest.raises(InputError, match="already exists"):
        BagWriter(written["bag"], "v", SessionReader(WALK).rig)


@pytest.mark.parametrize(
    ("field", "value", "fragment"),
    [
        ("d", [np.nan, 0, 0, 0, 0], "NaN or inf"),
        ("d", [0.1, 0.0, 0.0], "3 distortion coefficients"),  # stopped a replay inside OpenCV
        ("k", [1e-9, 0, 648, 0, 1e-9, 486, 0, 0, 1], "focal length"),
        ("k", [1285.7, 0, -5000, 0, 1285.7, 486, 0, 0, 1], "principal point"),
        ("width", 0, "image size"),
    ],
)
def test_a_bag_camera_info_is_checked_as_a_calibration_file_is(tmp_path, field, value, fragment):
    """Before any frame: a CameraInfo no calibration file could hold is refused naming the bag and the
    topic (it had run a whole replay without a pose); --calibration, which overrides it, is the way round."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from tagloc.io.rosbag import COMPRESSED_TYPE, INFO_TYPE, _typestore, camera_info

    store = _typestore()
    T = store.types
    session = SessionReader(WALK)
    path = tmp_path / "cam"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        img_c = w.add_connection("/cam/image/compressed", COMPRESSED_TYPE, typestore=store)
        info_c = w.add_connection("/cam/camera_info", INFO_TYPE, typestore=store)
        for i in range(3):
            ns = round((session.timestamps[i] + 100.0) * 1e9)
            header = T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](*divmod(ns, 10**9)), "cam")
            data = np.frombuffer(session.frame_path(i).read_bytes(), np.uint8)
            w.write(img_c, ns, store.serialize_cdr(T[COMPRESSED_TYPE](header, "jpeg", data), COMPRESSED_TYPE))
            info = camera_info(T, header, session.camera)
            setattr(info, field, np.asarray(value, float) if isinstance(value, list) else value)
            w.write(info_c, ns, store.serialize_cdr(info, INFO_TYPE))
    with pytest.raises(SessionError, match=rf"^{re.escape(str(path))}: /cam/camera_info: .*{re.escape(fragment)}"):
        BagSession(path, "/cam/image/compressed", WALK / "map.csv")
    bag = BagSession(path, "/cam/image/compressed", WALK / "map.csv", calibration=WALK / "camera.yaml")
    assert np.array_equal(bag.camera.K, session.camera.K)


def _damage_mid_bag(bag: Path, out: Path) -> Path:
    """A copy of ``bag`` whose middle chunk's first record claims a length past the file's end (what a
    disk error or a torn copy leaves): the reader gives the messages before it, then fails."""
    shutil.copytree(bag, out)
    mcap = next(out.glob("*.mcap"))
    d = bytearray(mcap.read_bytes())
    off, chunks = 8, []  # after the magic: opcode (1 byte), length (8), content
    while off + 9 <= len(d) and d[off] != 0x0F:  # up to the footer
        if d[off] == 0x06:
            chunks.append(off)
        off += 9 + int.from_bytes(d[off + 1 : off + 9], "little")
    # A chunk: 9-byte record head, times (16), sizes and CRC (12), compression (4 + n), records' length (8).
    p = chunks[len(chunks) // 2] + 9 + 28
    p += 4 + int.from_bytes(d[p - 4 : p], "little") + 8
    assert d[p - 4 - 8 : p - 8] == b"\0\0\0\0"  # uncompressed, so the records follow as they are
    d[p + 1 : p + 9] = (10**12).to_bytes(8, "little")
    mcap.write_bytes(bytes(d))
    return out


def test_a_bag_damaged_mid_file_is_refused_in_one_line_keeping_what_came_before(tmp_path, written):
    bag = _damage_mid_bag(written["bag"], tmp_path / "damaged.bag2")
    src = BagSession(bag, IMAGE_TOPIC, WALK / "map.csv", WALK / "rig.json")
    seen = []
    with pytest.raises(SessionError, match=rf"^{re.escape(str(bag))}: damaged after (\d+) messages \(") as err:
        run_session(src, on_result=seen.append)
    assert "\n" not in str(err.value)
    assert 10 <= len(seen) < 60  # the frames before the damage were localised and handed on
    out = tmp_path / "converted"
    with pytest.raises(
        SessionError, match=rf"damaged after \d+ messages .*; {re.escape(str(out))} holds the \d+ frames"
    ) as err:
        bag_to_session(bag, IMAGE_TOPIC, out, WALK / "map.csv", WALK / "rig.json")
    kept = int(re.search(r"holds the (\d+) frames", str(err.value)).group(1))
    conv = SessionReader(out)  # what came before the damage is a session to replay
    assert len(conv) == kept == len(seen)
    assert np.array_equal(conv.timestamps, written["session"].timestamps[: len(seen)])


def test_covariance_and_names():
    cov3 = np.array([[4e-4, 1e-5, 2e-6], [1e-5, 9e-4, 3e-6], [2e-6, 3e-6, 1e-3]])
    cov6 = covariance_6x6(cov3)
    assert cov6[0, 5] == 2e-6 and cov6[1, 5] == 3e-6 and cov6[5, 5] == 1e-3
    assert np.array_equal(covariance_3x3(cov6), cov3)
    assert np.all(np.linalg.eigvalsh(cov6) > 0)
    assert (ros_name("vest-1"), ros_name("07"), ros_name("a.b/c")) == ("vest_1", "v07", "a_b_c")


def test_cameras_named_alike_are_refused_before_the_bag_is_made(tmp_path):
    # Each camera's topics are /tagloc/VEST/CAM/...: two cameras named "front" and "front" (or
    # "front-left" and "front_left") made rosbag2 stop with an internal error, leaving a bag
    # directory that the next run refused as existing.
    from tagloc.eval.multicam import front_rear_rig

    for names in (("front", "front"), ("front-left", "front_left")):
        rig = front_rear_rig()
        for cam, name in zip(rig.cameras, names):
            cam.name = name
        with pytest.raises(InputError, match="distinct names"):
            BagWriter(tmp_path / "b", "v", rig)
        assert not (tmp_path / "b").exists()
    BagWriter(tmp_path / "b", "v", front_rear_rig()).close()


def test_initialising_writes_no_pose(tmp_path):
    rig = SessionReader(WALK).rig
    w = BagWriter(tmp_path / "b", "v", rig)
    out = TrackerOutput(0.5, np.zeros(3), np.eye(3), TrackState.INITIALISING, np.inf)
    assert w.publish(PoseMessage("v", 0, out)) is False
    w.close()
    msgs = _read_all(tmp_path / "b")
    assert "/tagloc/v/pose" not in msgs and len(msgs["/tagloc/v/pose_json"]) == 1 and w.dropped == 1


def test_cli_session_from_bag(written, capsys):
    from tagloc.cli import main

    out = written["tmp"] / "cli_session"
    args = ["session", "from-bag", str(written["bag"]), "--topic", IMAGE_TOPIC, "--map", str(WALK / "map.csv")]
    assert main([*args, "--rig", str(WALK / "rig.json"), "-o", str(out), "--quiet"]) == 0
    assert "60 frames written, 0 skipped" in capsys.readouterr().out
    assert len(SessionReader(out)) == 60
    assert main(["session", "from-bag", str(written["bag"]), "--topic", "/nope", "--map", str(WALK / "map.csv"),
                 "-o", str(written["tmp"] / "x")]) != 0  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no topic '/nope'" in err[0]


def test_a_session_from_a_bag_may_not_overwrite_the_files_it_reads(written, capsys):
    """``-o site`` with ``--map site/map.csv --rig site/rig.json`` had rewritten the map at 0.1 mm and
    replaced the site's calibration by the bag's CameraInfo, exit 0."""
    from tagloc.cli import main

    site = written["tmp"] / "site"
    site.mkdir()
    for name in ("rig.json", "camera.yaml"):
        shutil.copy(WALK / name, site / name)
    rows = [r.split(",") for r in (WALK / "map.csv").read_text().splitlines()]
    # A survey to the micrometre (x 1.9544 -> 1.954412): the session's map.csv holds 0.1 mm.
    lines = [",".join(rows[0])] + [",".join([r[0], r[1] + "12", *r[2:]]) for r in rows[1:]]
    (site / "map.csv").write_text("\n".join(lines) + "\n")
    before = {p.name: p.read_bytes() for p in site.iterdir()}
    base = ["session", "from-bag", str(written["bag"]), "--topic", IMAGE_TOPIC, "-o", str(site), "--quiet"]
    for given, clash in [
        (["--map", str(site / "map.csv"), "--rig", str(site / "rig.json")], "map.csv"),
        (["--map", str(WALK / "map.csv"), "--rig", str(site / "rig.json")], "rig.json"),
        (["--map", str(WALK / "map.csv"), "--calibration", str(site / "camera.yaml")], "camera.yaml"),
    ]:
        assert main([*base, *given]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [
            f"tagloc session: error: {site / clash}: is one of the conversion's inputs, which the session would overwrite"
        ]
    assert {p.name: p.read_bytes() for p in site.iterdir()} == before


def test_cli_replay_to_a_bag_and_back(tmp_path, capsys):
    from tagloc.cli import main

    bag = tmp_path / "walk.bag2"
    png = tmp_path / "walk.png"
    args = ["replay", str(WALK), "--quiet", "--out", str(tmp_path / "a.tum"), "--png", str(png)]
    assert main([*args, "--bag", str(bag), "--bag-images"]) == 0
    assert png.stat().st_size > 10_000  # the floor plan (matplotlib)
    topics = {k: len(v) for k, v in _read_all(bag).items()}
    assert topics["/tagloc/replay/pose_json"] == topics[IMAGE_TOPIC.replace("vest_1", "replay")] == 60
    img_topic = "/tagloc/replay/front/image/compressed"
    args = ["replay", str(bag), "--quiet", "--topic", img_topic, "--map", str(WALK / "map.csv")]
    rrd = tmp_path / "bag.rrd"
    assert main([*args, "--rig", str(WALK / "rig.json"), "--out", str(tmp_path / "b.tum"), "--rerun", str(rrd)]) == 0
    assert (tmp_path / "a.tum").read_bytes() == (tmp_path / "b.tum").read_bytes()
    from tagloc.io.rerun_view import read_rrd

    assert len(read_rrd(rrd)["world/body/front/image"].frames) == 60  # the bag's images reach the viewer
    capsys.readouterr()
    assert main(["replay", str(bag), "--quiet"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "needs --topic" in err[0]


def test_cli_live_records_a_bag(tmp_path):
    from tagloc.cli import main

    bag = tmp_path / "live.bag2"
    args = ["live", "--camera", str(WALK), "--config", str(WALK), "--no-pace", "--max-frames", "10"]
    assert main([*args, "--vest", "v07", "--record-bag", str(bag)]) == 0
    msgs = _read_all(bag)
    assert len(msgs["/tagloc/v07/pose_json"]) == 10 and len(msgs["/tagloc/v07/front/detections"]) == 10
    assert not any("image" in t for t in msgs)  # images only on request


def test_corrupt_image_messages_are_skipped_and_counted(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    session = SessionReader(WALK)
    frames = list(session.frames())[:3]
    path = tmp_path / "cam"
    with Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as w:  # SQLite storage read too
        conn = w.add_connection("/cam/image/compressed", "sensor_msgs/msg/CompressedImage", typestore=store)
        for f in frames:
            ns = round((f.timestamp + 100.0) * 1e9)
            header = T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](*divmod(ns, 10**9)), "cam")
            data = cv2.imencode(".jpg", f.image)[1].ravel() if f.index != 1 else np.frombuffer(b"not a jpeg", np.uint8)
            msg = T["sensor_msgs/msg/CompressedImage"](header, "jpeg", data)
            w.write(conn, ns, store.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))
    bag = BagSession(path, "/cam/image/compressed", WALK / "map.csv", WALK / "rig.json")  # no CameraInfo: the rig's
    got = list(bag.frames())
    assert [f.image is None for f in got] == [False, True, False]
    assert len(bag.skipped) == 1 and "frame 1" in bag.skipped[0][1] and "corrupt" in got[1].error
    n, skipped = bag_to_session(path, "/cam/image/compressed", tmp_path / "s", WALK / "map.csv", WALK / "rig.json")
    assert (n, skipped) == (2, 1)


@pytest.mark.parametrize("received_after_s", [0.08, 1000.0])
def test_a_message_that_cannot_be_read_costs_one_frame_not_those_after_it(tmp_path, received_after_s):
    """An image message whose bytes are not the type's has no header stamp: it took the bag's receive
    time, on which a driver's latency (80 ms here, beyond the 33 ms frame interval) or header stamps
    from another clock (1000 s) put it after the frames that follow, each then refused by the replay
    and skipped by the conversion (1000 s: the session kept the 3 frames before it of 8)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from tagloc.pipeline.localiser import Localiser

    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    frames = list(SessionReader(WALK).frames())[:8]
    path = tmp_path / "cam"
    with Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        conn = w.add_connection("/cam/image/compressed", "sensor_msgs/msg/CompressedImage", typestore=store)
        for f in frames:
            ns = round((f.timestamp + 100.0) * 1e9)
            header = T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](*divmod(ns, 10**9)), "cam")
            msg = T["sensor_msgs/msg/CompressedImage"](header, "jpeg", cv2.imencode(".jpg", f.image)[1].ravel())
            raw = store.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage")
            w.write(conn, ns + round(received_after_s * 1e9), raw[:40] if f.index == 3 else raw)
    src = BagSession(path, "/cam/image/compressed", WALK / "map.csv", WALK / "rig.json")
    loc = Localiser(src.map, src.rig)
    replayed = [loc.process(f) for f in src.frames()]
    assert [r.skipped is not None for r in replayed] == [False, False, False, True, False, False, False, False]
    assert loc.counts["refused_timestamps"] == 0 and len(src.skipped) == 1
    n, skipped = bag_to_session(path, "/cam/image/compressed", tmp_path / "s", WALK / "map.csv", WALK / "rig.json")
    assert (n, skipped) == (7, 1)
    s = SessionReader(tmp_path / "s")
    assert list(s.index) == [0, 1, 2, 4, 5, 6, 7]
    assert np.allclose(s.timestamps, [frames[k].timestamp + 100.0 for k in s.index], atol=1e-6)


def test_a_session_from_a_bag_whose_stamps_repeat_or_go_back_replays(tmp_path):
    """A camera driver that stamps two images alike (or one before its predecessor): the session
    written from the bag skips that frame, as a replay of the bag does, instead of being refused
    whole at its frames.csv."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    frames = list(SessionReader(WALK).frames())[:5]
    stamps = [100.0, 100.1, 100.1, 100.05, 100.2]  # frame 2 repeats frame 1's stamp, frame 3 goes back
    path = tmp_path / "cam"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/cam/image/compressed", "sensor_msgs/msg/CompressedImage", typestore=store)
        for k, (f, t) in enumerate(zip(frames, stamps)):
            header = T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](*divmod(round(t * 1e9), 10**9)), "cam")
            msg = T["sensor_msgs/msg/CompressedImage"](header, "jpeg", cv2.imencode(".jpg", f.image)[1].ravel())
            w.write(conn, 10**9 * 100 + k, store.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))
    n, skipped = bag_to_session(path, "/cam/image/compressed", tmp_path / "s", WALK / "map.csv", WALK / "rig.json")
    assert (n, skipped) == (3, 2)
    s = SessionReader(tmp_path / "s")
    assert list(s.index) == [0, 1, 4] and np.allclose(s.timestamps, [100.0, 100.1, 100.2])
    assert all(f.image is not None for f in s.frames())


def test_a_session_from_a_bag_keeps_a_frame_within_the_last_ones_microsecond(tmp_path):
    """Two images stamped 300 ns apart: a replay of the bag takes both, so the session does too, the
    second at the next microsecond (it was skipped as not after the first, as frames.csv holds it,
    though the README said a replay skips it too: a review)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from tagloc.pipeline.localiser import Localiser

    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    frames = list(SessionReader(WALK).frames())[:4]
    ns = [100 * 10**9, 100 * 10**9 + 300, 100 * 10**9 + 800, 100 * 10**9 + 10**8]
    path = tmp_path / "cam"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/cam/image/compressed", "sensor_msgs/msg/CompressedImage", typestore=store)
        for k, (f, t) in enumerate(zip(frames, ns)):
            header = T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](*divmod(t, 10**9)), "cam")
            msg = T["sensor_msgs/msg/CompressedImage"](header, "jpeg", cv2.imencode(".jpg", f.image)[1].ravel())
            w.write(conn, 10**9 * 100 + k, store.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))
    src = BagSession(path, "/cam/image/compressed", WALK / "map.csv", WALK / "rig.json")
    loc = Localiser(src.map, src.rig)
    replayed = [loc.process(f) for f in src.frames()]
    assert len(replayed) == 4 and loc.counts["refused_timestamps"] == 0
    n, skipped = bag_to_session(path, "/cam/image/compressed", tmp_path / "s", WALK / "map.csv", WALK / "rig.json")
    assert (n, skipped) == (4, 0)
    s = SessionReader(tmp_path / "s")
    assert list(s.index) == [0, 1, 2, 3] and np.allclose(s.timestamps, [100.0, 100.000001, 100.000002, 100.1])


def test_an_unreadable_source_directory_is_named_as_given(tmp_path, monkeypatch):
    """A session directory the user may not read: the error names it, not metadata.yaml inside it
    (probed to tell a bag from a session). Stat is refused as for a mode-000 directory and a non-root user."""
    from tagloc.io.rosbag import is_bag

    d = tmp_path / "sess"
    d.mkdir()
    real_exists = Path.exists

    def refused(self, *a, **k):
        if self.parent == d:
            raise PermissionError(13, "Permission denied", str(self))
        return real_exists(self, *a, **k)

    monkeypatch.setattr(Path, "exists", refused)
    with pytest.raises(SessionError, match=rf"^{re.escape(str(d))}: no permission to read$"):
        is_bag(d)


def test_a_raw_image_whose_rows_are_shorter_than_its_width_is_refused():
    """``step`` below width x bytes per pixel cannot hold a row: the message is undecodable, not an error."""
    from types import SimpleNamespace

    from tagloc.io.rosbag import _image_to_grey

    def msg(enc: str, step: int, w: int = 100, h: int = 10) -> SimpleNamespace:
        return SimpleNamespace(encoding=enc, height=h, width=w, step=step, data=bytes(h * max(step, 1)), is_bigendian=0)

    assert _image_to_grey(msg("bgr8", 100), "sensor_msgs/msg/Image") is None
    assert _image_to_grey(msg("mono16", 150), "sensor_msgs/msg/Image") is None
    assert _image_to_grey(msg("bgr8", 300), "sensor_msgs/msg/Image").shape == (10, 100)
    assert _image_to_grey(msg("mono8", 128), "sensor_msgs/msg/Image").shape == (10, 100)


def test_an_empty_image_topic_or_one_without_a_usable_frame_is_refused(tmp_path):
    """A topic holding no messages, or only frames in an encoding tagloc cannot read: the replay had
    exited 0 having localised nothing, and from-bag written (exit 0) a session listing no frames,
    which every reader then refuses."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    rig = WALK / "rig.json"
    path = tmp_path / "empty"
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        w.add_connection("/cam/image_raw", "sensor_msgs/msg/Image", typestore=store)
    with pytest.raises(SessionError, match="/cam/image_raw holds no messages"):
        BagSession(path, "/cam/image_raw", WALK / "map.csv", rig)
    with pytest.raises(SessionError, match="holds no messages"):
        bag_to_session(path, "/cam/image_raw", tmp_path / "s0", WALK / "map.csv", rig)
    assert not (tmp_path / "s0").exists()

    path = tmp_path / "yuv"
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/cam/image_raw", "sensor_msgs/msg/Image", typestore=store)
        for k in range(3):
            header = T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](100 + k, 0), "cam")
            msg = T["sensor_msgs/msg/Image"](header, 4, 4, "yuv422", 0, 8, np.zeros(32, np.uint8))
            w.write(conn, (100 + k) * 10**9, store.serialize_cdr(msg, "sensor_msgs/msg/Image"))
    with pytest.raises(SessionError, match=r"none of the 3 frames of /cam/image_raw could be converted \(frame 0: "):
        bag_to_session(path, "/cam/image_raw", tmp_path / "s1", WALK / "map.csv", rig)
    # Nothing listed, so the directory can be written again (it holds no session).
    assert (tmp_path / "s1" / "frames.csv").read_text() == "index,timestamp_s\n"


def test_a_frames_detections_and_image_share_its_poses_stamp_across_a_reset_clock(tmp_path):
    """After the source's clock goes back (a camera restarted), the output path stamps poses on from
    the last one; the frame's detections, image and CameraInfo had kept the source's time, 99 s
    before their pose, so nothing in the bag paired them (message filters, TF at the image's stamp)."""
    from tagloc.core.rig import default_rig
    from tagloc.pipeline.output import OutputConfig, Outputs

    rig = default_rig()
    dt = 1 / 30
    stamps = [100.0 + k * dt for k in range(3)] + [1.0 + k * dt for k in range(3)]
    out = Outputs(load_map(WALK / "map.csv"), rig, OutputConfig(), warn=lambda _: None)
    bag = BagWriter(tmp_path / "b", "v1", rig, images=True)
    out.add_sink(bag)
    image = np.full((rig[0].camera.height, rig[0].camera.width), 128, np.uint8)
    for index, t in enumerate(stamps):
        o = TrackerOutput(t, np.array([1.0, 2.0, 0.5]), np.eye(3) * 1e-4, TrackState.TRACKING, 0.1)
        res = FrameResult(index, t, [], o)
        out.emit(res)
        bag.write_frame(Frame(index, t, image), res)
    out.close()
    msgs = _read_all(tmp_path / "b")

    def stamped(topic: str) -> list[float]:
        return [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for _, m in msgs[topic]]

    poses = stamped("/tagloc/v1/pose")
    assert np.all(np.diff(poses) > 0) and poses[3] == pytest.approx(100.0 + 3 * dt, abs=1e-6)
    for topic in ("/tagloc/v1/front/detections", "/tagloc/v1/front/image/compressed", "/tagloc/v1/front/camera_info"):
        assert stamped(topic) == pytest.approx(poses, abs=1e-9), topic
        assert [ns / 1e9 for ns, _ in msgs[topic]] == pytest.approx(poses, abs=1e-9), topic


def test_an_encoding_tagloc_does_not_read_is_named(tmp_path):
    """A bayer camera's frames: each skipped naming its encoding and what tagloc reads ("corrupt or in
    an unsupported encoding" left the user to guess which)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    path = tmp_path / "bayer"
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/cam/image_raw", "sensor_msgs/msg/Image", typestore=store)
        for k, enc in enumerate(["bayer_rggb8", "mono8"]):
            header = T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](100 + k, 0), "cam")
            msg = T["sensor_msgs/msg/Image"](header, 4, 4, enc, 0, 4, np.zeros(16, np.uint8))
            w.write(conn, (100 + k) * 10**9, store.serialize_cdr(msg, "sensor_msgs/msg/Image"))
    src = BagSession(path, "/cam/image_raw", WALK / "map.csv", WALK / "rig.json")
    got = list(src.frames())
    assert got[0].image is None and got[1].image is not None
    assert got[0].error == (
        "frame 0: /cam/image_raw message at t=100.000000 has encoding 'bayer_rggb8', which tagloc does not read"
        " (mono8, bgr8, rgb8, bgra8, rgba8, mono16)"
    )
    assert src.skipped == [(0, got[0].error)]


def test_a_time_before_zero_is_refused_in_one_line_and_the_bag_stays_readable(tmp_path, capsys):
    """A session whose clock starts at -10 s (frames.csv allows it): replay --bag failed at its first
    frame with an internal OverflowError from the MCAP writer, leaving a bag directory no reader
    opens. Now replay refuses it before any work, and the writer refuses such a time before writing
    any of it (tagloc live), closing a bag that reads."""
    from rosbags.rosbag2 import Reader

    from tagloc.cli import main

    walk = tmp_path / "walk"
    shutil.copytree(WALK, walk)
    rows = (walk / "frames.csv").read_text().splitlines()
    shifted = [rows[0]] + [f"{i},{float(t) - 10.0:.6f}" for i, t in (r.split(",") for r in rows[1:])]
    (walk / "frames.csv").write_text("\n".join(shifted) + "\n")
    (walk / "groundtruth.tum").unlink(missing_ok=True)
    bag, tum = tmp_path / "walk.bag2", tmp_path / "walk.tum"
    assert main(["replay", str(walk), "--quiet", "--bag", str(bag), "--out", str(tum)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "frame 0: time -10.000000 s is before 0, which a ROS bag cannot hold" in err[0]
    assert not bag.exists() and not tum.exists()

    writer = BagWriter(bag, "v1", SessionReader(walk).rig)
    o = TrackerOutput(-10.0, np.zeros(3), np.eye(3) * 1e-4, TrackState.TRACKING, 0.1)
    with pytest.raises(InputError, match=r"walk.bag2: time -10.000000 s is before 0"):
        writer.publish(PoseMessage("v1", 0, o))
    writer.close()
    with Reader(bag) as r:
        assert r.message_count == 0


def test_a_time_past_ros_2s_int32_seconds_is_refused_in_one_line(tmp_path, capsys):
    """A clock jumped far ahead (the tracker copes with 1e300 s): a bag stamp's seconds are an int32,
    and writing one stopped the run with an internal struct.error (1e10 s) or OverflowError (1e300 s)."""
    from rosbags.rosbag2 import Reader

    from tagloc.cli import main

    walk = tmp_path / "walk"
    shutil.copytree(WALK, walk)
    rows = (walk / "frames.csv").read_text().splitlines()
    rows[-1] = f"{rows[-1].split(',')[0]},10000000000.000000"  # the last frame 317 years on
    (walk / "frames.csv").write_text("\n".join(rows) + "\n")
    (walk / "groundtruth.tum").unlink(missing_ok=True)
    bag = tmp_path / "walk.bag2"
    assert main(["replay", str(walk), "--quiet", "--bag", str(bag)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "frame 59: time 1e+10 s is past ROS 2's last time (2147483648 s" in err[0]
    assert not bag.exists()

    writer = BagWriter(bag, "v1", SessionReader(walk).rig)
    for t in (1.0, 1e10, 1e300, math.inf):
        o = TrackerOutput(t, np.zeros(3), np.eye(3) * 1e-4, TrackState.TRACKING, 0.1)
        if t == 1.0:
            writer.publish(PoseMessage("v1", 0, o))
            continue
        with pytest.raises(InputError, match="is past ROS 2's last time"):
            writer.publish(PoseMessage("v1", 1, o))
    writer.close()
    with Reader(bag) as r:
        assert r.message_count == 4  # the first frame's: /tf_static, pose_json, pose, /tf
