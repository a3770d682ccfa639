"""Keeping the refined map small: the torch-free pruning of acesplat/splatcore/prune.py, under the names the
refiner imports."""

from __future__ import annotations

from acesplat.splatcore.prune import PRUNE_OPACITY, cap_keep, transparent

__all__ = ["PRUNE_OPACITY", "cap_keep", "transparent"]
