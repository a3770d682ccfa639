"""Gaussian initialisation head: per-pixel Gaussian attributes from [adapted features, coordinate prior].

Fully convolutional. It predicts residuals around an analytic start, with its last layer zeroed so a
fresh head already gives a usable set: colour = the pixel's colour (SH DC), opacity = OPACITY_PRIOR,
an isotropic scale that covers the spacing between instantiated pixels at the pixel's depth, identity
rotation. Centres are not predicted: they are the SCR coordinates at pixel resolution
(:mod:`.pixel_coords`). The coordinate prior holds the pixel's colour, its centre in normalised scene
coordinates and its log depth; colour is part of it because the SCR encoder sees grayscale only.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn as nn

from acesplat.core.gaussians import MAX_SH_DEGREE, SH_C0, sh_coeff_count

OPACITY_PRIOR = 0.8
"""Opacity a fresh head gives every Gaussian (3DGS starts random points at 0.1; ours sit on surfaces)."""
SCALE_PRIOR = 0.7
"""Standard deviation of a fresh Gaussian in units of the spacing between instantiated pixels."""
PRIOR_CHANNELS = 7
"""rgb - 0.5 (3), normalised world centre (3), log(depth / scene scale) (1)."""


@dataclass(frozen=True)
class InitHeadConfig:
    feature_channels: int = 8
    """Adapter output width."""
    width: int = 32
    sh_degree: int = 0
    """SH degree the head predicts (higher bands start at zero in the scene set; one view cannot observe them)."""

    def __post_init__(self) -> None:
        if self.feature_channels < 1 or self.width < 1 or not 0 <= self.sh_degree <= MAX_SH_DEGREE:
            raise ValueError(f"invalid InitHeadConfig {self}")

    @property
    def out_channels(self) -> int:
        """opacity (1) + SH (3K) + log-scale (3) + quaternion (4)."""
        return 1 + 3 * sh_coeff_count(self.sh_degree) + 3 + 4

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class SceneNorm:
    """Centre and scale (metres) that bring the scene's coordinates to roughly unit size for the head."""

    centre: tuple[float, float, float]
    scale: float

    @classmethod
    def from_views(cls, camera_centres: np.ndarray, depths: np.ndarray) -> SceneNorm:
        c = np.asarray(camera_centres, np.float64).reshape(-1, 3)
        d = np.asarray(depths, np.float64).reshape(-1)
        spread = float(np.max(np.linalg.norm(c - c.mean(0), axis=1))) if len(c) else 0.0
        depth = float(np.median(d)) if d.size else 1.0
        return cls(tuple(float(v) for v in c.mean(0)), max(spread, depth, 1e-3))  # type: ignore[arg-type]

    def as_dict(self) -> dict:
        return {"centre": list(self.centre), "scale": self.scale}


def coordinate_prior(rgb: np.ndarray, centres: np.ndarray, depth: np.ndarray, norm: SceneNorm) -> np.ndarray:
    """The head's prior input (PRIOR_CHANNELS, H, W) float32 from rgb (H, W, 3) in [0, 1], world
    centres (H, W, 3) and camera depths (H, W)."""
    c = (centres - np.asarray(norm.centre)) / norm.scale
    logd = np.log(np.maximum(depth, 1e-6) / norm.scale)[..., None]
    prior = np.concatenate([rgb - 0.5, c, logd], axis=-1)
    return np.ascontiguousarray(np.nan_to_num(prior).transpose(2, 0, 1), dtype=np.float32)


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
    if raw.ndim != 2 or raw.shape[1] != 1 + 3 * k_head + 7:
        raise ValueError(f"raw must have shape (N, {1 + 3 * k_head + 7}), got {tuple(raw.shape)}")
    if k < k_head:
        raise ValueError(f"scene SH degree {sh_degree} is below the head's {head_sh_degree}")
    opacity = raw[:, 0] + math.log(OPACITY_PRIOR / (1.0 - OPACITY_PRIOR))
    sh_head = raw[:, 1 : 1 + 3 * k_head].reshape(n, k_head, 3)
    dc = (rgb - 0.5) / SH_C0
    sh = torch.cat([(sh_head[:, :1] + dc[:, None]), sh_head[:, 1:], raw.new_zeros((n, k - k_head, 3))], dim=1)
    base_scale = torch.log(SCALE_PRIOR * spacing_px * depth / focal_px)
    log_scales = raw[:, 1 + 3 * k_head : 4 + 3 * k_head] + base_scale[:, None]
    identity = raw.new_tensor([1.0, 0.0, 0.0, 0.0])
    quats = raw[:, 4 + 3 * k_head : 8 + 3 * k_head] + identity
    return {"means": centres, "log_scales": log_scales, "quats": quats, "opacity_logits": opacity, "sh": sh}
