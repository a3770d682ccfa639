"""Gaussian initialisation head: per-pixel Gaussian attributes from [adapted features, coordinate prior].

Fully convolutional. It predicts residuals around the analytic start of acesplat/splatcore/seeding.py, with its
last layer zeroed so a fresh head already gives a usable set: colour = the pixel's colour (SH DC), opacity =
OPACITY_PRIOR, an isotropic scale that covers the spacing between instantiated pixels at the pixel's depth,
identity rotation. Centres are not predicted: they are the SCR coordinates at pixel resolution
(acesplat/splatcore/pixel_coords.py). Its prior input and residual layout are acesplat/splatcore/head_io.py's,
which the exported graph and the edge share.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn as nn

from acesplat.core.config import knob
from acesplat.core.gaussians import MAX_SH_DEGREE, SH_C0, sh_coeff_count
from acesplat.splatcore.head_io import (
    IDENTITY_QUAT,
    OPACITY_CHANNEL,
    PRIOR_CHANNELS,
    residual_channels,
    residual_slices,
)
from acesplat.splatcore.seeding import OPACITY_PRIOR, SCALE_PRIOR


@dataclass(frozen=True)
class InitHeadConfig:
    feature_channels: int = knob(8, "Adapter output width the head takes.")
    width: int = knob(32, "Width of the head's 1x1 layers.")
    sh_degree: int = knob(
        0, "SH degree the head predicts (higher bands start at zero in the scene set; one view cannot observe them)."
    )

    def __post_init__(self) -> None:
        if self.feature_channels < 1 or self.width < 1 or not 0 <= self.sh_degree <= MAX_SH_DEGREE:
            raise ValueError(f"invalid InitHeadConfig {self}")

    @property
    def out_channels(self) -> int:
        """opacity (1) + SH (3K) + log-scale (3) + quaternion (4)."""
        return residual_channels(self.sh_degree)

    def as_dict(self) -> dict:
        return asdict(self)


class InitHead(nn.Module):
    """(B, feature_channels, H, W) features + (B, PRIOR_CHANNELS, H, W) prior -> (B, out_channels, H, W) residuals."""

    def __init__(self, cfg: InitHeadConfig = InitHeadConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        self.conv1 = nn.Conv2d(cfg.feature_channels + PRIOR_CHANNELS, cfg.width, 1)
        self.conv2 = nn.Conv2d(cfg.width, cfg.width, 1)
        self.out = nn.Conv2d(cfg.width, cfg.out_channels, 1)
        for m in (self.conv1, self.conv2):
            nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
            nn.init.zeros_(m.bias)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, feats: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
        if feats.ndim != 4 or feats.shape[1] != self.cfg.feature_channels:
            raise ValueError(
                f"features must have shape (B, {self.cfg.feature_channels}, H, W), got {tuple(feats.shape)}"
            )
        if prior.shape[0] != feats.shape[0] or prior.shape[1] != PRIOR_CHANNELS or prior.shape[2:] != feats.shape[2:]:
            raise ValueError(
                f"prior must have shape {(feats.shape[0], PRIOR_CHANNELS, *feats.shape[2:])}, got {tuple(prior.shape)}"
            )
        x = torch.relu(self.conv1(torch.cat([feats, prior], dim=1)))
        x = torch.relu(self.conv2(x))
        return self.out(x)


def decode_gaussians(
    raw: torch.Tensor,
    rgb: torch.Tensor,
    centres: torch.Tensor,
    depth: torch.Tensor,
    focal_px: float,
    spacing_px: float,
    head_sh_degree: int,
    sh_degree: int,
) -> dict[str, torch.Tensor]:
    """Gaussian attributes of N selected pixels.

    raw (N, out_channels) head residuals at those pixels; rgb (N, 3) in [0, 1]; centres (N, 3);
    depth (N,) camera z; spacing_px: distance between instantiated pixels. Returns tensors for
    :mod:`.params` with SH of ``sh_degree`` (bands the head does not predict are zero).
    """
    n = raw.shape[0]
    k_head = sh_coeff_count(head_sh_degree)
    k = sh_coeff_count(sh_degree)
    if raw.ndim != 2 or raw.shape[1] != residual_channels(head_sh_degree):
        raise ValueError(f"raw must have shape (N, {residual_channels(head_sh_degree)}), got {tuple(raw.shape)}")
    if k < k_head:
        raise ValueError(f"scene SH degree {sh_degree} is below the head's {head_sh_degree}")
    sl = residual_slices(head_sh_degree)
    opacity = raw[:, OPACITY_CHANNEL] + math.log(OPACITY_PRIOR / (1.0 - OPACITY_PRIOR))
    sh_head = raw[:, sl["sh"]].reshape(n, k_head, 3)
    dc = (rgb - 0.5) / SH_C0
    sh = torch.cat([(sh_head[:, :1] + dc[:, None]), sh_head[:, 1:], raw.new_zeros((n, k - k_head, 3))], dim=1)
    base_scale = torch.log(SCALE_PRIOR * spacing_px * depth / focal_px)  # splatcore.seeding.start_log_scales
    log_scales = raw[:, sl["log_scales"]] + base_scale[:, None]
    quats = raw[:, sl["quats"]] + raw.new_tensor(IDENTITY_QUAT)
    return {"means": centres, "log_scales": log_scales, "quats": quats, "opacity_logits": opacity, "sh": sh}
