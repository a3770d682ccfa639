"""Keeping the map small, torch-free: which Gaussians became transparent, and which a hard cap on the count keeps.

Without a cap a long run grows the map (and every render) without end; the cap drops the least
opaque Gaussians first, which contribute least to any image. Stage 2's lifecycle prunes at the same threshold.
"""

from __future__ import annotations

import numpy as np

from acesplat.core.gaussians import Gaussians, sigmoid

PRUNE_OPACITY = 0.005
"""3DGS's pruning threshold: Gaussians less opaque than this are removed."""


def transparent(g: Gaussians, min_opacity: float = PRUNE_OPACITY) -> np.ndarray:
    """Mask (N,) of Gaussians whose opacity fell below ``min_opacity`` (or became non-finite)."""
    op = sigmoid(g.opacity_logits.astype(np.float64))
    bad = (
        ~np.all(np.isfinite(g.means), axis=1)
        | ~np.isfinite(g.opacity_logits)
        | ~np.all(np.isfinite(g.log_scales), axis=1)
    )
    return (op < min_opacity) | bad


def cap_keep(g: Gaussians, cap: int) -> np.ndarray:
    """Mask (N,) keeping the ``cap`` most opaque Gaussians (all of them if there are at most ``cap``); ties keep
    the earlier Gaussian, so the result is deterministic."""
    if cap < 0:
        raise ValueError(f"cap must be non-negative, got {cap}")
    n = len(g)
    keep = np.ones(n, bool)
    if n <= cap:
        return keep
    order = np.lexsort((np.arange(n), -g.opacity_logits.astype(np.float64)))
    keep[:] = False
    keep[order[:cap]] = True
    return keep
