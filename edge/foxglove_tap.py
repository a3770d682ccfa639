"""Foxglove outputs: a live WebSocket view and MCAP logs of what the localizer sees, and MCAP recordings it replays.

Channels (Foxglove's well-known protobuf schemas, so Foxglove and ROS 2 tooling open them without plugins):

- ``/camera/image`` foxglove.CompressedImage: the network's input (gray, at the bundle's size, undistorted and
  cropped) as JPEG; in a recording (``record --mcap``) the frame as captured, lossless PNG;
- ``/camera/calibration`` foxglove.CameraCalibration of that image (K, P, and D in OpenCV order as ``plumb_bob`` or
  ``rational_polynomial``);
- ``/tf`` foxglove.FrameTransform ``world`` -> ``camera_optical`` and ``/camera/pose`` foxglove.PoseInFrame in
  ``world``: the localized pose;
- ``/camera/trajectory`` foxglove.PosesInFrame: the poses so far (the last ``trail`` of them);
- ``/camera/true_pose`` foxglove.PoseInFrame: the ground truth, when the source has it;
- ``/edge/status`` JSON (edge.outputs.outcome_line: state TRACKING/LOST, inliers, quality, stage timings in ms) and
  ``/edge/log`` foxglove.Log (state changes and the loop's events).

Frames: our pose is camera-to-world with OpenCV axes (x right, y down, z forward) in metres; the camera frame is
therefore published as the *optical* frame ``camera_optical`` (ROS REP 103's ``*_optical`` convention), and the
transform ``world`` -> ``camera_optical`` is T_c2w itself (translation, rotation as a quaternion x, y, z, w).
This module is the only place the pose changes representation.

MCAP files are written beside their path as ``PATH.partial`` and renamed into place when the tap closes (end of
run, Ctrl-C, an exception). The file is chunked and a chunk is closed at least every ``flush_s``: after a hard crash
(power loss, kill -9) ``PATH.partial`` is a readable MCAP without its summary, holding every chunk written up to
then (`mcap recover` or ``iter_mcap(..., stream=True)`` read it).

The per-frame work on the localizer's thread is a hand-off: encoding and logging run on the tap's own thread, fed
by a short queue that drops its oldest frame when full (counted); the WebSocket server drops a slow client's oldest
messages beyond its backlog. foxglove-sdk and mcap are imported lazily (the ``foxglove`` extra).
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob
from acesplat.core.errors import InputError
from acesplat.core.geometry import matrix_to_quat, quat_to_matrix
from acesplat.core.pose import TrackingState
from edge.runtime import FrameOutcome, FrameTap
from edge.sources import SourceFrame

INSTALL_HINT = "pip install 'acesplat-edge[foxglove]'"
WORLD_FRAME = "world"
CAMERA_FRAME = "camera_optical"
"""The camera's optical frame: OpenCV axes (x right, y down, z forward)."""
TOPIC_IMAGE = "/camera/image"
TOPIC_CALIBRATION = "/camera/calibration"
TOPIC_TF = "/tf"
TOPIC_POSE = "/camera/pose"
TOPIC_TRAJECTORY = "/camera/trajectory"
TOPIC_TRUE_POSE = "/camera/true_pose"
TOPIC_STATUS = "/edge/status"
TOPIC_LOG = "/edge/log"
PARTIAL_SUFFIX = ".partial"

STATUS_SCHEMA = {
    "type": "object",
    "title": "acesplat.EdgeStatus",
    "properties": {
        "timestamp_us": {"type": "integer"},
        "frame_id": {"type": "integer"},
        "name": {"type": "string"},
        "T_c2w": {"type": ["array", "null"], "items": {"type": "array", "items": {"type": "number"}}},
        "inliers": {"type": "integer"},
        "quality": {"type": ["number", "null"]},
        "state": {"type": "string", "enum": [s.name for s in TrackingState]},
        "ms": {"type": "object", "additionalProperties": {"type": ["number", "null"]}},
        "alignment": {"type": ["string", "null"]},
    },
}


def require_foxglove() -> Any:
    """The foxglove module, or a one-line InputError naming the extra to install."""
    try:
        import foxglove
        import foxglove.channels  # noqa: F401
        import foxglove.messages  # noqa: F401
        import mcap  # noqa: F401
    except ImportError as e:
        raise InputError(
            None, f"Foxglove output needs foxglove-sdk and mcap ({e.name} missing): {INSTALL_HINT}"
        ) from None
    return foxglove


@dataclass
class FoxgloveSettings:
    """The Foxglove outputs (``--foxglove PORT``, ``--mcap PATH``)."""

    host: str = knob("127.0.0.1", "Address the live server binds (0.0.0.0 to view the robot from another machine).")
    jpeg_quality: int = knob(80, "JPEG quality of the live view and logs (1-100).")
    trail: int = knob(500, "Poses kept in the trajectory message (bounds its size).")
    queue: int = knob(8, "Frames waiting for the tap's thread; beyond, the oldest is dropped (and counted).")
    backlog: int = knob(64, "Messages the server buffers per client; beyond, its oldest are dropped.")
    flush_s: float = knob(1.0, "Close an MCAP chunk at least this often: what a hard crash can lose.")

    def check(self) -> None:
        if not 1 <= self.jpeg_quality <= 100:
            raise InputError(None, f"JPEG quality must be in 1..100, got {self.jpeg_quality}")
        if self.trail < 1 or self.queue < 1 or self.backlog < 1 or not self.flush_s > 0:
            raise InputError(None, "trail, queue and backlog must be positive, and flush_s above 0")


# --------------------------------------------------------------------------------------------- messages
def _stamp(fx: Any, seconds: float) -> Any:
    ns = int(round(seconds * 1e9))
    return fx.messages.Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _pose_parts(m: Any, T: np.ndarray) -> tuple[Any, Any]:
    """foxglove.Vector3 and Quaternion of a camera-to-world (4, 4) matrix: the optical frame's position and
    orientation in world."""
    w, x, y, z = matrix_to_quat(T[:3, :3])
    t = T[:3, 3]
    return (
        m.Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
        m.Quaternion(x=float(x), y=float(y), z=float(z), w=float(w)),
    )


def _pose_msg(m: Any, T: np.ndarray) -> Any:
    """foxglove.Pose of a camera-to-world (4, 4) matrix."""
    position, orientation = _pose_parts(m, T)
    return m.Pose(position=position, orientation=orientation)


def pose_matrix(pose: Any) -> np.ndarray:
    """The (4, 4) camera-to-world matrix of a decoded foxglove.Pose (inverse of the conversion above)."""
    o, p = pose.orientation, pose.position
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(np.array([o.w, o.x, o.y, o.z]))
    T[:3, 3] = [p.x, p.y, p.z]
    return T


def calibration_msg(m: Any, stamp: Any, intr: Intrinsics, distortion: np.ndarray | None) -> Any:
    """foxglove.CameraCalibration of a pinhole camera with OpenCV-ordered distortion (k1 k2 p1 p2 [k3 [k4 k5 k6]])."""
    D = [] if distortion is None else [float(v) for v in np.asarray(distortion).reshape(-1)]
    if D and not any(D):
        D = []
    if D:
        D = D + [0.0] * (5 - len(D)) if len(D) <= 5 else D + [0.0] * (8 - len(D))
        model = "plumb_bob" if len(D) == 5 else "rational_polynomial"
    else:
        model = "plumb_bob"
        D = [0.0] * 5
    K = np.asarray(intr.K, dtype=float)
    P = np.zeros((3, 4))
    P[:, :3] = K
    return m.CameraCalibration(
        timestamp=stamp,
        frame_id=CAMERA_FRAME,
        width=int(intr.width),
        height=int(intr.height),
        distortion_model=model,
        D=D,
        K=K.reshape(-1).tolist(),
        R=np.eye(3).reshape(-1).tolist(),
        P=P.reshape(-1).tolist(),
    )


def encode_image(image: np.ndarray, fmt: str, jpeg_quality: int = 80) -> bytes:
    """JPEG or PNG bytes of an RGB (H, W, 3) or gray (H, W) uint8 image (colour stored as RGB, as Foxglove reads)."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if fmt == "jpeg" else []
    ok, buf = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", image, params)
    if not ok:
        raise ValueError(f"cannot encode a {image.shape} image as {fmt}")
    return buf.tobytes()


def decode_image(data: bytes) -> np.ndarray:
    """RGB (H, W, 3) or gray (H, W) uint8 from JPEG/PNG bytes."""
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError("not a JPEG/PNG image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if img.ndim == 3 else img


# --------------------------------------------------------------------------------------------- sinks
class _Channels:
    """The channels on one foxglove Context (every sink attached to the context gets every message)."""

    def __init__(self, fx: Any, ctx: Any) -> None:
        ch = fx.channels
        self.image = ch.CompressedImageChannel(TOPIC_IMAGE, context=ctx)
        self.calibration = ch.CameraCalibrationChannel(TOPIC_CALIBRATION, context=ctx)
        self.tf = ch.FrameTransformChannel(TOPIC_TF, context=ctx)
        self.pose = ch.PoseInFrameChannel(TOPIC_POSE, context=ctx)
        self.trajectory = ch.PosesInFrameChannel(TOPIC_TRAJECTORY, context=ctx)
        self.true_pose = ch.PoseInFrameChannel(TOPIC_TRUE_POSE, context=ctx)
        self.status = fx.Channel(TOPIC_STATUS, schema=STATUS_SCHEMA, context=ctx)
        self.log = ch.LogChannel(TOPIC_LOG, context=ctx)


class McapFile:
    """An MCAP writer on a foxglove Context, written to ``PATH.partial`` and renamed into place by ``close``."""

    def __init__(self, fx: Any, ctx: Any, path: str | Path) -> None:
        self.path = Path(path)
        if self.path.is_dir():
            raise InputError(self.path, "--mcap needs a file path, this is a folder")
        self.partial = self.path.with_name(self.path.name + PARTIAL_SUFFIX)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.partial, "wb"):
                pass
        except OSError as e:
            raise InputError(self.path, f"cannot write the MCAP file here ({e.strerror})") from None
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        opts = MCAPWriteOptions(compression=MCAPCompression.Lz4, profile="")
        try:
            self.writer = fx.open_mcap(self.partial, allow_overwrite=True, context=ctx, writer_options=opts)
        except Exception as e:
            self.partial.unlink(missing_ok=True)
            raise InputError(self.path, f"cannot write the MCAP file here ({e})") from None
        self._last_flush = time.monotonic()

    def maybe_flush(self, every_s: float) -> None:
        now = time.monotonic()
        if now - self._last_flush >= every_s:
            self.writer.flush()
            self._last_flush = now

    def close(self) -> None:
        if self.writer is None:
            return
        writer, self.writer = self.writer, None
        writer.close()
        os.replace(self.partial, self.path)


def start_live_server(fx: Any, ctx: Any, port: int, settings: FoxgloveSettings) -> Any:
    """foxglove-sdk's WebSocket server on ``port`` (0: any free port), one line if the port is taken."""
    if not 0 <= port <= 65535:
        raise InputError(None, f"--foxglove port must be in 0..65535, got {port}")
    try:
        return fx.start_server(
            name="acesplat-edge", host=settings.host, port=port, context=ctx, message_backlog_size=settings.backlog
        )
    except RuntimeError as e:
        reason = str(e).split(": ", 1)[-1]
        raise InputError(None, f"--foxglove cannot serve on {settings.host}:{port} ({reason})") from None


# --------------------------------------------------------------------------------------------- the tap
class FoxgloveTap(FrameTap):
    """A localizer tap publishing each frame on the Foxglove channels to a live server (``port``) and/or an MCAP
    file (``mcap``); with both, each frame is encoded once for the two."""

    def __init__(
        self, port: int | None = None, mcap: str | Path | None = None, settings: FoxgloveSettings | None = None
    ) -> None:
        if port is None and mcap is None:
            raise ValueError("FoxgloveTap needs a port, an MCAP path, or both")
        self.settings = settings or FoxgloveSettings()
        self.settings.check()
        fx = require_foxglove()
        self._fx, self._m = fx, fx.messages
        self._ctx = fx.Context()
        self.ch = _Channels(fx, self._ctx)
        self.server = start_live_server(fx, self._ctx, port, self.settings) if port is not None else None
        self._port = None if self.server is None else self.server.port
        try:
            self.mcap = McapFile(fx, self._ctx, mcap) if mcap is not None else None
        except BaseException:
            if self.server is not None:
                self.server.stop()
            raise
        self.frames = 0
        self.dropped = 0
        self.errors = 0
        self.last_error = ""
        self.work_ms = 0.0
        self._trail: deque = deque(maxlen=self.settings.trail)
        self._state: int | None = None
        self._queue: deque = deque()
        self._cond = threading.Condition()
        self._closing = False
        self._thread = threading.Thread(target=self._run, name="foxglove-tap", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int | None:
        """The live server's port (the one chosen when asked for 0)."""
        return self._port

    def on_frame(self, out: FrameOutcome) -> None:
        self._put(("frame", out))

    def on_event(self, event: Any) -> None:
        self._put(("event", event))

    def _put(self, item: tuple) -> None:
        with self._cond:
            if self._closing:
                return
            if len(self._queue) >= self.settings.queue:
                self._queue.popleft()
                self.dropped += 1
            self._queue.append(item)
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                if not self._queue and not self._closing:
                    self._cond.wait(self.settings.flush_s)
                item = self._queue.popleft() if self._queue else None
                if item is None and self._closing:
                    return
            try:
                if item is not None:
                    t0 = time.perf_counter()
                    if item[0] == "frame":
                        self.publish(item[1])
                        self.frames += 1
                    else:
                        self._log_event(item[1])
                    self.work_ms += (time.perf_counter() - t0) * 1000.0
                if self.mcap is not None:
                    self.mcap.maybe_flush(self.settings.flush_s)
            except Exception as e:  # a failing output must not stop localization
                self.errors += 1
                self.last_error = f"{type(e).__name__}: {e}"

    def publish(self, out: FrameOutcome) -> None:
        """Log one outcome on every channel (the tap's thread calls this; synchronous, for tests and benches)."""
        m, ch = self._m, self.ch
        rec = out.record
        ts = rec.timestamp_us / 1e6
        stamp = _stamp(self._fx, ts)
        image, intr, dist = out.gray, out.intrinsics, None
        if image is None and out.frame is not None:
            image, intr, dist = out.frame.image, out.frame.intrinsics, out.frame.distortion
        if image is not None:
            data = encode_image(image, "jpeg", self.settings.jpeg_quality)
            if intr is not None:
                ch.calibration.log(calibration_msg(m, stamp, intr, dist))
            ch.image.log(m.CompressedImage(timestamp=stamp, frame_id=CAMERA_FRAME, data=data, format="jpeg"))
        T = np.asarray(rec.T_c2w, dtype=float)
        if rec.state == TrackingState.TRACKING and np.all(np.isfinite(T)):  # a pose the gate refused is not drawn
            position, orientation = _pose_parts(m, T)
            pose = m.Pose(position=position, orientation=orientation)
            ch.tf.log(
                m.FrameTransform(
                    timestamp=stamp,
                    parent_frame_id=WORLD_FRAME,
                    child_frame_id=CAMERA_FRAME,
                    translation=position,
                    rotation=orientation,
                )
            )
            ch.pose.log(m.PoseInFrame(timestamp=stamp, frame_id=WORLD_FRAME, pose=pose))
            self._trail.append(pose)
            ch.trajectory.log(m.PosesInFrame(timestamp=stamp, frame_id=WORLD_FRAME, poses=list(self._trail)))
        if out.gt_pose is not None:
            ch.true_pose.log(m.PoseInFrame(timestamp=stamp, frame_id=WORLD_FRAME, pose=_pose_msg(m, out.gt_pose)))
        from edge.outputs import outcome_line

        ch.status.log(outcome_line(out))
        if rec.state != self._state:
            name = TrackingState(rec.state).name
            level = m.LogLevel.Info if rec.state == TrackingState.TRACKING else m.LogLevel.Warning
            ch.log.log(m.Log(timestamp=stamp, level=level, message=f"{name} at frame {rec.frame_id}", name="edge"))
            self._state = rec.state

    def _log_event(self, e: Any) -> None:
        m = self._m
        level = m.LogLevel.Warning if e.kind in ("disconnected", "skipped") else m.LogLevel.Info
        text = f"{e.kind}: {e.detail}" + (f" (gap {e.gap_s:.1f} s)" if getattr(e, "gap_s", None) else "")
        self.ch.log.log(m.Log(timestamp=_stamp(self._fx, time.time()), level=level, message=text, name="edge"))
        if e.kind == "disconnected":
            self._state = None

    def close(self, timeout: float = 10.0) -> dict:
        """Publish what is queued, finalize and rename the MCAP file, stop the server; the counters."""
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self._thread.join(timeout)
        try:
            if self.mcap is not None:
                self.mcap.close()
        finally:
            if self.server is not None:
                self.server.stop()
        report = {"frames": self.frames, "dropped": self.dropped, "errors": self.errors}
        if self.frames:
            report["ms_per_frame"] = round(self.work_ms / self.frames, 3)
        if self.last_error:
            report["last_error"] = self.last_error
        if self.mcap is not None:
            report["mcap"] = str(self.mcap.path)
        if self.server is not None:
            report["port"] = self._port
        return report


# --------------------------------------------------------------------------------------------- recordings
class McapRecorder:
    """Writes frames as captured (lossless PNG, their calibration and true pose) for ``replay:PATH.mcap``."""

    def __init__(self, path: str | Path) -> None:
        fx = require_foxglove()
        self._fx, self._m = fx, fx.messages
        self._ctx = fx.Context()
        ch = fx.channels
        self.image = ch.CompressedImageChannel(TOPIC_IMAGE, context=self._ctx)
        self.calibration = ch.CameraCalibrationChannel(TOPIC_CALIBRATION, context=self._ctx)
        self.true_pose = ch.PoseInFrameChannel(TOPIC_TRUE_POSE, context=self._ctx)
        self.file = McapFile(fx, self._ctx, path)
        self.flush_s = FoxgloveSettings().flush_s

    def write(self, f: SourceFrame) -> None:
        m = self._m
        stamp = _stamp(self._fx, f.timestamp)
        if f.intrinsics is not None:
            self.calibration.log(calibration_msg(m, stamp, f.intrinsics, f.distortion))
        if f.gt_pose is not None:
            self.true_pose.log(m.PoseInFrame(timestamp=stamp, frame_id=WORLD_FRAME, pose=_pose_msg(m, f.gt_pose)))
        data = encode_image(f.image, "png")
        self.image.log(m.CompressedImage(timestamp=stamp, frame_id=CAMERA_FRAME, data=data, format="png"))
        self.file.maybe_flush(self.flush_s)

    def close(self) -> None:
        self.file.close()


def _protobuf_decoder_factory() -> Any:
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from mcap.decoder import DecoderFactory

    class ProtobufDecoder(DecoderFactory):
        def __init__(self) -> None:
            self._cache: dict[int, Any] = {}

        def decoder_for(self, message_encoding: str, schema: Any) -> Any:
            if message_encoding == "json":
                return lambda data: json.loads(data)
            if message_encoding != "protobuf" or schema is None or schema.encoding != "protobuf":
                return None
            if schema.id not in self._cache:
                fds = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
                pool = descriptor_pool.DescriptorPool()
                pending = list(fds.file)
                while pending:  # dependencies first, in whatever order the set lists them
                    left = []
                    for fd in pending:
                        try:
                            pool.Add(fd)
                        except TypeError:
                            left.append(fd)
                    if len(left) == len(pending):
                        raise ValueError(f"schema {schema.name}: unresolvable protobuf dependencies")
                    pending = left
                cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
                self._cache[schema.id] = cls.FromString
            return self._cache[schema.id]

    return ProtobufDecoder()


def iter_mcap(path: str | Path, topics: list[str] | None = None, stream: bool = False) -> Iterator[tuple[str, Any]]:
    """(topic, decoded message) in file order: protobuf messages as protobuf objects, JSON ones as dicts.

    ``stream`` reads without the summary (a ``.partial`` file left by a crash, up to its last whole chunk).
    """
    require_foxglove()
    from mcap.exceptions import EndOfFile
    from mcap.reader import NonSeekingReader, make_reader

    with open(path, "rb") as f:
        factory = [_protobuf_decoder_factory()]
        if stream:
            reader = NonSeekingReader(f, decoder_factories=factory, record_size_limit=None)
        else:
            reader = make_reader(f, decoder_factories=factory)
        it = reader.iter_decoded_messages(topics=topics, log_time_order=False)
        try:
            for _schema, channel, _message, decoded in it:
                yield channel.topic, decoded
        except EndOfFile:
            if not stream:
                raise  # a finalized file does not end early; a crashed one ends at its last whole record


class McapReplaySource:
    """Frames from an MCAP file's ``/camera/image`` (with ``/camera/calibration`` and ``/camera/true_pose`` of the
    same timestamp when present): what ``record --mcap`` or ``--mcap`` wrote.

    ``realtime`` replays at the recorded timestamps; otherwise frames come as fast as they are asked for.
    """

    def __init__(
        self, path: str | Path, calibration: Any = None, realtime: bool = False, clock=time.monotonic, sleep=time.sleep
    ) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(self.path, "replay MCAP file does not exist")
        require_foxglove()
        try:
            self._count = self._image_count()
        except Exception as e:
            raise InputError(self.path, f"not a readable MCAP file ({e})") from None
        self.calibration = calibration
        self.description = f"replay:{self.path}"
        self.live = realtime
        self._clock, self._sleep = clock, sleep
        self._it = iter_mcap(self.path, [TOPIC_IMAGE, TOPIC_CALIBRATION, TOPIC_TRUE_POSE])
        self._calib: tuple[int, Any] | None = None
        self._pose: tuple[int, Any] | None = None
        self._i = 0
        self._t0: tuple[float, float] | None = None

    def _image_count(self) -> int:
        from mcap.reader import make_reader

        with open(self.path, "rb") as f:
            summary = make_reader(f).get_summary()
        if summary is None or summary.statistics is None:
            raise ValueError("no summary: finalize it first (mcap recover)")
        ids = [c.id for c in summary.channels.values() if c.topic == TOPIC_IMAGE]
        return sum(summary.statistics.channel_message_counts.get(i, 0) for i in ids)

    def __len__(self) -> int:
        return self._count

    def read(self) -> SourceFrame | None:
        for topic, msg in self._it:
            ns = msg.timestamp.seconds * 1_000_000_000 + msg.timestamp.nanos
            if topic == TOPIC_CALIBRATION:
                self._calib = (ns, msg)
            elif topic == TOPIC_TRUE_POSE:
                self._pose = (ns, msg)
            elif topic == TOPIC_IMAGE:
                return self._frame(ns, msg)
        return None

    def _frame(self, ns: int, msg: Any) -> SourceFrame:
        i = self._i
        self._i += 1
        ts = ns / 1e9
        if self.live:
            if self._t0 is None:
                self._t0 = (self._clock(), ts)
            wait = self._t0[0] + (ts - self._t0[1]) - self._clock()
            if wait > 0:
                self._sleep(wait)
        from edge.sources import UnreadableFrame

        try:
            image = decode_image(msg.data)
        except ValueError as e:
            raise UnreadableFrame(f"{self.path.name}#{i}", str(e)) from None
        h, w = image.shape[:2]
        intr, dist = None, None
        if self._calib is not None:
            c = self._calib[1]
            K = np.asarray(c.K, dtype=float).reshape(3, 3)
            intr = Intrinsics.from_K(K, int(c.width), int(c.height))
            if (intr.width, intr.height) != (w, h):
                intr = intr.resized(w, h)
            dist = np.asarray(c.D, dtype=float) if any(c.D) else None
        elif self.calibration is not None:
            intr, dist = self.calibration.intrinsics_for(w, h), self.calibration.distortion
        gt = pose_matrix(self._pose[1].pose) if self._pose is not None and self._pose[0] == ns else None
        return SourceFrame(image, ts, intr, i, f"{i:06d}", dist, gt)

    def reconnect(self) -> None:
        return None

    def close(self) -> None:
        self._it.close()
