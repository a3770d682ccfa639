"""A pose refined by dense flow from a reference view to the query and PnP on the pairs (torch-free).

One method for two kinds of reference: a mapping image warped to the estimated pose with its depth
(acesplat.align.keyframe_align: ``acesplat eval --align``, the edge's ``--align``) and the map rendered from the
estimated pose (``align_to_render``: the edge refiner's keyframes). Either way the reference shows the scene from
(nearly) the query's viewpoint with a 3D point at each pixel; its textured pixels are sampled, DIS optical flow
carries them to where the query shows them (forward-backward checked), PnP-RANSAC (+ LM, then a Cauchy polish over
all pairs) on the (3D point, query pixel) pairs gives the pose, and guards keep the start pose when there are too few
points or inliers or the correction is too large to be a refinement. The thresholds are an ``AlignConfig``;
``KEYFRAME_ALIGN`` and ``RENDER_ALIGN`` are the two references' settings (bench/herz_gap.md, bench/refine.md; costs
in bench/align.md), ``TRACK_ALIGN`` the edge tracker's cheap per-frame one (edge/tracking.py; bench/tracking.md).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob
from acesplat.core.geometry import invert_pose, make_pose, pose_error
from acesplat.core.pose_covariance import pose_covariance
from acesplat.core.pose_refine import refine_pose_robust, reprojection

FLOW_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}
THINNING = ("even", "confidence")
WARPS = ("keyframe", "query")
MATCHERS = ("dense", "sparse")
COVERED_ALPHA = 0.5
"""Alpha at which a rendered pixel counts towards the render's coverage."""
MIN_DEPTH_M = 1e-3
"""Rendered depth at or below this is no surface."""


@dataclass(frozen=True)
class AlignConfig:
    """Thresholds of flow + PnP alignment; the defaults are the keyframe alignment's (KEYFRAME_ALIGN)."""

    sample_step_px: int = knob(2, "Reference pixels are sampled on a grid this many pixels apart.")
    min_gradient: float = knob(
        20.0, "Sobel magnitude (8-bit) a sampled reference pixel needs: flat areas have no flow."
    )
    max_fb_error_px: float | None = knob(
        0.5, "Forward-backward flow disagreement above this marks an occlusion or mismatch (None: no check)."
    )
    max_photo_diff: float | None = knob(
        None, "A pair whose gray levels (8-bit) differ by more than this is no match (a blank or covered query; None)."
    )
    reproj_px: float = knob(1.0, "PnP-RANSAC inlier threshold in query pixels (flow errors are sub-pixel).")
    ransac_iterations: int = knob(200, "PnP-RANSAC iterations.")
    refine_lm: bool = knob(True, "Refine the RANSAC pose by Levenberg-Marquardt on its inliers.")
    robust_px: float | None = knob(
        0.25,
        "Then refine it over all pairs by Cauchy-weighted Gauss-Newton at this scale (px): a smooth function of the "
        "pairs, where the inlier set flips with sub-0.01 px changes of the tracks (bench/align.md); None: not.",
    )
    min_points: int = knob(300, "Fewer pairs than this (or fewer inliers) keep the start pose.")
    min_inlier_ratio: float = knob(0.5, "RANSAC inliers needed, as a share of the pairs PnP was given.")
    max_shift_m: float = knob(0.5, "A correction beyond this (m) means the start pose was wrong, not imprecise.")
    max_shift_deg: float = knob(3.0, "A correction beyond this (deg) means the start pose was wrong, not imprecise.")
    rounds: int = knob(
        1,
        "Match-PnP rounds (keyframes), each from the last round's pose (dense: 2, DENSE_ALIGN); a render is one round.",
    )
    min_anchor_kept: float = knob(
        0.8, "Share of the SCR correspondences' inliers the refined pose must keep (keyframes; bench/herz_gap.md)."
    )
    min_alpha: float = knob(0.8, "Rendered pixels sampled are this opaque at least (renders; bench/refine.md).")
    max_mse: float = knob(0.01, "A render whose MSE against the image exceeds this is not trusted (bench/refine.md).")
    min_coverage: float = knob(0.5, "A render covering less of the view than this is not trusted (bench/refine.md).")
    flow_preset: str = knob("medium", "DIS optical flow preset: ultrafast, fast or medium (bench/align.md).")
    first_flow_scale: float = knob(
        0.5, "The first round's flow runs on images scaled by this (coarse-to-fine; 1: full size; bench/align.md)."
    )
    max_pairs: int = knob(5000, "PnP gets at most this many pairs, thinned (0: all; bench/align.md).")
    thinning: str = knob("confidence", "How pairs beyond max_pairs are dropped: even (over the image) or confidence.")
    converged_m: float = knob(0.0, "Stop the rounds when one moves the pose less than this (m; 0: never).")
    converged_deg: float = knob(0.0, "...and less than this (deg).")
    enough_pairs: int = knob(0, "Keyframes are used nearest first until this many pairs (0: all; bench/align.md).")
    warp_step_px: int = knob(
        1, "The keyframe warp is inverted on pixels this far apart and upsampled (1: every pixel; bench/align.md)."
    )
    threads: int = knob(2, "Keyframes are warped and flowed in this many threads (OpenCV releases the GIL).")
    warp: str = knob(
        "keyframe",
        "Depth that warps a keyframe to the estimate: keyframe (its own, inverted by fixed-point iteration) or query "
        "(the query's SCR depth, one backward remap: faster, less accurate where the SCR depth is far off; the "
        "keyframe's depth without SCR coordinates or when it cannot fit; bench/align.md).",
    )
    matcher: str = knob(
        "sparse",
        "How keyframe pixels are found in the query: dense (the keyframe warped to the estimate, DIS flow) or sparse "
        "(the keyframe's corners, triangulated between keyframes, tracked by pyramidal Lucas-Kanade from where the "
        "estimate projects them, the keyframe warped by its dominant plane; ignores warp; bench/align.md).",
    )
    corners: int = knob(800, "Sparse matcher: corners per keyframe (Shi-Tomasi, strongest first).")
    lk_window_px: int = knob(15, "Sparse matcher: Lucas-Kanade window side (px; bench/align.md).")
    lk_plane_warp: bool = knob(
        True, "Sparse matcher: the keyframe is first warped by its dominant plane's homography to the estimate."
    )

    def __post_init__(self) -> None:
        if min(self.sample_step_px, self.ransac_iterations, self.rounds, self.warp_step_px, self.threads) < 1:
            raise ValueError(f"sample_step_px, ransac_iterations, rounds, warp_step_px, threads must be >= 1: {self}")
        if self.min_points < 4:
            raise ValueError(f"min_points must be >= 4, got {self.min_points}")
        if self.robust_px is not None and not self.robust_px > 0:
            raise ValueError(f"robust_px must be > 0 or None, got {self.robust_px}")
        if self.max_photo_diff is not None and not self.max_photo_diff > 0:
            raise ValueError(f"max_photo_diff must be > 0 or None, got {self.max_photo_diff}")
        if self.max_fb_error_px is not None and not self.max_fb_error_px > 0:
            raise ValueError(f"max_fb_error_px must be > 0 or None, got {self.max_fb_error_px}")
        if not (self.reproj_px > 0 and 0 <= self.min_inlier_ratio <= 1 and 0 < self.first_flow_scale <= 1):
            raise ValueError(f"need reproj_px > 0, min_inlier_ratio in [0, 1], first_flow_scale in (0, 1]: {self}")
        if (
            self.flow_preset not in FLOW_PRESETS
            or self.thinning not in THINNING
            or self.warp not in WARPS
            or self.matcher not in MATCHERS
        ):
            raise ValueError(
                f"flow_preset must be one of {sorted(FLOW_PRESETS)}, thinning one of {THINNING}, warp one of {WARPS}, "
                f"matcher one of {MATCHERS}"
            )
        if self.corners < 4 or self.lk_window_px < 5:
            raise ValueError(f"corners must be >= 4 and lk_window_px >= 5: {self}")
        if self.max_pairs and self.max_pairs < self.min_points:
            raise ValueError(f"max_pairs {self.max_pairs} is below min_points {self.min_points}")
        if self.thinning == "confidence" and self.max_fb_error_px is None:
            raise ValueError("thinning by confidence needs the forward-backward check (max_fb_error_px)")


KEYFRAME_ALIGN = AlignConfig()
"""Mapping images' corners, triangulated between them, tracked into the query from the estimate (bench/align.md)."""
DENSE_ROUNDS = 2
"""Rounds of the dense matcher (DENSE_ALIGN): its first runs the flow at half size."""
DENSE_ALIGN = replace(KEYFRAME_ALIGN, matcher="dense", rounds=DENSE_ROUNDS)
"""Mapping images warped to the estimate with their depth, two rounds of DIS flow (bench/herz_gap.md, bench/align.md:
as accurate as the sparse matcher on herzjesu25 and fountain11, at 5-8x its time)."""
RENDER_ALIGN = replace(
    DENSE_ALIGN,
    max_fb_error_px=None,
    ransac_iterations=100,
    refine_lm=False,
    robust_px=None,
    min_points=400,
    max_shift_m=0.15,
    rounds=1,
    first_flow_scale=1.0,
    max_pairs=0,
    thinning="even",
)
"""The map rendered at the estimate (bench/refine.md): no forward-backward check, RANSAC alone, one round."""
TRACK_ALIGN = replace(
    DENSE_ALIGN,
    sample_step_px=4,
    max_photo_diff=30.0,
    flow_preset="fast",
    first_flow_scale=0.5,
    ransac_iterations=50,
    robust_px=None,
    min_points=200,
    max_shift_m=0.1,
    rounds=1,
    max_pairs=1000,
    thinning="even",
)
"""Every frame while tracking (edge/tracking.py), against one keyframe from the predicted pose: a coarse sample grid,
pairs whose gray levels differ are dropped (a blank frame is no match), flow at half size, at most 1000 pairs, one
round; a prediction off by more than 10 cm is not refined (bench/tracking.md)."""


@dataclass(frozen=True)
class Alignment:
    """pose (4, 4): the refined camera-to-world, or the start pose unless ``status`` is 'aligned'.

    status: 'aligned'; 'few_points' (too little textured overlap with the references); 'no_fit' (PnP failed or
    too few inliers); 'too_far' (the correction exceeded max_shift_*: the start pose was wrong, not imprecise);
    keyframes only: 'disagrees' (the refined pose lost the SCR correspondences' inliers); renders only: 'unlike'
    (the render does not resemble the image, or covers too little of it, to trust a flow between them).
    points: pairs found (last round); inliers: PnP's among those it was given; mse: a render's against the image;
    covariance (6, 6): of an aligned pose, from the last round's inliers (acesplat.core.pose_covariance), else None.
    """

    pose: np.ndarray
    status: str
    points: int = 0
    inliers: int = 0
    shift_m: float = 0.0
    shift_deg: float = 0.0
    mse: float = float("nan")
    covariance: np.ndarray | None = None


def dis_flow(cfg: AlignConfig) -> cv2.DISOpticalFlow:
    """The DIS optical flow of ``cfg.flow_preset``."""
    return cv2.DISOpticalFlow_create(FLOW_PRESETS[cfg.flow_preset])


def sample_grid(h: int, w: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns (h', w') int of the pixels of an (h, w) image sampled ``step`` apart."""
    return np.mgrid[0:h:step, 0:w:step]


def gradient(gray: np.ndarray) -> np.ndarray:
    """Sobel gradient magnitude (H, W) float32 of an (H, W) uint8 image."""
    return np.hypot(cv2.Sobel(gray, cv2.CV_32F, 1, 0), cv2.Sobel(gray, cv2.CV_32F, 0, 1))


def bilinear(a: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """a (H, W, C) sampled at (x, y) (N,), clamped to the image: (N, C)."""
    h, w = a.shape[:2]
    x = np.clip(x, 0.0, w - 1.0)
    y = np.clip(y, 0.0, h - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), w - 2)
    y0 = np.minimum(np.floor(y).astype(np.int64), h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return (
        a[y0, x0] * (1 - fx) * (1 - fy)
        + a[y0, x0 + 1] * fx * (1 - fy)
        + a[y0 + 1, x0] * (1 - fx) * fy
        + a[y0 + 1, x0 + 1] * fx * fy
    )


def _flow(a: np.ndarray, b: np.ndarray, flow: cv2.DISOpticalFlow, scale: float) -> tuple[np.ndarray, float]:
    """Flow from a to b (H', W', 2) computed on both scaled by ``scale``, and the scale it is at."""
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    if scale == 1.0:
        return flow.calc(a, b, None), 1.0
    h, w = a.shape
    size = (max(8, round(w * scale)), max(8, round(h * scale)))
    small = [cv2.resize(x, size, interpolation=cv2.INTER_AREA) for x in (a, b)]
    return flow.calc(small[0], small[1], None), size[0] / w


def _flow_at(f: np.ndarray, s: float, p: np.ndarray) -> np.ndarray:
    """A flow field at scale s sampled at full-size pixels p (N, 2), in full-size pixels (N, 2)."""
    if s == 1.0:
        return bilinear(f, p[:, 0], p[:, 1])
    q = (p + 0.5) * s - 0.5
    return bilinear(f, q[:, 0], q[:, 1]) / s


def flow_to_query(
    ref: np.ndarray,
    query: np.ndarray,
    at: np.ndarray,
    flow: cv2.DISOpticalFlow,
    cfg: AlignConfig,
    scale: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where ``query`` (H, W) uint8 shows the pixels ``at`` (M, 2) of ``ref`` (H, W) uint8: seen (M, 2), the
    forward-backward check's verdict keep (M,) bool (the seen pixel inside the query and the flow back within
    ``cfg.max_fb_error_px``; all True without the check; with ``cfg.max_photo_diff`` also the two gray levels
    alike) and its error (M,) px (0 without the check).
    ``scale`` < 1 computes the flow on downscaled images (coarse and cheaper)."""
    if ref.shape != query.shape or ref.ndim != 2:
        raise ValueError(f"reference {ref.shape} and query {query.shape} must be the same (H, W)")
    fwd, s = _flow(ref, query, flow, scale)
    seen = at + _flow_at(fwd, s, at)
    like = np.ones(len(at), bool)
    if cfg.max_photo_diff is not None:  # a textureless query flows nowhere, consistently: the gray levels tell
        a = bilinear(ref[..., None].astype(np.float32), at[:, 0], at[:, 1])[:, 0]
        b = bilinear(query[..., None].astype(np.float32), seen[:, 0], seen[:, 1])[:, 0]
        like = np.abs(a - b) <= cfg.max_photo_diff
    if cfg.max_fb_error_px is None:
        return seen, like, np.zeros(len(at))
    h, w = query.shape
    bwd, s = _flow(query, ref, flow, scale)
    back = seen + _flow_at(bwd, s, seen)
    err = np.linalg.norm(back - at, axis=1)
    keep = like & (err < cfg.max_fb_error_px)
    keep &= (seen[:, 0] >= 0) & (seen[:, 0] <= w - 1) & (seen[:, 1] >= 0) & (seen[:, 1] <= h - 1)
    return seen, keep, err


def thin(count: int, err: np.ndarray, cfg: AlignConfig) -> np.ndarray:
    """Indices of the ``count`` pairs PnP gets under ``cfg.max_pairs``: evenly spaced in their order (the pairs
    come in raster order, so this thins evenly over the image) or the lowest forward-backward errors ``err``."""
    if not cfg.max_pairs or count <= cfg.max_pairs:
        return np.arange(count)
    if cfg.thinning == "confidence":
        return np.sort(np.argsort(err, kind="stable")[: cfg.max_pairs])
    return np.unique(np.linspace(0, count - 1, cfg.max_pairs).round().astype(np.int64))


ROBUST_SCALE_STEPS = (4.0, 2.0, 1.0)
"""The polish (AlignConfig.robust_px) anneals its Cauchy scale through these multiples of the final one."""
ROBUST_STEPS = 10
"""Gauss-Newton steps per scale at most (each scale stops once a step moves the pose by nothing)."""


PairSource = Callable[[np.ndarray, int], tuple[np.ndarray, np.ndarray, np.ndarray]]
"""(pose (4, 4), round) -> world points (M, 3), query pixels (M, 2), forward-backward errors (M,)."""


def refine_pose(
    start_c2w: np.ndarray, intrinsics: Intrinsics, pairs: PairSource, cfg: AlignConfig, rounds: int | None = None
) -> Alignment:
    """The camera-to-world ``start_c2w`` (4, 4) refined by PnP on ``pairs(pose, round)`` (pixels of a camera
    with ``intrinsics``), ``rounds`` times (default ``cfg.rounds``) each from the last pose, under the guards."""
    start = np.asarray(start_c2w, np.float64)
    if start.shape != (4, 4) or not np.all(np.isfinite(start)):
        raise ValueError(f"pose must be a finite (4, 4) camera-to-world, got shape {start.shape}")
    K = intrinsics.K
    pose, points, inliers = start, 0, 0
    used: tuple[np.ndarray, np.ndarray] | None = None
    for r in range(cfg.rounds if rounds is None else rounds):
        X, uv, err = pairs(pose, r)
        points = len(X)
        if points < cfg.min_points:
            return Alignment(start, "few_points", points)
        use = thin(points, err, cfg)
        if len(use) < points:
            X, uv = X[use], uv[use]
        w2c = invert_pose(pose)
        rvec0, _ = cv2.Rodrigues(w2c[:3, :3])
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            X,
            uv,
            K,
            None,
            rvec0,
            w2c[:3, 3].reshape(3, 1).copy(),
            useExtrinsicGuess=True,
            iterationsCount=cfg.ransac_iterations,
            reprojectionError=cfg.reproj_px,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
        inliers = 0 if inl is None else len(inl)
        if not ok or inliers < max(cfg.min_points, cfg.min_inlier_ratio * len(X)):
            return Alignment(start, "no_fit", points, inliers)
        idx = inl[:, 0]
        used = X[idx], uv[idx]
        if cfg.refine_lm:
            rvec, tvec = cv2.solvePnPRefineLM(X[idx], uv[idx], K, None, rvec, tvec)
        if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
            return Alignment(start, "no_fit", points, inliers)
        if cfg.robust_px is not None:  # over all pairs: its steps only lower the cost, so the pose stays finite
            scales = tuple(m * cfg.robust_px for m in ROBUST_SCALE_STEPS)
            rvec, tvec = refine_pose_robust(uv, X, K, rvec.reshape(3), tvec.reshape(3), scales, ROBUST_STEPS)
            _, _, e = reprojection(X, uv, K, cv2.Rodrigues(rvec)[0], tvec)
            used = X[e < cfg.reproj_px], uv[e < cfg.reproj_px]
        last, pose = pose, invert_pose(make_pose(cv2.Rodrigues(rvec)[0], tvec.reshape(3)))
        dt, dr = pose_error(pose, start)
        if dt > cfg.max_shift_m or dr > cfg.max_shift_deg:
            return Alignment(start, "too_far", points, inliers, dt, dr)
        if cfg.converged_m > 0 or cfg.converged_deg > 0:
            st, sr = pose_error(pose, last)
            if st < cfg.converged_m and sr < cfg.converged_deg:
                break
    dt, dr = pose_error(pose, start)
    cov = pose_covariance(used[0], used[1], intrinsics, pose) if used is not None else None
    return Alignment(pose, "aligned", points, inliers, dt, dr, covariance=cov)


def gray8(rgb: np.ndarray) -> np.ndarray:
    """An RGB image (H, W, 3) in [0, 1] as (H, W) uint8 gray."""
    return cv2.cvtColor((np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def align_to_render(
    render_rgb: np.ndarray,
    render_alpha: np.ndarray,
    render_depth: np.ndarray,
    image: np.ndarray,
    k: Intrinsics,
    pose_c2w: np.ndarray,
    cfg: AlignConfig = RENDER_ALIGN,
) -> Alignment:
    """Correct ``pose_c2w`` (4, 4) from a render of the map at that pose (rgb (H, W, 3), alpha (H, W), camera
    depth (H, W)) and the captured ``image`` (H, W, 3) in [0, 1], both with intrinsics ``k``: one round of flow
    from the render to the image and PnP on (rendered 3D point, observed pixel)."""
    h, w = k.height, k.width
    if (
        render_rgb.shape != (h, w, 3)
        or image.shape != (h, w, 3)
        or render_alpha.shape != (h, w)
        or render_depth.shape != (h, w)
    ):
        raise ValueError(
            f"render {render_rgb.shape}, alpha {render_alpha.shape}, depth {render_depth.shape} and image "
            f"{image.shape} must all match the {h}x{w} intrinsics"
        )
    pose = np.asarray(pose_c2w, np.float64)
    a, b = gray8(render_rgb), gray8(image)
    ys, xs = sample_grid(h, w, cfg.sample_step_px)
    grad = gradient(a)
    z = render_depth[ys, xs].astype(np.float64)
    use = (
        (render_alpha[ys, xs] >= cfg.min_alpha) & np.isfinite(z) & (z > MIN_DEPTH_M) & (grad[ys, xs] > cfg.min_gradient)
    )
    n = int(use.sum())
    opaque = render_alpha >= cfg.min_alpha
    mse = float(np.mean((render_rgb[opaque] - image[opaque]) ** 2)) if opaque.any() else float("inf")
    coverage = float(np.mean(render_alpha >= COVERED_ALPHA))
    if n < cfg.min_points:
        return Alignment(pose, "few_points", n, mse=mse)
    if mse > cfg.max_mse or coverage < cfg.min_coverage:
        return Alignment(pose, "unlike", n, mse=mse)
    at = np.stack([xs[use].astype(np.float64), ys[use].astype(np.float64)], axis=1)
    X = k.unproject(at, z[use]) @ pose[:3, :3].T + pose[:3, 3]

    def pairs(_pose: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        seen, keep, err = flow_to_query(a, b, at, dis_flow(cfg), cfg, cfg.first_flow_scale if r == 0 else 1.0)
        return X[keep], seen[keep], err[keep]

    return replace(refine_pose(pose, k, pairs, cfg, rounds=1), mse=mse)
