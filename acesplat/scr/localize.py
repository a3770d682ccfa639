"""Desktop localization and evaluation: SCR prediction at 1/8 resolution, the shared PnP solver, and optionally
the pose refined against the nearest mapping images (acesplat.align.keyframe_align)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import torch

from acesplat.align.flow_pnp import Alignment
from acesplat.align.keyframe_align import PreciseSettings, align_scr_start, scr_copy, size_for_scr
from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob
from acesplat.core.gate import GateConfig, gate_result, mirror_checked
from acesplat.core.geometry import pose_error
from acesplat.core.grid import OUTPUT_STRIDE
from acesplat.core.metrics import FrameResult, accuracy_summary
from acesplat.core.pnp import PnPConfig, PnPResult, solve_from_grid
from acesplat.core.preprocess import size_for_short_side, to_gray_input
from acesplat.core.scene import SceneSplit
from acesplat.scr.network import SCRNetwork

if TYPE_CHECKING:
    from acesplat.scr.keyframes import MapKeyframes


@dataclass
class Localizer:
    """An SCR network plus the resolution it was mapped at and the PnP settings."""

    network: SCRNetwork
    short_side: int
    pnp: PnPConfig | dict = knob(
        reason="PnP settings: a PnPConfig, or a dict of overrides of its defaults ({} for none).", factory=PnPConfig
    )
    gate: GateConfig = knob(reason="When a pose counts as localized (acesplat.core.gate).", factory=GateConfig)
    input_size: tuple[int, int] | None = None
    """Exact (H, W) to run at instead of the short side's (a bundle's stride-aligned size, for parity)."""
    output_stride: int = knob(
        OUTPUT_STRIDE,
        "Pixels between predicted cells: 8, or 4 (--dense) for 4x the correspondences at about 3.5x the time "
        "(bench/herz_gap.md).",
    )
    """DENSE_OUTPUT_STRIDE predicts four times the cells (half-cell shifts); the errors of shifted cells are
    partly independent, so PnP averages more of them out."""
    keyframes: MapKeyframes | None = None
    """The mapping images: a localized pose is then refined against its nearest ones (acesplat.align.keyframe_align)."""
    precise: PreciseSettings = knob(reason="SCR's size when keyframes refine the pose.", factory=PreciseSettings)

    def network_input(self, rgb: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray, Intrinsics]:
        """The grayscale network input (H', W') uint8 of an RGB image (H, W, 3), and its intrinsics."""
        size = self.input_size or size_for_short_side(rgb.shape[0], rgb.shape[1], self.short_side)
        return to_gray_input(rgb, intrinsics, size)

    @torch.no_grad()
    def coordinates(self, gray: np.ndarray) -> np.ndarray:
        """Scene coordinates (h, w, 3), spaced ``output_stride`` pixels apart, of a network input (H', W') uint8."""
        return self.network(torch.from_numpy(gray)[None, None], self.output_stride)[0].permute(1, 2, 0).numpy()

    def predict(self, rgb: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray, Intrinsics]:
        """Scene coordinates (h, w, 3) for an RGB image (H, W, 3), and the intrinsics of the network input."""
        gray, intr = self.network_input(rgb, intrinsics)
        return self.coordinates(gray), intr

    def localize(self, rgb: np.ndarray, intrinsics: Intrinsics) -> PnPResult:
        return self.localize_and_align(rgb, intrinsics)[0]

    def localize_and_align(self, rgb: np.ndarray, intrinsics: Intrinsics) -> tuple[PnPResult, Alignment | None]:
        """The pose, refined against the keyframes when there are any and the frame localized; and the
        alignment's record (None when none was tried). With keyframes SCR runs on a copy of PreciseSettings'
        shorter side and the alignment on the full input, as on the edge; a start the alignment cannot take is
        solved again at full size."""
        gray, intr = self.network_input(rgb, intrinsics)
        pnp = self.pnp if isinstance(self.pnp, PnPConfig) else replace(PnPConfig(), **self.pnp)
        view = None
        if self.keyframes is not None:
            size = size_for_scr(gray.shape, self.precise.scr_short_side)
            if tuple(size) != gray.shape:
                view = (gray, intr)
                gray, intr = scr_copy(gray, intr, size)
        res, coords = self._solve(gray, intr, pnp)
        if self.keyframes is None:
            return res, None
        res, al, _ = align_scr_start(
            res,
            coords,
            gray,
            intr,
            self.output_stride,
            self.keyframes.near,
            lambda g, i: self._solve(g, i, pnp),
            view=view,
        )
        return res, al

    def _solve(self, gray: np.ndarray, intr: Intrinsics, pnp: PnPConfig) -> tuple[PnPResult, np.ndarray]:
        """PnP + gate (+ the mirror check) of a network input; and its coordinates (h, w, 3)."""
        coords = self.coordinates(gray)
        res = solve_from_grid(coords, intr, stride=self.output_stride, config=pnp)
        res = gate_result(res, coords, intr, pnp, self.output_stride, self.gate)
        res = mirror_checked(res, gray, intr, self.coordinates, pnp, self.output_stride, self.gate)
        return res, coords


def evaluate(split: SceneSplit, localizer: Localizer, progress: Callable[[int, int], None] | None = None) -> dict:
    """Localize every frame of a split and compare with its pose; the `acesplat eval` JSON."""
    results = []
    estimates = []
    statuses: dict[str, int] = {}
    for i, frame in enumerate(split.frames):
        rgb = frame.load_rgb()
        t0 = time.perf_counter()
        res, al = localizer.localize_and_align(rgb, frame.intrinsics)
        ms = (time.perf_counter() - t0) * 1000.0
        if al is not None:
            statuses[al.status] = statuses.get(al.status, 0) + 1
        if res.T_c2w is not None:
            t_err, r_err = pose_error(res.T_c2w, frame.pose)
        else:
            t_err, r_err = float("inf"), float("inf")
        results.append(FrameResult(frame.name, res.localized, t_err, r_err, res.inliers, ms, res.T_c2w))
        estimates.append(res.T_c2w)
        if progress:
            progress(i + 1, len(split.frames))
    summary = accuracy_summary(results)
    if localizer.keyframes is not None:
        summary["keyframe_alignment"] = statuses
    summary["estimates"] = estimates
    return summary
