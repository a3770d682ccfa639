"""Image preparation for the SCR network, shared by desktop and edge so both feed it identical pixels."""

from __future__ import annotations

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics


def size_for_short_side(height: int, width: int, short_side: int) -> tuple[int, int]:
    """(H, W) of an image rescaled so its shorter side is ``short_side`` (aspect ratio kept)."""
    s = short_side / min(height, width)
    return max(1, int(round(height * s))), max(1, int(round(width * s)))


def to_gray_input(rgb: np.ndarray, intrinsics: Intrinsics, size_hw: tuple[int, int]) -> tuple[np.ndarray, Intrinsics]:
    """RGB uint8 (H, W, 3) -> grayscale uint8 (h, w) at ``size_hw`` and the matching intrinsics."""
    h, w = size_hw
    gray = rgb if rgb.ndim == 2 else cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    if gray.shape != (h, w):
        shrinking = h < gray.shape[0]
        gray = cv2.resize(gray, (w, h), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)
    return gray, intrinsics.resized(w, h)
