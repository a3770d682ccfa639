"""Stage 2's seeds at depths re-measured between neighbouring training views, where they triangulate.

The Gaussians start at the SCR coordinates, and on a real scene those carry Stage 1's error (centimetres on a
facade metres deep: bench/splat_init.md). The training poses are exact, so the same re-measurement that gives the
pose alignment its keyframe depths (acesplat.align.keyframe_depth: flow to two neighbours with a useful baseline,
triangulation along each pixel's ray) gives each seeding view better depths wherever its neighbours see the same
surface. Still RGB + poses only: no other input than the scene's images and poses.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from acesplat.align.keyframe_align import Keyframe
from acesplat.align.keyframe_depth import depth_neighbours, refine_depth
from acesplat.core.geometry import transform_points
from acesplat.core.grid import DENSE_OUTPUT_STRIDE, OUTPUT_STRIDE, cell_centers
from acesplat.scr.mapping import TrainingImage
from acesplat.scr.novel_views import head_depth
from acesplat.splat.views import SplatView
from acesplat.splatcore.validity import ValidityConfig, cell_validity

DENSE_STEP = OUTPUT_STRIDE // DENSE_OUTPUT_STRIDE
"""Cell (i, j) of the seeding grid sits on dense cell (2i, 2j): both grids put cell k at stride * k + 4 px."""


@torch.no_grad()
def remeasure_views(
    seeding: Sequence[SplatView],
    everyone: Sequence[SplatView],
    network: torch.nn.Module,
    validity: ValidityConfig = ValidityConfig(),
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Replace, in place, the SCR coordinates of each ``seeding`` view's cells that its neighbours among
    ``everyone`` (the training views, exact poses) triangulate, by the triangulated point on the cell's ray, and
    recompute the view's validity. Views need their SCR outputs (views.run_scr). Returns cells, cells re-measured,
    and the median relative depth change of those."""
    network.eval()
    index = {id(v): i for i, v in enumerate(everyone)}
    images = [TrainingImage(v.gray, v.intrinsics, v.pose) for v in everyone]
    c2ws = np.stack([v.pose for v in everyone])
    cells = moved = 0
    changes: list[np.ndarray] = []
    for n, v in enumerate(seeding):
        if v.coords is None:
            raise ValueError(f"view {v.name} has no SCR coordinates; run views.run_scr first")
        i = index[id(v)]
        z = head_depth(network, images[i])
        known = z[z > 0]
        if known.size:
            nbs = depth_neighbours(c2ws, i, float(np.median(known)))
            plain = [
                Keyframe(
                    images[j].gray,
                    images[j].intrinsics,
                    images[j].c2w,
                    np.zeros((1, 1), np.float32),
                    DENSE_OUTPUT_STRIDE,
                )
                for j in nbs
            ]
            kf = Keyframe(images[i].gray, images[i].intrinsics, images[i].c2w, z, DENSE_OUTPUT_STRIDE)
            zr = refine_depth(kf, plain)
            h, w = v.coords.shape[:2]
            zs, zh = zr[::DENSE_STEP, ::DENSE_STEP][:h, :w], z[::DENSE_STEP, ::DENSE_STEP][:h, :w]
            use = np.zeros((h, w), bool)
            use[: zs.shape[0], : zs.shape[1]] = (zs != zh) & (zs > 0) & (zh > 0)
            if use.any():
                zz = np.zeros((h, w), np.float64)
                zz[: zs.shape[0], : zs.shape[1]] = zs
                uv = cell_centers(h, w).reshape(h, w, 2)[use]
                X = transform_points(v.pose, v.intrinsics.unproject(uv, zz[use]))
                changes.append(np.abs(zz[use] / np.pad(zh, ((0, h - zh.shape[0]), (0, w - zh.shape[1])))[use] - 1.0))
                coords = v.coords.copy()
                coords[use] = X.astype(coords.dtype)
                v.coords = coords
                v.validity = cell_validity(coords, v.pose, v.intrinsics, validity)
            moved += int(use.sum())
        cells += int(np.prod(v.coords.shape[:2]))
        if progress:
            progress(n + 1, len(seeding))
    return {
        "cells": cells,
        "remeasured_cells": moved,
        "median_depth_change": float(np.median(np.concatenate(changes))) if changes else 0.0,
    }
