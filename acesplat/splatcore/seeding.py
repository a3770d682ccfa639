"""Gaussians at pixels: the analytic start every seeded Gaussian begins from, torch-free.

A Gaussian standing for a spacing x spacing block of pixels takes the block's colour (the image low-passed at the
spacing, not one aliased pixel's), an isotropic scale that covers the gap to its neighbours at its depth, identity
rotation and a prior opacity. The init head predicts residuals around this start (:mod:`.head_io`); without a head
(the edge's SCR seeder) it is used as is.
"""

from __future__ import annotations

import cv2
import numpy as np

from acesplat.core.gaussians import Gaussians, logit, rgb_to_sh_dc

SCALE_PRIOR = 0.7
"""Standard deviation of a new Gaussian in units of the spacing between seeded pixels (at its depth)."""
OPACITY_PRIOR = 0.8
"""Opacity a fresh init head gives every Gaussian (3DGS starts random points at 0.1; ours sit on surfaces)."""
SCR_SEED_OPACITY = 0.7
"""Opacity of Gaussians seeded without the head (the edge's SCR seeder: :func:`gaussians_at`'s default)."""
BLOCK_SIGMA = 0.4
"""Low-pass of the colour a Gaussian takes, in units of the seeding spacing."""


def block_colours(rgb: np.ndarray, spacing_px: float) -> np.ndarray:
    """rgb (H, W, 3) low-passed with a Gaussian of BLOCK_SIGMA x spacing, float32 (unchanged at spacing <= 1)."""
    if spacing_px <= 1.0:
        return rgb
    s = BLOCK_SIGMA * spacing_px
    return cv2.GaussianBlur(np.asarray(rgb, np.float32), (0, 0), sigmaX=s, sigmaY=s, borderType=cv2.BORDER_REFLECT)


def start_log_scales(
    depth: np.ndarray, focal_px: float, spacing_px: float, scale_prior: float = SCALE_PRIOR
) -> np.ndarray:
    """Log standard deviation (N,) of isotropic Gaussians at camera depths ``depth`` (N,) seeded ``spacing_px``
    pixels apart: log(scale_prior * spacing * depth / focal), depth clamped at 1e-6."""
    return np.log(scale_prior * spacing_px * np.maximum(np.asarray(depth, np.float64), 1e-6) / focal_px)


def gaussians_at(
    centres: np.ndarray,
    depth: np.ndarray,
    rgb: np.ndarray,
    focal_px: float,
    spacing_px: float,
    sh_degree: int,
    dtype: type = np.float32,
    opacity: float = SCR_SEED_OPACITY,
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
    g.log_scales[:] = start_log_scales(depth, focal_px, spacing_px)[:, None]
    g.opacity_logits[:] = logit(np.full(n, opacity))
    g.sh[:, 0, :] = rgb_to_sh_dc(np.asarray(rgb, np.float64))
    return g
