"""The optimised scene set as torch parameters, and the conversion to and from numpy Gaussians.

One ``nn.Parameter`` per attribute (rather than one packed tensor) so each gets its own learning
rate and the lifecycle can grow and shrink them together with their optimiser state.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from acesplat.core.gaussians import Gaussians

PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")
"""SH is held as two tensors, the DC band (N, 1, 3) and the rest (N, K-1, 3): 3DGS gives the rest a
20x smaller learning rate, and Adam ignores a rescaled gradient, so they must be separate parameters."""

GaussianParams = dict[str, torch.nn.Parameter]
"""{name: (N, ...) parameter} for every name in PARAM_NAMES."""


def split_sh(tensors: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Tensors with one ``sh`` (N, K, 3) -> the same with ``sh_dc`` and ``sh_rest``."""
    out = {k: v for k, v in tensors.items() if k != "sh"}
    out["sh_dc"] = tensors["sh"][:, :1]
    out["sh_rest"] = tensors["sh"][:, 1:]
    return out


def render_tensors(params: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The five tensors the rasterizer takes (``sh`` rejoined, differentiable in both halves)."""
    return {
        "means": params["means"],
        "log_scales": params["log_scales"],
        "quats": params["quats"],
        "opacity_logits": params["opacity_logits"],
        "sh": torch.cat([params["sh_dc"], params["sh_rest"]], dim=1),
    }


def params_from_gaussians(g: Gaussians, device: str | torch.device = "cpu") -> GaussianParams:
    """Fresh float32 parameters (copies) holding ``g``'s values."""
    arrays = (g.means, g.log_scales, g.quats, g.opacity_logits, g.sh[:, :1], g.sh[:, 1:])
    return {
        name: torch.nn.Parameter(torch.from_numpy(np.ascontiguousarray(a, np.float32)).to(device).clone())
        for name, a in zip(PARAM_NAMES, arrays)
    }


def params_from_tensors(tensors: Mapping[str, torch.Tensor]) -> GaussianParams:
    """Detached float32 parameters from tensors with one ``sh`` (e.g. the init head's output)."""
    check_tensors(tensors)
    return {name: torch.nn.Parameter(t.detach().float().contiguous().clone()) for name, t in split_sh(tensors).items()}


def gaussians_from_params(params: Mapping[str, torch.Tensor]) -> Gaussians:
    """A numpy float32 copy of the parameters (what gets written to PLY)."""
    t = render_tensors(params)
    check_tensors(t)
    return Gaussians(
        *(t[n].detach().cpu().float().numpy().copy() for n in ("means", "log_scales", "quats", "opacity_logits", "sh"))
    )


TENSOR_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh")


def check_tensors(t: Mapping[str, torch.Tensor]) -> int:
    """Number of Gaussians, after checking the five rasterizer tensors are present and shaped consistently."""
    missing = [n for n in TENSOR_NAMES if n not in t]
    if missing:
        raise ValueError(f"Gaussian tensors miss {missing}")
    n = t["means"].shape[0]
    shapes = {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4), "opacity_logits": (n,)}
    for name, shape in shapes.items():
        if tuple(t[name].shape) != shape:
            raise ValueError(f"{name} must have shape {shape}, got {tuple(t[name].shape)}")
    sh = t["sh"]
    if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3 or sh.shape[1] not in (1, 4, 9, 16):
        raise ValueError(f"sh must have shape ({n}, K, 3) with K in 1, 4, 9, 16, got {tuple(sh.shape)}")
    return int(n)


def cat_tensors(parts: list[Mapping[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Concatenate several Gaussian tensor dicts (same keys and SH size) along the Gaussian axis."""
    if not parts:
        raise ValueError("nothing to concatenate")
    return {n: torch.cat([p[n] for p in parts], dim=0) for n in parts[0]}
