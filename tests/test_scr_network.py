"""SCR network: shapes, the homogeneous output and mean offset, ACE-compatible encoder files, the map file."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from acesplat.core.errors import InputError
from acesplat.scr.encoders import ENCODER_KEYS, load_encoder
from acesplat.scr.mapfile import SceneMap, encoder_for_map, load_map, save_map
from acesplat.scr.network import ACE_ENCODER, Encoder, EncoderConfig, Head, HeadConfig, SCRNetwork, count_macs

TINY = EncoderConfig(4, 8, 8, 16, 16, 32)


def test_output_stride_and_shape() -> None:
    net = SCRNetwork(Encoder(TINY), Head(torch.zeros(3), 32, HeadConfig(16, 1)))
    out = net(torch.randint(0, 255, (2, 1, 48, 64)).float())
    assert out.shape == (2, 3, 6, 8)


def test_dense_output_holds_the_stride_8_cells_and_those_of_the_half_cell_shifted_image() -> None:
    torch.manual_seed(0)
    enc = Encoder(TINY).eval()
    x = torch.randn(1, 1, 160, 224)
    with torch.no_grad():
        sparse, dense, shifted = enc(x), enc(x, output_stride=4), enc(x[:, :, 4:, 4:])
    assert dense.shape == (1, 32, 40, 56) and sparse.shape == (1, 32, 20, 28)
    torch.testing.assert_close(dense[:, :, ::2, ::2], sparse, rtol=1e-5, atol=1e-5)
    # Odd cells are the cells of the image cropped by 4 px, away from the borders whose zero padding differs.
    m = 6
    odd = dense[:, :, 1::2, 1::2]
    torch.testing.assert_close(
        odd[:, :, m:-m, m:-m], shifted[:, :, m : odd.shape[2] - m, m : odd.shape[3] - m], rtol=1e-5, atol=1e-5
    )
    net = SCRNetwork(enc, Head(torch.zeros(3), 32, HeadConfig(16, 1))).eval()
    assert net(torch.zeros(1, 1, 48, 64), output_stride=4).shape == (1, 3, 12, 16)
    with pytest.raises(ValueError, match="output_stride"):
        enc(x, output_stride=2)


def test_homogeneous_output_divides_by_softplus_scale_and_adds_mean() -> None:
    mean = torch.tensor([1.0, -2.0, 3.0])
    head = Head(mean, 32, HeadConfig(16, 0, homogeneous=True))
    with torch.no_grad():
        for p in head.parameters():
            p.zero_()
        # Make the final layer output (x, y, z, h_raw) = (2, 4, 6, 0) everywhere.
        head.fc3.bias.copy_(torch.tensor([2.0, 4.0, 6.0, 0.0]))
    out = head(torch.randn(1, 32, 2, 2))
    beta = np.log(2) / (1 - 1 / 4.0)
    h = np.log1p(np.exp(beta * 0.0)) / beta + 1 / 4.0  # softplus_beta(0) = ln2 / beta = 0.75, plus 1/max_scale
    expected = np.array([2.0, 4.0, 6.0]) / h + mean.numpy()
    np.testing.assert_allclose(out[0, :, 0, 0].detach().numpy(), expected, rtol=1e-5)
    assert h == pytest.approx(1.0)  # ACE's choice of beta makes a zero output mean scale 1


@pytest.mark.parametrize("homogeneous,width,in_ch", [(True, 16, 32), (False, 32, 32)])
def test_forward_points_is_the_convolutional_head(homogeneous: bool, width: int, in_ch: int) -> None:
    torch.manual_seed(0)
    head = Head(torch.tensor([0.5, -1.0, 2.0]), in_ch, HeadConfig(width, 2, homogeneous=homogeneous))
    f = torch.randn(37, in_ch)
    grid = head(f.T[None, :, :, None])[0, :, :, 0].T.detach()
    np.testing.assert_allclose(head.forward_points(f).detach().numpy(), grid.detach().numpy(), rtol=1e-5, atol=1e-6)
    # bfloat16 hidden layers: about 3 significant digits in the hidden activations, float32 output.
    low = head.forward_points(f, autocast_bf16=True).detach()
    assert low.dtype == torch.float32
    assert float((low - grid).abs().max()) < 0.05 * float(grid.abs().max())


def test_forward_points_rejects_wrong_shapes() -> None:
    head = Head(torch.zeros(3), 32, HeadConfig(16, 0))
    with pytest.raises(ValueError, match=r"\(N, 32\)"):
        head.forward_points(torch.randn(4, 16))
    with pytest.raises(ValueError):
        head.forward_points(torch.randn(1, 32, 2, 2))


def test_homogeneous_scale_is_clamped() -> None:
    head = Head(torch.zeros(3), 32, HeadConfig(16, 0, homogeneous=True))
    with torch.no_grad():
        for p in head.parameters():
            p.zero_()
        head.fc3.bias.copy_(torch.tensor([1.0, 1.0, 1.0, 1e4]))
    out = head(torch.randn(1, 32, 1, 1))
    # h is clamped at 1 / min_scale = 100.
    np.testing.assert_allclose(out[0, :, 0, 0].detach().numpy(), [0.01, 0.01, 0.01], rtol=1e-5)


def test_macs_match_ace_published_figure() -> None:
    m = count_macs(ACE_ENCODER, HeadConfig(512, 1), 480, 640)
    assert m["encoder_gmac"] + m["head_gmac"] == pytest.approx(39.3, abs=0.3)


def _ace_shaped_state_dict() -> dict[str, torch.Tensor]:
    # The names and shapes of ACE's published encoder file, filled with random numbers.
    shapes = {
        "conv1": (32, 1, 3, 3),
        "conv2": (64, 32, 3, 3),
        "conv3": (128, 64, 3, 3),
        "conv4": (256, 128, 3, 3),
        "res1_conv1": (256, 256, 3, 3),
        "res1_conv2": (256, 256, 1, 1),
        "res1_conv3": (256, 256, 3, 3),
        "res2_conv1": (512, 256, 3, 3),
        "res2_conv2": (512, 512, 1, 1),
        "res2_conv3": (512, 512, 3, 3),
        "res2_skip": (512, 256, 1, 1),
    }
    g = torch.Generator().manual_seed(0)
    sd = {}
    for name, shape in shapes.items():
        sd[f"{name}.weight"] = torch.randn(shape, generator=g) * 0.05
        sd[f"{name}.bias"] = torch.randn(shape[0], generator=g) * 0.01
    return sd


def test_ace_encoder_file_loads(tmp_path) -> None:
    sd = _ace_shaped_state_dict()
    assert {k.rsplit(".", 1)[0] for k in sd} == set(ENCODER_KEYS)
    path = tmp_path / "ace_encoder_pretrained.pt"
    torch.save(sd, path)
    enc, ident = load_encoder(path)
    assert enc.cfg == ACE_ENCODER
    assert ident.name == "ace_encoder_pretrained.pt" and len(ident.sha256) == 64
    for k, v in sd.items():
        assert torch.equal(enc.state_dict()[k], v)
    assert enc(torch.zeros(1, 1, 32, 32)).shape == (1, 512, 4, 4)


def test_encoder_file_errors(tmp_path) -> None:
    with pytest.raises(InputError, match="not found"):
        load_encoder(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    torch.save({"conv1.weight": torch.zeros(1)}, bad)
    with pytest.raises(InputError, match="missing"):
        load_encoder(bad)
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a torch file")
    with pytest.raises(InputError, match="junk.pt"):
        load_encoder(junk)


def test_map_round_trip_and_encoder_hash_check(tmp_path) -> None:
    enc = Encoder(TINY)
    enc_path = tmp_path / "enc.pt"
    torch.save(enc.state_dict(), enc_path)
    enc2, ident = load_encoder(enc_path)
    head = Head(torch.tensor([0.5, 1.0, 1.5]), 32, HeadConfig(16, 1))
    m = SceneMap(head, ident, np.array([0.5, 1.0, 1.5]), 120, {"scene": "x"})
    save_map(tmp_path / "m.pt", m)
    m2 = load_map(tmp_path / "m.pt")
    assert m2.short_side == 120 and m2.metadata == {"scene": "x"}
    x = torch.randn(1, 32, 3, 3)
    # The head is stored in fp16: equal to fp16 precision.
    torch.testing.assert_close(m2.head(x), head(x), rtol=2e-2, atol=2e-2)
    assert encoder_for_map(m2, tmp_path / "m.pt") is not None
    torch.save(Encoder(TINY).state_dict(), enc_path)  # a different encoder at the same path
    with pytest.raises(InputError, match="m.pt"):
        encoder_for_map(m2, tmp_path / "m.pt")
