"""Training the adapter and init head under the rendering loss.

One step: a view's Gaussians come out of the head on a fine pixel lattice (random offset), are
rendered into that view or one of its nearest neighbours, and the rendering loss flows back through
the rasterizer into the head and the adapter. Rendering into a neighbour is what teaches the head
opacities and scales that hold up away from the view they came from.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from acesplat.core.config import knob_default
from acesplat.splat.instantiate import GaussianInitializer, ViewPixels, view_pixels
from acesplat.splat.losses import rendering_loss
from acesplat.splat.raster_torch import render
from acesplat.splat.views import SplatView
from acesplat.splatcore.head_io import SceneNorm
from acesplat.splatcore.lattice import lattice_pixels
from acesplat.splatcore.validity import ValidityConfig

HEAD_STRIDE = 2
"""Lattice stride of the Gaussians a head step renders (finer than the scene set's; one view only)."""
HEAD_NEIGHBOURS = 3
"""A head step renders into its own view or one of this many nearest views."""


def nearest_views(poses: np.ndarray, k: int) -> np.ndarray:
    """(V, min(k, V-1)) indices of each camera's nearest other cameras, by centre distance among those
    looking within 90 degrees of its own direction (all of them if none does)."""
    poses = np.asarray(poses, np.float64)
    v = len(poses)
    k = min(k, v - 1)
    if k <= 0:
        return np.zeros((v, 0), np.int64)
    c = poses[:, :3, 3]
    fwd = poses[:, :3, 2]
    d = np.linalg.norm(c[:, None] - c[None], axis=-1)
    d = np.where(fwd @ fwd.T > 0.0, d, d + 1e6)
    np.fill_diagonal(d, np.inf)
    return np.argsort(d, axis=1, kind="stable")[:, :k]


class HeadTrainer:
    """Rendering-loss steps for the initializer over a set of views with cached features."""

    def __init__(
        self,
        init: GaussianInitializer,
        views: Sequence[SplatView],
        norm: SceneNorm,
        sh_degree: int,
        stride: int = HEAD_STRIDE,
        neighbours: int = HEAD_NEIGHBOURS,
        background: np.ndarray | None = None,
        fill: bool = False,
        max_depth_ratio: float = knob_default(ValidityConfig, "max_depth_ratio"),
    ) -> None:
        self.init = init
        self.views = list(views)
        self.norm = norm
        self.sh_degree = sh_degree
        self.stride = stride
        self.fill = fill
        self.max_depth_ratio = max_depth_ratio
        self.neighbours = nearest_views(np.stack([v.pose for v in self.views]), neighbours)
        self.background = np.zeros(3) if background is None else np.asarray(background, np.float64)
        self._pixels: dict[int, ViewPixels] = {}
        self.targets = [torch.from_numpy(v.rgb) for v in self.views]

    def pixels(self, i: int) -> ViewPixels:
        if i not in self._pixels:
            self._pixels[i] = view_pixels(self.views[i], self.norm, self.max_depth_ratio, fill=self.fill)
        return self._pixels[i]

    def loss(self, rng: np.random.Generator) -> torch.Tensor | None:
        """The rendering loss of one random view's head Gaussians in it or a neighbour (None if it has no valid
        pixel)."""
        i = int(rng.integers(len(self.views)))
        pix = self.pixels(i)
        idx = lattice_pixels(pix.valid, self.stride, (int(rng.integers(self.stride)), int(rng.integers(self.stride))))
        if idx.size == 0:
            return None
        g = self.init.view_gaussians(self.views[i], pix, idx, float(self.stride), self.sh_degree)
        nb = self.neighbours[i]
        j = i if nb.size == 0 or rng.random() < 1.0 / (nb.size + 1) else int(nb[rng.integers(nb.size)])
        t = self.views[j]
        out = render(
            g["means"],
            g["log_scales"],
            g["quats"],
            g["opacity_logits"],
            g["sh"],
            t.pose,
            t.intrinsics,
            self.background,
            sh_degree=min(self.sh_degree, self.init.head.cfg.sh_degree),
        )
        return rendering_loss(out.color, self.targets[j].to(out.color.device))
