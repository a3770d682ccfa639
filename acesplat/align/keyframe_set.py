"""The keyframes a bundle carries for pose refinement on the edge, as one ``.npz`` of plain arrays (torch-free).

Plain arrays (no pickled objects: loaded with ``allow_pickle=False``) so a bundle from elsewhere cannot run
code; every array's shape and every pose is checked on load, and the error names the file.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from acesplat.align.keyframe_align import KEYFRAMES, Keyframe, keyframe_corners, nearest_keyframes
from acesplat.align.keyframe_depth import CORNER_NEIGHBOURS, depth_neighbours, triangulate_corners
from acesplat.core.atomic import atomic_path
from acesplat.core.bundle import MANIFEST_NAME, ROLE_KEYFRAMES, Bundle
from acesplat.core.camera import Intrinsics
from acesplat.core.errors import InputError
from acesplat.core.geometry import rigidity_problem
from acesplat.core.grid import DENSE_OUTPUT_STRIDE, OUTPUT_STRIDE


@dataclass(frozen=True)
class KeyframeSet:
    """gray (N, H, W) uint8; depth (N, h, w) float32 z-depth at cells ``stride`` px apart (0 unknown);
    c2w (N, 4, 4); K (N, 3, 3), all for images of H x W."""

    gray: np.ndarray
    depth: np.ndarray
    c2w: np.ndarray
    K: np.ndarray
    stride: int
    _made: dict[int, Keyframe] = field(default_factory=dict, compare=False, repr=False)

    def __len__(self) -> int:
        return int(self.gray.shape[0])

    def keyframe(self, i: int) -> Keyframe:
        """Keyframe i, one object per index (it caches what the sparse matcher derives from it)."""
        if i not in self._made:
            h, w = self.gray.shape[1:]
            self._made[i] = Keyframe(
                self.gray[i], Intrinsics.from_K(self.K[i], w, h), self.c2w[i], self.depth[i], self.stride
            )
        return self._made[i]

    def prepare_corners(self, count: int) -> None:
        """Make every keyframe's corners and plane for the sparse matcher now, each corner's depth triangulated with
        the keyframe's neighbours (acesplat.align.keyframe_depth.triangulate_corners)."""
        prepare_corners(self.keyframe, self.c2w, count)

    def near(
        self, pose_c2w: np.ndarray, k: int = KEYFRAMES, depth: float | None = None, corners: int = 0
    ) -> list[Keyframe]:
        """Up to ``k`` keyframes nearest the camera-to-world ``pose_c2w`` (4, 4) and looking the same way (by
        viewpoint change when the scene ``depth`` in front of the query is given: nearest_keyframes); with
        ``corners``, each carries that many corners triangulated between keyframes (made on first use)."""
        idx = nearest_keyframes(self.c2w, pose_c2w, k, depth=depth)
        if corners:
            prepare_corners(self.keyframe, self.c2w, corners, idx)
        return [self.keyframe(i) for i in idx]

    @classmethod
    def stack(cls, keyframes: list[Keyframe]) -> KeyframeSet:
        if not keyframes:
            raise ValueError("a keyframe set needs at least one keyframe")
        strides = {k.stride for k in keyframes}
        if len(strides) != 1:
            raise ValueError(f"keyframes of one set share a stride, got {sorted(strides)}")
        return cls(
            np.stack([k.gray for k in keyframes]),
            np.stack([k.depth for k in keyframes]).astype(np.float32),
            np.stack([k.c2w for k in keyframes]).astype(np.float64),
            np.stack([k.intrinsics.K for k in keyframes]),
            strides.pop(),
        )


def prepare_corners(
    keyframe: Callable[[int], Keyframe], c2ws: np.ndarray, count: int, which: Sequence[int] | None = None
) -> None:
    """Triangulated corners (acesplat.align.keyframe_depth.triangulate_corners) for the keyframes ``keyframe(i)``
    (of camera-to-worlds c2ws (N, 4, 4)) of ``which`` (default: all) that have none yet, each with its
    depth_neighbours."""
    for i in range(len(c2ws)) if which is None else which:
        kf = keyframe(i)
        made = kf.cache.get(("corners", count))
        if made is not None and made.triangulated is not None:
            continue
        known = kf.depth[kf.depth > 0]
        nbs = depth_neighbours(c2ws, i, float(np.median(known)), CORNER_NEIGHBOURS) if known.size else []
        triangulate_corners(kf, [keyframe(j) for j in nbs], count)


def triangulated_points(
    keyframes: Sequence[Keyframe], rgbs: Sequence[np.ndarray], count: int
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Points (N, 3) and colours (N, 3) of every keyframe's ``count`` strongest corners that its neighbouring
    keyframes triangulate (acesplat.align.keyframe_depth.triangulate_corners), and how many each gave: places
    matched between the images and triangulated with their poses, as SfM points are (Stage 2's 'corners' start;
    the keyframes' depth grids are only the first guess).

    ``rgbs`` (H, W, 3) per keyframe, at its image's size: the seeds' colours."""
    if len(rgbs) != len(keyframes) or not keyframes:
        raise ValueError(f"need one colour image per keyframe, got {len(rgbs)} for {len(keyframes)}")
    for kf, rgb in zip(keyframes, rgbs, strict=True):
        if np.shape(rgb) != (*kf.gray.shape, 3):
            raise ValueError(f"a colour image is {np.shape(rgb)}, its keyframe {kf.gray.shape}")
    prepare_corners(keyframes.__getitem__, np.stack([kf.c2w for kf in keyframes]), count)
    points, colours, per_view = [], [], []
    for kf, rgb in zip(keyframes, rgbs, strict=True):
        c = keyframe_corners(kf, count)
        keep = c.triangulated  # set by prepare_corners
        u = np.rint(c.uv[keep]).astype(np.int64)
        points.append(c.X[keep])
        colours.append(np.asarray(rgb)[u[:, 1], u[:, 0]].astype(np.float32))
        per_view.append(int(keep.sum()))
    return np.concatenate(points), np.concatenate(colours), per_view


def save_keyframes(path: str | Path, ks: KeyframeSet) -> None:
    """Write ``ks`` to ``path`` (.npz, depth as float16), atomically."""
    with atomic_path(path, ".npz") as tmp:
        np.savez_compressed(
            tmp, gray=ks.gray, depth=ks.depth.astype(np.float16), c2w=ks.c2w, K=ks.K, stride=np.int64(ks.stride)
        )


def load_keyframes(path: str | Path) -> KeyframeSet:
    """Read and check a keyframe file; InputError naming it on anything malformed."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in ("gray", "depth", "c2w", "K", "stride")}
    except FileNotFoundError:
        raise InputError(path, "keyframe file not found") from None
    except (KeyError, ValueError, OSError) as e:
        raise InputError(path, f"not a keyframe file ({e})") from None
    gray, depth, c2w, K = arrays["gray"], arrays["depth"].astype(np.float32), arrays["c2w"], arrays["K"]
    stride = int(arrays["stride"])
    n = gray.shape[0] if gray.ndim == 3 else -1
    if gray.dtype != np.uint8 or n < 1:
        raise InputError(path, f"gray must be (N, H, W) uint8 with N >= 1, got {gray.shape} {gray.dtype}")
    if depth.ndim != 3 or c2w.shape != (n, 4, 4) or K.shape != (n, 3, 3) or depth.shape[0] != n:
        raise InputError(path, f"{n} images but depth {depth.shape}, c2w {c2w.shape}, K {K.shape}")
    if stride not in (OUTPUT_STRIDE, DENSE_OUTPUT_STRIDE):
        raise InputError(path, f"stride must be {DENSE_OUTPUT_STRIDE} or {OUTPUT_STRIDE}, got {stride}")
    h, w = gray.shape[1:]
    if depth.shape[1] * stride < h - stride or depth.shape[2] * stride < w - stride:
        raise InputError(path, f"a depth grid of {depth.shape[1:]} at stride {stride} does not cover {h}x{w} images")
    for i in range(n):
        problem = rigidity_problem(c2w[i])
        if problem:
            raise InputError(path, f"keyframe {i}: {problem}")
        if not (np.all(np.isfinite(K[i])) and K[i][0, 0] > 0 and K[i][1, 1] > 0):
            raise InputError(path, f"keyframe {i}: focal length must be positive and finite")
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
    return KeyframeSet(gray, depth, c2w.astype(np.float64), K.astype(np.float64), stride)


def bundle_keyframes(bundle: Bundle) -> KeyframeSet:
    """The keyframes a bundle carries for pose refinement; InputError naming the manifest if it has none."""
    if not bundle.has(ROLE_KEYFRAMES):
        raise InputError(bundle.root / MANIFEST_NAME, "bundle has no keyframes to align to; re-export with --keyframes")
    return load_keyframes(bundle.path(ROLE_KEYFRAMES))
