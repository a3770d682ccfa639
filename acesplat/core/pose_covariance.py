"""The uncertainty of a pose solved from 2D-3D correspondences (torch-free).

First-order propagation of the pixel noise through the projection: with J (2N, 6) the Jacobian of the stacked
reprojection residuals with respect to a pose perturbation and sigma^2 the residuals' variance, the pose covariance
is sigma^2 (J^T J)^-1. The perturbation is the world frame's, as ``PoseRecord.covariance`` states it: the camera
centre moved by dc (m) and the camera-to-world rotation turned on the left, R -> exp([w]x) R (w in rad).
"""

from __future__ import annotations

import numpy as np

from acesplat.core.camera import Intrinsics

MIN_POINTS = 4
"""Fewer correspondences than this do not determine a pose (no covariance)."""


def projection_jacobian(points: np.ndarray, intrinsics: Intrinsics, T_c2w: np.ndarray) -> np.ndarray:
    """d(pixel)/d(dc, w) (N, 2, 6) of world points (N, 3) seen by the camera-to-world ``T_c2w`` (4, 4), for the
    perturbation c -> c + dc, R -> exp([w]x) R (world frame)."""
    X = np.asarray(points, np.float64).reshape(-1, 3)
    T = np.asarray(T_c2w, np.float64)
    R, c = T[:3, :3], T[:3, 3]
    Xc = (X - c) @ R  # R^T (X - c) per row
    x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    fx, fy = intrinsics.fx, intrinsics.fy
    # Xc' = R^T exp(-[w]x) (X - c - dc) ~ Xc - R^T dc + [Xc]x R^T w  (R^T [a]x = [R^T a]x R^T): the camera-frame
    # Jacobian of (dc', w') = (R^T dc, R^T w), then rotated back to the world
    Jc = np.zeros((len(X), 2, 6))
    Jc[:, 0, 0] = -fx / z
    Jc[:, 0, 2] = fx * x / z**2
    Jc[:, 1, 1] = -fy / z
    Jc[:, 1, 2] = fy * y / z**2
    Jc[:, 0, 3] = fx * x * y / z**2
    Jc[:, 0, 4] = -fx * (1.0 + x * x / z**2)
    Jc[:, 0, 5] = fx * y / z
    Jc[:, 1, 3] = fy * (1.0 + y * y / z**2)
    Jc[:, 1, 4] = -fy * x * y / z**2
    Jc[:, 1, 5] = -fy * x / z
    B = np.zeros((6, 6))
    B[:3, :3] = B[3:, 3:] = R.T
    return np.einsum("nij,jk->nik", Jc, B)  # einsum, not BLAS: a thread pool for a 6x6 product costs more


def pose_covariance(
    points: np.ndarray,
    pixels: np.ndarray,
    intrinsics: Intrinsics,
    T_c2w: np.ndarray,
    sigma_px: float | None = None,
) -> np.ndarray | None:
    """Covariance (6, 6) of the camera-to-world ``T_c2w`` (4, 4) solved from inlier correspondences, world points
    (N, 3) and their pixels (N, 2): position (m^2) then the left rotation vector (rad^2), world frame.

    ``sigma_px``: the pixel noise's standard deviation per axis; None estimates it from the residuals
    (sum r^2 / (2N - 6)). None when there are fewer than MIN_POINTS correspondences in front of the camera or the
    geometry does not determine the pose (a singular J^T J).
    """
    X = np.asarray(points, np.float64).reshape(-1, 3)
    uv = np.asarray(pixels, np.float64).reshape(-1, 2)
    T = np.asarray(T_c2w, np.float64)
    if X.shape[0] != uv.shape[0]:
        raise ValueError(f"points {X.shape} and pixels {uv.shape} differ in count")
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"pose must be a finite (4, 4) camera-to-world, got shape {T.shape}")
    if sigma_px is not None and not sigma_px > 0:
        raise ValueError(f"sigma_px must be positive, got {sigma_px}")
    Xc = (X - T[:3, 3]) @ T[:3, :3]
    ok = np.all(np.isfinite(X), axis=1) & np.all(np.isfinite(uv), axis=1) & (Xc[:, 2] > 1e-9)
    X, uv, Xc = X[ok], uv[ok], Xc[ok]
    n = len(X)
    if n < MIN_POINTS:
        return None
    J = projection_jacobian(X, intrinsics, T).reshape(-1, 6)
    if sigma_px is None:
        K = intrinsics.K
        proj = np.stack([K[0, 0] * Xc[:, 0] / Xc[:, 2] + K[0, 2], K[1, 1] * Xc[:, 1] / Xc[:, 2] + K[1, 2]], axis=1)
        dof = max(2 * n - 6, 1)
        var = float(np.sum((proj - uv) ** 2)) / dof
    else:
        var = float(sigma_px) ** 2
    H = np.einsum("ni,nj->ij", J, J)
    if not np.all(np.isfinite(H)) or np.linalg.cond(H) > 1e15:
        return None
    cov = var * np.linalg.inv(H)
    return 0.5 * (cov + cov.T)
