"""Robust pose refinement: Gauss-Newton with Cauchy weights over an annealed scale.

Why: RANSAC's pose comes from a minimal sample and its inlier set from one fixed threshold; a
least-squares polish on that set weighs a 9 px residual like a 1 px one. Scene coordinate
predictions have a dense core of precise points and a long tail, so reweighting every
correspondence by its residual (Cauchy), from a wide scale down to about a pixel, lets the
precise core decide the pose (bench/pnp_choice.md measures the gain).
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


def reprojection(
    points: np.ndarray, pixels: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera points (N, 3), residuals (N, 2) and their norms (N,) (inf behind the camera) of world points
    (N, 3) seen by world-to-camera (R (3, 3), t (3,)) against pixels (N, 2).

    Projected here rather than by cv2.projectPoints, which costs ~20x more (it always builds the Jacobian
    for intrinsics and distortion too); the solver's inlier recount uses it as well.
    """
    Xc = points @ R.T + t
    z = Xc[:, 2]
    zs = np.where(z > 1e-9, z, 1.0)
    res = np.stack([K[0, 0] * Xc[:, 0] / zs + K[0, 2], K[1, 1] * Xc[:, 1] / zs + K[1, 2]], axis=1) - pixels
    e = np.hypot(res[:, 0], res[:, 1])
    e[z <= 1e-9] = np.inf
    return Xc, res, e


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
    R = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]
    t = np.asarray(tvec, np.float64).reshape(3).copy()
    fx, fy = K[0, 0], K[1, 1]

    def jacobian(Xc: np.ndarray) -> np.ndarray:
        """d(residual)/d(w, v) (N, 2, 6) for the update Xc -> exp([w]x) Xc + v (rotation about the camera)."""
        x, y, z = Xc[:, 0], Xc[:, 1], np.maximum(Xc[:, 2], 1e-9)
        iz, iz2 = 1.0 / z, 1.0 / (z * z)
        J = np.empty((len(Xc), 2, 6))
        # du/dXc = fx (1/z, 0, -x/z^2), dv/dXc = fy (0, 1/z, -y/z^2); dXc/dw = -[Xc]x, dXc/dv = I.
        J[:, 0, 0] = -fx * x * y * iz2
        J[:, 0, 1] = fx * (1.0 + x * x * iz2)
        J[:, 0, 2] = -fx * y * iz
        J[:, 0, 3] = fx * iz
        J[:, 0, 4] = 0.0
        J[:, 0, 5] = -fx * x * iz2
        J[:, 1, 0] = -fy * (1.0 + y * y * iz2)
        J[:, 1, 1] = fy * x * y * iz2
        J[:, 1, 2] = fy * x * iz
        J[:, 1, 3] = 0.0
        J[:, 1, 4] = fy * iz
        J[:, 1, 5] = -fy * y * iz2
        return J

    for s in scales:
        # Each scale works on the correspondences within its cutoff at the pose it starts from: the
        # gross outliers leave once, so later steps cost a fraction of the first.
        Xc, res, e = reprojection(points, pixels, K, R, t)
        near = e < CUTOFF * s
        if np.count_nonzero(near) < MIN_SUPPORT:
            break
        pts, pix = points[near], pixels[near]
        Xc, res, e = Xc[near], res[near], e[near]
        damping = 1e-4
        cost = cauchy_cost(e, s)
        for _ in range(steps_per_scale):
            w = cauchy_weights(e, s)
            keep = w > 0
            if np.count_nonzero(keep) < MIN_SUPPORT:
                break
            J = jacobian(Xc[keep]).reshape(-1, 6)
            w2 = np.repeat(w[keep], 2)
            H = J.T @ (J * w2[:, None])
            g = J.T @ (w2 * res[keep].reshape(-1))
            for _attempt in range(4):
                step = cv2.solve(
                    H + damping * np.diag(np.diag(H) + 1e-12), -g.reshape(6, 1), flags=cv2.DECOMP_CHOLESKY
                )[1].reshape(6)
                dR = cv2.Rodrigues(step[:3].reshape(3, 1))[0]
                R_new, t_new = dR @ R, dR @ t + step[3:]
                Xc_new, res_new, e_new = reprojection(pts, pix, K, R_new, t_new)
                cost_new = cauchy_cost(e_new, s)
                if cost_new <= cost:
                    damping = max(damping / 10.0, 1e-7)
                    break
                damping *= 10.0
            else:
                break
            R, t, Xc, res, e, cost = R_new, t_new, Xc_new, res_new, e_new, cost_new
    return cv2.Rodrigues(R)[0].reshape(3), t
