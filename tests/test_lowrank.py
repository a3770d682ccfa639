"""acesplat.scr.lowrank: the reduced-rank convolution against brute force, and the encoder built with it."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from acesplat.scr.encoders import load_encoder
from acesplat.scr.lowrank import factorize_conv, layer_outputs, lowrank_encoder
from acesplat.scr.network import Encoder, EncoderConfig, FactorizedConv2d, HeadConfig, count_macs, normalize_gray
from tests.macs_reference import encoder_macs


def _samples(conv: nn.Conv2d, x: torch.Tensor) -> torch.Tensor:
    """(N, C_out) outputs of ``conv`` on ``x`` (B, C_in, h, w), one row per pixel."""
    with torch.no_grad():
        return conv(x).permute(0, 2, 3, 1).reshape(-1, conv.out_channels)


def test_outputs_confined_to_a_subspace_are_reproduced_exactly_at_its_rank() -> None:
    torch.manual_seed(0)
    conv = nn.Conv2d(6, 10, 3, 1, 1)
    basis = torch.linalg.qr(torch.randn(10, 3))[0]  # the outputs' 3-d subspace (around the bias)
    with torch.no_grad():
        conv.weight.copy_(torch.einsum("or,rikl->oikl", basis, torch.randn(3, 6, 3, 3)))
    x = torch.randn(2, 6, 9, 11)
    pair, kept = factorize_conv(conv, _samples(conv, x), rank=3)
    with torch.no_grad():
        assert torch.allclose(pair(x), conv(x), atol=1e-4)
        other = torch.randn(1, 6, 5, 7)  # any input: the weights themselves have rank 3
        assert torch.allclose(pair(other), conv(other), atol=1e-4)
    assert kept == pytest.approx(1.0, abs=1e-9)


def test_kept_variance_and_the_fit_match_a_numpy_principal_component_reference() -> None:
    torch.manual_seed(1)
    conv = nn.Conv2d(4, 8, 3, 1, 1)
    x = torch.randn(3, 4, 10, 10)
    y = _samples(conv, x).double().numpy()
    pair, kept = factorize_conv(conv, torch.from_numpy(y), rank=5)
    mu = y.mean(0)
    eigval, eigvec = np.linalg.eigh(np.cov(y - mu, rowvar=False, bias=True))
    order = np.argsort(eigval)[::-1]
    eigval, eigvec = eigval[order], eigvec[:, order]
    assert kept == pytest.approx(eigval[:5].sum() / eigval.sum(), rel=1e-9)
    u = eigvec[:, :5]
    want = mu + (y - mu) @ u @ u.T  # projection onto the top 5 principal components
    with torch.no_grad():
        got = pair(x).permute(0, 2, 3, 1).reshape(-1, 8).double().numpy()
    assert np.abs(got - want).max() < 1e-4 * np.abs(want).max()


def test_the_reduced_channels_are_whitened_on_the_fitting_samples() -> None:
    torch.manual_seed(2)
    conv = nn.Conv2d(5, 12, 3, 1, 1)
    x = torch.randn(4, 5, 8, 8) * torch.tensor([1.0, 5.0, 0.1, 2.0, 1.0])[None, :, None, None]
    pair, _ = factorize_conv(conv, _samples(conv, x), rank=4)
    with torch.no_grad():
        z = pair.reduce(x).permute(0, 2, 3, 1).reshape(-1, 4).double()
    assert torch.allclose(z.mean(0), torch.zeros(4, dtype=torch.float64), atol=1e-5)
    assert torch.allclose(z.std(0, unbiased=False), torch.ones(4, dtype=torch.float64), atol=1e-4)


def test_dilation_runs_the_reduce_layer_dilated_as_the_encoder_does_at_stride_4() -> None:
    torch.manual_seed(3)
    pair = FactorizedConv2d(3, 7, 2, 3)
    x = torch.randn(1, 3, 12, 12)
    r, e = pair.reduce, pair.expand
    want = F.conv2d(F.conv2d(x, r.weight, r.bias, padding=2, dilation=2), e.weight, e.bias)
    with torch.no_grad():
        assert torch.allclose(pair(x, dilation=2), want, atol=1e-6)
        assert pair(x).shape == (1, 7, 12, 12) and pair.kernel_size == (3, 3)


def test_bad_arguments_are_refused_before_any_work() -> None:
    conv = nn.Conv2d(4, 8, 3, 1, 1)
    ok = torch.randn(20, 8)
    with pytest.raises(ValueError, match="rank must be in"):
        factorize_conv(conv, ok, rank=8)
    with pytest.raises(ValueError, match="rank must be in"):
        factorize_conv(conv, ok, rank=0)
    with pytest.raises(ValueError, match=r"outputs must be \(N, 8\)"):
        factorize_conv(conv, torch.randn(20, 7), rank=2)
    with pytest.raises(ValueError, match="at least 2 samples"):
        factorize_conv(conv, torch.randn(1, 8), rank=2)
    with pytest.raises(TypeError, match="stride-1"):
        factorize_conv(nn.Conv2d(4, 8, 3, 2, 1), ok, rank=2)


def _images(n: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:48, 0:64]
    out = []
    for _ in range(n):
        f = rng.uniform(0.05, 0.4, 2)
        img = 128 + 60 * np.sin(f[0] * xx + rng.uniform(0, 6)) * np.cos(f[1] * yy) + rng.normal(0, 20, (48, 64))
        out.append(np.clip(img, 0, 255).astype(np.uint8))
    return out


@pytest.mark.parametrize("stride", [8, 4])
def test_lowrank_encoder_keeps_the_features_and_leaves_the_original_untouched(stride: int) -> None:
    torch.manual_seed(4)
    enc = Encoder(EncoderConfig(c1=8, c2=8, c3=16, c4=16, res2=24, out=32)).eval()
    before = {k: v.clone() for k, v in enc.state_dict().items()}
    fit = _images(4, 0)
    small, report = lowrank_encoder(enc, fit, rank=24)
    assert isinstance(small.res2_conv3, FactorizedConv2d) and isinstance(enc.res2_conv3, nn.Conv2d)
    assert all(torch.equal(before[k], v) for k, v in enc.state_dict().items())
    assert report["rank"] == 24 and report["samples"] == 4 * 6 * 8 and report["images"] == 4
    assert report["macs_per_cell"] == 24 * (24 * 9 + 32) < report["macs_per_cell_full"] == 32 * 24 * 9
    assert 0.9 < report["kept_variance"] <= 1.0
    x = normalize_gray(torch.from_numpy(_images(1, 7)[0]).float()[None, None])  # an image it was not fitted on
    with torch.no_grad():
        a, b = enc(x, stride), small(x, stride)
    assert a.shape == b.shape
    assert float((a - b).norm() / a.norm()) < 0.1


def test_layer_outputs_are_one_row_per_stride_8_cell() -> None:
    enc = Encoder(EncoderConfig(c1=8, c2=8, c3=16, c4=16, res2=24, out=32)).eval()
    rows = layer_outputs(enc, _images(2, 1))
    assert rows.shape == (2 * 6 * 8, 32)
    with pytest.raises(ValueError, match="grayscale"):
        layer_outputs(enc, [np.zeros((48, 64, 3), np.uint8)])
    with pytest.raises(ValueError, match="at least one image"):
        layer_outputs(enc, [])


def test_a_factorized_encoder_file_loads_as_built_and_counts_its_macs(tmp_path) -> None:
    torch.manual_seed(5)
    cfg = EncoderConfig(c1=8, c2=8, c3=16, c4=16, res2=24, out=32)
    small, _ = lowrank_encoder(Encoder(cfg).eval(), _images(3, 2), rank=12)
    path = tmp_path / "factorized.pt"
    torch.save(small.state_dict(), path)
    loaded, _ = load_encoder(path)
    assert loaded.cfg == EncoderConfig(c1=8, c2=8, c3=16, c4=16, res2=24, out=32, rank=12)
    assert isinstance(loaded.res2_conv3, FactorizedConv2d)
    x = normalize_gray(torch.from_numpy(_images(1, 9)[0]).float()[None, None])
    with torch.no_grad():
        assert torch.equal(loaded(x), small(x))
    macs = encoder_macs(loaded, 48, 64)  # brute force: every convolution at its output size
    assert count_macs(loaded.cfg, HeadConfig(16, 1), 48, 64)["encoder_gmac"] * 1e9 == pytest.approx(sum(macs))
    assert (
        count_macs(loaded.cfg, HeadConfig(16, 1), 48, 64)["encoder_gmac"]
        < count_macs(cfg, HeadConfig(16, 1), 48, 64)["encoder_gmac"]
    )
