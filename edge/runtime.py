"""Per-frame localization on the edge: prepare, infer, PnP, gate; with a timing for every stage.

Stages (milliseconds): capture (source read and decode), preprocess (gray, undistort, crop,
resize), inference (onnxruntime), pnp (RANSAC + LM + gate), align (with --align: the pose refined against
the bundle's keyframes, acesplat.align.keyframe_align; 0 otherwise) and total (from the start of the
capture to the pose, including any wait between capture and processing).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from acesplat.align.keyframe_align import align_scr_pose
from acesplat.align.keyframe_set import bundle_keyframes
from acesplat.core.bundle import Bundle
from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob, knob_default
from acesplat.core.errors import InputError
from acesplat.core.gate import GateConfig, gate_result
from acesplat.core.pnp import PnPConfig, PnPResult, solve_from_grid
from acesplat.core.pose import PoseRecord, TrackingState
from edge.frame_prep import FramePrep
from edge.inference import ScrSession, SessionSettings
from edge.sources import SourceFrame

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
    """With --align: the keyframe alignment's status ('aligned' or why the PnP pose was kept); None if not tried."""
    frame: SourceFrame | None = None
    """The frame as captured (image, its intrinsics and distortion)."""
    gray: np.ndarray | None = None
    """The prepared network input (H, W) uint8."""
    coords: np.ndarray | None = None
    """Scene coordinates (h, w, 3) float32 the network predicted."""
    features: np.ndarray | None = None
    """The encoder features (C, h, w) when a tap needs them and the graph outputs them, else None."""

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

    method: str = knob("ransac_ap3p", "PnP method (the measured choice: bench/pnp_choice.md).")
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
    ) -> None:
        if pace_ms is not None and not pace_ms > 0:
            raise ValueError(f"pace must be positive, got {pace_ms} ms")
        self.bundle = bundle
        self.precision = precision
        self.input_size = bundle.input_size
        self.stride = bundle.output_stride
        self.session = ScrSession(bundle.scr_model(precision), self.input_size, threads, provider)
        self.prep = FramePrep(self.input_size)
        self.pnp = pnp or PnPSettings()
        self.gate = gate or GateConfig()
        """When a pose is TRACKING (acesplat.core.gate): the same decision as the desktop's."""
        self.previous: np.ndarray | None = None
        """The last frame's camera-to-world pose if it was TRACKING (the gate's motion check), else None."""
        self.keyframes = bundle_keyframes(bundle) if align else None
        """The bundle's keyframes when poses are refined against them (InputError at start if it has none)."""
        self.pace_ms = pace_ms
        """Each frame takes at least this long from its capture start (a replay then arrives at a camera's rate)."""
        self.taps: list[FrameTap] = []

    def add_tap(self, tap: FrameTap) -> None:
        """Deliver every frame's outcome (and the loop's events) to ``tap`` from now on, after the taps before it."""
        if not isinstance(tap, FrameTap):
            raise TypeError(f"a tap must be an edge.runtime.FrameTap, got {type(tap).__name__}")
        self.taps.append(tap)

    def notify(self, event: Any) -> None:
        """Hand a loop event (edge.loop.LoopEvent) to every tap."""
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
        if frame.intrinsics is None:
            raise InputError(None, f"frame {frame.name or frame.frame_id} has no intrinsics: pass --intrinsics FILE")
        t_start = time.perf_counter() - capture_ms / 1000.0 if t_start is None else t_start
        t0 = time.perf_counter()
        gray, intr = self.prep(frame.image, frame.intrinsics, frame.distortion)
        t1 = time.perf_counter()
        if self.session.has_features and any(t.needs_features for t in self.taps):
            coords, feats = self.session.run_with_features(gray)
        else:
            coords, feats = self.session.run(gray), None
        t2 = time.perf_counter()
        pnp = self.pnp.config()
        res = solve_from_grid(coords, intr, stride=self.stride, config=pnp)
        res = gate_result(res, coords, intr, pnp, self.stride, self.gate, self.previous)
        self.previous = res.T_c2w if res.localized else None
        t3 = time.perf_counter()
        status = None
        if self.keyframes is not None and res.localized and res.T_c2w is not None:
            al = align_scr_pose(gray, intr, coords, self.stride, res.T_c2w, self.keyframes.near)
            res, status = replace(res, T_c2w=al.pose), al.status
        t4 = time.perf_counter()
        times = {
            "capture": capture_ms,
            "preprocess": (t1 - t0) * 1000.0,
            "inference": (t2 - t1) * 1000.0,
            "pnp": (t3 - t2) * 1000.0,
            "align": (t4 - t3) * 1000.0,
            "total": (t4 - t_start) * 1000.0,
        }
        return FrameOutcome(
            to_record(frame, res), res, times, frame.name, frame.gt_pose, intr, status, frame, gray, coords, feats
        )


def to_record(frame: SourceFrame, res: PnPResult | None) -> PoseRecord:
    """PoseRecord for the bridge and the logs; a frame that failed the gate is LOST (its pose, if any, is still
    given)."""
    ts_us = int(round(frame.timestamp * 1e6))
    if res is None or res.T_c2w is None:
        T = np.full((4, 4), np.nan)
        return PoseRecord(ts_us, T, 0, TrackingState.LOST, 0.0, frame.frame_id)
    state = TrackingState.TRACKING if res.localized else TrackingState.LOST
    return PoseRecord(ts_us, res.T_c2w, res.inliers, state, float(res.inlier_ratio), frame.frame_id)
