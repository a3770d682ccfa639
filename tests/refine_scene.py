"""A tiny synthetic room and depth-seeded Gaussians for the refinement tests (shared helpers, no tests here)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from acesplat.core.gaussians import Gaussians, concat_gaussians
from acesplat.core.geometry import transform_points
from acesplat.core.scene import Frame, read_split
from acesplat.splatcore.seeding import gaussians_at
from edge.refine.guard import psnr, view_mse
from edge.refine.refiner import Keyframe

SIZE = (48, 64)
_CACHE: dict[str, Path] = {}


def tiny_room(tmp_path_factory) -> list[Frame]:
    """Training frames of the built-in room at 48x64 (written once per session)."""
    if "room" not in _CACHE:
        from acesplat.synth import synthesize

        out = tmp_path_factory.mktemp("refine") / "room"
        synthesize(out, seed=0, train_frames=16, test_frames=1, size=SIZE, supersample=1, overwrite=True)
        _CACHE["room"] = out
    return read_split(_CACHE["room"], "train").frames


def rgb01(f: Frame) -> np.ndarray:
    return f.load_rgb().astype(np.float32) / 255.0


def depth_gaussians(
    f: Frame, stride: int, rng: np.random.Generator, pos_noise: float = 0.0, col_noise: float = 0.0
) -> Gaussians:
    """Gaussians on a pixel lattice of a frame, at its true depths, optionally perturbed."""
    d, rgb, k = f.load_depth(), rgb01(f), f.intrinsics
    ys, xs = np.mgrid[stride // 2 : d.shape[0] : stride, stride // 2 : d.shape[1] : stride]
    uv = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
    z = d[ys.ravel(), xs.ravel()].astype(np.float64)
    X = transform_points(f.pose, k.unproject(uv, z)) + rng.normal(0, pos_noise, (z.size, 3))
    c = np.clip(rgb[ys.ravel(), xs.ravel()] + rng.normal(0, col_noise, (z.size, 3)), 0, 1)
    return gaussians_at(X, z, c, k.fx, stride, 0)


def perturbed_map(frames: list[Frame], seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    return concat_gaussians([depth_gaussians(f, 3, rng, 0.02, 0.15) for f in frames])


def true_cells(f: Frame) -> np.ndarray:
    """Scene coordinates (h, w, 3) of the stride-8 cells from the true depth: a perfect SCR prediction."""
    d, k = f.load_depth(), f.intrinsics
    h, w = -(-d.shape[0] // 8), -(-d.shape[1] // 8)
    ys, xs = np.mgrid[0:h, 0:w]
    u, v = xs * 8 + 4, ys * 8 + 4
    z = d[np.minimum(v, d.shape[0] - 1).ravel(), np.minimum(u, d.shape[1] - 1).ravel()]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)
    return transform_points(f.pose, k.unproject(uv, z)).reshape(h, w, 3)


def keyframe(f: Frame, pose: np.ndarray | None = None) -> Keyframe:
    return Keyframe(f.pose if pose is None else pose, rgb01(f), f.intrinsics, true_cells(f), f.intrinsics, f.name)


def mean_psnr(g: Gaussians, frames: list[Frame]) -> float:
    return float(np.mean([psnr(view_mse(g, f.pose, f.intrinsics, rgb01(f), np.zeros(3))) for f in frames]))
