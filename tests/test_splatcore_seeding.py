"""The torch-free splat core shared by Stage 2 and the edge, against analytic or brute-force references: the
seeding lattice, the analytic start, the init head's prior and residual layout, pruning, trusted cell depths and
the two pixel samplers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from acesplat.core.camera import Intrinsics
from acesplat.core.gaussians import SH_C0, Gaussians, logit, sigmoid
from acesplat.core.geometry import invert_pose, look_at
from acesplat.core.grid import OUTPUT_STRIDE
from acesplat.splatcore.bundle_section import INIT_INPUTS, ROLE_GAUSSIANS, ROLE_SPLAT_INIT
from acesplat.splatcore.head_io import (
    OPACITY_CHANNEL,
    PRIOR_CHANNELS,
    SceneNorm,
    coordinate_prior,
    decode_residuals,
    residual_channels,
    residual_slices,
)
from acesplat.splatcore.lattice import choose_stride, lattice_pixels, seed_pixels
from acesplat.splatcore.pixel_coords import pixel_coordinates, pixel_depths
from acesplat.splatcore.prune import PRUNE_OPACITY, cap_keep, transparent
from acesplat.splatcore.seeding import (
    BLOCK_SIGMA,
    OPACITY_PRIOR,
    SCALE_PRIOR,
    SCR_SEED_OPACITY,
    block_colours,
    gaussians_at,
    start_log_scales,
)
from acesplat.splatcore.validity import ValidityConfig, cell_trust, cell_validity

K = Intrinsics(50.0, 50.0, 31.5, 23.5, 64, 48)
POSE = look_at(np.array([0.3, -0.2, 1.0]), np.array([0.5, 3.0, 1.2]))


def cells_at_depth(z: np.ndarray, pose: np.ndarray = POSE, k: Intrinsics = K) -> np.ndarray:
    """World coordinates (h, w, 3) on each cell's ray through (8j + 4, 8i + 4) at camera depth z (h, w)."""
    h, w = z.shape
    ys, xs = np.mgrid[0:h, 0:w]
    u, v = xs * OUTPUT_STRIDE + OUTPUT_STRIDE / 2, ys * OUTPUT_STRIDE + OUTPUT_STRIDE / 2
    Xc = np.stack([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z], -1)
    return Xc @ pose[:3, :3].T + pose[:3, 3]


# ----------------------------------------------------------------------------------------------- lattice
def test_lattice_pixels_match_a_brute_force_scan() -> None:
    rng = np.random.default_rng(0)
    mask = rng.random((17, 23)) < 0.6
    for stride, off in [(1, (0, 0)), (3, (1, 2)), (4, (7, -1)), (5, (0, 4))]:
        want = [
            r * 23 + c
            for r in range(17)
            for c in range(23)
            if mask[r, c] and (r - off[0]) % stride == 0 and (c - off[1]) % stride == 0
        ]
        assert lattice_pixels(mask, stride, off).tolist() == want
    with pytest.raises(ValueError, match="stride"):
        lattice_pixels(mask, 0)
    with pytest.raises(ValueError, match="mask"):
        lattice_pixels(mask.ravel(), 2)


def test_choose_stride_is_the_smallest_that_fits() -> None:
    for valid, budget in [(0, 5), (10, 10), (11, 10), (1000, 7), (123_456, 60_000), (5, 1)]:
        s = choose_stride(valid, budget)
        assert valid / s**2 <= budget
        assert s == 1 or valid / (s - 1) ** 2 > budget
    with pytest.raises(ValueError):
        choose_stride(10, 0)


def test_seed_pixels_lie_on_one_lattice_within_budget() -> None:
    rng = np.random.default_rng(3)
    mask = rng.random((40, 60)) < 0.7
    for spacing, max_new in [(1, 10_000), (2, 10_000), (2, 100), (3, 7)]:
        idx, s = seed_pixels(mask, spacing, max_new, rng)
        assert s >= spacing and idx.size <= max_new and mask.ravel()[idx].all()
        r, c = np.divmod(idx, 60)
        assert len(set(r % s)) <= 1 and len(set(c % s)) <= 1  # one offset
        if idx.size:  # the whole lattice through that offset, not a subset of it
            assert idx.tolist() == lattice_pixels(mask, s, (int(r[0]), int(c[0]))).tolist()
    assert seed_pixels(mask, 2, 0, rng)[0].size == 0
    with pytest.raises(ValueError):
        seed_pixels(mask, 0, 10, rng)


# ------------------------------------------------------------------------------------------ analytic start
def test_gaussians_at_is_the_analytic_start() -> None:
    centres = np.array([[0.0, 1.0, 2.0], [1.0, -1.0, 5.0]])
    depth = np.array([2.0, 5.0])
    rgb = np.array([[0.1, 0.5, 0.9], [1.0, 0.0, 0.25]])
    g = gaussians_at(centres, depth, rgb, focal_px=100.0, spacing_px=3.0, sh_degree=2)
    assert len(g) == 2 and g.sh_degree == 2 and g.means.dtype == np.float32
    np.testing.assert_allclose(g.means, centres)
    np.testing.assert_allclose(np.exp(g.log_scales), np.repeat((SCALE_PRIOR * 3.0 * depth / 100.0)[:, None], 3, 1))
    np.testing.assert_allclose(sigmoid(g.opacity_logits), SCR_SEED_OPACITY, rtol=1e-6)
    np.testing.assert_allclose(SH_C0 * g.sh[:, 0] + 0.5, rgb, atol=1e-6)
    assert not g.sh[:, 1:].any()
    np.testing.assert_allclose(g.quats, [[1, 0, 0, 0]] * 2)
    g2 = gaussians_at(centres, depth, rgb, 100.0, 3.0, 0, opacity=OPACITY_PRIOR)
    np.testing.assert_allclose(sigmoid(g2.opacity_logits), OPACITY_PRIOR, rtol=1e-6)
    with pytest.raises(ValueError, match="centres"):
        gaussians_at(centres, depth[:1], rgb, 100.0, 3.0, 0)


def test_start_log_scales_clamp_depth() -> None:
    got = start_log_scales(np.array([0.0, 4.0]), 200.0, 2.0, scale_prior=0.5)
    np.testing.assert_allclose(got, np.log([0.5 * 2.0 * 1e-6 / 200.0, 0.5 * 2.0 * 4.0 / 200.0]))


def test_block_colours_low_pass_at_the_spacing() -> None:
    rgb = np.random.default_rng(0).random((31, 41, 3)).astype(np.float32)
    assert block_colours(rgb, 1.0) is rgb
    flat = np.full((20, 30, 3), 0.3, np.float32)
    np.testing.assert_allclose(block_colours(flat, 4.0), 0.3, atol=1e-6)
    impulse = np.zeros((61, 61, 3), np.float32)
    impulse[30, 30] = 1.0
    out = block_colours(impulse, 5.0)[..., 0].astype(np.float64)
    assert out.sum() == pytest.approx(1.0, abs=1e-4)
    ys, xs = np.mgrid[0:61, 0:61]
    var = float((out * ((xs - 30) ** 2)).sum() / out.sum())
    assert math.sqrt(var) == pytest.approx(BLOCK_SIGMA * 5.0, rel=0.02)  # a Gaussian of BLOCK_SIGMA x spacing


# -------------------------------------------------------------------------------------- init head interface
def test_residual_layout_tiles_the_channels() -> None:
    for deg in range(4):
        sl = residual_slices(deg)
        k = (deg + 1) ** 2
        assert OPACITY_CHANNEL == 0 and sl["sh"] == slice(1, 1 + 3 * k)
        assert sl["log_scales"].start == sl["sh"].stop and sl["quats"].start == sl["log_scales"].stop
        assert sl["quats"].stop == residual_channels(deg) == 1 + 3 * k + 7


def test_decode_residuals_adds_to_the_analytic_start() -> None:
    rng = np.random.default_rng(1)
    n, deg = 5, 1
    raw = rng.normal(0, 0.1, (n, residual_channels(deg))).astype(np.float32)
    rgb, centres, depth = rng.random((n, 3)), rng.normal(0, 1, (n, 3)), rng.uniform(1, 3, n)
    g = decode_residuals(raw, rgb, centres, depth, 80.0, 2.0, deg, 3)
    sl = residual_slices(deg)
    np.testing.assert_allclose(g.opacity_logits, raw[:, 0] + logit(np.array(OPACITY_PRIOR)), rtol=1e-6)
    np.testing.assert_allclose(g.sh[:, 0], raw[:, 1:4] + (rgb - 0.5) / SH_C0, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(g.sh[:, 1:4], raw[:, 4:13].reshape(n, 3, 3), rtol=1e-6)
    assert not g.sh[:, 4:].any()
    base = np.log(SCALE_PRIOR * 2.0 * depth / 80.0)[:, None]
    np.testing.assert_allclose(g.log_scales, raw[:, sl["log_scales"]] + base, rtol=1e-5)
    np.testing.assert_allclose(g.quats, raw[:, sl["quats"]] + [1, 0, 0, 0], rtol=1e-6)
    np.testing.assert_allclose(g.means, centres, rtol=1e-6)
    with pytest.raises(ValueError, match="below"):
        decode_residuals(raw, rgb, centres, depth, 80.0, 2.0, deg, 0)
    with pytest.raises(ValueError, match="raw"):
        decode_residuals(raw[:, :-1], rgb, centres, depth, 80.0, 2.0, deg, 3)


def test_numpy_decode_matches_the_torch_head_decode() -> None:
    torch = pytest.importorskip("torch")
    from acesplat.splat.init_head import decode_gaussians

    rng = np.random.default_rng(2)
    n, deg = 7, 1
    raw = rng.normal(0, 0.2, (n, residual_channels(deg))).astype(np.float32)
    rgb = rng.random((n, 3)).astype(np.float32)
    centres = rng.normal(0, 1, (n, 3)).astype(np.float32)
    depth = rng.uniform(1, 3, n).astype(np.float32)
    g = decode_residuals(raw, rgb, centres, depth, 80.0, 2.0, deg, 2)
    t = decode_gaussians(*(torch.from_numpy(a) for a in (raw, rgb, centres, depth)), 80.0, 2.0, deg, 2)
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        np.testing.assert_allclose(getattr(g, name), t[name].numpy(), rtol=1e-5, atol=1e-6, err_msg=name)


def test_coordinate_prior_both_precisions_match_the_definition() -> None:
    rng = np.random.default_rng(4)
    H, W = 6, 9
    rgb = rng.random((H, W, 3)).astype(np.float32)
    centres = rng.normal(3, 2, (H, W, 3))
    depth = rng.uniform(0.5, 4, (H, W))
    depth[0, 0] = 0.0
    centres[1, 1] = np.nan
    norm = SceneNorm((1.0, -2.0, 0.5), 2.5)
    want = np.empty((PRIOR_CHANNELS, H, W))
    for r in range(H):
        for c in range(W):
            want[0:3, r, c] = rgb[r, c] - 0.5
            want[3:6, r, c] = (centres[r, c] - np.array(norm.centre)) / norm.scale
            want[6, r, c] = math.log(max(depth[r, c], 1e-6) / norm.scale)
    want = np.nan_to_num(want)
    for in_place in (False, True):
        got = coordinate_prior(rgb, centres, depth, norm, float32_in_place=in_place)
        assert got.dtype == np.float32 and got.shape == (PRIOR_CHANNELS, H, W)
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError):
        coordinate_prior(rgb[:-1], centres, depth, norm)


def test_scene_norm_round_trips_through_its_dict() -> None:
    norm = SceneNorm.from_views(np.array([[0.0, 0, 0], [2.0, 0, 0]]), np.array([0.5, 3.0, 4.0]))
    assert norm.centre == (1.0, 0.0, 0.0) and norm.scale == 3.0  # max(spread 1, median depth 3)
    assert SceneNorm.from_dict(norm.as_dict()) == norm


def test_bundle_section_names() -> None:
    assert (ROLE_GAUSSIANS, ROLE_SPLAT_INIT, INIT_INPUTS) == ("gaussians", "splat_init_fp32", ("features", "prior"))


# ----------------------------------------------------------------------------------------------- pruning
def test_transparent_and_cap_keep_match_brute_force() -> None:
    rng = np.random.default_rng(5)
    g = Gaussians.zeros(30, 0)
    g.opacity_logits[:] = rng.normal(-3, 3, 30)
    g.opacity_logits[[3, 4]] = g.opacity_logits[5]  # ties
    g.means[7, 1] = np.nan
    g.log_scales[9, 0] = np.inf
    bad = {7, 9}
    want = [sigmoid(np.float64(g.opacity_logits[i])) < PRUNE_OPACITY or i in bad for i in range(30)]
    assert transparent(g).tolist() == want
    order = sorted(range(30), key=lambda i: (-float(g.opacity_logits[i]), i))
    for cap in (0, 4, 12, 30, 40):
        assert set(np.flatnonzero(cap_keep(g, cap))) == set(order[:cap])
    with pytest.raises(ValueError):
        cap_keep(g, -1)


# ------------------------------------------------------------------------------------- trusted cell depths
def test_cell_trust_is_cell_validity_with_brute_force_depths() -> None:
    rng = np.random.default_rng(6)
    z = rng.uniform(1.0, 4.0, (6, 8))
    coords = cells_at_depth(z)
    coords[0, 0] = np.nan
    coords[2, 3] += 0.5  # off its ray: fails the reprojection test
    coords[4, 4] = cells_at_depth(np.full((6, 8), 300.0))[4, 4]  # beyond depth_max
    depth, ok = cell_trust(coords, POSE, K)
    v = cell_validity(coords, POSE, K)
    assert ok.tolist() == v.valid.tolist()
    assert not ok[0, 0] and not ok[2, 3] and not ok[4, 4] and ok.sum() == 45
    w2c = invert_pose(POSE)
    for i in range(6):
        for j in range(8):
            if ok[i, j]:
                assert depth[i, j] == pytest.approx(float(w2c[2, :3] @ coords[i, j] + w2c[2, 3]), rel=1e-12)
            else:
                assert np.isnan(depth[i, j])
    _, strict = cell_trust(coords, POSE, K, ValidityConfig(depth_max=2.0))
    assert not (strict & (z > 2.0)).any()


def test_both_pixel_samplers_agree_on_a_smooth_surface() -> None:
    """At the network's resolution the edge's resampler and Stage 2's exact interpolation give the same depths
    wherever both trust a pixel (they differ only in precision and in how wide the edge test looks)."""
    ys, xs = np.mgrid[0:6, 0:8]
    z = 2.0 + 0.05 * xs + 0.03 * ys
    coords = cells_at_depth(z)
    trusted = np.ones((6, 8), bool)
    centres, depth, valid = pixel_coordinates(coords, trusted, POSE, K, 1.25)
    pix = pixel_depths(coords, POSE, K, K)
    both = valid & pix.valid
    assert both.mean() > 0.95
    np.testing.assert_allclose(pix.depth[both], depth[both], rtol=1e-5)
    np.testing.assert_allclose(pix.centres[both], centres[both], atol=1e-5)
    # A depth edge: both samplers refuse the pixels fed from both sides; the edge's 3x3 test refuses a wider band.
    step = np.where(xs < 4, 1.0, 3.0)
    _, _, v_exact = pixel_coordinates(cells_at_depth(step), trusted, POSE, K, 1.25)
    v_edge = pixel_depths(cells_at_depth(step), POSE, K, K).valid
    assert not v_exact[:, 28:36].any() and not v_edge[:, 28:36].any()
    assert (v_edge <= v_exact).all()
