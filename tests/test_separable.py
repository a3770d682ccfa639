"""acesplat.scr.network.SeparableConv2d: the separable layer against the full convolution it equals, and the
encoder built with it (loading, the dense stride, multiply-accumulates)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from acesplat.scr.encoders import load_encoder
from acesplat.scr.network import Encoder, EncoderConfig, HeadConfig, SeparableConv2d, count_macs, normalize_gray
from tests.macs_reference import encoder_macs

SMALL = {"c1": 8, "c2": 8, "c3": 16, "c4": 16, "res2": 24, "out": 32}


def _as_full(sep: SeparableConv2d) -> tuple[torch.Tensor, torch.Tensor]:
    """The full (out, in, k, k) kernel and bias the separable layer computes away from the image border: output
    channel o filters point_o . x with depth_o, so W[o, i] = depth[o] * point[o, i] and the point bias passes
    through the sum of depth[o]."""
    p = sep.point.weight[:, :, 0, 0]  # (out, in)
    d = sep.depth.weight[:, 0]  # (out, k, k)
    w = d[:, None] * p[:, :, None, None]
    b = sep.depth.bias + sep.point.bias * d.sum(dim=(1, 2))
    return w, b


@pytest.mark.parametrize("dilation", [1, 2])
def test_separable_conv_equals_the_full_convolution_it_factors(dilation: int) -> None:
    torch.manual_seed(0)
    sep = SeparableConv2d(6, 10, 3)
    nn.init.normal_(sep.point.bias)
    nn.init.normal_(sep.depth.bias)
    x = torch.randn(2, 6, 13, 17)
    w, b = _as_full(sep)
    with torch.no_grad():
        got = sep(x, dilation=dilation)
        want = F.conv2d(x, w, b, padding=dilation, dilation=dilation)
    assert got.shape == want.shape == (2, 10, 13, 17)
    inner = (slice(None), slice(None), slice(dilation, -dilation), slice(dilation, -dilation))
    assert torch.allclose(got[inner], want[inner], atol=1e-5)
    # at the border the point bias meets the depthwise layer's zero padding, which the full layer's padding does
    # not see: the two differ there only by the bias
    with torch.no_grad():
        sep.point.bias.zero_()
        assert torch.allclose(
            sep(x, dilation=dilation), F.conv2d(x, *_as_full(sep), padding=dilation, dilation=dilation), atol=1e-5
        )
    assert sep.kernel_size == (3, 3)


def test_a_separable_encoder_file_loads_as_built_and_counts_its_macs(tmp_path) -> None:
    torch.manual_seed(1)
    cfg = EncoderConfig(**SMALL, separable=True)
    enc = Encoder(cfg).eval()
    assert isinstance(enc.res2_conv3, SeparableConv2d)
    path = tmp_path / "separable.pt"
    torch.save(enc.state_dict(), path)
    loaded, _ = load_encoder(path)
    assert loaded.cfg == cfg and isinstance(loaded.res2_conv3, SeparableConv2d)
    rng = np.random.default_rng(0)
    x = normalize_gray(torch.from_numpy(rng.integers(0, 256, (48, 64)).astype(np.float32))[None, None])
    with torch.no_grad():
        for stride in (8, 4):
            assert torch.equal(loaded(x, stride), enc(x, stride))
        assert loaded(x, 4).shape[2:] == (12, 16)
    macs = encoder_macs(loaded, 48, 64)  # brute force: every convolution at its output size
    assert len(macs) == 12  # the full layer's place holds two convolutions
    got = count_macs(loaded.cfg, HeadConfig(16, 1), 48, 64)["encoder_gmac"]
    assert got * 1e9 == pytest.approx(sum(macs))
    assert got < count_macs(EncoderConfig(**SMALL), HeadConfig(16, 1), 48, 64)["encoder_gmac"]


def test_an_encoder_is_factorized_or_separable_not_both() -> None:
    with pytest.raises(ValueError, match="either factorized"):
        EncoderConfig(**SMALL, rank=8, separable=True)
