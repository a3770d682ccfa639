"""The torch autograd wrapper: same numbers as the numpy rasterizer, gradients by autograd and gradcheck."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from acesplat.core.gaussians import Gaussians
from acesplat.raster import ndc_grad_norm, rasterize
from acesplat.splat import render, screen_grad_norm
from tests.raster_reference import random_scene, render_reference

PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh")


def _tensors(params: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    return {n: torch.tensor(params[n], requires_grad=True) for n in PARAMS}


def test_render_matches_numpy_and_reference_gradients() -> None:
    params, pose, k = random_scene(50, 8, dtype=np.float64)
    bg = (0.2, 0.4, 0.6)
    ours = _tensors(params)
    out = render(**ours, pose_c2w=pose, intrinsics=k, background=bg)
    np.testing.assert_array_equal(out.color.detach().numpy(), rasterize(Gaussians(**params), pose, k, bg).color)

    ref_t = _tensors(params)
    ref = render_reference(**ref_t, pose_c2w=pose, k=k, background=np.array(bg), sh_degree=3)
    rng = np.random.default_rng(0)
    wc = torch.tensor(rng.normal(size=(k.height, k.width, 3)))
    wd = torch.tensor(rng.normal(size=(k.height, k.width)))
    ((out.color * wc).sum() + (out.depth * wd).sum() + out.alpha.sum()).backward()
    ((ref.color * wc).sum() + (ref.depth * wd).sum() + ref.alpha.sum()).backward()
    for n in PARAMS:
        a, b = ours[n].grad.numpy(), ref_t[n].grad.numpy()
        assert np.linalg.norm(a - b) <= 1e-8 * np.linalg.norm(b), n
    vis = out.visible.numpy()
    np.testing.assert_allclose(out.means2d.grad.numpy()[vis], ref.means2d.grad.numpy()[vis], rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(out.means2d.detach().numpy()[vis], ref.means2d.detach().numpy()[vis], rtol=1e-12)
    np.testing.assert_allclose(
        screen_grad_norm(out, k).numpy(), ndc_grad_norm(out.means2d.grad.numpy(), k.width, k.height)
    )
    assert out.radii.dtype == torch.int32 and (out.radii[~out.visible] == 0).all()


def test_colour_only_loss_and_float32() -> None:
    params, pose, k = random_scene(40, 9, dtype=np.float32)
    t = _tensors(params)
    out = render(**t, pose_c2w=torch.tensor(pose), intrinsics=k, background=torch.zeros(3))
    assert out.color.dtype == torch.float32
    out.color.mean().backward()
    for n in PARAMS:
        assert t[n].grad is not None and t[n].grad.dtype == torch.float32 and torch.isfinite(t[n].grad).all()
    assert t["means"].grad.abs().sum() > 0
    assert screen_grad_norm(render(**t, pose_c2w=pose, intrinsics=k), k).abs().sum() == 0  # before backward


def test_gradcheck_on_a_tiny_scene() -> None:
    """torch's own finite differences through the whole wrapper, every input element."""
    params, pose, k = random_scene(4, 13, width=16, height=12, dtype=np.float64, sh_degree=1)
    params["opacity_logits"][:] = [0.5, 1.0, -0.5, 2.0]
    t = tuple(torch.tensor(params[n], requires_grad=True) for n in PARAMS)

    def f(*args: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = render(*args, pose_c2w=pose, intrinsics=k, background=(0.3, 0.2, 0.1))
        return out.color, out.alpha, out.depth

    assert render(*t, pose_c2w=pose, intrinsics=k).visible.sum() >= 2
    assert torch.autograd.gradcheck(f, t, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_bad_tensors_are_refused() -> None:
    params, pose, k = random_scene(3, 0, dtype=np.float64)
    t = _tensors(params)
    with pytest.raises(TypeError, match="must all be float32 or all float64"):
        render(t["means"].float(), t["log_scales"], t["quats"], t["opacity_logits"], t["sh"], pose, k)
    with pytest.raises(TypeError, match="sh must be a torch.Tensor"):
        render(t["means"], t["log_scales"], t["quats"], t["opacity_logits"], params["sh"], pose, k)
    with pytest.raises(ValueError, match="quats must have shape"):
        render(t["means"], t["log_scales"], t["quats"][:, :3], t["opacity_logits"], t["sh"], pose, k)
