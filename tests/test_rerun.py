"""Rerun logging: write a recording from hand-made results, read the .rrd back with rerun-sdk."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from mosquitto import free_port

import tagloc.io.rerun_view as rv
from tagloc.core.geometry import planar_T
from tagloc.core.rig import default_rig
from tagloc.core.stickermap import StickerMap
from tagloc.core.types import (
    Detection,
    Fix,
    Frame,
    FrameResult,
    Identity,
    IdSource,
    Observation,
    TrackerOutput,
    TrackState,
)
from tagloc.io.rerun_view import RerunView, read_rrd

N = 12
FIRST_POSE = 2  # frames 0-1 initialising
OFFSET = 0.05  # estimate is this far (m, along y) from ground truth


def column(path, entity: str, component: str) -> list:
    """Values of one component of one entity, in frame order."""
    from rerun.chunk import RrdReader

    rows = []
    for chunk in RrdReader(str(path)).stream():
        if chunk.entity_path.lstrip("/") != entity:
            continue
        b = chunk.to_record_batch()
        if component not in b.schema.names:
            continue
        frames = b.column("frame").to_pylist() if "frame" in b.schema.names else [None] * b.num_rows
        rows += zip(frames, b.column(component).to_pylist())
    return [v for _, v in sorted(rows, key=lambda r: -1 if r[0] is None else r[0])]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    rv.PATH_PIECE = 4  # several trajectory pieces from a few frames
    path = tmp_path_factory.mktemp("rr") / "run.rrd"
    smap = StickerMap(np.array([7, 8, 9]), np.array([[0.0, 0.0], [1.5, 0.0], [3.0, 0.2]]), np.zeros(3))
    rig = default_rig()
    gt_t = np.arange(N) / 10
    gt = (gt_t, np.stack([planar_T(0.1 * k, 0.0, 0.0) for k in range(N)]))
    view = RerunView(smap, rig, save=path, groundtruth=gt, image_scale=0.5)
    rng = np.random.default_rng(3)
    for k in range(N):
        img = rng.integers(0, 255, (972, 1296), dtype=np.uint8)
        outer = np.array([[100.0, 100.0], [300.0, 110.0], [290.0, 300.0], [95.0, 290.0]])
        obs = [
            Observation(Detection(outer), 0, Identity(7, 0, IdSource.DECODED), Fix([], accepted=True)),
            Observation(Detection(outer + 400), 0, Identity(8, 2, IdSource.ORB, 0.8), Fix([], False, False, "gate")),
            Observation(Detection(outer + [600, 0]), 0),
        ]
        state = TrackState.INITIALISING if k < FIRST_POSE else TrackState.TRACKING
        out = TrackerOutput(
            k / 10, np.array([0.1 * k, OFFSET, 0.0]), np.diag([4e-4, 1e-4, 1e-3]), state, 0.1, 7, IdSource.DECODED
        )
        view.log(Frame(k, k / 10, img), FrameResult(k, k / 10, obs, out, {"detect": 4.0, "total": 6.0}))
    view.close()
    rv.PATH_PIECE = 256
    return path


def test_entities_and_frame_counts(recording):
    ents = read_rrd(recording)
    for static in ("world/map/stickers", "world/body/front", "world/groundtruth/path"):
        assert ents[static].static, static
    image = ents["world/body/front/image"]
    assert image.static  # the pinhole
    assert image.frames == list(range(N))
    assert "EncodedImage:blob" in image.components and "Pinhole:image_from_camera" in image.components
    assert ents["world/body/front/image/detections"].frames == list(range(N))
    posed = list(range(FIRST_POSE, N))
    for name in (
        "world/body",
        "world/estimate/ellipse",
        "plots/error/position_m",
        "plots/error/yaw_deg",
        "plots/uncertainty/position_2sigma_m",
        "plots/uncertainty/yaw_sigma_deg",
    ):
        assert ents[name].frames == posed, name
    for name in ("plots/timing/detect_ms", "plots/timing/total_ms", "status", "world/groundtruth/body"):
        assert ents[name].frames == list(range(N)), name
    pieces = sorted(k for k in ents if k.startswith("world/estimate/path/"))
    assert pieces == ["world/estimate/path/0000", "world/estimate/path/0001", "world/estimate/path/0002"]


def test_blueprint_is_in_the_file(recording):
    from rerun.chunk import RrdReader

    assert len(RrdReader(str(recording)).blueprints()) == 1


def test_map_labels_and_values(recording):
    labels = column(recording, "world/map/stickers", "LineStrips3D:labels")[0]
    assert labels == ["7", "8", "9"]
    strips = column(recording, "world/map/stickers", "LineStrips3D:strips")[0]
    first = np.array(strips[0])
    assert first.shape == (5, 3) and np.allclose(first[0], first[-1])  # closed square
    assert np.allclose(np.ptp(first[:, :2], axis=0), [0.1, 0.1]) and np.allclose(first[:, 2], 0)
    err = np.concatenate(column(recording, "plots/error/position_m", "Scalars:scalars"))
    assert np.allclose(err, OFFSET, atol=1e-9)
    two_sigma = np.concatenate(column(recording, "plots/uncertainty/position_2sigma_m", "Scalars:scalars"))
    assert np.allclose(two_sigma, 2 * 0.02)  # major axis: sqrt(4e-4) = 0.02 m


def test_image_is_downscaled_jpeg_and_outlines_scaled(recording):
    blob = column(recording, "world/body/front/image", "EncodedImage:blob")[0][0]  # one blob: a list of bytes
    img = cv2.imdecode(np.array(blob, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img.shape[:2] == (486, 648)
    K = np.array(column(recording, "world/body/front/image", "Pinhole:image_from_camera")[0]).reshape(3, 3)
    assert K[0, 0] == pytest.approx(default_rig()[0].camera.fx / 2, rel=1e-6)
    strips = column(recording, "world/body/front/image/detections", "LineStrips2D:strips")[0]
    assert np.allclose(np.array(strips[0])[0], [100 * 0.5 + 0.25 - 0.5] * 2)
    labels = column(recording, "world/body/front/image/detections", "LineStrips2D:labels")[0]
    assert labels == ["7 decoded", "8 orb (refused: gate)", "? none"]
    colours = column(recording, "world/body/front/image/detections", "LineStrips2D:colors")[0]
    assert len(set(colours)) == 3  # one colour per identification source


def test_trajectory_pieces_join(recording):
    p0 = np.array(column(recording, "world/estimate/path/0000", "LineStrips3D:strips")[-1][0])
    p1 = np.array(column(recording, "world/estimate/path/0001", "LineStrips3D:strips")[-1][0])
    assert len(p0) == 4 and len(p1) == 5
    assert np.allclose(p1[0], p0[-1])
    assert np.allclose(p0[:, 0], [0.2, 0.3, 0.4, 0.5])


def test_missing_viewer_is_a_clear_error(monkeypatch, tmp_path):
    from tagloc.core.errors import BackendUnavailable

    monkeypatch.setenv("PATH", str(tmp_path))  # no `rerun` executable to spawn
    monkeypatch.setenv("DISPLAY", ":0")
    monkeypatch.setattr(rv, "VIEWER_PORT", free_port())
    with pytest.raises(BackendUnavailable, match="Rerun viewer"):
        RerunView(StickerMap(np.array([1]), np.zeros((1, 2)), np.zeros(1)), default_rig(), spawn=True)


def test_a_frame_time_rerun_cannot_hold_or_going_back_stays_off_the_time_timeline(tmp_path):
    """Live refuses a non-finite or backward stamp and accepts a huge jump (skipped, counted, or the
    track lost): the view must neither stop the run on them nor draw the walk back in time."""
    from rerun.chunk import RrdReader

    smap = StickerMap(np.array([7]), np.zeros((1, 2)), np.zeros(1))
    for clock, base in (("duration", 0.0), ("timestamp", 1.7e9)):
        path = tmp_path / f"{clock}.rrd"
        view = RerunView(smap, default_rig(), save=path, clock=clock)
        out = TrackerOutput(base + 1.0, np.array([1.0, 2.0, 0.3]), np.eye(3) * 1e-3, TrackState.TRACKING, 0.1, 7)
        # (None: a library caller's frame without a time, refused by the localiser as a NaN is.)
        stamps = [base + 1.0, base + 1.1, float("nan"), base + 0.5, float("inf"), 1e300, None, base + 1.2]
        for k, t in enumerate(stamps):
            view.log(
                Frame(k, t, None), FrameResult(k, t, [], out, {"total": 1.0}, "refused" if k in (2, 3, 4, 6) else None)
            )
        view.close()
        assert read_rrd(path)["status"].frames == list(range(len(stamps)))
        timed = []
        for chunk in RrdReader(str(path)).stream():
            b = chunk.to_record_batch()
            if chunk.entity_path == "/status" and "time" in b.schema.names:
                timed += [
                    f for f, t in zip(b.column("frame").to_pylist(), b.column("time").to_pylist()) if t is not None
                ]
        assert sorted(timed) == [0, 1, 7], clock


def times_on_clock(path, entity: str) -> dict[int, float]:
    """frame -> seconds on the ``time`` timeline (a duration) of one entity's rows that have one."""
    from rerun.chunk import RrdReader

    out = {}
    for chunk in RrdReader(str(path)).stream():
        b = chunk.to_record_batch()
        if chunk.entity_path.lstrip("/") == entity and "time" in b.schema.names:
            for f, t in zip(b.column("frame").to_pylist(), b.column("time").cast("int64").to_pylist()):
                if t is not None:
                    out[f] = t / 1e9
    return out


def test_after_the_source_clock_is_reset_the_recording_carries_on_in_time(tmp_path):
    """Live restarts the track on a reset clock and publishes its stamps carried on from the last:
    the recording follows them rather than drawing the new track over the old one's times."""
    from tagloc.pipeline.output import OutputConfig, Outputs

    smap = StickerMap(np.array([7]), np.zeros((1, 2)), np.zeros(1))
    outputs = Outputs(smap, default_rig(), OutputConfig(rerun_save=tmp_path / "r.rrd"), warn=lambda m: None)

    def res(i: int, t: float, skipped: str | None = None) -> FrameResult:
        o = TrackerOutput(t, np.array([i, 0.0, 0.0]), np.eye(3) * 1e-4, TrackState.TRACKING, 0.1, 7)
        return FrameResult(i, t, [], o, {"total": 1.0}, skipped)

    # Frames 0-2 on the old clock, 3 refused (its stamp goes back), 4-5 on the new clock after the reset.
    for r in (res(0, 10.0), res(1, 10.1), res(2, 10.2), res(3, 0.0, "not after"), res(4, 0.05), res(5, 0.15)):
        outputs.emit(r)
    outputs.close()
    times = times_on_clock(tmp_path / "r.rrd", "world/body")
    assert sorted(times) == [0, 1, 2, 4, 5]  # the refused frame is on the frame timeline alone
    assert times[4] > times[2] and times[5] - times[4] == pytest.approx(0.1)


def test_a_viewer_url_where_nothing_listens_or_malformed_is_one_clear_error(tmp_path):
    """Rerun itself buffers the whole run for an unreachable viewer and only warns at the end."""
    import socket

    from tagloc.core.errors import BackendUnavailable, InputError

    s = socket.socket()
    s.bind(("127.0.0.1", 0))  # a port nothing listens on (bound, never listening)
    port = s.getsockname()[1]
    smap = StickerMap(np.array([1]), np.zeros((1, 2)), np.zeros(1))
    try:
        with pytest.raises(BackendUnavailable, match=f"no Rerun viewer at rerun\\+http://127.0.0.1:{port}/proxy"):
            RerunView(smap, default_rig(), connect=f"rerun+http://127.0.0.1:{port}/proxy")
    finally:
        s.close()
    for bad in ("foo", "http://127.0.0.1:9876", "rerun+http://127.0.0.1:99999/proxy", "rerun+http:///proxy"):
        with pytest.raises(InputError, match="Rerun viewer URL"):
            RerunView(smap, default_rig(), connect=bad)
    assert rv.viewer_address("rerun+http://10.0.0.2/proxy") == ("10.0.0.2", 9876)
    # Without a port Rerun connects to 9876 whatever the scheme (a review: rerun:// and rerun+https://
    # were probed at 443, so a viewer listening at 9876 was refused).
    assert rv.viewer_address("rerun://viewer.example/proxy") == ("viewer.example", 9876)
    assert rv.viewer_address("rerun+https://viewer.example/proxy") == ("viewer.example", 9876)
    assert rv.viewer_address("rerun+https://viewer.example:443/proxy") == ("viewer.example", 443)


def test_a_viewer_that_cannot_open_a_window_is_one_clear_error(monkeypatch, tmp_path):
    """Without a display the spawned viewer exits at once; Rerun only says so at the end."""
    from tagloc.core.errors import BackendUnavailable

    fake = tmp_path / "rerun"  # a viewer that exits at once, as Rerun's does without a display
    fake.write_text("#!/bin/sh\nexit 1\n")
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.setattr(rv, "VIEWER_PORT", free_port())
    smap = StickerMap(np.array([1]), np.zeros((1, 2)), np.zeros(1))
    for var in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"):
        monkeypatch.delenv(var, raising=False)
    with pytest.raises(BackendUnavailable, match="no display"):
        RerunView(smap, default_rig(), spawn=True)
    monkeypatch.setenv("DISPLAY", ":0")  # a display is named, yet the viewer does not start
    with pytest.raises(BackendUnavailable, match="the Rerun viewer did not start"):
        RerunView(smap, default_rig(), spawn=True)


@pytest.mark.parametrize("start, kind", [(0.0, "duration"), (1.7e9, "timestamp")])
def test_a_replay_keeps_an_epoch_clock_as_timestamps(tmp_path, start, kind):
    """A replayed live recording or ROS bag has epoch stamps: shown as a duration they read
    "19675 days"; a session's own clock stays a duration."""
    import pyarrow as pa
    from rerun.chunk import RrdReader

    from tagloc.pipeline.output import OutputConfig, Outputs

    smap = StickerMap(np.array([7]), np.zeros((1, 2)), np.zeros(1))
    outputs = Outputs(smap, default_rig(), OutputConfig(rerun_save=tmp_path / "r.rrd"), warn=lambda m: None)
    for i in range(3):
        o = TrackerOutput(start + i / 30, np.array([i, 0.0, 0.0]), np.eye(3) * 1e-4, TrackState.TRACKING, 0.1, 7)
        outputs.emit(FrameResult(i, start + i / 30, [], o, {"total": 1.0}))
    outputs.close()
    types = {
        c.to_record_batch().schema.field("time").type
        for c in RrdReader(str(tmp_path / "r.rrd")).stream()
        if "time" in c.timeline_names
    }
    assert types == {pa.timestamp("ns") if kind == "timestamp" else pa.duration("ns")}


def test_a_sticker_named_after_its_frame_is_relabelled_on_that_frame(tmp_path):
    """Live's deferred decode names a sticker after its frame was logged: the frame's outline must
    not stay drawn as unidentified while its fix is in the filter."""
    smap = StickerMap(np.array([7]), np.zeros((1, 2)), np.zeros(1))
    path = tmp_path / "late.rrd"
    view = RerunView(smap, default_rig(), save=path)
    outer = np.array([[100.0, 100.0], [300.0, 110.0], [290.0, 300.0], [95.0, 290.0]])
    det, other = Detection(outer), Detection(outer + 400)
    out = TrackerOutput(0.1, np.zeros(3), np.eye(3) * 1e-3, TrackState.TRACKING, 0.1, 7)
    img = np.zeros((972, 1296), np.uint8)
    view.log(Frame(3, 0.1, img), FrameResult(3, 0.1, [Observation(det, 0), Observation(other, 0)], out))
    view.log_late(3, [Observation(det, 0, Identity(7, 0, IdSource.DECODED), Fix([], accepted=True))])
    view.close()
    assert column(path, "world/body/front/image/detections", "LineStrips2D:labels")[-1] == ["7 decoded", "? none"]
    assert times_on_clock(path, "world/body/front/image/detections") == {3: pytest.approx(0.1)}  # the same place


def test_a_long_run_keeps_only_the_current_trajectory_piece(tmp_path, monkeypatch):
    # Every pose of the run had been kept to draw the pieces from (~110 bytes a frame: 95 MB over an
    # 8-hour shift at 30 fps); a piece needs only its own points and the last of the one before.
    monkeypatch.setattr(rv, "PATH_PIECE", 4)
    smap = StickerMap(np.array([7]), np.array([[0.0, 0.0]]), np.zeros(1))
    view = RerunView(smap, default_rig(), save=tmp_path / "r.rrd")
    for k in range(41):
        out = TrackerOutput(
            k / 10, np.array([0.1 * k, 0.0, 0.0]), np.diag([4e-4, 1e-4, 1e-3]), TrackState.TRACKING, 0.1
        )
        view.log(Frame(k, k / 10, None), FrameResult(k, k / 10, [], out, {}))
        assert len(view._path) <= rv.PATH_PIECE + 1
    view.close()
    pieces = [
        np.array(column(tmp_path / "r.rrd", f"world/estimate/path/{p:04d}", "LineStrips3D:strips")[-1][0])
        for p in range(11)
    ]
    assert [len(p) for p in pieces] == [4] + [5] * 9 + [2]
    for a, b in zip(pieces, pieces[1:]):
        assert np.allclose(b[0], a[-1])  # joined
    assert np.allclose(np.concatenate([pieces[0]] + [p[1:] for p in pieces[1:]])[:, 0], 0.1 * np.arange(41))
