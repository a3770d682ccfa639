"""The shared flow + PnP alignment core (acesplat.align.flow_pnp) against analytic references: a known image shift
is what the flow recovers, and exact pairs of a known pose are what PnP returns."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from acesplat.align.flow_pnp import (
    DENSE_ALIGN,
    KEYFRAME_ALIGN,
    RENDER_ALIGN,
    TRACK_ALIGN,
    AlignConfig,
    dis_flow,
    flow_to_query,
    refine_pose,
    thin,
)
from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import invert_pose, make_pose, pose_error, rodrigues_to_matrix

K = Intrinsics.from_focal(200.0, 160, 120)
SHIFT = (3.0, -2.0)


def texture(rng: np.random.Generator, h: int = 160, w: int = 200) -> np.ndarray:
    """Smooth random texture (H, W) uint8: blurred noise, so flow has gradients everywhere."""
    noise = rng.uniform(0, 255, (h, w)).astype(np.float32)
    return np.clip(cv2.GaussianBlur(noise, (0, 0), 2.0) * 3 - 255, 0, 255).astype(np.uint8)


def shifted_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A reference (120, 160) crop, the query showing the same texture moved by SHIFT px, and pixels inside both."""
    big = texture(np.random.default_rng(0))
    ref = big[20:140, 20:180]
    dx, dy = int(SHIFT[0]), int(SHIFT[1])
    query = big[20 - dy : 140 - dy, 20 - dx : 180 - dx]
    ys, xs = np.mgrid[10:110:3, 10:150:3]
    return ref, query, np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)


def test_the_flow_recovers_a_known_shift_and_passes_the_forward_backward_check() -> None:
    ref, query, at = shifted_pair()
    # medium refines the flow variationally at full size; fast works on coarser patches, as does a half-size flow
    for cfg, scale, tol in (
        (KEYFRAME_ALIGN, 1.0, 0.05),
        (replace(KEYFRAME_ALIGN, flow_preset="fast"), 1.0, 0.2),
        (KEYFRAME_ALIGN, 0.5, 0.25),
    ):
        seen, keep, err = flow_to_query(ref, query, at, dis_flow(cfg), cfg, scale)
        assert keep.mean() > 0.9
        assert np.median(np.abs(seen[keep] - at[keep] - SHIFT), axis=0) == pytest.approx([0, 0], abs=tol)
        assert np.all(err[keep] < cfg.max_fb_error_px)
    seen, keep, err = flow_to_query(ref, query, at, dis_flow(RENDER_ALIGN), RENDER_ALIGN)
    assert keep.all() and not err.any()  # no forward-backward check in the render preset


def test_a_swapped_query_fails_the_forward_backward_check() -> None:
    ref, _, at = shifted_pair()
    other = texture(np.random.default_rng(5), 120, 160)
    _, keep, _ = flow_to_query(ref, other, at, dis_flow(KEYFRAME_ALIGN), KEYFRAME_ALIGN)
    assert keep.mean() < 0.5


def exact_pairs(true_c2w: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """n world points in front of the camera (1-4 m deep) and their exact pixels under ``true_c2w``."""
    uv = rng.uniform([0, 0], [K.width, K.height], (n, 2))
    z = rng.uniform(1.0, 4.0, n)
    Xc = K.unproject(uv, z)
    return Xc @ true_c2w[:3, :3].T + true_c2w[:3, 3], uv


def test_exact_pairs_bring_a_perturbed_pose_back_and_the_guards_hold() -> None:
    rng = np.random.default_rng(1)
    true = make_pose(rodrigues_to_matrix(np.array([0.05, -0.1, 0.02])), np.array([0.3, -0.1, 0.2]))
    X, uv = exact_pairs(true, 2000, rng)
    uv_noisy = uv + rng.normal(0, 0.2, uv.shape)
    uv_noisy[:200] += rng.uniform(-30, 30, (200, 2))  # 10% outliers
    start = make_pose(rodrigues_to_matrix(np.array([0.0, 0.01, -0.005])) @ true[:3, :3], true[:3, 3] + [0.03, 0, -0.02])
    src = lambda pose, r: (X, uv_noisy, np.zeros(len(X)))  # noqa: E731
    for cfg in (
        KEYFRAME_ALIGN,
        RENDER_ALIGN,
        replace(KEYFRAME_ALIGN, max_pairs=500, thinning="even"),
        replace(KEYFRAME_ALIGN, converged_m=1e-3, converged_deg=0.01),
    ):
        al = refine_pose(start, K, src, cfg)
        dt, dr = pose_error(al.pose, true)
        assert al.status == "aligned" and dt < 2e-3 and dr < 0.05, (cfg, dt, dr)
        assert al.points == 2000 and al.inliers >= 0.85 * min(2000, cfg.max_pairs or 2000)
        assert al.shift_m == pytest.approx(pose_error(al.pose, start)[0])
    few = refine_pose(start, K, lambda p, r: (X[:100], uv[:100], np.zeros(100)), KEYFRAME_ALIGN)
    assert few.status == "few_points" and np.array_equal(few.pose, start)
    tight = refine_pose(start, K, src, replace(KEYFRAME_ALIGN, max_shift_m=0.01))
    assert tight.status == "too_far" and np.array_equal(tight.pose, start) and tight.shift_m > 0.01
    junk = refine_pose(start, K, lambda p, r: (X, rng.uniform(0, 160, uv.shape), np.zeros(len(X))), KEYFRAME_ALIGN)
    assert junk.status == "no_fit" and np.array_equal(junk.pose, start)


def test_the_robust_polish_makes_the_pose_a_smooth_function_of_the_pairs() -> None:
    """Far points (4-16 m) with 0.6 px noise: the 1 px inlier set flips when the pixels move by 0.01 px, and LM on it
    follows; the Cauchy polish over all pairs gives one pose for all such jitters, nearer the truth."""
    rng = np.random.default_rng(3)
    true = make_pose(rodrigues_to_matrix(np.array([0.05, -0.1, 0.02])), np.array([0.3, -0.1, 0.2]))
    X, uv = exact_pairs(true, 1500, rng)
    X = true[:3, 3] + (X - true[:3, 3]) * 4.0
    uv = uv + rng.normal(0, 0.6, uv.shape)
    uv[:150] += rng.uniform(-20, 20, (150, 2))  # 10% outliers
    results = {}
    for cfg in (KEYFRAME_ALIGN, replace(KEYFRAME_ALIGN, robust_px=None)):
        poses = []
        for _ in range(6):
            start = make_pose(true[:3, :3], true[:3, 3] + [0.03, 0, -0.02] + rng.normal(0, 0.001, 3))
            jitter = uv + rng.normal(0, 0.01, uv.shape)
            al = refine_pose(start, K, lambda p, r, j=jitter: (X, j, np.zeros(len(X))), cfg)
            assert al.status == "aligned"
            poses.append(al.pose)
        spread = max(pose_error(p, poses[0])[0] for p in poses)
        results[cfg.robust_px] = spread, np.mean([pose_error(p, true)[0] for p in poses])
    spread, err = results[KEYFRAME_ALIGN.robust_px]
    assert spread < 5e-4 and err < 4e-3, results
    assert err < results[None][1], results


def test_rounds_stop_early_once_converged() -> None:
    rng = np.random.default_rng(2)
    true = invert_pose(np.eye(4))
    X, uv = exact_pairs(true, 1000, rng)
    calls: list[int] = []

    def src(pose: np.ndarray, r: int):
        calls.append(r)
        return X, uv, np.zeros(len(X))

    refine_pose(true, K, src, replace(DENSE_ALIGN, converged_m=1e-3, converged_deg=0.01))
    assert calls == [0]
    calls.clear()
    refine_pose(true, K, src, DENSE_ALIGN)
    assert calls == [0, 1]


def test_thinning_keeps_the_cap_evenly_or_the_most_confident() -> None:
    err = np.array([0.4, 0.1, 0.3, 0.0, 0.2, 0.45])
    assert thin(6, err, KEYFRAME_ALIGN).tolist() == list(range(6))
    even = replace(KEYFRAME_ALIGN, max_pairs=300, thinning="even")
    assert len(thin(1000, np.zeros(1000), even)) == 300 and thin(1000, np.zeros(1000), even)[[0, -1]].tolist() == [
        0,
        999,
    ]
    conf = replace(KEYFRAME_ALIGN, max_pairs=300, thinning="confidence")
    e = np.r_[np.zeros(300), np.ones(700)][::-1].copy()
    assert thin(1000, e, conf).tolist() == list(range(700, 1000))


def test_the_presets_hold_the_two_aligners_settings_and_bad_configs_are_refused() -> None:
    assert (KEYFRAME_ALIGN.min_points, KEYFRAME_ALIGN.ransac_iterations, KEYFRAME_ALIGN.rounds) == (300, 200, 1)
    assert (KEYFRAME_ALIGN.matcher, KEYFRAME_ALIGN.corners, KEYFRAME_ALIGN.lk_window_px) == ("sparse", 800, 15)
    assert (KEYFRAME_ALIGN.max_fb_error_px, KEYFRAME_ALIGN.max_shift_m, KEYFRAME_ALIGN.refine_lm) == (0.5, 0.5, True)
    assert KEYFRAME_ALIGN.robust_px == DENSE_ALIGN.robust_px == 0.25
    assert RENDER_ALIGN.robust_px is None and TRACK_ALIGN.robust_px is None
    assert (DENSE_ALIGN.matcher, DENSE_ALIGN.rounds) == ("dense", 2)
    assert (DENSE_ALIGN.first_flow_scale, DENSE_ALIGN.max_pairs, DENSE_ALIGN.enough_pairs) == (0.5, 5000, 0)
    assert TRACK_ALIGN.matcher == RENDER_ALIGN.matcher == "dense"
    assert (RENDER_ALIGN.min_points, RENDER_ALIGN.ransac_iterations, RENDER_ALIGN.rounds) == (400, 100, 1)
    assert (RENDER_ALIGN.max_fb_error_px, RENDER_ALIGN.max_shift_m, RENDER_ALIGN.refine_lm) == (None, 0.15, False)
    for bad in (
        dict(rounds=0),
        dict(max_pairs=100),
        dict(flow_preset="slow"),
        dict(max_fb_error_px=None, thinning="confidence"),
        dict(first_flow_scale=2.0),
        dict(matcher="sift"),
        dict(corners=2),
        dict(lk_window_px=3),
        dict(robust_px=0.0),
    ):
        with pytest.raises(ValueError):
            AlignConfig(**bad)
