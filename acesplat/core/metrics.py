"""Accuracy and timing summaries shared by `acesplat eval` and the edge replay/profile commands."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

RECALL_THRESHOLDS = {
    "recall_5cm_5deg": (0.05, 5.0),
    "recall_10cm_5deg": (0.10, 5.0),
    "recall_25cm_2deg": (0.25, 2.0),
}


@dataclass
class FrameResult:
    """Per-frame outcome of localization against a known pose."""

    name: str
    localized: bool
    translation_m: float
    rotation_deg: float
    inliers: int
    ms: float
    pose_c2w: np.ndarray | None = None
    """The estimated camera-to-world (4, 4), when there is one: two runs over the same frames compare by it."""

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "localized": self.localized,
            "translation_m": finite_or_none(self.translation_m),
            "rotation_deg": finite_or_none(self.rotation_deg),
            "inliers": self.inliers,
            "ms": self.ms,
            "pose_c2w": None if self.pose_c2w is None else np.asarray(self.pose_c2w, np.float64).tolist(),
        }


def finite_or_none(x: float) -> float | None:
    """JSON has no infinity: an error that does not exist (no pose) is written as null."""
    return float(x) if np.isfinite(x) else None


def accuracy_summary(results: Sequence[FrameResult]) -> dict:
    """The JSON keys both `acesplat eval` and `acesplat-edge replay` report.

    Recalls are percentages of all frames; a frame that failed the inlier gate counts as a miss
    and enters the medians with infinite error (so failures cannot improve a median).
    """
    n = len(results)
    t = np.array([r.translation_m if r.localized else np.inf for r in results], dtype=np.float64)
    a = np.array([r.rotation_deg if r.localized else np.inf for r in results], dtype=np.float64)
    out: dict = {"frames": n, "localized": int(sum(r.localized for r in results))}
    out["median_translation_m"] = finite_or_none(float(np.median(t))) if n else None
    out["median_rotation_deg"] = finite_or_none(float(np.median(a))) if n else None
    for key, (tm, deg) in RECALL_THRESHOLDS.items():
        out[key] = 100.0 * float(np.count_nonzero((t <= tm) & (a <= deg))) / n if n else 0.0
    out["mean_ms"] = float(np.mean([r.ms for r in results])) if n else None
    out["per_frame"] = [r.as_dict() for r in results]
    return out


def timing_stats(samples_ms: Sequence[float]) -> dict:
    """mean, p50, p90, p95, p99, max of a list of milliseconds (as trtexec and onnxruntime_perf_test report)."""
    x = np.asarray(samples_ms, dtype=np.float64)
    if x.size == 0:
        return {k: float("nan") for k in ("mean", "p50", "p90", "p95", "p99", "max")}
    p = np.percentile(x, [50, 90, 95, 99])
    return {
        "mean": float(x.mean()),
        "p50": float(p[0]),
        "p90": float(p[1]),
        "p95": float(p[2]),
        "p99": float(p[3]),
        "max": float(x.max()),
    }
