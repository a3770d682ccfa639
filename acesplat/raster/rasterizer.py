"""Differentiable tile rasterizer for 3D Gaussians on the CPU: numpy in, numpy out, no torch.

The model is 3DGS's: EWA projection through a pinhole camera (OpenCV axes, pixel centres at integer
coordinates), +0.3 px^2 low-pass dilation, SH colour with the +0.5 offset clamped at 0, alpha =
min(0.99, opacity * exp(-d^2/2)), front-to-back compositing that stops before transmittance drops
below 1e-4. One deliberate difference: each Gaussian is cut off exactly where alpha < 1/255 or beyond
3 sigma, per pixel, instead of wherever its tiles happen to end, so the image does not depend on the
tiling and a dense per-pixel reference reproduces it to rounding.

Pipeline: project (parallel over Gaussians, one 64-byte screen-space record each: conic, colour,
opacity, depth, cut-off) -> stable depth sort -> bin into 16x16 tiles, copying each tile's records
contiguously in depth order -> composite (parallel over tiles). The backward replays each pixel
back to front from the stored final transmittance and last contributor, writes one gradient slot
per (tile, Gaussian) pair (no two threads share one), then sums each Gaussian's slots and chains
through the projection (parallel over Gaussians). Parallel loops run GIL-free numba kernels over
chunks on a small thread pool (see ``_threads``); results do not depend on the thread count.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.gaussians import Gaussians
from acesplat.core.geometry import invert_pose, rigidity_problem
from acesplat.raster import _layout as L
from acesplat.raster._project_kernels import (
    ALPHA_MIN,
    DILATION,
    FRUSTUM_SLACK,
    MAHA2_MAX,
    project_backward,
    project_forward,
)
from acesplat.raster._threads import parallel_for
from acesplat.raster._tile_kernels import (
    ALPHA_MAX,
    T_MIN,
    TILE,
    bin_tiles,
    composite_backward,
    composite_forward,
    scatter_records,
)

DEFAULT_NEAR = 0.01
DEFAULT_FAR = 1e10

__all__ = [
    "ALPHA_MAX",
    "ALPHA_MIN",
    "DILATION",
    "FRUSTUM_SLACK",
    "MAHA2_MAX",
    "T_MIN",
    "TILE",
    "RasterContext",
    "RenderResult",
    "RasterGradients",
    "rasterize",
    "rasterize_backward",
    "ndc_grad_norm",
]


@dataclass(frozen=True)
class RasterContext:
    """Everything the backward pass needs from a forward pass (treat as opaque)."""

    gaussians: Gaussians
    sh_degree: int
    view: np.ndarray  # (4, 4) world-to-camera, float64
    campos: np.ndarray  # (3,) camera centre in world
    intrinsics: Intrinsics
    background: np.ndarray  # (3,) float64
    order: np.ndarray  # (V,) visible Gaussian indices in depth order
    tile_offsets: np.ndarray  # (n_tiles + 1,) each tile's range of tile_rec rows
    tile_rec: np.ndarray  # (M, REC_WIDTH) screen-space records, per tile in depth order
    g_offsets: np.ndarray  # (N + 1,) each Gaussian's range of gradient slots
    entry_slot: np.ndarray  # (M,) gradient slot of each tile_rec row
    tile_order: np.ndarray
    final_trans: np.ndarray  # (H, W) final transmittance
    last: np.ndarray  # (H, W) int32, list entries up to the last contributor
    alpha: np.ndarray  # (H, W) the forward's outputs, for the expected-depth gradient
    depth: np.ndarray


@dataclass(frozen=True)
class RenderResult:
    """One rendered view. Images are in the Gaussians' dtype.

    color (H, W, 3) composited over the background; alpha (H, W) coverage = 1 - final transmittance;
    depth (H, W) expected camera z of the visible surface (weighted depth sum / alpha, 0 where alpha
    is 0); means2d (N, 2) projected centres in pixels (0 when culled); radii (N,) 3-sigma screen
    radius in pixels as 3DGS reports it (0 when culled); visible (N,) not culled: camera z in
    [near, far], opacity >= 1/255, and its cut-off ellipse's bounding box overlaps the image;
    n_tile_entries total (tile, Gaussian) pairs.
    """

    color: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    means2d: np.ndarray
    radii: np.ndarray
    visible: np.ndarray
    n_tile_entries: int
    ctx: RasterContext


@dataclass(frozen=True)
class RasterGradients:
    """Gradients of a scalar loss for every Gaussian parameter, shaped like the parameters.

    means2d (N, 2) is the gradient with respect to the projected centres in pixels, the signal 3DGS
    densification accumulates; means2d_ndc_norm (N,) is its norm in normalised device coordinates,
    the quantity 3DGS compares with its 2e-4 threshold (see :func:`ndc_grad_norm`).
    """

    means: np.ndarray
    log_scales: np.ndarray
    quats: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray
    means2d: np.ndarray
    means2d_ndc_norm: np.ndarray


def rasterize(
    gaussians: Gaussians,
    pose_c2w: np.ndarray,
    intrinsics: Intrinsics,
    background: np.ndarray | tuple[float, float, float] | None = None,
    sh_degree: int | None = None,
    near: float = DEFAULT_NEAR,
    far: float = DEFAULT_FAR,
) -> RenderResult:
    """Render ``gaussians`` seen from camera-to-world ``pose_c2w`` (4, 4) with ``intrinsics``.

    background (3,) RGB behind everything (default black). sh_degree: how many SH bands to use,
    at most the set's own degree (default all; 3DGS raises it during training). Gaussians with
    camera z outside [near, far] are culled.
    """
    if not isinstance(gaussians, Gaussians):
        raise TypeError(f"gaussians must be a Gaussians set, got {type(gaussians).__name__}")
    g = _contiguous(gaussians)
    view, campos = _check_pose(pose_c2w)
    width, height = _check_intrinsics(intrinsics)
    bg = _check_background(background)
    deg = _check_sh_degree(sh_degree, g)
    if not (0.0 < near < far):
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    k = intrinsics
    n = len(g)
    dtype = g.dtype

    rec = np.empty((n, L.REC_WIDTH), dtype)
    bbox = np.empty((n, 4), np.int32)
    radii = np.empty(n, np.int32)
    visible = np.empty(n, np.bool_)
    means2d = np.empty((n, 2), dtype)
    if n:
        parallel_for(
            project_forward,
            n,
            g.means,
            g.log_scales,
            g.quats,
            g.opacity_logits,
            g.sh,
            deg,
            view,
            campos,
            float(k.fx),
            float(k.fy),
            float(k.cx),
            float(k.cy),
            float(width),
            float(height),
            float(near),
            float(far),
            rec,
            bbox,
            radii,
            visible,
            means2d,
        )
    vis_idx = np.flatnonzero(visible)
    order = _depth_order(rec[vis_idx, L.DEPTH], vis_idx)
    tiles_x = -(-width // TILE)
    tiles_y = -(-height // TILE)
    tile_offsets, g_offsets, slot_pos = bin_tiles(bbox, visible, order, tiles_x, tiles_y)
    m = int(tile_offsets[-1])
    tile_rec = np.empty((m, L.REC_WIDTH), dtype)
    entry_slot = np.empty(m, np.int64)
    parallel_for(scatter_records, n, rec, g_offsets, slot_pos, tile_rec, entry_slot)
    tile_order = _tile_order(tiles_x * tiles_y)

    color = np.empty((height, width, 3), dtype)
    alpha = np.empty((height, width), dtype)
    depth = np.empty((height, width), dtype)
    trans = np.empty((height, width), dtype)
    last = np.empty((height, width), np.int32)
    parallel_for(
        composite_forward,
        len(tile_order),
        tile_rec,
        tile_offsets,
        tile_order,
        tiles_x,
        width,
        height,
        bg,
        color,
        alpha,
        depth,
        trans,
        last,
    )
    ctx = RasterContext(
        gaussians=g,
        sh_degree=deg,
        view=view,
        campos=campos,
        intrinsics=intrinsics,
        background=bg,
        order=order,
        tile_offsets=tile_offsets,
        tile_rec=tile_rec,
        g_offsets=g_offsets,
        entry_slot=entry_slot,
        tile_order=tile_order,
        final_trans=trans,
        last=last,
        alpha=alpha,
        depth=depth,
    )
    return RenderResult(
        color=color,
        alpha=alpha,
        depth=depth,
        means2d=means2d,
        radii=radii,
        visible=visible,
        n_tile_entries=int(tile_offsets[-1]),
        ctx=ctx,
    )


def rasterize_backward(
    result: RenderResult,
    v_color: np.ndarray,
    v_alpha: np.ndarray | None = None,
    v_depth: np.ndarray | None = None,
) -> RasterGradients:
    """Gradients of a loss for every parameter, given its gradients for ``result``'s images.

    v_color (H, W, 3), v_alpha (H, W), v_depth (H, W): dL/d of result.color, .alpha, .depth
    (None = the loss does not use that image).
    """
    if not isinstance(result, RenderResult):
        raise TypeError(f"result must be a RenderResult from rasterize(), got {type(result).__name__}")
    c = result.ctx
    g = c.gaussians
    h, w = c.final_trans.shape
    v_color = _check_image_grad("v_color", v_color, (h, w, 3))
    v_alpha = np.zeros((h, w)) if v_alpha is None else _check_image_grad("v_alpha", v_alpha, (h, w))
    if v_depth is None:
        v_depth_sum = np.zeros((h, w))
    else:
        v_depth = _check_image_grad("v_depth", v_depth, (h, w))
        # depth = depth_sum / alpha where alpha > 0, so d/d(depth_sum) = 1 / alpha and
        # d/d(alpha) = -depth / alpha.
        alpha = c.alpha.astype(np.float64)
        covered = alpha > 0.0
        safe = np.where(covered, alpha, 1.0)
        v_depth_sum = np.where(covered, v_depth / safe, 0.0)
        v_alpha = v_alpha - np.where(covered, v_depth * c.depth / safe, 0.0)

    dtype = g.dtype
    k = c.intrinsics
    slot_grads = np.empty((len(c.tile_rec), L.GRAD_WIDTH), dtype)
    parallel_for(
        composite_backward,
        len(c.tile_order),
        c.tile_rec,
        c.tile_offsets,
        c.tile_order,
        -(-w // TILE),
        w,
        h,
        c.background,
        c.final_trans,
        c.last,
        v_color,
        v_alpha,
        v_depth_sum,
        c.entry_slot,
        slot_grads,
    )
    n = len(g)
    out = RasterGradients(
        means=np.zeros((n, 3), dtype),
        log_scales=np.zeros((n, 3), dtype),
        quats=np.zeros((n, 4), dtype),
        opacity_logits=np.zeros(n, dtype),
        sh=np.zeros(g.sh.shape, dtype),
        means2d=np.zeros((n, 2), dtype),
        means2d_ndc_norm=np.zeros(n),
    )
    if len(c.order):
        parallel_for(
            project_backward,
            n,
            g.means,
            g.log_scales,
            g.quats,
            g.opacity_logits,
            g.sh,
            c.sh_degree,
            c.view,
            c.campos,
            float(k.fx),
            float(k.fy),
            float(k.cx),
            float(k.cy),
            float(w),
            float(h),
            c.g_offsets,
            slot_grads,
            out.means,
            out.log_scales,
            out.quats,
            out.opacity_logits,
            out.sh,
            out.means2d,
        )
        out.means2d_ndc_norm[:] = ndc_grad_norm(out.means2d, w, h)
    return out


def ndc_grad_norm(v_means2d: np.ndarray, width: int, height: int) -> np.ndarray:
    """Norm (N,) of the projected-centre gradient in normalised device coordinates.

    3DGS measures the densification signal per unit of NDC (the image spans 2 units), so its
    threshold (2e-4) applies to this, not to the per-pixel gradient.
    """
    v = np.asarray(v_means2d, dtype=np.float64)
    return np.hypot(v[:, 0] * (0.5 * width), v[:, 1] * (0.5 * height))


# --- checks and small helpers -------------------------------------------------------------------


def _contiguous(g: Gaussians) -> Gaussians:
    arrays = (g.means, g.log_scales, g.quats, g.opacity_logits, g.sh)
    if all(a.flags.c_contiguous for a in arrays):
        return g
    return Gaussians(*(np.ascontiguousarray(a) for a in arrays))


def _check_pose(pose_c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pose = np.asarray(pose_c2w, dtype=np.float64)
    problem = rigidity_problem(pose)
    if problem is not None:
        raise ValueError(f"pose_c2w: {problem}")
    return np.ascontiguousarray(invert_pose(pose)), np.ascontiguousarray(pose[:3, 3])


def _check_intrinsics(k: Intrinsics) -> tuple[int, int]:
    if not isinstance(k, Intrinsics):
        raise TypeError(f"intrinsics must be an Intrinsics, got {type(k).__name__}")
    if not (k.width > 0 and k.height > 0):
        raise ValueError(f"image size must be positive, got {k.width}x{k.height}")
    vals = np.array([k.fx, k.fy, k.cx, k.cy], dtype=np.float64)
    if not np.all(np.isfinite(vals)) or k.fx <= 0 or k.fy <= 0:
        raise ValueError(f"intrinsics need finite values and positive focal lengths, got {k}")
    return int(k.width), int(k.height)


def _check_background(background) -> np.ndarray:
    if background is None:
        return np.zeros(3)
    bg = np.asarray(background, dtype=np.float64).reshape(-1)
    if bg.shape != (3,) or not np.all(np.isfinite(bg)):
        raise ValueError(f"background must be 3 finite values, got {background!r}")
    return np.ascontiguousarray(bg)


def _check_sh_degree(sh_degree: int | None, g: Gaussians) -> int:
    if sh_degree is None:
        return g.sh_degree
    if not (isinstance(sh_degree, (int, np.integer)) and 0 <= sh_degree <= g.sh_degree):
        raise ValueError(f"sh_degree must be an int in 0..{g.sh_degree} (the set's degree), got {sh_degree!r}")
    return int(sh_degree)


def _check_image_grad(name: str, v: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    v = np.asarray(v)
    if v.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {v.shape}")
    if not np.issubdtype(v.dtype, np.floating):
        raise TypeError(f"{name} must be floating point, got {v.dtype}")
    return np.ascontiguousarray(v, dtype=np.float64)


def _depth_order(depth: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``index`` sorted by ``depth`` (all >= near > 0), ties in index order (a stable sort).

    For float32 one unstable sort of 64-bit keys (depth bits above index) is several times faster
    than a stable argsort; positive IEEE floats order like their bit patterns.
    """
    if depth.dtype == np.float32 and index.size and index[-1] < 2**32:
        keys = (depth.view(np.uint32).astype(np.uint64) << np.uint64(32)) | index.astype(np.uint64)
        keys.sort()
        return (keys & np.uint64(0xFFFFFFFF)).astype(np.int64)
    return index[np.argsort(depth, kind="stable")]


@functools.lru_cache(maxsize=16)
def _tile_order(n_tiles: int) -> np.ndarray:
    """A fixed shuffle of the tiles, so the parallel loop's equal contiguous chunks get equal work
    (neighbouring tiles have similar loads; sky rows and ground rows do not)."""
    order = np.random.default_rng(12345).permutation(n_tiles).astype(np.int64)
    order.flags.writeable = False
    return order
