"""The pose covariance from 2D-3D correspondences against a numerical Jacobian and Monte Carlo poses."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import invert_pose, look_at, make_pose, rodrigues_to_matrix
from acesplat.core.pose_covariance import pose_covariance, projection_jacobian

K = Intrinsics.from_focal(300.0, 320, 240)


def _scene(n: int = 200, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    T = look_at(np.array([0.3, -2.0, 1.2]), np.array([0.0, 0.0, 1.0]))
    uv = rng.uniform([10, 10], [310, 230], (n, 2))
    z = rng.uniform(1.5, 4.0, n)
    X = K.unproject(uv, z) @ T[:3, :3].T + T[:3, 3]
    return T, X, uv


def _project(X: np.ndarray, T: np.ndarray) -> np.ndarray:
    Xc = (X - T[:3, 3]) @ T[:3, :3]
    return Xc[:, :2] / Xc[:, 2:3] * [K.fx, K.fy] + [K.cx, K.cy]


def _perturb(T: np.ndarray, d: np.ndarray) -> np.ndarray:
    return make_pose(rodrigues_to_matrix(d[3:]) @ T[:3, :3], T[:3, 3] + d[:3])


def _delta(T: np.ndarray, T0: np.ndarray) -> np.ndarray:
    """(dc, w) with T = perturb(T0, (dc, w))."""
    w = cv2.Rodrigues(T[:3, :3] @ T0[:3, :3].T)[0].ravel()
    return np.r_[T[:3, 3] - T0[:3, 3], w]


def test_jacobian_matches_finite_differences() -> None:
    T, X, _ = _scene(20)
    J = projection_jacobian(X, K, T)
    eps = 1e-6
    num = np.stack(
        [(_project(X, _perturb(T, eps * e)) - _project(X, _perturb(T, -eps * e))) / (2 * eps) for e in np.eye(6)],
        axis=2,
    )
    np.testing.assert_allclose(J, num, rtol=1e-5, atol=1e-4)


def test_covariance_matches_monte_carlo_poses() -> None:
    """Poses solved from pixels with known noise (sigma 1 px) scatter as the covariance says."""
    T, X, uv = _scene(150)
    sigma = 1.0
    rng = np.random.default_rng(1)
    w2c = invert_pose(T)
    r0 = cv2.Rodrigues(w2c[:3, :3])[0]
    deltas = []
    for _ in range(400):
        noisy = uv + rng.normal(0.0, sigma, uv.shape)
        _, r, t = cv2.solvePnP(X, noisy, K.K, None, r0.copy(), w2c[:3, 3:].copy(), True, cv2.SOLVEPNP_ITERATIVE)
        deltas.append(_delta(invert_pose(make_pose(cv2.Rodrigues(r)[0], t.ravel())), T))
    mc = np.cov(np.array(deltas).T)
    cov = pose_covariance(X, uv, K, T, sigma_px=sigma)
    assert cov.shape == (6, 6) and np.allclose(cov, cov.T)
    # 400 samples: each variance within ~15% (chi-square, 5 sigma), correlations within 0.2
    np.testing.assert_allclose(np.diag(mc), np.diag(cov), rtol=0.2)
    s = np.sqrt(np.diag(cov))
    np.testing.assert_allclose(mc / np.outer(s, s), cov / np.outer(s, s), atol=0.2)
    # sigma estimated from the residuals of one noisy solution: the same covariance within the estimate's spread
    noisy = uv + rng.normal(0.0, sigma, uv.shape)
    _, r, t = cv2.solvePnP(X, noisy, K.K, None, r0.copy(), w2c[:3, 3:].copy(), True, cv2.SOLVEPNP_ITERATIVE)
    est = pose_covariance(X, noisy, K, invert_pose(make_pose(cv2.Rodrigues(r)[0], t.ravel())))
    np.testing.assert_allclose(np.diag(est), np.diag(cov), rtol=0.3)


def test_degenerate_and_bad_inputs() -> None:
    T, X, uv = _scene(10)
    assert pose_covariance(X[:3], uv[:3], K, T) is None
    behind = X.copy()
    behind[:] = T[:3, 3] - 1.0 * T[:3, 2]  # every point behind the camera
    assert pose_covariance(behind, uv, K, T) is None
    with pytest.raises(ValueError, match="differ in count"):
        pose_covariance(X, uv[:5], K, T)
    with pytest.raises(ValueError, match="finite"):
        pose_covariance(X, uv, K, np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="sigma_px"):
        pose_covariance(X, uv, K, T, sigma_px=0.0)
