"""A keyframe's depth re-measured from its neighbouring keyframes: flow, then triangulation with the known poses.

Why: keyframe alignment (acesplat.align.keyframe_align) takes the 3D points from the keyframe's depth, and that
depth comes from the SCR head, whose error of a few centimetres moves a warp by about a pixel and aligned poses
by centimetres (bench/herz_gap.md). The mapping poses are exact, so each keyframe pixel found in a neighbour by
the same warp + flow is triangulated along its own ray; the flow's sub-pixel error then sets the depth error,
not the head.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from acesplat.align.flow_pnp import KEYFRAME_ALIGN, dis_flow
from acesplat.align.keyframe_align import (
    MAX_VIEW_ANGLE_DEG,
    Corners,
    Keyframe,
    corner_tracks,
    keyframe_corners,
    keyframe_highpass,
    keyframe_matches,
    resample_to,
)
from acesplat.core.geometry import invert_pose, transform_points
from acesplat.core.grid import OUTPUT_STRIDE

NEIGHBOURS = 2
BASELINE_RATIO = 0.1
"""Neighbours are the keyframes whose baseline is nearest this fraction of the scene depth (and that look within
MAX_VIEW_ANGLE_DEG): the adjacent frame of a dense sequence shows too little parallax to triangulate
(bench/herz_gap.md)."""
MIN_PARALLAX_PX_PER_DEPTH = 2.0
"""A pixel is triangulated only if a depth change of 100% moves it this far in the neighbour (a baseline that
shows the depth at all); at 0.1 px of flow noise and 2 px that is 5% of the depth at worst."""
CORNER_NEIGHBOURS = 4
"""Keyframes a keyframe's corners are triangulated with (triangulate_corners; bench/align.md: 2 left herzjesu25's
sparse alignment at 1.65 cm median, 3-4 brought it to 0.83-0.93 cm)."""
TRIANGULATION_TRACKING = replace(KEYFRAME_ALIGN, lk_window_px=21)
"""Lucas-Kanade between keyframes for triangulate_corners: a wider window than the query's, across their wider
baselines (bench/align.md: 21 px here and 15 px for the query gave herzjesu25 0.87 cm and fountain11 0.28 cm;
15 px for both 0.90 and 0.50 cm)."""
MIN_SAMPLES = 2
"""Triangulated samples a cell needs before its depth is replaced (their median); other cells keep theirs."""
MAX_CHANGE = 0.25
"""A triangulated depth more than this fraction away from the head's is a mismatch, not a correction."""


def depth_neighbours(c2ws: np.ndarray, i: int, depth: float, k: int = NEIGHBOURS) -> list[int]:
    """Up to ``k`` cameras of c2ws (N, 4, 4) to triangulate camera ``i``'s depth with: baselines nearest
    BASELINE_RATIO x ``depth``, viewing directions within MAX_VIEW_ANGLE_DEG; never ``i`` itself."""
    c = np.asarray(c2ws, np.float64)
    ratio = np.linalg.norm(c[:, :3, 3] - c[i, :3, 3], axis=1) / max(depth, 1e-9)
    angle = np.degrees(np.arccos(np.clip(c[:, :3, 2] @ c[i, :3, 2], -1.0, 1.0)))
    ok = (angle <= MAX_VIEW_ANGLE_DEG) & (ratio > 0)
    order = [int(j) for j in np.argsort(np.abs(ratio - BASELINE_RATIO), kind="stable") if ok[j] and j != i]
    return order[:k]


def triangulate_along_rays(
    uv: np.ndarray, kf: Keyframe, seen: np.ndarray, K_nb: np.ndarray, c2w_nb: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Depth (M,) along the keyframe's rays through pixels uv (M, 2) that best reproject to ``seen`` (M, 2) in a
    neighbour (intrinsics K_nb (3, 3), camera-to-world (4, 4)), and the pixels per unit relative depth (M,)."""
    k = kf.intrinsics
    ray = np.stack([(uv[:, 0] - k.cx) / k.fx, (uv[:, 1] - k.cy) / k.fy, np.ones(len(uv))], axis=1)  # z = 1
    T = invert_pose(c2w_nb) @ kf.c2w
    a = (ray @ T[:3, :3].T) @ K_nb.T  # pixel-homogeneous direction per unit depth
    b = K_nb @ T[:3, 3]  # pixel-homogeneous offset
    # u (a2 z + b2) = a0 z + b0 and v (a2 z + b2) = a1 z + b1: least squares in z over both.
    A = np.stack([seen[:, 0] * a[:, 2] - a[:, 0], seen[:, 1] * a[:, 2] - a[:, 1]], axis=1)
    B = np.stack([b[0] - seen[:, 0] * b[2], b[1] - seen[:, 1] * b[2]], axis=1)
    den = np.sum(A * A, axis=1)
    z = np.where(den > 0, np.sum(A * B, axis=1) / np.where(den > 0, den, 1.0), np.nan)
    # Sensitivity: how far the projection moves per relative depth change, z * |d pixel / d z|.
    h = a[:, 2:3] * z[:, None] + b[2]
    p = (a[:, :2] * z[:, None] + b[:2]) / h
    dp = (a[:, :2] * h - (a[:, :2] * z[:, None] + b[:2]) * a[:, 2:3]) / (h * h)
    sens = np.abs(z) * np.linalg.norm(dp, axis=1)
    ok = np.isfinite(z) & (z > 0) & (h[:, 0] > 0) & np.all(np.isfinite(p), axis=1)
    return np.where(ok, z, np.nan), np.where(ok, sens, 0.0)


def refine_depth(kf: Keyframe, neighbours: Sequence[Keyframe]) -> np.ndarray:
    """The keyframe's depth grid (h, w) with every cell that enough neighbour pixels triangulate replaced by their
    median; ``neighbours`` are other keyframes (their images and exact poses; their depths are not used)."""
    flow = dis_flow(KEYFRAME_ALIGN)
    gh, gw = kf.depth.shape
    first = OUTPUT_STRIDE / 2.0
    cells, depths = [], []
    for nb in neighbours:
        query = resample_to(nb.gray, nb.intrinsics, kf.intrinsics)
        uv, z_head, seen, _ = keyframe_matches(query, nb.c2w, kf, flow)
        if not len(uv):
            continue
        z, sens = triangulate_along_rays(uv, kf, seen, kf.intrinsics.K, nb.c2w)
        ok = (sens >= MIN_PARALLAX_PX_PER_DEPTH) & (np.abs(z - z_head) <= MAX_CHANGE * z_head)
        cx = np.clip(np.rint((uv[ok, 0] - first) / kf.stride).astype(np.int64), 0, gw - 1)
        cy = np.clip(np.rint((uv[ok, 1] - first) / kf.stride).astype(np.int64), 0, gh - 1)
        cells.append(cy * gw + cx)
        depths.append(z[ok])
    out = kf.depth.astype(np.float32).copy()
    if not cells:
        return out
    cell, z = np.concatenate(cells), np.concatenate(depths)
    order = np.argsort(cell, kind="stable")
    cell, z = cell[order], z[order]
    starts = np.flatnonzero(np.r_[True, cell[1:] != cell[:-1]])
    counts = np.diff(np.r_[starts, len(cell)])
    flat = out.reshape(-1)
    for s, n in zip(starts[counts >= MIN_SAMPLES], counts[counts >= MIN_SAMPLES]):
        flat[cell[s]] = np.median(z[s : s + n])
    return out


def triangulate_corners(kf: Keyframe, neighbours: Sequence[Keyframe], count: int) -> Corners:
    """The keyframe's corners (acesplat.align.keyframe_align.keyframe_corners) with each one's depth triangulated
    from where Lucas-Kanade finds it in ``neighbours`` (their images and exact poses), stored in ``kf.cache`` for
    the sparse matcher: the depth grid is interpolated between cells, and corners sit where depth and texture
    change within one. A corner keeps its grid depth where no neighbour shows it with enough parallax or the
    triangulation strays past MAX_CHANGE; several neighbours' depths are averaged, weighted by parallax squared.
    The result's ``triangulated`` is set (all False without corners or neighbours), so it is made once."""
    c = keyframe_corners(kf, count)
    if not len(c.uv) or not neighbours:
        out = replace(c, triangulated=np.zeros(len(c.uv), bool))
        kf.cache[("corners", count)] = out
        return out
    uv = c.uv.astype(np.float64)
    z_grid = transform_points(invert_pose(kf.c2w), c.X)[:, 2]
    num, den = np.zeros(len(uv)), np.zeros(len(uv))
    for nb in neighbours:
        idx, seen, _ = corner_tracks(keyframe_highpass(nb), nb.intrinsics, nb.c2w, kf, c, TRIANGULATION_TRACKING)
        if not len(idx):
            continue
        z, sens = triangulate_along_rays(uv[idx], kf, seen, nb.intrinsics.K, nb.c2w)
        ok = (sens >= MIN_PARALLAX_PX_PER_DEPTH) & (np.abs(z - z_grid[idx]) <= MAX_CHANGE * z_grid[idx])
        w = sens[ok] ** 2
        np.add.at(num, idx[ok], w * z[ok])
        np.add.at(den, idx[ok], w)
    z = np.where(den > 0, num / np.where(den > 0, den, 1.0), z_grid)
    out = replace(c, X=transform_points(kf.c2w, kf.intrinsics.unproject(uv, z)), triangulated=den > 0)
    kf.cache[("corners", count)] = out
    return out
