"""The comparison starts (3DGS point-cloud init, random points) and the LPIPS module, by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from acesplat.core.errors import InputError
from acesplat.core.gaussians import sh_dc_to_rgb
from acesplat.splat.lpips import LPIPSAlex, load_lpips
from acesplat.splat.point_init import POINT_OPACITY, gaussians_from_points, random_points


def test_point_gaussians_follow_the_3dgs_recipe():
    pts = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.0, 2.0, 0], [0.0, 0, 4.0], [10.0, 0, 0]])
    cols = np.linspace(0, 1, 15).reshape(5, 3)
    g = gaussians_from_points(pts, cols, sh_degree=1)
    # mean distance to the 3 nearest other points, the same on all three axes
    expected0 = (1.0 + 2.0 + 4.0) / 3
    assert math.exp(float(g.log_scales[0, 0])) == pytest.approx(expected0, rel=1e-5)
    np.testing.assert_allclose(g.log_scales[:, 0], g.log_scales[:, 2])
    np.testing.assert_allclose(g.opacities(), POINT_OPACITY, rtol=1e-5)
    np.testing.assert_allclose(sh_dc_to_rgb(g.sh[:, 0]), cols, atol=1e-6)
    assert g.sh.shape == (5, 4, 3) and float(np.abs(g.sh[:, 1:]).max()) == 0.0
    np.testing.assert_allclose(g.unit_quats(), [[1, 0, 0, 0]] * 5)
    with pytest.raises(ValueError):
        gaussians_from_points(pts[:1], cols[:1])
    with pytest.raises(ValueError):
        gaussians_from_points(pts, cols[:4])


def test_random_points_fill_the_cube_around_the_cameras():
    cams = np.array([[1.0, 1.0, 1.0], [3.0, 1.0, 1.0]])
    pts, cols = random_points(2000, cams, 0.5, np.random.default_rng(0))
    assert pts.shape == (2000, 3) and cols.shape == (2000, 3)
    assert np.all(np.abs(pts - [2.0, 1.0, 1.0]) <= 0.5) and np.all((cols >= 0) & (cols <= 1))
    assert np.abs(pts.mean(0) - [2.0, 1.0, 1.0]).max() < 0.05


def _lpips_file(path, seed: int = 0, drop: str | None = None) -> None:
    torch.manual_seed(seed)
    m = LPIPSAlex()
    sd = {
        f"features.{k.split('.')[1]}.{k.split('.')[2]}": v for k, v in m.state_dict().items() if k.startswith("convs.")
    }
    for j, lin in enumerate(m.lins):
        sd[f"lin{j}.model.1.weight"] = lin.weight.detach().abs()  # LPIPS's linear weights are non-negative
    sd.pop(drop, None)
    torch.save(sd, path)


def test_lpips_is_a_distance_and_reads_the_published_key_names(tmp_path):
    _lpips_file(tmp_path / "both.pth")
    fn = load_lpips(tmp_path / "both.pth")
    rng = np.random.default_rng(0)
    a = torch.from_numpy(rng.random((64, 64, 3)).astype(np.float32))
    b = torch.from_numpy(np.clip(a.numpy() + 0.2 * rng.standard_normal((64, 64, 3)), 0, 1).astype(np.float32))
    c = torch.from_numpy(np.clip(a.numpy() + 0.05 * rng.standard_normal((64, 64, 3)), 0, 1).astype(np.float32))
    assert fn(a, a) == pytest.approx(0.0, abs=1e-7)
    assert fn(a, b) == pytest.approx(fn(b, a), rel=1e-5)
    assert fn(a, b) > fn(a, c) > 0.0


def test_lpips_missing_tensor_names_the_key(tmp_path):
    _lpips_file(tmp_path / "bad.pth", drop="lin3.model.1.weight")
    with pytest.raises(InputError, match="lin3.model.1.weight"):
        load_lpips(tmp_path / "bad.pth")
    with pytest.raises(InputError, match="not found"):
        load_lpips(tmp_path / "none.pth")
