"""The keyframe's pose, corrected against the map before the map is fitted to the keyframe.

Stage 1 poses are a few centimetres off; fitting the Gaussians to an image seen from a pose that far off smears
the map, and the photometric guard cannot tell (the keyframe itself does get better). So the map is rendered from the
estimated pose (colour and depth), dense optical flow carries each rendered pixel to where the camera
actually saw it, and PnP on (rendered 3D point, observed pixel) pairs gives the pose the image was taken
from (bench/refine.md has the measured corrections).

A large correction means the estimated pose disagreed with the map: such a keyframe is not used
(a flow field cannot bridge a gross error, so the corrected pose would not be trustworthy either).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import invert_pose, make_pose, pose_error

MIN_ALPHA = 0.8
"""Rendered pixels used: nearly opaque (a surface the map knows; bench/refine.md)..."""
MIN_GRADIENT = 20.0
"""...and textured (Sobel magnitude of the 8-bit render; flow is undetermined on flat colour)."""
SAMPLE_STEP = 2
MIN_POINTS = 400
"""Fewer textured points than this (a small or plain image) do not pin the pose better than the localizer did
(bench/refine.md)."""
MIN_INLIER_RATIO = 0.5
REPROJ_PX = 1.0
"""RANSAC threshold at the render's resolution (flow errors are sub-pixel on textured pixels)."""
MAX_MSE = 0.01
"""The flow between a render and a photograph is trusted only where the map already explains the photograph (MSE
over the opaque rendered pixels; 20 dB PSNR; bench/refine.md)."""
MIN_COVERAGE = 0.5
"""...and only where the map covers most of the view (share of the render with alpha >= 0.5): on a partial view the
points constrain the pose poorly (bench/refine.md)."""
MAX_SHIFT_M = 0.15
MAX_SHIFT_DEG = 3.0
"""A correction beyond these means the pose was wrong, not imprecise."""


@dataclass(frozen=True)
class Alignment:
    """pose (4, 4) the corrected camera-to-world (the input pose unless ``status`` is 'aligned'); status:
    'aligned', 'few_points' (too little texture the map covers: pose kept), 'unlike' (the render does not resemble
    the image well enough, or covers too little of it, to trust a flow between them: pose kept), 'no_fit' (PnP failed
    or too few inliers: pose kept), 'too_far' (the correction exceeded the limits: do not use the keyframe)."""

    pose: np.ndarray
    status: str
    mse: float = float("nan")
    points: int = 0
    inliers: int = 0
    shift_m: float = 0.0
    shift_deg: float = 0.0


def _gray8(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor((np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def align_pose(
    render_rgb: np.ndarray,
    render_alpha: np.ndarray,
    render_depth: np.ndarray,
    image: np.ndarray,
    k: Intrinsics,
    pose_c2w: np.ndarray,
    max_shift_m: float = MAX_SHIFT_M,
    max_shift_deg: float = MAX_SHIFT_DEG,
    max_mse: float = MAX_MSE,
) -> Alignment:
    """Correct ``pose_c2w`` (4, 4) from a render of the map at that pose (rgb (H, W, 3), alpha (H, W), camera
    depth (H, W)) and the captured ``image`` (H, W, 3) in [0, 1], both with intrinsics ``k``."""
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
    a, b = _gray8(render_rgb), _gray8(image)
    ys, xs = np.mgrid[0:h:SAMPLE_STEP, 0:w:SAMPLE_STEP]
    grad = np.hypot(cv2.Sobel(a, cv2.CV_32F, 1, 0), cv2.Sobel(a, cv2.CV_32F, 0, 1))
    z = render_depth[ys, xs].astype(np.float64)
    use = (render_alpha[ys, xs] >= MIN_ALPHA) & np.isfinite(z) & (z > 1e-3) & (grad[ys, xs] > MIN_GRADIENT)
    n = int(use.sum())
    opaque = render_alpha >= MIN_ALPHA
    mse = float(np.mean((render_rgb[opaque] - image[opaque]) ** 2)) if opaque.any() else float("inf")
    coverage = float(np.mean(render_alpha >= 0.5))
    if n < MIN_POINTS:
        return Alignment(pose, "few_points", mse, n)
    if mse > max_mse or coverage < MIN_COVERAGE:
        return Alignment(pose, "unlike", mse, n)
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(a, b, None)
    u, v, z = xs[use].astype(np.float64), ys[use].astype(np.float64), z[use]
    X = k.unproject(np.stack([u, v], axis=1), z) @ pose[:3, :3].T + pose[:3, 3]
    seen = np.stack([u + flow[ys, xs, 0][use], v + flow[ys, xs, 1][use]], axis=1)
    w2c = invert_pose(pose)
    rvec0, _ = cv2.Rodrigues(w2c[:3, :3])
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        X,
        seen,
        k.K,
        None,
        rvec0,
        w2c[:3, 3].reshape(3, 1).copy(),
        useExtrinsicGuess=True,
        iterationsCount=100,
        reprojectionError=REPROJ_PX,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    n_in = 0 if inl is None else len(inl)
    if (
        not ok
        or n_in < max(MIN_POINTS, MIN_INLIER_RATIO * n)
        or not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec)))
    ):
        return Alignment(pose, "no_fit", mse, n, n_in)
    new = invert_pose(make_pose(cv2.Rodrigues(rvec)[0], tvec))
    dt, dr = pose_error(new, pose)
    if dt > max_shift_m or dr > max_shift_deg:
        return Alignment(pose, "too_far", mse, n, n_in, dt, dr)
    return Alignment(new, "aligned", mse, n, n_in, dt, dr)
