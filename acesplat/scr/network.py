"""The SCR network: ACE's encoder/head architecture with widths as parameters.

State-dict names follow ACE's so a user's ``ace_encoder_pretrained.pt`` loads into ``Encoder``
(its widths are read from the tensors' shapes). Input: grayscale normalised as ACE does
((x / 255 - 0.4) / 0.25); output: scene coordinates at 1/8 resolution (1/4 with ``output_stride=4``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from acesplat.core.config import knob
from acesplat.core.grid import DENSE_OUTPUT_STRIDE, OUTPUT_STRIDE

GRAY_MEAN = 0.4
GRAY_STD = 0.25
"""ACE's grayscale normalisation (torchvision Normalize(mean=0.4, std=0.25) on [0, 1] intensities)."""

HOMOGENEOUS_MIN_SCALE = 0.01
HOMOGENEOUS_MAX_SCALE = 4.0


@dataclass(frozen=True)
class EncoderConfig:
    """Channel widths of the encoder stages: conv1..conv4, the 256-wide res1 block, the res2 block and the output."""

    c1: int = 32
    c2: int = 64
    c3: int = 128
    c4: int = 256
    res2: int = 512
    out: int = 512
    rank: int = 0
    """Channels ``res2_conv3`` passes through when it is built factorized (FactorizedConv2d); 0: a full layer."""
    separable: bool = False
    """``res2_conv3`` built as a 1x1 convolution into its output width, then a depthwise 3x3 (SeparableConv2d)."""

    def __post_init__(self) -> None:
        if self.rank and self.separable:
            raise ValueError("res2_conv3 is either factorized (rank) or separable, not both")

    @classmethod
    def from_state_dict(cls, sd: dict[str, torch.Tensor]) -> EncoderConfig:
        factorized = "res2_conv3.reduce.weight" in sd
        separable = "res2_conv3.point.weight" in sd
        out_key = "res2_conv3.expand" if factorized else "res2_conv3.point" if separable else "res2_conv3"
        return cls(
            c1=sd["conv1.weight"].shape[0],
            c2=sd["conv2.weight"].shape[0],
            c3=sd["conv3.weight"].shape[0],
            c4=sd["conv4.weight"].shape[0],
            res2=sd["res2_conv1.weight"].shape[0],
            out=sd[f"{out_key}.weight"].shape[0],
            rank=sd["res2_conv3.reduce.weight"].shape[0] if factorized else 0,
            separable=separable,
        )

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


ACE_ENCODER = EncoderConfig()
"""ACE's published encoder (39 GMAC at 480x640)."""


@dataclass(frozen=True)
class HeadConfig:
    """Scene-specific head: width of its 1x1 layers and the number of extra residual blocks."""

    width: int = knob(512, "Width of the head's 1x1 layers (ACE's 512).")
    blocks: int = knob(1, "Extra residual blocks of the head (ACE's 1).")
    homogeneous: bool = knob(True, "Predict homogeneous coordinates (ACE's clamped fourth channel) instead of xyz.")

    def as_dict(self) -> dict:
        return asdict(self)


class FactorizedConv2d(nn.Module):
    """A k x k convolution through ``rank`` channels: ``reduce`` (in -> rank, k x k), then ``expand`` (rank -> out,
    1 x 1), with no nonlinearity between. Built by acesplat.scr.lowrank from a full layer."""

    def __init__(self, in_channels: int, out_channels: int, rank: int, kernel_size: int) -> None:
        super().__init__()
        self.reduce = nn.Conv2d(in_channels, rank, kernel_size, 1, kernel_size // 2)
        self.expand = nn.Conv2d(rank, out_channels, 1, 1, 0)

    @property
    def kernel_size(self) -> tuple[int, int]:
        return self.reduce.kernel_size

    def forward(self, x: torch.Tensor, dilation: int = 1) -> torch.Tensor:
        """(B, in, h, w) -> (B, out, h, w); ``dilation`` as for the layer it replaces (the encoder's stride 4)."""
        r = self.reduce
        k = r.kernel_size[0]
        return self.expand(F.conv2d(x, r.weight, r.bias, padding=dilation * (k // 2), dilation=dilation))


class SeparableConv2d(nn.Module):
    """A k x k convolution as ``point`` (in -> out, 1 x 1) then ``depth`` (a k x k filter per output channel), with
    no nonlinearity between: about k^2 times cheaper than the full layer, and its outputs still span all ``out``
    directions (each channel filters its own combination of the inputs over the k x k window). Not the default
    encoder's: bench/encoder_rank.md measured what it costs the head on real scenes."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int) -> None:
        super().__init__()
        self.point = nn.Conv2d(in_channels, out_channels, 1, 1, 0)
        self.depth = nn.Conv2d(out_channels, out_channels, kernel_size, 1, kernel_size // 2, groups=out_channels)

    @property
    def kernel_size(self) -> tuple[int, int]:
        return self.depth.kernel_size

    def forward(self, x: torch.Tensor, dilation: int = 1) -> torch.Tensor:
        """(B, in, h, w) -> (B, out, h, w); ``dilation`` as for the layer it replaces (the encoder's stride 4)."""
        d = self.depth
        k = d.kernel_size[0]
        return F.conv2d(
            self.point(x), d.weight, d.bias, padding=dilation * (k // 2), dilation=dilation, groups=d.groups
        )


class Encoder(nn.Module):
    """Fully convolutional feature extractor with output stride 8."""

    def __init__(self, cfg: EncoderConfig = ACE_ENCODER) -> None:
        super().__init__()
        self.cfg = cfg
        self.conv1 = nn.Conv2d(1, cfg.c1, 3, 1, 1)
        self.conv2 = nn.Conv2d(cfg.c1, cfg.c2, 3, 2, 1)
        self.conv3 = nn.Conv2d(cfg.c2, cfg.c3, 3, 2, 1)
        self.conv4 = nn.Conv2d(cfg.c3, cfg.c4, 3, 2, 1)
        self.res1_conv1 = nn.Conv2d(cfg.c4, cfg.c4, 3, 1, 1)
        self.res1_conv2 = nn.Conv2d(cfg.c4, cfg.c4, 1, 1, 0)
        self.res1_conv3 = nn.Conv2d(cfg.c4, cfg.c4, 3, 1, 1)
        self.res2_conv1 = nn.Conv2d(cfg.c4, cfg.res2, 3, 1, 1)
        self.res2_conv2 = nn.Conv2d(cfg.res2, cfg.res2, 1, 1, 0)
        self.res2_conv3: nn.Module = (
            FactorizedConv2d(cfg.res2, cfg.out, cfg.rank, 3)
            if cfg.rank
            else SeparableConv2d(cfg.res2, cfg.out, 3)
            if cfg.separable
            else nn.Conv2d(cfg.res2, cfg.out, 3, 1, 1)
        )
        self.res2_skip = nn.Conv2d(cfg.c4, cfg.out, 1, 1, 0)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                # Default init makes deep ReLU features nearly constant; Kaiming keeps them informative.
                nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
                nn.init.zeros_(m.bias)

    def forward(self, x: torch.Tensor, output_stride: int = OUTPUT_STRIDE) -> torch.Tensor:
        """(B, 1, H, W) normalised grayscale -> (B, out, H/s, W/s) features, s = ``output_stride`` (8 or 4).

        At 4 the same weights run the last stage densely (conv4 without its stride, the 3x3 layers after it
        dilated by 2: "a trous"), which gives the features of the image shifted by half a cell in x, y and
        both in one pass: four times the cells at about four times the cost. Cell k of the dense grid is
        the pixel 4 k + 4, so its even cells are the stride-8 cells (8 j + 4).
        """
        if output_stride not in (OUTPUT_STRIDE, DENSE_OUTPUT_STRIDE):
            raise ValueError(f"output_stride must be {OUTPUT_STRIDE} or {DENSE_OUTPUT_STRIDE}, got {output_stride}")
        d = OUTPUT_STRIDE // output_stride

        def conv(m: nn.Module, x: torch.Tensor) -> torch.Tensor:
            """A layer after conv4: as built at stride 8, dilated by d at stride 4."""
            if d == 1:
                return m(x)
            if isinstance(m, (FactorizedConv2d, SeparableConv2d)):
                return m(x, dilation=d)
            k = m.kernel_size[0]
            return F.conv2d(x, m.weight, m.bias, padding=d * (k // 2), dilation=d)

        x = F.relu(self.conv1(x))
        x = F.relu(self.conv2(x))
        x = F.relu(self.conv3(x))
        if d == 1:
            res = F.relu(self.conv4(x))
        else:  # conv4 without its stride: the grid stays at stride 4
            res = F.relu(F.conv2d(x, self.conv4.weight, self.conv4.bias, padding=self.conv4.padding))
        x = F.relu(conv(self.res1_conv1, res))
        x = F.relu(conv(self.res1_conv2, x))
        x = F.relu(conv(self.res1_conv3, x))
        res = res + x
        x = F.relu(conv(self.res2_conv1, res))
        x = F.relu(conv(self.res2_conv2, x))
        x = F.relu(conv(self.res2_conv3, x))
        return conv(self.res2_skip, res) + x

    @classmethod
    def from_state_dict(cls, sd: dict[str, torch.Tensor]) -> Encoder:
        enc = cls(EncoderConfig.from_state_dict(sd))
        enc.load_state_dict(sd)
        return enc


class Head(nn.Module):
    """Per-pixel MLP (1x1 convolutions) from features to scene coordinates.

    Predicts homogeneous coordinates (x, y, z, h) with h kept in [1/max_scale, 1/min_scale] by a softplus,
    relative to ``mean`` (the mean training camera position), so a fresh head starts near the scene.
    """

    def __init__(self, mean: torch.Tensor, in_channels: int = 512, cfg: HeadConfig = HeadConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        w = cfg.width
        self.in_channels = in_channels
        self.head_skip = nn.Identity() if in_channels == w else nn.Conv2d(in_channels, w, 1, 1, 0)
        self.res3_conv1 = nn.Conv2d(in_channels, w, 1, 1, 0)
        self.res3_conv2 = nn.Conv2d(w, w, 1, 1, 0)
        self.res3_conv3 = nn.Conv2d(w, w, 1, 1, 0)
        self.res_blocks = nn.ModuleList(
            nn.ModuleList([nn.Conv2d(w, w, 1, 1, 0) for _ in range(3)]) for _ in range(cfg.blocks)
        )
        self.fc1 = nn.Conv2d(w, w, 1, 1, 0)
        self.fc2 = nn.Conv2d(w, w, 1, 1, 0)
        self.fc3 = nn.Conv2d(w, 4 if cfg.homogeneous else 3, 1, 1, 0)
        self.register_buffer("max_scale", torch.tensor([HOMOGENEOUS_MAX_SCALE]))
        self.register_buffer("min_scale", torch.tensor([HOMOGENEOUS_MIN_SCALE]))
        self.register_buffer("max_inv_scale", 1.0 / self.max_scale)
        self.register_buffer("h_beta", math.log(2) / (1.0 - self.max_inv_scale))
        self.register_buffer("min_inv_scale", 1.0 / self.min_scale)
        self.register_buffer("mean", torch.as_tensor(mean, dtype=torch.float32).clone().view(1, 3, 1, 1))
        # The same constants as plain floats for forward(): traced graphs (ONNX) then see literals, not tensor reads.
        self._h_beta = math.log(2) / (1.0 - 1.0 / HOMOGENEOUS_MAX_SCALE)
        self._max_inv_scale = 1.0 / HOMOGENEOUS_MAX_SCALE
        self._min_inv_scale = 1.0 / HOMOGENEOUS_MIN_SCALE

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        """(B, C, h, w) features -> (B, 3, h, w) scene coordinates."""
        return self._run(feats, lambda m, x: m(x), self.mean)

    def forward_points(self, feats: torch.Tensor, autocast_bf16: bool = False) -> torch.Tensor:
        """(N, C) features -> (N, 3) scene coordinates: the same network as matrix products.

        Training sees features as a flat batch; torch's CPU 1x1 convolution over a (1, C, N, 1) tensor is
        about 5x slower than the equivalent matrix product (measured in bench/head_speed.py). With
        ``autocast_bf16`` the hidden layers run in bfloat16 (AMX/AVX512-BF16 CPUs, CUDA); the output
        layer and the homogeneous division stay float32, so coordinates keep millimetre resolution.
        """
        if feats.dim() != 2 or feats.shape[1] != self.in_channels:
            raise ValueError(f"expected features (N, {self.in_channels}), got {tuple(feats.shape)}")

        def lin(m: nn.Module, x: torch.Tensor) -> torch.Tensor:
            if isinstance(m, nn.Identity):
                return x
            if m is self.fc3:
                with torch.autocast(feats.device.type, enabled=False):
                    return F.linear(x.float(), m.weight.flatten(1), m.bias)
            return F.linear(x, m.weight.flatten(1), m.bias)

        # One autocast region for the whole body: its cache converts each weight to bfloat16 once per call.
        with torch.autocast(feats.device.type, dtype=torch.bfloat16, enabled=autocast_bf16):
            return self._run(feats, lin, self.mean.view(1, 3))

    def _run(self, feats: torch.Tensor, lin: Callable, mean: torch.Tensor) -> torch.Tensor:
        """The head body, written once for both layouts: ``lin(layer, x)`` applies one 1x1 layer."""
        x = F.relu(lin(self.res3_conv1, feats))
        x = F.relu(lin(self.res3_conv2, x))
        x = F.relu(lin(self.res3_conv3, x))
        res = lin(self.head_skip, feats) + x
        for block in self.res_blocks:
            x = F.relu(lin(block[0], res))
            x = F.relu(lin(block[1], x))
            x = F.relu(lin(block[2], x))
            res = res + x
        sc = F.relu(lin(self.fc1, res))
        sc = F.relu(lin(self.fc2, sc))
        sc = lin(self.fc3, sc).float()
        if self.cfg.homogeneous:
            h = F.softplus(sc[:, 3:4], beta=self._h_beta) + self._max_inv_scale
            h = torch.clamp(h, max=self._min_inv_scale)
            sc = sc[:, :3] / h
        return sc + mean


def normalize_gray(gray_u8: torch.Tensor) -> torch.Tensor:
    """uint8 or float [0, 255] grayscale (B, 1, H, W) -> ACE's normalised input."""
    return (gray_u8.float() / 255.0 - GRAY_MEAN) / GRAY_STD


class SCRNetwork(nn.Module):
    """Encoder + head: raw grayscale in [0, 255] (B, 1, H, W) -> scene coordinates (B, 3, H/8, W/8).

    Normalisation happens inside so an exported graph needs nothing but the image.
    """

    def __init__(self, encoder: Encoder, head: Head) -> None:
        super().__init__()
        self.encoder = encoder
        self.head = head

    def forward(self, gray: torch.Tensor, output_stride: int = OUTPUT_STRIDE) -> torch.Tensor:
        """(B, 1, H, W) -> (B, 3, H/s, W/s) scene coordinates; ``output_stride`` as in Encoder.forward."""
        return self.head(self.encoder(normalize_gray(gray), output_stride))


def count_macs(encoder_cfg: EncoderConfig, head_cfg: HeadConfig, height: int, width: int) -> dict[str, float]:
    """Multiply-accumulates of encoder and head at an input size (convolutions only), in GMAC."""
    c = encoder_cfg
    h1, w1 = height, width
    h2, w2 = math.ceil(height / 2), math.ceil(width / 2)
    h4, w4 = math.ceil(h2 / 2), math.ceil(w2 / 2)
    h8, w8 = math.ceil(h4 / 2), math.ceil(w4 / 2)
    last = c.rank * (9 * c.res2 + c.out) if c.rank else c.out * (c.res2 + 9) if c.separable else 9 * c.res2 * c.out
    enc = (
        h1 * w1 * 9 * 1 * c.c1
        + h2 * w2 * 9 * c.c1 * c.c2
        + h4 * w4 * 9 * c.c2 * c.c3
        + h8 * w8 * (9 * c.c3 * c.c4 + 9 * c.c4 * c.c4 + c.c4 * c.c4 + 9 * c.c4 * c.c4)
        + h8 * w8 * (9 * c.c4 * c.res2 + c.res2 * c.res2 + c.c4 * c.out)
        + h8 * w8 * last
    )
    w = head_cfg.width
    head_layers = c.out * w * (2 if c.out != w else 1) + 2 * w * w + head_cfg.blocks * 3 * w * w + 2 * w * w + w * 4
    head = h8 * w8 * head_layers
    return {"encoder_gmac": enc / 1e9, "head_gmac": head / 1e9}
