"""The Gaussian lifecycle of 3DGS (densify, prune, opacity reset, SH bands) as a strategy object.

Kept apart from rendering and from the optimisation loop: the loop calls the hooks around its
backward pass and optimiser step, the strategy owns the statistics and edits the parameters and the
optimiser state (Adam moments follow their Gaussians; new Gaussians start with zero moments).

3DGS's schedule is written for 30,000 iterations; a CPU budget affords far fewer, so every count is
scaled by ``total / REFERENCE_ITERATIONS`` (:meth:`LifecycleSchedule.scaled`), with floors so that
statistics still average over enough views and an opacity reset still has time to recover. The
densification window (and with it the last opacity reset) is a fraction of the run, judged by the
caller's progress: under a wall-clock budget the iteration count is only an estimate, and iterations
slow down as Gaussians multiply (bench/stage2.md: a window in iterations).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import torch

from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob
from acesplat.core.gaussians import MAX_SH_DEGREE
from acesplat.core.geometry import quat_to_matrix
from acesplat.splat.params import PARAM_NAMES, GaussianParams
from acesplat.splat.raster_torch import RenderOutput, screen_grad_norm
from acesplat.splatcore.prune import PRUNE_OPACITY

REFERENCE_ITERATIONS = 30_000
"""3DGS's iteration count, the unit of the counts below."""
DENSIFY_EVERY = 100
DENSIFY_FROM = 500
DENSIFY_UNTIL = 15_000
DENSIFY_FROM_FRACTION = DENSIFY_FROM / REFERENCE_ITERATIONS
DENSIFY_UNTIL_FRACTION = DENSIFY_UNTIL / REFERENCE_ITERATIONS
"""3DGS densifies (and resets opacities) in the first half of the run and only optimises in the second."""
OPACITY_RESET_EVERY = 3_000
SH_UP_EVERY = 1_000
SPLIT_COUNT = 2
SPLIT_SCALE_DIVISOR = 0.8 * SPLIT_COUNT
RESET_OPACITY = 0.01
MIN_DENSIFY_EVERY = 20
"""Never densify on statistics from fewer iterations than this (a Gaussian must be seen from several views)."""
MIN_RESET_EVERY = 1000
"""Never reset opacities more often than this: recovering from a reset takes a few hundred steps (bench/stage2.md)."""


@dataclass(frozen=True)
class LifecycleSchedule:
    """When things happen: periods in iterations of this run, the densification window in fractions of it."""

    densify_every: int
    densify_from: float
    densify_until: float
    reset_every: int
    sh_up_every: int

    @classmethod
    def scaled(cls, total_iterations: int) -> LifecycleSchedule:
        """3DGS's schedule shrunk (or stretched) to ``total_iterations``."""
        if total_iterations < 1:
            raise ValueError(f"total_iterations must be >= 1, got {total_iterations}")
        s = total_iterations / REFERENCE_ITERATIONS
        return cls(
            densify_every=max(MIN_DENSIFY_EVERY, round(DENSIFY_EVERY * s)),
            densify_from=DENSIFY_FROM_FRACTION,
            densify_until=DENSIFY_UNTIL_FRACTION,
            reset_every=max(MIN_RESET_EVERY, round(OPACITY_RESET_EVERY * s)),
            sh_up_every=max(1, round(SH_UP_EVERY * s)),
        )

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class LifecycleConfig:
    scene_extent: float = knob(reason="Scene size in metres (3DGS: 1.1 x the largest camera distance from their mean).")
    max_gaussians: int = knob(reason="Cap on the number of Gaussians (clones and splits stop there).")
    grad_threshold: float = knob(
        2e-4, "Mean NDC norm of the projected-centre gradient above which a Gaussian is densified (3DGS's)."
    )
    prune_opacity: float = knob(PRUNE_OPACITY, "Gaussians less opaque than this are pruned (3DGS's threshold).")
    percent_dense: float = knob(
        0.01, "Gaussians larger than this fraction of the scene extent are split, smaller ones cloned (3DGS's)."
    )
    max_sh_degree: int = knob(MAX_SH_DEGREE, "Highest SH degree the bands grow to.")
    opacity_reset: bool = knob(True, "Reset opacities on 3DGS's (scaled) schedule inside the densification window.")
    densify: bool = knob(True, "Clone and split on schedule (False: prune on schedule but never clone or split).")


@dataclass
class LifecycleState:
    """Per-Gaussian densification statistics since the last densification."""

    grad_sum: torch.Tensor  # (N,) float64 sum of NDC gradient norms over the views that saw the Gaussian
    seen: torch.Tensor  # (N,) int64 number of those views

    @classmethod
    def zeros(cls, n: int) -> LifecycleState:
        return cls(torch.zeros(n, dtype=torch.float64), torch.zeros(n, dtype=torch.int64))

    def mean_grad(self) -> torch.Tensor:
        return self.grad_sum / self.seen.clamp(min=1)


@dataclass
class LifecycleEvents:
    """What one call changed (all zero most of the time)."""

    cloned: int = 0
    split: int = 0
    pruned: int = 0
    capped: int = 0
    opacity_reset: bool = False
    counts: dict = field(default_factory=dict)


class GaussianLifecycle:
    """3DGS's adaptive density control with a cap on the count. Hooks, in loop order:

    ``sh_degree(step)`` before rendering; ``step_post_backward`` after ``loss.backward()`` (collects
    the screen-space gradient statistics); ``step_post_optimizer`` after the optimiser step (densify,
    prune, reset; may replace the parameter tensors).
    """

    def __init__(self, cfg: LifecycleConfig, schedule: LifecycleSchedule) -> None:
        if cfg.scene_extent <= 0 or cfg.max_gaussians < 1:
            raise ValueError(f"invalid LifecycleConfig {cfg}")
        self.cfg = cfg
        self.schedule = schedule

    def init_state(self, n: int) -> LifecycleState:
        return LifecycleState.zeros(n)

    def sh_degree(self, step: int) -> int:
        """Active SH degree: one more band every ``sh_up_every`` iterations, as 3DGS does."""
        return min(self.cfg.max_sh_degree, step // self.schedule.sh_up_every)

    def step_post_backward(self, state: LifecycleState, out: RenderOutput, intrinsics: Intrinsics) -> None:
        """Add this view's projected-centre gradient norms to the Gaussians it showed."""
        n = out.means2d.shape[0]
        if state.grad_sum.shape[0] != n:
            raise ValueError(f"lifecycle state has {state.grad_sum.shape[0]} Gaussians, render has {n}")
        norms = screen_grad_norm(out, intrinsics).double().cpu()
        vis = (out.radii > 0).cpu() & torch.isfinite(norms)
        state.grad_sum[vis] += norms[vis]
        state.seen[vis] += 1

    def step_post_optimizer(
        self,
        params: GaussianParams,
        optimizer: torch.optim.Optimizer,
        state: LifecycleState,
        step: int,
        progress: float,
        generator: torch.Generator | None = None,
    ) -> LifecycleEvents:
        """Densify and prune every ``densify_every`` iterations inside the densification window, reset
        opacities every ``reset_every`` inside it. ``step`` counts completed iterations (1 after the first);
        ``progress`` is the fraction of the run done (of the time budget, or of a fixed iteration count)."""
        s = self.schedule
        ev = LifecycleEvents()
        inside = s.densify_from <= progress <= s.densify_until
        if inside and step % s.densify_every == 0 and step > 0:
            ev = densify_and_prune(params, optimizer, state, self.cfg, generator)
        if self.cfg.opacity_reset and step % s.reset_every == 0 and step > 0 and progress <= s.densify_until:
            reset_opacity(params, optimizer, RESET_OPACITY)
            ev.opacity_reset = True
        return ev


# --- the operations (functions over params + optimiser state) -----------------------------------


def densify_and_prune(
    params: GaussianParams,
    optimizer: torch.optim.Optimizer,
    state: LifecycleState,
    cfg: LifecycleConfig,
    generator: torch.Generator | None = None,
) -> LifecycleEvents:
    """Clone small and split large Gaussians whose mean gradient passes the threshold, then prune
    transparent ones; the count never exceeds ``cfg.max_gaussians``. Resets the statistics."""
    n = params["means"].shape[0]
    grad = state.mean_grad()
    with torch.no_grad():
        candidates = (grad >= cfg.grad_threshold) & (state.seen > 0) & cfg.densify
        big = params["log_scales"].detach().exp().amax(dim=1).cpu() > cfg.percent_dense * cfg.scene_extent
        opacity = torch.sigmoid(params["opacity_logits"].detach()).cpu()
        prune = opacity < cfg.prune_opacity
        finite = torch.ones(n, dtype=torch.bool)
        for name in PARAM_NAMES:
            finite &= torch.isfinite(params[name].detach().reshape(n, -1)).all(dim=1).cpu()
        prune |= ~finite
        candidates &= ~prune  # a clone of a transparent Gaussian would be pruned with it
        # The cap: each clone adds one Gaussian, each split SPLIT_COUNT - 1; keep the strongest gradients.
        room = cfg.max_gaussians - int(n - prune.sum())
        cand_idx = torch.nonzero(candidates).flatten()
        cost = torch.where(big[cand_idx], SPLIT_COUNT - 1, 1)
        order = torch.argsort(grad[cand_idx], descending=True)
        fits = torch.cumsum(cost[order], 0) <= max(room, 0)
        chosen = cand_idx[order[fits]]
        capped = int(cand_idx.numel() - chosen.numel())
        clone_idx = chosen[~big[chosen]]
        split_idx = chosen[big[chosen]]

        new_parts = [_clone_values(params, clone_idx), _split_values(params, split_idx, generator)]
        remove = prune.clone()
        remove[split_idx] = True
    keep = ~remove
    _keep_rows(params, optimizer, keep)
    added = {name: torch.cat([p[name] for p in new_parts], 0) for name in PARAM_NAMES}
    _append_rows(params, optimizer, added)
    total = params["means"].shape[0]
    state.grad_sum = torch.zeros(total, dtype=torch.float64)
    state.seen = torch.zeros(total, dtype=torch.int64)
    return LifecycleEvents(
        cloned=int(clone_idx.numel()),
        split=int(split_idx.numel()),
        pruned=int(prune.sum()),
        capped=capped,
        counts={"before": n, "after": total},
    )


def reset_opacity(params: GaussianParams, optimizer: torch.optim.Optimizer, max_opacity: float = RESET_OPACITY) -> None:
    """Clamp every opacity to at most ``max_opacity`` and forget its Adam moments (3DGS's reset)."""
    p = params["opacity_logits"]
    cap = math.log(max_opacity / (1.0 - max_opacity))
    with torch.no_grad():
        p.clamp_(max=cap)
    st = optimizer.state.get(p)
    if st:
        for k in ("exp_avg", "exp_avg_sq"):
            if k in st:
                st[k].zero_()


def _clone_values(params: GaussianParams, idx: torch.Tensor) -> dict[str, torch.Tensor]:
    return {name: params[name].detach()[idx.to(params[name].device)].clone() for name in PARAM_NAMES}


def _split_values(
    params: GaussianParams, idx: torch.Tensor, generator: torch.Generator | None
) -> dict[str, torch.Tensor]:
    """SPLIT_COUNT children per Gaussian, centred at samples of the parent, each SPLIT_SCALE_DIVISOR smaller."""
    dev = params["means"].device
    idx = idx.to(dev)
    m = params["means"].detach()[idx]
    ls = params["log_scales"].detach()[idx]
    q = params["quats"].detach()[idx]
    k = idx.numel()
    R = torch.from_numpy(quat_to_matrix(_normalised(q).cpu().double().numpy()).reshape(k, 3, 3)).to(m)
    noise = torch.randn((SPLIT_COUNT, k, 3), generator=generator, dtype=torch.float64).to(m)
    offsets = torch.einsum("kij,skj->ski", R, noise * ls.exp()[None])
    out = {
        "means": (m[None] + offsets).reshape(-1, 3),
        "log_scales": (ls - math.log(SPLIT_SCALE_DIVISOR)).repeat(SPLIT_COUNT, 1),
    }
    for name in ("quats", "opacity_logits", "sh_dc", "sh_rest"):
        v = params[name].detach()[idx]
        out[name] = v.repeat(SPLIT_COUNT, *([1] * (v.ndim - 1)))
    return out


def _normalised(q: torch.Tensor) -> torch.Tensor:
    n = q.norm(dim=1, keepdim=True)
    ident = torch.zeros_like(q)
    ident[:, 0] = 1.0
    return torch.where(n > 0, q / n.clamp(min=1e-12), ident)


def _replace_param(
    params: GaussianParams, optimizer: torch.optim.Optimizer, name: str, new: torch.Tensor, state_fn
) -> None:
    """Swap ``params[name]`` for a new Parameter holding ``new``, carrying its optimiser state through ``state_fn``."""
    old = params[name]
    fresh = torch.nn.Parameter(new.detach().contiguous())
    for group in optimizer.param_groups:
        for i, p in enumerate(group["params"]):
            if p is old:
                group["params"][i] = fresh
    st = optimizer.state.pop(old, None)
    if st:
        optimizer.state[fresh] = {
            k: (state_fn(v) if isinstance(v, torch.Tensor) and v.shape == old.shape else v) for k, v in st.items()
        }
    params[name] = fresh


def _keep_rows(params: GaussianParams, optimizer: torch.optim.Optimizer, keep: torch.Tensor) -> None:
    if bool(keep.all()):
        return
    for name in PARAM_NAMES:
        k = keep.to(params[name].device)
        _replace_param(params, optimizer, name, params[name].detach()[k], lambda v, k=k: v[k])


def _append_rows(params: GaussianParams, optimizer: torch.optim.Optimizer, rows: dict[str, torch.Tensor]) -> None:
    if rows["means"].shape[0] == 0:
        return
    for name in PARAM_NAMES:
        extra = rows[name].to(params[name])
        _replace_param(
            params,
            optimizer,
            name,
            torch.cat([params[name].detach(), extra], 0),
            lambda v, e=extra: torch.cat([v, torch.zeros_like(e)], 0),
        )
