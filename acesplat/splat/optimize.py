"""Per-scene optimisation of a Gaussian set (and, jointly, the init head) under the rendering loss.

One AdamW over everything: the Gaussian attributes with 3DGS's learning rates (weight decay 0: it
would pull log-scales and logits towards arbitrary values) and the adapter + head with the paper's
2e-4..2e-3, all under one one-cycle shape driven by the fraction of the iterations done (or of a wall-clock cap,
when one binds first).
Each iteration renders one training view; every ``head_every`` iterations the head's own rendering
loss joins it. A step whose gradients are not all finite is skipped and counted: no parameter and
no optimiser moment ever sees a NaN or an infinity.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from acesplat.core.config import knob
from acesplat.splat.head_training import HeadTrainer
from acesplat.splat.lifecycle import GaussianLifecycle, LifecycleConfig, LifecycleSchedule, LifecycleState
from acesplat.splat.losses import psnr_from_mse, rendering_loss
from acesplat.splat.params import GaussianParams, render_tensors
from acesplat.splat.raster_torch import render
from acesplat.splat.schedule import NET_LR_MAX, gaussian_factor, one_cycle_factor
from acesplat.splat.views import SplatView

LR_MEANS = 1.6e-4
"""Peak position learning rate per metre of scene extent (3DGS's spatial scaling)."""
LR_SH_DC = 2.5e-3
LR_SH_REST = LR_SH_DC / 20.0
LR_OPACITY = 2.5e-2
LR_SCALES = 5e-3
LR_QUATS = 1e-3
ADAM_EPS = 1e-15
"""3DGS's epsilon: position gradients are tiny, and Adam's default 1e-8 would swamp them."""
NET_WEIGHT_DECAY = 0.01
PROBE_ITERATIONS = 5
"""Iterations timed under a wall-clock cap before the lifecycle schedule is scaled to the iterations the cap affords."""
HISTORY_EVERY = 10
GAUSSIAN_ONE_CYCLE = False


@dataclass
class OptimizeConfig:
    scene_extent: float = knob(reason="Scene size in metres: scales the position learning rate and the lifecycle.")
    max_gaussians: int = knob(reason="Cap on the number of Gaussians.")
    sh_degree: int = knob(3, "Highest SH degree of the scene set.")
    iterations: int = knob(
        2000,
        "Optimisation iterations: fixed work, so the scene set is the same on every CPU (about what 10 minutes "
        "afforded on a 25-image real scene on 2 cores: bench/stage2.md).",
    )
    opacity_reset: bool = knob(True, "Reset opacities on 3DGS's (scaled) schedule.")
    densify: bool = knob(True, "Clone and split Gaussians on schedule (pruning runs either way).")
    head_every: int = knob(5, "The head's rendering loss joins every this many iterations (0: never; ~1 render).")
    background: tuple[float, float, float] = knob((0.0, 0.0, 0.0), "Background colour of every render.")
    seed: int = knob(0, "Seed of the view order and of splits.")


@dataclass
class OptimizeResult:
    iterations: int
    iterations_planned: int
    head_steps: int
    skipped_steps: int
    seconds: float
    schedule: LifecycleSchedule | None
    events: dict = field(default_factory=dict)
    history: list[dict] = field(default_factory=list)


EvalFn = Callable[[GaussianParams, float, int], None]
"""Called with (params, training seconds so far, iteration); its own time is not charged to the budget."""
ProgressFn = Callable[[str, float, dict], None]


def make_optimizer(params: GaussianParams, scene_extent: float, nets: torch.nn.Module | None) -> torch.optim.AdamW:
    peaks = {
        "means": LR_MEANS * scene_extent,
        "log_scales": LR_SCALES,
        "quats": LR_QUATS,
        "opacity_logits": LR_OPACITY,
        "sh_dc": LR_SH_DC,
        "sh_rest": LR_SH_REST,
    }
    groups = [
        {"params": [params[n]], "name": n, "peak_lr": lr, "lr": lr, "weight_decay": 0.0, "eps": ADAM_EPS}
        for n, lr in peaks.items()
    ]
    if nets is not None:
        groups.append(
            {
                "params": list(nets.parameters()),
                "name": "nets",
                "peak_lr": NET_LR_MAX,
                "lr": NET_LR_MAX,
                "weight_decay": NET_WEIGHT_DECAY,
                "eps": 1e-8,
            }
        )
    return torch.optim.AdamW(groups, fused=True)


def set_learning_rates(optimizer: torch.optim.Optimizer, progress: float) -> None:
    """Networks follow the one-cycle; Gaussian attributes its warm-up, then 3DGS's schedule."""
    for g in optimizer.param_groups:
        f = (
            one_cycle_factor(progress)
            if g["name"] == "nets" or GAUSSIAN_ONE_CYCLE
            else gaussian_factor(g["name"], progress)
        )
        g["lr"] = g["peak_lr"] * f


def finite_gradients(optimizer: torch.optim.Optimizer) -> bool:
    """True if every gradient is finite; otherwise clears all gradients (the step must then be skipped)."""
    for g in optimizer.param_groups:
        for p in g["params"]:
            # one reduction per tensor: any NaN or infinity makes the sum non-finite
            if p.grad is not None and not bool(torch.isfinite(p.grad.sum())):
                optimizer.zero_grad(set_to_none=True)
                return False
    return True


def optimise_gaussians(
    params: GaussianParams,
    views: Sequence[SplatView],
    cfg: OptimizeConfig,
    seconds: float | None = None,
    head: HeadTrainer | None = None,
    progress: ProgressFn | None = None,
    eval_fn: EvalFn | None = None,
    eval_every_s: float | None = None,
) -> OptimizeResult:
    """Optimise ``params`` in place on ``views`` for ``cfg.iterations`` iterations, or until ``seconds`` (a cap).

    Under a cap the first PROBE_ITERATIONS are timed; if the cap cannot afford the planned iterations, the lifecycle
    schedule is scaled to those it can, and progress is the larger of the iterations' and the clock's, so a capped
    run still anneals (``iterations < iterations_planned`` then says it was cut short). With ``head``, the adapter
    and init head are optimised jointly. ``eval_fn`` (every ``eval_every_s`` seconds of training time) is for
    measuring quality against time.
    """
    if not views:
        raise ValueError("no training views")
    rng = np.random.default_rng(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    optimizer = make_optimizer(params, cfg.scene_extent, head.init if head is not None else None)
    lifecycle_cfg = LifecycleConfig(
        scene_extent=cfg.scene_extent,
        max_gaussians=cfg.max_gaussians,
        max_sh_degree=cfg.sh_degree,
        opacity_reset=cfg.opacity_reset,
        densify=cfg.densify,
    )
    if cfg.iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {cfg.iterations}")
    if seconds is not None and seconds <= 0:
        raise ValueError(f"seconds must be positive, got {seconds}")
    schedule = LifecycleSchedule.scaled(max(1, cfg.iterations))
    lifecycle = GaussianLifecycle(lifecycle_cfg, schedule)
    probed = seconds is None
    state = LifecycleState.zeros(params["means"].shape[0])
    targets = [torch.from_numpy(v.rgb) for v in views]
    bg = np.asarray(cfg.background, np.float64)
    order: list[int] = []
    events = {"cloned": 0, "split": 0, "pruned": 0, "capped": 0, "opacity_resets": 0, "densifications": 0}
    history: list[dict] = []
    it = head_steps = skipped = 0
    paused = 0.0
    start = time.monotonic()
    next_eval = 0.0
    psnr_run = float("nan")

    def elapsed() -> float:
        return time.monotonic() - start - paused

    while True:
        t_train = elapsed()
        if eval_fn is not None and eval_every_s and t_train >= next_eval:
            t_e = time.monotonic()
            eval_fn(params, t_train, it)
            paused += time.monotonic() - t_e
            next_eval = t_train + eval_every_s
        p = it / cfg.iterations if cfg.iterations else 1.0
        if seconds is not None:
            p = max(p, t_train / seconds)
        if p >= 1.0:
            break
        if not probed and it >= PROBE_ITERATIONS:
            probed = True
            affordable = int(seconds / max(t_train / it, 1e-9))
            if affordable < cfg.iterations:  # the cap binds: the lifecycle's periods fit the iterations it affords
                schedule = LifecycleSchedule.scaled(max(it + 1, affordable))
                lifecycle = GaussianLifecycle(lifecycle_cfg, schedule)
        set_learning_rates(optimizer, p)
        if not order:
            order = list(rng.permutation(len(views)))
        vi = order.pop()
        v = views[vi]
        deg = lifecycle.sh_degree(it)
        out = render(**render_tensors(params), pose_c2w=v.pose, intrinsics=v.intrinsics, background=bg, sh_degree=deg)
        loss = rendering_loss(out.color, targets[vi])
        head_loss = None
        if head is not None and cfg.head_every > 0 and it % cfg.head_every == 0:
            head_loss = head.loss(rng)
            if head_loss is not None:
                loss = loss + head_loss
                head_steps += 1
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        it += 1
        if not finite_gradients(optimizer):
            skipped += 1
            continue
        lifecycle.step_post_backward(state, out, v.intrinsics)
        optimizer.step()
        ev = lifecycle.step_post_optimizer(params, optimizer, state, it, p, gen)
        events["cloned"] += ev.cloned
        events["split"] += ev.split
        events["pruned"] += ev.pruned
        events["capped"] += ev.capped
        events["opacity_resets"] += int(ev.opacity_reset)
        events["densifications"] += int(bool(ev.counts))
        with torch.no_grad():
            mse = float(torch.mean((out.color.detach() - targets[vi]) ** 2))
        psnr_run = psnr_from_mse(mse) if np.isnan(psnr_run) else 0.9 * psnr_run + 0.1 * psnr_from_mse(mse)
        if it % HISTORY_EVERY == 0 or it == 1:
            history.append(
                {
                    "iteration": it,
                    "seconds": round(elapsed(), 3),
                    "progress": round(p, 4),
                    "loss": float(loss.detach()),
                    "psnr_running": round(psnr_run, 3),
                    "gaussians": int(params["means"].shape[0]),
                    "sh_degree": deg,
                    "head_loss": None if head_loss is None else float(head_loss.detach()),
                }
            )
        if progress:
            progress(
                "optimise",
                p,
                {"it": it, "psnr": psnr_run, "gaussians": int(params["means"].shape[0]), "skipped": skipped},
            )
    return OptimizeResult(
        iterations=it,
        iterations_planned=cfg.iterations,
        head_steps=head_steps,
        skipped_steps=skipped,
        seconds=elapsed(),
        schedule=schedule,
        events=events,
        history=history,
    )
