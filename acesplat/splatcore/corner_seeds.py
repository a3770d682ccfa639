"""Gaussian seeds at the training images' corners, triangulated between the images with their known poses (torch-free).

3DGS starts from SfM points: places matched between images and triangulated, each at the accuracy of the matching.
The SCR cells carry a coordinate everywhere but at the head's depth error, which views 10-15 degrees away see as
parallax (bench/splat_init.md). The keyframe alignment already finds each mapping image's corners in its
neighbouring images by Lucas-Kanade and triangulates them along their rays (acesplat.align.keyframe_depth); those
corners, where a neighbour triangulated them, are this start's points. The keyframes' depth grids (the SCR head's,
re-measured between neighbours: acesplat.scr.keyframes) only give the first guess of their depth and the plane the
tracking warps by. RGB and poses only, like the rest.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from acesplat.align.keyframe_align import Keyframe, keyframe_corners
from acesplat.align.keyframe_set import prepare_corners


def corner_seeds(
    keyframes: Sequence[Keyframe], rgbs: Sequence[np.ndarray], count: int
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Points (N, 3) and colours (N, 3) of every keyframe's ``count`` strongest corners that its neighbouring
    keyframes triangulate (acesplat.align.keyframe_depth.triangulate_corners), and how many each gave.

    ``rgbs`` (H, W, 3) per keyframe, at its image's size: the seeds' colours."""
    if len(rgbs) != len(keyframes) or not keyframes:
        raise ValueError(f"need one colour image per keyframe, got {len(rgbs)} for {len(keyframes)}")
    for kf, rgb in zip(keyframes, rgbs, strict=True):
        if np.shape(rgb) != (*kf.gray.shape, 3):
            raise ValueError(f"a colour image is {np.shape(rgb)}, its keyframe {kf.gray.shape}")
    prepare_corners(keyframes.__getitem__, np.stack([kf.c2w for kf in keyframes]), count)
    points, colours, per_view = [], [], []
    for kf, rgb in zip(keyframes, rgbs, strict=True):
        c = keyframe_corners(kf, count)
        keep = c.triangulated if c.triangulated is not None else np.zeros(len(c.uv), bool)
        u = np.rint(c.uv[keep]).astype(np.int64)
        points.append(c.X[keep])
        colours.append(np.asarray(rgb)[u[:, 1], u[:, 0]].astype(np.float32))
        per_view.append(int(keep.sum()))
    return np.concatenate(points), np.concatenate(colours), per_view
