"""Refinement beside the edge localizer, as one of its taps: frames in, keyframes to the worker, numbers out.

Every command that localizes (localize, replay, profile) refines through the same tap. With ``pace`` (every
command) the localizer holds each frame until the worker is idle or the frame's budget has passed, and the worker
is parked before the next localization, so no refinement code runs beside inference and PnP; a piece that overran
shows as that frame's 'park' time, inside its localization latency. Without ``pace`` (bench_refine's 'unpaced'
setting only) the worker runs beside back-to-back localizations at a lower priority (bench/refine.md).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from acesplat.core.bundle import Bundle
from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob
from acesplat.core.gaussians import Gaussians
from acesplat.core.metrics import timing_stats
from acesplat.core.pose import TrackingState
from acesplat.splatcore.validity import cell_trust
from edge.frame_prep import crop_to_aspect
from edge.refine.deadline import Clock, CostEstimate
from edge.refine.guard import psnr, render_view, view_mse
from edge.refine.keyframes import KeyframePolicy, KeyframeSelector
from edge.refine.persist import SplatSaver
from edge.refine.refiner import Keyframe, RefineConfig, Refiner
from edge.refine.witness import Witness, WitnessPool, repair, spread
from edge.refine.worker import NICE, Candidate, RefineWorker
from edge.runtime import EdgeLocalizer, FrameOutcome, FrameTap
from edge.sources import SourceFrame

ROLLBACKS = ("rolled_back_pose", "rolled_back_keyframe", "rolled_back_held", "rolled_back_view")
"""The outcomes of a batch that was not committed (edge.refine.refiner.BatchReport), counted in the report."""
PARK_TIMEOUT_S = 1.0
"""Longest a paced localization waits for the worker's running piece (pieces are predicted to end in their window;
this bounds a misprediction)."""


@dataclass
class RefineOptions:
    """How refinement runs beside the localizer (the edge commands' --refine)."""

    budget_ms: float = knob(100.0, "Per-frame time of localization + refinement (ms).")
    max_side: int = knob(80, "Longer side refinement renders at (px); bench/refine.md has the render times.")
    save_path: Path | None = knob(None, "Write the refined Gaussians here (PLY); None: keep them in memory.")
    save_every_s: float = knob(30.0, "Seconds between periodic saves of the refined map.")
    margin: float = knob(0.0, "Share of the budget left free at its end (bench/refine.md).")
    pace: bool = knob(True, "Hold each frame for the worker up to its budget; False only for bench_refine.")
    evaluate: bool = knob(False, "Keep each frame with a ground-truth pose to report PSNR before/after (replay).")
    raster_threads: int | None = knob(1, "Rasterizer threads (None: all cores); one keeps refinement on its thread.")
    use_initializer: bool = knob(True, "Seed through the bundle's ONNX initializer when it has one.")
    witnesses: int = knob(64, "Tracked frames kept to prove at the end that refinement lowered none (0: no check).")
    witness_side: int = knob(320, "Longer side the witnesses are checked at: the loss shows at full size (px).")
    witness_tolerance_db: float = knob(0.0, "PSNR a witness may lose before its view is restored (dB).")
    pinned_witnesses: int = knob(
        32, "Mapping images (a bundle exported with --keyframes) also held as witnesses, spread over the viewpoints."
    )
    config: RefineConfig = knob(reason="What one keyframe's batch may do.", factory=RefineConfig)
    policy: KeyframePolicy = knob(reason="Which frames become keyframes.", factory=KeyframePolicy)

    def __post_init__(self) -> None:
        if not self.budget_ms > 0:
            raise ValueError(f"budget must be positive, got {self.budget_ms} ms")
        if not 0.0 <= self.margin < 1.0:
            raise ValueError(f"margin must be in [0, 1), got {self.margin}")
        if self.max_side < 8:
            raise ValueError(f"refinement size must be at least 8 px, got {self.max_side}")
        if (
            self.witnesses < 0
            or self.pinned_witnesses < 0
            or self.witness_side < 8
            or not self.witness_tolerance_db >= 0
        ):
            raise ValueError(
                f"witnesses must be >= 0, their side >= 8 px and their tolerance >= 0 dB, got {self.witnesses}, "
                f"{self.witness_side}, {self.witness_tolerance_db}"
            )


def refine_intrinsics(k_input: Intrinsics, max_side: int) -> Intrinsics:
    s = min(1.0, max_side / max(k_input.width, k_input.height))
    return k_input.resized(max(1, int(round(k_input.width * s))), max(1, int(round(k_input.height * s))))


def colour_at(
    image: np.ndarray, intr: Intrinsics, dist: np.ndarray | None, k_input: Intrinsics, k_out: Intrinsics
) -> np.ndarray:
    """The captured image brought to ``k_out`` the way frame preparation brings it to the network input
    (undistort, centre crop to the input's aspect, resize), as float32 RGB in [0, 1]."""
    rgb = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
    if dist is not None and np.any(np.asarray(dist) != 0):
        rgb = cv2.undistort(rgb, intr.K, np.asarray(dist, np.float64))
    rgb, _ = crop_to_aspect(rgb, intr, k_input.width / k_input.height)
    if rgb.shape[:2] != (k_out.height, k_out.width):
        shrink = k_out.height < rgb.shape[0]
        rgb = cv2.resize(rgb, (k_out.width, k_out.height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    return rgb.astype(np.float32) / 255.0


class InitializerSeeder(Protocol):
    """A seeder beside the SCR one (edge.refine.onnx_seeder.OnnxSeeder): what a session needs of it."""

    needs_features: bool
    """It reads the keyframe's encoder features (the localizer's graph must output them)."""

    def time_once(self, estimate: CostEstimate | None = None) -> float:
        """Seconds of one run, measured now (recorded into ``estimate``)."""
        ...

    def __call__(
        self, kf: Keyframe, need: np.ndarray, max_new: int, sh_degree: int, rng: np.random.Generator
    ) -> Gaussians: ...


class RefineSession(FrameTap):
    """Refinement beside an :class:`edge.runtime.EdgeLocalizer`, as one of its taps (``localizer.add_tap``).

    Before each localization the worker is preempted (with pacing: its running piece is waited for); after it, a
    confident frame goes to the worker with the frame's deadline (its capture start plus the budget). With pacing
    the localizer then holds the frame until the worker is idle or the budget has passed.
    """

    def __init__(
        self,
        input_size: tuple[int, int],
        gaussians: Gaussians,
        opts: RefineOptions,
        seeder: InitializerSeeder | None = None,
        clock: Clock = time.perf_counter,
    ) -> None:
        """``input_size`` (H, W): the localizer's network input, the keyframes' full resolution."""
        if len(input_size) != 2 or min(input_size) < 1:
            raise ValueError(f"input size must be (H, W) positive, got {input_size}")
        self.opts = opts
        self.clock = clock
        self.initial = gaussians.astype(np.float32)
        self.needs_features = seeder is not None and seeder.needs_features
        self.pace_ms = opts.budget_ms if opts.pace else None
        self._raster_threads_before: int | None = None
        if opts.raster_threads is not None:
            from acesplat.raster import get_num_threads, set_num_threads

            self._raster_threads_before = get_num_threads()
            set_num_threads(opts.raster_threads)
        # BLAS on one thread while refining: OpenBLAS's workers busy-wait after each call and would keep both cores
        # spinning into the next localization (bench/refine.md).
        self._blas_limits = [threadpool_limits(limits=1, user_api="blas")]
        try:
            self.refiner = Refiner(self.initial.copy(), opts.config, seeder=seeder, clock=clock)
            h, w = input_size
            k_in = Intrinsics.from_focal(float(w), int(w), int(h))
            self.calibration_ms = self.refiner.warm_up(refine_intrinsics(k_in, opts.max_side), k_in)
            # Compiling the kernels can load another BLAS (numba's, through scipy) after the first limit: hold it too.
            self._blas_limits.append(threadpool_limits(limits=1, user_api="blas"))
            if seeder is not None:  # measure the ONNX initializer (adapter + head) before it competes for a deadline
                self.calibration_ms["initializer_ms"] = 1000.0 * seeder.time_once(self.refiner.seed_cost)
        except BaseException:  # a session that never started must not leave the process on one BLAS thread
            self._restore_thread_limits()
            raise
        self.saver = SplatSaver(opts.save_path, opts.save_every_s) if opts.save_path else None
        # Paced: the worker never runs beside localization (parked), so it need not yield the CPU to it.
        self.worker = RefineWorker(
            self.refiner, KeyframeSelector(opts.policy), self.saver, clock, nice=0 if opts.pace else NICE
        )
        self.frames = 0
        self.witness_pool = WitnessPool(opts.witnesses)
        self.repair_report: dict | None = None
        self.wait_ms: list[float] = []
        self.park_ms: list[float] = []
        """Per frame: how long its localization waited for the worker's running piece (paced sessions)."""
        self.counts_over_time: list[tuple[int, int]] = [(0, len(self.initial))]
        self.views: list[tuple[np.ndarray, Intrinsics, np.ndarray]] = []
        """With ``evaluate``: (ground-truth pose (4, 4), intrinsics, RGB (H, W, 3) in [0, 1]) of each frame."""
        self._closed = False
        self.summary: dict | None = None
        self.view_psnr: list[tuple[float, float]] | None = None
        """After ``close`` with ``evaluate``: (PSNR under the loaded map, under the refined map) of each view."""
        self.seeder_name = "scr" if seeder is None else "custom"

    def before_frame(self, frame: SourceFrame) -> None:
        """Preempt the worker, so a batch stops as soon as the next localization begins; with pacing, wait for its
        running piece first: nothing of refinement runs beside localization."""
        self.worker.preempt()
        if self.opts.pace:
            t0 = self.clock()
            self.worker.wait_parked(PARK_TIMEOUT_S)
            self.park_ms.append(1000.0 * (self.clock() - t0))

    def on_frame(self, out: FrameOutcome) -> None:
        """Offer a localized frame to the worker with the frame's deadline."""
        if self._closed or out.frame is None:
            return
        self.frames += 1
        frame, coords, feats = out.frame, out.coords, out.features
        image, intr, dist, k_input = frame.image, frame.intrinsics, frame.distortion, out.intrinsics
        if k_input is None:
            return
        k_ref = refine_intrinsics(k_input, self.opts.max_side)
        if self.opts.evaluate and out.gt_pose is not None:  # scored at the network input size, not the refinement size
            self.views.append(
                (np.asarray(out.gt_pose, np.float64), k_input, colour_at(image, intr, dist, k_input, k_input))
            )
        total_ms = float(out.times_ms.get("total", 0.0))
        # Refinement's pieces end a margin before the next frame: a piece that runs longer than predicted then
        # still ends before the next localization instead of delaying it.
        frame_end = self.clock() - total_ms / 1000.0 + self.opts.budget_ms / 1000.0
        deadline_at = frame_end - self.opts.margin * self.opts.budget_ms / 1000.0
        rec = out.record
        tracking = rec.state == TrackingState.TRACKING
        if tracking and self.opts.witnesses:
            k_w = refine_intrinsics(k_input, self.opts.witness_side)
            rgb_w = colour_at(image, intr, dist, k_input, k_w)
            rgb_w = np.clip(np.asarray(rgb_w, np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
            self.witness_pool.add(Witness(np.array(rec.T_c2w, np.float64), k_w, rgb_w, out.name or str(rec.frame_id)))
        if tracking and rec.inliers >= self.opts.policy.min_inliers and coords is not None:
            pose = np.array(rec.T_c2w, np.float64)
            name = out.name or str(rec.frame_id)

            def make_keyframe() -> Keyframe:
                detail = colour_at(image, intr, dist, k_input, k_input)  # optimisation crops at the input size
                small = cv2.resize(detail, (k_ref.width, k_ref.height), interpolation=cv2.INTER_AREA)
                return Keyframe(pose, small, k_ref, coords, k_input, name, feats, detail, k_input)

            def cell_depth() -> tuple[np.ndarray, Intrinsics]:
                return cell_trust(coords, pose, k_input)[0], k_input

            self.worker.submit(
                Candidate(pose, rec.inliers, tracking, deadline_at, make_keyframe, cell_depth, name, float(rec.quality))
            )
        if not self.opts.pace:
            self.counts_over_time.append((self.frames, self.refiner.count()))

    def hold(self, until: float) -> None:
        """Paced: wait until the worker is idle or ``until`` (perf_counter seconds): refinement gets what
        localization left of the budget (a live camera's frames arriving meanwhile are dropped by the loop)."""
        if self._closed:
            return
        t0 = self.clock()
        self.worker.wait_idle(max(0.0, until - self.clock()))
        self.wait_ms.append(1000.0 * (self.clock() - t0))
        self.counts_over_time.append((self.frames, self.refiner.count()))

    def _repair(self) -> bool:
        """Undo refinement on every witness it left worse (edge/refine/witness.py); True if the map changed."""
        witnesses = self.witness_pool.all()
        if not witnesses:
            return False
        self._restore_thread_limits()  # localization is over: the check may use every core
        self.repair_report = repair(self.refiner, witnesses, self.opts.witness_tolerance_db)
        return bool(self.repair_report["harmed_before"])

    def _restore_thread_limits(self) -> None:
        if self._raster_threads_before is not None:
            from acesplat.raster import set_num_threads

            set_num_threads(self._raster_threads_before)
            self._raster_threads_before = None
        for limit in reversed(self._blas_limits):
            limit.restore_original_limits()
        self._blas_limits = []

    def close(self) -> dict:
        """Stop the worker (saving the map if asked) and return the ``refine`` report."""
        if self._closed:
            return self.summary or {}
        self._closed = True
        self.worker.close(before_save=self._repair)
        self._restore_thread_limits()
        ws = self.worker.stats
        reps = ws.reports
        steps_ms = [ms for r in reps for ms in r.step_ms]
        t = self.refiner.totals
        s: dict = {
            "budget_ms": self.opts.budget_ms,
            "seeder": self.seeder_name,
            "calibration_ms": self.calibration_ms,
            "refine_max_side": self.opts.max_side,
            "frames": self.frames,
            "candidates": ws.candidates,
            "dropped": self.worker.dropped,
            "late": ws.late,
            "keyframes": t["keyframes"],
            "keyframes_committed": t["committed"],
            "keyframes_rolled_back": t["rolled_back"],
            "keyframes_no_time": t["no_time"],
            "rollbacks": {k: sum(r.outcome == k for r in reps) for k in ROLLBACKS},
            "selection": dict(self.worker.selector.counts),
            "gaussians_initial": len(self.initial),
            "gaussians_added": t["gaussians_added"],
            "gaussians_pruned": t["pruned"],
            "gaussians_capped": t["capped"],
            "gaussians_final": self.refiner.count(),
            "gaussian_cap": self.refiner.cap,
            "steps": t["steps"],
            "seeded_by": {k: sum(r.seeded_by == k for r in reps) for k in ("primary", "scr")},
            "nonfinite_skipped": t["nonfinite_skipped"],
            "steps_stopped_by_deadline": int(sum(r.stopped_by_deadline for r in reps)),
            "timing_ms": {
                "window": timing_stats(ws.window_work_ms),
                "candidate_wall": timing_stats(ws.busy_ms),
                "batch": timing_stats([r.ms.get("total", 0.0) for r in reps]),
                "step": timing_stats(steps_ms),
                "render": timing_stats([r.ms["render"] for r in reps if "render" in r.ms]),
                "guard": timing_stats([r.ms["guard"] for r in reps if "guard" in r.ms]),
                "wait": timing_stats(self.wait_ms),
                "park": timing_stats(self.park_ms),
                "overrun": timing_stats(ws.overrun_ms),
                "piece_spill": timing_stats(ws.piece_spill_ms),
            },
            "pieces": len(ws.piece_spill_ms),
            "pieces_past_deadline": int(sum(v > 0 for v in ws.piece_spill_ms)),
            "batches_over_deadline": int(sum(v > 0 for v in ws.overrun_ms)),
            "late_pieces": [
                {"piece": k, "predicted_ms": p, "took_ms": t, "late_ms": late} for k, p, t, late in ws.late_pieces[:20]
            ],
            "alignment": {
                k: sum(r.align == k for r in reps) for k in ("aligned", "unlike", "few_points", "no_fit", "too_far")
            },
            "gaussians_over_time": [list(p) for p in self.counts_over_time],
            "errors": ws.errors[:20],
            "witness": {
                "offered": self.witness_pool.offered,
                "kept": len(self.witness_pool),
                "pinned": len(self.witness_pool.pinned),
                "tolerance_db": self.opts.witness_tolerance_db,
                **(self.repair_report or {}),
            },
        }
        if self.saver is not None:
            s["save"] = self.saver.as_dict()
        if self.views:
            bg = np.asarray(self.opts.config.background, np.float64)
            final = self.refiner.snapshot()
            self.view_psnr = [
                (psnr(view_mse(self.initial, p, k, rgb, bg)), psnr(view_mse(final, p, k, rgb, bg)))
                for p, k, rgb in self.views
            ]
            before, after = (np.array(v, np.float64) for v in zip(*self.view_psnr))
            s["psnr_before"] = float(np.mean(before))
            s["psnr_after"] = float(np.mean(after))
            s["psnr_views"] = len(self.views)
            s["psnr_size"] = [self.views[0][1].height, self.views[0][1].width]
            s.update(harm_report(before, after, self.opts.config.view_tolerance_db))
        self.summary = s
        return s


def harm_report(before: np.ndarray, after: np.ndarray, tolerance_db: float) -> dict:
    """The per-view verdict of a refinement run: ``before``/``after`` (V,) PSNR (dB) of each evaluated view under the
    loaded and the refined map. A view whose PSNR fell more than ``tolerance_db`` is harmed, and one harmed view
    fails the run whatever the average did. Keys: failed, views_harmed, psnr_worst_change_db (None without views),
    harm_tolerance_db, harmed (up to 20 of them, worst first: view index, psnr_before, psnr_after)."""
    before, after = np.asarray(before, np.float64), np.asarray(after, np.float64)
    if before.shape != after.shape or before.ndim != 1:
        raise ValueError(f"per-view PSNR before {before.shape} and after {after.shape} must be matching (V,)")
    with np.errstate(invalid="ignore"):  # inf - inf: a view rendered exactly before and after did not change
        change = np.where(before == after, 0.0, after - before)
    harmed = np.flatnonzero(change < -tolerance_db)
    worst = harmed[np.argsort(change[harmed])]
    return {
        "failed": bool(harmed.size),
        "views_harmed": int(harmed.size),
        "psnr_worst_change_db": float(change.min()) if change.size else None,
        "harm_tolerance_db": float(tolerance_db),
        "harmed": [
            {"view": int(i), "psnr_before": float(before[i]), "psnr_after": float(after[i])} for i in worst[:20]
        ],
    }


def write_before_after(session: RefineSession, out_dir: Path, count: int = 3) -> list[dict]:
    """PNG triptychs (captured frame | map before refinement | map after), rendered from ground-truth poses of the
    evaluated views (after ``close``): the ``count`` views whose PSNR changed most, either way, so a view the
    refinement harmed is shown, not hidden. Returns one record per file."""
    from acesplat.core.atomic import write_bytes

    if not session.views or count <= 0:
        return []
    if session.view_psnr is None:
        raise ValueError("write_before_after needs a closed session")
    bg = np.asarray(session.opts.config.background, np.float64)
    final = session.refiner.snapshot()
    rows = [(abs(after - before), i, before, after) for i, (before, after) in enumerate(session.view_psnr)]
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for _, i, before, after in sorted(rows, reverse=True)[:count]:
        pose, k, rgb = session.views[i]
        panels = [rgb]
        for g in (session.initial, final):
            r = render_view(g, pose, k, bg)
            panels.append(np.broadcast_to(bg.astype(np.float32), rgb.shape) if r is None else r.color)
        strip = np.concatenate([np.clip(p_, 0.0, 1.0) for p_ in panels], axis=1)
        ok, png = cv2.imencode(".png", cv2.cvtColor((strip * 255.0 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR))
        if not ok:
            raise RuntimeError("PNG encoding failed")
        path = out_dir / f"view{i:04d}_frame_before_after.png"
        write_bytes(path, png.tobytes())
        written.append({"path": str(path), "view": i, "psnr_before": before, "psnr_after": after})
    return written


def start_refinement(
    localizer: EdgeLocalizer, bundle: Bundle, opts: RefineOptions, warn: Callable[[str], None]
) -> RefineSession | None:
    """A session on the bundle's Gaussians, registered as a tap of ``localizer``, or None (after one line through
    ``warn``) when the bundle has none."""
    from edge.refine.bundle_models import bundle_gaussians, no_models_message

    g = bundle_gaussians(bundle)
    if g is None:
        warn(no_models_message(bundle))
        return None
    from edge.refine.onnx_seeder import onnx_seeder_for

    seeder = (
        onnx_seeder_for(
            bundle, threads=1, spacing=opts.config.seed_spacing, warn=warn, provider=localizer.session.provider
        )
        if opts.use_initializer
        else None
    )
    if seeder is not None and not localizer.session.has_features:
        warn(f"{bundle.root}: the SCR model has no features output for the initializer; seeding from SCR coordinates")
        seeder = None
    session = RefineSession(localizer.input_size, g, opts, seeder=seeder)
    session.seeder_name = "onnx_initializer" if seeder is not None else "scr"
    for w in mapping_witnesses(bundle, opts.pinned_witnesses, opts.witness_side):
        session.witness_pool.pin(w)
    localizer.add_tap(session)
    return session


def mapping_witnesses(bundle: Bundle, count: int, max_side: int) -> list[Witness]:
    """Up to ``count`` of the mapping images a bundle carries as alignment keyframes (grey, surveyed poses), spread
    over the viewpoints and brought to longer side ``max_side``; none when it carries none."""
    from acesplat.align.keyframe_set import bundle_keyframes
    from acesplat.core.bundle import ROLE_KEYFRAMES

    if count <= 0 or not bundle.has(ROLE_KEYFRAMES):
        return []
    ks = bundle_keyframes(bundle)
    out = []
    for i in spread(list(ks.c2w), count):
        kf = ks.keyframe(i)
        k = refine_intrinsics(kf.intrinsics, max_side)
        gray = kf.gray
        if (k.height, k.width) != gray.shape:
            gray = cv2.resize(gray, (k.width, k.height), interpolation=cv2.INTER_AREA)
        out.append(Witness(np.array(kf.c2w, np.float64), k, np.ascontiguousarray(gray, np.uint8), f"keyframe {i}"))
    return out
