"""ROS bags in and out, without a ROS install (``rosbags``: pure Python rosbag2 MCAP/SQLite and ROS 1).

Writing (:class:`BagWriter`, a sink like those of :mod:`tagloc.io.sinks`) makes a rosbag2 directory in
MCAP storage. Topic names use the vest ID made into a valid ROS name (:func:`ros_name`: ``vest-1`` ->
``vest_1``); ``CAM`` is the rig camera's name::

    /tagloc/VEST/pose             geometry_msgs/msg/PoseWithCovarianceStamped   frame "map", once posed
    /tagloc/VEST/pose_json        std_msgs/msg/String   the tagloc pose message (JSON), every frame
    /tf                           tf2_msgs/msg/TFMessage   map -> VEST/body, once posed
    /tf_static                    tf2_msgs/msg/TFMessage   VEST/body -> VEST/CAM (once, transient local)
    /tagloc/VEST/CAM/detections   tagloc_msgs/msg/StickerDetections   every frame (see DETECTIONS_MSGDEF)
    /tagloc/VEST/CAM/image/compressed   sensor_msgs/msg/CompressedImage (JPEG), only with images=True
    /tagloc/VEST/CAM/camera_info  sensor_msgs/msg/CameraInfo, only with images=True

The pose's 6x6 covariance (x, y, z, roll, pitch, yaw; row-major, as ROS orders it) holds the
tracker's 3x3 over (x, y, yaw); z, roll and pitch are not estimated and get ``UNESTIMATED_VARIANCE``
(the ROS convention for "not measured": a variance so large that any fusion ignores it).
Header stamps and bag times are the frame timestamps (the session clock in replay, the epoch in live).

Reading (:class:`BagSession`): a rosbag2 (MCAP or SQLite) or ROS 1 bag with a camera topic
(``sensor_msgs/Image`` or ``CompressedImage``) is a session: same interface as
:class:`tagloc.io.session.SessionReader`, frames streamed one at a time, corrupt ones skipped and
counted. :func:`bag_to_session` converts it to the session layout, :func:`read_pose_messages`
reads back the pose messages for the fleet monitor.
"""

from __future__ import annotations

import json
import math
import os
import re
import statistics
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from tagloc.core.camera import Camera, check_calibration, distortion_model_problem, load_calibration
from tagloc.core.errors import BackendUnavailable, InputError, SessionError, warn_stderr
from tagloc.core.geometry import planar_T
from tagloc.core.rig import Rig, default_rig, load_rig, local_calibration_names
from tagloc.core.stickermap import StickerMap, load_map
from tagloc.core.types import Frame, FrameResult, Observation, TrackState, seconds_text
from tagloc.io.session import (
    FRAMES_CSV,
    MAP_FILE,
    RIG_FILE,
    SESSION_JSON,
    SessionInfo,
    SessionWriter,
    after_last,
    decode_grey,
)
from tagloc.io.sinks import SCHEMA, PoseMessage, Sink

# ROS asks for a huge variance on axes that are not measured (z, roll, pitch of a planar pose), so that
# a downstream filter (robot_localization, nav2's AMCL consumers) gives them no weight. m^2 and rad^2.
UNESTIMATED_VARIANCE = 1e6
WORLD_FRAME = "map"  # REP 105's name for the fixed world frame the sticker map lives in
MAX_BAG_TIME_S = 2**31  # builtin_interfaces/Time's seconds are an int32: a stamp must be below this
IMAGE_JPEG_QUALITY = 90  # when a frame has to be encoded for the bag (no original JPEG at hand)
# Reading a bag, an image whose header stamp is more than WILD_STAMP_STEPS frame intervals (the
# median) past one of the next WILD_STAMP_WINDOW frames' (that frame after the frames before it) has
# a wild stamp: that frame is skipped, not every frame after it. As the localiser's
# clock_reset_frames: a run of frames that long on another clock is a clock that jumped, not a
# stray stamp. Within 2 intervals the later frame is the one refused (a stamp's jitter: either one).
WILD_STAMP_WINDOW = 5
WILD_STAMP_STEPS = 2.0
SKIPPED_NAMED = 5  # skipped frames a bag conversion names (the rest are counted)
SIZE_PROBE_FRAMES = 30  # frames a bag conversion reads for a readable image to check its size, up front
# rosbag2 metadata version 8 (Iron's), the oldest rosbags writes: Humble's rosbag2 reads each topic's
# offered_qos_profiles as a YAML string with integer policies, which version 8 writes and Iron and
# Jazzy read too; version 9 (Jazzy's) makes it a list of named policies, and Humble's `ros2 bag info`
# and `ros2 bag play` then stop at "yaml-cpp: bad conversion".
BAG_VERSION = 8

DETECTION_MSGDEF = """\
int32 sticker_id
string source
float64[8] corners_px
bool accepted
string gate_reason
"""
DETECTIONS_MSGDEF = """\
std_msgs/Header header
tagloc_msgs/StickerDetection[] detections
"""
DETECTION_TYPE = "tagloc_msgs/msg/StickerDetection"
DETECTIONS_TYPE = "tagloc_msgs/msg/StickerDetections"
POSE_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
STRING_TYPE = "std_msgs/msg/String"
TF_TYPE = "tf2_msgs/msg/TFMessage"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPE = "sensor_msgs/msg/Image"
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
IMAGE_TYPES = (COMPRESSED_TYPE, IMAGE_TYPE, "sensor_msgs/Image", "sensor_msgs/CompressedImage")


def _typestore():
    """The ROS 2 Humble typestore with tagloc's detection messages registered."""
    try:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    except ImportError as exc:  # pragma: no cover - rosbags is a dependency
        raise BackendUnavailable("rosbags is not installed; pip install rosbags") from exc
    store = get_typestore(Stores.ROS2_HUMBLE)
    types = get_types_from_msg(DETECTION_MSGDEF, DETECTION_TYPE)
    types.update(get_types_from_msg(DETECTIONS_MSGDEF, DETECTIONS_TYPE))
    store.register(types)
    return store


def ros_name(name: str) -> str:
    """``name`` as one valid ROS graph-name token: [A-Za-z0-9_], not starting with a digit."""
    token = re.sub(r"[^A-Za-z0-9_]", "_", name) or "_"
    return f"v{token}" if token[0].isdigit() else token


def covariance_6x6(cov3: np.ndarray) -> np.ndarray:
    """ROS 6x6 pose covariance (x, y, z, roll, pitch, yaw) from the (3, 3) one over (x, y, yaw)."""
    cov = np.zeros((6, 6))
    idx = [0, 1, 5]
    cov[np.ix_(idx, idx)] = cov3
    for k in (2, 3, 4):
        cov[k, k] = UNESTIMATED_VARIANCE
    return cov


def covariance_3x3(cov6: np.ndarray) -> np.ndarray:
    """The (3, 3) covariance over (x, y, yaw) inside a ROS 6x6 one."""
    idx = [0, 1, 5]
    return np.asarray(cov6, float).reshape(6, 6)[np.ix_(idx, idx)]


def _ns(t: float) -> int:
    return int(round(t * 1e9))


def check_bag_time(t: float, where: str) -> None:
    """Refuse a time a bag cannot hold: before 0 (rosbag2 stores unsigned nanoseconds; rosbags failed
    deep inside the MCAP writer and left a bag directory no reader opens), or from ROS 2's int32
    seconds on (2038-01-19 as an epoch time; a clock jumped to 1e10 s or 1e300 s stopped the run with
    an internal struct or overflow error)."""
    if not t >= 0:
        raise InputError(
            f"{where}: time {seconds_text(t)} s is before 0, which a ROS bag cannot hold; shift the session's clock "
            "(frames.csv) or leave out the bag"
        )
    if not t < MAX_BAG_TIME_S:
        raise InputError(
            f"{where}: time {t:.6g} s is past ROS 2's last time ({MAX_BAG_TIME_S} s, builtin_interfaces/Time's "
            "int32 seconds), which a ROS bag cannot hold; fix the clock or leave out the bag"
        )


def _stamp_s(stamp: object) -> float:
    """Seconds of a ROS time (ROS 2 ``sec``/``nanosec``; ROS 1 ``secs``/``nsecs`` after rosbags' mapping)."""
    sec = getattr(stamp, "sec", getattr(stamp, "secs", 0))
    nsec = getattr(stamp, "nanosec", getattr(stamp, "nsecs", 0))
    # One correctly rounded division: a stamp made by _ns from a time with at most 9 decimals gives it back exactly.
    return (int(sec) * 1_000_000_000 + int(nsec)) / 1e9


class BagWriter(Sink):
    """Write poses (and, per frame, detections and optionally images) to a rosbag2 in MCAP storage.

    Use like a pose sink (:meth:`publish`); :meth:`write_frame` adds a frame's detections and, with
    ``images``, its image and calibration. The bag is complete once :meth:`close` has run (rosbag2
    writes its ``metadata.yaml`` then).

    Args:
        path: bag directory to create (must not exist).
        vest: vest ID (topics are ``/tagloc/<ros_name(vest)>/...``).
        rig: the rig (camera frames for /tf_static, calibration for CameraInfo).
        images: also write camera images (CompressedImage) and CameraInfo; off by default for size.
        storage: "mcap" (default) or "sqlite3".
    """

    def __init__(self, path: str | Path, vest: str, rig: Rig, images: bool = False, storage: str = "mcap"):
        super().__init__()
        from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.path = Path(path)
        self.name = f"bag {self.path}"
        if self.path.exists():
            raise InputError(f"{self.path}: already exists; rosbag2 writes a new directory")
        if storage not in ("mcap", "sqlite3"):
            raise InputError(f"bag storage must be mcap or sqlite3, not {storage!r}")
        from tagloc.io.sinks import check_vest_id

        self.vest = ros_name(check_vest_id(vest))
        # Each camera's topics and TF frame are named after it: two cameras of one name (as ROS names)
        # would share them, which rosbag2 refuses mid-setup, leaving a bag directory behind.
        cams = [ros_name(c.name) for c in rig.cameras]
        if len(set(cams)) < len(cams):
            raise InputError(
                f"{self.path}: the rig's cameras need distinct names for a bag's topics, not "
                + ", ".join(repr(c.name) for c in rig.cameras)
                + f" (as ROS names: {', '.join(cams)}); rename them in rig.json"
            )
        self.rig = rig
        self.images = bool(images)
        self._store = _typestore()
        self._types = self._store.types
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._writer = Writer(self.path, version=BAG_VERSION, storage_plugin=plugin)
        self._writer.open()
        base = f"/tagloc/{self.vest}"
        add = self._writer.add_connection
        self._pose = add(f"{base}/pose", POSE_TYPE, typestore=self._store)
        self._json = add(f"{base}/pose_json", STRING_TYPE, typestore=self._store)
        self._tf = add("/tf", TF_TYPE, typestore=self._store)
        # /tf_static is latched in ROS 2 (transient local): players re-send it to late subscribers.
        latched = Qos(
            QosHistory.KEEP_LAST,
            1,
            QosReliability.RELIABLE,
            QosDurability.TRANSIENT_LOCAL,
            QosTime(0, 0),
            QosTime(0, 0),
            QosLiveliness.AUTOMATIC,
            QosTime(0, 0),
            False,
        )
        self._tf_static = add("/tf_static", TF_TYPE, typestore=self._store, offered_qos_profiles=[latched])
        self._det, self._img, self._info = {}, {}, {}
        for k, rc in enumerate(rig.cameras):
            cam = f"{base}/{ros_name(rc.name)}"
            self._det[k] = add(f"{cam}/detections", DETECTIONS_TYPE, typestore=self._store)
            if self.images:
                self._img[k] = add(f"{cam}/image/compressed", COMPRESSED_TYPE, typestore=self._store)
                self._info[k] = add(f"{cam}/camera_info", INFO_TYPE, typestore=self._store)
        self._static_written = False
        # A frame's messages go at the time its pose was published: after the source's clock is reset
        # the output path stamps poses on from the last one (tagloc.pipeline.output), and the frame's
        # detections and image must share its pose's stamp for a consumer to pair them (message
        # filters, a TF lookup at the image's stamp). The offset is the last published pose's.
        self._published: tuple[int, float] | None = None  # (frame index, stamp) of the last pose message
        self._offset = 0.0
        self.frames = 0

    # --- message builders -------------------------------------------------------------------
    def _header(self, t: float, frame_id: str):
        T = self._types
        ns = _ns(t)
        return T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000),
            frame_id=frame_id,
        )

    def _transform(self, t: float, parent: str, child: str, T_parent_child: np.ndarray):
        T = self._types
        q = _quaternion(T_parent_child[:3, :3])
        return T["geometry_msgs/msg/TransformStamped"](
            header=self._header(t, parent),
            child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](*(float(v) for v in T_parent_child[:3, 3])),
                rotation=T["geometry_msgs/msg/Quaternion"](*q),
            ),
        )

    def _write(self, connection, t: float, msg: object) -> None:
        check_bag_time(t, str(self.path))  # before anything of the frame is written: the bag stays readable
        self._writer.write(connection, _ns(t), self._store.serialize_cdr(msg, connection.msgtype))

    def body_frame(self) -> str:
        """TF name of the vest's body frame."""
        return f"{self.vest}/body"

    def camera_frame(self, camera: int) -> str:
        """TF name of rig camera ``camera``."""
        return f"{self.vest}/{ros_name(self.rig[camera].name)}"

    # --- sink interface ---------------------------------------------------------------------
    def publish(self, message: PoseMessage) -> bool:
        """Write the pose (PoseWithCovarianceStamped, /tf) and the JSON message; no pose while initialising."""
        T = self._types
        out = message.output
        t = float(out.t)
        if not self._static_written:
            tfs = [
                self._transform(t, self.body_frame(), self.camera_frame(k), rc.T_body_camera)
                for k, rc in enumerate(self.rig.cameras)
            ]
            self._write(self._tf_static, t, T[TF_TYPE](transforms=tfs))
            self._static_written = True
        self._published = (message.index, t)
        self._write(self._json, t, T[STRING_TYPE](data=message.encode().decode()))
        if out.state == TrackState.INITIALISING:
            self.dropped += 1
            return False
        x, y, yaw = (float(v) for v in out.pose)
        Tw = planar_T(x, y, yaw)
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x, y, 0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](*_quaternion(Tw[:3, :3])),
        )
        msg = T[POSE_TYPE](
            header=self._header(t, WORLD_FRAME),
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=covariance_6x6(out.cov).ravel()),
        )
        self._write(self._pose, t, msg)
        self._write(self._tf, t, T[TF_TYPE](transforms=[self._transform(t, WORLD_FRAME, self.body_frame(), Tw)]))
        self.sent += 1
        return True

    def write_frame(
        self, frame: Frame, result: FrameResult, encoded: bytes | None = None, late: Sequence[Observation] = ()
    ) -> None:
        """Write a frame's sticker detections and, with ``images``, its image (``encoded`` JPEG bytes if given),
        at the time its pose was published (the frame's time, plus the offset of a reset source clock).

        ``late``: the frame's detections its deferred decoding named after the frame was published
        (``tagloc live``; :attr:`Localiser.late`), written in place of their unidentified entries, so
        that the detections hold every fix the tracker fused, as the frame log does."""
        T = self._types
        if self._published is not None and self._published[0] == result.index:
            self._offset = self._published[1] - float(result.output.t)
        t = float(result.timestamp) + self._offset
        k = frame.camera
        dets = []
        for o in result.observations:
            if o.camera != k:
                continue
            o = next((n for n in late if n.detection is o.detection), o)
            dets.append(
                T[DETECTION_TYPE](
                    sticker_id=-1 if o.sticker_id is None else int(o.sticker_id),
                    source=o.source.value,
                    corners_px=np.asarray(o.detection.outer, float).ravel(),
                    accepted=bool(o.accepted),
                    gate_reason=o.gate_reason or "",
                )
            )
        header = self._header(t, self.camera_frame(k))
        self._write(self._det[k], t, T[DETECTIONS_TYPE](header=header, detections=dets))
        if self.images and (encoded is not None or frame.image is not None):
            if encoded is None:
                ok, buf = cv2.imencode(".jpg", frame.image, [cv2.IMWRITE_JPEG_QUALITY, IMAGE_JPEG_QUALITY])
                encoded = buf.tobytes() if ok else b""
            data = np.frombuffer(encoded, np.uint8)
            self._write(self._img[k], t, T[COMPRESSED_TYPE](header=header, format="jpeg", data=data))
            self._write(self._info[k], t, camera_info(self._types, header, self.rig[k].camera))
        self.frames += 1

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None


def camera_info(types: dict, header: object, cam: Camera) -> object:
    """A ``sensor_msgs/msg/CameraInfo`` for an OpenCV calibration (plumb_bob or rational_polynomial)."""
    d = np.asarray(cam.dist, float)
    model = "plumb_bob" if len(d) <= 5 else "rational_polynomial"
    if len(d) < 5:
        d = np.r_[d, np.zeros(5 - len(d))]
    P = np.c_[cam.K, np.zeros(3)]
    return types[INFO_TYPE](
        header=header,
        height=int(cam.height),
        width=int(cam.width),
        distortion_model=model,
        d=d,
        k=np.asarray(cam.K, float).ravel(),
        r=np.eye(3).ravel(),
        p=P.ravel(),
        binning_x=0,
        binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](0, 0, 0, 0, False),
    )


def camera_from_info(msg: object) -> Camera:
    """The calibration in a CameraInfo message (ROS 2 ``k``/``d`` or ROS 1 ``K``/``D``), checked as a
    calibration file is (:func:`tagloc.core.camera.check_calibration`): NaN coefficients, a focal
    length of 1e-9 px or three distortion coefficients had run a whole replay without a pose, or
    stopped it inside OpenCV."""
    K = np.asarray(getattr(msg, "k", None) if hasattr(msg, "k") else msg.K, float)
    D = np.asarray(getattr(msg, "d", None) if hasattr(msg, "d") else msg.D, float)
    if K.size != 9 or not np.all(np.isfinite(K)) or K[0] <= 0:
        raise InputError("CameraInfo holds no calibration (K is empty or zero)")
    if why := distortion_model_problem(getattr(msg, "distortion_model", None)):
        raise InputError(f"CameraInfo {why}, and give it with --calibration")
    cam = Camera(K.reshape(3, 3), D if D.size else np.zeros(5), int(msg.width), int(msg.height))
    return check_calibration(cam, "CameraInfo")


def _quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix (scipy's conversion)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return float(x), float(y), float(z), float(w)


# --- reading --------------------------------------------------------------------------------------


def _open_reader(path: Path):
    try:
        from rosbags.highlevel import AnyReader
    except ImportError as exc:  # pragma: no cover - rosbags is a dependency
        raise BackendUnavailable("rosbags is not installed; pip install rosbags") from exc
    if not path.exists():
        raise SessionError(f"{path}: no such bag")
    if path.is_dir() and not (path / "metadata.yaml").exists():
        storage = sorted([*path.glob("*.mcap"), *path.glob("*.db3")])
        if storage:
            # rosbag2 writes metadata.yaml (and an MCAP file's index and footer) when the bag is
            # closed: storage files without it are a recording that was killed (kill -9, power loss).
            # rosbags reads no such file, so the user is told why, and what is safe next time.
            raise SessionError(
                f"{path}: has {storage[0].name} but no metadata.yaml: the recording was likely interrupted "
                "(killed before its bag was closed) and cannot be read; ROS 2's `mcap recover` and "
                "`ros2 bag reindex` may repair it, and `tagloc live --record DIR` records a crash-safe session"
            )
        raise SessionError(f"{path}: not a rosbag2 directory (no metadata.yaml)")
    if path.is_file() and path.suffix != ".bag":
        raise SessionError(f"{path}: want a rosbag2 directory or a ROS 1 .bag file")
    try:
        reader = AnyReader([path], default_typestore=_typestore())
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises many error types for a damaged bag
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if "end magic" in reason:
            # An MCAP file without its footer: cut short, as a recording that was killed leaves it.
            reason += " The file ends early: the recording was likely interrupted"
        raise SessionError(f"{path}: cannot read bag ({reason})") from exc
    return reader


def _messages(reader, path: Path, connections: list) -> Iterator[tuple[object, int, bytes]]:
    """``reader.messages(connections=...)``, with a record the bag cannot give (damaged mid-file)
    refused as a one-line :class:`SessionError` naming the bag and how far it was read: the messages
    before it have been handed on (a replay's outputs and a converted session keep them)."""
    it = iter(reader.messages(connections=connections))
    n = 0
    while True:
        try:
            item = next(it)
        except StopIteration:
            return
        except Exception as exc:  # noqa: BLE001 - rosbags raises many error types for a damaged bag
            reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise SessionError(f"{path}: damaged after {n} messages ({reason})") from exc
        n += 1
        yield item


def is_bag(path: str | Path) -> bool:
    """Whether ``path`` looks like a bag (a rosbag2 directory or a ROS 1 .bag file) rather than a session."""
    p = Path(path)
    try:
        return (p.is_dir() and (p / "metadata.yaml").exists()) or (p.is_file() and p.suffix == ".bag")
    except PermissionError:
        # Named as the user gave it, not as the file inside that was probed.
        raise SessionError(f"{p}: no permission to read") from None


# Bytes per pixel of the sensor_msgs/Image encodings tagloc reads (lower-cased).
RAW_ENCODINGS = {
    "mono8": 1,
    "8uc1": 1,
    "bgr8": 3,
    "rgb8": 3,
    "8uc3": 3,
    "bgra8": 4,
    "rgba8": 4,
    "mono16": 2,
    "16uc1": 2,
}


def _unreadable(i: int, topic: str, t: float, msg: object, msgtype: str) -> str:
    """Why frame ``i``'s image message could not be read: an encoding tagloc does not read is named
    (a bayer or YUV camera's every frame is skipped, and "corrupt" alone sent the user to the bag)."""
    where = f"frame {i}: {topic} message at t={t:.6f}"
    enc = getattr(msg, "encoding", None)
    if msg is not None and not msgtype.endswith("CompressedImage") and str(enc).lower() not in RAW_ENCODINGS:
        return f"{where} has encoding {str(enc)[:40]!r}, which tagloc does not read (mono8, bgr8, rgb8, bgra8, rgba8, mono16)"
    return f"{where} is corrupt or in an unsupported encoding"


def _image_to_grey(msg: object, msgtype: str) -> np.ndarray | None:
    """(H, W) uint8 from a CompressedImage or Image message, None if it cannot be decoded."""
    if msgtype.endswith("CompressedImage"):
        return decode_grey(bytes(msg.data))
    enc = msg.encoding.lower()
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.frombuffer(bytes(msg.data), np.uint8)
    channels = RAW_ENCODINGS
    # A row (step bytes) must hold the width's pixels, and the data every row.
    if enc not in channels or h <= 0 or w <= 0 or step < channels[enc] * w or data.size < h * step:
        return None
    rows = data[: h * step].reshape(h, step)
    if enc in ("mono16", "16uc1"):
        big = bool(getattr(msg, "is_bigendian", 0))
        img16 = rows[:, : 2 * w].copy().view(">u2" if big else "<u2").reshape(h, w)
        return (img16 >> 8).astype(np.uint8)
    n = channels[enc]
    img = rows[:, : n * w].reshape(h, w, n) if n > 1 else rows[:, :w]
    if n == 1:
        return np.ascontiguousarray(img)
    code = {
        "bgr8": cv2.COLOR_BGR2GRAY,
        "8uc3": cv2.COLOR_BGR2GRAY,
        "rgb8": cv2.COLOR_RGB2GRAY,
        "bgra8": cv2.COLOR_BGRA2GRAY,
        "rgba8": cv2.COLOR_RGBA2GRAY,
    }[enc]
    return cv2.cvtColor(np.ascontiguousarray(img), code)


def _info_topic_for(topic: str) -> str:
    """The CameraInfo topic a ROS camera driver publishes beside ``topic`` (image_transport's convention)."""
    parts = topic.rstrip("/").split("/")
    if parts[-1] in ("compressed", "theora", "compressedDepth"):
        parts = parts[:-1]
    return "/".join(parts[:-1] + ["camera_info"])


class BagSession:
    """A bag's camera topic as a session (the interface of :class:`tagloc.io.session.SessionReader`).

    Args:
        path: rosbag2 directory (MCAP or SQLite) or ROS 1 ``.bag`` file.
        topic: image topic (``sensor_msgs/Image`` or ``CompressedImage``).
        map_path: sticker map CSV.
        rig_path: rig JSON (camera pose in the body frame); default rig without it.
        calibration: calibration file; overrides the bag's CameraInfo, which overrides the rig's.
        info_topic: CameraInfo topic; default: beside ``topic`` (``.../camera_info``), else the only one.

    Frame timestamps are the image headers' stamps (the bag's receive time when a stamp is zero);
    frames are numbered 0, 1, ... in bag order. A frame whose stamp is wild (after the frames that
    follow it, see :data:`WILD_STAMP_WINDOW`) is skipped and counted like an undecodable one.
    """

    def __init__(
        self,
        path: str | Path,
        topic: str,
        map_path: str | Path,
        rig_path: str | Path | None = None,
        calibration: str | Path | None = None,
        info_topic: str | None = None,
    ):
        self.path = Path(path)
        self.map_path = Path(map_path)
        self.topic = topic
        self.map: StickerMap = load_map(self.map_path)
        reader = _open_reader(self.path)
        try:
            conns = [c for c in reader.connections if c.topic == topic]
            if not conns:
                cams = sorted({c.topic for c in reader.connections if c.msgtype in IMAGE_TYPES})
                raise SessionError(
                    f"{self.path}: no topic {topic!r}; image topics in the bag: {', '.join(cams) or 'none'}"
                )
            if conns[0].msgtype not in IMAGE_TYPES:
                raise SessionError(f"{self.path}: {topic} is {conns[0].msgtype}, not an Image or CompressedImage")
            self.msgtype = conns[0].msgtype
            self.count = sum(c.msgcount for c in conns)
            if self.count == 0:
                # As a session whose frames.csv lists none: nothing to localise (a replay had exited 0
                # with no output, a conversion written a session that replay refuses).
                raise SessionError(f"{self.path}: {topic} holds no messages")
            # --calibration overrides the bag's CameraInfo, so a bad one (the very case for it) is not read.
            self._info_used: str | None = None  # the CameraInfo topic the calibration came from
            bag_camera = (
                None
                if calibration
                else self._bag_calibration(reader, info_topic or _info_topic_for(topic), info_topic is not None)
            )
        finally:
            reader.close()
        camera = load_calibration(calibration) if calibration else bag_camera
        if rig_path is not None:
            self.rig: Rig = load_rig(rig_path, camera)
        elif camera is not None:
            self.rig = default_rig(camera=camera)
        else:
            raise SessionError(f"{self.path}: no CameraInfo for {topic}; give --calibration or --rig")
        # Where the calibration came from, for a message that has to name it.
        if calibration:
            self.calibration_source = f"{calibration} (--calibration)"
        elif bag_camera is not None:
            self.calibration_source = f"the bag's CameraInfo on {self._info_used}"
        else:
            self.calibration_source = str(Path(rig_path).parent / self.rig.cameras[0].calibration_file)
        self.index = np.arange(self.count)
        self.skipped: list[tuple[int, str]] = []
        self.warnings: list[str] = []  # as SessionReader's: odd but usable (none known for bags yet)
        self.info = SessionInfo(source=f"rosbag {self.path.name} {topic}", fps=0.0)

    def _bag_calibration(self, reader, info_topic: str, explicit: bool) -> Camera | None:
        infos = [c for c in reader.connections if c.msgtype in (INFO_TYPE, "sensor_msgs/CameraInfo")]
        chosen = [c for c in infos if c.topic == info_topic]
        if not chosen:
            if explicit:
                raise SessionError(f"{self.path}: no CameraInfo topic {info_topic!r}")
            if len({c.topic for c in infos}) != 1:
                return None
            chosen = infos
        for conn, _, raw in _messages(reader, self.path, chosen):
            self._info_used = conn.topic
            try:
                return camera_from_info(reader.deserialize(raw, conn.msgtype))
            except InputError as exc:
                raise SessionError(f"{self.path}: {conn.topic}: {exc}") from None
        return None

    def __len__(self) -> int:
        return self.count

    @property
    def camera(self) -> Camera:
        """The first camera's calibration."""
        return self.rig.cameras[0].camera

    def frame_path(self, index: int, camera: int = 0) -> Path | None:
        """Bags hold no image files."""
        return None

    def groundtruth(self) -> None:
        """Bags carry no ground truth tagloc can read."""
        return None

    def _stamped_messages(self) -> Iterator[_RawImage]:
        """Every image message of the topic in bag order, deserialised (None when it cannot be), with
        its receive time and header stamp."""
        reader = _open_reader(self.path)
        try:
            conns = [c for c in reader.connections if c.topic == self.topic]
            for i, (conn, bag_ns, raw) in enumerate(_messages(reader, self.path, conns)):
                received = bag_ns / 1e9
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                except Exception:  # noqa: BLE001 - a corrupt message is one skipped frame
                    yield _RawImage(i, received, None, None, conn.msgtype)
                    continue
                t = _stamp_s(msg.header.stamp)
                yield _RawImage(i, received, t if t > 0 else received, msg, conn.msgtype)
        finally:
            reader.close()

    def encoded_frames(self) -> Iterator[BagImage]:
        """Every image message, in bag order, with its frame time (see :class:`BagImage`)."""
        return judge_stamps(self._stamped_messages(), self.topic)

    def frames(self, with_images: bool = True) -> Iterator[Frame]:
        """Yield every frame in order; undecodable ones, and those of a wild stamp, come with
        ``image=None`` and ``error`` set."""
        for f in self.encoded_frames():
            if not with_images:
                yield Frame(f.index, f.t, None, 0, f.wild)
                continue
            err = f.wild
            img = None if f.msg is None or err else _image_to_grey(f.msg, f.msgtype)
            if img is None:
                err = err or _unreadable(f.index, self.topic, f.t, f.msg, f.msgtype)
                self.skipped.append((f.index, err))
            yield Frame(f.index, f.t, img, 0, err)


def _frame_interval(stamps: Iterable[float | None]) -> float:
    """The median step between consecutive stamps that advance (0 with none)."""
    seq = [t for t in stamps if t is not None]
    steps = [b - a for a, b in zip(seq, seq[1:]) if b > a]
    return statistics.median(steps) if steps else 0.0


class _RawImage(NamedTuple):
    """An image message as the bag holds it: header stamp None when the message cannot be read."""

    index: int
    received: float
    stamp: float | None
    msg: object
    msgtype: str


class BagImage(NamedTuple):
    """An image message of a bag's camera topic.

    Attributes:
        index: its place on the topic (0, 1, ... in bag order): the frame's index.
        t: the frame time (s): the header stamp, else (a corrupt message, a wild stamp) the receive
            time moved onto the frames' clock.
        msg: the deserialised message, None when it could not be.
        msgtype: its ROS type.
        wild: why its header stamp was not taken (a wild stamp: skip the frame), else None.
    """

    index: int
    t: float
    msg: object
    msgtype: str
    wild: str | None = None


def judge_stamps(messages: Iterable[_RawImage], topic: str, window: int = WILD_STAMP_WINDOW) -> Iterator[BagImage]:
    """The frames of ``messages`` with their times, a wild stamp found by looking ``window`` frames ahead.

    A stamp is wild when one of the next ``window`` frames is stamped between the last stamp taken and
    it, more than :data:`WILD_STAMP_STEPS` frame intervals (the median of the stamps around it) before
    it: that one frame is out of order, not all the frames after it. (Taken, a camera stamp 2^31 s
    in the future made a conversion skip every later frame as "not after" it, and a replay take it
    as a reset clock and shift every later pose by as much.) A stamp before the last one is passed on
    as it is: a lone one is refused by the localiser, and a run of them is a clock that was reset
    (but frames before a reset within the bag's first ``window`` frames are taken as the wild ones:
    with no stamp before them, the shorter run is the one out of order).
    """
    ahead: deque[_RawImage] = deque()
    taken: deque[float] = deque(maxlen=2 * window)  # the last stamps taken, for the frame interval
    last = -math.inf  # the last stamp taken
    offset = 0.0  # that frame's time less its receive time (s)

    def settle(r: _RawImage) -> BagImage:
        nonlocal last, offset
        if r.stamp is None:
            # No header to take its time from: its receive time, moved onto the frames' clock as the
            # last frame's was. Unmoved, a driver's latency (or header stamps on another clock) put it
            # after the frames that follow, each then skipped as not after it: one corrupt message
            # cost the rest of the session.
            return BagImage(r.index, r.received + offset, None, r.msgtype)
        between = [(a.stamp, a.index) for a in ahead if a.stamp is not None and last < a.stamp < r.stamp]
        nxt, k = min(between) if between else (r.stamp, r.index)
        if between and r.stamp - nxt > WILD_STAMP_STEPS * _frame_interval([*taken, *(a.stamp for a in ahead)]):
            # Its time for the frame's place in the stream: the receive time on the frames' clock,
            # kept between its neighbours so that neither is refused for it.
            t = r.received + offset
            lo = last if math.isfinite(last) else nxt - 1.0
            if not lo < t < nxt:
                t = (lo + nxt) / 2
            why = (
                f"frame {r.index}: {topic} message stamped {seconds_text(r.stamp)} s, after frame {k}'s "
                f"{seconds_text(nxt)} s that follows it (a wild stamp)"
            )
            return BagImage(r.index, t, r.msg, r.msgtype, why)
        last, offset = r.stamp, r.stamp - r.received
        taken.append(r.stamp)
        return BagImage(r.index, r.stamp, r.msg, r.msgtype)

    it = iter(messages)
    try:
        for r in it:
            ahead.append(r)
            if len(ahead) > window:
                yield settle(ahead.popleft())
        while ahead:
            yield settle(ahead.popleft())
    finally:
        close = getattr(it, "close", None)
        if close is not None:
            close()  # the bag reader's, when the caller stops early


def bag_to_session(
    bag: str | Path,
    topic: str,
    out: str | Path,
    map_path: str | Path,
    rig_path: str | Path | None = None,
    calibration: str | Path | None = None,
    info_topic: str | None = None,
    progress: bool = False,
    warn: Callable[[str], None] | None = None,
) -> tuple[int, int]:
    """Convert a bag's camera topic to a session directory; returns (frames written, frames skipped).

    JPEG images are copied byte for byte; other images are written as PNG (lossless). A frame whose
    stamp is not after the one before it is skipped like an undecodable one, as a replay of the bag
    refuses it: a session must advance frame by frame, and one such line made the whole session
    refused. One after it but within the last written frame's microsecond (the resolution of
    ``frames.csv``) goes on at the next microsecond, as ``tagloc live`` moves a camera's frame on,
    since a replay of the bag takes it (skipped, the session lacked a frame the bag's replay has).
    A frame of a wild stamp (see :func:`judge_stamps`) is skipped, not the frames after it, and so
    is one whose image is not the calibration's size; when the first image is not, nothing is
    written (every reader would refuse the session). ``warn`` (default: a line on stderr) is given
    one line naming the first :data:`SKIPPED_NAMED` skipped frames.
    """
    from itertools import chain

    from tqdm import tqdm

    src = BagSession(bag, topic, map_path, rig_path, calibration, info_topic)
    _check_inputs_kept(Path(out), src, rig_path, calibration)
    cam = src.rig.cameras[0].camera
    frames = src.encoded_frames()
    head = _check_first_size(src, frames, (cam.width, cam.height))
    written = 0
    skipped: list[str] = []  # why each skipped frame was
    last = -math.inf  # the last written frame's time
    last_t = -math.inf  # the last stamp a replay of the bag takes (the localiser refuses one not after it)
    with SessionWriter(out, src.map, src.rig, SessionInfo(source=src.info.source, fps=0.0), image_ext=".png") as w:
        try:
            for f in tqdm(chain(head, frames), total=len(src), disable=not progress, unit="frame"):
                if f.wild:
                    skipped.append(f.wild)
                    continue
                if not f.t > last_t:
                    skipped.append(
                        f"frame {f.index}: {topic} message stamped {seconds_text(f.t)} s, not after the previous "
                        f"frame's {seconds_text(last_t)} s"
                    )
                    continue
                last_t = f.t
                stamp = after_last(f.t, last)
                why = _convert(w, f, stamp, (cam.width, cam.height), topic)
                if why is None:
                    written += 1
                    last = stamp
                else:
                    skipped.append(why)
        except SessionError as exc:
            raise SessionError(f"{exc}; {out} holds the {written} frames before it") from exc
    if not written:
        # A session listing no frames is refused by every reader: say so now, not at its replay.
        first = skipped[0] if skipped else "none"
        raise SessionError(f"{src.path}: none of the {len(skipped)} frames of {topic} could be converted ({first})")
    if skipped:
        more = f"; and {len(skipped) - SKIPPED_NAMED} more" if len(skipped) > SKIPPED_NAMED else ""
        (warn or warn_stderr)(
            f"{src.path}: {len(skipped)} frame{'s' if len(skipped) > 1 else ''} skipped: "
            + "; ".join(skipped[:SKIPPED_NAMED])
            + more
        )
    return written, len(skipped)


def _check_first_size(src: BagSession, frames: Iterator[BagImage], size: tuple[int, int]) -> list[BagImage]:
    """Refuse a bag whose first readable image (within its first frames) is not ``size`` (the
    calibration's), before anything is written: a session of such frames was written whole, and
    every reader then refused every frame. Returns the frames read to find it, to be converted."""
    head: list[BagImage] = []
    for f in frames:
        head.append(f)
        img = None if f.msg is None or f.wild else _image_to_grey(f.msg, f.msgtype)
        if img is not None:
            h, w = img.shape[:2]
            if (w, h) != size:
                raise SessionError(
                    f"{src.path}: {src.topic}: images are {w}x{h} px but the calibration {src.calibration_source} "
                    f"is for {size[0]}x{size[1]}; give the calibration of the camera that recorded them"
                )
            break
        if len(head) >= SIZE_PROBE_FRAMES:
            break  # all unreadable so far: each later one is checked as it is converted
    return head


def _check_inputs_kept(out: Path, src: BagSession, rig_path: str | Path | None, calibration: str | Path | None) -> None:
    """Refuse a session directory ``out`` whose files would be written over one the conversion reads:
    ``-o site`` with ``--map site/map.csv`` had rewritten the map at the session's 0.1 mm, and the
    calibration the rig names replaced by the bag's CameraInfo."""
    inputs = [src.map_path, rig_path, calibration]
    if rig_path is not None:
        inputs += [Path(rig_path).parent / c.calibration_file for c in src.rig.cameras]
    read = {os.path.realpath(p) for p in inputs if p is not None}
    names = [SESSION_JSON, MAP_FILE, RIG_FILE, FRAMES_CSV, *local_calibration_names(src.rig)]
    for name in names:
        if os.path.realpath(out / name) in read:
            raise SessionError(f"{out / name}: is one of the conversion's inputs, which the session would overwrite")


def _convert(w: SessionWriter, f: BagImage, t: float, size: tuple[int, int], topic: str) -> str | None:
    """Write one bag image message to the session ``w`` at time ``t``: None, or why it is skipped
    (undecodable, or not ``size``, the calibration's: a replay skips such a frame)."""
    msg, msgtype = f.msg, f.msgtype
    img = None if msg is None else _image_to_grey(msg, msgtype)
    if img is None:
        return _unreadable(f.index, topic, f.t, msg, msgtype)
    h, wd = img.shape[:2]
    if (wd, h) != size:
        return f"frame {f.index}: image is {wd}x{h}, the calibration is for {size[0]}x{size[1]}"
    if msgtype.endswith("CompressedImage") and "jpeg" in msg.format.lower():
        w.write_encoded(f.index, t, bytes(msg.data), ".jpg")  # byte for byte: no second lossy encoding
    else:
        w.write(f.index, t, img)
    return None


@dataclass
class BagPose:
    """A pose message read back from a bag: receive time (bag clock, s), topic and the JSON document
    (or the message's text when it is not JSON: the monitor counts it invalid). ``error``: why a
    message the bag holds could not be read at all (its bytes are not the type's), counted invalid too."""

    t_bag: float
    topic: str
    doc: dict | str
    error: str | None = None


def read_pose_messages(path: str | Path) -> Iterator[BagPose]:
    """The tagloc pose messages in a bag, in time order.

    From ``/tagloc/*/pose_json`` when present (the full message, state included); otherwise rebuilt
    from ``/tagloc/*/pose`` PoseWithCovarianceStamped with state ``unknown``.
    """
    reader = _open_reader(Path(path))
    try:
        json_conns = [c for c in reader.connections if c.topic.endswith("/pose_json") and c.msgtype == STRING_TYPE]
        have_json = {c.topic.rsplit("/", 1)[0] for c in json_conns}
        pose_conns = [
            c
            for c in reader.connections
            if c.topic.startswith("/tagloc/") and c.msgtype == POSE_TYPE and c.topic.rsplit("/", 1)[0] not in have_json
        ]
        for conn, ns, raw in _messages(reader, Path(path), json_conns + pose_conns):
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception:  # noqa: BLE001 - rosbags raises many error types for bytes that are not the type
                # One bad message, as on the network: counted invalid, and the messages after it read.
                yield BagPose(ns / 1e9, conn.topic, "", f"{conn.topic}: not a readable {conn.msgtype} message")
                continue
            if conn.msgtype == STRING_TYPE:
                try:
                    doc = json.loads(msg.data)
                except (ValueError, RecursionError):
                    # Not JSON, or JSON Python will not decode (an integer of over 4300 digits, nesting
                    # past the recursion limit): passed on as text, for the monitor to count and explain.
                    doc = msg.data
                if not isinstance(doc, dict):
                    # JSON, but no object ([1, 2], 5, null): the text, which the monitor refuses as
                    # "not a JSON object" and counts invalid, as it does a message off the network.
                    doc = msg.data
            else:
                doc = _doc_from_pose(conn.topic, msg)
            yield BagPose(ns / 1e9, conn.topic, doc)
    finally:
        reader.close()


def _doc_from_pose(topic: str, msg: object) -> dict:
    from scipy.spatial.transform import Rotation

    o = msg.pose.pose.orientation
    q = np.array([o.x, o.y, o.z, o.w], float)
    # A quaternion that is no rotation (zero, NaN) gives no yaw: NaN, which the monitor refuses as
    # it refuses any non-finite number (scipy raised, and stopped the monitor).
    norm = float(np.linalg.norm(q))
    yaw = float(Rotation.from_quat(q).as_euler("xyz")[2]) if math.isfinite(norm) and norm > 1e-9 else math.nan
    p = msg.pose.pose.position
    return {
        "schema": SCHEMA,
        "vest": topic.split("/")[2],
        "frame": msg.header.frame_id,
        "t": _stamp_s(msg.header.stamp),
        "x": float(p.x),
        "y": float(p.y),
        "yaw": yaw,
        "yaw_deg": math.degrees(yaw),
        "cov": covariance_3x3(msg.pose.covariance).tolist(),
        "state": "unknown",
    }
