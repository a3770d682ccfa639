"""Novel views for the mapping buffer: the training images re-rendered between neighbouring cameras.

Why: with a few wide-baseline photographs (herzjesu25: 18 views, 2-4 m apart) the head learns the
encoder's features of those exact views, and a query from in between shows the surfaces at a scale and
slant the head never saw; its coordinates there are off by a few pixels, coherently over whole regions,
which no pose solver averages out (bench/herz_gap.md). Late in training the head already knows
the depth of every training pixel, so each training image can be warped to a camera between it and a
neighbour (acesplat.align.depth_warp) and its features, with that camera's pose, join the buffer. Nothing
but the training images and their poses is used.

Whether and when they help is measured in bench/herz_gap.md ("Novel views"); too few seeds to make them the
default, so ``acesplat map --novel-views 300`` asks for them.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch

from acesplat.align.depth_warp import warp_to_camera
from acesplat.core.geometry import interpolate_pose, invert_pose, rotation_angle_deg
from acesplat.core.grid import DENSE_OUTPUT_STRIDE, OUTPUT_STRIDE, cell_centers
from acesplat.scr.buffer import Buffer, BufferBuilder
from acesplat.scr.loss import DEPTH_MIN
from acesplat.scr.network import Encoder, Head, SCRNetwork

if TYPE_CHECKING:
    from acesplat.scr.mapping import TrainingImage

NOVEL_VIEWS = 300
"""Warped views to add when asked for (about 2,000 cells each at 360 px); mapping's default is none."""
NOVEL_VIEWS_AT = 0.8
"""Share of the head's schedule after which they are made: the low learning rates then add them to a fitted head
instead of spending it on them at the real views' expense (bench/herz_gap.md)."""
NOVEL_VIEWS_TIME_FRACTION = 0.12
"""At most this share of the mapping budget goes to warping and encoding them."""
NEIGHBOURS = 3
"""Each camera is paired with this many nearest cameras (by centre)."""
MAX_PAIR_ANGLE_DEG = 30.0
"""Pairs whose viewing directions differ more than this share too little of the scene to warp between."""
BETWEEN = (0.25, 0.75)
"""Where on the way from one camera of a pair to the other a novel camera sits."""
DEPTH_MEDIAN_PX = 5
"""Median filter over the predicted depth grid: one wrong cell must not tear the warped image."""
EDGE_MARGIN_PX = 4
"""A cell is used only if the warp is valid this far around its centre (the encoder sees a neighbourhood)."""


def neighbour_pairs(
    c2ws: np.ndarray, k: int = NEIGHBOURS, max_angle_deg: float = MAX_PAIR_ANGLE_DEG
) -> list[tuple[int, int]]:
    """Index pairs (i < j) of cameras c2ws (N, 4, 4) that are among each other's k nearest and look alike."""
    centres = c2ws[:, :3, 3]
    pairs: set[tuple[int, int]] = set()
    for i in range(len(c2ws)):
        d = np.linalg.norm(centres - centres[i], axis=1)
        d[i] = np.inf
        for j in np.argsort(d)[:k]:
            if np.isfinite(d[j]) and rotation_angle_deg(c2ws[i, :3, :3].T @ c2ws[j, :3, :3]) <= max_angle_deg:
                pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def sample_novel_cameras(c2ws: np.ndarray, n: int, rng: np.random.Generator) -> list[tuple[int, np.ndarray]]:
    """``n`` (source image, camera-to-world (4, 4)) between neighbouring cameras; the source is the nearer one
    more often (chosen with probability 1 - t)."""
    pairs = neighbour_pairs(c2ws)
    out = []
    for _ in range(n if pairs else 0):
        i, j = pairs[int(rng.integers(len(pairs)))]
        t = float(rng.uniform(*BETWEEN))
        src = i if rng.uniform() >= t else j
        out.append((src, interpolate_pose(c2ws[i], c2ws[j], t)))
    return out


@torch.no_grad()
def head_depth(network: SCRNetwork, image: TrainingImage) -> np.ndarray:
    """z-depth (h, w) of the image's dense cells (stride DENSE_OUTPUT_STRIDE) as the head predicts them."""
    device = next(network.parameters()).device
    coords = network(torch.from_numpy(image.gray)[None, None].to(device), DENSE_OUTPUT_STRIDE)[0].cpu()
    X = coords.permute(1, 2, 0).reshape(-1, 3).double().numpy()
    w2c = invert_pose(image.c2w)
    z = (X @ w2c[2, :3] + w2c[2, 3]).reshape(coords.shape[1:]).astype(np.float32)
    z = cv2.medianBlur(z, DEPTH_MEDIAN_PX)
    z[~(z > DEPTH_MIN)] = 0.0
    return z


@torch.no_grad()
def novel_view_buffer(
    images: list[TrainingImage],
    encoder: Encoder,
    encode: Callable[[np.ndarray], torch.Tensor],
    head: Head,
    n: int,
    rng: np.random.Generator,
    deadline: float,
) -> Buffer | None:
    """Buffer entries for up to ``n`` novel views; None if none could be made.

    ``encode`` is the buffer's encoder pass (mapping.buffer_encoding); ``encoder`` with ``head`` gives the depth.
    """
    was_training = head.training
    head.eval()
    network = SCRNetwork(encoder, head)
    depths: dict[int, np.ndarray] = {}
    builder = BufferBuilder()
    kernel = np.ones((2 * EDGE_MARGIN_PX + 1,) * 2, np.uint8)
    try:
        for src, c2w in sample_novel_cameras(np.stack([im.c2w for im in images]), n, rng):
            if time.monotonic() > deadline:
                break
            im = images[src]
            if src not in depths:
                depths[src] = head_depth(network, im)
            gray, valid = warp_to_camera(im.gray, depths[src], im.intrinsics, DENSE_OUTPUT_STRIDE, im.c2w, c2w)
            valid = cv2.erode(valid.astype(np.uint8), kernel).astype(bool)
            f = encode(gray)
            _, gh, gw = f.shape
            centres = cell_centers(gh, gw, OUTPUT_STRIDE)
            h, w = gray.shape
            ok = valid[np.minimum(centres[:, 1].astype(int), h - 1), np.minimum(centres[:, 0].astype(int), w - 1)]
            take = np.flatnonzero(ok)
            if take.size:
                builder.add_view(f, take, centres[take], c2w, im.intrinsics.K)
    finally:
        head.train(was_training)
    return builder.build()
