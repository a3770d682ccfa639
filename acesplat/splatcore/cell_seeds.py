"""Which SCR cells seed Gaussians: the trusted cells where the image has the most texture, torch-free.

3DGS starts from sparse SfM points: few, on texture, where matching and triangulation are exact. The SCR gives a
coordinate for every cell, but where the image is flat (sky, plaster, road) nothing in the pixels pins the
coordinate along the ray, and a Gaussian seeded there at the wrong depth fits its own view while spoiling the
others. So the cells are ranked by the image's gradient over them and the most textured ones seed, as many as a
sparse start has (bench/splat_init.md).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from acesplat.core.grid import OUTPUT_STRIDE, cell_centers


def cell_texture(gray: np.ndarray, cells_hw: tuple[int, int], stride: int = OUTPUT_STRIDE) -> np.ndarray:
    """Mean Sobel gradient magnitude (h, w) of ``gray`` (H, W) over each stride x stride cell of an (h, w) grid
    (cells past the image's last whole cell score 0)."""
    gray = np.asarray(gray)
    if gray.ndim != 2:
        raise ValueError(f"gray must be (H, W), got shape {gray.shape}")
    h, w = cells_hw
    g = gray.astype(np.float32)
    mag = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    out = np.zeros((h, w), np.float32)
    hh, ww = min(h, mag.shape[0] // stride), min(w, mag.shape[1] // stride)
    out[:hh, :ww] = mag[: hh * stride, : ww * stride].reshape(hh, stride, ww, stride).mean(axis=(1, 3))
    return out


def textured_cells(scores: Sequence[np.ndarray], valid: Sequence[np.ndarray], count: int) -> list[np.ndarray]:
    """Per view, the mask (h, w) of its cells among the ``count`` valid cells of highest score over all views
    (ties broken by view, then row-major order)."""
    if len(scores) != len(valid):
        raise ValueError(f"{len(scores)} score maps but {len(valid)} masks")
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count}")
    flat = []
    for i, (s, m) in enumerate(zip(scores, valid)):
        if np.shape(s) != np.shape(m):
            raise ValueError(f"view {i}: scores {np.shape(s)} and mask {np.shape(m)} differ")
        idx = np.flatnonzero(np.asarray(m, bool))
        flat.append(np.stack([np.full(idx.size, i), idx, np.asarray(s, np.float64).ravel()[idx]], 1))
    allc = np.concatenate(flat) if flat else np.zeros((0, 3))
    keep = allc[np.argsort(-allc[:, 2], kind="stable")[:count]] if count < len(allc) else allc
    out = [np.zeros(np.shape(m), bool) for m in valid]
    for i, idx, _ in keep:
        out[int(i)].reshape(-1)[int(idx)] = True
    return out


def cell_points(
    coords: np.ndarray, mask: np.ndarray, rgb: np.ndarray, stride: int = OUTPUT_STRIDE
) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) and colours (N, 3) of the cells in ``mask`` (h, w): each cell's scene coordinate (coords
    (h, w, 3)) with the colour of the pixel it was predicted for (rgb (H, W, 3), float in [0, 1])."""
    mask = np.asarray(mask, bool)
    if coords.shape[:2] != mask.shape or coords.shape[2:] != (3,):
        raise ValueError(f"coords {coords.shape} and mask {mask.shape} differ")
    uv = cell_centers(*mask.shape, stride)[mask.ravel()].astype(np.int64)
    u = np.minimum(uv[:, 0], rgb.shape[1] - 1)
    v = np.minimum(uv[:, 1], rgb.shape[0] - 1)
    return np.asarray(coords, np.float64)[mask], np.asarray(rgb)[v, u]
