"""Per-frame localization on the edge: prepare, infer, PnP, gate; with a timing for every stage.

Stages (milliseconds): capture (source read and decode), preprocess (gray, undistort, crop,
resize), inference (onnxruntime), pnp (RANSAC + LM + gate), align (with --align: the pose refined against
the bundle's keyframes, acesplat.align.keyframe_align; 0 otherwise) and total (from the start of the
capture to the pose, including any wait between capture and processing).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from acesplat.align.keyframe_align import align_scr_pose
from acesplat.align.keyframe_set import bundle_keyframes
from acesplat.core.bundle import Bundle
from acesplat.core.camera import Intrinsics
from acesplat.core.errors import InputError
from acesplat.core.pnp import DEFAULT_MIN_INLIERS, PnPResult, solve_from_grid
from acesplat.core.pose import PoseRecord, TrackingState
from edge.frame_prep import FramePrep
from edge.inference import ScrSession
from edge.sources import SourceFrame

STAGES = ("capture", "preprocess", "inference", "pnp", "align", "total")

DEFAULT_PNP_METHOD = "ransac_ap3p"
"""Chosen by measurement on real predictions (bench/pnp_choice.md)."""
DEFAULT_PNP_ITERATIONS = 256
"""RANSAC cap for the edge: a lost frame (nothing matches) costs a third of the desktop's 1000 iterations,
and good frames converge long before it (bench/pnp_choice.md)."""


@dataclass
class FrameOutcome:
    """What one frame produced: the pose record, the raw PnP result, and stage timings (ms)."""

    record: PoseRecord
    result: PnPResult | None
    times_ms: dict[str, float]
    name: str = ""
    gt_pose: np.ndarray | None = None
    intrinsics: Intrinsics | None = None
    alignment: str | None = None
    """With --align: the keyframe alignment's status ('aligned' or why the PnP pose was kept); None if not tried."""


@dataclass
class PnPSettings:
    method: str = DEFAULT_PNP_METHOD
    min_inliers: int = DEFAULT_MIN_INLIERS
    iterations: int = DEFAULT_PNP_ITERATIONS
    extra: dict = field(default_factory=dict)

    def kwargs(self) -> dict:
        return {"method": self.method, "min_inliers": self.min_inliers, "iterations": self.iterations, **self.extra}


class EdgeLocalizer:
    """A bundle's SCR model (FP32 or INT8) plus frame preparation and the shared PnP solver."""

    def __init__(
        self,
        bundle: Bundle,
        precision: str = "fp32",
        threads: int | None = None,
        pnp: PnPSettings | None = None,
        align: bool = False,
    ) -> None:
        self.bundle = bundle
        self.precision = precision
        self.input_size = bundle.input_size
        self.stride = bundle.output_stride
        self.session = ScrSession(bundle.scr_model(precision), self.input_size, threads)
        self.prep = FramePrep(self.input_size)
        self.pnp = pnp or PnPSettings()
        self.keyframes = bundle_keyframes(bundle) if align else None
        """The bundle's keyframes when poses are refined against them (InputError at start if it has none)."""

    def localize(self, frame: SourceFrame, capture_ms: float = 0.0, t_start: float | None = None) -> FrameOutcome:
        """Pose of one frame; ``t_start`` (perf_counter seconds) is when its capture began, for the total."""
        if frame.intrinsics is None:
            raise InputError(None, f"frame {frame.name or frame.frame_id} has no intrinsics: pass --intrinsics FILE")
        t_start = time.perf_counter() - capture_ms / 1000.0 if t_start is None else t_start
        t0 = time.perf_counter()
        gray, intr = self.prep(frame.image, frame.intrinsics, frame.distortion)
        t1 = time.perf_counter()
        coords = self.session.run(gray)
        t2 = time.perf_counter()
        res = solve_from_grid(coords, intr, stride=self.stride, **self.pnp.kwargs())
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
        return FrameOutcome(to_record(frame, res), res, times, frame.name, frame.gt_pose, intr, status)


def to_record(frame: SourceFrame, res: PnPResult | None) -> PoseRecord:
    """PoseRecord for the bridge and the logs; a frame that failed the gate is LOST (its pose, if any, is still given)."""
    ts_us = int(round(frame.timestamp * 1e6))
    if res is None or res.T_c2w is None:
        T = np.full((4, 4), np.nan)
        return PoseRecord(ts_us, T, 0, TrackingState.LOST, 0.0, frame.frame_id)
    state = TrackingState.TRACKING if res.localized else TrackingState.LOST
    return PoseRecord(ts_us, res.T_c2w, res.inliers, state, float(res.inlier_ratio), frame.frame_id)


def paced(localizer: EdgeLocalizer, budget_ms: float) -> EdgeLocalizer:
    """``localizer`` whose ``localize`` returns no earlier than ``budget_ms`` after the frame's start.

    A replay from files then arrives at a camera's rate: the reference for refinement runs, which
    idle between frames the same way (localization latency compared under equal pacing).
    """
    inner = localizer.localize

    def localize(frame, *args, **kwargs):
        out = inner(frame, *args, **kwargs)
        time.sleep(max(0.0, (budget_ms - out.times_ms["total"]) / 1000.0))
        return out

    localizer.localize = localize  # type: ignore[method-assign]
    return localizer
