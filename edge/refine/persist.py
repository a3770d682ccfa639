"""Saving the refined map as a standard 3DGS PLY, periodically and at exit, without ever losing the last good file.

``acesplat.core.ply.write_ply`` writes to a temporary file beside the target and renames it into
place, so a crash or a full disk mid-write leaves the previous file as it was. A failed save is
counted and reported, never raised: a full disk must not stop localization.
"""

from __future__ import annotations

import time
from pathlib import Path

from acesplat.core.gaussians import Gaussians
from acesplat.core.ply import write_ply
from edge.refine.deadline import Clock


class SplatSaver:
    def __init__(self, path: str | Path, every_s: float, clock: Clock = time.monotonic) -> None:
        """Save to ``path`` at most every ``every_s`` seconds (RefineOptions.save_every_s) and at exit."""
        if every_s <= 0:
            raise ValueError(f"save interval must be positive, got {every_s}")
        self.path = Path(path)
        self.every_s = every_s
        self.clock = clock
        self.last_save: float | None = None
        self.saves = 0
        self.failures = 0
        self.last_error: str | None = None
        self.dirty = False

    def mark_dirty(self) -> None:
        self.dirty = True

    def due(self) -> bool:
        return self.dirty and (self.last_save is None or self.clock() - self.last_save >= self.every_s)

    def maybe_save(self, g: Gaussians) -> bool:
        """Save if the map changed and the interval has passed; True if a save happened and worked."""
        return self.save(g) if self.due() else False

    def save(self, g: Gaussians) -> bool:
        self.last_save = self.clock()
        try:
            write_ply(self.path, g)
        except OSError as e:
            self.failures += 1
            self.last_error = f"{self.path}: {e.strerror or e}"
            return False
        self.saves += 1
        self.dirty = False
        return True

    def as_dict(self) -> dict:
        return {"path": str(self.path), "saves": self.saves, "failures": self.failures, "last_error": self.last_error}
