"""SCR coordinates (one per 8x8 cell of the SCR output grid) brought to pixel resolution, torch-free.

Interpolating the 3D coordinates themselves would put pixels that straddle a depth edge on a
straight line between foreground and background, off every pixel's ray. Instead each cell's
camera-frame depth is interpolated bilinearly (the same half-pixel alignment as the feature
adapter) and every pixel is unprojected along its own ray with the known pose, so a centre always
reprojects onto its pixel and only its distance comes from the SCR prediction. Where the cells that
feed a pixel disagree in depth by more than a ratio, the pixel is marked as an edge. Invalid cells
take no part: depth is interpolated over the valid ones.

Two samplers share that recipe. :func:`pixel_coordinates` (Stage 2) works at the network's input resolution in
float64, the edge test over the 2x2 cells each pixel is interpolated from. :func:`pixel_depths` (the edge) works at
any resolution of the same image (refinement runs at the camera's, not the network's), with OpenCV's float32
resize, and tests edges over each cell's 3x3 neighbourhood so it needs no per-pixel corner bookkeeping.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import distance_transform_edt

from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob_default
from acesplat.core.geometry import invert_pose
from acesplat.core.grid import OUTPUT_STRIDE
from acesplat.splatcore.validity import ValidityConfig, cell_trust

MIN_VALID_WEIGHT = 0.5
"""A pixel needs valid cells to carry at least this share of its bilinear interpolation weight."""


def _axis_weights(n_out: int, n_in: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices i0, i1 (n_out,) and weight of i1 for x8 bilinear upsampling with half-pixel centres.

    Stage 2 lifts the SCR's stride-8 cells (never the dense grid of `acesplat eval --dense`). Matches torch's
    ``interpolate(..., align_corners=False)``: source = (dst + 0.5) / 8 - 0.5,
    clamped at 0 below and at the last cell above.
    """
    src = np.maximum((np.arange(n_out) + 0.5) / OUTPUT_STRIDE - 0.5, 0.0)
    i0 = np.minimum(np.floor(src).astype(np.int64), n_in - 1)
    i1 = np.minimum(i0 + 1, n_in - 1)
    return i0, i1, src - i0


def _corners(values: np.ndarray, height: int, width: int):
    """The four cells (each (height, width)) every pixel is interpolated from, and the weights of the
    second row (height, 1) and second column (1, width)."""
    h, w = values.shape
    s = OUTPUT_STRIDE
    if not (s * (h - 1) < height <= s * h and s * (w - 1) < width <= s * w):
        raise ValueError(f"a {h}x{w} cell grid (stride {OUTPUT_STRIDE}) does not cover a {height}x{width} image")
    y0, y1, wy = _axis_weights(height, h)
    x0, x1, wx = _axis_weights(width, w)
    corners = (values[y0][:, x0], values[y0][:, x1], values[y1][:, x0], values[y1][:, x1])
    return corners, wy[:, None], wx[None, :]


def upsample_cells(values: np.ndarray, height: int, width: int) -> np.ndarray:
    """Bilinear x8 upsampling of per-cell values (h, w) to (height, width)."""
    (a, b, c, d), wy, wx = _corners(values, height, width)
    return (1 - wy) * ((1 - wx) * a + wx * b) + wy * ((1 - wx) * c + wx * d)


def corner_range(values: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Min and max (height, width) over the (up to 4) cells each pixel is interpolated from."""
    (a, b, c, d), _, _ = _corners(values, height, width)
    return np.minimum(np.minimum(a, b), np.minimum(c, d)), np.maximum(np.maximum(a, b), np.maximum(c, d))


def cell_depths(coords: np.ndarray, pose_c2w: np.ndarray) -> np.ndarray:
    """Camera-frame z (h, w) of scene coordinates ``coords`` (h, w, 3) seen from ``pose_c2w``."""
    w2c = invert_pose(pose_c2w)
    return np.einsum("hwj,j->hw", coords, w2c[2, :3]) + w2c[2, 3]


def pixel_rays(intrinsics: Intrinsics) -> np.ndarray:
    """Camera-frame ray directions with z = 1 (H, W, 3) through the pixel centres (integer coordinates)."""
    k = intrinsics
    u, v = np.meshgrid(np.arange(k.width, dtype=np.float64), np.arange(k.height, dtype=np.float64))
    return np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], axis=-1)


def pixel_coordinates(
    coords: np.ndarray, cell_valid: np.ndarray, pose_c2w: np.ndarray, intrinsics: Intrinsics, max_depth_ratio: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World centres (H, W, 3), camera depths (H, W) and validity (H, W) at pixel resolution.

    coords (h, w, 3) SCR coordinates of the cells of an image of ``intrinsics``' size; cell_valid
    (h, w) which cells to trust. Depth is interpolated from the valid cells only (weights renormalised);
    a pixel is valid when valid cells carry at least half of its interpolation weight (MIN_VALID_WEIGHT)
    and their depths agree within ``max_depth_ratio`` (max / min).
    """
    if coords.ndim != 3 or coords.shape[2] != 3 or cell_valid.shape != coords.shape[:2]:
        raise ValueError(f"coords must be (h, w, 3) and cell_valid (h, w), got {coords.shape} and {cell_valid.shape}")
    H, W = intrinsics.height, intrinsics.width
    z = cell_depths(np.asarray(coords, np.float64), pose_c2w)
    ok = np.asarray(cell_valid, bool) & np.isfinite(z) & (z > 0)
    okf = ok.astype(np.float64)
    zw = upsample_cells(np.where(ok, z, 0.0), H, W)
    weight = upsample_cells(okf, H, W)
    z_lo, _ = corner_range(np.where(ok, z, np.inf), H, W)
    _, z_hi = corner_range(np.where(ok, z, 0.0), H, W)
    valid = (weight >= MIN_VALID_WEIGHT) & (z_hi <= max_depth_ratio * z_lo)
    depth = np.where(valid, zw / np.maximum(weight, 1e-12), 0.0)
    X_cam = pixel_rays(intrinsics) * depth[..., None]
    pose = np.asarray(pose_c2w, np.float64)
    centres = X_cam @ pose[:3, :3].T + pose[:3, 3]
    return centres, depth, valid


def filled_depths(
    coords: np.ndarray, cell_valid: np.ndarray, pose_c2w: np.ndarray, intrinsics: Intrinsics
) -> tuple[np.ndarray, np.ndarray]:
    """Stand-in world centres (H, W, 3) and depths (H, W) for pixels whose own cells are not trusted.

    Every cell takes the depth of its nearest trusted cell and every pixel the depth of the cell it
    lies in (no interpolation, so no pixel lands between two surfaces); centres stay on their pixels'
    rays. All zeros if no cell is trusted.
    """
    H, W = intrinsics.height, intrinsics.width
    z = cell_depths(np.asarray(coords, np.float64), pose_c2w)
    ok = np.asarray(cell_valid, bool) & np.isfinite(z) & (z > 0)
    if not ok.any():
        return np.zeros((H, W, 3)), np.zeros((H, W))
    _, (iy, ix) = distance_transform_edt(~ok, return_indices=True)
    z_full = z[iy, ix]
    rows = np.minimum(np.arange(H) // OUTPUT_STRIDE, z.shape[0] - 1)
    cols = np.minimum(np.arange(W) // OUTPUT_STRIDE, z.shape[1] - 1)
    depth = z_full[rows][:, cols]
    X_cam = pixel_rays(intrinsics) * depth[..., None]
    pose = np.asarray(pose_c2w, np.float64)
    return X_cam @ pose[:3, :3].T + pose[:3, 3], depth


@dataclass(frozen=True)
class PixelDepths:
    """Per-pixel camera depth (H, W), world centres (H, W, 3) and validity (H, W) at one resolution."""

    depth: np.ndarray
    centres: np.ndarray
    valid: np.ndarray


def pixel_depths(
    coords: np.ndarray,
    pose_c2w: np.ndarray,
    k_input: Intrinsics,
    k_out: Intrinsics,
    max_depth_ratio: float = knob_default(ValidityConfig, "max_depth_ratio"),
) -> PixelDepths:
    """Depths and centres at the resolution of ``k_out`` (the input image rescaled) from the SCR cells
    ``coords`` (h, w, 3) of the input image of ``k_input`` (trusted cells: :func:`cell_trust`)."""
    z, ok = cell_trust(coords, pose_c2w, k_input)
    h, w = z.shape
    s = OUTPUT_STRIDE
    if not (s * (h - 1) < k_input.height <= s * h and s * (w - 1) < k_input.width <= s * w):
        raise ValueError(f"a {h}x{w} cell grid does not tile a {k_input.height}x{k_input.width} input image")
    size = (k_out.width, k_out.height)
    # The grid spans OUTPUT_STRIDE * (w, h) input pixels; resize maps it onto the output image with half-pixel
    # centres when the output has the input's aspect (crop the overhang of a rounded-up grid first).
    sx, sy = k_out.width / k_input.width, k_out.height / k_input.height
    full = (int(round(s * w * sx)), int(round(s * h * sy)))
    okf = ok.astype(np.float32)
    zw = cv2.resize(np.where(ok, z, 0.0).astype(np.float32), full, interpolation=cv2.INTER_LINEAR)[: size[1], : size[0]]
    wt = cv2.resize(okf, full, interpolation=cv2.INTER_LINEAR)[: size[1], : size[0]]
    kernel = np.ones((3, 3), np.uint8)
    z_lo = cv2.erode(np.where(ok, z, np.inf).astype(np.float32), kernel, borderType=cv2.BORDER_REPLICATE)
    z_hi = cv2.dilate(np.where(ok, z, 0.0).astype(np.float32), kernel, borderType=cv2.BORDER_REPLICATE)
    ratio = cv2.resize(z_hi / np.maximum(z_lo, 1e-6), full, interpolation=cv2.INTER_NEAREST)[: size[1], : size[0]]
    valid = (wt >= MIN_VALID_WEIGHT) & (ratio <= max_depth_ratio)
    depth = np.where(valid, zw / np.maximum(wt, 1e-6), 0.0).astype(np.float64)
    X_cam = pixel_rays(k_out) * depth[..., None]
    pose = np.asarray(pose_c2w, np.float64)
    return PixelDepths(depth=depth, centres=X_cam @ pose[:3, :3].T + pose[:3, 3], valid=valid)
