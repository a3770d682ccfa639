"""Training views for Stage 2: images at the map's resolution, with the frozen SCR network's outputs.

Stage 2 works at the resolution the map was built for (shorter side = the map's ``short_side``), so
the 1/8 feature grid lines up with the pixels exactly; ground truth is resized the same way.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from acesplat.core.camera import Intrinsics
from acesplat.core.preprocess import size_for_short_side, to_gray_input
from acesplat.core.scene import Frame
from acesplat.splatcore.validity import CellValidity, ValidityConfig, cell_validity


@dataclass
class SplatView:
    """One posed image at Stage 2 resolution.

    rgb (H, W, 3) float32 in [0, 1]; gray (H, W) uint8 (the SCR input); pose (4, 4) camera-to-world.
    After :func:`run_scr`: coords (h, w, 3) SCR scene coordinates, validity per cell, and features
    (1, C, h, w) float16 when kept.
    """

    name: str
    pose: np.ndarray
    intrinsics: Intrinsics
    rgb: np.ndarray
    gray: np.ndarray
    coords: np.ndarray | None = None
    validity: CellValidity | None = None
    features: torch.Tensor | None = None

    @property
    def size(self) -> tuple[int, int]:
        return self.intrinsics.height, self.intrinsics.width


def resize_rgb(rgb: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """RGB uint8 -> float32 [0, 1] at ``size_hw`` (area averaging when shrinking, as the SCR input)."""
    h, w = size_hw
    if rgb.shape[:2] != (h, w):
        interp = cv2.INTER_AREA if h < rgb.shape[0] else cv2.INTER_LINEAR
        rgb = cv2.resize(rgb, (w, h), interpolation=interp)
    return rgb.astype(np.float32) / 255.0


def load_view(frame: Frame, short_side: int) -> SplatView:
    """Read ``frame`` and bring it to Stage 2 resolution (shorter side ``short_side``)."""
    rgb = frame.load_rgb()
    size = size_for_short_side(rgb.shape[0], rgb.shape[1], short_side)
    gray, intr = to_gray_input(rgb, frame.intrinsics, size)
    return SplatView(frame.name, np.asarray(frame.pose, np.float64), intr, resize_rgb(rgb, size), gray)


def load_views(frames: Sequence[Frame], short_side: int) -> list[SplatView]:
    return [load_view(f, short_side) for f in frames]


@torch.no_grad()
def run_scr(
    views: Sequence[SplatView],
    network: torch.nn.Module,
    validity: ValidityConfig = ValidityConfig(),
    keep_features: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> None:
    """Fill each view's SCR coordinates, cell validity and (optionally) encoder features, in place.

    ``network`` is an :class:`acesplat.scr.network.SCRNetwork` (encoder + head), run frozen.
    """
    from acesplat.scr.network import normalize_gray

    network.eval()
    dev = next(network.parameters()).device
    for i, v in enumerate(views):
        x = normalize_gray(torch.from_numpy(v.gray)[None, None].to(dev))
        feats = network.encoder(x)
        coords = network.head(feats)[0].permute(1, 2, 0).double().cpu().numpy()
        v.coords = coords.astype(np.float32)
        v.validity = cell_validity(coords, v.pose, v.intrinsics, validity)
        v.features = feats.to(torch.float16).cpu() if keep_features else None
        if progress:
            progress(i + 1, len(views))
