"""The Gaussian lifecycle on hand-made gradient statistics: clone, split, prune, cap, reset, schedule."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob_default
from acesplat.splat.lifecycle import (
    DENSIFY_EVERY,
    DENSIFY_FROM,
    DENSIFY_UNTIL,
    MIN_DENSIFY_EVERY,
    MIN_RESET_EVERY,
    OPACITY_RESET_EVERY,
    REFERENCE_ITERATIONS,
    RESET_OPACITY,
    SH_UP_EVERY,
    SPLIT_SCALE_DIVISOR,
    GaussianLifecycle,
    LifecycleConfig,
    LifecycleSchedule,
    LifecycleState,
    densify_and_prune,
    reset_opacity,
)
from acesplat.splat.optimize import make_optimizer
from acesplat.splat.params import PARAM_NAMES
from acesplat.splat.raster_torch import RenderOutput
from acesplat.splatcore.prune import PRUNE_OPACITY

GRAD_THRESHOLD = knob_default(LifecycleConfig, "grad_threshold")
EXTENT = 10.0  # clone/split boundary: PERCENT_DENSE * 10 = 0.1 m


def logit(p: float) -> float:
    return math.log(p / (1 - p))


def make_params() -> dict[str, torch.nn.Parameter]:
    """Four Gaussians: 0 small + strong gradient, 1 large + strong gradient, 2 nearly transparent, 3 quiet."""
    means = torch.tensor([[0.0, 0, 5], [1.0, 0, 5], [2.0, 0, 5], [3.0, 0, 5]])
    log_scales = torch.log(torch.tensor([[0.05, 0.05, 0.05], [0.5, 0.2, 0.1], [0.05] * 3, [0.05] * 3]))
    quats = torch.tensor([[1.0, 0, 0, 0], [0.0, 0, 0, 1.0], [1.0, 0, 0, 0], [1.0, 0, 0, 0]])  # #1: 180 deg about z
    opac = torch.tensor([logit(0.5), logit(0.6), logit(PRUNE_OPACITY / 2), logit(0.7)])
    sh_dc = torch.arange(12, dtype=torch.float32).reshape(4, 1, 3)
    sh_rest = torch.zeros(4, 3, 3)
    vals = dict(zip(PARAM_NAMES, (means, log_scales, quats, opac, sh_dc, sh_rest)))
    return {k: torch.nn.Parameter(v.clone()) for k, v in vals.items()}


def stats(grads: list[float], seen: list[int]) -> LifecycleState:
    s = LifecycleState.zeros(len(grads))
    s.grad_sum = torch.tensor(grads, dtype=torch.float64) * torch.tensor(seen, dtype=torch.float64)
    s.seen = torch.tensor(seen)
    return s


def optimizer_with_moments(params):
    """An AdamW whose first moment of every Gaussian row holds that row's index + 1 (to follow rows through edits)."""
    opt = make_optimizer(params, EXTENT, None)
    for p in params.values():
        p.grad = torch.zeros_like(p)
    opt.step()
    for p in params.values():
        st = opt.state[p]
        rows = torch.arange(1, p.shape[0] + 1, dtype=p.dtype).reshape(-1, *([1] * (p.ndim - 1)))
        st["exp_avg"].copy_(rows.expand_as(p))
    return opt


def test_clone_split_prune_on_hand_made_statistics():
    params = make_params()
    opt = optimizer_with_moments(params)
    state = stats([3 * GRAD_THRESHOLD, 2 * GRAD_THRESHOLD, 5 * GRAD_THRESHOLD, 0.5 * GRAD_THRESHOLD], [4, 2, 3, 7])
    cfg = LifecycleConfig(scene_extent=EXTENT, max_gaussians=100)
    ev = densify_and_prune(params, opt, state, cfg, torch.Generator().manual_seed(0))
    assert (ev.cloned, ev.split, ev.pruned, ev.capped) == (1, 1, 1, 0)
    # kept: #0 and #3 in order, then the clone of #0, then two children of #1
    n = params["means"].shape[0]
    assert n == 5 and ev.counts == {"before": 4, "after": 5}
    m = params["means"].detach()
    assert torch.equal(m[0], torch.tensor([0.0, 0, 5])) and torch.equal(m[1], torch.tensor([3.0, 0, 5]))
    assert torch.equal(m[2], m[0])  # the clone starts on its parent
    children = m[3:]
    np.testing.assert_allclose(
        params["log_scales"].detach()[3:].numpy(),
        np.log(np.array([[0.5, 0.2, 0.1]] * 2) / SPLIT_SCALE_DIVISOR),
        rtol=1e-6,
    )
    # children are drawn from the parent: rotated by 180 deg about z the x/y offsets flip sign,
    # and |offset| / scale stays a standard normal draw (loosely bounded here)
    off = (children - torch.tensor([1.0, 0, 5])).numpy() / np.array([0.5, 0.2, 0.1])
    assert np.all(np.abs(off) < 5) and not np.allclose(off, 0)
    assert torch.equal(params["sh_dc"].detach()[3], torch.tensor([[3.0, 4.0, 5.0]]))  # parent #1's colour
    assert torch.equal(params["sh_dc"].detach()[2], torch.tensor([[0.0, 1.0, 2.0]]))
    # optimiser moments followed their rows; new rows start at zero; the optimiser holds the new tensors
    for name in PARAM_NAMES:
        p = params[name]
        assert any(q is p for g in opt.param_groups for q in g["params"])
        ea = opt.state[p]["exp_avg"].reshape(n, -1)
        if ea.shape[1]:
            assert torch.all(ea[0] == 1) and torch.all(ea[1] == 4) and torch.all(ea[2:] == 0)
    # statistics restart for the new set
    assert state.grad_sum.shape == (5,) and float(state.grad_sum.sum()) == 0.0


def test_unseen_gaussians_are_not_densified_and_the_cap_keeps_the_strongest():
    params = make_params()
    opt = optimizer_with_moments(params)
    state = stats([3 * GRAD_THRESHOLD, 2 * GRAD_THRESHOLD, 0.0, 9 * GRAD_THRESHOLD], [4, 2, 0, 0])
    state.grad_sum[3] = 1.0  # a sum without views: ignored (mean over zero views)
    cfg = LifecycleConfig(scene_extent=EXTENT, max_gaussians=4)
    # room after pruning #2 is 4 - 3 = 1: the clone of #0 (cost 1, strongest) fits, the split of #1 (cost 1) does not
    ev = densify_and_prune(params, opt, state, cfg)
    assert (ev.cloned, ev.split, ev.pruned, ev.capped) == (1, 0, 1, 1)
    assert params["means"].shape[0] == 4


def test_non_finite_gaussians_are_pruned():
    params = make_params()
    opt = optimizer_with_moments(params)
    with torch.no_grad():
        params["means"][3, 0] = float("nan")
    ev = densify_and_prune(
        params, opt, stats([0.0] * 4, [1] * 4), LifecycleConfig(scene_extent=EXTENT, max_gaussians=10)
    )
    assert ev.pruned == 2 and torch.isfinite(params["means"]).all()


def test_opacity_reset_clamps_and_forgets_moments():
    params = make_params()
    opt = optimizer_with_moments(params)
    before = torch.sigmoid(params["opacity_logits"].detach()).clone()
    reset_opacity(params, opt)
    after = torch.sigmoid(params["opacity_logits"].detach())
    np.testing.assert_allclose(after.numpy(), np.minimum(before.numpy(), RESET_OPACITY), rtol=1e-5)
    assert float(opt.state[params["opacity_logits"]]["exp_avg"].abs().sum()) == 0.0


def test_schedule_scales_3dgs_counts_with_floors():
    full = LifecycleSchedule.scaled(REFERENCE_ITERATIONS)
    assert (full.densify_every, full.reset_every, full.sh_up_every) == (DENSIFY_EVERY, OPACITY_RESET_EVERY, SH_UP_EVERY)
    # the window is a fraction of the run whatever its length: 3DGS's 500..15,000 of 30,000
    assert full.densify_from * REFERENCE_ITERATIONS == pytest.approx(DENSIFY_FROM)
    assert full.densify_until * REFERENCE_ITERATIONS == pytest.approx(DENSIFY_UNTIL)
    short = LifecycleSchedule.scaled(3000)
    assert short.densify_every == max(MIN_DENSIFY_EVERY, 10) and short.densify_until == full.densify_until
    assert short.reset_every == max(MIN_RESET_EVERY, 300) and short.sh_up_every == 100
    with pytest.raises(ValueError):
        LifecycleSchedule.scaled(0)


def test_hooks_fire_on_schedule():
    sched = LifecycleSchedule(densify_every=20, densify_from=0.2, densify_until=0.5, reset_every=60, sh_up_every=25)
    life = GaussianLifecycle(LifecycleConfig(scene_extent=EXTENT, max_gaussians=100), sched)
    assert [life.sh_degree(s) for s in (0, 24, 25, 50, 75, 1000)] == [0, 0, 1, 2, 3, 3]

    def fired(total: int) -> list[tuple[int, bool, bool]]:
        out = []
        for step in range(1, total + 1):
            params = make_params()
            opt = optimizer_with_moments(params)
            ev = life.step_post_optimizer(params, opt, stats([0.0] * 4, [1] * 4), step, step / total)
            if ev.counts or ev.opacity_reset:
                out.append((step, bool(ev.counts), ev.opacity_reset))
        return out

    assert fired(200) == [(40, True, False), (60, True, True), (80, True, False), (100, True, False)]
    # A run slower than its schedule assumed (100 iterations where 200 were planned): the window follows the
    # progress, so densification stops at half the run and no opacity reset comes late (step 60 is 60% in).
    assert fired(100) == [(20, True, False), (40, True, False)]


def test_post_backward_accumulates_ndc_gradient_norms_of_visible_gaussians():
    life = GaussianLifecycle(LifecycleConfig(scene_extent=EXTENT, max_gaussians=100), LifecycleSchedule.scaled(1000))
    k = Intrinsics(100.0, 100.0, 39.5, 29.5, 80, 60)
    state = life.init_state(3)
    for grads in ([[1e-5, 0.0], [0.0, 2e-5], [1.0, 1.0]], [[3e-5, 4e-5], [0.0, 0.0], [1.0, 1.0]]):
        m2d = torch.zeros(3, 2, requires_grad=True)
        m2d.grad = torch.tensor(grads)
        out = RenderOutput(
            color=torch.zeros(60, 80, 3),
            alpha=torch.zeros(60, 80),
            depth=torch.zeros(60, 80),
            means2d=m2d,
            radii=torch.tensor([3, 2, 0]),
            visible=torch.tensor([True, True, False]),
        )
        life.step_post_backward(state, out, k)
    # NDC norm: pixel gradient times half the image size per axis
    expected0 = math.hypot(1e-5 * 40, 0) + math.hypot(3e-5 * 40, 4e-5 * 30)
    assert state.grad_sum[0].item() == pytest.approx(expected0)
    assert state.grad_sum[1].item() == pytest.approx(2e-5 * 30)
    assert state.seen.tolist() == [2, 2, 0] and state.grad_sum[2].item() == 0.0
    assert state.mean_grad()[0].item() == pytest.approx(expected0 / 2)
