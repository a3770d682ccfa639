"""From views to Gaussians: the adapter and init head run on one view; views merge into a scene set.

Every valid pixel could become a Gaussian, far more than a CPU can optimise. Merging keeps, per view,
only the pixels no earlier view already seeded (acesplat/splatcore/fusion.py), then takes them on a lattice
whose stride is chosen so the set fits the budget of initial Gaussians (acesplat/splatcore/lattice.py), each
coloured by its block (acesplat/splatcore/seeding.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn

from acesplat.core.config import knob_default
from acesplat.splat.adapter import AdapterConfig, FeatureAdapter
from acesplat.splat.init_head import InitHead, InitHeadConfig, decode_gaussians
from acesplat.splat.params import cat_tensors
from acesplat.splat.views import SplatView
from acesplat.splatcore.fusion import DEPTH_TOLERANCE, novel_masks
from acesplat.splatcore.head_io import SceneNorm, coordinate_prior
from acesplat.splatcore.lattice import choose_stride, lattice_pixels
from acesplat.splatcore.pixel_coords import filled_depths, pixel_coordinates
from acesplat.splatcore.seeding import block_colours
from acesplat.splatcore.validity import ValidityConfig


@dataclass
class ViewPixels:
    """What the head needs of one view at pixel resolution (flat arrays are row-major over H x W)."""

    centres: torch.Tensor  # (H*W, 3) world
    depth: torch.Tensor  # (H*W,) camera z
    rgb: torch.Tensor  # (H*W, 3)
    prior: torch.Tensor  # (1, PRIOR_CHANNELS, H, W)
    valid: np.ndarray  # (H, W) bool: may seed a Gaussian
    trusted: np.ndarray  # (H, W) bool: its depth comes from trusted cells (valid minus the filled pixels)

    @property
    def shape(self) -> tuple[int, int]:
        return self.valid.shape  # type: ignore[return-value]

    def depth_map(self) -> np.ndarray:
        return self.depth.numpy().reshape(self.shape)

    def centre_map(self) -> np.ndarray:
        return self.centres.numpy().reshape(*self.shape, 3)


def view_pixels(
    view: SplatView,
    norm: SceneNorm,
    max_depth_ratio: float = knob_default(ValidityConfig, "max_depth_ratio"),
    fill: bool = False,
) -> ViewPixels:
    """Pixel-resolution centres, depths, prior and validity of a view whose SCR outputs are filled.

    With ``fill``, pixels without a trusted depth (but in a view with some trusted cells) may seed
    Gaussians too, at the depth of the nearest trusted cell: on their own rays, so their own view
    still sees them in the right place, and the optimisation moves them.
    """
    if view.coords is None or view.validity is None:
        raise ValueError(f"view {view.name} has no SCR coordinates; run views.run_scr first")
    centres, depth, trusted = pixel_coordinates(
        view.coords, view.validity.valid, view.pose, view.intrinsics, max_depth_ratio
    )
    valid = trusted
    if fill and view.validity.valid.any():
        c_fill, d_fill = filled_depths(view.coords, view.validity.valid, view.pose, view.intrinsics)
        centres = np.where(trusted[..., None], centres, c_fill)
        depth = np.where(trusted, depth, d_fill)
        valid = depth > 0
    prior = coordinate_prior(view.rgb, centres, depth, norm)
    return ViewPixels(
        centres=torch.from_numpy(centres.reshape(-1, 3).astype(np.float32)),
        depth=torch.from_numpy(depth.reshape(-1).astype(np.float32)),
        rgb=torch.from_numpy(view.rgb.reshape(-1, 3)),
        prior=torch.from_numpy(prior)[None],
        valid=valid,
        trusted=trusted,
    )


class GaussianInitializer(nn.Module):
    """The adapter and the init head together: a view's features and pixels -> its Gaussians."""

    def __init__(self, adapter_cfg: AdapterConfig, head_cfg: InitHeadConfig) -> None:
        super().__init__()
        if adapter_cfg.out_channels != head_cfg.feature_channels:
            raise ValueError(
                f"adapter gives {adapter_cfg.out_channels} channels, head expects {head_cfg.feature_channels}"
            )
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
        """Gaussians (differentiable in the adapter and head) at flat pixel ``indices`` (N,) of a view,
        coloured by the image low-passed at ``spacing_px``."""
        raw = self.raw(view, pix)
        dev = raw.device
        idx = torch.from_numpy(np.asarray(indices, np.int64)).to(dev)
        r = raw[0].reshape(raw.shape[1], -1)[:, idx].T
        focal = 0.5 * (view.intrinsics.fx + view.intrinsics.fy)
        rgb = torch.from_numpy(block_colours(view.rgb, spacing_px).reshape(-1, 3)).to(dev)[idx]
        return decode_gaussians(
            r,
            rgb,
            pix.centres.to(dev)[idx],
            pix.depth.to(dev)[idx],
            focal,
            spacing_px,
            self.head.cfg.sh_degree,
            sh_degree,
        )


@dataclass
class MergeReport:
    stride: int
    novel_pixels: int
    per_view: list[int]


@torch.no_grad()
def merge_views(
    views: Sequence[SplatView],
    pixels: Sequence[ViewPixels],
    init: GaussianInitializer,
    max_gaussians: int,
    sh_degree: int,
    rng: np.random.Generator,
    fuse: bool = True,
    depth_tol: float = DEPTH_TOLERANCE,
) -> tuple[dict[str, torch.Tensor], MergeReport]:
    """One scene set from every view's novel pixels (all valid pixels without ``fuse``) on a lattice
    whose stride keeps the set near ``max_gaussians``."""
    if fuse:
        masks = novel_masks(
            [v.pose for v in views],
            [v.intrinsics for v in views],
            [p.centre_map() for p in pixels],
            [p.depth_map() for p in pixels],
            [p.valid for p in pixels],
            depth_tol=depth_tol,
        )
    else:
        masks = [p.valid for p in pixels]
    novel = int(sum(int(m.sum()) for m in masks))
    stride = choose_stride(novel, max_gaussians)
    parts, counts = [], []
    for v, pix, m in zip(views, pixels, masks):
        idx = lattice_pixels(m, stride, (int(rng.integers(stride)), int(rng.integers(stride))))
        counts.append(int(idx.size))
        if idx.size:
            parts.append(init.view_gaussians(v, pix, idx, float(stride), sh_degree))
    report = MergeReport(stride, novel, counts)
    if not parts:
        return {}, report
    return cat_tensors(parts), report
