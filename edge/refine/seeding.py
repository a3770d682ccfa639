"""New Gaussians for the pixels a keyframe needs, placed at the SCR scene coordinates.

The SCR network predicts one scene coordinate per 8x8 cell. Interpolating 3D points across a depth
edge would put Gaussians between foreground and background, off every pixel's ray, so each cell's
camera depth is interpolated instead (bilinear, half-pixel centres, renormalised over the trusted
cells) and each pixel is unprojected along its own ray with the keyframe's pose. Pixels whose
neighbouring cells disagree in depth by more than a ratio straddle an edge and are not seeded.

(acesplat/splat/pixel_coords.py does the same for Stage 2 on the desktop; the edge cannot import the
torch package it lives in, and needs it at an arbitrary refinement resolution.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.gaussians import Gaussians, logit, rgb_to_sh_dc
from edge.refine.coverage import camera_points

STRIDE = 8
DEPTH_RANGE_M = (0.05, 200.0)
REPROJ_MAX_PX = 8.0
"""A cell is trusted when its coordinate reprojects within one cell of where it was predicted (input pixels)."""
MAX_DEPTH_RATIO = 1.25
MIN_VALID_WEIGHT = 0.5
SCALE_PRIOR = 0.7
"""New Gaussians' standard deviation in units of the spacing between seeded pixels (at their depth)."""
OPACITY_PRIOR = 0.7
BLOCK_SIGMA = 0.4
"""A Gaussian standing for a spacing x spacing block takes the block's colour (blur sigma in spacings)."""


@dataclass(frozen=True)
class PixelDepths:
    """Per-pixel camera depth (H, W), world centres (H, W, 3) and validity (H, W) at one resolution."""

    depth: np.ndarray
    centres: np.ndarray
    valid: np.ndarray


def cell_trust(coords: np.ndarray, pose_c2w: np.ndarray, k_input: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Camera depths (h, w) of SCR coordinates ``coords`` (h, w, 3) and which cells to trust.

    ``k_input`` are the intrinsics of the network's input image (cells tile it with STRIDE px).
    """
    coords = np.asarray(coords, np.float64)
    if coords.ndim != 3 or coords.shape[2] != 3:
        raise ValueError(f"coords must have shape (h, w, 3), got {coords.shape}")
    h, w = coords.shape[:2]
    finite = np.all(np.isfinite(coords), axis=2)
    X = camera_points(np.where(finite[..., None], coords, 0.0).reshape(-1, 3), pose_c2w).reshape(h, w, 3)
    z = X[..., 2]
    ok = finite & (z >= DEPTH_RANGE_M[0]) & (z <= DEPTH_RANGE_M[1])
    zs = np.where(ok, z, 1.0)
    u = k_input.fx * X[..., 0] / zs + k_input.cx
    v = k_input.fy * X[..., 1] / zs + k_input.cy
    ys, xs = np.mgrid[0:h, 0:w]
    err = np.hypot(u - (xs * STRIDE + STRIDE / 2.0), v - (ys * STRIDE + STRIDE / 2.0))
    ok &= err <= REPROJ_MAX_PX
    return np.where(ok, z, np.nan), ok


def pixel_depths(
    coords: np.ndarray,
    pose_c2w: np.ndarray,
    k_input: Intrinsics,
    k_out: Intrinsics,
    max_depth_ratio: float = MAX_DEPTH_RATIO,
) -> PixelDepths:
    """Depths and centres at the resolution of ``k_out`` (the input image rescaled) from cells of the input image."""
    z, ok = cell_trust(coords, pose_c2w, k_input)
    h, w = z.shape
    if not (STRIDE * (h - 1) < k_input.height <= STRIDE * h and STRIDE * (w - 1) < k_input.width <= STRIDE * w):
        raise ValueError(f"a {h}x{w} cell grid does not tile a {k_input.height}x{k_input.width} input image")
    size = (k_out.width, k_out.height)
    # The grid spans STRIDE * (w, h) input pixels; resize maps it onto the output image with half-pixel
    # centres when the output has the input's aspect (crop the overhang of a rounded-up grid first).
    sx, sy = k_out.width / k_input.width, k_out.height / k_input.height
    full = (int(round(STRIDE * w * sx)), int(round(STRIDE * h * sy)))
    okf = ok.astype(np.float32)
    zw = cv2.resize(np.where(ok, z, 0.0).astype(np.float32), full, interpolation=cv2.INTER_LINEAR)[: size[1], : size[0]]
    wt = cv2.resize(okf, full, interpolation=cv2.INTER_LINEAR)[: size[1], : size[0]]
    kernel = np.ones((3, 3), np.uint8)
    z_lo = cv2.erode(np.where(ok, z, np.inf).astype(np.float32), kernel, borderType=cv2.BORDER_REPLICATE)
    z_hi = cv2.dilate(np.where(ok, z, 0.0).astype(np.float32), kernel, borderType=cv2.BORDER_REPLICATE)
    ratio = cv2.resize(z_hi / np.maximum(z_lo, 1e-6), full, interpolation=cv2.INTER_NEAREST)[: size[1], : size[0]]
    valid = (wt >= MIN_VALID_WEIGHT) & (ratio <= max_depth_ratio)
    depth = np.where(valid, zw / np.maximum(wt, 1e-6), 0.0).astype(np.float64)
    u, v = np.meshgrid(np.arange(k_out.width, dtype=np.float64), np.arange(k_out.height, dtype=np.float64))
    X_cam = (
        np.stack([(u - k_out.cx) / k_out.fx, (v - k_out.cy) / k_out.fy, np.ones_like(u)], axis=-1) * depth[..., None]
    )
    pose = np.asarray(pose_c2w, np.float64)
    return PixelDepths(depth=depth, centres=X_cam @ pose[:3, :3].T + pose[:3, 3], valid=valid)


def seed_pixels(mask: np.ndarray, spacing: int, max_new: int, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """Flat indices of pixels of ``mask`` (H, W) on a lattice (random offset) at least ``spacing`` apart,
    coarsened until at most ``max_new`` remain; returns (indices, spacing used)."""
    if spacing < 1 or max_new < 0:
        raise ValueError(f"spacing must be >= 1 and max_new >= 0, got {spacing}, {max_new}")
    count = int(mask.sum())
    if count == 0 or max_new == 0:
        return np.zeros(0, np.int64), spacing
    s = max(spacing, math.ceil(math.sqrt(count / max_new)))
    while True:
        oy, ox = (int(v) for v in rng.integers(0, s, 2))
        sel = np.zeros_like(mask, dtype=bool)
        sel[oy::s, ox::s] = True
        idx = np.flatnonzero(sel & mask)
        if idx.size <= max_new:
            return idx, s
        s += 1


def block_colours(rgb: np.ndarray, spacing: float) -> np.ndarray:
    """rgb (H, W, 3) low-passed at the seeding spacing."""
    if spacing <= 1.0:
        return rgb
    s = BLOCK_SIGMA * spacing
    return cv2.GaussianBlur(np.asarray(rgb, np.float32), (0, 0), sigmaX=s, sigmaY=s, borderType=cv2.BORDER_REFLECT)


def gaussians_at(
    centres: np.ndarray,
    depth: np.ndarray,
    rgb: np.ndarray,
    focal_px: float,
    spacing_px: float,
    sh_degree: int,
    dtype: type = np.float32,
    opacity: float = OPACITY_PRIOR,
) -> Gaussians:
    """Isotropic Gaussians at ``centres`` (N, 3) with colours ``rgb`` (N, 3), sized to cover the gap to their
    neighbours: sigma = SCALE_PRIOR * spacing * depth / focal (depth (N,) camera z)."""
    centres = np.asarray(centres)
    n = centres.shape[0]
    if centres.shape != (n, 3) or np.shape(depth) != (n,) or np.shape(rgb) != (n, 3):
        raise ValueError(
            f"need centres (N, 3), depth (N,), rgb (N, 3); got {centres.shape}, {np.shape(depth)}, {np.shape(rgb)}"
        )
    g = Gaussians.zeros(n, sh_degree, dtype)
    g.means[:] = centres
    g.log_scales[:] = np.log(SCALE_PRIOR * spacing_px * np.maximum(np.asarray(depth, np.float64), 1e-6) / focal_px)[
        :, None
    ]
    g.opacity_logits[:] = logit(np.full(n, opacity))
    g.sh[:, 0, :] = rgb_to_sh_dc(np.asarray(rgb, np.float64))
    return g


def seed_from_scr(
    coords: np.ndarray,
    pose_c2w: np.ndarray,
    k_input: Intrinsics,
    rgb: np.ndarray,
    k_out: Intrinsics,
    need: np.ndarray,
    spacing: int,
    max_new: int,
    sh_degree: int,
    rng: np.random.Generator,
    dtype: type = np.float32,
) -> Gaussians:
    """Gaussians for the ``need`` pixels (H, W) of a keyframe image ``rgb`` (H, W, 3) in [0, 1] of intrinsics
    ``k_out``, from its SCR ``coords`` (h, w, 3) predicted on the input image of ``k_input``."""
    if rgb.shape[:2] != (k_out.height, k_out.width) or need.shape != rgb.shape[:2]:
        raise ValueError(
            f"rgb {rgb.shape} and need {need.shape} must match the {k_out.height}x{k_out.width} intrinsics"
        )
    pix = pixel_depths(coords, pose_c2w, k_input, k_out)
    idx, s = seed_pixels(need & pix.valid, spacing, max_new, rng)
    if idx.size == 0:
        return Gaussians.empty(sh_degree, dtype)
    col = block_colours(rgb, float(s)).reshape(-1, 3)[idx]
    focal = 0.5 * (k_out.fx + k_out.fy)
    return gaussians_at(
        pix.centres.reshape(-1, 3)[idx], pix.depth.reshape(-1)[idx], col, focal, float(s), sh_degree, dtype
    )
