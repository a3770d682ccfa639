"""Which SCR predictions to trust as Gaussian centres, torch-free.

A cell's scene coordinate is kept when it is finite, lies within a plausible depth range in front of
the camera, and reprojects (with the known pose) close to the pixel it was predicted for. The last
test is the map agreeing with the images: on training views a good map passes almost everywhere,
a map of another scene (or one built from differently sized images) almost nowhere.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import invert_pose

from .pixel_coords import STRIDE

DEPTH_MIN_M = 0.05
DEPTH_MAX_M = 200.0
REPROJ_MAX_PX = 8.0
"""Reprojection tolerance in pixels of the map's input image: one cell (ACE's PnP inlier threshold is 10 px)."""
MAX_DEPTH_RATIO = 1.25
"""Pixels interpolated from cells whose depths differ by more than this ratio straddle an edge."""


@dataclass(frozen=True)
class ValidityConfig:
    depth_min: float = DEPTH_MIN_M
    depth_max: float = DEPTH_MAX_M
    reproj_max_px: float = REPROJ_MAX_PX
    max_depth_ratio: float = MAX_DEPTH_RATIO

    def __post_init__(self) -> None:
        if not (0 < self.depth_min < self.depth_max) or self.reproj_max_px <= 0 or self.max_depth_ratio < 1:
            raise ValueError(f"invalid ValidityConfig {self}")

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class CellValidity:
    """Per-cell verdicts (h, w) bool; ``valid`` is their conjunction."""

    finite: np.ndarray
    in_depth_range: np.ndarray
    reprojects: np.ndarray
    valid: np.ndarray

    @property
    def fraction(self) -> float:
        return float(self.valid.mean()) if self.valid.size else 0.0


def cell_pixels(h: int, w: int) -> np.ndarray:
    """Pixel (u, v) (h, w, 2) each cell's coordinate is trained to reproject to: (8j + 4, 8i + 4)."""
    ys, xs = np.mgrid[0:h, 0:w]
    return np.stack([xs * STRIDE + STRIDE / 2.0, ys * STRIDE + STRIDE / 2.0], axis=-1).astype(np.float64)


def cell_validity(
    coords: np.ndarray, pose_c2w: np.ndarray, intrinsics: Intrinsics, cfg: ValidityConfig = ValidityConfig()
) -> CellValidity:
    """Validity of SCR coordinates ``coords`` (h, w, 3) predicted for an image of ``intrinsics``' size
    seen from camera-to-world ``pose_c2w`` (4, 4)."""
    coords = np.asarray(coords, np.float64)
    if coords.ndim != 3 or coords.shape[2] != 3:
        raise ValueError(f"coords must have shape (h, w, 3), got {coords.shape}")
    h, w = coords.shape[:2]
    finite = np.all(np.isfinite(coords), axis=-1)
    w2c = invert_pose(pose_c2w)
    Xc = np.where(finite[..., None], coords, 0.0) @ w2c[:3, :3].T + w2c[:3, 3]
    z = Xc[..., 2]
    in_range = finite & (z >= cfg.depth_min) & (z <= cfg.depth_max)
    z_safe = np.where(in_range, z, 1.0)
    k = intrinsics
    uv = np.stack([k.fx * Xc[..., 0] / z_safe + k.cx, k.fy * Xc[..., 1] / z_safe + k.cy], axis=-1)
    err = np.linalg.norm(uv - cell_pixels(h, w), axis=-1)
    reprojects = in_range & (err <= cfg.reproj_max_px)
    return CellValidity(finite=finite, in_depth_range=in_range, reprojects=reprojects, valid=reprojects.copy())
