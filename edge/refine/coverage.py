"""Where a view needs new Gaussians: what the current map covers, and how well it explains the image.

Two measures. ``analyse_render`` looks at an actual render (alpha and photometric error per pixel) and
gives the pixel mask to seed. ``projected_coverage`` is a cheap stand-in used for keyframe selection
before anything is rendered: the share of the view's cells that some Gaussian centre projects into,
at a depth consistent with the SCR prediction of that cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import invert_pose

ALPHA_MIN = 0.5
"""Below this accumulated opacity a pixel is not covered by the map."""
ERROR_MAX = 0.15
"""Mean absolute RGB error (0..1) above which a covered pixel is badly explained."""
DEPTH_RATIO = 1.25
"""A Gaussian centre counts for a cell when its depth is within this ratio of the cell's SCR depth."""


@dataclass(frozen=True)
class RenderAnalysis:
    """need (H, W) bool pixels to seed; coverage = mean(alpha >= ALPHA_MIN); mse of the render over all pixels."""

    need: np.ndarray
    coverage: float
    mse: float
    mean_abs_error: float


def analyse_render(
    color: np.ndarray, alpha: np.ndarray, target: np.ndarray, alpha_min: float = ALPHA_MIN, error_max: float = ERROR_MAX
) -> RenderAnalysis:
    """color (H, W, 3) and alpha (H, W) of a render, target (H, W, 3) in [0, 1]."""
    color = np.asarray(color)
    if color.ndim != 3 or color.shape[2] != 3 or alpha.shape != color.shape[:2] or target.shape != color.shape:
        raise ValueError(
            f"need color (H, W, 3), alpha (H, W), target (H, W, 3); got {color.shape}, {alpha.shape}, {target.shape}"
        )
    diff = np.asarray(color, np.float32) - np.asarray(target, np.float32)
    err = np.abs(diff).mean(axis=2)
    covered = alpha >= alpha_min
    need = ~covered | (err > error_max)
    return RenderAnalysis(
        need=need, coverage=float(covered.mean()), mse=float(np.mean(diff * diff)), mean_abs_error=float(err.mean())
    )


def camera_points(means: np.ndarray, pose_c2w: np.ndarray) -> np.ndarray:
    """World points (N, 3) in the camera frame of ``pose_c2w``."""
    w2c = invert_pose(np.asarray(pose_c2w, np.float64))
    return np.asarray(means, np.float64) @ w2c[:3, :3].T + w2c[:3, 3]


def frustum_mask(
    means: np.ndarray,
    log_scales: np.ndarray,
    pose_c2w: np.ndarray,
    k: Intrinsics,
    near: float = 0.01,
    sigmas: float = 3.0,
) -> np.ndarray:
    """Gaussians (N,) that can touch the image: in front of the camera and within ``sigmas`` of their
    largest scale of the image rectangle (a conservative test, so rendering only these changes nothing).

    float32 arithmetic with one temporary per quantity: it runs on the whole map several times per
    keyframe (bench/refine.md)."""
    w2c = invert_pose(np.asarray(pose_c2w, np.float64)).astype(np.float32)
    X = np.asarray(means, np.float32) @ w2c[:3, :3].T
    X += w2c[:3, 3]
    z = X[:, 2]
    r = np.exp(np.max(np.asarray(log_scales, np.float32), axis=1)) * np.float32(sigmas)
    front = z > near
    inv = np.float32(1.0) / np.where(front, z, np.float32(1.0))
    ru = (k.fx * r) * inv + 1.0
    u = (k.fx * X[:, 0]) * inv + k.cx
    inside = np.abs(u - (k.width - 1) / 2.0) < (k.width / 2.0 + ru)
    rv = (k.fy * r) * inv + 1.0
    v = (k.fy * X[:, 1]) * inv + k.cy
    inside &= np.abs(v - (k.height - 1) / 2.0) < (k.height / 2.0 + rv)
    # A Gaussian straddling the camera plane is kept: its projection is unbounded.
    return (front & inside) | ((~front) & (z + r > near))


def projected_coverage(
    means: np.ndarray,
    pose_c2w: np.ndarray,
    k: Intrinsics,
    cell_depth: np.ndarray,
    stride: int = 8,
    depth_ratio: float = DEPTH_RATIO,
) -> float:
    """Share of the cells (h, w) with a finite positive SCR depth ``cell_depth`` that receive a Gaussian
    centre at a consistent depth. ``k`` is the intrinsics of the image the cells tile (cell size ``stride``)."""
    h, w = cell_depth.shape
    ok = np.isfinite(cell_depth) & (cell_depth > 0)
    if not ok.any():
        return 0.0
    X = camera_points(means, pose_c2w)
    z = X[:, 2]
    front = z > 1e-6
    zs = np.where(front, z, 1.0)
    col = np.floor((k.fx * X[:, 0] / zs + k.cx + 0.5) / stride).astype(np.int64)
    row = np.floor((k.fy * X[:, 1] / zs + k.cy + 0.5) / stride).astype(np.int64)
    inb = front & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    col, row, z = col[inb], row[inb], z[inb]
    d = np.where(ok, cell_depth, np.nan)[row, col]
    good = np.isfinite(d) & (z <= d * depth_ratio) & (z >= d / depth_ratio)
    hit = np.zeros((h, w), bool)
    hit[row[good], col[good]] = True
    return float(hit[ok].mean())
