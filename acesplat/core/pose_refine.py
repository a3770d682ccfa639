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
STEP_TOL = 1e-9
"""A step turning less than this (rad) and moving less than this relative to the translation ends its scale."""


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


def _project(
    points: np.ndarray, pixels: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Normalised camera coordinates x/z, y/z, inverse depths (N,), pixel residuals du, dv (N,) stacked (2, N) and
    squared residual norms (N,) (inf behind the camera) of world points (N, 3) under world-to-camera (R, t)."""
    Xc = points @ R.T + t
    z = Xc[:, 2]
    front = z > 1e-9
    iz = 1.0 / np.where(front, z, 1.0)
    xn, yn = Xc[:, 0] * iz, Xc[:, 1] * iz
    res = np.empty((2, len(z)))
    np.subtract(K[0, 0] * xn + K[0, 2], pixels[:, 0], out=res[0])
    np.subtract(K[1, 1] * yn + K[1, 2], pixels[:, 1], out=res[1])
    e2 = res[0] * res[0] + res[1] * res[1]
    e2[~front] = np.inf
    return xn, yn, iz, res, e2


def _cost2(e2: np.ndarray, scale: float) -> float:
    """cauchy_cost from squared residual norms (N,)."""
    return float(0.5 * scale * scale * np.sum(np.log1p(np.minimum(e2, (CUTOFF * scale) ** 2) / (scale * scale))))


def _normal_equations(
    xn: np.ndarray, yn: np.ndarray, iz: np.ndarray, res: np.ndarray, w: np.ndarray, fx: float, fy: float
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted Gauss-Newton H (6, 6) and gradient g (6,) for the update Xc -> exp([w]x) Xc + v (rotation about the
    camera): du/dXc = fx (1/z, 0, -x/z^2), dv/dXc = fy (0, 1/z, -y/z^2); dXc/dw = -[Xc]x, dXc/dv = I."""
    m = len(xn)
    J = np.empty((6, 2, m))  # one contiguous row per pose parameter: residual u then v
    xy = xn * yn
    np.multiply(-fx, xy, out=J[0, 0])
    np.multiply(fx, 1.0 + xn * xn, out=J[1, 0])
    np.multiply(-fx, yn, out=J[2, 0])
    np.multiply(fx, iz, out=J[3, 0])
    J[4, 0] = 0.0
    np.multiply(-fx * xn, iz, out=J[5, 0])
    np.multiply(-fy, 1.0 + yn * yn, out=J[0, 1])
    np.multiply(fy, xy, out=J[1, 1])
    np.multiply(fy, xn, out=J[2, 1])
    J[3, 1] = 0.0
    np.multiply(fy, iz, out=J[4, 1])
    np.multiply(-fy * yn, iz, out=J[5, 1])
    J = J.reshape(6, 2 * m)
    Jw = J * np.concatenate([w, w])
    return Jw @ J.T, Jw @ res.reshape(-1)


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
    damping grows instead), so the result is never worse than the start under the final scale. A scale
    ends early once a step moves the pose by less than STEP_TOL.
    """
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if pixels.shape[0] != points.shape[0]:
        raise ValueError(f"pixels {pixels.shape} and points {points.shape} differ in count")
    R = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]
    t = np.asarray(tvec, np.float64).reshape(3).copy()
    fx, fy = K[0, 0], K[1, 1]

    for s in scales:
        # Each scale works on the correspondences within its cutoff at the pose it starts from: the
        # gross outliers leave once, so later steps cost a fraction of the first.
        cut2 = (CUTOFF * s) ** 2
        xn, yn, iz, res, e2 = _project(points, pixels, K, R, t)
        near = e2 < cut2
        if np.count_nonzero(near) < MIN_SUPPORT:
            break
        pts, pix = points[near], pixels[near]
        xn, yn, iz, res, e2 = xn[near], yn[near], iz[near], res[:, near], e2[near]
        damping = 1e-4
        cost = _cost2(e2, s)
        for _ in range(steps_per_scale):
            keep = e2 < cut2  # cauchy_weights is zero exactly beyond the cutoff
            kept = np.count_nonzero(keep)
            if kept < MIN_SUPPORT:
                break
            if kept == len(e2):
                H, g = _normal_equations(xn, yn, iz, res, 1.0 / (1.0 + e2 / (s * s)), fx, fy)
            else:
                w = 1.0 / (1.0 + e2[keep] / (s * s))
                H, g = _normal_equations(xn[keep], yn[keep], iz[keep], res[:, keep], w, fx, fy)
            for _attempt in range(4):
                step = cv2.solve(
                    H + damping * np.diag(np.diag(H) + 1e-12), -g.reshape(6, 1), flags=cv2.DECOMP_CHOLESKY
                )[1].reshape(6)
                dR = cv2.Rodrigues(step[:3].reshape(3, 1))[0]
                R_new, t_new = dR @ R, dR @ t + step[3:]
                proj = _project(pts, pix, K, R_new, t_new)
                cost_new = _cost2(proj[4], s)
                if cost_new <= cost:
                    damping = max(damping / 10.0, 1e-7)
                    break
                damping *= 10.0
            else:
                break
            R, t, cost = R_new, t_new, cost_new
            xn, yn, iz, res, e2 = proj
            if np.abs(step[:3]).max() < STEP_TOL and np.abs(step[3:]).max() < STEP_TOL * (1.0 + np.abs(t).max()):
                break
    return cv2.Rodrigues(R)[0].reshape(3), t
