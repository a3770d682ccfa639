"""Deadlines and step-cost estimates: refinement never starts work it cannot finish in time.

The clock is injectable so tests drive it by hand. A piece of work's cost is predicted from the
last few measurements (their median times a safety margin: robust to one slow outlier, which on a
shared CPU would otherwise block every later piece whose estimate it inflated); before any
measurement the caller's prior is used.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable

import numpy as np

Clock = Callable[[], float]

SAFETY = 1.2


class Deadline:
    """A point in time on ``clock`` (seconds); ``preempt`` moves it to now (the localization thread needs the CPU)."""

    def __init__(self, at: float, clock: Clock = time.perf_counter) -> None:
        self.at = float(at)
        self.clock = clock

    @classmethod
    def after(cls, seconds: float, clock: Clock = time.perf_counter) -> Deadline:
        return cls(clock() + seconds, clock)

    def remaining(self) -> float:
        return self.at - self.clock()

    def expired(self) -> bool:
        return self.remaining() <= 0.0

    def preempt(self) -> None:
        self.at = min(self.at, self.clock())

    def allows(self, cost_s: float, reserve_s: float = 0.0) -> bool:
        """True if work of ``cost_s`` (plus ``reserve_s`` kept for what must follow) ends before the deadline."""
        return cost_s + reserve_s <= self.remaining()


class CostEstimate:
    """Predicted duration (seconds) of a recurring piece of work."""

    def __init__(self, prior_s: float, safety: float = SAFETY, window: int = 5, name: str = "") -> None:
        if prior_s < 0:
            raise ValueError(f"prior must be non-negative, got {prior_s}")
        self.name = name
        """What the work is (reports name late pieces by it)."""
        self.prior_s = prior_s
        self.safety = safety
        self.recent: deque[float] = deque(maxlen=window)
        self.last_s: float | None = None
        self.count = 0

    def record(self, seconds: float) -> None:
        self.count += 1
        self.last_s = seconds
        self.recent.append(seconds)

    def predict(self) -> float:
        if not self.recent:
            return self.prior_s
        return self.safety * float(np.median(self.recent))


def timed(clock: Clock, fn: Callable[[], object], estimate: CostEstimate | None = None) -> tuple[object, float]:
    """Run ``fn`` and return (its result, seconds on ``clock``), recording the time in ``estimate``."""
    t0 = clock()
    out = fn()
    dt = clock() - t0
    if estimate is not None:
        estimate.record(dt)
    return out, dt
