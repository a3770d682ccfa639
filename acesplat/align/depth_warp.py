"""Re-render an image from another camera with a coarse depth map (torch-free).

Mapping uses it to make views between neighbouring training cameras: the head learns what the
encoder sees of a surface from in-between viewpoints, which 18 photographs alone do not show it.
The depth is a grid of z-values at the SCR network's prediction cells (acesplat.core.grid.cell_centers,
stride 8 or 4); the warp is the exact reprojection of each source pixel at its
interpolated depth, inverted by fixed-point iteration, so it needs no mesh and no z-buffer. Where the
inverse does not close (folds at occluding edges, outside the source) the pixel is marked invalid.
"""

from __future__ import annotations

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import invert_pose
from acesplat.core.grid import cell_centers

FIXED_POINT_STEPS = 12
"""Iterations of s <- v - D(s); the displacement field of a smooth surface contracts in a few."""
CLOSE_TOLERANCE_PX = 0.5
"""A warped pixel is valid if its source pixel maps back to it within this distance."""
FULL_SIZE_STEPS = 2
"""With a coarse inversion (``inverse_step`` > 1), fixed-point iterations at full size after the upsampled start:
they settle the pixels where the coarse grid's interpolation is off (depth edges) before the closing check."""


def _check(gray: np.ndarray, depth: np.ndarray, intrinsics: Intrinsics, stride: int) -> None:
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"gray must be (H, W) uint8, got {gray.shape} {gray.dtype}")
    if gray.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(f"gray is {gray.shape}, intrinsics are for {(intrinsics.height, intrinsics.width)}")
    if depth.ndim != 2 or stride < 1:
        raise ValueError(f"depth must be a (h, w) grid and stride positive, got {depth.shape}, {stride}")
    if depth.shape[0] * stride < gray.shape[0] - stride or depth.shape[1] * stride < gray.shape[1] - stride:
        raise ValueError(f"a depth grid of {depth.shape} at stride {stride} does not cover an image of {gray.shape}")


def forward_map(
    depth: np.ndarray, intrinsics: Intrinsics, stride: int, c2w_src: np.ndarray, c2w_dst: np.ndarray
) -> np.ndarray:
    """Where each source pixel lands in the destination camera: (H, W, 2) float32, NaN where it cannot.

    ``depth`` (h, w) holds source z-depths at the cell centres; 0 or non-finite means unknown.
    """
    return pixel_map(depth, intrinsics, stride, c2w_src, c2w_dst, with_depth=False)


def pixel_map(
    depth: np.ndarray,
    intrinsics: Intrinsics,
    stride: int,
    c2w_src: np.ndarray,
    c2w_dst: np.ndarray,
    dst_intrinsics: Intrinsics | None = None,
    with_depth: bool = True,
) -> np.ndarray:
    """Where each source pixel lands in a destination camera (``dst_intrinsics``, default the source's) and, with
    ``with_depth``, its z-depth there: (H, W, 3) float32 (x, y, z) or (H, W, 2), NaN where it cannot. H x W is the
    source's size; ``depth`` as forward_map's."""
    dst_intrinsics = intrinsics if dst_intrinsics is None else dst_intrinsics
    gh, gw = depth.shape
    centres = cell_centers(gh, gw, stride)
    first = float(centres[0, 0])  # pixel of cell 0 on either axis
    z = depth.reshape(-1).astype(np.float64)
    X_src = intrinsics.unproject(centres, z)
    T = invert_pose(c2w_dst) @ c2w_src
    X_dst = X_src @ T[:3, :3].T + T[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = dst_intrinsics.project(X_dst)
    if with_depth:
        uv = np.concatenate([uv, X_dst[:, 2:3]], axis=1)
    uv[~((z > 0) & np.isfinite(z) & (X_dst[:, 2] > 1e-6))] = np.nan
    grid = uv.reshape(gh, gw, uv.shape[1])
    # Two cells of linear extrapolation on every side (odd reflection), so that pixels between the outermost
    # cell centres and the image border get positions too (replicating the border would pin them there).
    pad = 2
    grid = np.pad(grid, ((pad, pad), (pad, pad), (0, 0)), mode="reflect", reflect_type="odd")
    h, w = intrinsics.height, intrinsics.width
    py, px = np.mgrid[0:h, 0:w].astype(np.float32)
    nan = float("nan")
    # Bilinear between cell centres; NaN spreads to every pixel next to an unknown cell.
    return cv2.remap(
        grid.astype(np.float32),
        (px - first) / stride + pad,
        (py - first) / stride + pad,
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=(nan,) * grid.shape[2],
    )


def warp_to_camera(
    gray: np.ndarray,
    depth: np.ndarray,
    intrinsics: Intrinsics,
    stride: int,
    c2w_src: np.ndarray,
    c2w_dst: np.ndarray,
    inverse_step: int = 1,
    forward: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The source image (H, W) uint8 as the destination camera (same intrinsics) would see it, and a validity
    mask (H, W) bool.

    ``depth`` (h, w): source z-depth at the cells spaced ``stride`` px apart; c2w_* (4, 4) camera-to-world.
    ``inverse_step`` > 1 inverts the forward map on destination pixels that many apart and upsamples the inverse
    (FIXED_POINT_STEPS iterations there, FULL_SIZE_STEPS at full size): the depth grid is coarse, so the map is
    smooth between its cells, and the closing check is still made on every pixel. ``forward``: forward_map's
    result (H, W, 2) for these cameras, when the caller has it already.
    """
    _check(gray, depth, intrinsics, stride)
    if inverse_step < 1:
        raise ValueError(f"inverse_step must be >= 1, got {inverse_step}")
    h, w = gray.shape
    F = forward_map(depth, intrinsics, stride, c2w_src, c2w_dst) if forward is None else forward
    if F.shape != (h, w, 2):
        raise ValueError(f"forward map is {F.shape}, expected {(h, w, 2)}")
    v = _pixel_grid(h, w)
    D = F - v
    finite = np.isfinite(D).all(-1)
    if not finite.any():
        return np.zeros_like(gray), np.zeros(gray.shape, bool)
    start = np.median(D[finite], axis=0).astype(np.float32)
    # Replicated borders keep the last row and column (bilinear reads one past them); leaving the source
    # image is tested explicitly instead.
    if inverse_step == 1:
        s = _fixed_point(D, v, v - start, FIXED_POINT_STEPS)
    else:
        vc = np.ascontiguousarray(v[::inverse_step, ::inverse_step])
        sc = _fixed_point(D, vc, vc - start, FIXED_POINT_STEPS)
        # upsample the inverse displacement (smooth), not the positions, then settle at full size; a coarse pixel
        # that did not close starts its neighbours from the median displacement, as the full inversion does
        ec = vc - sc
        ec = np.where(np.isfinite(ec), ec, start).astype(np.float32)
        e = cv2.remap(ec, v / np.float32(inverse_step), None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        s = _fixed_point(D, v, v - e, FULL_SIZE_STEPS)
    s = np.where(np.isfinite(s), s, np.float32(-1.0))
    back = cv2.remap(F, s, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) - v
    err = np.hypot(back[..., 0], back[..., 1])
    eps = 1e-3  # the iteration lands on the border only up to rounding
    inside = (s[..., 0] >= -eps) & (s[..., 0] <= w - 1 + eps) & (s[..., 1] >= -eps) & (s[..., 1] <= h - 1 + eps)
    valid = inside & (err < CLOSE_TOLERANCE_PX)  # NaN compares False
    s[~valid] = -1.0
    out = cv2.remap(gray, s, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out, valid


def _pixel_grid(h: int, w: int) -> np.ndarray:
    """(H, W, 2) float32 pixel coordinates (x, y)."""
    py, px = np.mgrid[0:h, 0:w].astype(np.float32)
    return np.stack([px, py], -1)


def _fixed_point(D: np.ndarray, v: np.ndarray, s: np.ndarray, steps: int) -> np.ndarray:
    """``steps`` iterations of s <- v - D(s): source pixels (..., 2) of the destination pixels v (..., 2) under
    the displacement field D (H, W, 2), from the start s."""
    for _ in range(steps):
        s = v - cv2.remap(D, s, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return s
