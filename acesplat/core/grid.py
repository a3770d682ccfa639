"""The SCR output grid: where each predicted scene coordinate sits in the network's input image.

One cell per ``OUTPUT_STRIDE`` pixels (or ``DENSE_OUTPUT_STRIDE`` for the dense prediction); every consumer (PnP,
mapping targets, alignment, Gaussian seeding, the edge) reads cell positions from here.
"""

from __future__ import annotations

import numpy as np

from acesplat.core.geometry import invert_pose
from acesplat.core.pose_refine import reprojection

OUTPUT_STRIDE = 8
"""SCR predictions are made for every 8th pixel; cell (i, j) belongs to pixel (8 j + 4, 8 i + 4)."""
DENSE_OUTPUT_STRIDE = 4
"""A dense prediction (half the cell spacing) has cell (i, j) at pixel (4 j + 4, 4 i + 4): its even cells are the
stride-8 cells, its odd ones those of the image shifted by half a cell."""
STRIDES = (OUTPUT_STRIDE, DENSE_OUTPUT_STRIDE)


def cell_centers(grid_h: int, grid_w: int, stride: int = OUTPUT_STRIDE) -> np.ndarray:
    """Pixel coordinates (grid_h * grid_w, 2) of the prediction cells, row-major, for a grid spaced ``stride``
    pixels apart (OUTPUT_STRIDE or DENSE_OUTPUT_STRIDE): cell k at stride * k + OUTPUT_STRIDE / 2."""
    check_stride(stride)
    ys, xs = np.mgrid[0:grid_h, 0:grid_w]
    half = OUTPUT_STRIDE / 2.0
    return np.stack([xs.ravel() * stride + half, ys.ravel() * stride + half], axis=1).astype(np.float64)


def check_stride(stride: int) -> int:
    """``stride`` if it is a stride the SCR network predicts at; ValueError otherwise."""
    if stride not in STRIDES:
        raise ValueError(f"stride must be {OUTPUT_STRIDE} or {DENSE_OUTPUT_STRIDE}, got {stride}")
    return stride


def grid_correspondences(coords: np.ndarray, stride: int = OUTPUT_STRIDE) -> tuple[np.ndarray, np.ndarray]:
    """Scene points (h * w, 3) and their cells' pixels (h * w, 2) of a coordinate grid (3, h, w) or (h, w, 3)."""
    coords = np.asarray(coords)
    if coords.ndim != 3:
        raise ValueError(f"coordinate grid must be 3-D, got shape {coords.shape}")
    if coords.shape[0] == 3 and coords.shape[2] != 3:
        coords = np.moveaxis(coords, 0, -1)
    h, w, _ = coords.shape
    return coords.reshape(-1, 3), cell_centers(h, w, stride)


def cell_reprojection_errors(
    coords: np.ndarray, pose_c2w: np.ndarray, K: np.ndarray, stride: int = OUTPUT_STRIDE
) -> np.ndarray:
    """Pixel distance (h * w,) between each cell and its coordinate (h, w, 3) projected by the camera ``pose_c2w``
    (4, 4) with intrinsics K (3, 3); inf behind the camera, NaN where the coordinate is NaN (so never within a
    threshold)."""
    points, pixels = grid_correspondences(coords, stride)
    w2c = invert_pose(pose_c2w)
    return reprojection(points.astype(np.float64), pixels, K, w2c[:3, :3], w2c[:3, 3])[2]
