"""Luxonis OAK cameras through the depthai v3 API (an optional extra, imported only when used).

The device resizes to the bundle's input size itself (``Camera.requestOutput``), so the host gets
frames ready for the network. The intrinsics follow the resize mode: CROP cuts the sensor image to
the output aspect ratio then scales, STRETCH scales each axis on its own, LETTERBOX scales to fit
and pads; each gives a different K, computed here from the calibration stored on the device.
A missing, unplugged or silent device (no frame within ``FRAME_TIMEOUT_S``) raises ``SourceDisconnected``,
which the loop answers with ``reconnect()``.
"""

from __future__ import annotations

import datetime
from typing import Any

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.errors import InputError
from edge.calibration import CameraCalibration
from edge.sources import SourceDisconnected, SourceFrame

RESIZE_MODES = ("crop", "stretch", "letterbox")
FRAME_TIMEOUT_S = 2.0
"""A running device silent this long is reported lost (the loop then reconnects with backoff)."""
FIRST_FRAME_TIMEOUT_S = 10.0
"""The first frame after a (re)start may wait for the sensor and auto-exposure to come up."""


def resize_intrinsics(K: np.ndarray, sensor_wh: tuple[int, int], out_wh: tuple[int, int], mode: str) -> Intrinsics:
    """K of the device output (W, H) from the calibration K of the full sensor image ``sensor_wh``.

    Pixel-corner convention as in Intrinsics.resized: a centre at i + 0.5 maps to (i + 0.5) * s + offset.
    """
    if mode not in RESIZE_MODES:
        raise InputError(None, f"resize mode must be one of {RESIZE_MODES}, got {mode!r}")
    W0, H0 = sensor_wh
    W, H = out_wh
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if mode == "stretch":
        sx, sy, ox, oy = W / W0, H / H0, 0.0, 0.0
        crop_x = crop_y = 0.0
    elif mode == "crop":
        s = max(W / W0, H / H0)  # scale so the output is covered, then cut the overflow evenly
        sx = sy = s
        crop_x, crop_y = (W0 * s - W) / 2.0, (H0 * s - H) / 2.0
        ox, oy = -crop_x, -crop_y
    else:  # letterbox
        s = min(W / W0, H / H0)
        sx = sy = s
        ox, oy = (W - W0 * s) / 2.0, (H - H0 * s) / 2.0
    return Intrinsics(fx * sx, fy * sy, (cx + 0.5) * sx - 0.5 + ox, (cy + 0.5) * sy - 0.5 + oy, int(W), int(H))


def import_depthai() -> Any:
    try:
        import depthai  # noqa: PLC0415  (optional extra)
    except ImportError:
        raise InputError(None, "the oak source needs depthai v3: pip install 'acesplat-edge[oak]'") from None
    if not hasattr(depthai, "node") or not hasattr(depthai.node, "Camera"):
        raise InputError(None, "the oak source needs the depthai v3 API (Camera node); upgrade depthai")
    return depthai


class OakSource:
    """An OAK camera delivering frames at ``size_hw`` (H, W); ``dai`` may be passed in (tests use a fake)."""

    live = True

    def __init__(
        self,
        size_hw: tuple[int, int],
        resize_mode: str = "crop",
        socket: str = "CAM_A",
        fps: float = 30.0,
        calibration: CameraCalibration | None = None,
        dai: Any = None,
        frame_timeout_s: float = FRAME_TIMEOUT_S,
        first_frame_timeout_s: float = FIRST_FRAME_TIMEOUT_S,
    ) -> None:
        if resize_mode not in RESIZE_MODES:
            raise InputError(None, f"oak resize mode must be one of {RESIZE_MODES}, got {resize_mode!r}")
        if not (frame_timeout_s > 0 and first_frame_timeout_s > 0):
            raise InputError(None, f"oak frame timeouts must be > 0, got {frame_timeout_s}, {first_frame_timeout_s}")
        self.dai = dai if dai is not None else import_depthai()
        if not hasattr(self.dai.CameraBoardSocket, socket):
            raise InputError(None, f"no OAK camera socket {socket!r} (CAM_A, CAM_B, ...)")
        self.size_hw = size_hw
        self.resize_mode = resize_mode
        self.socket_name = socket
        self.fps = fps
        self.override = calibration
        self.frame_timeout_s = float(frame_timeout_s)
        self.first_frame_timeout_s = float(first_frame_timeout_s)
        self._timeout_s = self.first_frame_timeout_s
        self.description = f"oak:{resize_mode}"
        self.pipeline: Any = None
        self.queue: Any = None
        self.intrinsics: Intrinsics | None = None
        self.distortion: np.ndarray | None = None
        self._i = 0
        try:
            self._start()
        except SourceDisconnected as e:
            raise InputError(None, f"no OAK device available ({e})") from None

    def _start(self) -> None:
        dai = self.dai
        h, w = self.size_hw
        socket = getattr(dai.CameraBoardSocket, self.socket_name)
        pipeline = None
        try:
            pipeline = dai.Pipeline()  # opens the first available device; RuntimeError when there is none
            cam = pipeline.create(dai.node.Camera).build(socket)
            mode = getattr(dai.ImgResizeMode, self.resize_mode.upper())
            out = cam.requestOutput((w, h), type=dai.ImgFrame.Type.BGR888i, resizeMode=mode, fps=self.fps)
            queue = out.createOutputQueue(maxSize=1, blocking=False)
            pipeline.start()
            calib = None if self.override is not None else pipeline.getDefaultDevice().readCalibration()
        except self._device_errors() as e:
            if pipeline is not None:
                self._stop(pipeline)
            raise SourceDisconnected(f"{type(e).__name__}: {e}") from None
        if self.override is not None:
            intr = self.override.intrinsics_for(w, h)
            dist = self.override.distortion
        else:
            try:
                K0, W0, H0 = calib.getDefaultIntrinsics(socket)
                dist = np.asarray(calib.getDistortionCoefficients(socket), dtype=np.float64)
            except RuntimeError as e:  # the device's EEPROM has no calibration for this socket
                self._stop(pipeline)
                raise InputError(None, f"OAK {self.socket_name}: {e}; pass the intrinsics with --intrinsics") from None
            intr = resize_intrinsics(np.asarray(K0, dtype=np.float64), (int(W0), int(H0)), (w, h), self.resize_mode)
        self.pipeline, self.queue = pipeline, queue
        self.intrinsics, self.distortion = intr, dist
        self._timeout_s = self.first_frame_timeout_s

    def _device_errors(self) -> tuple[type[BaseException], ...]:
        """What depthai raises for a missing, lost or silent device: RuntimeError (XLinkError derives from it) and a
        closed queue's ``MessageQueue.QueueException`` (derives from Exception only)."""
        return (RuntimeError, self.dai.MessageQueue.QueueException)

    def read(self) -> SourceFrame | None:
        if self.pipeline is None:
            raise SourceDisconnected(self.description)
        try:
            if not self.pipeline.isRunning():
                raise SourceDisconnected(f"{self.description}: pipeline stopped")
            msg = self.queue.get(datetime.timedelta(seconds=self._timeout_s))
            if msg is None:  # get(timeout) gives None when no frame came in time
                raise SourceDisconnected(f"{self.description}: no frame for {self._timeout_s:g} s")
            bgr = msg.getCvFrame()
            ts = msg.getTimestamp().total_seconds()
            seq = int(msg.getSequenceNum())
        except self._device_errors() as e:
            raise SourceDisconnected(f"{self.description}: {type(e).__name__}: {e}") from None
        self._timeout_s = self.frame_timeout_s
        self._i += 1
        image = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB) if bgr.ndim == 3 else bgr
        return SourceFrame(image, ts, self.intrinsics, seq, f"{seq:06d}", self.distortion)

    def reconnect(self) -> None:
        self.close()
        self._start()

    def _stop(self, pipeline: Any) -> None:
        """Stop ``pipeline`` and release its device so the next ``dai.Pipeline()`` can open it again."""
        try:
            pipeline.stop()
        except self._device_errors():
            pass
        try:
            pipeline.getDefaultDevice().close()
        except self._device_errors():
            pass

    def close(self) -> None:
        if self.pipeline is not None:
            pipeline, self.pipeline, self.queue = self.pipeline, None, None
            self._stop(pipeline)
