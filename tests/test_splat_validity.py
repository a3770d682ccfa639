"""Validity mask, pixel-resolution centres and view fusion on hand-made planar scenes."""

from __future__ import annotations

import numpy as np
import pytest

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import look_at, make_pose
from acesplat.splatcore.fusion import covered_by, novel_masks
from acesplat.splatcore.pixel_coords import filled_depths, pixel_coordinates, pixel_rays
from acesplat.splatcore.validity import (
    ValidityConfig,
    cell_pixels,
    cell_validity,
    confirm_across_views,
    cross_view_agreement,
)

K = Intrinsics(50.0, 50.0, 31.5, 23.5, 64, 48)
POSE = look_at(np.array([0.3, -0.2, 1.0]), np.array([0.5, 3.0, 1.2]))


def plane_coords(depth_cells: np.ndarray, pose: np.ndarray = POSE, k: Intrinsics = K) -> np.ndarray:
    """World coordinates (h, w, 3) of each cell's ray (through (8j+4, 8i+4)) at camera depth depth_cells (h, w)."""
    uv = cell_pixels(*depth_cells.shape)
    Xc = np.stack([(uv[..., 0] - k.cx) / k.fx, (uv[..., 1] - k.cy) / k.fy, np.ones(depth_cells.shape)], -1)
    Xc *= depth_cells[..., None]
    return Xc @ pose[:3, :3].T + pose[:3, 3]


def test_exact_coordinates_are_valid_everywhere():
    v = cell_validity(plane_coords(np.full((6, 8), 2.0)), POSE, K)
    assert v.valid.all() and v.fraction == 1.0


def test_each_failure_is_caught_by_its_own_test():
    z = np.full((6, 8), 2.0)
    z[2, 2] = 500.0  # beyond the depth range
    z[4, 4] = -1.0  # behind the camera
    coords = plane_coords(z)
    coords[0, 5] = np.nan
    # move cell (1, 1) sideways by 12 px at its depth: off its pixel by more than the 8 px tolerance
    R = POSE[:3, :3]
    coords[1, 1] += R[:, 0] * (12.0 / K.fx * 2.0)
    coords[3, 6] += R[:, 0] * (5.0 / K.fx * 2.0)  # 5 px: inside the tolerance
    v = cell_validity(coords, POSE, K, ValidityConfig(depth_min=0.05, depth_max=100.0, reproj_max_px=8.0))
    assert not v.finite[0, 5] and v.finite.sum() == 47
    assert not v.in_depth_range[2, 2] and not v.in_depth_range[4, 4]
    assert v.in_depth_range[1, 1] and not v.reprojects[1, 1]
    assert v.valid[3, 6]
    bad = {(0, 5), (2, 2), (4, 4), (1, 1)}
    assert {tuple(p) for p in np.argwhere(~v.valid)} == bad


def test_validity_config_rejects_nonsense():
    with pytest.raises(ValueError):
        ValidityConfig(depth_min=2.0, depth_max=1.0)
    with pytest.raises(ValueError):
        ValidityConfig(reproj_max_px=0.0)


def test_pixel_centres_lie_on_their_own_rays():
    z = 2.0 + 0.1 * np.random.default_rng(0).random((6, 8))
    centres, depth, valid = pixel_coordinates(plane_coords(z), np.ones((6, 8), bool), POSE, K, 1.25)
    assert valid.all()
    w2c = np.linalg.inv(POSE)
    Xc = centres @ w2c[:3, :3].T + w2c[:3, 3]
    np.testing.assert_allclose(Xc[..., 2], depth, rtol=1e-12)
    uv = np.stack([K.fx * Xc[..., 0] / Xc[..., 2] + K.cx, K.fy * Xc[..., 1] / Xc[..., 2] + K.cy], -1)
    u, v = np.meshgrid(np.arange(64), np.arange(48))
    np.testing.assert_allclose(uv, np.stack([u, v], -1), atol=1e-9)
    assert np.all((depth >= z.min() - 1e-12) & (depth <= z.max() + 1e-12))
    np.testing.assert_allclose(pixel_rays(K)[..., 2], 1.0)


def test_depth_edges_and_invalid_cells():
    z = np.full((6, 8), 1.0)
    z[:, 4:] = 3.0  # a step between cell columns 3 and 4 (pixels ~28..35)
    cell_ok = np.ones((6, 8), bool)
    cell_ok[1, 1] = False
    coords = plane_coords(z)
    coords[1, 1] = [1e3, 1e3, 1e3]  # garbage that must take no part
    _, depth, valid = pixel_coordinates(coords, cell_ok, POSE, K, 1.25)
    assert not valid[:, 29:35].any()  # interpolated across the step
    assert valid[:, 40:].all() and valid[20:, :24].all()
    np.testing.assert_allclose(depth[valid & (np.arange(64) < 28)], 1.0, rtol=1e-12)  # the garbage cell did not leak in
    assert not valid[11, 11]  # the invalid cell carries most of this pixel's weight
    assert valid[11, 16] and depth[11, 16] == pytest.approx(1.0)  # here valid cells carry more than half


def test_untrusted_pixels_take_the_nearest_trusted_depth_on_their_own_rays():
    z = np.full((6, 8), 2.0)
    z[:, 5:] = 4.0
    ok = np.zeros((6, 8), bool)
    ok[0, 0] = ok[5, 7] = True  # two trusted cells: depth 2 top-left, depth 4 bottom-right
    centres, depth = filled_depths(plane_coords(z), ok, POSE, K)
    assert depth[0, 0] == pytest.approx(2.0) and depth[47, 63] == pytest.approx(4.0)
    assert depth[8, 2] == pytest.approx(2.0) and depth[44, 60] == pytest.approx(4.0)  # nearest trusted cell, per block
    assert np.all(np.isclose(depth, 2.0) | np.isclose(depth, 4.0))  # nothing between the two surfaces
    w2c = np.linalg.inv(POSE)
    Xc = centres @ w2c[:3, :3].T + w2c[:3, 3]
    u, v = np.meshgrid(np.arange(64), np.arange(48))
    np.testing.assert_allclose(K.fx * Xc[..., 0] / Xc[..., 2] + K.cx, u, atol=1e-9)
    np.testing.assert_allclose(K.fy * Xc[..., 1] / Xc[..., 2] + K.cy, v, atol=1e-9)
    _, none = filled_depths(plane_coords(z), np.zeros((6, 8), bool), POSE, K)
    assert not none.any()


def _pixels(pose: np.ndarray, plane_z: float):
    """Pixel centres/depths/validity of a camera at ``pose`` looking at the world plane z = plane_z."""
    rays = pixel_rays(K) @ pose[:3, :3].T  # world directions
    t = (plane_z - pose[2, 3]) / rays[..., 2]
    centres = pose[:3, 3] + rays * t[..., None]
    depth = t  # camera z equals the ray parameter for rays with camera z = 1
    return centres, depth, np.ones((48, 64), bool)


def test_fusion_keeps_only_unseen_surface():
    base = make_pose(np.eye(3), [0.0, 0.0, 0.0])  # looking along +z at the plane z = 5
    same = base.copy()
    shifted = make_pose(np.eye(3), [3.0, 0.0, 0.0])  # half the image overlaps (footprint 0.1 m/px, 64 px = 6.4 m)
    away = make_pose(np.diag([-1.0, 1.0, -1.0]), [0.0, 0.0, 10.0])  # sees the plane from the other side
    poses = [base, same, shifted, away]
    pix = [_pixels(p, 5.0) for p in poses]
    masks = novel_masks(poses, [K] * 4, [p[0] for p in pix], [p[1] for p in pix], [p[2] for p in pix])
    assert masks[0].all()
    assert not masks[1].any()  # the same view adds nothing
    cols = np.nonzero(masks[2].any(axis=0))[0]
    assert 31 <= cols.min() <= 34 and cols.max() == 63  # only the part beyond the first view's edge is new
    assert masks[2][:, cols.min() :].all()
    # the far side of the plane seen from z = 10: same surface points, same footprint, so covered where they overlap
    assert masks[3].sum() < masks[3].size


def test_a_coarser_view_does_not_cover_a_finer_one():
    far = make_pose(np.eye(3), [0.0, 0.0, 0.0])  # plane at 5 m
    near = make_pose(np.eye(3), [0.0, 0.0, 2.5])  # plane at 2.5 m: twice as fine
    (cf, df, vf), (cn, dn, vn) = _pixels(far, 5.0), _pixels(near, 5.0)
    assert not covered_by(cn, dn, vn, K, df, vf, far, K).any()  # far view is 2x coarser than the near pixels
    cov = covered_by(cf, df, vf, K, dn, vn, near, K)  # the near view covers the far view's centre region
    assert cov[20:28, 28:36].all() and not cov[0, 0]
    # depth disagreement beyond the tolerance: not the same surface
    assert not covered_by(cf * 1.1, df * 1.1, vf, K, dn, vn, near, K).any()  # 10% further along the rays


def test_depth_errors_along_the_ray_are_caught_by_a_neighbouring_view():
    a = make_pose(np.eye(3), [0.0, 0.0, 0.0])  # both look along +z at the plane z = 4
    b = make_pose(np.eye(3), [0.4, 0.0, 0.0])
    ca, cb = plane_coords(np.full((6, 8), 4.0), a), plane_coords(np.full((6, 8), 4.0), b)
    ca[2, 3] = ca[2, 3] * 0.7  # 30% closer along its own ray: still reprojects perfectly in view a
    assert cell_validity(ca, a, K).valid.all()
    ok = np.ones((6, 8), bool)
    seen, agrees = cross_view_agreement(ca, K, cb, ok, b, K)
    assert not agrees[2, 3] and seen[2, 3]
    others = np.ones((6, 8), bool)
    others[2, 3] = False
    assert np.array_equal(agrees[others], seen[others])  # every other cell agrees wherever view b sees it
    assert not seen[:, 0].any() and seen[:, 1:].all()  # b, 0.4 m to the right, misses a's left column
    confirmed = confirm_across_views([ca, cb], [ok, ok], [a, b], [K, K])
    assert not confirmed[0][2, 3] and confirmed[0][:, 0].all()  # unseen cells keep their own verdict
    # b cannot tell which of the two is wrong: its cell landing on the corrupted one is not confirmed either
    assert confirmed[0].sum() == 47 and confirmed[1].sum() == 47 and not confirmed[1][2, 2]
