"""One keyframe's refinement batch: render, align the pose, find what is missing, seed, optimise within the
deadline, guard, commit.

The batch works on a private copy of the Gaussians the keyframe sees (plus its new ones), so the
map itself changes only at the commit, all at once, and rolling back is simply not committing.
Where the map covers the view, the keyframe's pose is first corrected against it (``align``): fitting
the map to a frame seen from a pose a few centimetres off smears it. Optimisation steps fit random
crops of the keyframe at full resolution (fitting the whole view at the refinement size washes out
detail the low-resolution loss cannot see), so the keyframe is checked with one more render after
them; with no full-resolution image the steps fit the whole view and the best measured state is kept.

Time: the batch is a generator that announces each piece of work with the estimate of its cost
before doing it; the driver (``refine`` for one deadline, the worker across several frames' windows)
answers whether it may run, so work that would overrun is never started. A granted piece is timed by
the driver (``grant``) up to the batch's next request, so its estimate learns all it runs, not only
its main call. Renders are split into tiles so each piece fits in what a frame's localization leaves
of the budget.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Protocol

import cv2
import numpy as np

from acesplat.align.flow_pnp import RENDER_ALIGN, align_to_render
from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob
from acesplat.core.gaussians import Gaussians, concat_gaussians
from acesplat.raster import rasterize, rasterize_backward
from acesplat.splatcore.prune import PRUNE_OPACITY, transparent
from edge.refine.adam import LearningRates, RowAdam
from edge.refine.coverage import ALPHA_MIN, RenderAnalysis, analyse_render, frustum_mask
from edge.refine.deadline import Clock, CostEstimate, Deadline
from edge.refine.guard import (
    HELD_TOLERANCE,
    HeldView,
    HeldViews,
    all_finite,
    downsample,
    harmed_views,
    held_verdict,
    loaded_bound,
    view_mse,
)
from edge.refine.seeding import seed_from_scr
from edge.refine.store import GaussianStore

DIVERGE = 1.5
"""A step whose measured error exceeds the batch's best by this factor ends the batch (keeping the best)."""
POSE_CHECK_FACTOR = 2.5
"""A keyframe whose error on the pixels the map already covers exceeds this multiple of the median of recent
committed keyframes' is taken for a wrong pose and not used (bench/refine.md)."""
STEP_PER_RENDER = 2.5
"""A step (render + backward + Adam) costs about this many keyframe renders until measured."""
POSE_CHECK_MIN_COVERAGE = 0.3
POSE_CHECK_HISTORY = 8
POSE_CHECK_MIN_HISTORY = 3


@dataclass(frozen=True)
class RefineConfig:
    """What one keyframe's batch may do, and the priors of its time estimates."""

    cap: int = knob(60_000, "Most Gaussians refinement may grow the map to; a larger loaded map keeps all of its own.")
    max_new: int = knob(1500, "New Gaussians per keyframe at most.")
    seed_spacing: int = knob(2, "Pixels between seeded Gaussians (refinement resolution).")
    max_steps: int = knob(30, "Optimisation steps per keyframe at most (the deadline usually stops it first).")
    crop_side: int = knob(80, "Longer side of the full-resolution crops the steps fit (bench/refine.md).")
    held: int = knob(16, "Earlier committed keyframes the photometric guard checks (bench/refine.md).")
    tiles: int = knob(2, "Keyframe renders are split into tiles x tiles pieces, each fitting one frame's window.")
    align: bool = knob(True, "Correct each keyframe's pose against the map before using it (acesplat.align.flow_pnp).")
    align_side: int = knob(160, "Longer side of the pose alignment's render (bench/refine.md).")
    align_tiles: int = knob(3, "The pose alignment's render is split into this many tiles a side.")
    align_max_m: float = knob(RENDER_ALIGN.max_shift_m, "Largest pose correction the alignment may make (m).")
    align_max_deg: float = knob(RENDER_ALIGN.max_shift_deg, "Largest pose correction the alignment may make (deg).")
    guard_max_side: int = knob(48, "Longer side of the guarded views' renders (from the full-resolution frame).")
    held_tolerance: float = knob(HELD_TOLERANCE, "Relative error increase a held view may take in one batch.")
    view_tolerance_db: float = knob(
        0.05, "PSNR a guarded view may end below its PSNR under the loaded map (dB); also what a report calls harm."
    )
    alpha_min: float = knob(ALPHA_MIN, "Alpha at which a pixel counts as covered by the map.")
    error_max: float = knob(float("inf"), "Also seed covered pixels whose error exceeds this (off: bench/refine.md).")
    prune_opacity: float = knob(PRUNE_OPACITY, "Gaussians below this opacity after a batch are removed.")
    lr: LearningRates = knob(reason="Adam learning rates per parameter.", factory=LearningRates)
    background: tuple[float, float, float] = knob((0.0, 0.0, 0.0), "Render background (RGB in [0, 1]).")
    step_prior_s: float = knob(0.05, "A step's predicted seconds before one is measured.")
    render_prior_s: float = knob(0.03, "A render tile's predicted seconds before one is measured.")
    seed: int = knob(0, "Seed of the batch's random crops and seeding.")

    def __post_init__(self) -> None:
        if (
            self.cap < 1
            or self.max_new < 0
            or self.seed_spacing < 1
            or self.max_steps < 0
            or self.held < 0
            or self.tiles < 1
            or self.align_tiles < 1
            or self.crop_side < 4
            or not self.view_tolerance_db >= 0
        ):
            raise ValueError(f"invalid RefineConfig {self}")


@dataclass
class Keyframe:
    """A localized frame prepared for refinement.

    rgb (H, W, 3) float32 in [0, 1] at refinement resolution with intrinsics ``k``; pose (4, 4)
    camera-to-world as localized; coords (h, w, 3) the SCR prediction on the network input of
    ``k_input`` (None: nothing can be seeded).
    """

    pose: np.ndarray
    rgb: np.ndarray
    k: Intrinsics
    coords: np.ndarray | None = None
    k_input: Intrinsics | None = None
    name: str = ""
    features: np.ndarray | None = None
    """The SCR graph's encoder features (C, h, w) for the frame, for the ONNX initializer."""
    detail: np.ndarray | None = None
    """The frame at full resolution (H', W', 3) float32 in [0, 1] with intrinsics ``k_detail``: optimisation steps fit
    random crops of it (None: steps fit the whole ``rgb``)."""
    k_detail: Intrinsics | None = None


class Seeder(Protocol):
    def __call__(
        self, kf: Keyframe, need: np.ndarray, max_new: int, sh_degree: int, rng: np.random.Generator
    ) -> Gaussians: ...


def scr_seeder(
    kf: Keyframe, need: np.ndarray, max_new: int, sh_degree: int, rng: np.random.Generator, spacing: int = 2
) -> Gaussians:
    """Seed from the SCR coordinates upsampled along pixel rays, coloured from the keyframe."""
    if kf.coords is None or kf.k_input is None:
        return Gaussians.empty(sh_degree)
    return seed_from_scr(kf.coords, kf.pose, kf.k_input, kf.rgb, kf.k, need, spacing, max_new, sh_degree, rng)


@dataclass
class BatchReport:
    """What one keyframe's batch did. ``outcome``: committed, rolled_back_pose (the map disagrees with the
    keyframe where it covers it: a wrong pose), rolled_back_keyframe (no gain on the keyframe),
    rolled_back_held (an earlier keyframe got worse), rolled_back_view (a guarded view, the keyframe or a held
    one, would end worse than under the loaded map), no_time (could not start), empty."""

    name: str
    outcome: str
    steps: int = 0
    nonfinite_skipped: int = 0
    diverged: bool = False
    added: int = 0
    pruned: int = 0
    capped: int = 0
    mse_before: float = float("nan")
    mse_after: float = float("nan")
    held_before: list[float] = field(default_factory=list)
    held_after: list[float] = field(default_factory=list)
    held_loaded: list[float] = field(default_factory=list)
    """The held views' errors under the loaded map (same order as ``held_before``)."""
    kf_loaded_mse: float = float("nan")
    """The keyframe's error at guard resolution under the loaded map, and after the batch (``kf_guard_mse``)."""
    kf_guard_mse: float = float("nan")
    coverage: float = float("nan")
    seeded_by: str = ""
    covered_mse: float = float("nan")
    ms: dict[str, float] = field(default_factory=dict)
    step_ms: list[float] = field(default_factory=list)
    stopped_by_deadline: bool = False
    align: str = ""
    """The pose alignment's status (acesplat.align.flow_pnp.Alignment), '' when not run."""
    align_shift_m: float = 0.0
    align_shift_deg: float = 0.0
    windows: int = 1
    """Frames' time windows the batch ran in (the worker carries a batch over several frames)."""

    @property
    def committed(self) -> bool:
        return self.outcome == "committed"


@dataclass
class _View:
    """What a batch saw from its keyframe (pose aligned where the map covers the view)."""

    kf: Keyframe
    kf_px: int
    in_view: np.ndarray
    """(M,) rows of the map in the keyframe's view."""
    seen: np.ndarray
    """(M,) bool: which of them the keyframe's render drew."""
    an: RenderAnalysis


@dataclass
class _Work:
    """A batch's private copy of the Gaussians it optimises and what the steps made of it."""

    active_idx: np.ndarray
    """(A,) map rows the copy's first A rows came from (the rest are new)."""
    best: Gaussians
    active: Gaussians
    opt: RowAdam
    crops: bool
    """Steps fit random crops of the full-resolution image (their errors are not comparable)."""
    best_mse: float = float("inf")
    measured: int = 0
    """Steps that measured the keyframe whole."""
    gone: np.ndarray | None = None
    """(len(best),) bool: pruned as transparent."""
    kept: Gaussians | None = None
    kf_view: HeldView | None = None
    """The keyframe at guard resolution, as the guard checked it (it joins the held views at the commit)."""


class Refiner:
    """Owns the map (a float32 Gaussian set) and refines it one keyframe batch at a time (not thread-safe)."""

    def __init__(
        self,
        gaussians: Gaussians,
        cfg: RefineConfig = RefineConfig(),
        seeder: Callable | None = None,
        clock: Clock = time.perf_counter,
    ) -> None:
        self.loaded = gaussians.astype(np.float32).copy()
        """The map as loaded: the floor every guarded view is held to."""
        self.cap = max(cfg.cap, len(self.loaded))
        """The configured cap limits growth only: a loaded map above it is never pruned to fit."""
        self.store = GaussianStore(self.loaded, self.cap)  # copies into its own arrays
        self.cfg = cfg
        self.clock = clock
        self.scr_seeder = lambda kf, need, n, deg, rng: scr_seeder(kf, need, n, deg, rng, cfg.seed_spacing)
        self.seeder = seeder or self.scr_seeder
        self.rng = np.random.default_rng(cfg.seed)
        self.bg = np.asarray(cfg.background, np.float64)
        self.held = HeldViews(cfg.held)
        self.covered_history: deque[float] = deque(maxlen=POSE_CHECK_HISTORY)
        self.version = 0
        """Bumped at every commit: held views' cached errors are valid for one version."""
        self.step_cost = CostEstimate(cfg.step_prior_s, name="step")
        self.render_cost = CostEstimate(cfg.render_prior_s, name="render")
        self.step_per_render = STEP_PER_RENDER
        """Step cost / keyframe render cost, measured at warm-up. Renders happen on every keyframe, steps only
        when they fit: a step estimate left from slower times would never be corrected, so after a batch
        without steps each render adds this multiple of its own cost as a step sample."""
        self.stepless_batches = 0
        self.commit_cost = CostEstimate(0.0, name="commit")
        self.seed_cost = CostEstimate(0.0, name="seed")
        self.scr_seed_cost = CostEstimate(0.0, name="scr_seed")
        self.cull_cost = CostEstimate(0.0, name="cull")
        """Selecting the map's Gaussians in a keyframe's view (then the render's first tile is set up)."""
        self.setup_cost = CostEstimate(0.0, name="setup")
        """A batch's private copy of the Gaussians in view and its optimiser state."""
        self.align_render_cost = CostEstimate(cfg.render_prior_s, name="align_render")
        """One tile of the full-resolution render the pose alignment compares with the keyframe."""
        self.align_cost = CostEstimate(cfg.render_prior_s, name="align")
        """Optical flow and PnP of the pose alignment."""
        self.guard_view_cost = CostEstimate(cfg.render_prior_s, name="guard_view")
        """One held-view render at guard resolution."""
        self.guard_prep_cost = CostEstimate(0.0, name="guard_prep")
        """What a guarded view's render needs first: culling the map (and the batch's rows) to the view, the copy."""
        self.prune_cost = CostEstimate(0.0, name="prune")
        """After the steps: the batch's transparent Gaussians dropped (a copy of the rest), the guard's first copy."""
        self.totals = {
            "keyframes": 0,
            "committed": 0,
            "rolled_back": 0,
            "no_time": 0,
            "steps": 0,
            "nonfinite_skipped": 0,
            "gaussians_added": 0,
            "pruned": 0,
            "capped": 0,
            "rolled_back_view": 0,
        }

    # ------------------------------------------------------------------------------------------
    def warm_up(self, k: Intrinsics | None = None, k_detail: Intrinsics | None = None) -> dict:
        """Load (or compile) the rasterizer's kernels, then measure what a batch's pieces cost on this map.

        Without measurements every piece would wait for a prior guess to fit the deadline, and a pessimistic
        guess would never let the first piece run (so nothing would ever be measured). The measurement renders
        the map at ``k``'s size from its median centre along its two widest directions (both ways), as cameras
        inside the scene looking at walls would, and keeps the median; returns the measured milliseconds. Pieces:
        culling the map to a view, one tile of a keyframe render at ``k``, one step on a crop of ``k_detail`` (the
        keyframes' full-resolution size; default ``k``), one held view at guard size.
        """
        g = Gaussians.zeros(2, self.map.sh_degree, np.float32)
        g.means[:, 2] = 2.0
        g.log_scales[:] = -3.0
        small = Intrinsics.from_focal(16.0, 16, 16)
        r = rasterize(g, np.eye(4), small, self.bg)
        rasterize_backward(r, np.ones((16, 16, 3), np.float32))
        if k is None or len(self.map) < 2:
            return {}
        from acesplat.core.geometry import look_at

        m = self.map.means.astype(np.float64)
        c = np.median(m, axis=0)
        axes = np.linalg.svd(m - c, full_matrices=False)[2]
        target = np.full((k.height, k.width, 3), 0.5, np.float32)
        held_rgb, held_k = downsample(target, k, self.cfg.guard_max_side)
        rows = []
        y0, y1, x0, x1 = tile_bounds(k.height, k.width, self.cfg.tiles)[0]
        k_tile = window_intrinsics(k, y0, y1, x0, x1)
        kd = k_detail or k  # steps fit crops of the full-resolution image when keyframes carry one
        k_crop, crop = random_crop(kd, np.full((kd.height, kd.width, 3), 0.5, np.float32), self.cfg.crop_side, self.rng)
        for d in (axes[0], -axes[0], axes[1], -axes[1]):  # four views around the scene's centre; the median counts
            up = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
            pose = look_at(c, c + d, up)
            t0 = self.clock()
            view = np.flatnonzero(frustum_mask(self.map.means, self.map.log_scales, pose, k))
            t1 = self.clock()
            if not view.size:
                continue
            mt = frustum_mask(self.map.means[view], self.map.log_scales[view], pose, k_tile)
            rasterize(self.map.subset(view[mt]), pose, k_tile, self.bg)
            t2 = self.clock()
            sub = self.map.subset(view)  # the batch's copy (not a step's cost)
            t3 = self.clock()
            m = frustum_mask(sub.means, sub.log_scales, pose, k_crop)
            r = rasterize(sub.subset(m), pose, k_crop, self.bg)
            grads = rasterize_backward(r, (2.0 / crop.size) * (r.color - crop))
            vis = r.visible
            RowAdam(sub, self.cfg.lr).step_rows(
                sub, _Grads(**{p: getattr(grads, p)[vis] for p in _PARAMS}), np.flatnonzero(m)[vis]
            )
            t4 = self.clock()
            view_mse(self.map, pose, held_k, held_rgb, self.bg)
            t5 = self.clock()
            rows.append((t1 - t0, t2 - t1, t4 - t3, t5 - t4))
        if not rows:
            return {}
        cull_s, render_s, step_s, guard_s = (float(v) for v in np.median(np.array(rows), axis=0))
        self.cull_cost.record(cull_s)
        self.render_cost.record(render_s)
        self.step_cost.record(step_s)
        self.step_per_render = step_s / max(render_s, 1e-6)
        self.guard_view_cost.record(guard_s)
        self.guard_prep_cost.record(cull_s)
        return {
            "cull_ms": 1000 * cull_s,
            "tile_render_ms": 1000 * render_s,
            "step_ms": 1000 * step_s,
            "guard_view_ms": 1000 * guard_s,
        }

    def refine(self, kf: Keyframe, deadline: Deadline) -> BatchReport:
        """Run one batch for ``kf`` within one deadline; the map changes only if the batch is committed.

        Optional work (a step, the ONNX seeder) is skipped when it would not end before the deadline with the
        guard's reserve kept; required work (the first render, the guard and commit) that would not fit
        abandons the batch ('no_time'). :class:`edge.refine.worker.RefineWorker` drives the same batch over
        several frames' windows instead.
        """
        rep = BatchReport(name=kf.name, outcome="no_time")
        gen = self.batch(kf, rep)
        try:
            kind, est, reserve = next(gen)
            while True:
                ok = deadline.allows(est.predict(), reserve)
                if not ok and kind == "must":
                    return self.abandon(gen, rep)
                if not ok and kind == "step":
                    rep.stopped_by_deadline = True
                kind, est, reserve = grant(gen, ok, est, self.clock)
        except StopIteration:
            return rep

    def abandon(self, gen, rep: BatchReport) -> BatchReport:
        """Close a batch that ran out of time before its required work; the map is unchanged."""
        gen.close()
        rep.outcome = "no_time"
        self.totals["no_time"] += 1
        self._count(rep)
        return rep

    def batch(self, kf: Keyframe, rep: BatchReport):
        """One keyframe's batch as a generator of work requests.

        Yields (kind, the CostEstimate of the piece, seconds to keep after it) before each piece of work and receives
        whether to do it: kind 'must' (the batch cannot go on without it), 'step' (one optimisation step;
        False ends the optimisation), 'option' (the ONNX seeder; False seeds from SCR coordinates). Fills
        ``rep``; the map changes only in the last piece, the commit. Steps: look at the map from the keyframe
        (render, align the pose, check it), seed what is missing, set up the batch's copy, optimise it, guard,
        commit.
        """
        _check_keyframe(kf)
        self.totals["keyframes"] += 1
        t_start = self.clock()
        view = yield from self._look(kf, rep)
        if view is not None:
            new = yield from self._seed(view, rep)
            work = yield from self._set_up(view, new)
            if work is None:
                rep.outcome = "empty"
            else:
                yield from self._optimise(view, work, rep)
                rollback = yield from self._guard(view, work, rep)
                if rollback is None:
                    yield from self._commit(view, work, rep)
                else:
                    rep.outcome = rollback
                    self.totals["rolled_back"] += 1
                    self.totals["rolled_back_view"] += rollback == "rolled_back_view"
                    self._count(rep)
        rep.ms["total"] = 1000.0 * (self.clock() - t_start)
        return rep

    def _look(self, kf: Keyframe, rep: BatchReport):
        """What the map shows from the keyframe and where it falls short, from the pose aligned to the map where it
        covers the view; None (``rep`` says why) when the keyframe's pose is taken for wrong."""
        cfg, clock = self.cfg, self.clock
        kf_px = kf.k.width * kf.k.height
        yield ("must", self.cull_cost, self.guard_reserve(kf_px) + 2 * self.kf_check_reserve())
        # Rendered tile by tile: each tile is a piece of work small enough for one frame's window.
        t0 = clock()
        reserve = self.guard_reserve(kf_px) + self.kf_check_reserve()
        in_view, color, alpha, seen, an = yield from self._analyse(kf, reserve)
        rep.ms["render"] = 1000.0 * (clock() - t0)
        # Where the map covers the view, the pose is corrected against it and the analysis redone from the
        # corrected pose. New territory keeps the localizer's pose.
        if cfg.align and an.coverage >= RENDER_ALIGN.min_coverage:
            t0 = clock()
            al = yield from self._align(kf)
            rep.align, rep.align_shift_m, rep.align_shift_deg = al.status, al.shift_m, al.shift_deg
            if al.status == "too_far" or (al.status == "no_fit" and an.mse <= RENDER_ALIGN.max_mse):
                # The map covers and explains the view, yet the frame's pose disagrees with it or no pose fits the
                # flow: fitting the map to it would smear it. A view the map explains poorly (new territory seen
                # from afar) keeps the localizer's pose: there the map has more to gain than a few centimetres can
                # spoil (bench/refine.md).
                rep.outcome = "rolled_back_pose"
                rep.mse_before, rep.coverage = an.mse, an.coverage
                self.totals["rolled_back"] += 1
                rep.ms["align"] = 1000.0 * (clock() - t0)
                return None
            if al.status == "aligned":
                kf = replace(kf, pose=al.pose)
                yield ("must", self.cull_cost, 0.0)
                in_view, color, alpha, seen, an = yield from self._analyse(kf, reserve)
            rep.ms["align"] = 1000.0 * (clock() - t0)
        rep.mse_before, rep.coverage = an.mse, an.coverage
        if self.stepless_batches:
            # No step ran lately, so the step estimate is stale; what a tile's render cost implies stands in for a step.
            self.step_cost.record(self.step_per_render * self.render_cost.predict() / self.render_cost.safety)
        if self._pose_disagrees(kf, color, alpha, rep):
            rep.outcome = "rolled_back_pose"
            self.totals["rolled_back"] += 1
            return None
        return _View(kf, kf_px, in_view, seen, an)

    def _align(self, kf: Keyframe):
        """The keyframe's pose aligned to the map (acesplat.align.flow_pnp.Alignment), from a render at the
        alignment's size."""
        cfg = self.cfg
        yield ("must", self.cull_cost, 0.0)
        k_al, img = _align_image(kf, cfg.align_side)
        near = np.flatnonzero(frustum_mask(self.map.means, self.map.log_scales, kf.pose, k_al))
        c_al, a_al, _, d_al = yield from self._render_tiles(
            self.map, kf.pose, k_al, 0.0, near, cfg.align_tiles, self.align_render_cost
        )
        yield ("must", self.align_cost, 0.0)
        al_cfg = replace(RENDER_ALIGN, max_shift_m=cfg.align_max_m, max_shift_deg=cfg.align_max_deg)
        al = align_to_render(c_al, a_al, d_al, img, k_al, kf.pose, al_cfg)
        return al

    def _pose_disagrees(self, kf: Keyframe, color: np.ndarray, alpha: np.ndarray, rep: BatchReport) -> bool:
        """Unless the pose was aligned to the map, a keyframe whose error where the map covers it is far above recent
        keyframes' is taken for a wrong pose (fills ``rep.covered_mse`` when the map covers enough of the view)."""
        covered = alpha >= self.cfg.alpha_min
        if covered.mean() < POSE_CHECK_MIN_COVERAGE:
            return False
        d = np.asarray(color, np.float32)[covered] - kf.rgb[covered]
        rep.covered_mse = float(np.mean(d * d))
        return (
            rep.align != "aligned"
            and len(self.covered_history) >= POSE_CHECK_MIN_HISTORY
            and rep.covered_mse > POSE_CHECK_FACTOR * float(np.median(self.covered_history))
        )

    def _seed(self, view: _View, rep: BatchReport):
        """New Gaussians where the map is missing or wrong: the primary seeder (the ONNX initializer: adapter + head)
        only when it fits, else the SCR seeder."""
        cfg, clock, kf = self.cfg, self.clock, view.kf
        room = max(0, min(cfg.max_new, self.cap - self.count()))
        new = Gaussians.empty(self.map.sh_degree)
        if room and view.an.need.any():  # nothing to seed: no piece (an empty run would spoil the seeders' estimates)
            primary = self.seeder is not self.scr_seeder and (
                yield ("option", self.seed_cost, self.guard_reserve(view.kf_px) + self.kf_check_reserve())
            )
            if not primary:
                yield ("must", self.scr_seed_cost, 0.0)
            t0 = clock()
            seeder = self.seeder if primary else self.scr_seeder
            new = seeder(kf, view.an.need, room, self.map.sh_degree, self.rng)
            new = (
                new.with_sh_degree(self.map.sh_degree).astype(np.float32)
                if len(new)
                else Gaussians.empty(self.map.sh_degree)
            )
            rep.seeded_by = "primary" if primary else "scr"
            rep.ms["seed"] = 1000.0 * (clock() - t0)
        return new

    def _set_up(self, view: _View, new: Gaussians):
        """The batch's private copy (the map's rows the keyframe sees, then ``new``) and its optimiser state: a piece
        of its own (copies of every row in view); None when there is nothing to optimise."""
        yield ("must", self.setup_cost, 0.0)
        active_idx = view.in_view[view.seen]
        active = concat_gaussians([self.map.subset(active_idx), new])
        if len(active) == 0:
            return None
        # With a full-resolution image each step fits a random crop of it (see RefineConfig.crop_side); the crops'
        # errors are not comparable, so then the keyframe is checked once after the steps instead of keeping the
        # best step.
        crops = view.kf.detail is not None and view.kf.k_detail is not None
        work = _Work(active_idx, active.copy() if not crops else active, active, RowAdam(active, self.cfg.lr), crops)
        return work

    def _optimise(self, view: _View, work: _Work, rep: BatchReport):
        """Adam steps on the batch's copy while they fit before the deadline (keeping the guard's reserve), then
        what became transparent pruned."""
        cfg, clock, kf, active, crops = self.cfg, self.clock, view.kf, work.active, work.crops
        t0 = clock()
        target = np.ascontiguousarray(kf.detail if crops else kf.rgb, np.float32)
        while rep.steps + rep.nonfinite_skipped < cfg.max_steps:
            reserve = self.guard_reserve(view.kf_px) + (0.0 if work.measured and not crops else self.kf_check_reserve())
            if not (yield ("step", self.step_cost, reserve)):
                break
            ts = clock()
            if crops:
                k_step, tgt = random_crop(kf.k_detail, target, cfg.crop_side, self.rng)
                rows = frustum_mask(active.means, active.log_scales, kf.pose, k_step)
                part = active.subset(rows)
            else:
                k_step, tgt, rows, part = kf.k, target, None, active
            r = rasterize(part, kf.pose, k_step, self.bg)
            diff = r.color - tgt
            mse = float(np.mean(diff * diff))
            if not crops:
                work.measured += 1
                if mse < work.best_mse:
                    work.best_mse = mse
                    work.best = active.copy()
                elif mse > DIVERGE * work.best_mse:
                    rep.diverged = True
                    break
            grads = rasterize_backward(r, (2.0 / diff.size) * diff)
            if not all_finite(grads):
                rep.nonfinite_skipped += 1
                continue
            if crops:
                vis = r.visible
                work.opt.step_rows(
                    active, _Grads(**{p: getattr(grads, p)[vis] for p in _PARAMS}), np.flatnonzero(rows)[vis]
                )
            else:
                work.opt.step(active, grads, rows=r.visible)
            rep.step_ms.append(1000.0 * (clock() - ts))
            rep.steps += 1
        rep.ms["optimise"] = 1000.0 * (clock() - t0)
        yield ("must", self.prune_cost, 0.0)
        if crops:
            work.best = active
        self.stepless_batches = 0 if rep.steps else self.stepless_batches + 1
        work.gone = transparent(work.best, cfg.prune_opacity)
        rep.pruned = int(work.gone.sum())
        work.kept = work.best.subset(~work.gone)

    def _guard(self, view: _View, work: _Work, rep: BatchReport):
        """None to commit, else the rollback's outcome: the keyframe must gain, the held keyframes must not lose much,
        and no guarded view (the keyframe at guard resolution, each held keyframe) may end worse than under the
        loaded map (``RefineConfig.view_tolerance_db``), view by view. Each check is its own piece of work, so a
        batch can spread them over several frames' windows. Fills ``rep.mse_after`` and the guarded views' errors."""
        cfg, clock, kf, kept = self.cfg, self.clock, view.kf, work.kept
        is_active = np.zeros(len(self.map), bool)
        is_active[work.active_idx] = True
        guard_s = 0.0
        kf_before, kf_after = rep.mse_before, work.best_mse
        if work.measured == 0:
            # No step measured the keyframe whole (seeding only, or crop steps): render it once more, after (its
            # 'before' is the first render). Only the Gaussians in its view can change its image, so the render
            # needs just those.
            t0 = clock()
            after_map = concat_gaussians([self.map.subset(view.in_view[~view.seen]), kept])
            c_after, _, _, _ = yield from self._render_tiles(after_map, kf.pose, kf.k, 0.0)
            kf_after = float(np.mean((c_after - kf.rgb) ** 2))
            guard_s += clock() - t0
        rep.mse_after = kf_after
        if not kf_after < kf_before:
            rep.ms["guard"] = 1000.0 * guard_s
            return "rolled_back_keyframe"
        # The keyframe joins the guarded views at the commit, so it must end within the bound of the loaded map too.
        t0 = clock()
        kv = _guard_view(kf, cfg.guard_max_side)
        yield from self._loaded_error(kv)
        kv.mse = yield from self._error_after(kv, kept, is_active)
        work.kf_view = kv
        rep.kf_loaded_mse, rep.kf_guard_mse = kv.loaded_mse, kv.mse
        guard_s += clock() - t0
        if kv.mse > loaded_bound(kv.loaded_mse, cfg.view_tolerance_db):
            rep.ms["guard"] = 1000.0 * guard_s
            return "rolled_back_view"
        for hv in self.held:
            # Each held-view render is a piece of its own at guard size, so the checks spread over frames' windows.
            t0 = clock()
            if hv.version != self.version or hv.mse is None:  # its error under the current map
                yield ("must", self.guard_prep_cost, 0.0)
                idx = np.flatnonzero(frustum_mask(self.map.means, self.map.log_scales, hv.pose, hv.k))
                c, _, _, _ = yield from self._guard_render(self.map, hv, idx)
                hv.mse, hv.version = float(np.mean((c - hv.target) ** 2)), self.version
            yield from self._loaded_error(hv)
            rep.held_before.append(hv.mse)
            rep.held_loaded.append(hv.loaded_mse)
            rep.held_after.append((yield from self._error_after(hv, kept, is_active)))
            guard_s += clock() - t0
            if rep.held_after[-1] > rep.held_before[-1] * (1.0 + cfg.held_tolerance) or harmed_views(
                rep.held_after[-1:], rep.held_loaded[-1:], cfg.view_tolerance_db
            ):
                break  # this held view got too much worse: no need to look at the others
        rep.ms["guard"] = 1000.0 * guard_s
        if harmed_views(rep.held_after, rep.held_loaded, cfg.view_tolerance_db):
            return "rolled_back_view"
        if not held_verdict(kf_before, kf_after, rep.held_before, rep.held_after, cfg.held_tolerance):
            return "rolled_back_held"
        return None

    def _loaded_error(self, hv: HeldView):
        """Fill ``hv.loaded_mse`` (its error under the map as loaded) if not known yet: one tiled render."""
        if hv.loaded_mse is not None:
            return
        yield ("must", self.guard_prep_cost, 0.0)
        idx = np.flatnonzero(frustum_mask(self.loaded.means, self.loaded.log_scales, hv.pose, hv.k))
        c, _, _, _ = yield from self._guard_render(self.loaded, hv, idx)
        hv.loaded_mse = float(np.mean((c - hv.target) ** 2))

    def _error_after(self, hv: HeldView, kept: Gaussians, is_active: np.ndarray):
        """The error of guarded view ``hv`` under the map as the commit would leave it: the map's rows the batch did not
        touch plus its ``kept`` ones (``is_active`` (M,) marks the touched rows); no render when nothing the batch
        changed can reach the view (its current error stands)."""
        yield ("must", self.guard_prep_cost, 0.0)
        mine = frustum_mask(kept.means, kept.log_scales, hv.pose, hv.k) if len(kept) else np.zeros(0, bool)
        touched = bool(is_active.any()) and bool(
            np.any(frustum_mask(self.map.means[is_active], self.map.log_scales[is_active], hv.pose, hv.k))
        )
        if not mine.any() and not touched and hv.mse is not None and hv.version == self.version:
            return hv.mse
        rest = np.flatnonzero(frustum_mask(self.map.means, self.map.log_scales, hv.pose, hv.k) & ~is_active)
        g = concat_gaussians([self.map.subset(rest), kept.subset(mine)])
        c, _, _, _ = yield from self._guard_render(g, hv)
        return float(np.mean((c - hv.target) ** 2))

    def _guard_render(self, g: Gaussians, hv: HeldView, idx: np.ndarray | None = None):
        """``g`` (its rows ``idx`` when given) rendered from guarded view ``hv``: one piece at guard size."""
        return (yield from self._render_tiles(g, hv.pose, hv.k, 0.0, idx, tiles=1, cost=self.guard_view_cost))

    def _commit(self, view: _View, work: _Work, rep: BatchReport):
        """The batch's rows replace theirs, new ones join, pruned ones leave, the cap holds; the keyframe becomes a
        held view."""
        cfg, clock, kf = self.cfg, self.clock, view.kf
        yield ("must", self.commit_cost, 0.0)
        t0 = clock()
        best, gone, active_idx = work.best, work.gone, work.active_idx
        n_old = active_idx.size
        self.store.write_rows(active_idx, best.subset(np.arange(n_old)))
        self.store.hide(active_idx[gone[:n_old]])
        added = best.subset(np.flatnonzero(~gone[n_old:]) + n_old)
        self.store.append(added)
        rep.capped = self.store.enforce()
        rep.added = len(added)
        self.version += 1
        kv = work.kf_view
        if kv is None:  # a batch committed without the guard (not the refiner's own path)
            kv = _guard_view(kf, cfg.guard_max_side)
        if rep.capped == 0:  # the guard rendered exactly this map: its 'after' errors are current
            for hv, after in zip(self.held, rep.held_after):
                hv.mse, hv.version = after, self.version
            kv.version = self.version
        else:
            kv.mse = None
        self.held.add(kv)
        rep.outcome = "committed"
        if np.isfinite(rep.covered_mse):
            self.covered_history.append(rep.covered_mse)
        rep.ms["commit"] = 1000.0 * (clock() - t0)
        self.totals["committed"] += 1
        self.totals["gaussians_added"] += rep.added
        self.totals["pruned"] += rep.pruned
        self.totals["capped"] += rep.capped
        self._count(rep)

    @property
    def map(self) -> Gaussians:
        """The map's rows as views (no copy); rows removed since the last compaction render as nothing."""
        return self.store.view

    def count(self) -> int:
        """Gaussians in the map (removed rows awaiting compaction not counted)."""
        return self.store.live_count()

    def snapshot(self) -> Gaussians:
        """A compact copy of the map (for saving and scoring)."""
        return self.store.live()

    def restore_view(self, pose_c2w: np.ndarray, k: Intrinsics) -> tuple[int, int, int]:
        """Put back what refinement changed in one view: every row of the loaded map that reaches the view, as it is
        now or as it was loaded, returns to its loaded values (un-hidden, re-added if compacted away), and every row
        refinement added that reaches the view is hidden. Returns (rows restored, of them brought back after
        pruning or the cap removed them, added rows hidden)."""
        st, n = self.store, self.store.n
        now = frustum_mask(st.view.means, st.view.log_scales, pose_c2w, k)
        origin = st.origin[:n]
        was = np.flatnonzero(frustum_mask(self.loaded.means, self.loaded.log_scales, pose_c2w, k))
        row_of = np.full(len(self.loaded), -1, np.int64)
        has = origin >= 0
        row_of[origin[has]] = np.flatnonzero(has)
        src = np.union1d(origin[now & has], was)
        rows = row_of[src]
        kept = rows >= 0
        st.write_rows(rows[kept], self.loaded.subset(src[kept]))
        revived = int(st.hidden[rows[kept]].sum() + (~kept).sum())
        st.hidden[rows[kept]] = False
        new_rows = np.flatnonzero(now & ~has & ~st.hidden[:n])
        st.hide(new_rows)
        if not kept.all():
            st.append(self.loaded.subset(src[~kept]), origin=src[~kept])
        self.version += 1
        return int(src.size), revived, int(new_rows.size)

    def restore_all(self) -> None:
        """The map back to exactly the map as loaded."""
        self.store = GaussianStore(self.loaded, self.cap)
        self.version += 1

    def kf_check_reserve(self) -> float:
        """Time for rendering the keyframe whole once (tile by tile): its check after crop steps or seeding."""
        return len(tile_bounds(1 << 16, 1 << 16, self.cfg.tiles)) * self.render_cost.predict()

    def _analyse(self, kf: Keyframe, reserve: float):
        """Cull the map to the keyframe's view and render it there (tiled); returns (in_view (M,) rows, color, alpha,
        seen (M,), the RenderAnalysis). The first piece (the cull) was granted by the caller."""
        in_view = (
            np.flatnonzero(frustum_mask(self.map.means, self.map.log_scales, kf.pose, kf.k))
            if len(self.map)
            else np.zeros(0, np.int64)
        )
        color, alpha, seen, _ = yield from self._render_tiles(self.map, kf.pose, kf.k, reserve, in_view)
        an = analyse_render(color, alpha, kf.rgb, self.cfg.alpha_min, self.cfg.error_max)
        return in_view, color, alpha, seen, an

    def _render_tiles(
        self,
        g: Gaussians,
        pose: np.ndarray,
        k: Intrinsics,
        reserve: float,
        idx: np.ndarray | None = None,
        tiles: int | None = None,
        cost: CostEstimate | None = None,
    ):
        """Render ``g`` (only its rows ``idx`` (M,) int when given) tile by tile (``tiles`` x ``tiles``, default the
        config's), each tile a required piece of work predicted by ``cost`` (default a keyframe tile's); returns
        (color (H, W, 3), alpha (H, W), seen (M,) which rows any tile drew, depth (H, W)). The same pixels as one
        render of the whole image."""
        idx = np.arange(len(g)) if idx is None else np.asarray(idx, np.int64)
        cost = self.render_cost if cost is None else cost
        color = np.empty((k.height, k.width, 3), np.float32)
        alpha = np.zeros((k.height, k.width), np.float32)
        depth = np.zeros((k.height, k.width), np.float32)
        seen = np.zeros(idx.size, bool)
        for y0, y1, x0, x1 in tile_bounds(k.height, k.width, tiles or self.cfg.tiles):
            yield ("must", cost, reserve)
            kt = window_intrinsics(k, y0, y1, x0, x1)
            m = frustum_mask(g.means[idx], g.log_scales[idx], pose, kt) if idx.size else np.zeros(0, bool)
            if m.any():
                r = rasterize(g.subset(idx[m]), pose, kt, self.bg)
                color[y0:y1, x0:x1], alpha[y0:y1, x0:x1], depth[y0:y1, x0:x1] = r.color, r.alpha, r.depth
                seen[np.flatnonzero(m)[r.visible]] = True
            else:
                color[y0:y1, x0:x1] = self.bg.astype(np.float32)
        return color, alpha, seen, depth

    def guard_reserve(self, kf_pixels: int) -> float:
        """Time kept for the pruning after the steps, the guard (renders at guard size, each after its culls: the
        keyframe under the loaded map and after; one per held view, one more when its cached error is stale, one more
        when its loaded error is unknown) and the commit."""
        renders = 2 + sum(1 + (h.version != self.version or h.mse is None) + (h.loaded_mse is None) for h in self.held)
        per_render = self.guard_view_cost.predict() + self.guard_prep_cost.predict()
        return renders * per_render + self.prune_cost.predict() + self.commit_cost.predict()

    def _count(self, rep: BatchReport) -> None:
        self.totals["steps"] += rep.steps
        self.totals["nonfinite_skipped"] += rep.nonfinite_skipped


def _align_image(kf: Keyframe, side: int) -> tuple[Intrinsics, np.ndarray]:
    """The keyframe at the pose alignment's resolution: its full-resolution image brought to longer side ``side``
    (its refinement-size image when it has no other)."""
    if kf.detail is None or kf.k_detail is None:
        return kf.k, kf.rgb
    k = kf.k_detail
    s = min(1.0, side / max(k.width, k.height))
    if s >= 1.0:
        return k, kf.detail
    w, h = max(1, int(round(k.width * s))), max(1, int(round(k.height * s)))
    return k.resized(w, h), cv2.resize(kf.detail, (w, h), interpolation=cv2.INTER_AREA)


def _guard_view(kf: Keyframe, max_side: int) -> HeldView:
    """The keyframe as a guarded view: its full-resolution image (its refinement-size one when it has no other)
    brought to longer side ``max_side`` at most, so the guard sees the detail the crop steps fit."""
    rgb, k = (kf.detail, kf.k_detail) if kf.detail is not None and kf.k_detail is not None else (kf.rgb, kf.k)
    small_rgb, small_k = downsample(rgb, k, max_side)
    return HeldView(np.array(kf.pose, np.float64), small_k, np.ascontiguousarray(small_rgb, np.float32), kf.name)


def random_crop(k: Intrinsics, image: np.ndarray, side: int, rng: np.random.Generator) -> tuple[Intrinsics, np.ndarray]:
    """A random window of ``image`` (H, W, 3) with the aspect of ``k`` and longer side ``side`` (at most the image),
    and the intrinsics that render exactly that window."""
    s = min(1.0, side / max(k.width, k.height))
    w, h = max(1, int(round(k.width * s))), max(1, int(round(k.height * s)))
    x0, y0 = int(rng.integers(0, k.width - w + 1)), int(rng.integers(0, k.height - h + 1))
    return window_intrinsics(k, y0, y0 + h, x0, x0 + w), image[y0 : y0 + h, x0 : x0 + w]


_PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh")


class _Grads:
    """Gradients of some rows of a Gaussian set (what RowAdam reads)."""

    def __init__(self, **arrays: np.ndarray) -> None:
        self.__dict__.update(arrays)


def tile_bounds(height: int, width: int, tiles: int) -> list[tuple[int, int, int, int]]:
    """(y0, y1, x0, x1) of a ``tiles`` x ``tiles`` grid over an image (empty tiles left out)."""
    ys = np.linspace(0, height, tiles + 1).round().astype(int)
    xs = np.linspace(0, width, tiles + 1).round().astype(int)
    return [
        (int(ys[i]), int(ys[i + 1]), int(xs[j]), int(xs[j + 1]))
        for i in range(tiles)
        for j in range(tiles)
        if ys[i + 1] > ys[i] and xs[j + 1] > xs[j]
    ]


def window_intrinsics(k: Intrinsics, y0: int, y1: int, x0: int, x1: int) -> Intrinsics:
    """Intrinsics rendering exactly the pixels [y0, y1) x [x0, x1) of an image of ``k``."""
    return Intrinsics(k.fx, k.fy, k.cx - x0, k.cy - y0, x1 - x0, y1 - y0)


Request = tuple[str, CostEstimate, float]
"""What a batch yields before a piece of work: (kind, the estimate of its cost, seconds to keep after it)."""


def grant(gen, ok: bool, estimate: CostEstimate, clock: Clock) -> Request:
    """Answer a batch's request (``ok``: the piece may run) and return its next request (StopIteration when the batch
    ends). Granted work is timed up to the next request and recorded in the request's estimate: a piece costs
    everything the batch runs before it asks again."""
    if not ok:
        return gen.send(False)
    t0 = clock()
    try:
        return gen.send(True)
    finally:
        estimate.record(clock() - t0)


def _check_keyframe(kf: Keyframe) -> None:
    if kf.rgb.ndim != 3 or kf.rgb.shape[2] != 3 or kf.rgb.shape[:2] != (kf.k.height, kf.k.width):
        raise ValueError(f"keyframe rgb {kf.rgb.shape} does not match its {kf.k.height}x{kf.k.width} intrinsics")
    if kf.detail is not None and (kf.k_detail is None or kf.detail.shape != (kf.k_detail.height, kf.k_detail.width, 3)):
        raise ValueError(f"keyframe detail image {kf.detail.shape} does not match its intrinsics")
    if np.shape(kf.pose) != (4, 4) or not np.all(np.isfinite(kf.pose)):
        raise ValueError("keyframe pose must be a finite (4, 4) matrix")
