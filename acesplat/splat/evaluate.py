"""Rendering views of a finished set and scoring them against the ground truth (PSNR, SSIM, LPIPS).

Renders go through the numpy rasterizer (no autograd), exactly what the edge would render.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from acesplat.core.atomic import atomic_path
from acesplat.core.errors import InputError
from acesplat.core.gaussians import Gaussians
from acesplat.raster import rasterize
from acesplat.splat.losses import psnr, ssim
from acesplat.splat.views import SplatView


@dataclass
class FrameScore:
    name: str
    psnr: float
    ssim: float
    lpips: float | None = None


def render_image(g: Gaussians, view: SplatView, background: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """(H, W, 3) float32 render of ``g`` from ``view``'s camera, clipped to [0, 1]."""
    out = rasterize(g, view.pose, view.intrinsics, background=np.asarray(background, np.float64))
    return np.clip(out.color, 0.0, 1.0).astype(np.float32)


def write_comparison(path: Path, render: np.ndarray, truth: np.ndarray) -> None:
    """PNG of the render (left) beside the ground truth (right)."""
    side = np.concatenate([render, truth], axis=1)
    img = cv2.cvtColor(np.clip(np.rint(side * 255.0), 0, 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img):
            raise InputError(path, "cannot write PNG")


def evaluate_views(
    g: Gaussians,
    views: Sequence[SplatView],
    background: Sequence[float] = (0.0, 0.0, 0.0),
    out_dir: Path | None = None,
    lpips_fn: Callable[[torch.Tensor, torch.Tensor], float] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Mean PSNR / SSIM (and LPIPS with ``lpips_fn``) over ``views``; comparison PNGs into ``out_dir``."""
    scores = []
    for i, v in enumerate(views):
        img = render_image(g, v, background)
        a, b = torch.from_numpy(img), torch.from_numpy(v.rgb)
        with torch.no_grad():
            s = FrameScore(v.name, psnr(a, b), float(ssim(a.double(), b.double())))
            if lpips_fn is not None:
                s.lpips = float(lpips_fn(a, b))
        scores.append(s)
        if out_dir is not None:
            write_comparison(Path(out_dir) / f"{v.name}.png", img, v.rgb)
        if progress:
            progress(i + 1, len(views))
    out = {
        "psnr": float(np.mean([s.psnr for s in scores])) if scores else None,
        "ssim": float(np.mean([s.ssim for s in scores])) if scores else None,
        "frames": len(scores),
        "per_frame": [asdict(s) for s in scores],
    }
    if lpips_fn is not None:
        out["lpips"] = float(np.mean([s.lpips for s in scores])) if scores else None  # type: ignore[arg-type]
    return out
