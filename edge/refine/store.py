"""The refined map's storage: arrays with spare capacity, so a commit never copies the whole map.

A commit overwrites the rows of the Gaussians its keyframe saw, appends its new ones, and hides the
ones it pruned (opacity logit set to HIDDEN, which the rasterizer culls like any transparent Gaussian).
Only when hidden rows pile up (or the cap is exceeded) are the arrays compacted, which copies
(copying the whole map at every commit costs more than a window of the per-frame budget: bench/stage2.md).
"""

from __future__ import annotations

import numpy as np

from acesplat.core.gaussians import Gaussians
from acesplat.splatcore.prune import cap_keep

PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh")
HIDDEN = -30.0
"""Opacity logit of a removed Gaussian awaiting compaction (opacity 1e-13: below every cut-off)."""
COMPACT_FRACTION = 0.05
GROWTH = 1.5


class GaussianStore:
    def __init__(self, g: Gaussians, cap: int) -> None:
        self.cap = cap
        self.sh_degree = g.sh_degree
        n = len(g)
        self._buf = {p: np.empty((max(16, int(n * GROWTH)),) + getattr(g, p).shape[1:], np.float32) for p in PARAMS}
        for p in PARAMS:
            self._buf[p][:n] = getattr(g, p)
        self.n = n
        self.hidden = np.zeros(self._capacity(), bool)
        self.origin = np.full(self._capacity(), -1, np.int64)
        """Per row: its index in the map the store was made from, -1 for a row appended since."""
        self.origin[:n] = np.arange(n)
        self.compactions = 0

    def _capacity(self) -> int:
        return self._buf["means"].shape[0]

    @property
    def view(self) -> Gaussians:
        """The live rows (no copy), hidden ones included (they render as nothing)."""
        return Gaussians(*(self._buf[p][: self.n] for p in PARAMS))

    def live_count(self) -> int:
        return int(self.n - self.hidden[: self.n].sum())

    def live(self) -> Gaussians:
        """A compact copy without hidden rows (for saving and reporting)."""
        return self.view.subset(~self.hidden[: self.n])

    def write_rows(self, idx: np.ndarray, g: Gaussians) -> None:
        for p in PARAMS:
            self._buf[p][idx] = getattr(g, p)

    def hide(self, idx: np.ndarray) -> None:
        self._buf["opacity_logits"][idx] = HIDDEN
        self.hidden[idx] = True

    def append(self, g: Gaussians, origin: np.ndarray | None = None) -> None:
        """Add the rows of ``g``; ``origin`` (M,) int their indices in the initial map (default -1: new rows)."""
        m = len(g)
        if self.n + m > self._capacity():
            new_cap = max(int((self.n + m) * GROWTH), 16)
            for p in PARAMS:
                buf = np.empty((new_cap,) + self._buf[p].shape[1:], np.float32)
                buf[: self.n] = self._buf[p][: self.n]
                self._buf[p] = buf
            hidden = np.zeros(new_cap, bool)
            hidden[: self.n] = self.hidden[: self.n]
            self.hidden = hidden
            origins = np.full(new_cap, -1, np.int64)
            origins[: self.n] = self.origin[: self.n]
            self.origin = origins
        for p in PARAMS:
            self._buf[p][self.n : self.n + m] = getattr(g, p)
        self.hidden[self.n : self.n + m] = False
        self.origin[self.n : self.n + m] = -1 if origin is None else np.asarray(origin, np.int64)
        self.n += m

    def enforce(self) -> int:
        """Hold the cap (hiding the least opaque live Gaussians) and compact when hidden rows pile up;
        returns how many live Gaussians the cap removed."""
        live = ~self.hidden[: self.n]
        capped = 0
        if live.sum() > self.cap:
            idx = np.flatnonzero(live)
            keep = cap_keep(self.view.subset(idx), self.cap)
            self.hide(idx[~keep])
            capped = int((~keep).sum())
        if self.hidden[: self.n].sum() > COMPACT_FRACTION * max(self.n, 1):
            self.compact()
        return capped

    def compact(self) -> None:
        keep = np.flatnonzero(~self.hidden[: self.n])
        for p in PARAMS:
            self._buf[p][: keep.size] = self._buf[p][keep]
        self.origin[: keep.size] = self.origin[keep]
        self.origin[keep.size :] = -1
        self.n = keep.size
        self.hidden[:] = False
        self.compactions += 1
