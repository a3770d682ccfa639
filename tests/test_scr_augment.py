"""Mapping augmentation keeps every pixel on its true scene coordinate."""

from __future__ import annotations

import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import invert_pose, look_at, transform_points
from acesplat.scr.augment import AUGMENT_PRESETS, augment, cell_validity


def test_rotated_and_scaled_view_projects_scene_points_where_the_warp_moved_them() -> None:
    rng = np.random.default_rng(0)
    intr = Intrinsics(150.0, 160.0, 70.0, 52.0, 160, 120)  # off-centre principal point, non-square pixels
    T = look_at(np.array([0.0, 0.0, 1.0]), np.array([0.0, 5.0, 1.0]))
    # A bright dot at a known 3D point; find it in the augmented image and compare with its projection.
    X = np.array([[0.4, 5.0, 1.3]])
    u, v = intr.project(transform_points(invert_pose(T), X))[0]
    img = np.zeros((120, 160), np.uint8)
    img[int(round(v)) - 1 : int(round(v)) + 2, int(round(u)) - 1 : int(round(u)) + 2] = 255
    for _ in range(5):
        view = augment(img, intr, T, rng, brightness=0.0, contrast=0.0)
        expected = view.intrinsics.project(transform_points(invert_pose(view.c2w), X))[0]
        ys, xs = np.nonzero(view.gray > 60)
        w = view.gray[ys, xs].astype(float)
        found = np.array([np.sum(xs * w) / w.sum(), np.sum(ys * w) / w.sum()])
        assert np.linalg.norm(found - expected) < 1.5


def test_cell_validity_needs_a_full_patch() -> None:
    mask = np.ones((16, 24), np.uint8)
    mask[0, 0] = 0
    v = cell_validity(mask)
    assert v.shape == (2, 3)
    assert not v[0, 0] and v[1, 0] and v[0, 1]


def test_photometric_preset_keeps_the_camera_and_every_cell() -> None:
    rng = np.random.default_rng(1)
    intr = Intrinsics(150.0, 150.0, 80.0, 60.0, 160, 120)
    T = look_at(np.array([0.0, 0.0, 1.0]), np.array([0.0, 5.0, 1.0]))
    img = rng.integers(0, 256, (120, 160), dtype=np.uint8)
    p = AUGMENT_PRESETS["photometric"]
    view = augment(img, intr, T, rng, p.scale_range, p.rotation_deg)
    np.testing.assert_allclose(view.c2w, T, atol=1e-12)
    np.testing.assert_allclose(view.intrinsics.K, intr.K, atol=1e-12)
    np.testing.assert_allclose(view.pixel_map, np.eye(3), atol=1e-12)
    assert view.cell_valid.all()
    assert not np.array_equal(view.gray, img)  # brightness and contrast still vary
