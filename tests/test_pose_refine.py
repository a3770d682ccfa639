"""Robust pose refinement against exact poses, heavy-tailed noise and a least-squares polish."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import invert_pose, look_at, make_pose, pose_error, rodrigues_to_matrix, transform_points
from acesplat.core.grid import cell_centers
from acesplat.core.pnp import solve_pnp
from acesplat.core.pose_refine import cauchy_cost, cauchy_weights, refine_pose_robust

INTR = Intrinsics(200.0, 200.0, 79.5, 59.5, 160, 120)


def _scene(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (N, 2), their exact world points (N, 3) 3-5 m away, and the camera-to-world pose."""
    T = look_at(np.array([0.3, -0.2, 1.5]), np.array([0.5, 4.0, 1.2]))
    pix = cell_centers(15, 20)
    X = transform_points(T, INTR.unproject(pix, 3.0 + rng.uniform(0, 2.0, len(pix))))
    return pix, X, T


def _rt(T_c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    w2c = invert_pose(T_c2w)
    return cv2.Rodrigues(w2c[:3, :3])[0].reshape(3), w2c[:3, 3].copy()


def _c2w(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    return invert_pose(make_pose(rodrigues_to_matrix(r), t))


def test_cauchy_weights_and_cost_by_hand() -> None:
    e = np.array([0.0, 1.0, 2.0, 25.0])
    np.testing.assert_allclose(cauchy_weights(e, 2.0), [1.0, 0.8, 0.5, 0.0])  # 25 px > 10 x scale: cut
    assert cauchy_cost(np.array([2.0]), 2.0) == pytest.approx(2.0 * np.log(2.0))


def test_recovers_the_exact_pose_from_a_perturbed_start_despite_outliers() -> None:
    """Exact down to rounding once the scale is small enough that no outlier lands within it (at the
    default 1 px a near-miss outlier still pulls by ~0.2 mm: an M-estimator's bias, not a failure)."""
    rng = np.random.default_rng(0)
    pix, X, T = _scene(rng)
    bad = rng.random(len(X)) < 0.4
    X[bad] += rng.normal(0, 1.0, (bad.sum(), 3))
    r, t = _rt(T)
    start = (r + [0.01, -0.01, 0.005], t + [0.05, 0.02, -0.04])
    r1, t1 = refine_pose_robust(pix, X, INTR.K, *start)
    assert pose_error(_c2w(r1, t1), T)[0] < 1e-3
    r2, t2 = refine_pose_robust(pix, X, INTR.K, *start, scales=(4.0, 2.0, 1.0, 0.5, 0.25))
    dt, dr = pose_error(_c2w(r2, t2), T)
    assert dt < 1e-9 and dr < 1e-6


def test_beats_least_squares_on_heavy_tailed_noise() -> None:
    """Half the points are 0.3 px noisy, half 5 px: Cauchy weighting lets the precise half decide."""
    errs_robust, errs_ls = [], []
    for seed in range(8):
        rng = np.random.default_rng(seed)
        pix, X, T = _scene(rng)
        noisy = pix + rng.normal(0, 0.3, pix.shape)
        wide = rng.random(len(pix)) < 0.5
        noisy[wide] += rng.normal(0, 5.0, (wide.sum(), 2))
        ls = solve_pnp(noisy, X, INTR, robust_scales=())
        rob = solve_pnp(noisy, X, INTR)
        errs_ls.append(pose_error(ls.T_c2w, T)[0])
        errs_robust.append(pose_error(rob.T_c2w, T)[0])
    assert np.median(errs_robust) < 0.7 * np.median(errs_ls)


def test_never_raises_the_final_scale_cost() -> None:
    rng = np.random.default_rng(5)
    pix, X, T = _scene(rng)
    noisy = pix + rng.standard_t(1.5, pix.shape)
    r, t = _rt(T)
    r0, t0 = r + 0.002, t + 0.01
    r1, t1 = refine_pose_robust(noisy, X, INTR.K, r0, t0, scales=(1.0,))

    def cost(rv, tv):
        proj, _ = cv2.projectPoints(X, rv, tv, INTR.K, np.zeros(5))
        return cauchy_cost(np.linalg.norm(proj.reshape(-1, 2) - noisy, axis=1), 1.0)

    assert cost(r1, t1) <= cost(r0, t0)


def test_points_behind_the_camera_do_not_pull() -> None:
    rng = np.random.default_rng(6)
    pix, X, T = _scene(rng)
    # Mirror a fifth of the points through the camera centre: they project near their pixels but lie behind.
    C = T[:3, 3]
    k = len(X) // 5
    X[:k] = C - (X[:k] - C)
    r, t = _rt(T)
    r1, t1 = refine_pose_robust(pix, X, INTR.K, r + 0.003, t + 0.02)
    assert pose_error(_c2w(r1, t1), T)[0] < 1e-6


def test_count_mismatch_is_an_error() -> None:
    with pytest.raises(ValueError, match="differ in count"):
        refine_pose_robust(np.zeros((5, 2)), np.zeros((4, 3)), INTR.K, np.zeros(3), np.zeros(3))
