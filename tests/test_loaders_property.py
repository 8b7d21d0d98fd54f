"""Property tests of every loader (map, calibration, rig, session.json, frames.csv, ground truth,
reference cache): any byte string, or a valid file mutated at random, gives either a valid object or
a TaglocError whose message is one line naming the file, never another exception."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tagloc.core.camera import Camera, default_camera, load_calibration, save_calibration
from tagloc.core.errors import TaglocError
from tagloc.core.rig import default_rig, load_rig, save_rig
from tagloc.core.stickermap import StickerMap, load_map
from tagloc.io.session import SessionInfo, SessionReader, SessionWriter, read_tum, write_tum

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# An edit: (kind, position as a fraction of the file, length, bytes).
EDIT = st.tuples(
    st.sampled_from(["replace", "insert", "delete", "truncate", "duplicate"]),
    st.floats(0.0, 1.0),
    st.integers(1, 40),
    st.binary(min_size=1, max_size=12),
)


def mutate(data: bytes, edits: list[tuple[str, float, int, bytes]]) -> bytes:
    """Apply byte edits to a valid file: what a bad disk, a cut copy or a careless hand makes of it."""
    b = bytearray(data)
    for kind, where, n, blob in edits:
        i = int(where * len(b))
        if kind == "replace":
            b[i : i + len(blob)] = blob
        elif kind == "insert":
            b[i:i] = blob
        elif kind == "delete":
            del b[i : i + n]
        elif kind == "truncate":
            del b[i:]
        else:
            b[i:i] = b[i : i + n]
    return bytes(b)


def check_loader(load: Callable[[Path], object], path: Path, data: bytes) -> None:
    path.write_bytes(data)
    try:
        load(path)
    except TaglocError as exc:
        msg = str(exc)
        assert msg and "\n" not in msg, msg
        assert path.name in msg or str(path.parent) in msg, msg


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """A valid little session (map, rig, OpenCV calibration, three frames, ground truth)."""
    d = tmp_path_factory.mktemp("prop") / "s"
    smap = StickerMap(np.array([3, 4, 5]), np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.5]]), np.radians([0, 90, 35]))
    with SessionWriter(d, smap, default_rig(), SessionInfo(source="test", fps=10.0), image_ext=".png") as w:
        for k in range(3):
            w.write(k, k * 0.1, np.full((8, 8), 10 * k, np.uint8))
    write_tum(d / "groundtruth.tum", np.arange(3) * 0.1, [np.eye(4)] * 3)
    ros = d / "ros.yaml"
    ros.write_text(
        "image_width: 1296\nimage_height: 972\ncamera_matrix: {rows: 3, cols: 3, data: "
        "[1285.7, 0, 647.5, 0, 1285.7, 485.5, 0, 0, 1]}\ndistortion_coefficients: {rows: 1, cols: 5, "
        "data: [0.1, -0.2, 0, 0, 0]}\n"
    )
    return d


@pytest.fixture(scope="module")
def refs_file(tmp_path_factory) -> Path:
    from tagloc.vision.refs import build_refs, save_refs

    p = tmp_path_factory.mktemp("refs") / "m.refs.npz"
    save_refs(build_refs([7, 8], progress=False), p)
    return p


def _scratch() -> Path:
    return Path(tempfile.mkdtemp(prefix="tagloc-prop-"))


@SETTINGS
@given(data=st.binary(max_size=400), edits=st.lists(EDIT, max_size=4), use_random=st.booleans())
def test_map_loader(base, data, edits, use_random):
    d = _scratch()
    try:
        check_loader(load_map, d / "map.csv", data if use_random else mutate((base / "map.csv").read_bytes(), edits))
    finally:
        shutil.rmtree(d)


@SETTINGS
@given(
    data=st.binary(max_size=400),
    edits=st.lists(EDIT, min_size=1, max_size=4),
    which=st.sampled_from(["random", "camera.yaml", "ros.yaml"]),
)
def test_calibration_loader(base, data, edits, which):
    d = _scratch()
    try:
        content = data if which == "random" else mutate((base / which).read_bytes(), edits)
        path = d / "camera.yaml"
        path.write_bytes(content)
        try:
            cam = load_calibration(path)
        except TaglocError as exc:
            assert "\n" not in str(exc) and "camera.yaml" in str(exc)
        else:
            # Whatever loads is usable: finite, positive focal lengths, principal point inside.
            assert isinstance(cam, Camera) and np.isfinite(cam.K).all() and cam.fx > 0 and cam.fy > 0
            assert 0 < cam.width and -0.5 <= cam.K[0, 2] <= cam.width - 0.5
    finally:
        shutil.rmtree(d)


@SETTINGS
@given(data=st.binary(max_size=400), edits=st.lists(EDIT, min_size=1, max_size=4), use_random=st.booleans())
def test_rig_loader(base, data, edits, use_random):
    d = _scratch()
    try:
        shutil.copy(base / "camera.yaml", d / "camera.yaml")
        check_loader(load_rig, d / "rig.json", data if use_random else mutate((base / "rig.json").read_bytes(), edits))
    finally:
        shutil.rmtree(d)


@SETTINGS
@given(
    data=st.binary(max_size=400),
    edits=st.lists(EDIT, min_size=1, max_size=4),
    name=st.sampled_from(["session.json", "frames.csv", "map.csv", "rig.json", "camera.yaml"]),
    use_random=st.booleans(),
)
def test_session_reader(base, data, edits, name, use_random):
    d = _scratch() / "s"
    try:
        shutil.copytree(base, d)
        content = data if use_random else mutate((base / name).read_bytes(), edits)
        (d / name).write_bytes(content)
        try:
            r = SessionReader(d)
            frames = list(r.frames())
        except TaglocError as exc:
            assert "\n" not in str(exc)
        else:
            stamps = [f.timestamp for f in frames]
            assert stamps == sorted(set(stamps)) and all(np.isfinite(stamps))  # the reader's promise
            assert len({f.index for f in frames}) == len(frames)
    finally:
        shutil.rmtree(d.parent)


@SETTINGS
@given(data=st.binary(max_size=400), edits=st.lists(EDIT, min_size=1, max_size=4), use_random=st.booleans())
def test_groundtruth_loader(base, data, edits, use_random):
    d = _scratch()
    try:
        raw = data if use_random else mutate((base / "groundtruth.tum").read_bytes(), edits)
        check_loader(read_tum, d / "groundtruth.tum", raw)
    finally:
        shutil.rmtree(d)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.binary(max_size=400), edits=st.lists(EDIT, min_size=1, max_size=3), use_random=st.booleans())
def test_reference_cache_loader(refs_file, data, edits, use_random):
    from tagloc.vision.refs import load_refs

    d = _scratch()
    try:
        check_loader(load_refs, d / "m.refs.npz", data if use_random else mutate(refs_file.read_bytes(), edits))
    finally:
        shutil.rmtree(d)


def test_the_base_files_load(base, refs_file):
    """The unmutated files are valid, so the properties above test mutations of real files."""
    from tagloc.vision.refs import load_refs

    assert len(load_map(base / "map.csv")) == 3 and load_rig(base / "rig.json").cameras
    assert load_calibration(base / "camera.yaml").size == load_calibration(base / "ros.yaml").size == (1296, 972)
    assert len(list(SessionReader(base).frames())) == 3 and len(read_tum(base / "groundtruth.tum")[0]) == 3
    assert load_refs(refs_file).ids.tolist() == [7, 8]
    save_calibration(default_camera(), base / "again.yaml")
    save_rig(default_rig(), base / "again.json", write_calibrations=False)
