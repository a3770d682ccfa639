"""From views to Gaussians: the adapter and init head run on one view; views merge into a scene set.

Every valid pixel could become a Gaussian, far more than a CPU can optimise, so pixels are taken on
a lattice of ``stride`` (with a per-view offset, so overlapping views do not stack their Gaussians
on one lattice) and the stride is chosen from the budget of initial Gaussians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
import torch.nn as nn

from .adapter import AdapterConfig, FeatureAdapter
from .init_head import InitHead, InitHeadConfig, SceneNorm, coordinate_prior, decode_gaussians
from .params import cat_tensors
from .pixel_coords import pixel_coordinates
from .validity import MAX_DEPTH_RATIO
from .views import SplatView


@dataclass
class ViewPixels:
    """What the head needs of one view at pixel resolution (flat arrays are row-major over H x W)."""

    centres: torch.Tensor  # (H*W, 3) world
    depth: torch.Tensor  # (H*W,) camera z
    rgb: torch.Tensor  # (H*W, 3)
    prior: torch.Tensor  # (1, PRIOR_CHANNELS, H, W)
    valid: np.ndarray  # (H, W) bool


def view_pixels(view: SplatView, norm: SceneNorm, max_depth_ratio: float = MAX_DEPTH_RATIO) -> ViewPixels:
    """Pixel-resolution centres, depths, prior and validity of a view whose SCR outputs are filled."""
    if view.coords is None or view.validity is None:
        raise ValueError(f"view {view.name} has no SCR coordinates; run views.run_scr first")
    centres, depth, valid = pixel_coordinates(view.coords, view.validity.valid, view.pose, view.intrinsics, max_depth_ratio)
    prior = coordinate_prior(view.rgb, centres, depth, norm)
    return ViewPixels(
        centres=torch.from_numpy(centres.reshape(-1, 3).astype(np.float32)),
        depth=torch.from_numpy(depth.reshape(-1).astype(np.float32)),
        rgb=torch.from_numpy(view.rgb.reshape(-1, 3)),
        prior=torch.from_numpy(prior)[None],
        valid=valid,
    )


def lattice_pixels(valid: np.ndarray, stride: int, offset: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Flat indices (N,) of the valid pixels at rows offset[0] + k*stride and columns offset[1] + l*stride."""
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    H, W = valid.shape
    oy, ox = offset[0] % stride, offset[1] % stride
    sel = np.zeros_like(valid, dtype=bool)
    sel[oy::stride, ox::stride] = True
    return np.flatnonzero(sel & valid)


def choose_stride(valid_pixels: int, max_gaussians: int) -> int:
    """Smallest lattice stride that keeps about ``valid_pixels / stride^2`` within ``max_gaussians``."""
    if max_gaussians < 1:
        raise ValueError(f"max_gaussians must be >= 1, got {max_gaussians}")
    return max(1, math.ceil(math.sqrt(valid_pixels / max_gaussians)))


class GaussianInitializer(nn.Module):
    """The adapter and the init head together: a view's features and pixels -> its Gaussians."""

    def __init__(self, adapter_cfg: AdapterConfig, head_cfg: InitHeadConfig) -> None:
        super().__init__()
        if adapter_cfg.out_channels != head_cfg.feature_channels:
            raise ValueError(f"adapter gives {adapter_cfg.out_channels} channels, head expects {head_cfg.feature_channels}")
        self.adapter = FeatureAdapter(adapter_cfg)
        self.head = InitHead(head_cfg)

    def raw(self, view: SplatView, pix: ViewPixels) -> torch.Tensor:
        """Head residuals (1, out_channels, H, W) of a view."""
        if view.features is None:
            raise ValueError(f"view {view.name} has no cached features")
        dev = self.head.out.weight.device
        H, W = view.size
        feats = self.adapter(view.features.to(dev).float(), H, W)
        return self.head(feats, pix.prior.to(dev))

    def view_gaussians(
        self, view: SplatView, pix: ViewPixels, indices: np.ndarray, spacing_px: float, sh_degree: int
    ) -> dict[str, torch.Tensor]:
        """Gaussians (differentiable in the adapter and head) at flat pixel ``indices`` (N,) of a view."""
        raw = self.raw(view, pix)
        dev = raw.device
        idx = torch.from_numpy(np.asarray(indices, np.int64)).to(dev)
        r = raw[0].reshape(raw.shape[1], -1)[:, idx].T
        focal = 0.5 * (view.intrinsics.fx + view.intrinsics.fy)
        return decode_gaussians(
            r, pix.rgb.to(dev)[idx], pix.centres.to(dev)[idx], pix.depth.to(dev)[idx],
            focal, spacing_px, self.head.cfg.sh_degree, sh_degree,
        )


@torch.no_grad()
def merge_views(
    views: Sequence[SplatView],
    pixels: Sequence[ViewPixels],
    init: GaussianInitializer,
    stride: int,
    sh_degree: int,
    rng: np.random.Generator,
) -> tuple[dict[str, torch.Tensor], list[int]]:
    """One over-complete scene set from every view's lattice pixels, and how many each view gave."""
    parts, counts = [], []
    for v, pix in zip(views, pixels):
        idx = lattice_pixels(pix.valid, stride, (int(rng.integers(stride)), int(rng.integers(stride))))
        counts.append(int(idx.size))
        if idx.size:
            parts.append(init.view_gaussians(v, pix, idx, float(stride), sh_degree))
    if not parts:
        return {}, counts
    return cat_tensors(parts), counts
