"""The numba tile rasterizer against a dense pure-torch reference, finite differences and closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from acesplat.core.camera import Intrinsics
from acesplat.core.gaussians import SH_C0, Gaussians
from acesplat.raster import (
    RenderResult,
    get_num_threads,
    ndc_grad_norm,
    rasterize,
    rasterize_backward,
    set_num_threads,
)
from acesplat.raster._project_kernels import sh_basis
from tests.raster_reference import random_scene, render_reference

PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh")


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    """Relative error of a whole tensor: ||a - b|| / ||b||."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300))


def _loss_weights(k: Intrinsics, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    hw = (k.height, k.width)
    return rng.normal(size=hw + (3,)), rng.normal(size=hw), rng.normal(size=hw)


def _compare_with_reference(params, pose, k, bg, sh_degree, seed, tol_value, tol_grad):
    g = Gaussians(**params)
    res = rasterize(g, pose, k, bg, sh_degree=sh_degree)
    wc, wa, wd = _loss_weights(k, seed)
    grads = rasterize_backward(res, wc, wa, wd)

    t = {n: torch.tensor(params[n], dtype=torch.float64, requires_grad=True) for n in PARAMS}
    ref = render_reference(**t, pose_c2w=pose, k=k, background=bg, sh_degree=sh_degree)
    loss = (
        (ref.color * torch.tensor(wc)).sum()
        + (ref.alpha * torch.tensor(wa)).sum()
        + (ref.depth * torch.tensor(wd)).sum()
    )
    loss.backward()

    errors = {
        "color": _rel(res.color, ref.color.detach().numpy()),
        "alpha": _rel(res.alpha, ref.alpha.detach().numpy()),
        "depth": _rel(res.depth, ref.depth.detach().numpy()),
        "means2d": _rel(res.means2d[res.visible], ref.means2d.detach().numpy()[res.visible]),
    }
    for name in ("color", "alpha", "depth", "means2d"):
        assert errors[name] < tol_value, (name, errors)
    for name in PARAMS:
        err = _rel(getattr(grads, name), t[name].grad.numpy())
        assert err < tol_grad, (name, err)
    assert _rel(grads.means2d, ref.means2d.grad.numpy()) < tol_grad
    np.testing.assert_allclose(grads.means2d_ndc_norm, ndc_grad_norm(grads.means2d, k.width, k.height))
    return res, ref


@pytest.mark.parametrize("seed, sh_degree", [(0, 3), (1, 1), (2, 0), (3, 2)])
def test_float64_matches_dense_reference(seed: int, sh_degree: int) -> None:
    params, pose, k = random_scene(60, seed, dtype=np.float64)
    bg = np.array([0.1, 0.5, 0.9])
    res, ref = _compare_with_reference(params, pose, k, bg, sh_degree, seed, 1e-10, 1e-8)
    # The scene exercises every special case, so agreement above covers them.
    s = ref.stats
    assert s["culled"] > 0 and s["terminated_pixels"] > 0 and s["alpha_clamped"] > 0
    assert s["colour_clamped"] > 0 and s["tangent_clamped"] > 0 and s["contributions"] > 300
    assert res.visible.sum() < len(res.visible)


def test_stored_degree_above_active_degree_gets_zero_sh_gradient_beyond() -> None:
    params, pose, k = random_scene(30, 7, dtype=np.float64)
    res = rasterize(Gaussians(**params), pose, k, sh_degree=1)
    grads = rasterize_backward(res, np.ones((k.height, k.width, 3)))
    assert np.abs(grads.sh[:, :4]).sum() > 0
    assert not grads.sh[:, 4:].any()


@pytest.mark.parametrize("seed", [4, 5])
def test_float32_matches_dense_reference(seed: int) -> None:
    params, pose, k = random_scene(80, seed, dtype=np.float32)
    params = {n: a.astype(np.float32) for n, a in params.items()}
    res, _ = _compare_with_reference(params, pose, k, np.array([0.3, 0.3, 0.3]), 3, seed, 1e-4, 1e-4)
    assert res.color.dtype == np.float32 and res.depth.dtype == np.float32


def test_finite_differences() -> None:
    params, pose, k = random_scene(40, 11, dtype=np.float64)
    bg = np.array([0.2, 0.1, 0.0])
    wc, wa, wd = _loss_weights(k, 3)

    def loss(p) -> float:
        r = rasterize(Gaussians(**p), pose, k, bg)
        return float((r.color * wc).sum() + (r.alpha * wa).sum() + (r.depth * wd).sum())

    res = rasterize(Gaussians(**params), pose, k, bg)
    grads = rasterize_backward(res, wc, wa, wd)
    rng = np.random.default_rng(0)
    visible = np.flatnonzero(res.visible)
    picks = []
    for i in rng.choice(visible, size=6, replace=False):
        picks += [
            ("means", (i, rng.integers(3))),
            ("log_scales", (i, rng.integers(3))),
            ("quats", (i, rng.integers(4))),
            ("opacity_logits", (i,)),
            ("sh", (i, 0, rng.integers(3))),
            ("sh", (i, rng.integers(1, 16), rng.integers(3))),
        ]
    eps = 1e-6
    numeric, analytic = [], []
    for name, idx in picks:
        plus = {n: a.copy() for n, a in params.items()}
        minus = {n: a.copy() for n, a in params.items()}
        plus[name][idx] += eps
        minus[name][idx] -= eps
        numeric.append((loss(plus) - loss(minus)) / (2 * eps))
        analytic.append(getattr(grads, name)[idx])
    numeric, analytic = np.array(numeric), np.array(analytic)
    assert np.count_nonzero(analytic) > len(picks) // 2
    np.testing.assert_allclose(analytic, numeric, rtol=1e-4, atol=1e-5 * np.abs(numeric).max())


def test_single_gaussian_closed_form() -> None:
    """One isotropic Gaussian: every pixel has a formula (the EWA covariance written out by hand)."""
    f, x, y, z, sigma, op, dc = 50.0, 0.02, -0.01, 2.0, 0.04, 0.8, np.array([0.3, -0.2, 1.0])
    k = Intrinsics(f, f, 15.0, 12.0, 31, 25)
    g = Gaussians(
        np.array([[x, y, z]]),
        np.full((1, 3), math.log(sigma)),
        np.array([[1.0, 0.0, 0.0, 0.0]]),
        np.array([math.log(op / (1 - op))]),
        dc.reshape(1, 1, 3),
    )
    bg = np.array([0.5, 0.25, 0.0])
    res = rasterize(g, np.eye(4), k, bg)
    mx, my = f * x / z + 15.0, f * y / z + 12.0
    jac = np.array([[f / z, 0.0, -f * x / z**2], [0.0, f / z, -f * y / z**2]])
    cov = sigma**2 * jac @ jac.T + 0.3 * np.eye(2)
    conic = np.linalg.inv(cov)
    rgb = np.maximum(SH_C0 * dc + 0.5, 0.0)
    ys, xs = np.mgrid[0 : k.height, 0 : k.width]
    d = np.stack([xs - mx, ys - my], axis=-1)
    d2 = np.einsum("hwi,ij,hwj->hw", d, conic, d)
    a = op * np.exp(-0.5 * d2)
    a = np.where((d2 <= 9.0) & (a >= 1 / 255), np.minimum(a, 0.99), 0.0)
    assert (a > 0).sum() > 20
    np.testing.assert_allclose(res.alpha, a, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(res.color, a[..., None] * rgb + (1 - a[..., None]) * bg, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(res.depth, np.where(a > 0, z, 0.0), rtol=1e-12)
    np.testing.assert_allclose(res.means2d[0], [mx, my], rtol=1e-12)
    mid = 0.5 * (cov[0, 0] + cov[1, 1])
    lam = mid + math.sqrt(max(0.1, mid * mid - np.linalg.det(cov)))  # 3DGS's eigenvalue bound
    assert res.radii[0] == math.ceil(3 * math.sqrt(lam))


def test_culling_and_empty_scenes_give_background() -> None:
    k = Intrinsics(30.0, 30.0, 10.0, 8.0, 20, 16)
    bg = np.array([0.1, 0.2, 0.3])
    empty = rasterize(Gaussians.zeros(0, 3, np.float64), np.eye(4), k, bg)
    np.testing.assert_array_equal(empty.color, np.broadcast_to(bg, (16, 20, 3)))
    assert not empty.alpha.any() and not empty.depth.any()
    g = Gaussians.zeros(4, 0, np.float64)
    # behind the camera, before the near plane, past the far plane, off-screen
    g.means[:] = [[0, 0, -1.0], [0, 0, 0.005], [0, 0, 50.0], [100.0, 0, 1.0]]
    g.log_scales[:] = math.log(0.05)
    g.opacity_logits[:] = 3.0
    res = rasterize(g, np.eye(4), k, bg, far=20.0)
    assert not res.visible.any() and not res.radii.any() and res.n_tile_entries == 0
    np.testing.assert_array_equal(res.color, np.broadcast_to(bg, (16, 20, 3)))
    grads = rasterize_backward(res, np.ones((16, 20, 3)), np.ones((16, 20)), np.ones((16, 20)))
    assert not any(getattr(grads, n).any() for n in PARAMS)
    # The same Gaussian at z = 5 inside [near, far] is drawn.
    g.means[2, 2] = 5.0
    assert rasterize(g, np.eye(4), k, bg, far=20.0).visible.tolist() == [False, False, True, False]


def test_results_do_not_depend_on_thread_count() -> None:
    params, pose, k = random_scene(200, 21, width=70, height=50, dtype=np.float32)
    g = Gaussians(**params)
    wc, wa, wd = _loss_weights(k, 1)
    before = get_num_threads()
    outs = []
    try:
        for n in (1, 3):
            set_num_threads(n)
            r = rasterize(g, pose, k)
            outs.append((r, rasterize_backward(r, wc, wa, wd)))
    finally:
        set_num_threads(before)
    (r1, g1), (r3, g3) = outs
    np.testing.assert_array_equal(r1.color, r3.color)
    np.testing.assert_array_equal(r1.depth, r3.depth)
    for n in PARAMS + ("means2d",):
        np.testing.assert_array_equal(getattr(g1, n), getattr(g3, n))


def test_sh_basis_is_orthonormal() -> None:
    """Gauss-Legendre in cos(theta) x uniform phi integrates these degree <= 6 products exactly."""
    nodes, weights = np.polynomial.legendre.leggauss(12)
    phis = np.arange(24) * 2 * np.pi / 24
    gram = np.zeros((16, 16))
    for zc, w in zip(nodes, weights):
        r = math.sqrt(1 - zc * zc)
        for phi in phis:
            b = np.array(sh_basis(r * math.cos(phi), r * math.sin(phi), zc))
            gram += np.outer(b, b) * w * (2 * np.pi / len(phis))
    np.testing.assert_allclose(gram, np.eye(16), atol=1e-12)


def test_ndc_grad_norm_scales_by_half_image() -> None:
    v = np.array([[1.0, 0.0], [0.0, 2.0], [3.0, 4.0]])
    np.testing.assert_allclose(ndc_grad_norm(v, 200, 100), [100.0, 100.0, math.hypot(300.0, 200.0)])


def test_bad_calls_fail_before_any_kernel() -> None:
    params, pose, k = random_scene(5, 0, dtype=np.float64)
    g = Gaussians(**params)
    with pytest.raises(TypeError, match="Gaussians set"):
        rasterize(params, pose, k)
    with pytest.raises(ValueError, match="pose must be 4x4"):
        rasterize(g, pose[:3], k)
    skew = pose.copy()
    skew[0, 1] += 0.1
    with pytest.raises(ValueError, match="not orthonormal"):
        rasterize(g, skew, k)
    with pytest.raises(TypeError, match="Intrinsics"):
        rasterize(g, pose, k.K)
    with pytest.raises(ValueError, match="positive focal"):
        rasterize(g, pose, Intrinsics(0.0, 1.0, 1.0, 1.0, 4, 4))
    with pytest.raises(ValueError, match="image size"):
        rasterize(g, pose, Intrinsics(1.0, 1.0, 1.0, 1.0, 0, 4))
    with pytest.raises(ValueError, match="background"):
        rasterize(g, pose, k, background=[0.0, 1.0])
    with pytest.raises(ValueError, match="sh_degree"):
        rasterize(g.with_sh_degree(1), pose, k, sh_degree=2)
    with pytest.raises(ValueError, match="near < far"):
        rasterize(g, pose, k, near=1.0, far=0.5)
    res = rasterize(g, pose, k)
    with pytest.raises(ValueError, match=r"v_color must have shape \(36, 40, 3\)"):
        rasterize_backward(res, np.zeros((36, 40)))
    with pytest.raises(ValueError, match="v_depth"):
        rasterize_backward(res, np.zeros((36, 40, 3)), v_depth=np.zeros((40, 36)))
    with pytest.raises(TypeError, match="RenderResult"):
        rasterize_backward(res.color, np.zeros((36, 40, 3)))
    assert isinstance(res, RenderResult)


def test_non_contiguous_inputs_are_accepted() -> None:
    params, pose, k = random_scene(20, 3, dtype=np.float64)
    g = Gaussians(**params)
    wide = np.zeros((20, 6))
    wide[:, ::2] = g.means
    g2 = Gaussians(wide[:, ::2], g.log_scales, g.quats, g.opacity_logits, g.sh)
    np.testing.assert_array_equal(rasterize(g2, pose, k).color, rasterize(g, pose, k).color)


def test_polynomial_exp_over_the_cut_off_range() -> None:
    from acesplat.raster._tile_kernels import exp_neg

    xs = np.linspace(-4.5, 0.0, 2001)
    got = np.array([exp_neg(x) for x in xs])
    np.testing.assert_allclose(got, np.exp(xs), rtol=1e-11, atol=0)


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="needs fork()")
def test_thread_pool_survives_fork() -> None:
    """A forked child (e.g. a data-loader worker) renders with its own pool instead of hanging."""
    import os

    params, pose, k = random_scene(50, 2, dtype=np.float32)
    g = Gaussians(**params)
    before = get_num_threads()
    set_num_threads(2)
    try:
        parent = rasterize(g, pose, k).color
        pid = os.fork()
        if pid == 0:  # pragma: no cover - runs in the child
            ok = np.array_equal(rasterize(g, pose, k).color, parent)
            os._exit(0 if ok else 3)
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0
    finally:
        set_num_threads(before)


def test_parallel_for_covers_every_index_once_and_reraises() -> None:
    from acesplat.raster._threads import parallel_for

    before = get_num_threads()
    set_num_threads(3)
    try:
        hits = np.zeros(1000, np.int64)

        def mark(lo: int, hi: int, out: np.ndarray) -> None:
            out[lo:hi] += 1

        parallel_for(mark, 1000, hits)
        assert (hits == 1).all()

        def fail(lo: int, hi: int) -> None:
            if lo <= 500 < hi:
                raise RuntimeError("chunk failed")

        with pytest.raises(RuntimeError, match="chunk failed"):
            parallel_for(fail, 1000)
        with pytest.raises(ValueError, match="at least one thread"):
            set_num_threads(0)
    finally:
        set_num_threads(before)
