"""Per-frame localization on the edge: prepare, infer, PnP, gate; with a timing for every stage.

Stages (milliseconds): capture (source read and decode), preprocess (gray, undistort, crop,
resize), inference (onnxruntime; 0 on a tracked frame that skips it), pnp (RANSAC + LM + gate), align (with --align:
the pose refined against the bundle's keyframes, acesplat.align.keyframe_align; with tracking: the tracked frame's
alignment, edge.tracking; 0 otherwise) and total (from the start of the capture to the pose, including any wait
between capture and processing).

A frame runs in two phases, ``prepare`` (preprocess, the tracker's plan, inference unless the frame is tracked) and
``solve`` (PnP + gate or the tracked alignment, covariance, record), so a pipeline can run them on two threads.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from acesplat.align.flow_pnp import KEYFRAME_ALIGN, AlignConfig
from acesplat.align.keyframe_align import (
    Keyframe,
    PreciseSettings,
    align_scr_start,
    scene_depth,
    scr_copy,
    size_for_scr,
)
from acesplat.align.keyframe_set import bundle_keyframes
from acesplat.core.bundle import ROLE_KEYFRAMES, Bundle
from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob, knob_default
from acesplat.core.errors import InputError
from acesplat.core.gate import GateConfig, gate_result, mirror_checked
from acesplat.core.geometry import invert_pose
from acesplat.core.grid import grid_correspondences
from acesplat.core.pnp import PnPConfig, PnPResult, solve_from_grid
from acesplat.core.pose import PoseRecord, TrackingState
from acesplat.core.pose_covariance import pose_covariance
from acesplat.core.pose_refine import reprojection
from edge.frame_prep import FramePrep
from edge.inference import ScrSession, SessionSettings
from edge.sources import SourceFrame
from edge.tracking import Plan, Tracker, TrackingConfig, frame_keyframe, track_to_keyframes

STAGES = ("capture", "preprocess", "inference", "pnp", "align", "total")


@dataclass
class FrameOutcome:
    """What one frame produced: the pose record, the raw PnP result, stage timings (ms) and, for the taps, what the
    frame was prepared into and what the network output (``without_data`` drops the arrays)."""

    record: PoseRecord
    result: PnPResult | None
    times_ms: dict[str, float]
    name: str = ""
    gt_pose: np.ndarray | None = None
    intrinsics: Intrinsics | None = None
    """Of the prepared network input (after undistortion, crop and resize)."""
    alignment: str | None = None
    """The alignment's status ('aligned' or why the pose it started from was kept; acesplat.align.flow_pnp.Alignment)
    with --align or tracking; None if not tried."""
    frame: SourceFrame | None = None
    """The frame as captured (image, its intrinsics and distortion)."""
    gray: np.ndarray | None = None
    """The prepared network input (H, W) uint8."""
    coords: np.ndarray | None = None
    """Scene coordinates (h, w, 3) float32 the network predicted."""
    features: np.ndarray | None = None
    """The encoder features (C, h, w) when a tap needs them and the graph outputs them, else None."""
    mode: str = "scr"
    """How the pose was made (edge.tracking.MODES): 'scr', 'tracked' or 'reanchor'."""
    fallback: str | None = None
    """Why a frame that was to be tracked went to SCR (the alignment's status, or 'too_far'); None otherwise."""
    reset: bool = False
    """This re-anchor jumped from the tracked prediction (the record's reset_counter incremented)."""
    retried: bool = False
    """SCR on the smaller copy (PreciseSettings) gave a start the alignment could not take: solved again at the
    bundle's size."""

    def without_data(self) -> FrameOutcome:
        """The same outcome without the per-frame arrays (frame, gray, coords, features): what a summary keeps."""
        return replace(self, frame=None, gray=None, coords=None, features=None)


class FrameTap:
    """Something that receives every frame a localizer processes (``EdgeLocalizer.add_tap``): override what you need.

    Calls, per frame: ``before_frame`` (before preparation starts), ``on_frame`` (with the outcome, before the
    localizer returns it), then, when the localizer paces, ``hold``. ``on_event`` receives the loop's events
    (edge.loop.LoopEvent); ``close`` ends the tap (the owner calls it).
    """

    needs_features: bool = False
    """The tap reads ``FrameOutcome.features`` (the localizer then asks the graph for them when it has them)."""
    pace_ms: float | None = None
    """The tap wants each frame held up to this budget (ms from the frame's capture start) for its own work."""

    def before_frame(self, frame: SourceFrame) -> None:
        """The frame's localization is about to start."""

    def on_frame(self, out: FrameOutcome) -> None:
        """The frame's outcome (with its arrays)."""

    def hold(self, until: float) -> None:
        """With pacing: return when the tap's work for this frame is done or at ``until`` (perf_counter seconds)."""

    def on_event(self, event: Any) -> None:
        """Something that is not a frame (edge.loop.LoopEvent)."""

    def close(self) -> Any:
        """End the tap (flush, join threads); may return a report."""
        return None


@dataclass
class PnPSettings:
    """The edge's PnP solver (acesplat.core.pnp.solve_from_grid)."""

    method: str = knob(knob_default(PnPConfig, "method"), "PnP method (PnPConfig's: bench/pnp_speed.md).")
    min_inliers: int = knob(knob_default(PnPConfig, "min_inliers"), "Inlier floor of TRACKING (PnPConfig's).")
    iterations: int = knob(256, "RANSAC cap: a lost frame costs a third of the desktop's (bench/pnp_choice.md).")
    extra: dict = knob(reason="Further keyword arguments of solve_from_grid.", factory=dict)

    def kwargs(self) -> dict:
        return {"method": self.method, "min_inliers": self.min_inliers, "iterations": self.iterations, **self.extra}

    def config(self) -> PnPConfig:
        """The same settings as a PnPConfig (its defaults for the rest)."""
        return replace(PnPConfig(), **self.kwargs())


class EdgeLocalizer:
    """A bundle's SCR model (FP32 or INT8) plus frame preparation and the shared PnP solver."""

    def __init__(
        self,
        bundle: Bundle,
        precision: str = "fp32",
        threads: int | None = None,
        pnp: PnPSettings | None = None,
        align: bool = False,
        pace_ms: float | None = None,
        provider: str = knob_default(SessionSettings, "provider"),
        gate: GateConfig | None = None,
        tracking: TrackingConfig | None = None,
        align_config: AlignConfig = KEYFRAME_ALIGN,
        scr_short_side: int = knob_default(PreciseSettings, "scr_short_side"),
        spinning: bool = knob_default(SessionSettings, "spinning"),
    ) -> None:
        if pace_ms is not None and not pace_ms > 0:
            raise ValueError(f"pace must be positive, got {pace_ms} ms")
        self.bundle = bundle
        self.precision = precision
        self.input_size = bundle.input_size
        self.stride = bundle.output_stride
        self.session = ScrSession(bundle.scr_model(precision), self.input_size, threads, provider, spinning)
        self.prep = FramePrep(self.input_size)
        self.pnp = pnp or PnPSettings()
        self.gate = gate or GateConfig()
        """When a pose is TRACKING (acesplat.core.gate): the same decision as the desktop's."""
        self.previous: np.ndarray | None = None
        """The last frame's camera-to-world pose if it was TRACKING (the gate's motion check), else None."""
        self.tracker = Tracker(tracking) if tracking is not None and tracking.enabled else None
        """Tracking between frames (edge.tracking), None: every frame solved alone."""
        refined = align or (self.tracker is not None and bundle.has(ROLE_KEYFRAMES))
        self.keyframes = bundle_keyframes(bundle) if refined else None
        """The bundle's keyframes when SCR poses are refined against them: with --align (InputError at start if it
        has none), and while tracking when it has them (re-anchors and fallbacks get the same precise alignment)."""
        self.align_config = align_config
        """How SCR poses are refined against the keyframes (acesplat.align.flow_pnp.AlignConfig)."""
        if self.keyframes is not None and align_config.matcher == "sparse":
            self.keyframes.prepare_corners(align_config.corners)  # at start, not on the first frames near each
        self.track_keyframes = self.keyframes if self.tracker is not None else None
        """The keyframes tracked frames align to; None: the last frame SCR solved is the reference."""
        self.scr_size = self.input_size
        """(H, W) SCR runs at: the bundle's size, or, when the keyframe alignment refines SCR poses and the graph is
        dynamic, the smaller size of PreciseSettings.scr_short_side (frames whose features a tap needs: the
        bundle's size)."""
        if self.keyframes is not None and self.session.dynamic:
            self.scr_size = size_for_scr(self.input_size, scr_short_side)
        self._anchor: Keyframe | None = None
        self._depth: float | None = None
        self.pace_ms = pace_ms
        """Each frame takes at least this long from its capture start (a replay then arrives at a camera's rate)."""
        self.taps: list[FrameTap] = []

    def add_tap(self, tap: FrameTap) -> None:
        """Deliver every frame's outcome (and the loop's events) to ``tap`` from now on, after the taps before it."""
        if not isinstance(tap, FrameTap):
            raise TypeError(f"a tap must be an edge.runtime.FrameTap, got {type(tap).__name__}")
        self.taps.append(tap)

    def notify(self, event: Any) -> None:
        """Hand a loop event (edge.loop.LoopEvent) to every tap. A source that went away ('disconnected') also ends
        tracking and the gate's motion check: the camera may be anywhere when it is back, so its first frame is
        solved by SCR from scratch."""
        if getattr(event, "kind", None) == "disconnected":
            self.previous = None
            if self.tracker is not None:
                self.tracker.lost()
        for tap in self.taps:
            tap.on_event(event)

    def localize(self, frame: SourceFrame, capture_ms: float = 0.0, t_start: float | None = None) -> FrameOutcome:
        """Pose of one frame; ``t_start`` (perf_counter seconds) is when its capture began, for the total.

        The taps see the frame before and after; with pacing (``pace_ms`` or a tap's) the call returns once the
        frame's budget has passed, or once every tap that paces is done with the frame (``FrameTap.hold``).
        """
        for tap in self.taps:
            tap.before_frame(frame)
        out = self._localize(frame, capture_ms, t_start)
        for tap in self.taps:
            tap.on_frame(out)
        self._pace(out)
        return out

    def _pace(self, out: FrameOutcome) -> None:
        holders = [t for t in self.taps if t.pace_ms is not None]
        budgets = [b for b in [self.pace_ms, *(t.pace_ms for t in holders)] if b is not None]
        if not budgets:
            return
        until = time.perf_counter() + (max(budgets) - out.times_ms["total"]) / 1000.0
        if holders:
            for tap in holders:
                tap.hold(until)
        else:
            time.sleep(max(0.0, until - time.perf_counter()))

    def _localize(self, frame: SourceFrame, capture_ms: float, t_start: float | None) -> FrameOutcome:
        return self.solve(self.prepare(frame, capture_ms, t_start))

    def prepare(
        self, frame: SourceFrame, capture_ms: float = 0.0, t_start: float | None = None, infer: bool | None = None
    ) -> Prepared:
        """The first phase of a frame: preprocess, the tracker's plan, inference (skipped on a frame to be tracked
        unless TrackingConfig.infer_tracked or a tap needs features). The plan is made from the tracker's state now:
        run ``solve`` of the previous frame first, or the plan is one frame old.

        ``infer`` given (a pipeline, edge.loop, running this while the previous frame is solved): no plan is made
        here (the tracker is the solving thread's); inference runs if ``infer`` (from ``infer_after``), and ``solve``
        plans the frame, infers it after all if the plan needs it, and drops coordinates the plan does not use."""
        if frame.intrinsics is None:
            raise InputError(None, f"frame {frame.name or frame.frame_id} has no intrinsics: pass --intrinsics FILE")
        t_start = time.perf_counter() - capture_ms / 1000.0 if t_start is None else t_start
        t0 = time.perf_counter()
        gray, intr = self.prep(frame.image, frame.intrinsics, frame.distortion)
        view = None
        if self.scr_size != self.input_size and not self._taps_need_features():
            view = (gray, intr)
            gray, intr = scr_copy(gray, intr, self.scr_size)
        t1 = time.perf_counter()
        times = {"capture": capture_ms, "preprocess": (t1 - t0) * 1000.0, "inference": 0.0}
        if infer is not None:
            p = Prepared(frame, gray, intr, None, t_start, times, view=view)
            if infer:
                self._infer(p)
            return p
        p = Prepared(frame, gray, intr, self._plan(frame.frame_id), t_start, times, view=view)
        if self._needs_coords(p.plan):
            self._infer(p)
        return p

    def _plan(self, frame_id: int | None = None) -> Plan:
        return self.tracker.plan(frame_id) if self.tracker is not None else Plan("scr")

    def _taps_need_features(self) -> bool:
        """Whether a tap asks for every frame's coordinates and features at the bundle's size (e.g. refinement's
        keyframes)."""
        return any(t.needs_features for t in self.taps)

    def _needs_coords(self, plan: Plan) -> bool:
        """Whether a frame planned ``plan`` runs inference: SCR, or a tracked frame whose coordinates are asked for
        (TrackingConfig.infer_tracked, or a tap that needs features)."""
        if plan.mode != "track" or self._taps_need_features():
            return True
        return bool(self.tracker is not None and self.tracker.config.infer_tracked)

    def infer_after(self, plan: Plan | None) -> bool:
        """Whether the frame after one planned ``plan`` will run inference if that frame goes as planned (a pipeline
        infers it ahead while this one is solved); None: no frame in between (the next frame gets the plan of now)."""
        if self.tracker is None:
            return True
        return self._needs_coords(self._plan() if plan is None else self.tracker.plan_after(plan))

    def plan_prepared(self, p: Prepared) -> Plan:
        """The plan of a frame a pipeline prepared ahead (``prepare(..., infer=...)``), made now from the tracker's
        state, as ``prepare`` would have; coordinates inferred ahead that the plan does not use are dropped, so the
        frame is solved as it would be without the pipeline."""
        if p.plan is None:
            p.plan = self._plan(p.frame.frame_id)
            if not self._needs_coords(p.plan):
                p.coords, p.features = None, None
        return p.plan

    def finish(self, p: Prepared) -> FrameOutcome:
        """Solve a frame a pipeline prepared ahead, with the taps and the pacing ``localize`` gives a frame."""
        for tap in self.taps:
            tap.before_frame(p.frame)
        out = self.solve(p)
        for tap in self.taps:
            tap.on_frame(out)
        self._pace(out)
        return out

    def _infer(self, p: Prepared) -> None:
        t1 = time.perf_counter()
        if self.session.has_features and self._taps_need_features():
            p.coords, p.features = self.session.run_with_features(p.gray)
        else:
            p.coords, p.features = self.session.run(p.gray), None
        p.times["inference"] = p.times.get("inference", 0.0) + (time.perf_counter() - t1) * 1000.0

    def solve(self, p: Prepared) -> FrameOutcome:
        """The second phase: the tracked alignment, or PnP + gate (then the re-anchor's alignment), the covariance and
        the pose record."""
        self.plan_prepared(p)
        if p.coords is None and self._needs_coords(p.plan):  # a pipeline did not infer it ahead
            self._infer(p)
        times = {**p.times, "pnp": 0.0, "align": 0.0}
        plan, fallback = p.plan, p.plan.reason  # 'too_far': the prediction moved more than a frame is tracked
        mode = "scr" if plan.mode == "scr" and fallback is None else "reanchor"
        if plan.mode == "track":
            t0 = time.perf_counter()
            al = self._track(p, plan.prediction)
            times["align"] = (time.perf_counter() - t0) * 1000.0
            if al.status == "aligned":
                self.tracker.tracked(al.pose, p.frame.frame_id)
                res = PnPResult(al.pose, al.inliers, al.points, True)
                rec = to_record(p.frame, res, al.covariance, self.tracker.reset_counter)
                self.previous = al.pose
                return self._outcome(p, rec, res, times, "tracked", al.status)
            fallback, mode = al.status, "reanchor"
            if p.coords is None:
                self._infer(p)
                times["inference"] = p.times["inference"]
        pnp = self.pnp.config()
        # A scheduled re-anchor starts from the prediction (RANSAC is skipped only if the prediction explains the
        # cells: acesplat.core.pnp); a fallback or a first frame solves from scratch.
        prior = plan.prediction if plan.mode == "reanchor" and fallback is None else None
        res, cov = self._solve_scr(p, pnp, prior, times)
        status, retried = None, False
        if self.keyframes is not None:

            def resolve(gray: np.ndarray, intr: Intrinsics) -> tuple[PnPResult, np.ndarray]:
                # the smaller copy's start was not close enough: SCR at the bundle's size, then the alignment again
                nonlocal cov
                p.gray, p.intr, p.view = gray, intr, None
                t = time.perf_counter()
                p.coords = self.session.run(p.gray)
                times["inference"] += (time.perf_counter() - t) * 1000.0
                r, cov = self._solve_scr(p, pnp, prior, times)
                return r, p.coords

            t3 = time.perf_counter()
            solving = times["inference"] + times["pnp"]
            res, al, retried = align_scr_start(
                res, p.coords, p.gray, p.intr, self.stride, self.keyframes.near, resolve, self.align_config, p.view
            )
            # the alignment's time, without the full-size solve's (counted as inference and PnP)
            times["align"] += (time.perf_counter() - t3) * 1000.0 - (times["inference"] + times["pnp"] - solving)
            if al is not None:
                status = al.status
                cov = al.covariance if al.status == "aligned" else cov
        self.previous = res.T_c2w if res.localized else None
        reset = False
        if self.tracker is not None:
            reset = self.tracker.solved(res.T_c2w if res.localized else None, plan, p.frame.frame_id)
            if res.localized and self.track_keyframes is None:
                self._anchor = frame_keyframe(p.gray, p.intr, p.coords, self.stride, res.T_c2w, pnp.threshold_px)
            if res.localized:
                self._depth = scene_depth(grid_correspondences(p.coords, self.stride)[0], res.T_c2w)
        rc = self.tracker.reset_counter if self.tracker is not None else 0
        rec = to_record(p.frame, res, cov, rc)
        return self._outcome(p, rec, res, times, mode, status, fallback, reset, retried)

    def _solve_scr(
        self, p: Prepared, pnp: PnPConfig, prior: np.ndarray | None, times: dict[str, float]
    ) -> tuple[PnPResult, np.ndarray | None]:
        """PnP + gate (+ the mirror check) of the prepared frame's grid, and the pose's covariance; adds its time to
        ``times`` (the mirrored inference to 'inference', the rest to 'pnp')."""
        t0 = time.perf_counter()
        res = solve_from_grid(p.coords, p.intr, stride=self.stride, config=pnp, prior_c2w=prior)
        res = gate_result(res, p.coords, p.intr, pnp, self.stride, self.gate, self.previous)
        mirror_ms = 0.0

        def predict(gray: np.ndarray) -> np.ndarray:  # the mirrored frame's inference, timed as inference
            nonlocal mirror_ms
            t_m = time.perf_counter()
            coords = self.session.run(gray)
            mirror_ms = (time.perf_counter() - t_m) * 1000.0
            return coords

        res = mirror_checked(res, p.gray, p.intr, predict, pnp, self.stride, self.gate)
        cov = None
        if res.localized and res.T_c2w is not None:
            cov = grid_covariance(p.coords, p.intr, self.stride, res.T_c2w, pnp.threshold_px)
        times["pnp"] += (time.perf_counter() - t0) * 1000.0 - mirror_ms
        times["inference"] += mirror_ms
        return res, cov

    def _track(self, p: Prepared, start: np.ndarray):
        """The tracked alignment of the prepared frame from ``start`` (4, 4) (acesplat.align.flow_pnp.Alignment)."""
        cfg = self.tracker.config
        if self.track_keyframes is not None:
            refs = self.track_keyframes.near(start, k=cfg.keyframes, depth=self._depth)
        else:
            refs = [self._anchor] if self._anchor is not None else []
        anchor = grid_correspondences(p.coords, self.stride) if p.coords is not None else None
        gray, intr = p.gray, p.intr
        if p.view is not None:  # SCR ran on a smaller copy: align the full-size image, the cells mapped there
            gray, intr = p.view
            anchor = None if anchor is None else (anchor[0], p.intr.pixels_to(anchor[1], intr))
        return track_to_keyframes(gray, intr, start, refs, cfg.align, anchor)

    def _outcome(
        self,
        p: Prepared,
        rec: PoseRecord,
        res: PnPResult,
        times: dict[str, float],
        mode: str,
        status: str | None,
        fallback: str | None = None,
        reset: bool = False,
        retried: bool = False,
    ) -> FrameOutcome:
        times["total"] = (time.perf_counter() - p.t_start) * 1000.0
        times = {s: times[s] for s in STAGES}
        f = p.frame
        return FrameOutcome(
            rec,
            res,
            times,
            f.name,
            f.gt_pose,
            p.intr,
            status,
            f,
            p.gray,
            p.coords,
            p.features,
            mode,
            fallback,
            reset,
            retried,
        )


@dataclass
class Prepared:
    """A frame after the first phase (EdgeLocalizer.prepare): the network input ``gray`` (H, W) uint8 with its
    intrinsics, the tracker's plan, and the scene coordinates (h, w, 3) unless the frame is to be tracked."""

    frame: SourceFrame
    gray: np.ndarray
    intr: Intrinsics
    plan: Plan | None
    """None: prepared ahead by a pipeline; ``solve`` plans it."""
    t_start: float
    times: dict[str, float]
    coords: np.ndarray | None = None
    features: np.ndarray | None = None
    view: tuple[np.ndarray, Intrinsics] | None = None
    """The frame at the bundle's size (gray (H, W), intrinsics) when SCR runs on a smaller ``gray``; None: same."""


def grid_covariance(
    coords: np.ndarray, intrinsics: Intrinsics, stride: int, T_c2w: np.ndarray, threshold_px: float
) -> np.ndarray | None:
    """The pose covariance (6, 6) from the SCR grid's inliers under ``T_c2w`` (acesplat.core.pose_covariance)."""
    points, pixels = grid_correspondences(coords, stride)
    finite = np.all(np.isfinite(points), axis=1)
    points, pixels = points[finite], pixels[finite]
    w2c = invert_pose(T_c2w)
    _, _, err = reprojection(points, pixels, intrinsics.K, w2c[:3, :3], w2c[:3, 3])
    inl = err < threshold_px
    return pose_covariance(points[inl], pixels[inl], intrinsics, T_c2w)


def to_record(
    frame: SourceFrame, res: PnPResult | None, covariance: np.ndarray | None = None, reset_counter: int = 0
) -> PoseRecord:
    """PoseRecord for the bridge and the logs; a frame that failed the gate is LOST (its pose, if any, is still
    given); ``covariance`` (6, 6) only travels with a TRACKING pose."""
    ts_us = int(round(frame.timestamp * 1e6))
    if res is None or res.T_c2w is None:
        T = np.full((4, 4), np.nan)
        return PoseRecord(ts_us, T, 0, TrackingState.LOST, 0.0, frame.frame_id, reset_counter=reset_counter)
    state = TrackingState.TRACKING if res.localized else TrackingState.LOST
    cov = covariance if res.localized else None
    return PoseRecord(ts_us, res.T_c2w, res.inliers, state, float(res.inlier_ratio), frame.frame_id, cov, reset_counter)
