"""The tracking gate: whether a PnP pose is trustworthy enough to report as TRACKING (torch-free).

A fixed inlier count is fooled by frames of another scene: a few dozen random predictions always agree with some
pose. The gate instead asks how much of the prediction agrees (the inlier ratio over the cells with a valid
prediction), whether the agreeing cells cover the image (coverage of a coarse grid: a pose pinned by one cluster is
not trustworthy), how tightly they agree (the inliers' median residual against the PnP threshold), and, when the
caller has one, whether the pose agrees with the previous one. A pose that passes with a middling score must also
beat the frame's mirror image: a mirrored camera stream, or a photograph of a nearly symmetric facade, explains the
map from the mirrored position almost as well as a true view, and only the asymmetric details tell them apart.
Calibration and margins: bench/gate.md.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob
from acesplat.core.geometry import invert_pose, rotation_angle_deg
from acesplat.core.grid import OUTPUT_STRIDE, grid_correspondences
from acesplat.core.pose_refine import reprojection

if TYPE_CHECKING:
    from acesplat.core.pnp import PnPConfig, PnPResult


@dataclass(frozen=True)
class GateConfig:
    """When a pose counts as TRACKING; the PnP's ``min_inliers`` stays a floor in front of it."""

    min_score: float = knob(0.06, "Gate score (inlier ratio x coverage) a TRACKING pose needs (bench/gate.md).")
    min_ratio: float = knob(0.05, "Inliers over the cells with a valid prediction, at least.")
    min_coverage: float = knob(0.25, "Fraction of the coarse grid's cells that are covered, at least.")
    coarse_grid: int = knob(4, "Cells per side of the coarse grid the inliers' spread is measured on.")
    cell_ratio: float = knob(0.1, "Inlier ratio among a coarse cell's valid predictions for it to count as covered.")
    max_residual: float = knob(0.8, "Median inlier residual as a fraction of the PnP threshold, at most.")
    max_motion_m: float | None = knob(None, "Translation from the previous pose (m), at most; None: not checked.")
    max_motion_deg: float | None = knob(None, "Rotation from the previous pose (deg), at most; None: not checked.")
    mirror_below: float = knob(
        0.4, "A pose scoring below this must also beat the mirrored frame's score (0: never checked; bench/gate.md)."
    )

    def __post_init__(self) -> None:
        if self.coarse_grid < 1:
            raise ValueError(f"coarse_grid must be >= 1, got {self.coarse_grid}")
        for name in ("min_score", "min_ratio", "min_coverage", "cell_ratio", "max_residual", "mirror_below"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")


@dataclass(frozen=True)
class GateVerdict:
    """The gate's measurements, its score and whether the pose passed; ``reasons`` says why not (empty if it did)."""

    passed: bool
    score: float
    """ratio * coverage, in [0, 1]; compared with GateConfig.min_score."""
    inliers: int
    valid: int
    """Cells with a finite prediction."""
    ratio: float
    coverage: float
    """Fraction of the coarse grid's cells whose valid predictions are inliers at least ``cell_ratio`` of the time
    (a cell without valid predictions is not covered)."""
    hull: float
    """Convex-hull area of the inliers over the image area (reported, not gated)."""
    residual: float
    """Median inlier residual over the PnP threshold (1.0 when there are no inliers)."""
    motion: tuple[float, float] | None = None
    """Translation (m) and rotation (deg) from the previous pose, when one was given."""
    reasons: tuple[str, ...] = field(default=())
    mirror_score: float | None = None
    """The mirrored frame's score, when the mirror check ran (GateConfig.mirror_below)."""

    def as_dict(self) -> dict:
        return {
            "passed": self.passed,
            "score": self.score,
            "inliers": self.inliers,
            "valid": self.valid,
            "ratio": self.ratio,
            "coverage": self.coverage,
            "hull": self.hull,
            "residual": self.residual,
            "motion": list(self.motion) if self.motion is not None else None,
            "reasons": list(self.reasons),
            "mirror_score": self.mirror_score,
        }


def _hull_area(xy: np.ndarray) -> float:
    """Area of the convex hull of points (N, 2) (0 for fewer than 3 distinct points)."""
    pts = np.asarray(xy, dtype=np.float32).reshape(-1, 2)
    if len(pts) < 3:
        return 0.0
    return float(cv2.contourArea(cv2.convexHull(pts)))


def gate_pose(
    pixels: np.ndarray,
    points: np.ndarray,
    intrinsics: Intrinsics,
    T_c2w: np.ndarray | None,
    threshold_px: float,
    config: GateConfig | None = None,
    min_inliers: int = 0,
    previous: np.ndarray | None = None,
) -> GateVerdict:
    """The gate's verdict on camera-to-world ``T_c2w`` (4, 4) (None: no pose) from pixels (N, 2) and scene points
    (N, 3) (non-finite points are invalid cells) of the image ``intrinsics`` describe, with inliers within
    ``threshold_px``; ``min_inliers`` is the PnP's floor, ``previous`` (4, 4) the previous camera-to-world pose."""
    cfg = config or GateConfig()
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if pixels.shape[0] != points.shape[0]:
        raise ValueError(f"pixels {pixels.shape} and points {points.shape} differ in count")
    H, W = int(intrinsics.height), int(intrinsics.width)
    if H <= 0 or W <= 0 or not threshold_px > 0:
        raise ValueError(f"image size {W}x{H} and threshold {threshold_px} must be positive")
    finite = np.isfinite(points).all(axis=1)
    pixels, points = pixels[finite], points[finite]
    valid = int(pixels.shape[0])
    if T_c2w is None or valid == 0:
        return GateVerdict(False, 0.0, 0, valid, 0.0, 0.0, 0.0, 1.0, None, ("no pose",))
    T_w2c = invert_pose(np.asarray(T_c2w, dtype=np.float64))
    _, _, err = reprojection(points, pixels, intrinsics.K, T_w2c[:3, :3], T_w2c[:3, 3])
    inl = err < threshold_px
    n = int(np.count_nonzero(inl))
    ratio = n / valid
    g = cfg.coarse_grid
    cx = np.clip((pixels[:, 0] * g / W).astype(int), 0, g - 1)
    cy = np.clip((pixels[:, 1] * g / H).astype(int), 0, g - 1)
    cell = cy * g + cx
    cells = np.bincount(cell, minlength=g * g)
    cell_inliers = np.bincount(cell[inl], minlength=g * g)
    covered = (cells > 0) & (cell_inliers >= cfg.cell_ratio * cells)
    coverage = float(np.count_nonzero(covered)) / (g * g)
    hull = _hull_area(pixels[inl]) / (H * W)
    residual = float(np.median(err[inl]) / threshold_px) if n else 1.0
    score = ratio * coverage
    reasons = []
    if n < min_inliers:
        reasons.append(f"{n} inliers < {min_inliers}")
    if ratio < cfg.min_ratio:
        reasons.append(f"inlier ratio {ratio:.3f} < {cfg.min_ratio}")
    if coverage < cfg.min_coverage:
        reasons.append(f"coverage {coverage:.2f} < {cfg.min_coverage}")
    if residual > cfg.max_residual:
        reasons.append(f"median residual {residual:.2f} of the threshold > {cfg.max_residual}")
    if score < cfg.min_score:
        reasons.append(f"score {score:.3f} < {cfg.min_score}")
    motion = None
    if previous is not None:
        d = np.linalg.inv(np.asarray(previous, dtype=np.float64)) @ np.asarray(T_c2w, dtype=np.float64)
        motion = (float(np.linalg.norm(d[:3, 3])), float(rotation_angle_deg(d[:3, :3])))
        if cfg.max_motion_m is not None and motion[0] > cfg.max_motion_m:
            reasons.append(f"moved {motion[0]:.2f} m > {cfg.max_motion_m} m since the previous pose")
        if cfg.max_motion_deg is not None and motion[1] > cfg.max_motion_deg:
            reasons.append(f"turned {motion[1]:.1f} deg > {cfg.max_motion_deg} deg since the previous pose")
    return GateVerdict(not reasons, score, n, valid, ratio, coverage, hull, residual, motion, tuple(reasons))


def gate_grid(
    coords: np.ndarray,
    intrinsics: Intrinsics,
    T_c2w: np.ndarray | None,
    threshold_px: float,
    stride: int = OUTPUT_STRIDE,
    config: GateConfig | None = None,
    min_inliers: int = 0,
    previous: np.ndarray | None = None,
) -> GateVerdict:
    """gate_pose for a scene-coordinate grid (3, h, w) or (h, w, 3) of a network input with ``intrinsics``,
    ``stride`` pixels per cell."""
    points, pixels = grid_correspondences(coords, stride)
    return gate_pose(pixels, points, intrinsics, T_c2w, threshold_px, config, min_inliers, previous)


def gate_result(
    res: PnPResult,
    coords: np.ndarray,
    intrinsics: Intrinsics,
    pnp: PnPConfig,
    stride: int = OUTPUT_STRIDE,
    config: GateConfig | None = None,
    previous: np.ndarray | None = None,
) -> PnPResult:
    """``res`` (solve_from_grid's result for ``coords``) with ``localized`` decided by the gate and its verdict
    attached: the one TRACKING/LOST decision of the desktop and the edge. ``pnp`` gives the inlier threshold and
    the min_inliers floor."""
    v = gate_grid(coords, intrinsics, res.T_c2w, pnp.threshold_px, stride, config, pnp.min_inliers, previous)
    return replace(res, localized=bool(res.localized and v.passed), gate=v)


def mirror_frame(gray: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray, Intrinsics]:
    """The frame (H, W) mirrored left to right, and the intrinsics that image has: pixel u goes to W - 1 - u, so
    cx goes to W - 1 - cx (it is the image of the world mirrored in the camera's x)."""
    if gray.ndim != 2 or gray.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(f"frame must be (H, W) matching its intrinsics, got {gray.shape}")
    flipped = np.ascontiguousarray(gray[:, ::-1])
    return flipped, replace(intrinsics, cx=intrinsics.width - 1 - intrinsics.cx)


def needs_mirror_check(res: PnPResult, config: GateConfig | None = None) -> bool:
    """Whether ``res`` (gated) is TRACKING with a score below GateConfig.mirror_below."""
    cfg = config or GateConfig()
    return bool(res.localized and res.gate is not None and res.gate.score < cfg.mirror_below)


def mirror_result(
    res: PnPResult,
    mirror_coords: np.ndarray,
    mirror_intrinsics: Intrinsics,
    pnp: PnPConfig,
    stride: int = OUTPUT_STRIDE,
    config: GateConfig | None = None,
) -> PnPResult:
    """``res`` (gated) after the mirror check: the network's grid ``mirror_coords`` (h, w, 3) of the mirrored frame
    (mirror_frame) is solved and scored like the frame; if it scores at least as high, the frame is LOST."""
    from acesplat.core.pnp import solve_from_grid

    if res.gate is None:
        raise ValueError("the mirror check needs a gated result (gate_result)")
    m = solve_from_grid(mirror_coords, mirror_intrinsics, stride=stride, config=pnp)
    mv = gate_grid(mirror_coords, mirror_intrinsics, m.T_c2w, pnp.threshold_px, stride, config)
    v = replace(res.gate, mirror_score=mv.score)
    if mv.score >= v.score:
        reason = f"the mirrored frame fits the map as well (score {mv.score:.3f} >= {v.score:.3f})"
        v = replace(v, passed=False, reasons=(*v.reasons, reason))
    return replace(res, localized=bool(res.localized and v.passed), gate=v)


def mirror_checked(
    res: PnPResult,
    gray: np.ndarray,
    intrinsics: Intrinsics,
    predict: Callable[[np.ndarray], np.ndarray],
    pnp: PnPConfig,
    stride: int = OUTPUT_STRIDE,
    config: GateConfig | None = None,
) -> PnPResult:
    """``res`` (gated, for the network input ``gray`` (H, W) with ``intrinsics``) after the mirror check when it needs
    one (needs_mirror_check); ``predict`` gives the network's grid (h, w, 3) of the mirrored frame. The one path of
    the desktop localizer and the edge runtime."""
    if not needs_mirror_check(res, config):
        return res
    m_gray, m_intr = mirror_frame(gray, intrinsics)
    return mirror_result(res, predict(m_gray), m_intr, pnp, stride, config)
