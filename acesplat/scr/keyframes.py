"""The mapping images as keyframes for pose refinement (acesplat.align.keyframe_align), with their depth.

Depth is made once per training image, on its first use: predicted by the head on the dense grid (half the cell
spacing) and median-filtered as the novel views use it (acesplat.scr.novel_views.head_depth), then re-measured
by triangulation with two neighbours (acesplat.align.keyframe_depth). A query needs only its few nearest training
images, so a long mapping sequence costs only what is used.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from acesplat.align.keyframe_align import KEYFRAMES, Keyframe, nearest_keyframes
from acesplat.align.keyframe_depth import depth_neighbours, refine_depth
from acesplat.align.keyframe_set import KeyframeSet, prepare_corners
from acesplat.core.grid import DENSE_OUTPUT_STRIDE
from acesplat.core.preprocess import to_gray_input
from acesplat.core.scene import SceneSplit
from acesplat.scr.mapping import TrainingImage, load_training_images
from acesplat.scr.network import SCRNetwork
from acesplat.scr.novel_views import head_depth


class MapKeyframes:
    """The training split of a scene at the map's resolution; ``near(pose)`` gives the keyframes to align to."""

    def __init__(
        self,
        split: SceneSplit,
        network: SCRNetwork,
        short_side: int,
        k: int = KEYFRAMES,
        input_size: tuple[int, int] | None = None,
    ):
        """``input_size`` (H, W): the exact size queries run at (a bundle's), instead of the short side's."""
        if input_size is None:
            self.images = load_training_images(split, short_side)
        else:
            self.images = [
                TrainingImage(*to_gray_input(f.load_rgb(), f.intrinsics, input_size), f.pose) for f in split.frames
            ]
        self.c2ws = np.stack([im.c2w for im in self.images])
        self.network = network
        self.k = k
        self._depth: dict[int, np.ndarray] = {}
        self._head: dict[int, np.ndarray] = {}
        self._made: dict[int, Keyframe] = {}

    def head_depth(self, i: int) -> np.ndarray:
        if i not in self._head:
            self._head[i] = head_depth(self.network, self.images[i])
        return self._head[i]

    def depth(self, i: int) -> np.ndarray:
        """The head's depth, re-measured where neighbouring keyframes triangulate it (acesplat.align.keyframe_depth)."""
        if i not in self._depth:
            z = self.head_depth(i)
            known = z[z > 0]
            nbs = depth_neighbours(self.c2ws, i, float(np.median(known))) if known.size else []
            im = self.images[i]
            kf = Keyframe(im.gray, im.intrinsics, im.c2w, z, DENSE_OUTPUT_STRIDE)
            self._depth[i] = refine_depth(kf, [self._plain(j) for j in nbs])
        return self._depth[i]

    def _plain(self, j: int) -> Keyframe:
        """Keyframe j for its image and pose only (refine_depth does not read a neighbour's depth)."""
        im = self.images[j]
        return Keyframe(im.gray, im.intrinsics, im.c2w, np.zeros((1, 1), np.float32), DENSE_OUTPUT_STRIDE)

    def prepare(self, progress: Callable[[int, int], None] | None = None) -> None:
        """Predict every keyframe's depth now (so per-frame timings measure localization alone)."""
        for i in range(len(self.images)):
            self.depth(i)
            if progress:
                progress(i + 1, len(self.images))

    def prepare_corners(self, count: int) -> None:
        """Every keyframe's corners for the sparse matcher, triangulated between keyframes (KeyframeSet's)."""
        prepare_corners(self.keyframe, self.c2ws, count)

    def to_set(self) -> KeyframeSet:
        """Every keyframe with its depth, as the arrays a bundle carries (acesplat.align.keyframe_set)."""
        self.prepare()
        return KeyframeSet.stack([self.keyframe(i) for i in range(len(self.images))])

    def keyframe(self, i: int) -> Keyframe:
        """Keyframe i, one object per index (it caches what the sparse matcher derives from it)."""
        if i not in self._made:
            im = self.images[i]
            self._made[i] = Keyframe(im.gray, im.intrinsics, im.c2w, self.depth(i), DENSE_OUTPUT_STRIDE)
        return self._made[i]

    def near(
        self, pose_c2w: np.ndarray, depth: float | None = None, k: int | None = None, corners: int = 0
    ) -> list[Keyframe]:
        """Up to ``k`` (default: the set's) keyframes nearest the camera-to-world ``pose_c2w`` (4, 4) and looking the
        same way (by viewpoint change when the scene ``depth`` in front of the query is given: nearest_keyframes);
        with ``corners``, each carries that many corners triangulated between keyframes (made on first use)."""
        idx = nearest_keyframes(self.c2ws, pose_c2w, k or self.k, depth=depth)
        if corners:
            prepare_corners(self.keyframe, self.c2ws, corners, idx)
        return [self.keyframe(i) for i in idx]
