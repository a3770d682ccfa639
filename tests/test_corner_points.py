"""Corner seeds against the rendered room's true surface: triangulated between views, they undo a wrong first depth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from acesplat.align.keyframe_align import Keyframe
from acesplat.align.keyframe_set import triangulated_points
from acesplat.core.geometry import invert_pose, transform_points
from acesplat.core.grid import cell_centers
from acesplat.synth import default_intrinsics, make_room, make_trajectory, render_view
from acesplat.synth.dataset import texel_density_for

SIZE = (240, 320)


@pytest.fixture(scope="module")
def views():
    """Six consecutive views of the room's path as keyframes whose depth grid (stride 8) is 5% too deep, their
    colours and true depth."""
    K = default_intrinsics(SIZE)
    scene = make_room(0, texel_density=texel_density_for(K))
    poses = make_trajectory(scene.path, 60)[40:46]
    kfs, rgbs, depths = [], [], []
    for T in poses:
        rgb, depth = render_view(scene, T, K, supersample=1)
        uv = cell_centers(SIZE[0] // 8, SIZE[1] // 8).astype(np.int64)
        grid = (depth[uv[:, 1], uv[:, 0]] * 1.05).reshape(SIZE[0] // 8, SIZE[1] // 8).astype(np.float32)
        kfs.append(Keyframe(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), K, T, grid, 8))
        rgbs.append(rgb.astype(np.float32) / 255.0)
        depths.append(depth)
    return K, kfs, rgbs, depths


def test_triangulated_points_lie_on_the_surface_though_the_first_depth_is_off(views) -> None:
    K, kfs, rgbs, depths = views
    pts, cols, per_view = triangulated_points(kfs, rgbs, 300)
    assert len(pts) == len(cols) == sum(per_view) and min(per_view) > 50  # measured 141-289 of 300
    assert cols.min() >= 0.0 and cols.max() <= 1.0
    # each seed against the true depth where the first view's camera sees it
    pc = transform_points(invert_pose(kfs[0].c2w), pts)
    uv = pc @ K.K.T
    uv = uv[:, :2] / uv[:, 2:3]
    inside = (pc[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < SIZE[1] - 1) & (uv[:, 1] >= 0) & (uv[:, 1] < SIZE[0] - 1)
    u = np.rint(uv[inside]).astype(int)
    rel = np.abs(pc[inside, 2] / depths[0][u[:, 1], u[:, 0]] - 1.0)
    assert inside.sum() > 100 and np.median(rel) < 0.005, np.median(rel)  # measured 0.14% (p90 0.48%), from 5%
    with pytest.raises(ValueError, match="one colour image per keyframe"):
        triangulated_points(kfs, rgbs[:2], 300)
    with pytest.raises(ValueError, match="a colour image is"):
        triangulated_points(kfs[:1], [rgbs[0][:10]], 300)
