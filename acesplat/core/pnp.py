"""Camera pose from 2D-3D correspondences: PnP-RANSAC, robust refinement, an inlier gate.

Shared by desktop evaluation and the edge runtime so both compute poses the same way.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob
from acesplat.core.geometry import invert_pose, make_pose, rodrigues_to_matrix
from acesplat.core.grid import OUTPUT_STRIDE, grid_correspondences
from acesplat.core.pose_refine import ROBUST_SCALES, refine_pose_robust, reprojection
from acesplat.core.ransac import ransac_pnp

if TYPE_CHECKING:
    from acesplat.core.gate import GateVerdict

PNP_METHODS = (
    "batch_p3p",
    "usac_magsac",
    "usac_default",
    "usac_accurate",
    "ransac_p3p",
    "ransac_ap3p",
    "ransac_sqpnp",
    "ransac_epnp",
)
RANSAC_SEED = 0
"""RANSAC's random samples are seeded per call: the same predictions always give the same pose, so
torch-vs-ONNX parity, replays and tests compare solutions, not random draws."""


@dataclass(frozen=True)
class PnPConfig:
    """The PnP solver's settings, shared by desktop evaluation, the edge runtime and the benchmarks."""

    method: str = knob("batch_p3p", "PnP-RANSAC solver (one of PNP_METHODS; bench/pnp_speed.md, bench/pnp_choice.md).")
    threshold_px: float = knob(10.0, "Inlier threshold in pixels of the network input image (ACE's 10 px).")
    min_inliers: int = knob(
        50, "Inliers a pose needs at least; the tracking gate (acesplat.core.gate) then decides TRACKING."
    )
    iterations: int = knob(1000, "RANSAC iterations at most.")
    confidence: float = knob(0.9999, "RANSAC confidence: it stops early once this sure of the best sample.")
    robust_scales: tuple[float, ...] = knob(
        ROBUST_SCALES, "Cauchy scales (px) of the robust refinement; () refines RANSAC's inliers with LM instead."
    )
    fallback: str | None = knob(
        "usac_magsac", "Solver retried when the pose fails the inlier gate (AP3P can return the mirror pose); None."
    )
    prior_min_ratio: float = knob(
        0.1, "A pose prior is refined instead of running RANSAC when this share of the cells are its inliers."
    )

    def __post_init__(self) -> None:
        for m in (self.method, self.fallback):
            if m is not None and m not in PNP_METHODS:
                raise ValueError(f"unknown PnP method {m!r}; choose from {PNP_METHODS}")
        if not 0.0 <= self.prior_min_ratio <= 1.0:
            raise ValueError(f"prior_min_ratio must be in [0, 1], got {self.prior_min_ratio}")


@dataclass
class PnPResult:
    """A pose estimate; ``T_c2w`` is None when the solver failed."""

    T_c2w: np.ndarray | None
    inliers: int
    correspondences: int
    localized: bool
    gate: GateVerdict | None = None
    """The tracking gate's verdict once acesplat.core.gate.gate_result has decided ``localized``; None before."""

    @property
    def inlier_ratio(self) -> float:
        return self.inliers / self.correspondences if self.correspondences else 0.0


def _usac_params(method: str, threshold: float, iterations: int, confidence: float) -> cv2.UsacParams:
    params = cv2.UsacParams()
    params.threshold = threshold
    params.maxIterations = iterations
    params.confidence = confidence
    params.loMethod = cv2.LOCAL_OPTIM_SIGMA if method == "usac_magsac" else cv2.LOCAL_OPTIM_INNER_LO
    params.score = cv2.SCORE_METHOD_MAGSAC if method == "usac_magsac" else cv2.SCORE_METHOD_MSAC
    params.sampler = cv2.SAMPLING_UNIFORM
    params.final_polisher = cv2.NONE_POLISHER
    params.randomGeneratorState = RANSAC_SEED
    return params


def solve_pnp(
    pixels: np.ndarray,
    points: np.ndarray,
    intrinsics: Intrinsics,
    config: PnPConfig | None = None,
    prior_c2w: np.ndarray | None = None,
    **overrides: Any,
) -> PnPResult:
    """Camera-to-world pose from pixels (N, 2) and scene points (N, 3) of an undistorted pinhole image.

    RANSAC finds the pose, then a Cauchy-weighted refinement over all correspondences with the scale
    annealed through ``robust_scales`` (pixels) lets the precise ones decide (acesplat.core.pose_refine);
    with ``robust_scales=()`` Levenberg-Marquardt on RANSAC's inliers refines instead. The frame counts as
    localized only with at least ``min_inliers`` inliers (the floor of acesplat.core.gate, which decides TRACKING); a
    pose that fails it is retried once with ``fallback`` (None: no retry, for comparing solvers on their own).

    ``prior_c2w`` (4, 4), a predicted camera-to-world pose (tracking): when at least ``prior_min_ratio`` of the
    correspondences (and ``min_inliers``) are its inliers, it is refined as RANSAC's pose would be and RANSAC is
    skipped; when it explains fewer, or its refinement ends with fewer than ``min_inliers``, RANSAC runs as without it.

    ``config`` (default PnPConfig()) holds the settings; ``overrides`` replace some of its fields by name
    (e.g. ``method="usac_magsac"``, ``min_inliers=20``).
    """
    cfg = replace(config or PnPConfig(), **overrides) if overrides else (config or PnPConfig())
    pixels = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 2)
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    if pixels.shape[0] != points.shape[0]:
        raise ValueError(f"pixels {pixels.shape} and points {points.shape} differ in count")
    finite = np.isfinite(points).all(axis=1)
    pixels, points = pixels[finite], points[finite]
    n = pixels.shape[0]
    if n < 6:
        return PnPResult(None, 0, n, False)
    if prior_c2w is not None:
        from_prior = _refine_prior(pixels, points, intrinsics.K, prior_c2w, cfg)
        if from_prior is not None:
            return PnPResult(from_prior[0], from_prior[1], n, True)
    first = _ransac_and_refine(pixels, points, intrinsics.K, cfg.method, cfg)
    if first[1] >= cfg.min_inliers or cfg.fallback is None or cfg.fallback == cfg.method:
        best = first
    else:
        # P3P-family RANSAC scores hypotheses without a cheirality check and can return the mirror pose with the
        # scene behind the camera; the final recount then finds no inliers. Retry once with another solver.
        second = _ransac_and_refine(pixels, points, intrinsics.K, cfg.fallback, cfg)
        best = second if second[1] > first[1] else first
    T_c2w, inliers = best
    return PnPResult(T_c2w, inliers, n, T_c2w is not None and inliers >= cfg.min_inliers)


def _ransac_and_refine(
    pixels: np.ndarray,
    points: np.ndarray,
    K: np.ndarray,
    method: str,
    cfg: PnPConfig,
) -> tuple[np.ndarray | None, int]:
    """Camera-to-world pose and its inlier count under the final pose, or (None, 0) when the solver fails."""
    threshold_px, iterations, confidence = cfg.threshold_px, cfg.iterations, cfg.confidence
    dist = np.zeros(5)
    if method == "batch_p3p":
        found = ransac_pnp(pixels, points, K, threshold_px, iterations, confidence, RANSAC_SEED)
        if found is None or len(found[2]) < 4:
            return None, 0
        R0, t0, inl, _ = found
        rvec, tvec = cv2.Rodrigues(R0)[0], t0.reshape(3, 1).copy()
        # EPnP on the sample's inliers, as OpenCV's RANSAC ends, so the refinement starts from all of them.
        ok, r_all, t_all = cv2.solvePnP(points[inl], pixels[inl], K, dist, rvec, tvec, False, cv2.SOLVEPNP_EPNP)
        if ok and np.isfinite(r_all).all() and np.isfinite(t_all).all():
            R1 = rodrigues_to_matrix(r_all.reshape(3))
            _, _, err = reprojection(points, pixels, K, R1, t_all.reshape(3))
            if np.count_nonzero(err < threshold_px) >= len(inl):
                rvec, tvec, inl = r_all, t_all, np.flatnonzero(err < threshold_px)
        return _refine(pixels, points, K, rvec.reshape(3), tvec.reshape(3), inl, cfg)
    cv2.setRNGSeed(RANSAC_SEED)
    try:
        if method.startswith("usac"):
            ok, _, rvec, tvec, inl = cv2.solvePnPRansac(
                points, pixels, K, dist, params=_usac_params(method, threshold_px, iterations, confidence)
            )
        else:
            flag = {
                "ransac_p3p": cv2.SOLVEPNP_P3P,
                "ransac_ap3p": cv2.SOLVEPNP_AP3P,
                "ransac_sqpnp": cv2.SOLVEPNP_SQPNP,
                "ransac_epnp": cv2.SOLVEPNP_EPNP,
            }[method]
            ok, rvec, tvec, inl = cv2.solvePnPRansac(
                points,
                pixels,
                K,
                dist,
                iterationsCount=iterations,
                reprojectionError=threshold_px,
                confidence=confidence,
                flags=flag,
            )
    except cv2.error:
        return None, 0
    if not ok or inl is None or len(inl) < 4:
        return None, 0
    return _refine(pixels, points, K, rvec.reshape(3), tvec.reshape(3), inl.reshape(-1), cfg)


def _refine(
    pixels: np.ndarray,
    points: np.ndarray,
    K: np.ndarray,
    rvec: np.ndarray,
    tvec: np.ndarray,
    inliers: np.ndarray,
    cfg: PnPConfig,
) -> tuple[np.ndarray, int]:
    """RANSAC's world-to-camera pose (rvec (3,), tvec (3,)) refined over every correspondence (robust) or on the
    ``inliers`` indices (LM); the camera-to-world pose and its inlier count under it."""
    if cfg.robust_scales:
        # The robust refinement starts from RANSAC's pose directly: an LM polish first changed no
        # pose measurably (bench/pnp_choice.md) and cost 1.5 ms at 2700 correspondences.
        r, t = refine_pose_robust(pixels, points, K, rvec, tvec, tuple(cfg.robust_scales))
    else:
        rvec, tvec = cv2.solvePnPRefineLM(
            points[inliers], pixels[inliers], K, np.zeros(5), rvec.reshape(3, 1).copy(), tvec.reshape(3, 1).copy()
        )
        r, t = rvec.reshape(3), tvec.reshape(3)
    # Recount inliers under the final pose so the gate sees the final solution.
    R = rodrigues_to_matrix(r)
    _, _, err = reprojection(points, pixels, K, R, t)  # inf behind the camera: never an inlier
    return invert_pose(make_pose(R, t)), int(np.count_nonzero(err < cfg.threshold_px))


def _refine_prior(
    pixels: np.ndarray, points: np.ndarray, K: np.ndarray, prior_c2w: np.ndarray, cfg: PnPConfig
) -> tuple[np.ndarray, int] | None:
    """The prior's refined camera-to-world pose and inlier count, or None when the prior or its refinement explain
    too few correspondences (then RANSAC decides)."""
    prior = np.asarray(prior_c2w, dtype=np.float64)
    if prior.shape != (4, 4) or not np.isfinite(prior).all():
        raise ValueError(f"prior_c2w must be a finite (4, 4) pose, got shape {prior.shape}")
    T = invert_pose(prior)
    _, _, err = reprojection(points, pixels, K, T[:3, :3], T[:3, 3])
    inl = np.flatnonzero(err < cfg.threshold_px)
    need = max(cfg.min_inliers, cfg.prior_min_ratio * len(points))
    if len(inl) < max(need, 4):
        return None
    rvec = cv2.Rodrigues(T[:3, :3])[0].reshape(3)
    T_c2w, count = _refine(pixels, points, K, rvec, T[:3, 3].copy(), inl, cfg)
    return (T_c2w, count) if count >= need else None


def solve_from_grid(
    coords: np.ndarray,
    intrinsics: Intrinsics,
    stride: int = OUTPUT_STRIDE,
    config: PnPConfig | None = None,
    prior_c2w: np.ndarray | None = None,
    **overrides: Any,
) -> PnPResult:
    """Pose from a scene-coordinate grid (3, h, w) or (h, w, 3) predicted for an image with ``intrinsics``;
    ``config``, ``prior_c2w`` and ``overrides`` as for solve_pnp."""
    points, pixels = grid_correspondences(coords, stride)
    return solve_pnp(pixels, points, intrinsics, config, prior_c2w, **overrides)
