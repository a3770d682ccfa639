"""Guards that keep a bad keyframe or a bad step from damaging the map.

- Non-finite gradients: the step is skipped and counted (no parameter or moment sees a NaN).
- Photometric guard: a keyframe's batch of changes is committed only if it lowers the error on the
  keyframe itself and does not raise it much on the earlier keyframes held for the purpose. A keyframe
  whose pose is wrong can fit itself, but only by breaking the views that saw the same surfaces
  from the right place, so its batch is rolled back.
- The map as loaded is the floor: every guarded view (the held keyframes and the keyframe itself) must
  end within a small tolerance of its error under the loaded map or below it, view by view (an average
  can rise while one view falls), so no guarded view ever ends worse than it started.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.gaussians import Gaussians
from acesplat.raster import rasterize
from edge.refine.coverage import frustum_mask

HELD_TOLERANCE = 0.3
"""Largest relative MSE increase allowed on any held keyframe (bench/refine.md)."""


def all_finite(grads) -> bool:
    """True if every gradient array of ``grads`` (a RasterGradients) is finite."""
    return all(
        bool(np.all(np.isfinite(getattr(grads, p)))) for p in ("means", "log_scales", "quats", "opacity_logits", "sh")
    )


def render_view(g: Gaussians, pose_c2w: np.ndarray, k: Intrinsics, background: np.ndarray):
    """Render only the Gaussians that can reach the image (same pixels, less work); None if none can."""
    if len(g) == 0:
        return None
    m = frustum_mask(g.means, g.log_scales, pose_c2w, k)
    if not m.any():
        return None
    return rasterize(g.subset(m), pose_c2w, k, background)


def view_mse(g: Gaussians, pose_c2w: np.ndarray, k: Intrinsics, target: np.ndarray, background: np.ndarray) -> float:
    """Mean squared RGB error of ``g`` rendered from ``pose_c2w`` against ``target`` (H, W, 3) in [0, 1]."""
    r = render_view(g, pose_c2w, k, background)
    color = np.broadcast_to(np.asarray(background, np.float32), target.shape) if r is None else r.color
    d = np.asarray(color, np.float32) - np.asarray(target, np.float32)
    return float(np.mean(d * d))


def psnr(mse: float) -> float:
    return float("inf") if mse <= 0 else float(-10.0 * np.log10(mse))


@dataclass
class HeldView:
    """An earlier committed keyframe kept at guard resolution, with its error under map ``version`` (the
    guard's 'after' render of one commit is the next batch's 'before', so it is rendered once, not twice)."""

    pose: np.ndarray
    k: Intrinsics
    target: np.ndarray
    name: str = ""
    mse: float | None = None
    version: int = -1
    loaded_mse: float | None = None
    """Its error under the map as loaded (None: not rendered yet)."""


def downsample(rgb: np.ndarray, k: Intrinsics, max_side: int) -> tuple[np.ndarray, Intrinsics]:
    """rgb (H, W, 3) float32 area-averaged so its longer side is at most ``max_side``, with matching intrinsics."""
    h, w = rgb.shape[:2]
    s = min(1.0, max_side / max(h, w))
    if s >= 1.0:
        return rgb, k
    nw, nh = max(1, int(round(w * s))), max(1, int(round(h * s)))
    return cv2.resize(np.asarray(rgb, np.float32), (nw, nh), interpolation=cv2.INTER_AREA), k.resized(nw, nh)


class HeldViews:
    """The last ``capacity`` committed keyframes (guard resolution); older ones leave the guard."""

    def __init__(self, capacity: int) -> None:
        self.views: deque[HeldView] = deque(maxlen=max(0, capacity))

    def add(self, v: HeldView) -> None:
        if self.views.maxlen:
            self.views.append(v)

    def __len__(self) -> int:
        return len(self.views)

    def __iter__(self):
        return iter(list(self.views))


def held_verdict(
    kf_before: float, kf_after: float, before: list[float], after: list[float], tolerance: float = HELD_TOLERANCE
) -> bool:
    """True if the summed error over the keyframe and the held views fell, and no held view's error rose
    by more than ``tolerance`` (relative)."""
    if len(before) != len(after):
        raise ValueError(f"{len(before)} errors before but {len(after)} after")
    each = all(a <= b * (1.0 + tolerance) + 1e-12 for b, a in zip(before, after))
    return each and (kf_after + sum(after) < kf_before + sum(before))


def loaded_bound(loaded_mse: float, tolerance_db: float) -> float:
    """The largest error a guarded view may end with: its error under the loaded map, ``tolerance_db`` dB of PSNR
    worse at most."""
    if not tolerance_db >= 0:
        raise ValueError(f"tolerance must be >= 0 dB, got {tolerance_db}")
    return float(loaded_mse) * 10.0 ** (tolerance_db / 10.0) + 1e-12


def harmed_views(after: list[float], loaded: list[float], tolerance_db: float) -> list[int]:
    """Indices of the views whose error ``after`` exceeds their error under the loaded map (``loaded``, same order)
    by more than ``tolerance_db`` dB of PSNR: one view falling is a harm whatever the others gain."""
    if len(after) != len(loaded):
        raise ValueError(f"{len(after)} errors after but {len(loaded)} under the loaded map")
    return [i for i, (a, lo) in enumerate(zip(after, loaded)) if a > loaded_bound(lo, tolerance_db)]
