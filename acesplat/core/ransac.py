"""PnP-RANSAC in batches: a vectorised P3P, hypotheses scored on a sample of the cells, adaptive iterations.

Why: OpenCV's solvePnPRansac calls its minimal solver and scores every hypothesis on every correspondence one
hypothesis at a time; on a 3000-cell grid that is most of the PnP's time (bench/pnp_speed.md). Here a batch of
minimal samples is solved at once (Grunert's P3P, its quartic's roots as companion-matrix eigenvalues), every
hypothesis is scored with a cheirality check on a fixed random sample of the cells (a preemptive score), the best
few are scored on all of them, and the loop stops once the analytic iteration count for the best inlier ratio
found so far is reached.
"""

from __future__ import annotations

import math

import numpy as np

from acesplat.core.pose_refine import reprojection

SAMPLE_SIZE = 3
"""Correspondences per minimal sample (P3P)."""
BATCH = 128
"""Minimal samples solved per batch; the iteration count is checked between batches."""
SCORE_SAMPLE = 256
"""Cells every hypothesis is scored on before the best ones are scored on all cells."""
TOP_K = 4
"""Hypotheses per batch scored on every cell."""


def ransac_iterations(inlier_ratio: float, confidence: float, cap: int, sample_size: int = SAMPLE_SIZE) -> int:
    """Iterations after which an all-inlier minimal sample has been drawn with probability ``confidence``:
    ceil(log(1 - confidence) / log(1 - inlier_ratio ** sample_size)), clipped to [1, cap]."""
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    if cap < 1:
        raise ValueError(f"cap must be >= 1, got {cap}")
    w = min(max(float(inlier_ratio), 0.0), 1.0)
    p_good = w**sample_size
    if p_good >= 1.0:
        return 1
    if p_good <= 0.0:
        return cap
    n = math.log(1.0 - confidence) / math.log1p(-p_good)
    return int(min(max(math.ceil(n), 1), cap))


def _polymul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Products (B, n + m - 1) of batched polynomials a (B, n) and b (B, m), coefficients highest degree first."""
    out = np.zeros((a.shape[0], a.shape[1] + b.shape[1] - 1))
    for i in range(a.shape[1]):
        out[:, i : i + b.shape[1]] += a[:, i : i + 1] * b
    return out


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products (B, 3) (np.cross costs more in overhead than in arithmetic at these sizes)."""
    return np.stack(
        [
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ],
        axis=1,
    )


def _frame(p: np.ndarray) -> np.ndarray:
    """Orthonormal frames (B, 3, 3) (columns) of triangles p (B, 3, 3): x along p1 - p0, z normal to the plane."""
    e1 = p[:, 1] - p[:, 0]
    e1 /= np.sqrt(np.einsum("bi,bi->b", e1, e1))[:, None]
    e3 = _cross(e1, p[:, 2] - p[:, 0])
    e3 /= np.sqrt(np.einsum("bi,bi->b", e3, e3))[:, None]
    return np.stack([e1, _cross(e3, e1), e3], axis=2)


def p3p(bearings: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera poses from B minimal samples: unit bearings (B, 3, 3) and world points (B, 3, 3).

    Returns R (M, 3, 3), t (M, 3) and the sample each came from (M,), up to four real solutions per sample
    (Grunert: distances s_2 = u s_1, s_3 = v s_1, a quartic in v); degenerate samples give none.
    """
    f = np.asarray(bearings, np.float64)
    P = np.asarray(points, np.float64)
    if f.ndim != 3 or f.shape[1:] != (3, 3) or P.shape != f.shape:
        raise ValueError(f"bearings {f.shape} and points {P.shape} must both be (B, 3, 3)")
    a2 = np.sum((P[:, 1] - P[:, 2]) ** 2, axis=1)
    b2 = np.sum((P[:, 0] - P[:, 2]) ** 2, axis=1)
    c2 = np.sum((P[:, 0] - P[:, 1]) ** 2, axis=1)
    ca = np.sum(f[:, 1] * f[:, 2], axis=1)
    cb = np.sum(f[:, 0] * f[:, 2], axis=1)
    cg = np.sum(f[:, 0] * f[:, 1], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        k = (a2 - c2) / b2
        m = c2 / b2
        # u = N(v) / D(v); substituted into 1 + u^2 - 2 u cos(gamma) = (c^2 / b^2)(1 + v^2 - 2 v cos(beta)).
        N = np.stack([k - 1.0, -2.0 * k * cb, 1.0 + k], axis=1)
        D = np.stack([-2.0 * ca, 2.0 * cg], axis=1)
        rest = np.stack([-m, 2.0 * m * cb, 1.0 - m], axis=1)
        quartic = _polymul(N, N) + _polymul(rest, _polymul(D, D))
        quartic[:, 1:] -= _polymul(2.0 * cg[:, None] * N, D)
        lead = quartic[:, 0]
        ok = np.isfinite(quartic).all(axis=1) & (np.abs(lead) > 1e-12 * np.abs(quartic).max(axis=1))
        c = quartic[ok, 1:] / lead[ok, None]
    comp = np.zeros((c.shape[0], 4, 4))
    comp[:, 0, :] = -c
    comp[:, 1, 0] = comp[:, 2, 1] = comp[:, 3, 2] = 1.0
    roots = np.linalg.eigvals(comp) if len(comp) else np.zeros((0, 4), complex)
    src = np.repeat(np.flatnonzero(ok), 4)
    v = roots.reshape(-1)
    real = np.abs(v.imag) < 1e-6 * np.maximum(1.0, np.abs(v.real))
    v = v.real
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (N[src, 0] * v * v + N[src, 1] * v + N[src, 2]) / (D[src, 0] * v + D[src, 1])
        s1 = np.sqrt(b2[src] / (1.0 + v * v - 2.0 * v * cb[src]))
    good = real & (v > 0) & (u > 0) & np.isfinite(s1) & np.isfinite(u) & (s1 > 0)
    src, u, v, s1 = src[good], u[good], v[good], s1[good]
    Q = f[src] * np.stack([s1, u * s1, v * s1], axis=1)[:, :, None]
    Pw = P[src]
    with np.errstate(divide="ignore", invalid="ignore"):
        R = _frame(Q) @ np.transpose(_frame(Pw), (0, 2, 1))
    t = Q[:, 0] - np.einsum("bij,bj->bi", R, Pw[:, 0])
    fin = np.isfinite(R).all(axis=(1, 2)) & np.isfinite(t).all(axis=1)
    return R[fin], t[fin], src[fin]


def _inlier_counts(R: np.ndarray, t: np.ndarray, points_t: np.ndarray, pixels_t: np.ndarray, K: np.ndarray, thr: float):
    """Inliers (M,) of poses R (M, 3, 3), t (M, 3) among points (3, S) / pixels (2, S) (transposed, contiguous);
    points behind the camera never count.

    One matrix product for all poses, in homogeneous image coordinates q = K (R X + t) with the test
    |q_xy - q_z x|^2 < thr^2 q_z^2 (no division).
    """
    M = R.shape[0]
    KR = (K @ R).reshape(3 * M, 3)
    q = (KR @ points_t).reshape(M, 3, -1)
    q += (t @ K.T)[:, :, None]
    z = q[:, 2]
    du = q[:, 0] - pixels_t[0] * z
    dv = q[:, 1] - pixels_t[1] * z
    front = z > 1e-9
    du *= du
    dv *= dv
    du += dv
    return np.count_nonzero(front & (du < (thr * thr) * (z * z)), axis=1)


def ransac_pnp(
    pixels: np.ndarray,
    points: np.ndarray,
    K: np.ndarray,
    threshold_px: float,
    max_iterations: int,
    confidence: float,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int] | None:
    """The best world-to-camera pose (R (3, 3), t (3,)) for pixels (N, 2) and points (N, 3) of a pinhole K (3, 3),
    the indices of its inliers among all N, and the minimal samples drawn; None when no sample gave a pose.

    Samples are drawn ``BATCH`` at a time until ``ransac_iterations`` of the best inlier ratio (or
    ``max_iterations``) is reached; ``seed`` fixes the draws, so equal inputs give equal poses.
    """
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    n = pixels.shape[0]
    if points.shape[0] != n:
        raise ValueError(f"pixels {pixels.shape} and points {points.shape} differ in count")
    if n < SAMPLE_SIZE + 1:
        return None
    rng = np.random.default_rng(seed)
    Kinv = np.linalg.inv(K)
    rays = np.column_stack([pixels, np.ones(n)]) @ Kinv.T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    sub = rng.choice(n, SCORE_SAMPLE, replace=False) if n > SCORE_SAMPLE else np.arange(n)
    # Hypotheses are ranked in float32 (a thousandth of a pixel at these magnitudes); the inliers returned are
    # counted in float64.
    pts32, pix32 = np.ascontiguousarray(points.T, np.float32), np.ascontiguousarray(pixels.T, np.float32)
    K32 = K.astype(np.float32)
    sub_pts, sub_pix = np.ascontiguousarray(pts32[:, sub]), np.ascontiguousarray(pix32[:, sub])
    best: tuple[np.ndarray, np.ndarray, int] | None = None
    drawn, needed = 0, max_iterations
    while drawn < needed:
        b = min(BATCH, needed - drawn)
        idx = rng.integers(0, n, (2 * b, SAMPLE_SIZE))
        idx = idx[(idx[:, 0] != idx[:, 1]) & (idx[:, 0] != idx[:, 2]) & (idx[:, 1] != idx[:, 2])][:b]
        drawn += b
        R, t, _ = p3p(rays[idx], points[idx])
        if len(R) == 0:
            continue
        R32, t32 = R.astype(np.float32), t.astype(np.float32)
        pre = _inlier_counts(R32, t32, sub_pts, sub_pix, K32, threshold_px)
        top = np.argsort(-pre, kind="stable")[:TOP_K]
        full = _inlier_counts(R32[top], t32[top], pts32, pix32, K32, threshold_px)
        j = int(np.argmax(full))
        if best is None or full[j] > best[2]:
            best = (R[top[j]], t[top[j]], int(full[j]))
            needed = ransac_iterations(best[2] / n, confidence, max_iterations)
    if best is None:
        return None
    _, _, err = reprojection(points, pixels, K, best[0], best[1])
    return best[0], best[1], np.flatnonzero(err < threshold_px), drawn
