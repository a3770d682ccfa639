"""The Stage 2 rendering loss and image metrics: (1 - lambda) MSE + lambda D-SSIM, SSIM, PSNR.

SSIM follows the 3DGS training code's convention: an 11x11 Gaussian window (sigma 1.5), statistics
per channel, zero padding at the border (so every pixel gets a value and a gradient), the map averaged.
Images are torch tensors (..., H, W, 3) with values in [0, 1], the rasterizer's layout.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2
"""Wang et al.'s stabilising constants for a data range of 1."""
DSSIM_WEIGHT = 0.2
"""lambda of the rendering loss (3DGS and the paper)."""


def gaussian_window(
    size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA, dtype: torch.dtype = torch.float32
) -> torch.Tensor:
    """Normalised 1D Gaussian weights (size,); the 2D window is its outer product."""
    if size < 1 or size % 2 == 0:
        raise ValueError(f"window size must be odd and positive, got {size}")
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    w = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (w / w.sum()).to(dtype)


def _as_bchw(img: torch.Tensor, name: str) -> torch.Tensor:
    if not isinstance(img, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(img).__name__}")
    if img.ndim < 3 or img.shape[-1] not in (1, 3):
        raise ValueError(f"{name} must have shape (..., H, W, C) with C = 1 or 3, got {tuple(img.shape)}")
    h, w, c = img.shape[-3:]
    return img.reshape(-1, h, w, c).permute(0, 3, 1, 2)


def _blur(x: torch.Tensor, win: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter of (B, C, H, W), zero padded, per channel."""
    c = x.shape[1]
    k = win.shape[0]
    pad = k // 2
    x = F.conv2d(x, win.view(1, 1, 1, k).expand(c, 1, 1, k), padding=(0, pad), groups=c)
    return F.conv2d(x, win.view(1, 1, k, 1).expand(c, 1, k, 1), padding=(pad, 0), groups=c)


def ssim_map(
    img: torch.Tensor, ref: torch.Tensor, window: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA
) -> torch.Tensor:
    """Per-pixel, per-channel SSIM (B, C, H, W) of two images (..., H, W, C) in [0, 1]."""
    x = _as_bchw(img, "img")
    y = _as_bchw(ref, "ref")
    if x.shape != y.shape:
        raise ValueError(f"img and ref shapes differ: {tuple(img.shape)} vs {tuple(ref.shape)}")
    win = gaussian_window(window, sigma, x.dtype).to(x.device)
    mu_x, mu_y = _blur(x, win), _blur(y, win)
    sxx = _blur(x * x, win) - mu_x * mu_x
    syy = _blur(y * y, win) - mu_y * mu_y
    sxy = _blur(x * y, win) - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sxy + SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (sxx + syy + SSIM_C2)
    return num / den


def ssim(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean SSIM (a scalar tensor) of two images (..., H, W, C)."""
    return ssim_map(img, ref).mean()


def mse(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    if img.shape != ref.shape:
        raise ValueError(f"img and ref shapes differ: {tuple(img.shape)} vs {tuple(ref.shape)}")
    return torch.mean((img - ref) ** 2)


def rendering_loss(img: torch.Tensor, ref: torch.Tensor, lam: float = DSSIM_WEIGHT) -> torch.Tensor:
    """(1 - lam) MSE + lam (1 - SSIM): the Stage 2 objective for one rendered view."""
    return (1.0 - lam) * mse(img, ref) + lam * (1.0 - ssim(img, ref))


def psnr_from_mse(m: float) -> float:
    """PSNR in dB for a data range of 1 (inf for a perfect match)."""
    return float("inf") if m <= 0 else -10.0 * math.log10(m)


def psnr(img: torch.Tensor, ref: torch.Tensor) -> float:
    """PSNR in dB of two images in [0, 1]."""
    return psnr_from_mse(float(mse(img.detach().double(), ref.detach().double())))
