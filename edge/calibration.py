"""Camera calibration files for live sources: K (or one focal length), the image size it is for, distortion.

Formats: ACE text (one focal length or a 3x3 K), JSON ({fx, fy, cx, cy, width, height, distortion}
or {K, width, height, distortion}), and OpenCV YAML/XML (camera_matrix, distortion_coefficients,
image_width, image_height) as written by OpenCV's calibration tools.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.errors import InputError

ASPECT_TOLERANCE = 0.01
"""Relative aspect-ratio difference accepted when rescaling intrinsics to a frame of another size."""


@dataclass(frozen=True)
class CameraCalibration:
    """Pinhole K for an image of ``size`` (W, H) (None: the frames' own size) and optional distortion (OpenCV order)."""

    K: np.ndarray | None = None
    focal: float | None = None
    size: tuple[int, int] | None = None
    distortion: np.ndarray | None = None
    source: str = ""

    def intrinsics_for(self, width: int, height: int) -> Intrinsics:
        """Intrinsics of a frame of ``width`` x ``height``; rescaled when the calibration was made at another
        resolution."""
        if self.K is None:
            return Intrinsics.from_focal(float(self.focal), width, height)
        if self.size is None:
            intr = Intrinsics.from_K(self.K, width, height)
            if not (0 <= intr.cx <= width and 0 <= intr.cy <= height):
                raise InputError(
                    self.source or None,
                    f"principal point ({intr.cx:.1f}, {intr.cy:.1f}) lies outside the {width}x{height} frame: "
                    "calibration is for another image size",
                )
            return intr
        cw, ch = self.size
        intr = Intrinsics.from_K(self.K, cw, ch)
        if (cw, ch) == (width, height):
            return intr
        if abs((width / height) / (cw / ch) - 1.0) > ASPECT_TOLERANCE:
            raise InputError(
                self.source or None,
                f"frame is {width}x{height} but the calibration is for {cw}x{ch} (different aspect ratio)",
            )
        return intr.resized(width, height)

    @property
    def has_distortion(self) -> bool:
        return self.distortion is not None and bool(np.any(self.distortion != 0))


def _dist(values, path: Path) -> np.ndarray | None:
    if values is None:
        return None
    d = np.asarray(values, dtype=np.float64).reshape(-1)
    if d.size not in (4, 5, 8, 12, 14):
        raise InputError(path, f"distortion needs 4, 5, 8, 12 or 14 coefficients (OpenCV order), found {d.size}")
    if not np.all(np.isfinite(d)):
        raise InputError(path, "distortion has non-finite entries")
    return d


def _check_K(K: np.ndarray, path: Path) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(path, f"camera matrix needs finite positive focal lengths, got fx={K[0, 0]} fy={K[1, 1]}")
    return K


def _size(w, h, path: Path) -> tuple[int, int] | None:
    if w is None and h is None:
        return None
    try:
        w, h = int(w), int(h)
    except (TypeError, ValueError):
        raise InputError(path, "calibration needs both width and height (or neither)") from None
    if w <= 0 or h <= 0:
        raise InputError(path, f"calibration image size must be positive, got {w}x{h}")
    return w, h


def read_calibration_file(path: str | Path) -> CameraCalibration:
    """A calibration from any of the supported formats (chosen by suffix)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "intrinsics file does not exist")
    suffix = path.suffix.lower()
    if suffix == ".json":
        try:
            obj = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise InputError(path, f"not valid JSON ({e})") from None
        if not isinstance(obj, dict):
            raise InputError(path, "JSON intrinsics must be an object")
        try:
            if "K" in obj:
                K = _check_K(np.asarray(obj["K"], dtype=np.float64), path)
            else:
                K = _check_K(np.array([[obj["fx"], 0, obj["cx"]], [0, obj["fy"], obj["cy"]], [0, 0, 1]], float), path)
        except (KeyError, ValueError, TypeError):
            raise InputError(path, "JSON intrinsics need K (3x3) or fx, fy, cx, cy") from None
        dist = _dist(obj.get("distortion", obj.get("dist")), path)
        return CameraCalibration(
            K=K, size=_size(obj.get("width"), obj.get("height"), path), distortion=dist, source=str(path)
        )
    if suffix in (".yaml", ".yml", ".xml"):
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        if not fs.isOpened():
            raise InputError(path, "OpenCV cannot parse this YAML/XML file")
        try:
            K = fs.getNode("camera_matrix").mat()
            if K is None:
                raise InputError(path, "no camera_matrix in the OpenCV calibration file")
            d = fs.getNode("distortion_coefficients").mat()
            wn, hn = fs.getNode("image_width"), fs.getNode("image_height")
            size = _size(int(wn.real()), int(hn.real()), path) if not wn.empty() and not hn.empty() else None
        finally:
            fs.release()
        return CameraCalibration(K=_check_K(K, path), size=size, distortion=_dist(d, path), source=str(path))
    try:
        values = np.loadtxt(path, dtype=np.float64, ndmin=1).reshape(-1)
    except (ValueError, OSError) as e:
        raise InputError(path, f"cannot parse numbers ({e})") from None
    if not np.all(np.isfinite(values)):
        raise InputError(path, "calibration has non-finite entries")
    if values.size == 1:
        if values[0] <= 0:
            raise InputError(path, f"focal length must be positive, got {values[0]}")
        return CameraCalibration(focal=float(values[0]), source=str(path))
    if values.size == 9:
        return CameraCalibration(K=_check_K(values, path), source=str(path))
    raise InputError(path, f"calibration needs 1 number (focal) or 9 (3x3 K), found {values.size}")
