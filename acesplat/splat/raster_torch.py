"""Torch autograd wrapper around the numba Gaussian rasterizer, for Stage 2 training on the CPU.

The forward and backward are the torch-free kernels in :mod:`acesplat.raster`; this module
only converts tensors to numpy views and back, so training and the edge render identically.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from acesplat.core.camera import Intrinsics
from acesplat.core.gaussians import Gaussians
from acesplat.raster import RenderResult, ndc_grad_norm, rasterize, rasterize_backward
from acesplat.raster.rasterizer import DEFAULT_FAR, DEFAULT_NEAR


@dataclass
class RenderOutput:
    """One differentiable render.

    color (H, W, 3), alpha (H, W), depth (H, W): differentiable with respect to every Gaussian
    parameter passed to :func:`render`. means2d (N, 2): projected centres in pixels, a leaf tensor
    whose ``.grad`` after ``loss.backward()`` is dL/d(projected centre), the densification signal
    (use :func:`screen_grad_norm` for 3DGS's NDC-scaled norm). radii (N,) int and visible (N,) bool,
    as in :class:`acesplat.raster.RenderResult`.
    """

    color: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    means2d: torch.Tensor
    radii: torch.Tensor
    visible: torch.Tensor


class _Stash:
    """Carries the numpy RenderResult out of the autograd Function (apply returns tensors only)."""

    result: RenderResult | None = None


class _RasterizeFunction(torch.autograd.Function):
    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        means: torch.Tensor,
        log_scales: torch.Tensor,
        quats: torch.Tensor,
        opacity_logits: torch.Tensor,
        sh: torch.Tensor,
        means2d_probe: torch.Tensor,
        pose_c2w: np.ndarray,
        intrinsics: Intrinsics,
        background: np.ndarray | None,
        sh_degree: int | None,
        near: float,
        far: float,
        stash: _Stash,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        g = Gaussians(*(_np(t) for t in (means, log_scales, quats, opacity_logits, sh)))
        res = rasterize(g, pose_c2w, intrinsics, background, sh_degree, near, far)
        ctx.result = res
        ctx.device = means.device
        stash.result = res
        dev = means.device
        return (
            torch.from_numpy(res.color).to(dev),
            torch.from_numpy(res.alpha).to(dev),
            torch.from_numpy(res.depth).to(dev),
        )

    @staticmethod
    def backward(  # type: ignore[override]
        ctx: Any, v_color: torch.Tensor, v_alpha: torch.Tensor, v_depth: torch.Tensor
    ) -> tuple[torch.Tensor | None, ...]:
        res: RenderResult = ctx.result
        grads = rasterize_backward(
            res,
            _np(v_color) if v_color is not None else np.zeros(res.color.shape),
            _np(v_alpha) if v_alpha is not None else None,
            _np(v_depth) if v_depth is not None else None,
        )
        dev = ctx.device
        out = [
            torch.from_numpy(a).to(dev)
            for a in (grads.means, grads.log_scales, grads.quats, grads.opacity_logits, grads.sh, grads.means2d)
        ]
        return (*out, None, None, None, None, None, None, None)


def render(
    means: torch.Tensor,
    log_scales: torch.Tensor,
    quats: torch.Tensor,
    opacity_logits: torch.Tensor,
    sh: torch.Tensor,
    pose_c2w: np.ndarray | torch.Tensor,
    intrinsics: Intrinsics,
    background: np.ndarray | torch.Tensor | tuple[float, float, float] | None = None,
    sh_degree: int | None = None,
    near: float = DEFAULT_NEAR,
    far: float = DEFAULT_FAR,
) -> RenderOutput:
    """Differentiable render of N Gaussians from camera-to-world ``pose_c2w`` (4, 4).

    means (N, 3), log_scales (N, 3), quats (N, 4) wxyz, opacity_logits (N,), sh (N, K, 3): one
    floating dtype (float32 to train, float64 to check). The pose and background get no gradient.
    """
    params = {"means": means, "log_scales": log_scales, "quats": quats, "opacity_logits": opacity_logits, "sh": sh}
    for name, t in params.items():
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    dtypes = {t.dtype for t in params.values()}
    if len(dtypes) != 1 or means.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"Gaussian tensors must all be float32 or all float64, got {sorted(map(str, dtypes))}")
    pose = pose_c2w.detach().cpu().double().numpy() if isinstance(pose_c2w, torch.Tensor) else np.asarray(pose_c2w)
    bg = background.detach().cpu().double().numpy() if isinstance(background, torch.Tensor) else background
    probe = torch.zeros((means.shape[0] if means.ndim == 2 else 0, 2), dtype=means.dtype, device=means.device)
    probe.requires_grad_(True)
    stash = _Stash()
    color, alpha, depth = _RasterizeFunction.apply(
        means, log_scales, quats, opacity_logits, sh, probe, pose, intrinsics, bg, sh_degree, near, far, stash
    )
    res = stash.result
    assert res is not None
    with torch.no_grad():
        probe.copy_(torch.from_numpy(res.means2d))
    return RenderOutput(
        color=color,
        alpha=alpha,
        depth=depth,
        means2d=probe,
        radii=torch.from_numpy(res.radii).to(means.device),
        visible=torch.from_numpy(res.visible).to(means.device),
    )


def screen_grad_norm(out: RenderOutput, intrinsics: Intrinsics) -> torch.Tensor:
    """(N,) norm of out.means2d.grad in NDC units, the quantity 3DGS thresholds (2e-4) to densify.

    Zero before backward has run.
    """
    g = out.means2d.grad
    if g is None:
        return torch.zeros(out.means2d.shape[0], dtype=out.means2d.dtype, device=out.means2d.device)
    norms = ndc_grad_norm(_np(g), intrinsics.width, intrinsics.height)
    return torch.from_numpy(norms).to(dtype=out.means2d.dtype, device=out.means2d.device)


def _np(t: torch.Tensor) -> np.ndarray:
    """A numpy view (no copy when already contiguous on the CPU) of a tensor's data."""
    return t.detach().cpu().contiguous().numpy()
