"""Feature adapter and pixel-resolution coordinates: shapes and where a cell's value lands."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from acesplat.core.grid import cell_centers
from acesplat.splat.adapter import AdapterConfig, FeatureAdapter
from acesplat.splatcore.pixel_coords import corner_range, upsample_cells


@pytest.fixture(autouse=True)
def _one_torch_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def pass_through_adapter(channels: int = 4) -> FeatureAdapter:
    """An adapter whose 1x1 reduction and 3x3 convolutions copy channel 0: it then only upsamples."""
    a = FeatureAdapter(AdapterConfig(in_channels=channels, widths=(2, 2, 2, 2)))
    with torch.no_grad():
        for m in [a.reduce, *a.convs]:
            m.weight.zero_()
            m.bias.zero_()
            k = m.weight.shape[-1] // 2
            m.weight[0, 0, k, k] = 1.0
    return a


@pytest.mark.parametrize("hw", [(48, 64), (45, 61), (41, 57), (8, 8)])
def test_output_shape_follows_the_image(hw):
    h, w = hw
    grid = ((h + 7) // 8, (w + 7) // 8)  # what the stride-8 encoder gives (ceil)
    a = FeatureAdapter(AdapterConfig(in_channels=16))
    out = a(torch.randn(2, 16, *grid), h, w)
    assert out.shape == (2, a.cfg.out_channels, h, w)
    assert torch.isfinite(out).all()


def test_shape_errors():
    a = FeatureAdapter(AdapterConfig(in_channels=16))
    with pytest.raises(ValueError, match="does not cover"):
        a(torch.randn(1, 16, 6, 8), 60, 64)  # 6 cells cover at most 48 rows
    with pytest.raises(ValueError, match="does not cover"):
        a(torch.randn(1, 16, 6, 8), 40, 64)  # a 5-cell image would give a 5-row grid
    with pytest.raises(ValueError, match="features must have shape"):
        a(torch.randn(1, 8, 6, 8), 48, 64)
    with pytest.raises(ValueError):
        AdapterConfig(widths=(8, 8, 8))


@pytest.mark.parametrize("cell", [(0, 0), (2, 3), (5, 7), (3, 0)])
def test_a_cell_lands_on_its_own_pixels(cell):
    """A feature at cell (i, j) peaks on the pixels the cell covers, centred within half a pixel of (8j+4, 8i+4)."""
    i, j = cell
    a = pass_through_adapter()
    x = torch.zeros(1, 4, 6, 8)
    x[0, 0, i, j] = 1.0
    with torch.no_grad():
        y = a(x, 48, 64)[0, 0].numpy()
    rows, cols = np.nonzero(y == y.max())
    # The peak never leaves the cell's own 8x8 block (at the border, the clamped edge of it).
    assert set(rows) <= set(range(8 * i, 8 * i + 8)) and set(cols) <= set(range(8 * j, 8 * j + 8))
    centre = np.array(cell_centers(6, 8)[i * 8 + j])  # (8j + 4, 8i + 4), the project's cell convention
    if 0 < i < 5 and 0 < j < 7:  # away from the clamped border the response is symmetric
        assert set(rows) == {8 * i + 3, 8 * i + 4} and set(cols) == {8 * j + 3, 8 * j + 4}
        ys, xs = np.mgrid[0:48, 0:64]
        cy, cx = (y * ys).sum() / y.sum(), (y * xs).sum() / y.sum()
        assert abs(cx - centre[0]) <= 0.5 + 1e-9 and abs(cy - centre[1]) <= 0.5 + 1e-9
        assert (cx, cy) == pytest.approx((8 * j + 3.5, 8 * i + 3.5), abs=1e-6)


def test_numpy_upsampling_matches_torch_bilinear():
    rng = np.random.default_rng(0)
    v = rng.random((5, 7))
    ref = F.interpolate(torch.from_numpy(v)[None, None], scale_factor=8, mode="bilinear", align_corners=False)[0, 0]
    np.testing.assert_allclose(upsample_cells(v, 40, 56), ref.numpy(), atol=1e-12)
    np.testing.assert_allclose(upsample_cells(v, 37, 50), ref.numpy()[:37, :50], atol=1e-12)


def test_corner_range_brackets_the_interpolation():
    rng = np.random.default_rng(1)
    v = rng.random((5, 7))
    up = upsample_cells(v, 40, 56)
    lo, hi = corner_range(v, 40, 56)
    assert np.all(lo <= up + 1e-12) and np.all(up <= hi + 1e-12)
    # pixel (8j + 3, 8i + 3) sits between cells (i-1..i, j-1..j)
    assert lo[19, 27] == pytest.approx(v[1:3, 2:4].min()) and hi[19, 27] == pytest.approx(v[1:3, 2:4].max())
