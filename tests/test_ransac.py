"""Batched PnP-RANSAC: the P3P solver and the adaptive iteration count against analytic references."""

from __future__ import annotations

import math

import numpy as np
import pytest

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import invert_pose, look_at, rodrigues_to_matrix, transform_points
from acesplat.core.grid import cell_centers
from acesplat.core.ransac import BATCH, p3p, ransac_iterations, ransac_pnp

INTR = Intrinsics(485.0, 485.0, 270.0, 180.0, 540, 360)


@pytest.mark.parametrize(
    ("ratio", "confidence", "cap", "expected"),
    [
        (0.5, 0.99, 1000, math.ceil(math.log(0.01) / math.log(1 - 0.125))),  # 35
        (0.3, 0.9999, 1000, math.ceil(math.log(1e-4) / math.log(1 - 0.027))),  # 337
        (0.3, 0.9999, 256, 256),  # clipped to the cap
        (0.9, 0.9999, 256, math.ceil(math.log(1e-4) / math.log(1 - 0.729))),  # 8
        (1.0, 0.9999, 256, 1),
        (0.0, 0.9999, 256, 256),
    ],
)
def test_iteration_count_is_the_analytic_formula(ratio: float, confidence: float, cap: int, expected: int) -> None:
    assert ransac_iterations(ratio, confidence, cap) == expected


def test_iteration_count_rejects_bad_settings() -> None:
    with pytest.raises(ValueError, match="confidence"):
        ransac_iterations(0.5, 1.0, 100)
    with pytest.raises(ValueError, match="cap"):
        ransac_iterations(0.5, 0.99, 0)


def test_p3p_finds_the_true_pose_among_its_solutions() -> None:
    rng = np.random.default_rng(0)
    B = 200
    Rs = np.stack([rodrigues_to_matrix(rng.normal(0, 1, 3)) for _ in range(B)])
    ts = rng.normal(0, 1, (B, 3))
    Xc = rng.normal(0, 1, (B, 3, 3)) + [0, 0, 5]
    P = np.einsum("bji,bkj->bki", Rs, Xc - ts[:, None, :])  # world = R^T (Xc - t)
    f = Xc / np.linalg.norm(Xc, axis=2, keepdims=True)
    R, t, src = p3p(f, P)
    assert np.all((src >= 0) & (src < B)) and len(R) <= 4 * B
    best = np.full(B, np.inf)
    for r, tt, s in zip(R, t, src):
        best[s] = min(best[s], np.abs(r - Rs[s]).max() + np.abs(tt - ts[s]).max())
    assert np.mean(best < 1e-6) >= 0.99  # a near-degenerate sample may lose precision, none may be wrong often
    # Every solution reprojects its own sample exactly (the distances solve the law of cosines).
    proj = np.einsum("mij,mkj->mki", R, P[src]) + t[:, None, :]
    cos = np.sum(proj / np.linalg.norm(proj, axis=2, keepdims=True) * f[src], axis=2)
    assert np.quantile(1 - cos, 0.99) < 1e-9
    with pytest.raises(ValueError, match="B, 3, 3"):
        p3p(f[:, :2], P[:, :2])


def _facade(rng: np.random.Generator, outliers: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (N, 2) of a 45 x 68 grid, exact world points (N, 3) 5-8 m away with ``outliers`` of them moved
    0.5-1.5 m (far beyond 10 px), the outlier mask and the camera-to-world pose."""
    T = look_at(np.array([0.5, -6.0, 1.5]), np.array([0.0, 0.0, 2.0]))
    pix = cell_centers(45, 68)
    X = transform_points(T, INTR.unproject(pix, 5.0 + rng.uniform(0, 3.0, len(pix))))
    bad = rng.random(len(X)) < outliers
    d = rng.normal(size=(int(bad.sum()), 3))
    X[bad] += d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.5, 1.5, (int(bad.sum()), 1))
    return pix, X, bad, T


@pytest.mark.parametrize("outliers", [0.3, 0.6])
def test_ransac_stops_after_the_analytic_count_for_the_ratio_it_found(outliers: float) -> None:
    pix, X, bad, T = _facade(np.random.default_rng(1), outliers)
    R, t, inl, drawn = ransac_pnp(pix, X, INTR.K, 10.0, 1000, 0.9999)
    w2c = invert_pose(T)
    np.testing.assert_allclose(R, w2c[:3, :3], atol=1e-6)
    np.testing.assert_allclose(t, w2c[:3, 3], atol=1e-5)
    true_inliers = np.flatnonzero(~bad)
    assert np.isin(true_inliers, inl).all() and len(inl) - len(true_inliers) < 0.02 * len(X)
    needed = ransac_iterations(len(inl) / len(X), 0.9999, 1000)
    assert needed <= drawn < needed + BATCH
    again = ransac_pnp(pix, X, INTR.K, 10.0, 1000, 0.9999)
    np.testing.assert_array_equal(again[0], R)  # seeded: the same draws


def test_ransac_on_garbage_runs_to_the_cap() -> None:
    rng = np.random.default_rng(2)
    pix = cell_centers(45, 68)
    found = ransac_pnp(pix, rng.normal(0, 5, (len(pix), 3)), INTR.K, 10.0, 200, 0.9999)
    assert found is None or (found[3] == 200 and len(found[2]) < 0.05 * len(pix))
