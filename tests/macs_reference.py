"""Brute-force multiply-accumulate count of an encoder, for tests of acesplat.scr.network.count_macs."""

from __future__ import annotations

import torch
import torch.nn as nn

from acesplat.scr.network import Encoder, FactorizedConv2d, SeparableConv2d

PAIRS = {FactorizedConv2d: ("reduce", "expand"), SeparableConv2d: ("point", "depth")}
"""Two-convolution layers and their halves: each runs one half's weights through F.conv2d (its dilated form), so its
hooks never fire; the pair is counted at its own output size, which both halves share."""


def encoder_macs(encoder: Encoder, height: int, width: int) -> list[int]:
    """Multiply-accumulates of every convolution of ``encoder`` on a (1, 1, height, width) input, one entry per
    convolution, each counted at its output size."""
    macs: list[int] = []

    def count(m: nn.Module, _: tuple, o: torch.Tensor) -> None:
        layers = [getattr(m, name) for name in PAIRS[type(m)]] if type(m) in PAIRS else [m]
        macs.extend(o.shape[2] * o.shape[3] * c.weight[0].numel() * c.out_channels for c in layers)

    inside = {id(getattr(m, name)) for m in encoder.modules() if type(m) in PAIRS for name in PAIRS[type(m)]}
    hooks = [
        m.register_forward_hook(count)
        for m in encoder.modules()
        if type(m) in PAIRS or (isinstance(m, nn.Conv2d) and id(m) not in inside)
    ]
    try:
        with torch.no_grad():
            encoder(torch.zeros(1, 1, height, width))
    finally:
        for h in hooks:
            h.remove()
    return macs
