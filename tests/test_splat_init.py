"""Init head, per-view Gaussians and the merged scene set on a hand-made planar view."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from acesplat.core.camera import Intrinsics
from acesplat.core.gaussians import SH_C0
from acesplat.core.geometry import look_at
from acesplat.splat.adapter import AdapterConfig
from acesplat.splat.init_head import InitHead, InitHeadConfig, decode_gaussians
from acesplat.splat.instantiate import GaussianInitializer, merge_views, view_pixels
from acesplat.splat.params import check_tensors, gaussians_from_params, params_from_tensors
from acesplat.splat.views import SplatView
from acesplat.splatcore.head_io import PRIOR_CHANNELS, SceneNorm, coordinate_prior
from acesplat.splatcore.lattice import choose_stride, lattice_pixels
from acesplat.splatcore.seeding import OPACITY_PRIOR, SCALE_PRIOR, block_colours
from acesplat.splatcore.validity import cell_pixels, cell_validity

K = Intrinsics(40.0, 40.0, 23.5, 15.5, 48, 32)
POSE = look_at(np.array([0.0, 0.0, 1.0]), np.array([0.0, 4.0, 1.0]))


@pytest.fixture(autouse=True)
def _one_torch_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def planar_view(name: str = "v", depth: float = 2.0, pose: np.ndarray = POSE, channels: int = 8) -> SplatView:
    """A view of a fronto-parallel plane with exact SCR coordinates, a colour ramp and random features."""
    h, w = 4, 6
    uv = cell_pixels(h, w)
    Xc = np.stack([(uv[..., 0] - K.cx) / K.fx, (uv[..., 1] - K.cy) / K.fy, np.ones((h, w))], -1) * depth
    coords = Xc @ pose[:3, :3].T + pose[:3, 3]
    u, v = np.meshgrid(np.linspace(0, 1, 48), np.linspace(0, 1, 32))
    rgb = np.stack([u, v, 0.5 * np.ones_like(u)], -1).astype(np.float32)
    view = SplatView(name, pose, K, rgb, (rgb[..., 0] * 255).astype(np.uint8))
    view.coords = coords.astype(np.float32)
    view.validity = cell_validity(coords, pose, K)
    view.features = torch.randn(1, channels, h, w, generator=torch.Generator().manual_seed(0)).to(torch.float16)
    return view


def test_fresh_head_gives_the_analytic_start():
    head = InitHead(InitHeadConfig(feature_channels=8))
    raw = head(torch.randn(1, 8, 5, 7), torch.randn(1, PRIOR_CHANNELS, 5, 7))
    assert raw.shape == (1, 1 + 3 + 3 + 4, 5, 7) and float(raw.detach().abs().max()) == 0.0
    rgb = torch.tensor([[0.2, 0.4, 0.9], [1.0, 0.0, 0.5]])
    centres = torch.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    depth = torch.tensor([2.0, 4.0])
    g = decode_gaussians(
        torch.zeros(2, 11), rgb, centres, depth, focal_px=100.0, spacing_px=4.0, head_sh_degree=0, sh_degree=2
    )
    assert check_tensors(g) == 2 and g["sh"].shape == (2, 9, 3)
    np.testing.assert_allclose(
        (g["sh"][:, 0] * SH_C0 + 0.5).numpy(), rgb.numpy(), atol=1e-6
    )  # renders the pixel colour
    assert float(g["sh"][:, 1:].abs().max()) == 0.0
    np.testing.assert_allclose(torch.sigmoid(g["opacity_logits"]).numpy(), OPACITY_PRIOR, rtol=1e-6)
    np.testing.assert_allclose(
        g["log_scales"].exp().numpy(), (SCALE_PRIOR * 4.0 * depth / 100.0)[:, None].expand(2, 3).numpy(), rtol=1e-6
    )
    assert torch.equal(g["quats"], torch.tensor([[1.0, 0, 0, 0]] * 2)) and torch.equal(g["means"], centres)


def test_head_and_decode_shape_checks():
    head = InitHead(InitHeadConfig(feature_channels=8))
    with pytest.raises(ValueError, match="prior"):
        head(torch.randn(1, 8, 5, 7), torch.randn(1, PRIOR_CHANNELS, 5, 6))
    with pytest.raises(ValueError, match="features"):
        head(torch.randn(1, 4, 5, 7), torch.randn(1, PRIOR_CHANNELS, 5, 7))
    with pytest.raises(ValueError, match="raw"):
        decode_gaussians(torch.zeros(2, 10), torch.zeros(2, 3), torch.zeros(2, 3), torch.ones(2), 1.0, 1.0, 0, 0)
    with pytest.raises(ValueError):
        GaussianInitializer(AdapterConfig(in_channels=8, widths=(8, 8, 8, 4)), InitHeadConfig(feature_channels=8))


def test_lattice_and_stride():
    valid = np.ones((5, 6), bool)
    valid[0, 0] = False
    idx = lattice_pixels(valid, 2, (0, 1))
    assert idx.tolist() == [1, 3, 5, 13, 15, 17, 25, 27, 29]
    assert lattice_pixels(valid, 2, (2, 2)).tolist() == [2, 4, 12, 14, 16, 24, 26, 28]  # offsets wrap modulo the stride
    assert lattice_pixels(valid, 1).size == 29
    assert choose_stride(100, 100) == 1 and choose_stride(101, 100) == 2 and choose_stride(900, 100) == 3
    with pytest.raises(ValueError):
        lattice_pixels(valid, 0)


def test_block_colours_low_pass_only_beyond_one_pixel():
    rgb = np.random.default_rng(0).random((16, 16, 3)).astype(np.float32)
    assert block_colours(rgb, 1.0) is rgb
    flat = np.full((16, 16, 3), 0.25, np.float32)
    np.testing.assert_allclose(block_colours(flat, 4.0), 0.25, atol=1e-6)
    assert block_colours(rgb, 4.0).std() < rgb.std()


def test_coordinate_prior_and_scene_norm():
    norm = SceneNorm.from_views(np.array([[0.0, 0, 0], [2.0, 0, 0]]), np.array([1.0, 3.0, 5.0]))
    assert norm.centre == (1.0, 0.0, 0.0) and norm.scale == 3.0  # max(camera spread 1, median depth 3)
    rgb = np.full((2, 3, 3), 0.75, np.float32)
    centres = np.zeros((2, 3, 3))
    centres[..., 0] = 4.0
    prior = coordinate_prior(rgb, centres, np.full((2, 3), 3.0), norm)
    assert prior.shape == (PRIOR_CHANNELS, 2, 3) and prior.dtype == np.float32
    np.testing.assert_allclose(prior[:, 0, 0], [0.25, 0.25, 0.25, 1.0, 0.0, 0.0, 0.0], atol=1e-7)


def test_view_gaussians_sit_on_the_pixels_and_train_the_networks():
    view = planar_view()
    norm = SceneNorm((0.0, 2.0, 1.0), 2.0)
    init = GaussianInitializer(AdapterConfig(in_channels=8), InitHeadConfig())
    pix = view_pixels(view, norm)
    assert pix.valid.all() and pix.prior.shape == (1, PRIOR_CHANNELS, 32, 48)
    idx = lattice_pixels(pix.valid, 4)
    g = init.view_gaussians(view, pix, idx, 4.0, sh_degree=3)
    assert check_tensors(g) == idx.size == 8 * 12
    # centres project back onto their pixels at the plane's depth
    w2c = np.linalg.inv(POSE)
    Xc = g["means"].detach().double().numpy() @ w2c[:3, :3].T + w2c[:3, 3]
    np.testing.assert_allclose(Xc[:, 2], 2.0, rtol=1e-5)
    u = K.fx * Xc[:, 0] / Xc[:, 2] + K.cx
    np.testing.assert_allclose(u, idx % 48, atol=1e-3)
    # a loss on the Gaussians reaches both networks (the head's last layer starts at zero, so push it first)
    with torch.no_grad():
        init.head.out.weight.normal_(0, 0.1)
    g = init.view_gaussians(view, pix, idx, 4.0, sh_degree=3)
    loss = sum(t.float().pow(2).sum() for k, t in g.items() if k != "means")
    loss.backward()
    assert init.head.out.weight.grad.abs().sum() > 0
    assert init.adapter.reduce.weight.grad.abs().sum() > 0


def test_merge_keeps_one_layer_for_repeated_views_and_respects_the_budget():
    views = [planar_view("a"), planar_view("b")]
    norm = SceneNorm((0.0, 2.0, 1.0), 2.0)
    init = GaussianInitializer(AdapterConfig(in_channels=8), InitHeadConfig())
    pixels = [view_pixels(v, norm) for v in views]
    rng = np.random.default_rng(0)
    fused, rep = merge_views(views, pixels, init, 48 * 32, 1, rng)
    assert rep.stride == 1 and rep.per_view == [48 * 32, 0] and rep.novel_pixels == 48 * 32
    assert fused["means"].shape[0] == 48 * 32 and fused["sh"].shape == (48 * 32, 4, 3)
    stacked, rep2 = merge_views(views, pixels, init, 400, 1, rng, fuse=False)
    assert rep2.stride == math.ceil(math.sqrt(2 * 48 * 32 / 400)) == 3
    assert stacked["means"].shape[0] == sum(rep2.per_view) <= 2 * 11 * 16
    params = params_from_tensors(stacked)
    g = gaussians_from_params(params)
    assert len(g) == sum(rep2.per_view) and g.sh_degree == 1 and params["means"].requires_grad
