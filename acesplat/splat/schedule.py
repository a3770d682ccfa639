"""The one-cycle learning-rate shape, driven by the fraction of the budget used.

Driving it by the budget fraction (not an iteration count) makes a short run go through the whole
schedule, warm-up and annealing included, instead of stopping at its start.
"""

from __future__ import annotations

import math

NET_LR_MIN = 2e-4
NET_LR_MAX = 2e-3
"""The paper's one-cycle range for the adapter and init head."""
WARMUP = 0.1
"""Share of the run spent rising from the minimum to the peak."""
FINAL_DIVISOR = 100.0
"""The run ends at minimum / this."""


def one_cycle(progress: float, lr_min: float, lr_max: float, warmup: float = WARMUP) -> float:
    """Cosine rise from ``lr_min`` to ``lr_max`` over ``warmup``, then cosine decay to ``lr_min / FINAL_DIVISOR``."""
    if not 0.0 < lr_min <= lr_max or not 0.0 <= warmup < 1.0:
        raise ValueError(f"need 0 < lr_min <= lr_max and 0 <= warmup < 1, got {lr_min}, {lr_max}, {warmup}")
    p = min(max(progress, 0.0), 1.0)
    if p < warmup:
        return lr_min + (lr_max - lr_min) * 0.5 * (1.0 - math.cos(math.pi * p / warmup))
    q = (p - warmup) / (1.0 - warmup)
    lo = lr_min / FINAL_DIVISOR
    return lo + (lr_max - lo) * 0.5 * (1.0 + math.cos(math.pi * q))


def one_cycle_factor(progress: float, warmup: float = WARMUP) -> float:
    """The same shape as a multiplier of a peak learning rate (1 at the peak, NET_LR_MIN / NET_LR_MAX at the start)."""
    return one_cycle(progress, NET_LR_MIN, NET_LR_MAX, warmup) / NET_LR_MAX


POSITION_DECAY = 0.01
"""3DGS decays the position learning rate exponentially to this fraction of its start."""


def gaussian_factor(name: str, progress: float, warmup: float = WARMUP) -> float:
    """Multiplier of a Gaussian attribute's peak learning rate: the one-cycle warm-up, then 3DGS's own
    schedule (positions decay exponentially to POSITION_DECAY, the other attributes stay at their peak)."""
    p = min(max(progress, 0.0), 1.0)
    rise = one_cycle_factor(p, warmup) if p < warmup else 1.0
    if name == "means":
        return rise * POSITION_DECAY ** max((p - warmup) / (1.0 - warmup), 0.0)
    return rise
