"""Frame sources behind one small interface: ``read()`` gives the next frame, None at the end.

A frame carries the image, a timestamp, the intrinsics of that image (when known), distortion, and
a ground-truth pose when the source has one. Sources raise ``UnreadableFrame`` for one bad frame
(the runtime skips and counts it) and ``SourceDisconnected`` when a device vanished (the runtime
calls ``reconnect()`` with backoff). Specs: ``replay:DIR``, ``replay:FILE.mcap`` (edge.foxglove_tap),
``video:FILE``, ``camera:N``, ``oak``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob
from acesplat.core.errors import InputError
from acesplat.core.scene import find_split, list_split, read_calibration, read_matrix, read_pose, read_rgb
from edge.calibration import CameraCalibration, read_calibration_file

TIMESTAMPS_FILE = "timestamps.txt"
DISTORTION_FILE = "distortion.txt"
INTRINSICS_NAMES = (
    "intrinsics.json",
    "intrinsics.yaml",
    "intrinsics.yml",
    "intrinsics.xml",
    "intrinsics.txt",
    "calibration.txt",
    "calibration.json",
    "calibration.yaml",
)


@dataclass
class SourceFrame:
    """One captured image: RGB (H, W, 3) or grayscale (H, W) uint8, with what is known about it."""

    image: np.ndarray
    timestamp: float
    """Seconds on the source's clock (recorded time for replays, device or monotonic time for cameras)."""
    intrinsics: Intrinsics | None
    frame_id: int
    name: str = ""
    distortion: np.ndarray | None = None
    gt_pose: np.ndarray | None = None


class UnreadableFrame(Exception):
    """One frame could not be decoded; the source has moved past it."""

    def __init__(self, name: str, reason: str) -> None:
        super().__init__(f"{name}: {reason}")
        self.name = name
        self.reason = reason


class SourceDisconnected(Exception):
    """The device stopped delivering frames; ``reconnect()`` may bring it back."""


class FrameSource(Protocol):
    live: bool
    """Frames arrive in real time whether or not we keep up (the runtime drops rather than queues)."""
    description: str

    def read(self) -> SourceFrame | None: ...

    def reconnect(self) -> None: ...

    def close(self) -> None: ...


# --------------------------------------------------------------------------------------------- replay
def read_timestamps(path: Path, names: list[str]) -> list[float]:
    """``timestamps.txt``: one line per frame, either 'seconds' or 'name seconds', in name order."""
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    if len(lines) != len(names):
        raise InputError(path, f"{len(lines)} timestamps but {len(names)} images")
    out = []
    for ln, name in zip(lines, names):
        try:
            if len(ln) == 2:
                if ln[0] != name:
                    raise InputError(path, f"timestamp line for '{ln[0]}' where '{name}' was expected")
                out.append(float(ln[1]))
            elif len(ln) == 1:
                out.append(float(ln[0]))
            else:
                raise ValueError
        except ValueError:
            raise InputError(path, f"cannot parse timestamp line {' '.join(ln)!r}") from None
    return out


def resolve_replay_dir(path: Path) -> Path:
    """A split folder, a scene (its test split, else train), or a plain folder of images (acesplat.core.scene)."""
    if not path.is_dir():
        raise InputError(path, "replay folder does not exist")
    return find_split(path)


class ReplaySource:
    """Frames from disk in name order: the ACE layout or what `record` writes, or a folder of images plus one
    intrinsics file.

    ``realtime`` replays at the recorded timestamps (frames are then dropped when processing is slower);
    otherwise frames come as fast as they are asked for.
    """

    def __init__(
        self,
        path: str | Path,
        calibration: CameraCalibration | None = None,
        realtime: bool = False,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        root = resolve_replay_dir(Path(path))
        self.root = root
        self.description = f"replay:{root}"
        self.live = realtime
        self._clock, self._sleep = clock, sleep
        files = list_split(root)
        self.images = files.images
        names = [p.stem for p in self.images]
        self.poses: list[Path] | None = files.poses
        self.calibs: list[Path] | None = None
        self.calibration = calibration
        if calibration is None:
            if files.calibrations is not None:
                self.calibs = files.calibrations
            else:
                for n in INTRINSICS_NAMES:
                    if (root / n).is_file():
                        self.calibration = read_calibration_file(root / n)
                        break
        self.distortion = None
        if (root / DISTORTION_FILE).is_file():
            d = read_matrix(root / DISTORTION_FILE).reshape(-1)
            self.distortion = d
        elif self.calibration is not None:
            self.distortion = self.calibration.distortion
        ts_path = root / TIMESTAMPS_FILE
        self.timestamps = read_timestamps(ts_path, names) if ts_path.is_file() else None
        if realtime and self.timestamps is None:
            raise InputError(ts_path, "--realtime replays at recorded timestamps, but the folder has none")
        self._i = 0
        self._t0_wall: float | None = None

    def __len__(self) -> int:
        return len(self.images)

    def _intrinsics(self, i: int, w: int, h: int) -> Intrinsics | None:
        if self.calibs is not None:
            return read_calibration(self.calibs[i], w, h)
        if self.calibration is not None:
            return self.calibration.intrinsics_for(w, h)
        return None

    def read(self) -> SourceFrame | None:
        if self._i >= len(self.images):
            return None
        i = self._i
        self._i += 1
        path = self.images[i]
        if self.live and self.timestamps is not None:
            if self._t0_wall is None:
                self._t0_wall = self._clock() - self.timestamps[i] + self.timestamps[0]
            wait = self._t0_wall + (self.timestamps[i] - self.timestamps[0]) - self._clock()
            if wait > 0:
                self._sleep(wait)
        try:
            rgb = read_rgb(path)
        except InputError as e:
            raise UnreadableFrame(path.name, e.problem) from None
        h, w = rgb.shape[:2]
        ts = self.timestamps[i] if self.timestamps is not None else self._clock()
        gt = read_pose(self.poses[i]) if self.poses is not None else None
        return SourceFrame(rgb, ts, self._intrinsics(i, w, h), i, path.stem, self.distortion, gt)

    def reconnect(self) -> None:  # files do not disconnect
        return None

    def close(self) -> None:
        return None


# --------------------------------------------------------------------------------------------- video
class VideoSource:
    """A video file decoded by OpenCV; timestamps from the container."""

    live = False

    def __init__(self, path: str | Path, calibration: CameraCalibration | None) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(self.path, "video file does not exist")
        self.cap = cv2.VideoCapture(str(self.path))
        if not self.cap.isOpened():
            raise InputError(self.path, "OpenCV cannot open this video")
        self.calibration = calibration
        self.description = f"video:{self.path}"
        self._i = 0
        fps = float(self.cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self._period = 1.0 / fps if fps > 0 else 1.0 / 30.0

    def read(self) -> SourceFrame | None:
        ok, bgr = self.cap.read()
        if not ok or bgr is None:
            return None
        i = self._i
        self._i += 1
        ts = float(self.cap.get(cv2.CAP_PROP_POS_MSEC)) / 1000.0
        if ts <= 0.0 and i > 0:  # a container without stamps: the frame index at the stream's rate
            ts = i * self._period
        h, w = bgr.shape[:2]
        intr = self.calibration.intrinsics_for(w, h) if self.calibration else None
        dist = self.calibration.distortion if self.calibration else None
        return SourceFrame(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), ts, intr, i, f"{i:06d}", dist)

    def reconnect(self) -> None:
        return None

    def close(self) -> None:
        self.cap.release()


# --------------------------------------------------------------------------------------------- camera
def _open_v4l2(index: int) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(index, cv2.CAP_V4L2)
    if not cap.isOpened():
        cap.release()
        cap = cv2.VideoCapture(index)
    return cap


class CameraSource:
    """A live OpenCV/V4L2 camera; a failed read means the device vanished."""

    live = True

    def __init__(
        self,
        index: int,
        calibration: CameraCalibration | None,
        opener: Callable[[int], cv2.VideoCapture] = _open_v4l2,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.index = index
        self.calibration = calibration
        self.description = f"camera:{index}"
        self._opener, self._clock = opener, clock
        self.cap = opener(index)
        if not self.cap.isOpened():
            raise InputError(None, f"camera {index} cannot be opened (not connected, or busy)")
        self._i = 0

    def read(self) -> SourceFrame | None:
        if self.cap is None:
            raise SourceDisconnected(self.description)
        ok, bgr = self.cap.read()
        if not ok or bgr is None:
            raise SourceDisconnected(f"{self.description}: read failed")
        ts = self._clock()
        i = self._i
        self._i += 1
        h, w = bgr.shape[:2]
        intr = self.calibration.intrinsics_for(w, h) if self.calibration else None
        dist = self.calibration.distortion if self.calibration else None
        image = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB) if bgr.ndim == 3 else bgr
        return SourceFrame(image, ts, intr, i, f"{i:06d}", dist)

    def reconnect(self) -> None:
        if self.cap is not None:
            self.cap.release()
        self.cap = self._opener(self.index)
        if not self.cap.isOpened():
            self.cap.release()
            self.cap = None
            raise SourceDisconnected(f"{self.description}: still gone")

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()
            self.cap = None


# --------------------------------------------------------------------------------------------- open
@dataclass
class SourceOptions:
    """How a source is opened (``open_source``)."""

    calibration: CameraCalibration | None = knob(None, "Calibration for sources without one (--intrinsics).")
    input_size: tuple[int, int] | None = knob(None, "(H, W) the consumer wants; an OAK resizes on the device.")
    realtime: bool = knob(False, "Replay at the recorded timestamps (drops frames when slower).")
    extra: dict = knob(reason="Source-specific settings.", factory=dict)


def open_source(spec: str, opts: SourceOptions) -> FrameSource:
    """Parse ``replay:DIR``, ``replay:FILE.mcap``, ``video:FILE``, ``camera:N`` or ``oak[:crop|stretch|letterbox]``
    and open it."""
    kind, _, arg = spec.partition(":")
    kind = kind.lower()
    if kind == "replay":
        if not arg:
            raise InputError(None, "replay source needs a folder: replay:DIR")
        if arg.lower().endswith(".mcap"):
            from edge.foxglove_tap import McapReplaySource

            return McapReplaySource(arg, opts.calibration, realtime=opts.realtime)
        return ReplaySource(arg, opts.calibration, realtime=opts.realtime)
    if kind == "video":
        if not arg:
            raise InputError(None, "video source needs a file: video:FILE")
        if opts.calibration is None:
            raise InputError(Path(arg), "video source needs --intrinsics FILE")
        return VideoSource(arg, opts.calibration)
    if kind == "camera":
        try:
            index = int(arg or "0")
        except ValueError:
            raise InputError(None, f"camera source needs a device number: camera:N, got {spec!r}") from None
        return CameraSource(index, opts.calibration)
    if kind == "oak":
        from edge.oak import OakSource

        if opts.input_size is None:
            raise InputError(None, "oak source needs the bundle's input size")
        return OakSource(opts.input_size, resize_mode=arg or "crop", calibration=opts.calibration)
    raise InputError(None, f"unknown source {spec!r}: use replay:DIR, replay:FILE.mcap, video:FILE, camera:N or oak")
