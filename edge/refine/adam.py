"""Adam over a Gaussian set's numpy arrays, updating only the rows a view touched.

Refinement sees one view at a time: Gaussians outside it get zero gradient, and a dense Adam would
still move them on stale momentum (and spend time on them). Rows outside ``rows`` keep their values
and their moments, as in 3DGS implementations' "visible" Adam.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from acesplat.core.gaussians import Gaussians

PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh")


@dataclass(frozen=True)
class LearningRates:
    """Per-step learning rates. Larger than 3DGS's (which assume 30k steps): a keyframe gets a handful."""

    means: float = 2e-3
    """Metres per step (scaled by the scene extent in :meth:`scaled`)."""
    log_scales: float = 1e-2
    quats: float = 5e-3
    opacity_logits: float = 5e-2
    sh_dc: float = 2e-2
    sh_rest: float = 1e-3

    def scaled(self, scene_extent: float) -> "LearningRates":
        return LearningRates(self.means * scene_extent, self.log_scales, self.quats, self.opacity_logits, self.sh_dc, self.sh_rest)


class RowAdam:
    """Adam (beta1 0.9, beta2 0.999) whose moments follow a Gaussian set of fixed size."""

    def __init__(self, gaussians: Gaussians, lr: LearningRates, beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-15):
        self.lr = lr
        self.beta1, self.beta2, self.eps = beta1, beta2, eps
        self.m = {p: np.zeros_like(getattr(gaussians, p)) for p in PARAMS}
        self.v = {p: np.zeros_like(getattr(gaussians, p)) for p in PARAMS}
        self.t = np.zeros(len(gaussians), np.int64)
        """Per-row step count: bias correction is per row, since rows are updated at different times."""

    def step(self, g: Gaussians, grads, rows: np.ndarray | None = None) -> None:
        """Update ``g`` in place from ``grads`` (anything with the five gradient arrays) on boolean ``rows`` (N,)."""
        n = len(g)
        if self.t.shape[0] != n:
            raise ValueError(f"optimiser was made for {self.t.shape[0]} Gaussians, got {n}")
        idx = np.flatnonzero(np.ones(n, bool) if rows is None else rows)
        if idx.size == 0:
            return
        self.t[idx] += 1
        t = self.t[idx].astype(np.float64)
        c1 = (1.0 - self.beta1**t)
        c2 = (1.0 - self.beta2**t)
        for p in PARAMS:
            grad = getattr(grads, p)[idx].astype(np.float64)
            m = self.beta1 * self.m[p][idx] + (1.0 - self.beta1) * grad
            v = self.beta2 * self.v[p][idx] + (1.0 - self.beta2) * grad * grad
            self.m[p][idx] = m
            self.v[p][idx] = v
            shape = (-1,) + (1,) * (grad.ndim - 1)
            update = (m / c1.reshape(shape)) / (np.sqrt(v / c2.reshape(shape)) + self.eps)
            arr = getattr(g, p)
            if p == "sh":
                lr = np.full(arr.shape[1], self.lr.sh_rest)
                lr[0] = self.lr.sh_dc
                arr[idx] -= (update * lr[None, :, None]).astype(arr.dtype)
            else:
                arr[idx] -= (getattr(self.lr, p) * update).astype(arr.dtype)
