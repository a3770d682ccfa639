"""Which pixels of each view show surface that no earlier view already seeded, torch-free.

Merging every view's pixels stacks one layer of Gaussians per view on every surface: slow to render
(each pixel composites them all) and blurry (each layer has its own colour samples). Instead a
view only seeds the pixels whose 3D centre, projected into the nearest earlier views, lands on a
valid pixel of about the same depth that samples the surface at least about as finely. The result
stays over-complete where views disagree (e.g. noisy SCR depths), and is close to one layer where
they agree.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import invert_pose

DEPTH_TOLERANCE = 0.1
"""Relative depth difference under which two views see the same surface point (SCR depths are noisy; 10% vs 3%:
bench/stage2.md)."""
FINER_RATIO = 1.5
"""An earlier view covers a pixel only if its footprint there is at most this times the pixel's own."""
FUSION_NEIGHBOURS = 8
"""How many nearest earlier views each view is checked against."""


def covered_by(
    centres: np.ndarray,
    depth: np.ndarray,
    valid: np.ndarray,
    intrinsics: Intrinsics,
    other_depth: np.ndarray,
    other_valid: np.ndarray,
    other_pose: np.ndarray,
    other_intrinsics: Intrinsics,
    depth_tol: float = DEPTH_TOLERANCE,
    finer_ratio: float = FINER_RATIO,
) -> np.ndarray:
    """(H, W) bool: valid pixels whose centre another view already samples (same surface, similar footprint).

    centres (H, W, 3) world, depth (H, W) camera z, valid (H, W) of this view; other_depth (H', W')
    and other_valid (H', W') of the other view at pixel resolution.
    """
    H, W = valid.shape
    out = np.zeros((H, W), bool)
    idx = np.flatnonzero(valid)
    if idx.size == 0:
        return out
    X = centres.reshape(-1, 3)[idx]
    w2c = invert_pose(other_pose)
    Xc = X @ w2c[:3, :3].T + w2c[:3, 3]
    z = Xc[:, 2]
    k = other_intrinsics
    front = z > 1e-6
    zs = np.where(front, z, 1.0)
    u = np.rint(k.fx * Xc[:, 0] / zs + k.cx).astype(np.int64)
    v = np.rint(k.fy * Xc[:, 1] / zs + k.cy).astype(np.int64)
    inside = front & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
    uu, vv = np.where(inside, u, 0), np.where(inside, v, 0)
    d_other = other_depth[vv, uu]
    same = inside & other_valid[vv, uu] & (np.abs(d_other - z) <= depth_tol * z)
    own_fp = depth.reshape(-1)[idx] / intrinsics.fx
    other_fp = z / k.fx
    out.reshape(-1)[idx] = same & (other_fp <= finer_ratio * own_fp)
    return out


def novel_masks(
    poses: Sequence[np.ndarray],
    intrinsics: Sequence[Intrinsics],
    centres: Sequence[np.ndarray],
    depths: Sequence[np.ndarray],
    valids: Sequence[np.ndarray],
    neighbours: int = FUSION_NEIGHBOURS,
    depth_tol: float = DEPTH_TOLERANCE,
    finer_ratio: float = FINER_RATIO,
) -> list[np.ndarray]:
    """Per view (in the given order), the valid pixels not covered by any of its nearest earlier views."""
    n = len(poses)
    cams = np.stack([np.asarray(p)[:3, 3] for p in poses]) if n else np.zeros((0, 3))
    out = []
    for i in range(n):
        mask = np.asarray(valids[i], bool).copy()
        if i:
            d = np.linalg.norm(cams[:i] - cams[i], axis=1)
            for j in np.argsort(d, kind="stable")[:neighbours]:
                if not mask.any():
                    break
                mask &= ~covered_by(
                    centres[i],
                    depths[i],
                    mask,
                    intrinsics[i],
                    depths[j],
                    valids[j],
                    poses[j],
                    intrinsics[j],
                    depth_tol,
                    finer_ratio,
                )
        out.append(mask)
    return out
