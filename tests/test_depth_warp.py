"""The depth warp against analytic references: a plane seen from two cameras is related by a homography."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from acesplat.align.depth_warp import warp_to_camera
from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import make_pose, rodrigues_to_matrix
from acesplat.core.grid import cell_centers

H, W = 96, 128
INTR = Intrinsics(110.0, 110.0, 63.5, 47.5, W, H)
STRIDE = 4


def texture(seed: int = 0) -> np.ndarray:
    """Smooth random texture: bilinear resampling of it is accurate to a grey level or two."""
    rng = np.random.default_rng(seed)
    small = rng.uniform(0, 255, (H // 6, W // 6)).astype(np.float32)
    return np.clip(cv2.resize(small, (W, H), interpolation=cv2.INTER_CUBIC), 0, 255).astype(np.uint8)


def plane_depth(n_cam: np.ndarray, d: float) -> np.ndarray:
    """z-depth at the cell centres of the plane n . X = d (camera frame), a (h, w) grid."""
    gh, gw = H // STRIDE, W // STRIDE
    uv = cell_centers(gh, gw, STRIDE)  # the SCR network's dense cells, where head_depth samples depth
    rays = INTR.unproject(uv, np.ones(len(uv)))
    return (d / (rays @ n_cam)).reshape(gh, gw)


def plane_homography(R: np.ndarray, t: np.ndarray, n: np.ndarray, d: float) -> np.ndarray:
    """Pixels of the source camera -> pixels of the destination, for X_dst = R X_src + t and the plane n . X_src = d."""
    K = INTR.K
    return K @ (R + np.outer(t, n) / d) @ np.linalg.inv(K)


def compare(
    src_img: np.ndarray, c2w_dst: np.ndarray, n: np.ndarray, d: float, inverse_step: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    out, valid = warp_to_camera(src_img, plane_depth(n, d), INTR, STRIDE, np.eye(4), c2w_dst, inverse_step)
    w2c_dst = np.linalg.inv(c2w_dst)
    Hm = plane_homography(w2c_dst[:3, :3], w2c_dst[:3, 3], n, d)
    ref = cv2.warpPerspective(
        src_img, Hm, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    )
    inside = cv2.warpPerspective(np.ones_like(src_img), Hm, (W, H), flags=cv2.INTER_NEAREST, borderValue=0) > 0
    return out, valid, ref, inside


def test_identity_camera_returns_the_image_everywhere() -> None:
    img = texture()
    out, valid = warp_to_camera(img, np.full((H // STRIDE, W // STRIDE), 3.0), INTR, STRIDE, np.eye(4), np.eye(4))
    assert valid.all()
    assert np.abs(out.astype(int) - img).max() <= 1


def test_sideways_step_in_front_of_a_wall_shifts_the_image_by_f_b_over_d() -> None:
    img = texture(1)
    d, b = 4.0, 0.2  # wall 4 m ahead, camera 20 cm to the right: content moves f * b / d = 5.5 px left
    out, valid, ref, inside = compare(img, make_pose(np.eye(3), [b, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), d)
    shift = np.float32([[1, 0, -INTR.fx * b / d], [0, 1, 0]])
    shifted = cv2.warpAffine(img, shift, (W, H), flags=cv2.INTER_LINEAR)
    core = valid & inside
    assert core.mean() > 0.85
    assert not valid[:, -4:].any()  # the strip the source never saw
    assert np.abs(out[core].astype(int) - shifted[core]).mean() < 1.0


@pytest.mark.parametrize("inverse_step", [1, 4])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tilted_plane_and_turned_camera_match_the_plane_homography(seed: int, inverse_step: int) -> None:
    rng = np.random.default_rng(seed)
    img = texture(seed)
    n = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), 1.0])
    n /= np.linalg.norm(n)
    d = rng.uniform(2.0, 5.0)
    R = rodrigues_to_matrix(np.radians(rng.uniform(-4, 4, 3)))
    c2w_dst = make_pose(R, rng.uniform(-0.25, 0.25, 3))
    out, valid, ref, inside = compare(img, c2w_dst, n, d, inverse_step)
    core = valid & cv2.erode(inside.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert core.mean() > 0.6
    assert np.abs(out[core].astype(int) - ref[core]).mean() < 1.5
    # And validity follows visibility: nothing outside the source's footprint is claimed valid.
    assert not (valid & ~cv2.dilate(inside.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)).any()


def test_unknown_depth_is_invalid_and_bad_shapes_are_refused() -> None:
    img = texture()
    depth = np.zeros((H // STRIDE, W // STRIDE))
    depth[:, : depth.shape[1] // 2] = 3.0
    _, valid = warp_to_camera(img, depth, INTR, STRIDE, np.eye(4), np.eye(4))
    assert valid[:, : W // 2 - STRIDE].all() and not valid[:, W // 2 + STRIDE :].any()
    _, none = warp_to_camera(img, np.zeros_like(depth), INTR, STRIDE, np.eye(4), np.eye(4))
    assert not none.any()
    with pytest.raises(ValueError, match="uint8"):
        warp_to_camera(img.astype(np.float32), depth, INTR, STRIDE, np.eye(4), np.eye(4))
    with pytest.raises(ValueError, match="does not cover"):
        warp_to_camera(img, depth[:5], INTR, STRIDE, np.eye(4), np.eye(4))
    with pytest.raises(ValueError, match="intrinsics"):
        warp_to_camera(img[:50], depth, INTR, STRIDE, np.eye(4), np.eye(4))
    with pytest.raises(ValueError, match="inverse_step"):
        warp_to_camera(img, depth, INTR, STRIDE, np.eye(4), np.eye(4), inverse_step=0)
    with pytest.raises(ValueError, match="forward map"):
        warp_to_camera(img, depth, INTR, STRIDE, np.eye(4), np.eye(4), forward=np.zeros((H, W, 3), np.float32))


def test_coarse_inversion_matches_the_full_one_across_a_depth_edge() -> None:
    """A step from 2 m to 5 m seen from 30 cm sideways (an occlusion edge): the coarsely inverted warp claims the
    same pixels valid, up to a thin band along the edge, and gives them the same grey levels."""
    img = texture(3)
    depth = np.full((H // STRIDE, W // STRIDE), 5.0)
    depth[:, : depth.shape[1] // 2] = 2.0
    c2w = make_pose(rodrigues_to_matrix(np.radians([1.0, -2.0, 0.5])), [0.3, 0.05, 0.0])
    full, vfull = warp_to_camera(img, depth, INTR, STRIDE, np.eye(4), c2w)
    coarse, vcoarse = warp_to_camera(img, depth, INTR, STRIDE, np.eye(4), c2w, inverse_step=4)
    both = vfull & vcoarse
    assert vfull.mean() > 0.5
    assert (vfull ^ vcoarse).mean() < 0.03
    assert np.abs(full[both].astype(int) - coarse[both]).max() <= 1
