"""Desktop localization and evaluation: SCR prediction at 1/8 resolution, then the shared PnP solver."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import pose_error
from acesplat.core.metrics import FrameResult, accuracy_summary
from acesplat.core.pnp import OUTPUT_STRIDE, PnPResult, solve_from_grid
from acesplat.core.preprocess import size_for_short_side, to_gray_input
from acesplat.core.scene import SceneSplit

from .network import SCRNetwork


@dataclass
class Localizer:
    """An SCR network plus the resolution it was mapped at and the PnP settings."""

    network: SCRNetwork
    short_side: int
    pnp: dict
    input_size: tuple[int, int] | None = None
    """Exact (H, W) to run at instead of the short side's (a bundle's stride-aligned size, for parity)."""
    output_stride: int = OUTPUT_STRIDE
    """DENSE_OUTPUT_STRIDE predicts four times the cells (half-cell shifts) at about four times the network's
    cost; the errors of shifted cells are partly independent, so PnP averages more of them out."""

    @torch.no_grad()
    def predict(self, rgb: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray, Intrinsics]:
        """Scene coordinates (h, w, 3), spaced ``output_stride`` pixels apart, for an RGB image (H, W, 3), and
        the intrinsics of the network input."""
        size = self.input_size or size_for_short_side(rgb.shape[0], rgb.shape[1], self.short_side)
        gray, intr = to_gray_input(rgb, intrinsics, size)
        x = torch.from_numpy(gray)[None, None]
        coords = self.network(x, self.output_stride)[0].permute(1, 2, 0).numpy()
        return coords, intr

    def localize(self, rgb: np.ndarray, intrinsics: Intrinsics) -> PnPResult:
        coords, intr = self.predict(rgb, intrinsics)
        return solve_from_grid(coords, intr, stride=self.output_stride, **self.pnp)


def evaluate(
    split: SceneSplit, localizer: Localizer, progress: Callable[[int, int], None] | None = None
) -> dict:
    """Localize every frame of a split and compare with its pose; the `acesplat eval` JSON."""
    results = []
    estimates = []
    for i, frame in enumerate(split.frames):
        rgb = frame.load_rgb()
        t0 = time.perf_counter()
        res = localizer.localize(rgb, frame.intrinsics)
        ms = (time.perf_counter() - t0) * 1000.0
        if res.T_c2w is not None:
            t_err, r_err = pose_error(res.T_c2w, frame.pose)
        else:
            t_err, r_err = float("inf"), float("inf")
        results.append(FrameResult(frame.name, res.localized, t_err, r_err, res.inliers, ms))
        estimates.append(res.T_c2w)
        if progress:
            progress(i + 1, len(split.frames))
    summary = accuracy_summary(results)
    summary["estimates"] = estimates
    return summary
