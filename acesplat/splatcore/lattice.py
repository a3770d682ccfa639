"""Which pixels seed Gaussians: a regular lattice over a mask, its spacing chosen to fit a budget.

A Gaussian stands for a spacing x spacing block of pixels; a per-view (random) offset keeps views from stacking
their Gaussians on one lattice. Stage 2 picks one spacing for all views' novel pixels (:func:`choose_stride`),
the edge one per keyframe within its per-commit budget (:func:`seed_pixels`).
"""

from __future__ import annotations

import math

import numpy as np


def lattice_pixels(valid: np.ndarray, stride: int, offset: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Flat indices (N,) of the pixels of ``valid`` (H, W) at rows offset[0] + k*stride and columns
    offset[1] + l*stride (row-major order)."""
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    valid = np.asarray(valid, bool)
    if valid.ndim != 2:
        raise ValueError(f"valid must be an (H, W) mask, got shape {valid.shape}")
    oy, ox = offset[0] % stride, offset[1] % stride
    sel = np.zeros_like(valid, dtype=bool)
    sel[oy::stride, ox::stride] = True
    return np.flatnonzero(sel & valid)


def choose_stride(valid_pixels: int, max_gaussians: int) -> int:
    """Smallest lattice stride that keeps about ``valid_pixels / stride^2`` within ``max_gaussians``."""
    if max_gaussians < 1:
        raise ValueError(f"max_gaussians must be >= 1, got {max_gaussians}")
    return max(1, math.ceil(math.sqrt(valid_pixels / max_gaussians)))


def seed_pixels(mask: np.ndarray, spacing: int, max_new: int, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """Flat indices of pixels of ``mask`` (H, W) on a lattice (random offset) at least ``spacing`` apart,
    coarsened until at most ``max_new`` remain; returns (indices, spacing used)."""
    if spacing < 1 or max_new < 0:
        raise ValueError(f"spacing must be >= 1 and max_new >= 0, got {spacing}, {max_new}")
    count = int(mask.sum())
    if count == 0 or max_new == 0:
        return np.zeros(0, np.int64), spacing
    s = max(spacing, choose_stride(count, max_new))
    while True:
        oy, ox = (int(v) for v in rng.integers(0, s, 2))
        idx = lattice_pixels(mask, s, (oy, ox))
        if idx.size <= max_new:
            return idx, s
        s += 1
