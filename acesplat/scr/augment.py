"""Mapping-time augmentation: ACE's rescale, in-plane rotation, brightness and contrast.

The rotation is applied as the homography K Rz K^-1, which is exact for any principal point and
aspect ratio, and the pose is rotated with it so every pixel keeps its true scene coordinate.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.grid import OUTPUT_STRIDE

SCALE_MIN = 2.0 / 3.0
SCALE_MAX = 3.0 / 2.0
ROTATION_MAX_DEG = 15.0
BRIGHTNESS = 0.1
CONTRAST = 0.1


@dataclass(frozen=True)
class AugmentRanges:
    """Geometric ranges of one augmentation preset; brightness and contrast are always varied."""

    scale_range: tuple[float, float]
    rotation_deg: float


AUGMENT_PRESETS = {
    "ace": AugmentRanges((SCALE_MIN, SCALE_MAX), ROTATION_MAX_DEG),
    "photometric": AugmentRanges((1.0, 1.0), 0.0),
}
"""ACE's ranges, and brightness/contrast only (the views as the camera took them)."""


def augment_ranges(preset: str) -> AugmentRanges:
    """The ranges of a preset by name; ValueError naming the choices otherwise."""
    if preset not in AUGMENT_PRESETS:
        raise ValueError(f"augment must be one of {', '.join(sorted(AUGMENT_PRESETS))}, got {preset!r}")
    return AUGMENT_PRESETS[preset]


@dataclass
class AugmentedView:
    """An augmented grayscale image (H, W) with its intrinsics, pose and per-cell validity (H/8, W/8).

    ``pixel_map`` (3, 3) takes homogeneous pixels of the original image to the augmented one.
    """

    gray: np.ndarray
    intrinsics: Intrinsics
    c2w: np.ndarray
    cell_valid: np.ndarray
    pixel_map: np.ndarray


def rotation_z(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def cell_validity(mask: np.ndarray, stride: int = OUTPUT_STRIDE) -> np.ndarray:
    """A cell is valid when its whole stride x stride patch holds real image content."""
    h, w = mask.shape
    gh, gw = -(-h // stride), -(-w // stride)
    padded = np.zeros((gh * stride, gw * stride), dtype=mask.dtype)
    padded[:h, :w] = mask
    return padded.reshape(gh, stride, gw, stride).min(axis=(1, 3)) > 0


def augment(
    gray: np.ndarray,
    intrinsics: Intrinsics,
    c2w: np.ndarray,
    rng: np.random.Generator,
    scale_range: tuple[float, float] = (SCALE_MIN, SCALE_MAX),
    rotation_deg: float = ROTATION_MAX_DEG,
    brightness: float = BRIGHTNESS,
    contrast: float = CONTRAST,
) -> AugmentedView:
    """One random augmentation of a grayscale uint8 image (H, W)."""
    h, w = gray.shape
    s = rng.uniform(*scale_range)
    nh, nw = max(8, int(round(h * s))), max(8, int(round(w * s)))
    img = cv2.resize(gray, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    intr = intrinsics.resized(nw, nh)
    Rz = rotation_z(np.radians(rng.uniform(-rotation_deg, rotation_deg)))
    K = intr.K
    H = K @ Rz @ np.linalg.inv(K)
    img = cv2.warpPerspective(img, H, (nw, nh), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    mask = cv2.warpPerspective(
        np.ones((nh, nw), np.uint8), H, (nw, nh), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    )
    # New camera coordinates are Rz times the old ones: w2c' = Rz w2c, so c2w' = c2w Rz^T.
    Rz4 = np.eye(4)
    Rz4[:3, :3] = Rz.T
    c2w_aug = c2w @ Rz4
    b = rng.uniform(1 - brightness, 1 + brightness)
    c = rng.uniform(1 - contrast, 1 + contrast)
    f = img.astype(np.float32) * b
    mean = f[mask > 0].mean() if mask.any() else 0.0
    f = (f - mean) * c + mean
    img = np.clip(f, 0, 255).astype(np.uint8) * mask
    sx, sy = nw / w, nh / h
    S = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
    return AugmentedView(img, intr, c2w_aug, cell_validity(mask), H @ S)
