"""The optimisation loop: non-finite gradients are skipped and counted, never written; a fit improves."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from acesplat.splat.adapter import AdapterConfig
from acesplat.splat.evaluate import evaluate_views
from acesplat.splat.init_head import InitHeadConfig
from acesplat.splat.instantiate import GaussianInitializer, merge_views, view_pixels
from acesplat.splat.lifecycle import LifecycleSchedule
from acesplat.splat.optimize import (
    PROBE_ITERATIONS,
    OptimizeConfig,
    finite_gradients,
    make_optimizer,
    optimise_gaussians,
)
from acesplat.splat.params import PARAM_NAMES, gaussians_from_params, params_from_tensors
from acesplat.splatcore.head_io import SceneNorm
from tests.test_splat_init import planar_view


@pytest.fixture(autouse=True)
def _one_torch_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def planar_set(view):
    norm = SceneNorm((0.0, 2.0, 1.0), 2.0)
    init = GaussianInitializer(AdapterConfig(in_channels=8), InitHeadConfig())
    tensors, _ = merge_views([view], [view_pixels(view, norm)], init, 200, 1, np.random.default_rng(0))
    return params_from_tensors(tensors)


def test_finite_gradients_clears_a_poisoned_step():
    p = torch.nn.Parameter(torch.zeros(3))
    q = torch.nn.Parameter(torch.zeros(2))
    opt = torch.optim.AdamW([p, q])
    p.grad = torch.tensor([1.0, 2.0, 3.0])
    q.grad = torch.tensor([0.0, 1.0])
    assert finite_gradients(opt)
    q.grad = torch.tensor([float("inf"), 1.0])
    assert not finite_gradients(opt)
    assert p.grad is None and q.grad is None


def test_nan_gradients_are_skipped_counted_and_never_written():
    good = planar_view("good")
    bad = planar_view("bad")
    bad.rgb = bad.rgb.copy()
    bad.rgb[5, 7, 1] = np.nan  # a corrupt target pixel makes that view's loss and every gradient NaN
    params = planar_set(good)
    cfg = OptimizeConfig(scene_extent=2.0, max_gaussians=1000, sh_degree=1, iterations=12, seed=0)
    res = optimise_gaussians(params, [good, bad], cfg)
    assert res.iterations == 12 and res.skipped_steps == 6  # each view is drawn once per pass over the two
    for name in PARAM_NAMES:
        assert torch.isfinite(params[name]).all(), name
    g = gaussians_from_params(params)
    assert np.isfinite(evaluate_views(g, [good])["psnr"])


def test_optimisation_improves_a_blurred_start():
    """The optimiser alone (the lifecycle has its own tests): 60 steps sharpen a stride-3 start."""
    view = planar_view("v")
    params = planar_set(view)
    g0 = gaussians_from_params(params)
    before = evaluate_views(g0, [view])["psnr"]
    cfg = OptimizeConfig(scene_extent=2.0, max_gaussians=2000, sh_degree=1, iterations=60, densify=False, seed=0)
    res = optimise_gaussians(params, [view], cfg)
    after = evaluate_views(gaussians_from_params(params), [view])["psnr"]
    assert res.skipped_steps == 0 and res.history and res.history[-1]["iteration"] == 60
    assert after > before + 5.0  # measured 24.0 -> 32.0 dB


def test_the_default_is_fixed_work_and_a_binding_cap_cuts_it_short_on_a_scaled_schedule():
    """Without a cap every CPU runs the planned iterations on the schedule scaled to them; a cap that cannot afford
    them ends the run early (iterations < iterations_planned), on a schedule scaled to what it affords."""
    view = planar_view("v")
    cfg = OptimizeConfig(scene_extent=2.0, max_gaussians=2000, sh_degree=1, iterations=40, seed=0)
    free = optimise_gaussians(planar_set(view), [view], cfg)
    assert (free.iterations, free.iterations_planned) == (40, 40)
    assert free.schedule == LifecycleSchedule.scaled(40)
    long = OptimizeConfig(scene_extent=2.0, max_gaussians=2000, sh_degree=1, iterations=10**6, seed=0)
    capped = optimise_gaussians(planar_set(view), [view], long, seconds=0.5)
    assert capped.iterations_planned == 10**6 and PROBE_ITERATIONS < capped.iterations < 10**6
    assert capped.schedule.sh_up_every < LifecycleSchedule.scaled(10**6).sh_up_every  # rescaled after the probe
    assert capped.history[-1]["progress"] > 0.5  # the clock drove the schedule (the iterations alone: ~0)
    with pytest.raises(ValueError, match="seconds"):
        optimise_gaussians(planar_set(view), [view], cfg, seconds=0.0)


def test_optimizer_groups_have_their_learning_rates():
    params = planar_set(planar_view())
    opt = make_optimizer(params, 3.0, None)
    lrs = {g["name"]: g["peak_lr"] for g in opt.param_groups}
    assert lrs["means"] == pytest.approx(1.6e-4 * 3.0) and lrs["sh_rest"] == pytest.approx(lrs["sh_dc"] / 20)
    assert all(g["weight_decay"] == 0.0 for g in opt.param_groups)
