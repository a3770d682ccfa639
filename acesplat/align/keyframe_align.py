"""A localized pose refined against the mapping images: warp, dense flow, PnP (torch-free).

Why: the SCR head's coordinates for a view it never saw are off by a pixel or two coherently over whole
regions, which no pose solver averages out: test frames land centimetres off where training frames land within
one (bench/herz_gap.md). The training views themselves are known exactly (their
poses are the mapping input) and the head gives their depth to about a pixel, so each of the nearest
training views is re-rendered at the estimated pose (acesplat.align.depth_warp), dense optical flow carries
its pixels to where the query actually shows them, and PnP on (training pixel's 3D point, query pixel)
pairs gives the refined pose; repeated from the refined pose. The flow is sub-pixel on texture and the
3D points depend on the head's depth only through the small parallax between the training view and the
query, so the SCR pose's coherent error does not carry over; the keyframes' depth is re-measured between them
first (acesplat.align.keyframe_depth). The gain on herzjesu25 and the built-in room is in bench/herz_gap.md.

The query is first resampled to each training view's intrinsics (a homography, exact for pinhole
cameras), so cameras with other calibrations align too.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from acesplat.align.depth_warp import forward_map, pixel_map, warp_to_camera
from acesplat.align.flow_pnp import (
    DENSE_ROUNDS,
    KEYFRAME_ALIGN,
    AlignConfig,
    Alignment,
    bilinear,
    dis_flow,
    flow_to_query,
    gradient,
    refine_pose,
    sample_grid,
)
from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob, knob_default
from acesplat.core.geometry import invert_pose, transform_points
from acesplat.core.grid import OUTPUT_STRIDE, grid_correspondences
from acesplat.core.pnp import PnPConfig, PnPResult
from acesplat.core.pose_refine import reprojection

KEYFRAMES = 4
"""Training views used per query: one alone overlaps too little at a trajectory's ends (bench/herz_gap.md)."""
MAX_VIEW_ANGLE_DEG = 30.0
"""A training view looking more than this away from the query shows too little of the same scene to warp."""
QUERY_DEPTH_MEDIAN = 3
"""Median filter (cells) over the query's SCR depth before it warps a keyframe (``warp`` query): one wrong cell
would tear the warp around it."""
DENSE_FALLBACK_STATUSES = ("few_points",)
"""A sparse alignment that ends so is tried again with the dense matcher: too few corners to track (small or plain
images), where every textured pixel may still be enough."""
REWARP_STATUSES = ("few_points", "no_fit")
"""A query-depth warp (``warp`` query) that ends so is tried again with the keyframes' own depth: the SCR depth can be
wrong over whole regions (bench/align.md), the keyframes' is not."""
HIDDEN_DEPTH_RATIO = 0.1
"""With the query's depth warping (``warp`` query), a keyframe pixel whose own depth differs from the depth the query
puts there by more than this fraction shows another surface (one of the two views does not see it)."""
CORNER_QUALITY = 0.01
"""Sparse matcher: a corner's Shi-Tomasi score is at least this share of the keyframe's strongest."""
CORNER_SPACING_PX = 5
"""Sparse matcher: corners of a keyframe are at least this far apart (px)."""
LK_LEVELS = (2, 1)
"""Sparse matcher: pyramid levels above full size that Lucas-Kanade starts from, in the first round (a start pose
off by a few times its window) and in later ones (from a pose already refined)."""
LK_HIGHPASS_SIGMA = 6.0
"""Sparse matcher: both images lose their blur at this sigma (px) before Lucas-Kanade, which assumes equal
brightness where DIS compares zero-mean patches (bench/align.md: 0.98 -> 0.78 px median residual on herzjesu25)."""
LK_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
"""Sparse matcher: Lucas-Kanade stops after 30 iterations or a step under 0.01 px per level."""
DEPTH_EDGE_RATIO = 0.05
"""Sparse matcher: a corner whose depth a cell away varies by more than this fraction lies on a depth edge, where
the interpolated depth belongs to neither surface."""
PLANE_TOLERANCE = 0.03
"""Sparse matcher: depth cells within this fraction of the median depth of a keyframe's plane belong to it."""
PLANE_RANSAC_ITERATIONS = 64
"""Sparse matcher: plane hypotheses tried per keyframe."""
PLANE_SCORE_POINTS = 2000
"""Sparse matcher: hypotheses are scored on at most this many of the keyframe's depth cells (all refine the best)."""
ROTATION_WEIGHT = 0.25
"""Weight of the angle between viewing directions against the baseline's parallax (baseline / depth, radians) when
keyframes are ranked by viewpoint change: a keyframe's depth error moves its warp by the parallax only (a rotation
warps without depth), so the baseline counts most; the angle only breaks ties on a turn."""


@dataclass(frozen=True)
class Keyframe:
    """A mapping image with its known pose and a depth grid.

    gray (H, W) uint8 at the map's resolution; intrinsics of it; c2w (4, 4); depth (h, w) float32 z-depth at
    the prediction cells spaced ``stride`` px apart (acesplat.core.grid.cell_centers), 0 where unknown.
    cache: what the sparse matcher derives from the keyframe (its corners and plane), made on first use; a copy
    (dataclasses.replace) starts without.
    """

    gray: np.ndarray
    intrinsics: Intrinsics
    c2w: np.ndarray
    depth: np.ndarray
    stride: int
    cache: dict = field(default_factory=dict, init=False, compare=False, repr=False)


def nearest_keyframes(
    c2ws: np.ndarray,
    pose_c2w: np.ndarray,
    k: int = KEYFRAMES,
    max_angle_deg: float = MAX_VIEW_ANGLE_DEG,
    depth: float | None = None,
) -> list[int]:
    """Indices of up to ``k`` cameras c2ws (N, 4, 4) nearest to ``pose_c2w`` (4, 4) whose viewing direction is
    within ``max_angle_deg`` of it, nearest first.

    Nearest by centre distance, or, given the scene's typical ``depth`` in front of the query, by the change of
    viewpoint in radians: the angle between viewing directions plus the baseline's parallax, baseline / depth.
    On the built-in room's turns the cameras nearest by centre were 7-27 degrees apart, and a keyframe's depth
    error moves the result with the viewpoint change.
    """
    c2ws = np.asarray(c2ws, np.float64)
    if c2ws.ndim != 3 or c2ws.shape[1:] != (4, 4):
        raise ValueError(f"c2ws must be (N, 4, 4), got {c2ws.shape}")
    d = np.linalg.norm(c2ws[:, :3, 3] - pose_c2w[:3, 3], axis=1)
    angle = np.arccos(np.clip(np.einsum("ni,i->n", c2ws[:, :3, 2], pose_c2w[:3, 2]), -1.0, 1.0))
    ok = np.degrees(angle) <= max_angle_deg
    score = d if depth is None or not depth > 0 else ROTATION_WEIGHT * angle + d / depth
    order = [int(i) for i in np.argsort(score, kind="stable") if ok[i]]
    return order[:k]


def scene_depth(points: np.ndarray, pose_c2w: np.ndarray) -> float | None:
    """Median z-depth of scene points (N, 3) in front of the camera ``pose_c2w`` (4, 4); None if none are."""
    w2c = invert_pose(pose_c2w)
    z = points[np.all(np.isfinite(points), axis=1)] @ w2c[2, :3] + w2c[2, 3]
    z = z[z > 0]
    return float(np.median(z)) if z.size else None


def _depth_at(kf: Keyframe, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The keyframe's depth interpolated at pixels (u, v) (N,); 0 next to an unknown cell."""
    first = OUTPUT_STRIDE / 2.0  # pixel of cell 0 on either axis (acesplat.core.grid.cell_centers)
    gx, gy = (u - first) / kf.stride, (v - first) / kf.stride
    d = kf.depth.astype(np.float64)
    stacked = np.stack([d, (d > 0).astype(np.float64)], axis=-1)
    z, known = bilinear(stacked, gx, gy).T
    return np.where(known > 1.0 - 1e-9, z, 0.0)


def resample_to(gray: np.ndarray, src: Intrinsics, dst: Intrinsics) -> np.ndarray:
    """The image (H, W) uint8 taken with ``src`` as the same camera with ``dst`` intrinsics would see it."""
    if src == dst:
        return gray
    H = dst.K @ np.linalg.inv(src.K)
    return cv2.warpPerspective(gray, H, (dst.width, dst.height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def keyframe_matches(
    query: np.ndarray,
    pose_c2w: np.ndarray,
    kf: Keyframe,
    flow: cv2.DISOpticalFlow,
    cfg: AlignConfig = KEYFRAME_ALIGN,
    scale: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The keyframe's textured pixels (M, 2) with their depth (M,), where the query (H, W) uint8, already at
    the keyframe's intrinsics and seen from ``pose_c2w`` (4, 4), shows them (M, 2), and the flow's
    forward-backward error there (M,) px (acesplat.align.flow_pnp.flow_to_query; ``scale`` < 1: a coarse flow)."""
    h, w = kf.gray.shape
    fmap = forward_map(kf.depth, kf.intrinsics, kf.stride, kf.c2w, pose_c2w)  # keyframe pixel -> query pixel
    warped, valid = warp_to_camera(
        kf.gray, kf.depth, kf.intrinsics, kf.stride, kf.c2w, pose_c2w, cfg.warp_step_px, forward=fmap
    )
    ys, xs = sample_grid(h, w, cfg.sample_step_px)
    u, v = xs.ravel().astype(np.float64), ys.ravel().astype(np.float64)
    at = fmap[ys.ravel(), xs.ravel()].astype(np.float64)
    inside = np.isfinite(at).all(1) & (at[:, 0] >= 0) & (at[:, 0] <= w - 1) & (at[:, 1] >= 0) & (at[:, 1] <= h - 1)
    u, v, at = u[inside], v[inside], at[inside]
    ai = np.rint(at).astype(np.int64)
    keep = valid[ai[:, 1], ai[:, 0]] & (gradient(warped)[ai[:, 1], ai[:, 0]] > cfg.min_gradient)
    u, v, at = u[keep], v[keep], at[keep]
    z = _depth_at(kf, u, v)
    known = (z > 0) & np.isfinite(z)
    u, v, at, z = u[known], v[known], at[known], z[known]
    seen, ok, err = flow_to_query(warped, query, at, flow, cfg, scale)
    return np.stack([u[ok], v[ok]], axis=1), z[ok], seen[ok], err[ok]


@dataclass(frozen=True)
class Corners:
    """What the sparse matcher tracks from a keyframe: corner pixels uv (M, 2) float32 with their world points
    X (M, 3), the keyframe's dominant plane (4,) (n, d: n . X = d, |n| = 1, in its camera frame) or None."""

    uv: np.ndarray
    X: np.ndarray
    plane: np.ndarray | None
    triangulated: np.ndarray | None = None
    """(M,) bool: whose depth neighbouring keyframes triangulated (acesplat.align.keyframe_depth); None: not tried."""


def keyframe_corners(kf: Keyframe, count: int) -> Corners:
    """The keyframe's ``count`` strongest corners with a known depth off depth edges, and its plane; made once per
    keyframe and count (kept in ``kf.cache``, where a keyframe set may have put them triangulated between
    keyframes first: acesplat.align.keyframe_depth.triangulate_corners)."""
    key = ("corners", count)
    if key not in kf.cache:
        pts = cv2.goodFeaturesToTrack(kf.gray, count, CORNER_QUALITY, CORNER_SPACING_PX)
        uv = np.zeros((0, 2)) if pts is None else pts.reshape(-1, 2).astype(np.float64)
        z = _depth_at(kf, uv[:, 0], uv[:, 1])
        s = float(kf.stride)
        around = [_depth_at(kf, uv[:, 0] + dx, uv[:, 1] + dy) for dx, dy in ((-s, -s), (s, -s), (-s, s), (s, s))]
        lo, hi = np.minimum.reduce([z, *around]), np.maximum.reduce([z, *around])
        keep = (lo > 0) & np.isfinite(hi) & (hi <= (1.0 + DEPTH_EDGE_RATIO) * lo)
        uv, z = uv[keep], z[keep]
        X = transform_points(kf.c2w, kf.intrinsics.unproject(uv, z))
        kf.cache[key] = Corners(uv.astype(np.float32), X, keyframe_plane(kf))
    return kf.cache[key]


def keyframe_highpass(kf: Keyframe) -> np.ndarray:
    """The keyframe's image (H, W) uint8 as Lucas-Kanade compares it (highpass), made once (kept in ``kf.cache``)."""
    if "highpass" not in kf.cache:
        kf.cache["highpass"] = highpass(kf.gray)
    return kf.cache["highpass"]


def keyframe_plane(kf: Keyframe) -> np.ndarray | None:
    """The keyframe's dominant plane in its camera frame, (4,) n, d with n . X = d and |n| = 1: RANSAC over its
    depth cells (inliers within PLANE_TOLERANCE of the median depth), refined on its inliers; None without
    three cells of depth."""
    hh, ww = kf.depth.shape
    first = OUTPUT_STRIDE / 2.0
    gy, gx = np.mgrid[0:hh, 0:ww]
    z = kf.depth.ravel().astype(np.float64)
    ok = z > 0
    if ok.sum() < 3:
        return None
    uv = np.stack([first + gx.ravel() * kf.stride, first + gy.ravel() * kf.stride], axis=1)[ok]
    P = kf.intrinsics.unproject(uv, z[ok])
    tol = PLANE_TOLERANCE * float(np.median(z[ok]))
    rng = np.random.default_rng(0)
    idx = rng.integers(0, len(P), (PLANE_RANSAC_ITERATIONS, 3))
    a, b, c = P[idx[:, 0]], P[idx[:, 1]], P[idx[:, 2]]
    S = P if len(P) <= PLANE_SCORE_POINTS else P[rng.choice(len(P), PLANE_SCORE_POINTS, replace=False)]
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    good = norm > 1e-12
    if not good.any():
        return None
    n, a = n[good] / norm[good, None], a[good]
    d = np.einsum("ij,ij->i", n, a)
    counts = (np.abs(S @ n.T - d) < tol).sum(axis=0)
    best = int(np.argmax(counts))
    inl = P[np.abs(P @ n[best] - d[best]) < tol]
    if len(inl) < 3:
        return None
    centre = inl.mean(axis=0)
    normal = np.linalg.svd(inl - centre, full_matrices=False)[2][-1]
    return np.r_[normal, normal @ centre]


def plane_homography(
    kf: Keyframe, plane: np.ndarray | None, intrinsics: Intrinsics, pose_c2w: np.ndarray
) -> np.ndarray | None:
    """The homography (3, 3) from keyframe pixels to the pixels of a camera with ``intrinsics`` at ``pose_c2w``
    (4, 4) induced by the keyframe's ``plane`` (keyframe_plane); None without one."""
    if plane is None or abs(plane[3]) < 1e-9:
        return None
    rel = invert_pose(pose_c2w) @ kf.c2w  # keyframe camera -> query camera
    R, t = rel[:3, :3], rel[:3, 3]
    H = intrinsics.K @ (R + np.outer(t, plane[:3]) / plane[3]) @ np.linalg.inv(kf.intrinsics.K)
    return H / H[2, 2] if abs(H[2, 2]) > 1e-12 else None


def corner_tracks(
    query: np.ndarray,
    intrinsics: Intrinsics,
    pose_c2w: np.ndarray,
    kf: Keyframe,
    corners: Corners,
    cfg: AlignConfig = KEYFRAME_ALIGN,
    levels: int = LK_LEVELS[0],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices (M,) of the keyframe's ``corners`` (keyframe_corners) found in the query (H, W) uint8 with
    ``intrinsics`` (its highpass, as keyframe_highpass), where it shows them (M, 2) and the forward-backward error
    there (M,) px: each corner is tracked by pyramidal Lucas-Kanade from the keyframe (warped to the estimate
    ``pose_c2w`` (4, 4) by its plane with ``cfg.lk_plane_warp``) to the query, starting where the estimate projects
    its point, and back; ``levels`` pyramid levels above full size."""
    h, w = query.shape
    ref, at = keyframe_highpass(kf), corners.uv
    H = plane_homography(kf, corners.plane, intrinsics, pose_c2w) if cfg.lk_plane_warp else None
    if H is not None:  # the keyframe seen from the estimate as if its scene were its dominant plane
        ref = cv2.warpPerspective(ref, H, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        q = np.c_[at, np.ones(len(at))] @ H.T
        at = (q[:, :2] / q[:, 2:3]).astype(np.float32)
    pc = transform_points(invert_pose(pose_c2w), corners.X)
    front = pc[:, 2] > 1e-6
    p0 = pc[front] @ intrinsics.K.T
    p0 = p0[:, :2] / p0[:, 2:3]
    m = cfg.lk_window_px / 2.0
    inside = (p0[:, 0] >= m) & (p0[:, 0] <= w - 1 - m) & (p0[:, 1] >= m) & (p0[:, 1] <= h - 1 - m)
    idx = np.flatnonzero(front)[inside]
    src, p0 = at[idx], p0[inside].astype(np.float32)
    if len(src) == 0:
        return idx, p0.astype(np.float64), np.zeros(0)
    seen, err, keep = track_corners(ref, query, src, p0, cfg, levels)
    return idx[keep], seen[keep], err[keep]


def highpass(gray: np.ndarray) -> np.ndarray:
    """The image (H, W) uint8 less its blur at LK_HIGHPASS_SIGMA, doubled around 128: what Lucas-Kanade compares."""
    blur = cv2.GaussianBlur(gray, (0, 0), LK_HIGHPASS_SIGMA)
    return cv2.addWeighted(gray, 2.0, blur, -2.0, 128.0)


def track_corners(
    ref: np.ndarray,
    query: np.ndarray,
    src: np.ndarray,
    start: np.ndarray,
    cfg: AlignConfig = KEYFRAME_ALIGN,
    levels: int = LK_LEVELS[0],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels ``src`` (M, 2) of ``ref`` tracked into ``query`` (both (H, W) uint8) by pyramidal Lucas-Kanade from
    ``start`` (M, 2) and back: where they are seen (M, 2), the forward-backward error (M,) px and the verdict
    keep (M,) bool (both tracks converged, inside the query, the error within ``cfg.max_fb_error_px``); ``levels``
    pyramid levels above full size."""
    h, w = query.shape
    win = (cfg.lk_window_px, cfg.lk_window_px)
    lk = dict(winSize=win, maxLevel=levels, criteria=LK_CRITERIA, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    a = np.ascontiguousarray(src, np.float32).reshape(-1, 1, 2)
    seen, ok, _ = cv2.calcOpticalFlowPyrLK(
        ref, query, a, np.ascontiguousarray(start, np.float32).reshape(-1, 1, 2), **lk
    )
    back, ok2, _ = cv2.calcOpticalFlowPyrLK(query, ref, seen, a.copy(), **lk)
    seen = seen.reshape(-1, 2).astype(np.float64)
    err = np.linalg.norm(back.reshape(-1, 2) - a.reshape(-1, 2), axis=1).astype(np.float64)
    keep = (ok.ravel() == 1) & (ok2.ravel() == 1)
    keep &= (seen[:, 0] >= 0) & (seen[:, 0] <= w - 1) & (seen[:, 1] >= 0) & (seen[:, 1] <= h - 1)
    if cfg.max_fb_error_px is not None:
        keep &= err < cfg.max_fb_error_px
    return seen, err, keep


def query_depth(coords: np.ndarray, pose_c2w: np.ndarray) -> np.ndarray:
    """The z-depth (h, w) float32 of SCR coordinates (h, w, 3) in the camera ``pose_c2w`` (4, 4), median-filtered
    over QUERY_DEPTH_MEDIAN cells; 0 where a coordinate is missing or behind the camera."""
    w2c = invert_pose(pose_c2w)
    z = coords.reshape(-1, 3).astype(np.float64) @ w2c[2, :3] + w2c[2, 3]
    z = np.where(np.isfinite(z) & (z > 0), z, 0.0).reshape(coords.shape[:2]).astype(np.float32)
    return cv2.medianBlur(z, QUERY_DEPTH_MEDIAN)


def query_correspondences(
    query: np.ndarray,
    intrinsics: Intrinsics,
    depth: np.ndarray,
    stride: int,
    pose_c2w: np.ndarray,
    kf: Keyframe,
    flow: cv2.DISOpticalFlow,
    cfg: AlignConfig = KEYFRAME_ALIGN,
    scale: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """As keyframe_correspondences, with the keyframe warped to the query's estimate ``pose_c2w`` (4, 4) by the
    query's own ``depth`` (h, w) (cells ``stride`` px apart, query_depth): each query pixel samples the keyframe
    where that depth puts it, so the warp is one remap and needs no inversion. The flow corrects the warp's depth
    error; the 3D points come from the keyframe's depth at the pixels sampled. ``query`` (H, W) uint8 at its own
    ``intrinsics`` (no resampling); pixels returned are the query's."""
    h, w = query.shape
    kh, kw = kf.gray.shape
    m = pixel_map(depth, intrinsics, stride, pose_c2w, kf.c2w, kf.intrinsics)  # query pixel -> keyframe x, y, z
    mx = np.where(np.isfinite(m[..., 0]), m[..., 0], -1.0).astype(np.float32)
    my = np.where(np.isfinite(m[..., 1]), m[..., 1], -1.0).astype(np.float32)
    warped = cv2.remap(kf.gray, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    ys, xs = (a.ravel() for a in sample_grid(h, w, cfg.sample_step_px))
    src = m[ys, xs].astype(np.float64)
    ok = np.isfinite(src).all(1) & (src[:, 0] >= 0) & (src[:, 0] <= kw - 1) & (src[:, 1] >= 0)
    ok &= src[:, 1] <= kh - 1
    ok[ok] = gradient(warped)[ys[ok], xs[ok]] > cfg.min_gradient
    ys, xs, src = ys[ok], xs[ok], src[ok]
    z = _depth_at(kf, src[:, 0], src[:, 1])
    ok = (z > 0) & (np.abs(z - src[:, 2]) <= HIDDEN_DEPTH_RATIO * src[:, 2])
    at = np.stack([xs[ok], ys[ok]], axis=1).astype(np.float64)
    seen, keep, err = flow_to_query(warped, query, at, flow, cfg, scale)
    uv, zk = src[ok][keep, :2], z[ok][keep]
    X = transform_points(kf.c2w, kf.intrinsics.unproject(uv, zk))
    return X, seen[keep], err[keep]


def keyframe_correspondences(
    query: np.ndarray,
    pose_c2w: np.ndarray,
    kf: Keyframe,
    flow: cv2.DISOpticalFlow,
    cfg: AlignConfig = KEYFRAME_ALIGN,
    scale: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points (M, 3) of the keyframe's textured pixels, where the query (H, W) uint8, already at the
    keyframe's intrinsics, shows them (M, 2) given the query's estimated pose (4, 4), and the flow's
    forward-backward error (M,) px."""
    uv, z, seen, err = keyframe_matches(query, pose_c2w, kf, flow, cfg, scale)
    X = transform_points(kf.c2w, kf.intrinsics.unproject(uv, z))
    return X, seen, err


def _check(gray: np.ndarray, intrinsics: Intrinsics, pose_c2w: np.ndarray) -> None:
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"query must be (H, W) uint8, got {gray.shape} {gray.dtype}")
    if gray.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(f"query is {gray.shape}, its intrinsics are for {(intrinsics.height, intrinsics.width)}")
    if np.shape(pose_c2w) != (4, 4) or not np.all(np.isfinite(pose_c2w)):
        raise ValueError(f"pose must be a finite (4, 4) camera-to-world, got shape {np.shape(pose_c2w)}")


def align_to_keyframes(
    gray: np.ndarray,
    intrinsics: Intrinsics,
    pose_c2w: np.ndarray,
    keyframes: Sequence[Keyframe],
    anchor: tuple[np.ndarray, np.ndarray] | None = None,
    cfg: AlignConfig = KEYFRAME_ALIGN,
    coords: tuple[np.ndarray, int] | None = None,
) -> Alignment:
    """Refine the query's camera-to-world ``pose_c2w`` (4, 4) against ``keyframes`` (nearest first, see
    nearest_keyframes); ``gray`` (H, W) uint8 is the query at the map's resolution with ``intrinsics``.

    ``anchor``: the correspondences the start pose was solved from, scene points (N, 3) and pixels (N, 2) of
    ``gray``; a refined pose that loses their inliers is refused (``cfg.min_anchor_kept``).
    ``coords``: the query's SCR coordinates (h, w, 3) and their stride, for ``cfg.warp`` 'query'."""
    _check(gray, intrinsics, pose_c2w)
    start = np.asarray(pose_c2w, np.float64)
    if not keyframes:
        return Alignment(start, "few_points")
    sparse = cfg.matcher == "sparse"  # tracks the keyframes' own corners: no warp, no resampling
    by_query = cfg.warp == "query" and coords is not None and not sparse
    cameras = set() if by_query or sparse else {kf.intrinsics for kf in keyframes}
    queries = {k: resample_to(gray, intrinsics, k) for k in cameras}  # once per distinct camera
    # keyframes in parallel only when all of them are used anyway (enough_pairs stops at the first that suffice)
    threads = 1 if cfg.enough_pairs else min(cfg.threads, len(keyframes))

    corners = {id(kf): keyframe_corners(kf, cfg.corners) for kf in keyframes} if sparse else {}
    lk_query = highpass(gray) if sparse else gray

    def one(kf: Keyframe, pose: np.ndarray, depth: np.ndarray | None, r: int) -> tuple[np.ndarray, ...]:
        if sparse:
            levels = LK_LEVELS[min(r, 1)]
            c = corners[id(kf)]
            idx, seen, err = corner_tracks(lk_query, intrinsics, pose, kf, c, cfg, levels)
            return c.X[idx], seen, err
        scale = cfg.first_flow_scale if r == 0 else 1.0
        flow = dis_flow(cfg)  # DIS holds working buffers: one per call, so threads never share one
        if depth is not None:
            return query_correspondences(gray, intrinsics, depth, coords[1], pose, kf, flow, cfg, scale)
        X, uv, err = keyframe_correspondences(queries[kf.intrinsics], pose, kf, flow, cfg, scale)
        # back to the query's own pixels, so every keyframe's pairs share one camera matrix
        uvh = np.c_[uv, np.ones(len(uv))] @ (intrinsics.K @ np.linalg.inv(kf.intrinsics.K)).T
        return X, uvh[:, :2] / uvh[:, 2:3], err

    def pairs(pose: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        depth = query_depth(coords[0], pose) if by_query else None
        if threads > 1:
            with ThreadPoolExecutor(threads, thread_name_prefix="acesplat-align") as pool:
                found = list(pool.map(lambda kf: one(kf, pose, depth, r), keyframes))
        else:
            found, total = [], 0
            for kf in keyframes:
                found.append(one(kf, pose, depth, r))
                total += len(found[-1][0])
                if cfg.enough_pairs and total >= cfg.enough_pairs:
                    break
        return tuple(np.concatenate(parts) for parts in zip(*found, strict=True))

    al = refine_pose(start, intrinsics, pairs, cfg)
    if sparse and al.status in DENSE_FALLBACK_STATUSES:
        # too few corners to track (small or plain images): every textured pixel of the dense matcher instead
        dense = replace(cfg, matcher="dense", rounds=DENSE_ROUNDS)
        return align_to_keyframes(gray, intrinsics, start, keyframes, anchor, dense, coords)
    if by_query and al.status in REWARP_STATUSES:
        # where the query's SCR depth tears the warp (too few pairs agree), the keyframes' own depth warps them
        return align_to_keyframes(gray, intrinsics, start, keyframes, anchor, replace(cfg, warp="keyframe"))
    if al.status != "aligned" or anchor is None:
        return al
    if anchor_inliers(anchor, intrinsics, al.pose) < cfg.min_anchor_kept * anchor_inliers(anchor, intrinsics, start):
        return replace(al, pose=start, status="disagrees")
    return al


@dataclass
class PreciseSettings:
    """SCR poses refined against keyframes (--align; on the edge also while tracking with a keyframe bundle): SCR +
    PnP seeds the keyframe alignment, which measures the pose on the full-size frame."""

    scr_short_side: int = knob(
        240, "Shorter side of SCR that keyframes refine (never above the input's); the alignment restores precision."
    )


def size_for_scr(size_hw: tuple[int, int], short_side: int) -> tuple[int, int]:
    """``size_hw`` (H, W) scaled to the shorter side ``short_side`` (never up), sides rounded to multiples of 8."""
    if short_side < 8:
        raise ValueError(f"short side must be at least 8, got {short_side}")
    scale = min(1.0, short_side / min(size_hw))
    return tuple(max(8, int(round(v * scale / 8)) * 8) for v in size_hw)  # type: ignore[return-value]


def scr_copy(gray: np.ndarray, intrinsics: Intrinsics, size_hw: tuple[int, int]) -> tuple[np.ndarray, Intrinsics]:
    """The network input (H, W) uint8 resized (area) to ``size_hw`` (h, w) for SCR, with its intrinsics."""
    h, w = size_hw
    return cv2.resize(gray, (w, h), interpolation=cv2.INTER_AREA), intrinsics.resized(w, h)


def align_scr_pose(
    gray: np.ndarray,
    intrinsics: Intrinsics,
    coords: np.ndarray,
    stride: int,
    pose_c2w: np.ndarray,
    near: Callable[..., Sequence[Keyframe]],
    cfg: AlignConfig = KEYFRAME_ALIGN,
    view: tuple[np.ndarray, Intrinsics] | None = None,
) -> Alignment:
    """Refine a pose solved from the SCR grid ``coords`` (h, w, 3) (cells ``stride`` px apart) of ``gray``: the
    keyframes ``near(pose, depth=..., corners=...)`` gives for the scene's depth in front of it (with the sparse
    matcher, carrying its corners triangulated between keyframes), the grid as the anchor.
    ``view``: a larger image of the same frame (H', W') uint8 with its intrinsics when SCR ran on a smaller copy;
    the alignment then runs on it, the grid's pixels mapped there (without the query-depth warp, which needs the
    grid at the view's own stride). One path for the desktop localizer and the edge runtime."""
    anchor = grid_correspondences(coords, stride)
    corners = cfg.corners if cfg.matcher == "sparse" else 0
    keyframes = near(pose_c2w, depth=scene_depth(anchor[0], pose_c2w), corners=corners)
    query_coords: tuple[np.ndarray, int] | None = (coords, stride)
    if view is not None:
        gray_v, intr_v = view
        anchor = (anchor[0], intrinsics.pixels_to(anchor[1], intr_v))
        gray, intrinsics, query_coords = gray_v, intr_v, None
    return align_to_keyframes(gray, intrinsics, pose_c2w, keyframes, anchor=anchor, cfg=cfg, coords=query_coords)


def align_scr_start(
    res: PnPResult,
    coords: np.ndarray,
    gray: np.ndarray,
    intrinsics: Intrinsics,
    stride: int,
    near: Callable[..., Sequence[Keyframe]],
    resolve: Callable[[np.ndarray, Intrinsics], tuple[PnPResult, np.ndarray]],
    cfg: AlignConfig = KEYFRAME_ALIGN,
    view: tuple[np.ndarray, Intrinsics] | None = None,
) -> tuple[PnPResult, Alignment | None, bool]:
    """The precise path after SCR + PnP: ``res`` solved from ``coords`` (h, w, 3) of ``gray``, aligned to the
    keyframes (align_scr_pose). When SCR ran on a smaller copy (``view`` the full-size frame) and the alignment does
    not take its start, ``resolve(gray, intrinsics)`` solves the full-size frame again ((result, coords)) and that
    start is aligned instead, so the smaller copy never leaves a frame worse than the full-size path.

    Returns the result with the aligned pose (the alignment's pose whatever its status, as align_to_keyframes
    keeps the start when it cannot improve it), the alignment (None when the frame is not localized) and whether the
    full-size solve ran. One path for the desktop localizer and the edge runtime."""
    if not res.localized or res.T_c2w is None:
        return res, None, False
    al = align_scr_pose(gray, intrinsics, coords, stride, res.T_c2w, near, cfg, view)
    retried = False
    if al.status != "aligned" and view is not None:
        retried = True
        res, coords = resolve(*view)
        if not res.localized or res.T_c2w is None:
            return res, None, True
        al = align_scr_pose(view[0], view[1], coords, stride, res.T_c2w, near, cfg)
    return replace(res, T_c2w=al.pose), al, retried


def anchor_inliers(anchor: tuple[np.ndarray, np.ndarray], intrinsics: Intrinsics, pose_c2w: np.ndarray) -> int:
    """How many of the correspondences (points (N, 3), pixels (N, 2)) reproject within the solver's threshold."""
    points, pixels = anchor
    finite = np.all(np.isfinite(points), axis=1)
    w2c = invert_pose(pose_c2w)
    _, _, err = reprojection(points[finite], pixels[finite], intrinsics.K, w2c[:3, :3], w2c[:3, 3])
    return int(np.count_nonzero(err < knob_default(PnPConfig, "threshold_px")))
