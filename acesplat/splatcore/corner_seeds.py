"""Gaussian seeds at the training images' corners, triangulated between the images with their known poses (torch-free).

3DGS starts from SfM points: places matched between images and triangulated, each at the accuracy of the matching.
The SCR cells carry a coordinate everywhere but at the head's depth error, which views 10-15 degrees away see as
parallax (bench/splat_init.md). The keyframe alignment already finds each training image's corners in its
neighbouring images by Lucas-Kanade and triangulates them along their rays (acesplat.align.keyframe_depth); those
corners, where a neighbour triangulated them, are this start's points. The SCR cells only give the first guess of
their depth, the plane the tracking warps by and which cells are trusted. RGB and poses only, like the rest.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from acesplat.align.keyframe_align import Keyframe, keyframe_corners
from acesplat.align.keyframe_set import prepare_corners
from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import invert_pose
from acesplat.core.grid import OUTPUT_STRIDE


def cell_depth_grid(coords: np.ndarray, c2w: np.ndarray, trusted: np.ndarray | None = None) -> np.ndarray:
    """The z-depth (h, w) float32 of SCR coordinates (h, w, 3) in the camera ``c2w`` (4, 4); 0 where a coordinate
    is not finite, behind the camera or (given ``trusted`` (h, w) bool) not trusted."""
    coords = np.asarray(coords, np.float64)
    if coords.ndim != 3 or coords.shape[-1] != 3:
        raise ValueError(f"coords must be (h, w, 3), got {coords.shape}")
    if trusted is not None and trusted.shape != coords.shape[:2]:
        raise ValueError(f"trusted {trusted.shape} must be the grid's {coords.shape[:2]}")
    w2c = invert_pose(c2w)
    z = coords.reshape(-1, 3) @ w2c[2, :3] + w2c[2, 3]
    z = np.where(np.isfinite(z) & (z > 0), z, 0.0).reshape(coords.shape[:2])
    if trusted is not None:
        z = np.where(trusted, z, 0.0)
    return z.astype(np.float32)


def corner_seeds(
    grays: Sequence[np.ndarray],
    rgbs: Sequence[np.ndarray],
    intrinsics: Sequence[Intrinsics],
    c2ws: np.ndarray,
    depths: Sequence[np.ndarray],
    count: int,
    stride: int = OUTPUT_STRIDE,
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Points (N, 3) and colours (N, 3) of every view's ``count`` strongest corners that its neighbouring views
    triangulate (acesplat.align.keyframe_depth.triangulate_corners), and how many each view gave.

    grays (H, W) uint8 and rgbs (H, W, 3) per view, with their intrinsics and camera-to-worlds c2ws (N, 4, 4);
    depths (h, w) float32 per view at cells ``stride`` px apart (0 unknown; cell_depth_grid): the first guess."""
    n = len(grays)
    c2ws = np.asarray(c2ws, np.float64)
    if not (len(rgbs) == len(intrinsics) == len(depths) == n) or c2ws.shape != (n, 4, 4):
        raise ValueError(
            f"need as many images, colours, intrinsics, depths and (4, 4) poses, got {n}, {len(rgbs)}, "
            f"{len(intrinsics)}, {len(depths)} and {c2ws.shape}"
        )
    for g, c, k in zip(grays, rgbs, intrinsics, strict=True):
        if g.dtype != np.uint8 or g.shape != (k.height, k.width) or c.shape != (*g.shape, 3):
            raise ValueError(
                f"each view needs gray (H, W) uint8 and rgb (H, W, 3) at its intrinsics' {k.height}x{k.width}"
            )
    kfs = [Keyframe(g, k, c2ws[i], d, stride) for i, (g, k, d) in enumerate(zip(grays, intrinsics, depths))]
    prepare_corners(kfs.__getitem__, c2ws, count)
    points, colours, per_view = [], [], []
    for kf, rgb in zip(kfs, rgbs, strict=True):
        c = keyframe_corners(kf, count)
        keep = c.triangulated if c.triangulated is not None else np.zeros(len(c.uv), bool)
        u = np.rint(c.uv[keep]).astype(np.int64)
        points.append(c.X[keep])
        colours.append(np.asarray(rgb)[u[:, 1], u[:, 0]].astype(np.float32))
        per_view.append(int(keep.sum()))
    return np.concatenate(points), np.concatenate(colours), per_view
