"""Keyframe depth re-measured from neighbours: exact triangulation on a constructed ray, and a corrupted depth grid
of a rendered room view brought back towards the rendered depth."""

from __future__ import annotations

import numpy as np
import pytest

from acesplat.align.keyframe_align import Keyframe
from acesplat.align.keyframe_depth import depth_neighbours, refine_depth, triangulate_along_rays
from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import look_at, make_pose
from tests.test_keyframe_align import room  # noqa: F401  (the module fixture: rendered keyframes with true depth)


def test_triangulation_along_the_ray_recovers_the_depth_exactly() -> None:
    K = Intrinsics(300.0, 300.0, 160.0, 120.0, 320, 240)
    a = Keyframe(np.zeros((240, 320), np.uint8), K, np.eye(4), np.ones((2, 2), np.float32), 4)
    nb = make_pose(np.eye(3), np.array([0.5, 0.1, 0.0]))
    uv = np.array([[40.0, 30.0], [160.0, 120.0], [300.0, 200.0]])
    z_true = np.array([2.0, 5.0, 9.0])
    X = K.unproject(uv, z_true)
    seen = K.project(X - nb[:3, 3])  # the neighbour is only translated
    z, sens = triangulate_along_rays(uv, a, seen, K.K, nb)
    assert z == pytest.approx(z_true, rel=1e-9)
    # pixels per 100% depth change: f * baseline / z for a sideways baseline (|(0.5, 0.1)| = 0.51 m)
    assert sens == pytest.approx(300.0 * np.hypot(0.5, 0.1) / z_true, rel=0.02)


def test_neighbours_have_the_wanted_baseline_and_look_the_same_way() -> None:
    cams = np.stack([look_at(np.array([x, 0.0, 0.0]), np.array([x, 0.0, 10.0])) for x in (0.0, 0.2, 0.5, 1.0, 1.1)])
    assert depth_neighbours(cams, 0, depth=10.0) == [3, 4]  # 1 m = 0.1 x depth, then 1.1 m
    cams[3] = look_at(cams[3][:3, 3], np.array([11.0, 0.0, 0.0]))  # turned 45 degrees away
    assert depth_neighbours(cams, 0, depth=10.0) == [4, 2]
    assert 0 not in depth_neighbours(cams, 0, depth=1e-12)


def test_a_corrupted_depth_grid_comes_back_towards_the_rendered_depth(room) -> None:  # noqa: F811
    _, _, kfs, _, _ = room
    kf = kfs[1]
    rng = np.random.default_rng(0)
    bad = (kf.depth * rng.uniform(0.9, 1.1, kf.depth.shape)).astype(np.float32)  # +-10%: a head's error
    corrupted = Keyframe(kf.gray, kf.intrinsics, kf.c2w, bad, kf.stride)
    fixed = refine_depth(corrupted, [kfs[0], kfs[3]])
    changed = (kf.depth > 0) & (fixed != bad)  # cells enough textured neighbour pixels triangulated
    before = np.median(np.abs(bad - kf.depth)[changed] / kf.depth[changed])
    after = np.median(np.abs(fixed - kf.depth)[changed] / kf.depth[changed])
    # measured: 65% of cells changed, their median error 5.0% -> 2.7% (neighbours 0.1-0.2 m apart at 2-3 m)
    assert np.mean(changed) > 0.5 and after < 0.65 * before, (before, after, np.mean(changed))
    assert np.array_equal(refine_depth(corrupted, []), bad)
