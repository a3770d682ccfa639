"""Stage 2 loss and metrics against brute force, skimage and hand computation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from acesplat.splat.losses import (
    DSSIM_WEIGHT,
    SSIM_C1,
    SSIM_C2,
    gaussian_window,
    mse,
    psnr,
    psnr_from_mse,
    rendering_loss,
    ssim,
    ssim_map,
)
from acesplat.splat.schedule import NET_LR_MAX, NET_LR_MIN, POSITION_DECAY, gaussian_factor, one_cycle, one_cycle_factor


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Tiny tensors: thread hand-offs cost more than the work on a busy 2-core machine."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def brute_ssim_map(x: np.ndarray, y: np.ndarray, size: int = 11, sigma: float = 1.5) -> np.ndarray:
    """Per pixel and channel: weighted statistics over an explicit window, zero outside the image."""
    h, w, c = x.shape
    r = size // 2
    g1 = np.exp(-((np.arange(size) - r) ** 2) / (2 * sigma**2))
    win = np.outer(g1, g1)
    win /= win.sum()
    xp = np.zeros((h + 2 * r, w + 2 * r, c))
    yp = np.zeros_like(xp)
    xp[r : r + h, r : r + w] = x
    yp[r : r + h, r : r + w] = y
    out = np.zeros((h, w, c))
    for i in range(h):
        for j in range(w):
            px = xp[i : i + size, j : j + size]
            py = yp[i : i + size, j : j + size]
            for k in range(c):
                mx = (win * px[..., k]).sum()
                my = (win * py[..., k]).sum()
                vx = (win * px[..., k] ** 2).sum() - mx * mx
                vy = (win * py[..., k] ** 2).sum() - my * my
                cxy = (win * px[..., k] * py[..., k]).sum() - mx * my
                out[i, j, k] = ((2 * mx * my + SSIM_C1) * (2 * cxy + SSIM_C2)) / (
                    (mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2)
                )
    return out


def _pair(seed: int, h: int = 17, w: int = 23) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = rng.random((h, w, 3))
    y = np.clip(x + 0.15 * rng.standard_normal((h, w, 3)), 0, 1)
    return x, y


def test_window_is_normalised_gaussian():
    w = gaussian_window(11, 1.5, torch.float64)
    assert w.shape == (11,)
    assert float(w.sum()) == pytest.approx(1.0, abs=1e-12)
    assert float(w[5] / w[6]) == pytest.approx(math.exp(1 / (2 * 1.5**2)), rel=1e-12)
    with pytest.raises(ValueError):
        gaussian_window(10)


def test_ssim_map_matches_brute_force_with_zero_padding():
    x, y = _pair(0)
    got = ssim_map(torch.from_numpy(x), torch.from_numpy(y))[0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(got, brute_ssim_map(x, y), atol=1e-10)


def test_ssim_interior_matches_skimage():
    x, y = _pair(1, 40, 48)
    ref = structural_similarity(
        x, y, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=2
    )
    m = ssim_map(torch.from_numpy(x), torch.from_numpy(y))[0].numpy()
    assert float(m[:, 5:-5, 5:-5].mean()) == pytest.approx(ref, abs=1e-8)


def test_ssim_identity_and_symmetry():
    x, y = _pair(2)
    tx, ty = torch.from_numpy(x), torch.from_numpy(y)
    assert float(ssim(tx, tx)) == pytest.approx(1.0, abs=1e-12)
    assert float(ssim(tx, ty)) == pytest.approx(float(ssim(ty, tx)), abs=1e-12)
    assert float(ssim(tx, ty)) < 0.99


def test_ssim_gradient_matches_finite_differences():
    x, y = _pair(3, 6, 7)
    tx = torch.from_numpy(x).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a: ssim(a, torch.from_numpy(y)), (tx,), eps=1e-6, atol=1e-6)


def test_rendering_loss_and_psnr_by_hand():
    x, y = _pair(4)
    tx, ty = torch.from_numpy(x), torch.from_numpy(y)
    m = float(np.mean((x - y) ** 2))
    s = float(brute_ssim_map(x, y).mean())
    assert float(mse(tx, ty)) == pytest.approx(m, rel=1e-12)
    assert float(rendering_loss(tx, ty)) == pytest.approx((1 - DSSIM_WEIGHT) * m + DSSIM_WEIGHT * (1 - s), rel=1e-9)
    assert DSSIM_WEIGHT == 0.2
    assert psnr(tx, ty) == pytest.approx(-10 * math.log10(m), rel=1e-12)
    assert psnr_from_mse(0.01) == pytest.approx(20.0)
    assert psnr_from_mse(0.0) == math.inf


def test_shape_checks():
    with pytest.raises(ValueError):
        ssim(torch.zeros(8, 8, 3), torch.zeros(8, 9, 3))
    with pytest.raises(ValueError):
        ssim(torch.zeros(8, 8, 2), torch.zeros(8, 8, 2))
    with pytest.raises(TypeError):
        ssim(np.zeros((8, 8, 3)), torch.zeros(8, 8, 3))


def test_one_cycle_shape():
    assert one_cycle(0.0, NET_LR_MIN, NET_LR_MAX) == pytest.approx(2e-4)
    assert one_cycle(0.1, NET_LR_MIN, NET_LR_MAX) == pytest.approx(2e-3)
    assert one_cycle(1.0, NET_LR_MIN, NET_LR_MAX) == pytest.approx(2e-6)
    assert one_cycle(0.05, NET_LR_MIN, NET_LR_MAX) == pytest.approx(0.5 * (2e-4 + 2e-3))
    ps = np.linspace(0.1, 1, 50)
    assert np.all(np.diff([one_cycle(p, NET_LR_MIN, NET_LR_MAX) for p in ps]) < 0)
    assert one_cycle_factor(0.1) == pytest.approx(1.0)


def test_gaussian_schedule_warms_up_then_follows_3dgs():
    assert gaussian_factor("sh_dc", 0.0) == pytest.approx(NET_LR_MIN / NET_LR_MAX)
    assert gaussian_factor("sh_dc", 0.1) == gaussian_factor("opacity_logits", 0.7) == 1.0
    assert gaussian_factor("means", 0.1) == pytest.approx(1.0)
    assert gaussian_factor("means", 0.55) == pytest.approx(POSITION_DECAY**0.5)
    assert gaussian_factor("means", 1.0) == pytest.approx(POSITION_DECAY)
