"""Gaussians from a point cloud (3DGS's recipe): the `cells` start's textured SCR cells, and the conventional starts
Stage 2 is compared against.

3DGS seeds one Gaussian per point: isotropic, its scale the mean distance to the 3 nearest other
points, opacity 0.1, identity rotation, colour from the point. The point cloud is either sparse
SfM-style points (features matched between the images and triangulated with the known poses) or
3DGS's random initialisation (uniform points in a box, random colours).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from acesplat.core.gaussians import Gaussians, logit, rgb_to_sh_dc, sh_coeff_count

POINT_OPACITY = 0.1
KNN = 3
MIN_SCALE_M = 1e-7


def gaussians_from_points(points: np.ndarray, colours: np.ndarray, sh_degree: int = 3) -> Gaussians:
    """3DGS's initial set from points (N, 3) with colours (N, 3) in [0, 1]."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    col = np.asarray(colours, np.float64).reshape(-1, 3)
    n = len(pts)
    if n != len(col):
        raise ValueError(f"{n} points but {len(col)} colours")
    if n < 2:
        raise ValueError("need at least 2 points")
    k = min(KNN, n - 1)
    d, _ = cKDTree(pts).query(pts, k=k + 1)
    scale = np.maximum(np.mean(d[:, 1:], axis=1), MIN_SCALE_M)
    sh = np.zeros((n, sh_coeff_count(sh_degree), 3))
    sh[:, 0] = rgb_to_sh_dc(col)
    quats = np.zeros((n, 4))
    quats[:, 0] = 1.0
    return Gaussians(
        pts.astype(np.float32),
        np.log(np.repeat(scale[:, None], 3, axis=1)).astype(np.float32),
        quats.astype(np.float32),
        np.full(n, logit(np.array(POINT_OPACITY)), np.float32),
        sh.astype(np.float32),
    )


def random_points(
    n: int, camera_centres: np.ndarray, half_side: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """3DGS's random start: n points uniform in a cube of ``half_side`` around the cameras' mean, random colours."""
    c = np.asarray(camera_centres, np.float64).reshape(-1, 3).mean(axis=0)
    pts = c + rng.uniform(-half_side, half_side, (n, 3))
    return pts, rng.random((n, 3))


def triangulated_points(
    grays: Sequence[np.ndarray], rgbs: Sequence[np.ndarray], intrinsics: Sequence, poses: Sequence[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Sparse points from SIFT matches between neighbouring images triangulated with the known poses
    (Stage 1's target triangulation), each coloured by the pixel it was found at."""
    from acesplat.scr.targets import triangulate_targets

    found = triangulate_targets(list(grays), list(intrinsics), list(poses))
    pts, cols = [], []
    for t, rgb in zip(found, rgbs):
        if len(t.points) == 0:
            continue
        h, w = rgb.shape[:2]
        u = np.clip(np.rint(t.pixels[:, 0]).astype(int), 0, w - 1)
        v = np.clip(np.rint(t.pixels[:, 1]).astype(int), 0, h - 1)
        pts.append(t.points)
        cols.append(rgb[v, u])
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.concatenate(pts), np.concatenate(cols)
