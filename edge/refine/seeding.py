"""New Gaussians for the pixels a keyframe needs, placed at the SCR scene coordinates.

The torch-free core shared with Stage 2 lives in acesplat/splatcore: which cells to trust
(:func:`cell_trust`), their depths at the refinement resolution along each pixel's ray
(:func:`pixel_depths`), the seeding lattice (:func:`seed_pixels`) and the analytic start
(:func:`block_colours`, :func:`gaussians_at`). This module composes them for one keyframe.
"""

from __future__ import annotations

import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.gaussians import Gaussians
from acesplat.splatcore.lattice import seed_pixels
from acesplat.splatcore.pixel_coords import pixel_depths
from acesplat.splatcore.seeding import block_colours, gaussians_at


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
