"""Novel views between mapping cameras: which pairs, where the cameras go, and that their buffer entries are true."""

from __future__ import annotations

import numpy as np
import pytest

from acesplat.core.geometry import invert_pose, look_at, make_pose, rodrigues_to_matrix, rotation_angle_deg
from acesplat.scr.novel_views import BETWEEN, neighbour_pairs, sample_novel_cameras


def row_of_cameras(n: int, spacing: float = 1.0) -> np.ndarray:
    return np.stack([look_at(np.array([i * spacing, 0.0, 0.0]), np.array([i * spacing, 10.0, 0.0])) for i in range(n)])


def test_pairs_join_near_cameras_that_look_alike() -> None:
    cams = row_of_cameras(5)
    assert neighbour_pairs(cams, k=1) == [(0, 1), (1, 2), (2, 3), (3, 4)]
    assert (0, 2) in neighbour_pairs(cams, k=2) and (0, 4) not in neighbour_pairs(cams, k=2)
    # A neighbour that looks the other way shares nothing to warp.
    cams[2] = make_pose(rodrigues_to_matrix([0.0, 0.0, np.pi]) @ cams[2][:3, :3], cams[2][:3, 3])
    assert all(2 not in p for p in neighbour_pairs(cams, k=2))
    assert neighbour_pairs(cams[:1]) == []


def test_novel_cameras_lie_between_their_pair_and_warp_from_one_end() -> None:
    cams = row_of_cameras(6, spacing=2.0)
    rng = np.random.default_rng(0)
    out = sample_novel_cameras(cams, 200, rng)
    assert len(out) == 200
    for src, T in out:
        x = T[0, 3]
        # Inside the row, at least BETWEEN[0] of a 2 m step from its source, at most BETWEEN[1] of a 6 m pair.
        assert 0.0 < x < 10.0 and np.allclose(T[1:3, 3], 0.0)
        assert BETWEEN[0] * 2.0 - 1e-9 <= abs(x - cams[src, 0, 3]) <= BETWEEN[1] * 6.0 + 1e-9
        assert rotation_angle_deg(T[:3, :3].T @ cams[0, :3, :3]) == pytest.approx(0.0, abs=1e-6)
    two = sample_novel_cameras(cams[:2], 400, rng)
    near = np.mean([abs(T[0, 3] - cams[s, 0, 3]) <= 1.0 for s, T in two])
    assert near > 0.55  # the nearer camera is the source more often (expected 0.625)
    assert sample_novel_cameras(cams[:1], 10, rng) == []


def test_warping_a_rendered_frame_to_its_neighbour_reproduces_the_neighbour(tmp_path) -> None:
    """On the synthetic room, with rendered depth: the warp of one frame to the next frame's camera looks like
    the next frame (occlusions and lighting included), far more than the unwarped frame does."""
    import cv2

    from acesplat.align.depth_warp import warp_to_camera
    from acesplat.core.scene import read_split
    from acesplat.synth import synthesize

    size = (96, 128)
    synthesize(tmp_path / "s", seed=3, train_frames=12, test_frames=2, size=size, supersample=1)
    frames = read_split(tmp_path / "s", "train").frames
    for a, b in ((0, 1), (4, 5), (7, 8)):  # 16-40 deg apart: this short trajectory turns fast
        fa, fb = frames[a], frames[b]
        ga = cv2.cvtColor(fa.load_rgb(), cv2.COLOR_RGB2GRAY)
        gb = cv2.cvtColor(fb.load_rgb(), cv2.COLOR_RGB2GRAY)
        depth = fa.load_depth()[4::4, 4::4].astype(np.float64)  # at the dense cell centres, 4k + 4
        out, valid = warp_to_camera(ga, depth, fa.intrinsics, 4, fa.pose, fb.pose)
        assert valid.mean() > 0.3
        warped = np.abs(out[valid].astype(int) - gb[valid]).mean()
        unwarped = np.abs(ga[valid].astype(int) - gb[valid]).mean()
        assert warped < 0.25 * unwarped and warped < 8, (a, b, warped, unwarped)  # measured 3-4 vs 27-41


def test_novel_view_buffer_holds_cells_of_novel_cameras_and_leaves_the_head_as_it_was(tmp_path) -> None:
    import time

    import torch

    from acesplat.core.scene import read_split
    from acesplat.scr.mapping import MappingConfig, buffer_encoding, load_training_images
    from acesplat.scr.network import Encoder, EncoderConfig, Head
    from acesplat.scr.novel_views import novel_view_buffer
    from acesplat.synth import synthesize

    size = (96, 128)
    synthesize(tmp_path / "s", seed=3, train_frames=12, test_frames=2, size=size, supersample=1)
    images = load_training_images(read_split(tmp_path / "s", "train"), size[0])
    torch.manual_seed(0)
    enc = Encoder(EncoderConfig(c1=4, c2=4, c3=8, c4=8, res2=8, out=8)).eval()
    centre = np.mean([im.c2w[:3, 3] for im in images], axis=0)
    head = Head(torch.from_numpy(centre).float(), in_channels=8).train()
    with buffer_encoding(enc, MappingConfig(precision="fp32")) as encode:
        buf = novel_view_buffer(images, enc, encode, head, 20, np.random.default_rng(1), deadline=float("inf"))
        spent = novel_view_buffer(
            images, enc, encode, head, 20, np.random.default_rng(1), deadline=time.monotonic() - 1
        )
    assert head.training
    assert buf is not None
    n = buf["pixels"].shape[0]
    assert buf["feats"].shape == (n, 8) and buf["feats"].dtype == torch.float16
    views = buf["w2c"].shape[0]  # views where the untrained head put nothing in front of the camera are skipped
    assert 0 < views <= 20 and buf["K"].shape == (views, 3, 3) and int(buf["view"].max()) == views - 1
    assert torch.isnan(buf["target"]).all() and n > views * 10
    centres = np.stack([im.c2w[:3, 3] for im in images])
    for w2c in buf["w2c"].numpy().astype(np.float64):
        c2w = invert_pose(np.vstack([w2c, [0, 0, 0, 1]]))
        assert np.linalg.norm(centres - c2w[:3, 3], axis=1).min() > 1e-3  # a new camera, not a training one
    assert spent is None  # a spent budget makes nothing
