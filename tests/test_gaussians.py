"""Gaussians record: shape/dtype validation, helpers, activations."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from acesplat.core.gaussians import (
    SH_C0,
    Gaussians,
    concat_gaussians,
    logit,
    normalize_quats,
    rgb_to_sh_dc,
    sh_coeff_count,
    sh_dc_to_rgb,
    sh_degree_of,
    sigmoid,
)


def _random(n: int, degree: int = 3, dtype=np.float32, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    k = sh_coeff_count(degree)
    return Gaussians(
        rng.normal(size=(n, 3)).astype(dtype),
        rng.normal(size=(n, 3)).astype(dtype),
        rng.normal(size=(n, 4)).astype(dtype),
        rng.normal(size=n).astype(dtype),
        rng.normal(size=(n, k, 3)).astype(dtype),
    )


def test_valid_set_reports_its_shape_facts() -> None:
    g = _random(7, degree=2)
    assert len(g) == 7
    assert g.sh_degree == 2
    assert g.dtype == np.float32


@pytest.mark.parametrize(
    "field, bad, message",
    [
        ("means", np.zeros((5, 2), np.float32), "means must have shape"),
        ("log_scales", np.zeros((4, 3), np.float32), "log_scales must have shape (5, 3)"),
        ("quats", np.zeros((5, 3), np.float32), "quats must have shape (5, 4)"),
        ("opacity_logits", np.zeros((5, 1), np.float32), "opacity_logits must have shape (5,)"),
        ("sh", np.zeros((5, 5, 3), np.float32), "SH coefficient count must be 1, 4, 9 or 16"),
        ("sh", np.zeros((5, 4, 4), np.float32), "sh must have shape"),
    ],
)
def test_wrong_shapes_are_named(field: str, bad: np.ndarray, message: str) -> None:
    g = _random(5)
    kwargs = {f: getattr(g, f) for f in ("means", "log_scales", "quats", "opacity_logits", "sh")}
    kwargs[field] = bad
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        Gaussians(**kwargs)


def test_mixed_or_integer_dtypes_are_refused() -> None:
    g = _random(3)
    with pytest.raises(TypeError, match="must all be float32 or all float64"):
        Gaussians(g.means.astype(np.float64), g.log_scales, g.quats, g.opacity_logits, g.sh)
    with pytest.raises(TypeError, match="must all be float32 or all float64"):
        Gaussians(*(a.astype(np.int32) for a in (g.means, g.log_scales, g.quats, g.opacity_logits, g.sh)))
    with pytest.raises(TypeError, match="numpy array"):
        Gaussians([[0.0, 0.0, 0.0]], g.log_scales[:1], g.quats[:1], g.opacity_logits[:1], g.sh[:1])


def test_subset_by_mask_indices_and_slice() -> None:
    g = _random(6, seed=1)
    mask = np.array([True, False, True, False, False, True])
    by_mask = g.subset(mask)
    by_idx = g.subset(np.array([0, 2, 5]))
    by_slice = g.subset(slice(0, 6, 2))
    np.testing.assert_array_equal(by_mask.sh, g.sh[[0, 2, 5]])
    np.testing.assert_array_equal(by_idx.means, g.means[[0, 2, 5]])
    np.testing.assert_array_equal(by_slice.quats, g.quats[[0, 2, 4]])
    by_slice.means[0] = 99.0  # a copy, not a view
    assert g.means[0, 0] != 99.0
    with pytest.raises(ValueError, match="mask must have shape"):
        g.subset(np.array([True, False]))
    with pytest.raises(TypeError, match="boolean mask or integers"):
        g.subset(np.array([0.5]))


def test_concat_keeps_order_and_checks_compatibility() -> None:
    a, b = _random(3, seed=1), _random(2, seed=2)
    c = concat_gaussians([a, b])
    assert len(c) == 5
    np.testing.assert_array_equal(c.opacity_logits, np.concatenate([a.opacity_logits, b.opacity_logits]))
    with pytest.raises(ValueError, match="different SH degrees"):
        concat_gaussians([a, _random(2, degree=1)])
    with pytest.raises(ValueError, match="different dtypes"):
        concat_gaussians([a, _random(2, dtype=np.float64)])
    with pytest.raises(ValueError, match="at least one"):
        concat_gaussians([])


def test_with_sh_degree_pads_and_truncates() -> None:
    g = _random(4, degree=1)
    up = g.with_sh_degree(3)
    assert up.sh.shape == (4, 16, 3)
    np.testing.assert_array_equal(up.sh[:, :4], g.sh)
    assert not up.sh[:, 4:].any()
    down = up.with_sh_degree(0)
    np.testing.assert_array_equal(down.sh[:, 0], g.sh[:, 0])


def test_activations() -> None:
    x = np.array([-1000.0, -3.0, 0.0, 2.0, 1000.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        s = sigmoid(x)
    expected = [0.0, 1 / (1 + np.exp(3.0)), 0.5, 1 / (1 + np.exp(-2.0)), 1.0]
    np.testing.assert_allclose(s, expected, rtol=1e-12, atol=1e-300)
    assert sigmoid(np.float32([0.5])).dtype == np.float32
    p = np.array([0.01, 0.3, 0.99])
    np.testing.assert_allclose(sigmoid(logit(p)), p, rtol=1e-12)
    assert np.isfinite(logit(np.array([0.0, 1.0]))).all()
    q = normalize_quats(np.array([[2.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]]))
    np.testing.assert_allclose(q, [[1, 0, 0, 0], [1, 0, 0, 0], [0.5, 0.5, 0.5, 0.5]])
    g = _random(3)
    np.testing.assert_allclose(np.linalg.norm(g.unit_quats(), axis=1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(g.scales(), np.exp(g.log_scales))
    assert ((g.opacities() > 0) & (g.opacities() < 1)).all()


def test_sh_dc_colour_conversion_round_trips() -> None:
    rgb = np.array([[0.0, 0.5, 1.0]])
    np.testing.assert_allclose(sh_dc_to_rgb(rgb_to_sh_dc(rgb)), rgb, atol=1e-12)
    np.testing.assert_allclose(SH_C0, 0.28209479177387814, rtol=1e-15)


def test_sh_degree_helpers() -> None:
    assert [sh_coeff_count(d) for d in range(4)] == [1, 4, 9, 16]
    assert [sh_degree_of(k) for k in (1, 4, 9, 16)] == [0, 1, 2, 3]
    with pytest.raises(ValueError):
        sh_coeff_count(4)
    with pytest.raises(ValueError):
        sh_degree_of(8)


def test_zeros_and_empty() -> None:
    z = Gaussians.zeros(3, sh_degree=1, dtype=np.float64)
    assert z.sh.shape == (3, 4, 3) and z.dtype == np.float64
    np.testing.assert_array_equal(z.quats[:, 0], 1.0)
    e = Gaussians.empty()
    assert len(e) == 0 and e.sh_degree == 3
    assert len(e.astype(np.float64)) == 0
