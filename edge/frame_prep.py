"""Captured frame -> the network's grayscale input and the intrinsics of that input.

Order: undistort (at the capture resolution, maps cached per camera), centre-crop to the bundle's
aspect ratio when it differs (so the network never sees a stretched image), then the shared
``to_gray_input`` resize the desktop path uses, so edge and desktop feed identical pixels.
"""

from __future__ import annotations

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.preprocess import to_gray_input

ASPECT_TOLERANCE = 0.01


def crop_to_aspect(image: np.ndarray, intr: Intrinsics, aspect_wh: float) -> tuple[np.ndarray, Intrinsics]:
    """Centre crop of ``image`` with width / height = ``aspect_wh`` (whole pixels) and the shifted principal point."""
    h, w = image.shape[:2]
    if abs((w / h) / aspect_wh - 1.0) <= ASPECT_TOLERANCE:
        return image, intr
    if w / h > aspect_wh:
        cw, ch = int(round(h * aspect_wh)), h
    else:
        cw, ch = w, int(round(w / aspect_wh))
    x0, y0 = (w - cw) // 2, (h - ch) // 2
    out = Intrinsics(intr.fx, intr.fy, intr.cx - x0, intr.cy - y0, cw, ch)
    return image[y0 : y0 + ch, x0 : x0 + cw], out


class FramePrep:
    """Prepares frames for a bundle input size (H, W); caches undistortion maps per (K, distortion, size)."""

    def __init__(self, input_size: tuple[int, int]) -> None:
        self.input_size = (int(input_size[0]), int(input_size[1]))
        self._maps_key: tuple | None = None
        self._maps: tuple[np.ndarray, np.ndarray] | None = None

    def _undistort(self, gray: np.ndarray, intr: Intrinsics, dist: np.ndarray) -> np.ndarray:
        key = (
            intr.fx,
            intr.fy,
            intr.cx,
            intr.cy,
            intr.width,
            intr.height,
            tuple(np.asarray(dist).reshape(-1).tolist()),
        )
        if key != self._maps_key:
            self._maps = cv2.initUndistortRectifyMap(
                intr.K, np.asarray(dist, np.float64), None, intr.K, (intr.width, intr.height), cv2.CV_16SC2
            )
            self._maps_key = key
        return cv2.remap(gray, self._maps[0], self._maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    def __call__(
        self, image: np.ndarray, intr: Intrinsics, dist: np.ndarray | None = None
    ) -> tuple[np.ndarray, Intrinsics]:
        """Grayscale uint8 (H, W) at the input size and its pinhole intrinsics (distortion removed)."""
        if image.ndim not in (2, 3) or image.dtype != np.uint8:
            raise ValueError(f"frame must be uint8 (H, W) or (H, W, 3), got {image.dtype} {image.shape}")
        if (intr.width, intr.height) != (image.shape[1], image.shape[0]):
            raise ValueError(
                f"intrinsics are for {intr.width}x{intr.height}, frame is {image.shape[1]}x{image.shape[0]}"
            )
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        if dist is not None and np.any(np.asarray(dist) != 0):
            gray = self._undistort(gray, intr, dist)
        h, w = self.input_size
        gray, intr = crop_to_aspect(gray, intr, w / h)
        return to_gray_input(gray, intr, self.input_size)
