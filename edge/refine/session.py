"""Refinement attached to the edge localizer: frames in, keyframes to the worker, numbers out.

The localizer's code is not modified: ``RefineSession`` wraps the instance's ``localize`` (preempt the
worker, so a batch stops as soon as the next frame's localization begins; after the pose, hand the
frame over) and taps its SCR session for the scene coordinates. Every command that localizes
(localize, replay, profile) thus refines without changes to its loop. A confident frame goes to the
worker with the frame's deadline: its capture start plus the budget.

With ``pace`` (every command) the loop then waits until the worker is idle or the deadline has
passed: refinement gets what localization left of the budget, and a live camera's frames that arrive
meanwhile are dropped and counted by its source (the latest wins). Before the next localization the
worker is preempted and its running piece (predicted to end by the deadline) is waited for, so no
refinement code runs beside inference and PnP; a piece that overran shows as that frame's 'park'
time, inside its localization latency. Without ``pace`` (bench_refine's 'unpaced' setting only) the
worker runs beside back-to-back localizations at a lower priority: measured there, localization p95
rose 1.33x, which is why the commands pace.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from acesplat.core.camera import Intrinsics
from acesplat.core.gaussians import Gaussians
from acesplat.core.metrics import timing_stats
from acesplat.core.pose import TrackingState
from edge.frame_prep import crop_to_aspect
from edge.refine.deadline import Clock
from edge.refine.guard import psnr, render_view, view_mse
from edge.refine.keyframes import KeyframePolicy, KeyframeSelector
from edge.refine.persist import SAVE_EVERY_S, SplatSaver
from edge.refine.refiner import Keyframe, RefineConfig, Refiner
from edge.refine.seeding import cell_trust
from edge.refine.worker import NICE, Candidate, RefineWorker

MAX_SIDE = 80
"""Refinement renders at this longer side. Measured on 2 busy cores with a 45k-Gaussian map (SH degree 3):
a render took 15-45 ms at 160x120 and 10-27 ms at 80x60, beside 45-60 ms of localization in a 100 ms budget."""


PARK_TIMEOUT_S = 1.0
"""Longest a paced localization waits for the worker's running piece (pieces are predicted to end in their window;
this bounds a misprediction)."""


MARGIN = 0.0
"""Share of the budget before the next frame is due at which refinement stops (pieces predicted from recent runs can
take twice as long on a loaded machine). Measured at load ~3.3 with 0.1: demo test split at 200 ms, the wait of the
next localization for a running piece fell from p95 8-11 ms to ~0 (2 runs each); half-trajectory replay at 100 ms
(2 runs each), it was ~0 either way while commits fell 9-14 -> 6-9 and PSNR 17.09-17.45 -> 16.82-17.14 dB."""


@dataclass
class RefineOptions:
    budget_ms: float = 100.0
    max_side: int = MAX_SIDE
    save_path: Path | None = None
    save_every_s: float = SAVE_EVERY_S
    margin: float = MARGIN
    """Share of the budget left free at its end (see MARGIN)."""
    pace: bool = True
    """Wait for the worker (or the deadline) after each frame; False only for bench_refine's comparison."""
    evaluate: bool = False
    """Keep each frame with a ground-truth pose to report PSNR before/after (replay)."""
    raster_threads: int | None = 1
    """Rasterizer threads (None: all cores). One keeps all refinement work on the worker's low-priority thread."""
    use_initializer: bool = True
    """Seed through the bundle's ONNX initializer when it has one (else from SCR coordinates alone)."""
    config: RefineConfig = field(default_factory=RefineConfig)
    policy: KeyframePolicy = field(default_factory=KeyframePolicy)

    def __post_init__(self) -> None:
        if not self.budget_ms > 0:
            raise ValueError(f"budget must be positive, got {self.budget_ms} ms")
        if not 0.0 <= self.margin < 1.0:
            raise ValueError(f"margin must be in [0, 1), got {self.margin}")
        if self.max_side < 8:
            raise ValueError(f"refinement size must be at least 8 px, got {self.max_side}")


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


class _SessionTap:
    """Stands in for the localizer's SCR session: keeps each frame's coordinates (and, for the ONNX initializer,
    the encoder features the same run output) for the keyframe."""

    def __init__(self, inner: Any, session: RefineSession, features: bool) -> None:
        self._inner = inner
        self._session = session
        self._features = features

    def run(self, gray: np.ndarray) -> np.ndarray:
        if self._features:
            coords, feats = self._inner.run_with_features(gray)
        else:
            coords, feats = self._inner.run(gray), None
        self._session._last_coords = coords
        self._session._last_features = feats
        return coords

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


class RefineSession:
    """Refinement beside an :class:`edge.runtime.EdgeLocalizer` (``attach`` installs the taps)."""

    def __init__(
        self,
        localizer: Any,
        gaussians: Gaussians,
        opts: RefineOptions,
        seeder: Callable | None = None,
        clock: Clock = time.perf_counter,
    ) -> None:
        self.opts = opts
        self.clock = clock
        self.initial = gaussians.astype(np.float32)
        self._raster_threads_before: int | None = None
        if opts.raster_threads is not None:
            from acesplat.raster import get_num_threads, set_num_threads

            self._raster_threads_before = get_num_threads()
            set_num_threads(opts.raster_threads)
        # BLAS on one thread while refining: OpenBLAS's workers busy-wait after each call, so the worker's numpy
        # work left them spinning on both cores into the next localization (demo workdir, 200 ms, two inference
        # threads: localization p95 1.6-1.9x without refinement's; with BLAS on one thread 0.94-1.07x).
        self._blas_limits = [threadpool_limits(limits=1, user_api="blas")]
        try:
            self.refiner = Refiner(self.initial.copy(), opts.config, seeder=seeder, clock=clock)
            h, w = getattr(localizer, "input_size", (3 * opts.max_side // 4, opts.max_side))
            k_in = Intrinsics.from_focal(float(w), int(w), int(h))
            self.calibration_ms = self.refiner.warm_up(refine_intrinsics(k_in, opts.max_side), k_in)
            # Compiling the kernels can load another BLAS (numba's, through scipy) after the first limit: hold it too.
            self._blas_limits.append(threadpool_limits(limits=1, user_api="blas"))
            timing = getattr(seeder, "time_once", None)
            if timing is not None:  # measure the ONNX initializer (adapter + head) before it competes for a deadline
                self.calibration_ms["initializer_ms"] = 1000.0 * timing(self.refiner.seed_cost)
        except BaseException:  # a session that never started must not leave the process on one BLAS thread
            self._restore_thread_limits()
            raise
        self.saver = SplatSaver(opts.save_path, opts.save_every_s) if opts.save_path else None
        # Paced: the worker never runs beside localization (parked), so it need not yield the CPU to it.
        self.worker = RefineWorker(
            self.refiner, KeyframeSelector(opts.policy), self.saver, clock, nice=0 if opts.pace else NICE
        )
        self.frames = 0
        self.wait_ms: list[float] = []
        self.park_ms: list[float] = []
        """Per frame: how long its localization waited for the worker's running piece (paced sessions)."""
        self.counts_over_time: list[tuple[int, int]] = [(0, len(self.initial))]
        self._eval: list[tuple[np.ndarray, Intrinsics, np.ndarray]] = []
        self._last_coords: np.ndarray | None = None
        self._last_features: np.ndarray | None = None
        self._closed = False
        self.summary: dict | None = None
        self.seeder_name = "scr" if seeder is None else "custom"
        wants_features = bool(getattr(seeder, "needs_features", False))
        localizer.session = _SessionTap(localizer.session, self, wants_features)
        inner = localizer.localize

        def localize(frame, *args, **kwargs):
            self.worker.preempt()
            if opts.pace:  # let the worker finish its piece first: nothing of refinement runs beside localization
                t0 = self.clock()
                self.worker.wait_parked(PARK_TIMEOUT_S)
                self.park_ms.append(1000.0 * (self.clock() - t0))
            self._last_coords = self._last_features = None
            out = inner(frame, *args, **kwargs)
            if not self._closed:
                self.on_outcome(frame, out)
            return out

        localizer.localize = localize

    def on_outcome(self, frame: Any, out: Any) -> None:
        """Offer a localized frame to the worker; with pacing, wait for the worker or the frame's deadline."""
        self.frames += 1
        coords, feats = self._last_coords, self._last_features
        image, intr, dist, k_input = frame.image, frame.intrinsics, frame.distortion, out.intrinsics
        if k_input is None:
            return
        k_ref = refine_intrinsics(k_input, self.opts.max_side)
        if self.opts.evaluate and out.gt_pose is not None:  # scored at the network input size, not the refinement size
            self._eval.append(
                (np.asarray(out.gt_pose, np.float64), k_input, colour_at(image, intr, dist, k_input, k_input))
            )
        total_ms = float(out.times_ms.get("total", 0.0))
        # Refinement's pieces end a margin before the next frame: a piece that runs longer than predicted then
        # still ends before the next localization instead of delaying it.
        frame_end = self.clock() - total_ms / 1000.0 + self.opts.budget_ms / 1000.0
        deadline_at = frame_end - self.opts.margin * self.opts.budget_ms / 1000.0
        rec = out.record
        tracking = rec.state == TrackingState.TRACKING
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
        if self.opts.pace:
            t0 = self.clock()
            self.worker.wait_idle(max(0.0, frame_end - self.clock()))
            self.wait_ms.append(1000.0 * (self.clock() - t0))
        self.counts_over_time.append((self.frames, self.refiner.count()))

    def _restore_thread_limits(self) -> None:
        if self._raster_threads_before is not None:
            from acesplat.raster import set_num_threads

            set_num_threads(self._raster_threads_before)
        for limit in reversed(self._blas_limits):
            limit.restore_original_limits()

    def close(self) -> dict:
        """Stop the worker (saving the map if asked) and return the ``refine`` report."""
        if self._closed:
            return self.summary or {}
        self._closed = True
        self.worker.close()
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
            "selection": dict(self.worker.selector.counts),
            "gaussians_initial": len(self.initial),
            "gaussians_added": t["gaussians_added"],
            "gaussians_pruned": t["pruned"],
            "gaussians_capped": t["capped"],
            "gaussians_final": self.refiner.count(),
            "gaussian_cap": self.opts.config.cap,
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
                {"kind": k, "predicted_ms": p, "took_ms": t, "late_ms": late} for k, p, t, late in ws.late_pieces[:20]
            ],
            "alignment": {
                k: sum(r.align == k for r in reps) for k in ("aligned", "unlike", "few_points", "no_fit", "too_far")
            },
            "gaussians_over_time": [list(p) for p in self.counts_over_time],
            "errors": ws.errors[:20],
        }
        if self.saver is not None:
            s["save"] = self.saver.as_dict()
        if self._eval:
            bg = np.asarray(self.opts.config.background, np.float64)
            before = [psnr(view_mse(self.initial, p, k, rgb, bg)) for p, k, rgb in self._eval]
            final = self.refiner.snapshot()
            after = [psnr(view_mse(final, p, k, rgb, bg)) for p, k, rgb in self._eval]
            s["psnr_before"] = float(np.mean(before))
            s["psnr_after"] = float(np.mean(after))
            s["psnr_views"] = len(self._eval)
            s["psnr_size"] = [self._eval[0][1].height, self._eval[0][1].width]
        self.summary = s
        return s


def write_before_after(session: RefineSession, out_dir: Path, count: int = 3) -> list[dict]:
    """PNG triptychs (captured frame | map before refinement | map after), rendered from ground-truth poses of the
    evaluated views: the ``count`` views whose PSNR changed most, either way. Returns one record per file."""
    from acesplat.core.atomic import write_bytes

    if not session._eval or count <= 0:
        return []
    bg = np.asarray(session.opts.config.background, np.float64)
    final = session.refiner.snapshot()
    rows = []
    for i, (pose, k, rgb) in enumerate(session._eval):
        before, after = psnr(view_mse(session.initial, pose, k, rgb, bg)), psnr(view_mse(final, pose, k, rgb, bg))
        rows.append((abs(after - before), i, before, after))
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for _, i, before, after in sorted(rows, reverse=True)[:count]:
        pose, k, rgb = session._eval[i]
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
    localizer: Any, bundle: Any, opts: RefineOptions, warn: Callable[[str], None]
) -> RefineSession | None:
    """A session on the bundle's Gaussians, or None (after one line through ``warn``) when the bundle has none."""
    from edge.refine.bundle_models import bundle_gaussians, no_models_message

    g = bundle_gaussians(bundle)
    if g is None:
        warn(no_models_message(bundle))
        return None
    from edge.refine.onnx_seeder import onnx_seeder_for

    seeder = (
        onnx_seeder_for(bundle, threads=1, spacing=opts.config.seed_spacing, warn=warn)
        if opts.use_initializer
        else None
    )
    session_out = getattr(localizer.session, "has_features", True)
    if seeder is not None and not session_out:
        warn(f"{bundle.root}: the SCR model has no features output for the initializer; seeding from SCR coordinates")
        seeder = None
    session = RefineSession(localizer, g, opts, seeder=seeder)
    session.seeder_name = "onnx_initializer" if seeder is not None else "scr"
    return session
