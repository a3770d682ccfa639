"""Dense feature upsampling adapter: SCR features at 1/8 resolution -> per-pixel features.

Three stages of x2 bilinear upsampling, each followed by a 3x3 convolution, so every pixel gets a
feature and no transposed convolution can leave checkerboard artefacts. Bilinear upsampling with
``align_corners=False`` keeps cell (i, j) of the 1/8 grid centred on the pixels it was computed
from (rows 8i..8i+7, columns 8j..8j+7: the peak lands on pixels 8i+3..8i+4, 8j+3..8j+4, beside
the grid's nominal centre (8j+4, 8i+4)); a grid rounded up to a multiple of 8 is cropped at the
bottom and right, where its extra cells are.

Widths shrink as resolution grows so the full-resolution convolution stays cheap on a CPU.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from acesplat.core.config import knob

UPSAMPLE_STAGES = 3
"""Three x2 stages: 1/8 -> 1/4 -> 1/2 -> 1/1."""


@dataclass(frozen=True)
class AdapterConfig:
    """Input feature width and the widths at 1/8 (after a 1x1 reduction), 1/4, 1/2 and full resolution."""

    in_channels: int = knob(512, "Width of the SCR encoder's features (set from the map's encoder).")
    widths: tuple[int, int, int, int] = knob(
        (32, 24, 16, 8), "Widths at 1/8, 1/4, 1/2 and full resolution (narrow where the resolution is high: CPU cost)."
    )

    def __post_init__(self) -> None:
        if len(self.widths) != UPSAMPLE_STAGES + 1 or min(self.widths) < 1 or self.in_channels < 1:
            raise ValueError(
                f"AdapterConfig needs in_channels >= 1 and {UPSAMPLE_STAGES + 1} positive widths, got {self}"
            )

    @property
    def out_channels(self) -> int:
        return self.widths[-1]

    def as_dict(self) -> dict:
        d = asdict(self)
        d["widths"] = list(self.widths)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> AdapterConfig:
        return cls(in_channels=int(d["in_channels"]), widths=tuple(int(v) for v in d["widths"]))  # type: ignore[arg-type]


def upsample2(x: torch.Tensor) -> torch.Tensor:
    """x2 bilinear upsampling with half-pixel-centre alignment (B, C, h, w) -> (B, C, 2h, 2w)."""
    return F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False)


class FeatureAdapter(nn.Module):
    """(B, in_channels, h, w) SCR features -> (B, out_channels, H, W) with H <= 8h, W <= 8w."""

    def __init__(self, cfg: AdapterConfig = AdapterConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        w = cfg.widths
        self.reduce = nn.Conv2d(cfg.in_channels, w[0], 1)
        self.convs = nn.ModuleList(
            nn.Conv2d(w[i], w[i + 1], 3, padding=1, padding_mode="replicate") for i in range(UPSAMPLE_STAGES)
        )
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
                nn.init.zeros_(m.bias)

    def forward(self, feats: torch.Tensor, height: int, width: int) -> torch.Tensor:
        if feats.ndim != 4 or feats.shape[1] != self.cfg.in_channels:
            raise ValueError(f"features must have shape (B, {self.cfg.in_channels}, h, w), got {tuple(feats.shape)}")
        h, w = feats.shape[-2:]
        scale = 2**UPSAMPLE_STAGES
        if not (scale * (h - 1) < height <= scale * h and scale * (w - 1) < width <= scale * w):
            raise ValueError(f"a {h}x{w} feature grid (stride {scale}) does not cover a {height}x{width} image")
        x = F.relu(self.reduce(feats))
        for conv in self.convs:
            x = F.relu(conv(upsample2(x)))
        return x[:, :, :height, :width]
