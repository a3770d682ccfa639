"""Witness views: the views a session must prove, at its end, that refinement harmed none of.

The commit guard checks a keyframe's batch against the keyframe and the held keyframes at a small size. A batch
fitted to one view can still lower the sharpness of views it never checked, most of all views that saw the same
surfaces from nearer, and only at full resolution (bench/refine.md). So every tracked frame is a witness (a
bounded pool that keeps the most distinct viewpoints), and so are the mapping images a bundle carries as alignment
keyframes (pinned: grey, at their surveyed poses, the views the map was made from). :func:`repair` renders each
witness under the refined map and the map as loaded, at the witness size, and puts back what refinement changed in
any witness that lost: pass after pass, until no witness loses, or the map as loaded when the passes run out. The
map a session leaves is then never worse than the loaded one on any witness.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import pose_error
from edge.refine.coverage import frustum_mask
from edge.refine.guard import loaded_bound, psnr, render_view, view_mse
from edge.refine.store import PARAMS

DEGREE_AS_M = 0.01
"""Viewpoint distance of one degree of rotation, in metres of translation, when the pool picks distinct views."""
GRAY_WEIGHTS = np.array([0.299, 0.587, 0.114], np.float32)
"""RGB to grey as OpenCV's COLOR_RGB2GRAY, which made the keyframes' grey images."""


@dataclass
class Witness:
    """A view to hold the map to: ``pose`` (4, 4) camera-to-world (as localized, or surveyed), ``rgb`` (H, W, 3)
    uint8 at intrinsics ``k``, or (H, W) uint8 grey (then compared with the render's grey)."""

    pose: np.ndarray
    k: Intrinsics
    rgb: np.ndarray
    name: str = ""
    loaded_mse: float | None = None

    def target(self) -> np.ndarray:
        return self.rgb.astype(np.float32) * np.float32(1.0 / 255.0)

    def mse(self, g, target: np.ndarray, background: np.ndarray) -> float:
        """Mean squared error of ``g`` rendered from this view against ``target`` (its :meth:`target`)."""
        if target.ndim == 3:
            return view_mse(g, self.pose, self.k, target, background)
        r = render_view(g, self.pose, self.k, background)
        color = np.broadcast_to(np.asarray(background, np.float32), target.shape + (3,)) if r is None else r.color
        d = np.asarray(color, np.float32) @ GRAY_WEIGHTS - target
        return float(np.mean(d * d))


def check_witness(w: Witness) -> None:
    if np.shape(w.pose) != (4, 4) or w.rgb.dtype != np.uint8 or w.rgb.shape[:2] != (w.k.height, w.k.width):
        raise ValueError(f"witness needs a (4, 4) pose and ({w.k.height}, {w.k.width}[, 3]) uint8 image")
    if w.rgb.ndim not in (2, 3) or (w.rgb.ndim == 3 and w.rgb.shape[2] != 3):
        raise ValueError(f"witness image must be (H, W, 3) RGB or (H, W) grey, got {w.rgb.shape}")


def spread(poses: list[np.ndarray], n: int) -> list[int]:
    """Indices of at most ``n`` of ``poses`` (4, 4) spread over the viewpoints: farthest-point order from the first."""
    if not poses or n <= 0:
        return []
    chosen = [0]
    d = np.array([viewpoint_distance(poses[0], p) for p in poses])
    while len(chosen) < min(n, len(poses)):
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, [viewpoint_distance(poses[i], p) for p in poses])
    return sorted(chosen)


def viewpoint_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Translation (m) plus rotation (``DEGREE_AS_M`` m a degree) between camera-to-world poses ``a``, ``b`` (4, 4)."""
    t, r = pose_error(a, b)
    return t + DEGREE_AS_M * r


class WitnessPool:
    """At most ``capacity`` witnesses; when full, a new one replaces the older of the two closest viewpoints, so
    a long run keeps views spread over where it went instead of only the latest ones. The pairwise distances are
    kept, so an add costs ``capacity`` distances, not all pairs."""

    def __init__(self, capacity: int) -> None:
        if capacity < 0:
            raise ValueError(f"capacity must be >= 0, got {capacity}")
        self.capacity = capacity
        self.items: list[Witness] = []
        self.pinned: list[Witness] = []
        """Witnesses that never leave (the bundle's mapping images); not counted in ``capacity``."""
        self.offered = 0
        self._dist = np.full((capacity + 1, capacity + 1), np.inf)

    def pin(self, w: Witness) -> None:
        check_witness(w)
        self.pinned.append(w)

    def all(self) -> list[Witness]:
        return self.pinned + self.items

    def add(self, w: Witness) -> None:
        check_witness(w)
        self.offered += 1
        if self.capacity == 0:
            return
        n = len(self.items)
        d = [viewpoint_distance(v.pose, w.pose) for v in self.items]
        self._dist[n, :n] = self._dist[:n, n] = d
        self.items.append(w)
        if n + 1 <= self.capacity:
            return
        i, j = np.unravel_index(int(np.argmin(self._dist)), self._dist.shape)
        drop = int(min(i, j))  # the older of the closest pair
        del self.items[drop]
        keep = np.delete(np.arange(n + 1), drop)
        self._dist[:n, :n] = self._dist[np.ix_(keep, keep)]
        self._dist[n, :] = self._dist[:, n] = np.inf

    def __len__(self) -> int:
        return len(self.items)


def changed_rows(refiner) -> tuple[np.ndarray, np.ndarray]:
    """What refinement changed: (M,) bool over the store's rows (a row added and live, or a loaded row whose values
    differ or that is hidden), and the indices of loaded rows that changed, were hidden or are gone."""
    st, loaded = refiner.store, refiner.loaded
    n = st.n
    origin, hidden = st.origin[:n], st.hidden[:n]
    has = origin >= 0
    changed = ~has & ~hidden
    rows, src = np.flatnonzero(has), origin[has]
    diff = hidden[rows].copy()
    for p in PARAMS:
        a, b = getattr(st.view, p)[rows], getattr(loaded, p)[src]
        diff |= np.any((a != b).reshape(rows.size, -1), axis=1)
    changed[rows[diff]] = True
    present = np.zeros(len(loaded), bool)
    present[src] = True
    return changed, np.union1d(src[diff], np.flatnonzero(~present))


def repair(refiner, witnesses: list[Witness], tolerance_db: float, max_passes: int = 4) -> dict:
    """Undo refinement wherever a witness lost more than ``tolerance_db`` dB of PSNR against the map as loaded
    (``refiner.restore_view``), re-checking every witness after each pass; after ``max_passes`` passes with a loss
    left, the map as loaded (``refiner.restore_all``). A witness that no changed row reaches (as it is now or as it
    was loaded) renders as under the loaded map and is not rendered. Returns the report: witnesses, rendered in the
    first pass, harmed before the repair, passes, rows restored (revived: of them, rows pruning or the cap had
    removed), added rows removed, whether it fell back to the loaded map, worst loss before (dB), ms."""
    t0 = time.perf_counter()
    bg = np.asarray(refiner.cfg.background, np.float64)
    harmed_first: int | None = None
    worst = 0.0
    restored = revived = removed = passes = rendered = 0
    fell_back = False
    while True:
        changed, changed_loaded = changed_rows(refiner)
        m = refiner.map
        harmed = []
        for w in witnesses:
            reach = np.any(frustum_mask(m.means[changed], m.log_scales[changed], w.pose, w.k)) or np.any(
                frustum_mask(
                    refiner.loaded.means[changed_loaded], refiner.loaded.log_scales[changed_loaded], w.pose, w.k
                )
            )
            if not reach:
                continue
            t = w.target()
            if w.loaded_mse is None:
                w.loaded_mse = w.mse(refiner.loaded, t, bg)
            mse = w.mse(m, t, bg)
            if harmed_first is None:
                rendered += 1
            if mse > loaded_bound(w.loaded_mse, tolerance_db):
                harmed.append(w)
                if harmed_first is None:
                    worst = min(worst, psnr(mse) - psnr(w.loaded_mse))
        if harmed_first is None:
            harmed_first = len(harmed)
        if not harmed:
            break
        if passes == max_passes:
            refiner.restore_all()
            fell_back = True
            break
        passes += 1
        for w in harmed:
            a, b, c = refiner.restore_view(w.pose, w.k)
            restored, revived, removed = restored + a, revived + b, removed + c
    return {
        "witnesses": len(witnesses),
        "rendered": rendered,
        "harmed_before": int(harmed_first or 0),
        "passes": passes,
        "rows_restored": restored,
        "revived": revived,
        "added_removed": removed,
        "fell_back_to_loaded": fell_back,
        "worst_before_db": float(worst),
        "ms": 1000.0 * (time.perf_counter() - t0),
    }
