"""Pinhole camera intrinsics: one record, rescaled at the edges when images are resized."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of an image of ``width`` x ``height`` pixels (principal point in pixels)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        """The 3x3 calibration matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int) -> Intrinsics:
        K = np.asarray(K, dtype=np.float64)
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height))

    @classmethod
    def from_focal(cls, f: float, width: int, height: int) -> Intrinsics:
        """ACE's single-focal calibration: square pixels, principal point at the image centre."""
        return cls(float(f), float(f), width / 2.0, height / 2.0, int(width), int(height))

    def resized(self, width: int, height: int) -> Intrinsics:
        """Intrinsics of the same camera after resizing the image to ``width`` x ``height``.

        Uses the pixel-corner convention (a pixel centre at i + 0.5 maps to (i + 0.5) * s).
        """
        sx = width / self.width
        sy = height / self.height
        return Intrinsics(
            self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5, int(width), int(height)
        )

    def pixels_to(self, pixels: np.ndarray, other: Intrinsics) -> np.ndarray:
        """Pixels (N, 2) of this image at the same rays in ``other``, an image of the same camera (resized or
        cropped): u' = fx' (u - cx) / fx + cx', v' likewise."""
        uv = np.asarray(pixels, dtype=np.float64)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ValueError(f"pixels must be (N, 2), got {uv.shape}")
        sx, sy = other.fx / self.fx, other.fy / self.fy
        return np.stack([(uv[:, 0] - self.cx) * sx + other.cx, (uv[:, 1] - self.cy) * sy + other.cy], axis=1)

    def project(self, X_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) of camera-frame points ``X_cam`` (N, 3)."""
        z = X_cam[:, 2:3]
        return np.concatenate([self.fx * X_cam[:, 0:1] / z + self.cx, self.fy * X_cam[:, 1:2] / z + self.cy], axis=1)

    def unproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) at pixels ``uv`` (N, 2) with z-depth ``depth`` (N,)."""
        x = (uv[:, 0] - self.cx) / self.fx * depth
        y = (uv[:, 1] - self.cy) / self.fy * depth
        return np.stack([x, y, depth], axis=1)
