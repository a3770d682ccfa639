"""A cheaper encoder for the edge: one of its convolutions replaced by a low-rank pair fitted to the scene's images.

The encoder's last 3x3 convolution (``res2_conv3``) is a third of the SCR graph's inference at the default
bundle size (bench/int8_format.md). Its weights have no small rank (their singular values are flat), but its
*outputs* on a scene's images do: they lie close to a subspace of a few hundred of its output channels. The
reduced-rank fit keeps the principal subspace of the layer's outputs on images of the scene:

    y = W x + b  ~  mu + U_r U_r^T (W x + b - mu)

computed as a k x k convolution into ``rank`` channels (``U_r^T W``) and a 1 x 1 convolution back (``U_r``): the
least-squares best rank-``rank`` map of those images' outputs. The ``rank`` intermediate channels are whitened
(unit variance on the fitting images), so that one INT8 activation scale fits all of them.

Fitted on the mapping images (what the export already calibrates INT8 on), never on the test views.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn as nn

from acesplat.core.grid import OUTPUT_STRIDE
from acesplat.scr.network import Encoder, FactorizedConv2d, normalize_gray

LOWRANK_LAYER = "res2_conv3"
"""The layer the export can factorize: the encoder's last 3x3 convolution, its most expensive."""


def factorize_conv(conv: nn.Conv2d, outputs: torch.Tensor, rank: int) -> tuple[FactorizedConv2d, float]:
    """Rank-``rank`` replacement of ``conv`` fitted to ``outputs`` (N, C_out), samples of its pre-activation
    outputs on representative inputs; returns the pair and the share of the outputs' variance it keeps.

    The reduce layer's outputs have zero mean and unit variance over ``outputs`` (whitened principal components).
    """
    if not isinstance(conv, nn.Conv2d) or conv.groups != 1 or conv.stride != (1, 1):
        raise TypeError(f"factorize_conv takes an ungrouped stride-1 nn.Conv2d, got {conv}")
    if conv.kernel_size[0] != conv.kernel_size[1] or conv.padding != (conv.kernel_size[0] // 2,) * 2:
        raise ValueError(f"factorize_conv takes a square 'same' convolution, got {conv}")
    c_out, c_in, k, _ = conv.weight.shape
    if outputs.ndim != 2 or outputs.shape[1] != c_out:
        raise ValueError(f"outputs must be (N, {c_out}), got {tuple(outputs.shape)}")
    if outputs.shape[0] < 2:
        raise ValueError(f"outputs needs at least 2 samples, got {outputs.shape[0]}")
    if not 1 <= rank < c_out:
        raise ValueError(f"rank must be in [1, {c_out}) for a layer of {c_out} outputs, got {rank}")
    y = outputs.detach().double()
    mu = y.mean(0)
    cov = (y - mu).T @ (y - mu) / y.shape[0]
    eigval, eigvec = torch.linalg.eigh(cov)  # ascending
    eigval, eigvec = eigval.flip(0).clamp_min(0.0), eigvec.flip(1)
    total = float(eigval.sum())
    kept = float(eigval[:rank].sum()) / total if total > 0 else 1.0
    basis = eigvec[:, :rank]  # (C_out, rank)
    scale = eigval[:rank].sqrt()
    scale = torch.where(scale > 1e-9 * float(scale[0]), scale, torch.ones_like(scale))  # a constant component: as is
    w = conv.weight.detach().double()
    b = conv.bias.detach().double() if conv.bias is not None else torch.zeros(c_out, dtype=torch.float64)
    pair = FactorizedConv2d(c_in, c_out, rank, k)
    with torch.no_grad():
        pair.reduce.weight.copy_((torch.einsum("or,oikl->rikl", basis, w) / scale[:, None, None, None]).float())
        pair.reduce.bias.copy_(((basis.T @ (b - mu)) / scale).float())
        pair.expand.weight.copy_((basis * scale).float()[:, :, None, None])
        pair.expand.bias.copy_(mu.float())
    return pair.to(conv.weight.device), kept


@torch.no_grad()
def layer_outputs(encoder: Encoder, images: Sequence[np.ndarray], layer: str = LOWRANK_LAYER) -> torch.Tensor:
    """(N, C) outputs of ``encoder.<layer>`` (before its ReLU) on grayscale (H, W) uint8 ``images``, one row per
    stride-8 cell."""
    module = getattr(encoder, layer)
    rows: list[torch.Tensor] = []
    hook = module.register_forward_hook(lambda m, i, o: rows.append(o[0].flatten(1).T.detach()))
    try:
        for img in images:
            if img.ndim != 2:
                raise ValueError(f"images must be grayscale (H, W), got {img.shape}")
            encoder(normalize_gray(torch.from_numpy(np.ascontiguousarray(img)).float()[None, None]), OUTPUT_STRIDE)
    finally:
        hook.remove()
    if not rows:
        raise ValueError("layer_outputs needs at least one image")
    return torch.cat(rows)


def lowrank_encoder(
    encoder: Encoder, images: Sequence[np.ndarray], rank: int, layer: str = LOWRANK_LAYER
) -> tuple[Encoder, dict]:
    """A copy of ``encoder`` whose ``layer`` is factorized to ``rank`` on ``images`` (grayscale (H, W) uint8, the
    scene's mapping images); returns it and a report (layer, rank, samples, kept variance, MACs per cell)."""
    module = getattr(encoder, layer, None)
    if not isinstance(module, nn.Conv2d):
        raise ValueError(f"encoder has no full convolution {layer!r} to factorize")
    outputs = layer_outputs(encoder, images, layer)
    pair, kept = factorize_conv(module, outputs, rank)
    out = copy.deepcopy(encoder).eval()
    setattr(out, layer, pair)
    c_out, c_in, k, _ = module.weight.shape
    return out, {
        "layer": layer,
        "rank": int(rank),
        "images": len(images),
        "samples": int(outputs.shape[0]),
        "kept_variance": kept,
        "macs_per_cell": int(rank * (c_in * k * k + c_out)),
        "macs_per_cell_full": int(c_out * c_in * k * k),
    }
