"""Pose alignment of a keyframe against the map (acesplat.align.flow_pnp.align_to_render) on textured walls of
Gaussians."""

from __future__ import annotations

import numpy as np

from acesplat.align.flow_pnp import align_to_render
from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import look_at, pose_error
from acesplat.raster import rasterize
from acesplat.splatcore.seeding import gaussians_at
from tests.test_edge_scene import jitter

K = Intrinsics.from_focal(150.0, 160, 120)


def wall(rng: np.random.Generator):
    """A textured back wall at z = 2 m (x < 0) and a wall turning towards the camera (x >= 0): PnP needs depth
    variation (on one fronto-parallel plane a small shift and a small turn look alike). A 1.2 cm lattice of
    opaque Gaussians coloured in 7.5 cm blocks with some noise."""
    xs, ys = np.meshgrid(np.arange(-1.2, 1.2, 0.012), np.arange(-0.9, 0.9, 0.012))
    n = xs.size
    z = np.where(xs.ravel() < 0, 2.0, 2.0 - 0.8 * xs.ravel())
    centres = np.stack([xs.ravel(), ys.ravel(), z], 1)
    blocks = rng.uniform(0.3, 0.7, (24, 32, 3)).astype(np.float32)
    iy = np.clip(((ys.ravel() + 0.9) / 1.8 * 24).astype(int), 0, 23)
    ix = np.clip(((xs.ravel() + 1.2) / 2.4 * 32).astype(int), 0, 31)
    col = np.clip(blocks[iy, ix] + rng.normal(0, 0.02, (n, 3)), 0, 1)
    return gaussians_at(centres, z, col, 150.0 / 0.012, 1.2, 0, opacity=0.99)


def render(g, pose):
    r = rasterize(g, pose, K, np.zeros(3))
    return r.color.astype(np.float32), r.alpha, r.depth


def test_a_pose_a_few_centimetres_off_is_corrected_against_the_map() -> None:
    rng = np.random.default_rng(2)
    g = wall(rng)
    true = look_at(np.array([0.1, -0.05, 0.0]), np.array([0.0, 0.0, 2.0]), np.array([0.0, -1.0, 0.0]))
    image, _, _ = render(g, true)
    off = jitter(true, rng, 0.04, 0.8)
    c, a, d = render(g, off)
    al = align_to_render(c, a, d, image, K, off)
    assert al.status == "aligned", al
    t0, r0 = pose_error(off, true)
    t1, r1 = pose_error(al.pose, true)
    assert t1 < 0.3 * t0 and r1 < 0.3 * r0, (t0, t1, r0, r1)


def test_a_grossly_wrong_pose_is_flagged_and_kept() -> None:
    rng = np.random.default_rng(1)
    g = wall(rng)
    true = look_at(np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 2.0]), np.array([0.0, -1.0, 0.0]))
    image, _, _ = render(g, true)
    off = jitter(true, rng, 0.4, 8.0)
    c, a, d = render(g, off)
    al = align_to_render(c, a, d, image, K, off)
    assert al.status in ("too_far", "no_fit", "unlike"), al
    assert np.array_equal(al.pose, off)


def test_a_render_unlike_the_image_is_not_trusted() -> None:
    rng = np.random.default_rng(2)
    g = wall(rng)
    pose = look_at(np.zeros(3), np.array([0.0, 0.0, 2.0]), np.array([0.0, -1.0, 0.0]))
    c, a, d = render(g, pose)
    other = rng.uniform(0, 1, c.shape).astype(np.float32)  # a photograph of something else
    al = align_to_render(c, a, d, other, K, pose)
    assert al.status == "unlike" and np.array_equal(al.pose, pose)
