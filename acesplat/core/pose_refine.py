"""Robust pose refinement: Gauss-Newton with Cauchy weights over an annealed scale.

Why: RANSAC's pose comes from a minimal sample and its inlier set from one fixed threshold; a
least-squares polish on that set weighs a 9 px residual like a 1 px one. Scene coordinate
predictions have a dense core of precise points and a long tail, so reweighting every
correspondence by its residual (Cauchy), from a wide scale down to about a pixel, lets the
precise core decide the pose. Measured on the built-in scene's test split (bench/pnp_choice.py):
median error 6.2 -> 2.5 cm, 5 cm / 5 deg recall 37 -> 75%, for the same network.
"""

from __future__ import annotations

import cv2
import numpy as np

ROBUST_SCALES = (4.0, 2.0, 1.0)
"""Cauchy scales in pixels, coarse to fine."""
STEPS_PER_SCALE = 3
CUTOFF = 10.0
"""Residuals beyond this multiple of the current scale get weight zero (clear outliers)."""
MIN_SUPPORT = 12
"""Fewer weighted correspondences than this: the refinement stops and keeps what it has."""


def cauchy_weights(residuals: np.ndarray, scale: float) -> np.ndarray:
    """IRLS weights (N,) of the Cauchy loss s^2/2 log(1 + (r/s)^2) for residual norms (N,)."""
    w = 1.0 / (1.0 + (residuals / scale) ** 2)
    return np.where(residuals < CUTOFF * scale, w, 0.0)


def cauchy_cost(residuals: np.ndarray, scale: float) -> float:
    r = np.minimum(residuals, CUTOFF * scale)
    return float(np.sum(0.5 * scale * scale * np.log1p((r / scale) ** 2)))


def refine_pose_robust(
    pixels: np.ndarray,
    points: np.ndarray,
    K: np.ndarray,
    rvec: np.ndarray,
    tvec: np.ndarray,
    scales: tuple[float, ...] = ROBUST_SCALES,
    steps_per_scale: int = STEPS_PER_SCALE,
) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (rvec (3,), tvec (3,)) refined on pixels (N, 2) and points (N, 3) of a pinhole K (3, 3).

    Damped Gauss-Newton steps on the Cauchy cost; a step that raises the cost is not taken (the
    damping grows instead), so the result is never worse than the start under the final scale.
    """
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if pixels.shape[0] != points.shape[0]:
        raise ValueError(f"pixels {pixels.shape} and points {points.shape} differ in count")
    r = np.asarray(rvec, np.float64).reshape(3).copy()
    t = np.asarray(tvec, np.float64).reshape(3).copy()
    dist = np.zeros(5)

    def residuals(rv: np.ndarray, tv: np.ndarray, jac: bool):
        proj, J = cv2.projectPoints(points, rv, tv, K, dist)
        res = proj.reshape(-1, 2) - pixels
        Rm, _ = cv2.Rodrigues(rv)
        behind = points @ Rm[2] + tv[2] <= 0
        e = np.linalg.norm(res, axis=1)
        e[behind] = np.inf
        return res, e, (J[:, :6] if jac else None)

    for s in scales:
        damping = 1e-4
        res, e, J = residuals(r, t, True)
        cost = cauchy_cost(e, s)
        for _ in range(steps_per_scale):
            w = cauchy_weights(e, s)
            if np.count_nonzero(w) < MIN_SUPPORT:
                return r, t
            w2 = np.repeat(w, 2)
            res_flat = np.where(np.isfinite(res), res, 0.0).reshape(-1)
            H = J.T @ (J * w2[:, None])
            g = J.T @ (w2 * res_flat)
            for _attempt in range(4):
                step = np.linalg.solve(H + damping * np.diag(np.diag(H) + 1e-12), -g)
                r_new, t_new = r + step[:3], t + step[3:]
                res_new, e_new, _ = residuals(r_new, t_new, False)
                cost_new = cauchy_cost(e_new, s)
                if cost_new <= cost:
                    damping = max(damping / 10.0, 1e-7)
                    break
                damping *= 10.0
            else:
                break
            r, t = r_new, t_new
            res, e, J = residuals(r, t, True)
            cost = cauchy_cost(e, s)
    return r, t
