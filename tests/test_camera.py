"""acesplat.core.camera.Intrinsics: hand cases, round trips, and cv2.resize as the brute-force reference for
resized()."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from acesplat.core.camera import Intrinsics

CAM = Intrinsics(fx=100.0, fy=110.0, cx=63.2, cy=47.7, width=128, height=96)


def blob_image(intr: Intrinsics, uv: np.ndarray, sigma: float = 3.0) -> np.ndarray:
    """A Gaussian blob centred at pixel coordinate ``uv`` (OpenCV convention: pixel (i, j) centre at (i, j))."""
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    return np.exp(-((u - uv[0]) ** 2 + (v - uv[1]) ** 2) / (2 * sigma**2)).astype(np.float32)


def centroid(img: np.ndarray) -> np.ndarray:
    v, u = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    return np.array([(u * img).sum() / img.sum(), (v * img).sum() / img.sum()])


def test_K_and_from_K_round_trip() -> None:
    K = np.array([[100.0, 0.0, 63.2], [0.0, 110.0, 47.7], [0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(CAM.K, K)
    assert Intrinsics.from_K(K, 128, 96) == CAM


def test_from_focal_centres_principal_point() -> None:
    intr = Intrinsics.from_focal(500.0, 640, 480)
    assert (intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height) == (500.0, 500.0, 320.0, 240.0, 640, 480)


def test_project_hand_case() -> None:
    # x/z = 0.25, y/z = 0.5: u = 100 * 0.25 + 63.2, v = 110 * 0.5 + 47.7.
    np.testing.assert_allclose(CAM.project(np.array([[1.0, 2.0, 4.0]])), [[88.2, 102.7]], atol=1e-12)
    np.testing.assert_allclose(CAM.project(np.array([[0.0, 0.0, 3.0]])), [[CAM.cx, CAM.cy]], atol=1e-12)


def test_project_matches_opencv_projectPoints() -> None:
    X = np.random.default_rng(0).uniform([-1, -1, 1], [1, 1, 5], size=(50, 3))
    uv_cv, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), CAM.K, None)
    np.testing.assert_allclose(CAM.project(X), uv_cv[:, 0], atol=1e-9)


def test_project_unproject_round_trip() -> None:
    rng = np.random.default_rng(1)
    X = rng.uniform([-2, -2, 0.1], [2, 2, 20], size=(100, 3))
    np.testing.assert_allclose(CAM.unproject(CAM.project(X), X[:, 2]), X, rtol=1e-12, atol=1e-12)
    uv = rng.uniform(0, 100, size=(100, 2))
    depth = rng.uniform(0.5, 10, size=100)
    np.testing.assert_allclose(CAM.project(CAM.unproject(uv, depth)), uv, atol=1e-10)


@pytest.mark.parametrize("size", [(64, 48), (32, 24), (256, 192), (64, 32), (200, 150)])
def test_resized_equals_scaling_projections(size: tuple[int, int]) -> None:
    """Pixel-centre convention: pixel u (centre of pixel i at u = i) maps to (u + 0.5) * s - 0.5."""
    w, h = size
    small = CAM.resized(w, h)
    sx, sy = w / CAM.width, h / CAM.height
    X = np.random.default_rng(2).uniform([-1, -1, 1], [1, 1, 5], size=(30, 3))
    uv = CAM.project(X)
    scaled = np.stack([(uv[:, 0] + 0.5) * sx - 0.5, (uv[:, 1] + 0.5) * sy - 0.5], axis=1)
    np.testing.assert_allclose(small.project(X), scaled, atol=1e-10)
    assert (small.width, small.height) == (w, h)
    back = small.resized(CAM.width, CAM.height)
    np.testing.assert_allclose([back.fx, back.fy, back.cx, back.cy], [CAM.fx, CAM.fy, CAM.cx, CAM.cy], atol=1e-12)


@pytest.mark.parametrize(
    "size, interp",
    [
        ((64, 48), cv2.INTER_AREA),
        ((32, 24), cv2.INTER_AREA),
        ((64, 32), cv2.INTER_AREA),
        ((256, 192), cv2.INTER_LINEAR),
    ],
)
def test_resized_matches_cv2_resize(size: tuple[int, int], interp: int) -> None:
    """Brute force: a blob at a projected point, resized by OpenCV, lands where the resized intrinsics project it."""
    w, h = size
    X = np.array([[0.13, -0.07, 2.0]])
    uv = CAM.project(X)[0]
    img = cv2.resize(blob_image(CAM, uv), (w, h), interpolation=interp)
    measured = centroid(img)
    np.testing.assert_allclose(measured, CAM.resized(w, h).project(X)[0], atol=0.02)
    naive = np.array([uv[0] * w / CAM.width, uv[1] * h / CAM.height])  # cx * s, the pixel-corner mistake
    if (w, h) != (CAM.width, CAM.height):
        assert np.abs(measured - naive).max() > 0.2


@pytest.mark.parametrize("size", [(64, 48), (200, 150), (90, 96)])
def test_pixels_to_follows_the_rays(size: tuple[int, int]) -> None:
    """A point's pixel in one image maps to its pixel in a resized copy (reference: projecting the point there)."""
    w, h = size
    other = CAM.resized(w, h)
    X = np.random.default_rng(3).uniform([-1, -1, 1], [1, 1, 5], size=(40, 3))
    np.testing.assert_allclose(CAM.pixels_to(CAM.project(X), other), other.project(X), atol=1e-10)
    np.testing.assert_allclose(other.pixels_to(other.project(X), CAM), CAM.project(X), atol=1e-10)
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        CAM.pixels_to(np.zeros((3, 3)), other)
