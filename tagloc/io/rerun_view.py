"""Rerun visualisation of a localisation run: one recording, one blueprint.

Entity tree (``CAM`` is the rig camera's name, e.g. ``front``)::

    world/map/stickers              static: sticker outlines on the floor, labelled with their IDs
    world/map/extent                static: the floor's outline (the stickers' extent plus 1 m)
    world/body                      estimated body pose (Transform3D), per frame once tracking
    world/body/CAM                  static: T_body_camera
    world/body/CAM/image            static Pinhole (scaled to the logged image) + JPEG image per frame
    world/body/CAM/image/detections sticker outlines, coloured by how they were identified, with IDs
    world/estimate/path/NNNN        estimated trajectory, in pieces of PATH_PIECE frames
    world/estimate/ellipse          2-sigma position ellipse on the floor
    world/groundtruth/path          static: the whole ground-truth trajectory (when known)
    world/groundtruth/body          ground truth at the frame time (when known)
    plots/error/{position_m,yaw_deg}                     when ground truth is known
    plots/uncertainty/{position_2sigma_m,yaw_sigma_deg,since_fix_s}
    plots/timing/<stage>_ms         per-stage wall time of the localiser
    status                          text: tracker state, last sticker

Timelines: ``frame`` (sequence: frame index) and ``time`` (the frame clock: a duration for a
session's clock, a timestamp for a live camera's epoch-based clock, and for a replay of one: a live
recording or a ROS bag). A frame whose time is not finite, out of Rerun's range or before the last
frame's (a stamp the localiser refused) is on ``frame`` alone.

The trajectory is logged in pieces (each piece re-logged as it grows) so that every frame adds
a bounded amount of data and scrubbing back in time still shows the path as it was then.

Open a saved recording with ``rerun out.rrd``.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import sys
import urllib.parse
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from tagloc.core.errors import BackendUnavailable, InputError
from tagloc.core.geometry import interpolate_groundtruth, wrap_angle
from tagloc.core.rig import Rig
from tagloc.core.sticker import OUTER_CORNERS
from tagloc.core.stickermap import StickerMap
from tagloc.core.types import Frame, FrameResult, IdSource, Observation, TrackState, frame_seconds

PATH_PIECE = 256  # frames per trajectory piece
NETWORK_FLUSH_S = 5.0  # longest wait for a viewer when closing
VIEWER_PROBE_S = 2.0  # longest wait to reach a viewer's port at start
VIEWER_PORT = 9876  # where a spawned viewer listens (Rerun's default)
MAX_TIME_S = 9.2e9  # |time| Rerun holds: int64 nanoseconds (and below its 1e11 s "milliseconds?" check)

log = logging.getLogger(__name__)

SOURCE_COLOURS: dict[IdSource, tuple[int, int, int]] = {
    IdSource.DECODED: (40, 200, 60),
    IdSource.CHECKED: (150, 210, 40),
    IdSource.ORB: (40, 140, 255),
    IdSource.APPEARANCE: (230, 140, 20),
    IdSource.NONE: (220, 40, 40),
}
ESTIMATE_COLOUR = (255, 200, 0)
TRUTH_COLOUR = (160, 160, 160)


def import_rerun():
    """The rerun module; BackendUnavailable if rerun-sdk is missing."""
    try:
        import rerun as rr
    except ImportError as exc:  # pragma: no cover - rerun-sdk is a dependency
        raise BackendUnavailable("rerun-sdk is not installed; pip install rerun-sdk") from exc
    return rr


def new_recording(app_id: str, save, spawn: bool, connect: str | None, recording_id: str | None = None):
    """A Rerun recording stream, refusing a call that names nowhere to send it."""
    rr = import_rerun()
    if not (save or spawn or connect):
        raise InputError("Rerun: give a file to save to, spawn=True or a viewer URL")
    return rr.RecordingStream(app_id, recording_id=recording_id)


def viewer_address(url: str) -> tuple[str, int]:
    """(host, port) of a Rerun viewer URL (``rerun+http://HOST:PORT/proxy``, ``rerun+https://``,
    ``rerun://``; without a port, 9876 whatever the scheme, as Rerun itself connects: not the
    HTTPS port); InputError for anything else."""
    parts = urllib.parse.urlsplit(url)
    try:
        port = parts.port
    except ValueError:  # a port that is not a number in 0-65535
        port = -1
    if parts.scheme not in ("rerun", "rerun+http", "rerun+https") or not parts.hostname or port == -1:
        raise InputError(
            f"Rerun viewer URL {url!r}: expected rerun+http://HOST:PORT/proxy (or rerun+https://, rerun://)"
        )
    # Rerun puts 9876 in a URL without a port, rerun:// and rerun+https:// too (probing 443 refused a
    # viewer listening where Rerun would have reached it, and took one that was not).
    return parts.hostname, port or 9876


def viewer_listens(host: str, port: int, timeout: float = VIEWER_PROBE_S) -> str | None:
    """None when something accepts a TCP connection at host:port, else why not."""
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except OSError as exc:
        return exc.strerror or str(exc) or type(exc).__name__
    return None


def no_display() -> bool:
    """Whether a window cannot open here: on Linux and the BSDs, neither X11 nor Wayland is named."""
    if sys.platform in ("darwin", "win32"):
        return False
    return not any(os.environ.get(k) for k in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"))


def attach_sinks(rec, blueprint, save, spawn: bool, connect: str | None, spawn_hint: str) -> bool:
    """Send ``rec`` to a file (``save``), a viewer started here (``spawn``) and/or a viewer URL
    (``connect``), with ``blueprint`` as the default layout. Returns whether a network viewer is
    attached (its flush must be bounded). ``spawn_hint`` ends the error when no viewer can start."""
    rr = import_rerun()
    sinks = []
    if save:
        Path(save).parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rr.FileSink(str(save)))
    if spawn:
        # A viewer already listening is used as it is (Rerun starts none then). One started without a
        # display exits at once, and Rerun would only say so at the end, after buffering the whole run.
        running = viewer_listens("127.0.0.1", VIEWER_PORT) is None
        if not running and no_display():
            raise BackendUnavailable(
                "cannot start the Rerun viewer: no display (DISPLAY and WAYLAND_DISPLAY are not set); "
                "save a recording instead and open it (`rerun FILE.rrd`) where there is one"
            )
        # Start the viewer only; the stream is attached below with the other sinks.
        try:
            rec.spawn(port=VIEWER_PORT, connect=False)
        except RuntimeError as exc:  # the viewer executable is missing
            raise BackendUnavailable(
                f"cannot start the Rerun viewer ({str(exc).splitlines()[0].strip()}); {spawn_hint}"
            ) from exc
        if not running and (problem := viewer_listens("127.0.0.1", VIEWER_PORT)) is not None:
            raise BackendUnavailable(
                f"the Rerun viewer did not start (port {VIEWER_PORT}: {problem}; its own lines above say why); "
                f"{spawn_hint}"
            )
        sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{VIEWER_PORT}/proxy"))
    if connect:
        # Rerun only warns, at the end, that it never reached the viewer (after the whole run had been
        # buffered for it, then up to 10 s of waiting): refuse a URL where nothing listens at once.
        problem = viewer_listens(*viewer_address(connect))
        if problem is not None:
            raise BackendUnavailable(
                f"no Rerun viewer at {connect} ({problem}); start one there (`rerun`) or save a recording instead"
            )
        sinks.append(rr.GrpcSink(connect))
    rec.set_sinks(*sinks, default_blueprint=blueprint)
    return bool(spawn or connect)


def image_entity(rig: Rig, camera: int) -> str:
    """Entity path of a rig camera's image (also the origin of its 2D view)."""
    return f"world/body/{rig[camera].name}/image"


def blueprint(
    rig: Rig,
    groundtruth: bool = False,
    smap: StickerMap | None = None,
    box: tuple[float, float, float, float] | None = None,
):
    """Floor plan (top-down) and camera image(s) on the left, time series grouped by unit on the right.

    Each plot holds one unit: position error beside its 2-sigma bound (m), heading error beside its
    sigma (deg), time since the last fix (s), stage timings (ms). Each image view is bounded to its
    image, so the whole frame shows at its aspect ratio.
    """
    import rerun.blueprint as rrb

    images = []
    for k, rc in enumerate(rig.cameras):
        w, h = rc.camera.width, rc.camera.height
        images.append(
            rrb.Spatial2DView(
                origin=image_entity(rig, k),
                name=f"camera {rc.name}",
                visual_bounds=rrb.VisualBounds2D(x_range=[0, w], y_range=[0, h]),
            )
        )
    err = ["plots/error/position_m"] if groundtruth else []
    yerr = ["plots/error/yaw_deg"] if groundtruth else []
    series = [
        rrb.TimeSeriesView(
            origin="plots",
            contents=[*err, "plots/uncertainty/position_2sigma_m"],
            name="position: error and 2-sigma (m)" if groundtruth else "position 2-sigma (m)",
        ),
        rrb.TimeSeriesView(
            origin="plots",
            contents=[*yerr, "plots/uncertainty/yaw_sigma_deg"],
            name="heading: error and sigma (deg)" if groundtruth else "heading sigma (deg)",
        ),
        rrb.TimeSeriesView(origin="plots", contents=["plots/uncertainty/since_fix_s"], name="since last fix (s)"),
        rrb.TimeSeriesView(origin="plots/timing", name="stage timing (ms)"),
    ]
    plan = (
        top_down_view(smap, "world", "floor plan (top-down)", box)
        if smap is not None
        else rrb.Spatial3DView(origin="world", name="map")
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(plan, rrb.Horizontal(*images), row_shares=[3, 2]),
            rrb.Vertical(*series, rrb.TextDocumentView(origin="status", name="status")),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


FLOOR_GRID_M = 1.0  # floor-plan grid spacing: one square per metre gives the scale at a glance
WALK_MARGIN_M = 3.0  # floor shown around a known walk in the replay's floor plan
TOP_DOWN_HEIGHT_FACTOR = 1.1  # top-down eye height as a multiple of the map's larger side (whole map in view)


def map_corners(smap: StickerMap) -> np.ndarray:
    """(N, 4, 3) outer corners of every sticker in the world (m), in map order."""
    if not len(smap):
        return np.zeros((0, 4, 3))
    return np.stack([(smap.T_world_sticker(int(i)) @ np.c_[OUTER_CORNERS, np.ones(4)].T).T[:, :3] for i in smap.ids])


def map_extent(smap: StickerMap, margin_m: float = 1.0) -> tuple[float, float, float, float]:
    """(x_min, y_min, x_max, y_max) of the stickers' centres grown by ``margin_m`` (the floor shown)."""
    if not len(smap):
        return (-5.0, -5.0, 5.0, 5.0)
    xy = np.array([smap.T_world_sticker(int(i))[:2, 3] for i in smap.ids])
    lo, hi = xy.min(axis=0) - margin_m, xy.max(axis=0) + margin_m
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def top_down_view(smap: StickerMap, origin: str, name: str, box: tuple[float, float, float, float] | None = None):
    """A 3-D view looking straight down on the map (x right, y up), with a 1 m floor grid.

    ``box`` (x_min, y_min, x_max, y_max, m) is the floor to frame; the whole map by default.

    A 3-D view with its eye overhead keeps world coordinates as they are (a 2-D view would draw +y
    downwards, mirroring the warehouse).
    """
    import rerun as rr
    import rerun.blueprint as rrb

    x0, y0, x1, y1 = box or map_extent(smap)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    height = TOP_DOWN_HEIGHT_FACTOR * max(x1 - x0, y1 - y0)
    return rrb.Spatial3DView(
        origin=origin,
        name=name,
        line_grid=rrb.LineGrid3D(visible=True, spacing=FLOOR_GRID_M, plane=rr.components.Plane3D.XY),
        eye_controls=rrb.EyeControls3D(position=[cx, cy, height], look_target=[cx, cy, 0.0], eye_up=[0.0, 1.0, 0.0]),
    )


def log_floor_plan(rec, smap: StickerMap, entity: str) -> None:
    """Log (static) the map's stickers with their IDs and the floor's outline under ``entity``."""
    rr = import_rerun()
    rec.log(entity, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    corners = map_corners(smap)
    if len(corners):
        strips = np.concatenate([corners, corners[:, :1]], axis=1)  # close each square
        rec.log(
            f"{entity}/map/stickers",
            rr.LineStrips3D(
                strips, labels=[str(int(i)) for i in smap.ids], colors=(90, 90, 90), radii=rr.Radius.ui_points(1.0)
            ),
            static=True,
        )
    x0, y0, x1, y1 = map_extent(smap)
    rec.log(
        f"{entity}/map/extent",
        rr.LineStrips3D([[[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0], [x0, y0, 0]]], colors=(60, 60, 60)),
        static=True,
    )


def circle(center: tuple[float, float], a: float, b: float, angle: float, n: int = 48) -> np.ndarray:
    """(n + 1, 3) closed polyline on the floor: an ellipse with half-axes a (along ``angle``) and b."""
    th = np.linspace(0.0, 2 * np.pi, n + 1)
    c, s = math.cos(angle), math.sin(angle)
    ex, ey = a * np.cos(th), b * np.sin(th)
    return np.c_[center[0] + c * ex - s * ey, center[1] + s * ex + c * ey, np.zeros(n + 1)]


class RerunView:
    """Log a localisation run to Rerun: a file (``save``), a spawned viewer (``spawn``) or a viewer's gRPC URL.

    Args:
        smap, rig: the map and rig being localised against.
        save: .rrd file to write.
        spawn: start a local viewer and stream to it.
        connect: stream to a running viewer, e.g. ``rerun+http://127.0.0.1:9876/proxy``.
        groundtruth: (stamps (M,), T_world_body (M, 4, 4)) when known.
        image_scale: factor applied to the logged camera image (keeps .rrd files small).
        jpeg_quality: JPEG quality of the logged image.
        clock: "duration" (a session's clock, seconds from its start), "timestamp" (epoch seconds) or
            "auto" (a timestamp when the first frame's time is on the epoch, as a live recording's or a
            ROS bag's are, else a duration).
    """

    def __init__(
        self,
        smap: StickerMap,
        rig: Rig,
        *,
        save: str | Path | None = None,
        spawn: bool = False,
        connect: str | None = None,
        groundtruth: tuple[np.ndarray, np.ndarray] | None = None,
        image_scale: float = 0.5,
        jpeg_quality: int = 75,
        clock: str = "duration",
        app_id: str = "tagloc",
        recording_id: str | None = None,
    ):
        self.rec = new_recording(app_id, save, spawn, connect, recording_id)
        if clock not in ("duration", "timestamp", "auto"):
            raise InputError(f"Rerun clock must be 'duration', 'timestamp' or 'auto', not {clock!r}")
        if not 0.0 < image_scale <= 1.0:
            raise InputError(f"Rerun image scale must be in (0, 1], not {image_scale}")
        self.rig = rig
        self.image_scale = float(image_scale)
        self.jpeg_quality = int(jpeg_quality)
        self.clock = clock
        self.gt = groundtruth if groundtruth is not None and len(groundtruth[0]) else None
        box = None
        if self.gt is not None:
            # Frame the walk (with room around it) rather than the whole warehouse.
            lo, hi = self.gt[1][:, :2, 3].min(axis=0) - WALK_MARGIN_M, self.gt[1][:, :2, 3].max(axis=0) + WALK_MARGIN_M
            box = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
        bp = blueprint(rig, groundtruth=self.gt is not None, smap=smap, box=box)
        self._network = attach_sinks(
            self.rec, bp, save, spawn, connect, "put `rerun` on PATH or save a recording instead"
        )
        self._path: list[list[float]] = []  # the current trajectory piece's points
        self._piece = 0  # its number
        self._posed = 0  # frames with a pose logged so far
        self._last_t = -math.inf  # the last time put on the ``time`` timeline
        self._on_clock: float | None = None  # the current frame's time there (None: off it)
        # camera -> (frame index, its time on ``time``, observations drawn) of its last image
        self._shown: dict[int, tuple[int, float | None, list[Observation]]] = {}
        self._log_static(smap)

    def _log_static(self, smap: StickerMap) -> None:
        rr = import_rerun()
        rec = self.rec
        log_floor_plan(rec, smap, "world")
        for k, rc in enumerate(self.rig.cameras):
            T = rc.T_body_camera
            rec.log(f"world/body/{rc.name}", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), static=True)
            cam = rc.camera.scaled(self.image_scale) if self.image_scale != 1.0 else rc.camera
            rec.log(
                image_entity(self.rig, k),
                rr.Pinhole(
                    image_from_camera=cam.K,
                    resolution=[cam.width, cam.height],
                    camera_xyz=rr.ViewCoordinates.RDF,
                    image_plane_distance=0.3,
                ),
                static=True,
            )
        if self.gt is not None:
            xyz = self.gt[1][:, :3, 3].copy()
            xyz[:, 2] = 0.0
            rec.log(
                "world/groundtruth/path",
                rr.LineStrips3D([xyz], colors=TRUTH_COLOUR, radii=rr.Radius.ui_points(1.5)),
                static=True,
            )

    def _set_time(self, result: FrameResult, t: float) -> bool:
        """Put the next rows at the frame's index and at ``t`` on ``time``; False when ``t`` stays off
        ``time`` (on ``frame`` alone): not finite, beyond Rerun's nanosecond range or before the last
        frame's time. A frame the localiser refused for its stamp is still shown, but it must neither
        stop the run nor draw the walk back in time."""
        self.rec.set_time("frame", sequence=int(result.index))
        t = frame_seconds(t)  # a library caller's None too
        if not (math.isfinite(t) and abs(t) < MAX_TIME_S and t >= self._last_t):
            self._on_clock = None
            self._put_on_time(None)
            return False
        self._last_t = self._on_clock = t
        if self.clock == "auto":
            from tagloc.io.fleet import EPOCH_MIN_S

            # Decided once: Rerun keeps one type per timeline. An epoch clock as a duration would read
            # "19675 days" in the viewer.
            self.clock = "timestamp" if t >= EPOCH_MIN_S else "duration"
        self._put_on_time(t)
        return True

    def _put_on_time(self, t: float | None) -> None:
        """Put the next rows at ``t`` (s) on ``time``, as the clock's type, or off it (None)."""
        if t is None:
            self.rec.disable_timeline("time")
        elif self.clock == "duration":
            self.rec.set_time("time", duration=float(t))
        else:
            self.rec.set_time("time", timestamp=float(t))

    def log(self, frame: Frame, result: FrameResult, t: float | None = None) -> None:
        """Log one frame: image, detections, pose, uncertainty, errors and timings.

        ``t``: the frame's place on the ``time`` timeline (default its timestamp; :class:`Outputs`
        gives its published stamp, which carries on after the source's clock is reset)."""
        rr = import_rerun()
        rec = self.rec
        self._set_time(result, result.timestamp if t is None else t)
        out = result.output
        if frame.image is not None:
            self._log_image(frame, result)
        tracking = out.state != TrackState.INITIALISING
        if tracking:
            x, y, yaw = (float(v) for v in out.pose)
            rec.log(
                "world/body",
                rr.Transform3D(
                    translation=[x, y, 0.0], rotation_axis_angle=rr.RotationAxisAngle([0, 0, 1], radians=yaw)
                ),
            )
            piece = self._posed // PATH_PIECE
            self._posed += 1
            if piece != self._piece:
                # Each piece starts at the last point of the previous one so the line has no gaps.
                # The earlier points are in the recording already: kept here, a shift's poses had
                # grown the process by ~110 bytes a frame (95 MB over 8 h at 30 fps).
                self._path, self._piece = self._path[-1:], piece
            self._path.append([x, y, 0.0])
            rec.log(
                f"world/estimate/path/{piece:04d}",
                rr.LineStrips3D([self._path], colors=ESTIMATE_COLOUR, radii=rr.Radius.ui_points(2.0)),
            )
            evals, evecs = np.linalg.eigh(out.cov[:2, :2])
            half = 2.0 * np.sqrt(np.clip(evals, 0.0, None))
            angle = math.atan2(evecs[1, 1], evecs[0, 1])  # direction of the major axis
            rec.log(
                "world/estimate/ellipse",
                rr.Ellipsoids3D(
                    centers=[[x, y, 0.002]],
                    half_sizes=[[half[1], half[0], 1e-4]],
                    rotation_axis_angles=[rr.RotationAxisAngle([0, 0, 1], radians=angle)],
                    colors=ESTIMATE_COLOUR,
                    fill_mode=rr.components.FillMode.MajorWireframe,
                ),
            )
            rec.log("plots/uncertainty/position_2sigma_m", rr.Scalars(float(half[1])))
            rec.log("plots/uncertainty/yaw_sigma_deg", rr.Scalars(math.degrees(math.sqrt(max(out.cov[2, 2], 0.0)))))
            if self.gt is not None:
                self._log_error(result)
        if math.isfinite(out.since_fix):
            rec.log("plots/uncertainty/since_fix_s", rr.Scalars(float(out.since_fix)))
        for stage, ms in result.times_ms.items():
            rec.log(f"plots/timing/{stage}_ms", rr.Scalars(float(ms)))
        if self.gt is not None:
            gt, inside = interpolate_groundtruth(self.gt[0], self.gt[1], np.array([result.timestamp]))
            if inside[0]:
                rec.log(
                    "world/groundtruth/body", rr.Points3D([[gt[0, 0], gt[0, 1], 0.0]], colors=TRUTH_COLOUR, radii=0.04)
                )
        last = "-" if out.last_id is None else f"{out.last_id} ({out.last_source.value if out.last_source else '?'})"
        since = f"{out.since_fix:.2f} s" if math.isfinite(out.since_fix) else "never"
        seen = (
            ", ".join(
                f"{o.sticker_id if o.sticker_id is not None else '?'} {o.source.value}" for o in result.observations
            )
            or "none"
        )
        rec.log(
            "status",
            rr.TextDocument(
                f"**{out.state.value}**  \nframe {result.index}, t = {frame_seconds(result.timestamp):.3f} s  \n"
                f"last fix: {last}, {since} ago  \nseen: {seen}"
                + (f"  \nskipped: {result.skipped}" if result.skipped else ""),
                media_type=rr.MediaType.MARKDOWN,
            ),
        )

    def _log_error(self, result: FrameResult) -> None:
        rr = import_rerun()
        gt, inside = interpolate_groundtruth(self.gt[0], self.gt[1], np.array([result.timestamp]))
        if not inside[0]:
            return
        p = result.output.pose
        self.rec.log("plots/error/position_m", rr.Scalars(float(np.hypot(p[0] - gt[0, 0], p[1] - gt[0, 1]))))
        dyaw = wrap_angle(p[2] - gt[0, 2])
        self.rec.log("plots/error/yaw_deg", rr.Scalars(math.degrees(abs(dyaw))))

    def _log_image(self, frame: Frame, result: FrameResult) -> None:
        rr = import_rerun()
        s = self.image_scale
        img = frame.image
        if s != 1.0:
            img = cv2.resize(img, (round(img.shape[1] * s), round(img.shape[0] * s)), interpolation=cv2.INTER_AREA)
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:  # pragma: no cover - encoding a valid uint8 image does not fail
            return
        entity = image_entity(self.rig, frame.camera)
        self.rec.log(entity, rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg"))
        obs = [o for o in result.observations if o.camera == frame.camera]
        self._shown[frame.camera] = (result.index, self._on_clock, obs)
        self._log_detections(entity, obs)

    def log_late(self, index: int, observations: list[Observation]) -> None:
        """Relabel frame ``index``'s outlines with the stickers its deferred decodes named after the
        frame was logged (live; :attr:`FrameResult.late`), at that frame's place on the timelines.
        Without this a sticker whose fix was fused stays drawn as unidentified."""
        for camera, (shown, t, obs) in self._shown.items():
            late = [o for o in observations if o.camera == camera]
            if shown != index or not late:
                continue
            named = [next((n for n in late if n.detection is o.detection), o) for o in obs]
            self.rec.set_time("frame", sequence=int(index))
            self._put_on_time(t)
            self._shown[camera] = (shown, t, named)
            self._log_detections(image_entity(self.rig, camera), named)

    def _log_detections(self, entity: str, obs: list[Observation]) -> None:
        """The sticker outlines on the image at ``entity``, coloured by identification, with IDs."""
        rr = import_rerun()
        s = self.image_scale
        # Pixel centres sit at integers in OpenCV, so scaling maps p -> (p + 0.5) * s - 0.5.
        strips = [np.vstack([o.detection.outer, o.detection.outer[:1]]) * s + 0.5 * s - 0.5 for o in obs]
        labels = []
        for o in obs:
            text = "?" if o.sticker_id is None else str(o.sticker_id)
            text += f" {o.source.value}"
            if o.accepted is False:
                text += f" (refused: {o.gate_reason})" if o.gate_reason else " (refused)"
            labels.append(text)
        self.rec.log(
            f"{entity}/detections",
            rr.LineStrips2D(
                strips, colors=[SOURCE_COLOURS[o.source] for o in obs], labels=labels, radii=1.5, draw_order=10.0
            )
            if obs
            else rr.Clear(recursive=False),
        )

    def close(self) -> None:
        """Flush everything to the sinks and detach (waiting at most ``NETWORK_FLUSH_S`` for a viewer)."""
        try:
            # A file flushes in full; a viewer that died or never started must not hang the run.
            self.rec.flush(timeout_sec=NETWORK_FLUSH_S if self._network else 1e9)
        except Exception as exc:  # noqa: BLE001 - rerun raises a bare RuntimeError on timeout
            log.warning("Rerun: could not flush everything to the viewer (%s)", exc)
        self.rec.disconnect()


@dataclass
class RrdEntity:
    """What an .rrd holds for one entity: whether static, the frame indices logged, the components."""

    path: str
    static: bool = False
    frames: list[int] = field(default_factory=list)
    components: set[str] = field(default_factory=set)


def read_rrd(path: str | Path) -> dict[str, RrdEntity]:
    """Entities of the first recording in an .rrd file (for tests and checks), keyed by path without the leading /."""
    from rerun.chunk import RrdReader

    out: dict[str, RrdEntity] = {}
    for chunk in RrdReader(str(path)).stream():
        name = chunk.entity_path.lstrip("/")
        ent = out.setdefault(name, RrdEntity(name))
        batch = chunk.to_record_batch()
        ent.components.update(n for n in batch.schema.names if ":" in n)
        if chunk.is_static:
            ent.static = True
        elif "frame" in chunk.timeline_names:
            ent.frames.extend(int(v) for v in batch.column("frame").to_pylist())
    for ent in out.values():
        ent.frames.sort()
    return out
