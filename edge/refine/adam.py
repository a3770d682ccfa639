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
    """Per-step learning rates: 3DGS's (higher ones overfit each keyframe in paced replays: bench/refine.md)."""

    means: float = 1.6e-4
    """Metres per step (scaled by the scene extent in :meth:`scaled`)."""
    log_scales: float = 5e-3
    quats: float = 1e-3
    opacity_logits: float = 2.5e-2
    sh_dc: float = 2.5e-3
    sh_rest: float = 1.25e-4

    def scaled(self, scene_extent: float) -> LearningRates:
        return LearningRates(
            self.means * scene_extent, self.log_scales, self.quats, self.opacity_logits, self.sh_dc, self.sh_rest
        )


class RowAdam:
    """Adam (beta1 0.9, beta2 0.999) whose moments follow a Gaussian set of fixed size."""

    def __init__(
        self, gaussians: Gaussians, lr: LearningRates, beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-15
    ):
        self.lr = lr
        self.beta1, self.beta2, self.eps = beta1, beta2, eps
        self.m = {p: np.zeros(getattr(gaussians, p).shape, np.float32) for p in PARAMS}
        self.v = {p: np.zeros(getattr(gaussians, p).shape, np.float32) for p in PARAMS}
        self.t = np.zeros(len(gaussians), np.int64)
        """Per-row step count: bias correction is per row, since rows are updated at different times."""

    def step(self, g: Gaussians, grads, rows: np.ndarray | None = None) -> None:
        """Update ``g`` in place from ``grads`` (anything with the five gradient arrays) on boolean ``rows`` (N,).

        Whole-array arithmetic with the row mask folded in (no gather/scatter of rows): on a refinement batch
        most rows are visible, and measured this ran several times faster than updating indexed rows.
        """
        n = len(g)
        if self.t.shape[0] != n:
            raise ValueError(f"optimiser was made for {self.t.shape[0]} Gaussians, got {n}")
        mask = np.ones(n, bool) if rows is None else np.asarray(rows, bool)
        if mask.shape != (n,):
            raise ValueError(f"rows must have shape ({n},), got {mask.shape}")
        if not mask.any():
            return
        self.t += mask
        t = np.maximum(self.t, 1).astype(np.float64)
        step_scale = (np.sqrt(1.0 - self.beta2**t) / (1.0 - self.beta1**t)).astype(np.float32)
        b1, b2 = np.float32(self.beta1), np.float32(self.beta2)
        c1, c2 = np.float32(1.0 - self.beta1), np.float32(1.0 - self.beta2)  # not 1 - float32(beta): 1e-5 off
        for p in PARAMS:
            grad = np.asarray(getattr(grads, p), np.float32)
            shape = (-1,) + (1,) * (grad.ndim - 1)
            live = mask.reshape(shape)
            m, v = self.m[p], self.v[p]
            np.copyto(m, b1 * m + c1 * grad, where=live)
            np.copyto(v, b2 * v + c2 * grad * grad, where=live)
            # Adam with the bias corrections folded into the step: m_hat / (sqrt(v_hat) + eps).
            update = (step_scale.reshape(shape) * m) / (
                np.sqrt(v) + np.float32(self.eps) * np.sqrt((1.0 - self.beta2**t).astype(np.float32)).reshape(shape)
            )
            update = np.where(live, update, np.float32(0.0))
            arr = getattr(g, p)
            if p == "sh":
                lr = np.full(arr.shape[1], self.lr.sh_rest, np.float32)
                lr[0] = self.lr.sh_dc
                arr -= (update * lr[None, :, None]).astype(arr.dtype)
            else:
                arr -= (np.float32(getattr(self.lr, p)) * update).astype(arr.dtype)

    def step_rows(self, g: Gaussians, grads, idx: np.ndarray) -> None:
        """Update rows ``idx`` (M,) int of ``g`` in place from ``grads`` shaped like those rows (M, ...).

        For a step that sees a small part of the set (a crop of the view): gathering the rows costs less than
        the whole-array arithmetic of :meth:`step` when most rows are untouched."""
        idx = np.asarray(idx, np.int64)
        if idx.ndim != 1 or (idx.size and (idx.min() < 0 or idx.max() >= self.t.shape[0])):
            raise ValueError(f"row indices must be a 1-D array within [0, {self.t.shape[0]})")
        if idx.size == 0:
            return
        self.t[idx] += 1
        t = self.t[idx].astype(np.float64)
        step_scale = (np.sqrt(1.0 - self.beta2**t) / (1.0 - self.beta1**t)).astype(np.float32)
        eps = (np.float32(self.eps) * np.sqrt(1.0 - self.beta2**t)).astype(np.float32)
        b1, b2 = np.float32(self.beta1), np.float32(self.beta2)
        c1, c2 = np.float32(1.0 - self.beta1), np.float32(1.0 - self.beta2)
        for p in PARAMS:
            grad = np.asarray(getattr(grads, p), np.float32)
            if grad.shape[0] != idx.size:
                raise ValueError(f"{p} gradient has {grad.shape[0]} rows for {idx.size} indices")
            shape = (-1,) + (1,) * (grad.ndim - 1)
            m = b1 * self.m[p][idx] + c1 * grad
            v = b2 * self.v[p][idx] + c2 * grad * grad
            self.m[p][idx], self.v[p][idx] = m, v
            update = (step_scale.reshape(shape) * m) / (np.sqrt(v) + eps.reshape(shape))
            arr = getattr(g, p)
            if p == "sh":
                lr = np.full(arr.shape[1], self.lr.sh_rest, np.float32)
                lr[0] = self.lr.sh_dc
                arr[idx] -= (update * lr[None, :, None]).astype(arr.dtype)
            else:
                arr[idx] -= (np.float32(getattr(self.lr, p)) * update).astype(arr.dtype)
