"""All surface textures and their mip levels packed into one image, sampled trilinearly with cv2.remap.

One atlas image lets the renderer fetch every pixel's texels with one remap per mip level, whatever
surface the pixel sees. Each tile carries a one-texel border (a copy of its own edge, or of the
opposite edge for surfaces closed in u) so bilinear filtering clamps or wraps correctly without
per-pixel branches. Mip levels prefilter the textures so distant or grazing surfaces are averaged
instead of aliased (aliasing flickers between views and hurts matching and splatting PSNR).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

PAD = 1
ATLAS_WIDTH = 4096
MAX_ATLAS_HEIGHT = 32000
"""cv2.remap addresses source pixels with 16-bit integers."""
MIN_LEVEL_SIDE = 2
REMAP_COLS = 1024
"""Lookups are laid out as rows of this many pixels for cv2.remap."""


@dataclass(frozen=True)
class TextureAtlas:
    """Packed RGB uint8 tiles.

    ``image`` (AH, ATLAS_WIDTH, 3); per (surface, level) tables (S, L) float32 of the tile interior's
    top-left corner ``x0``, ``y0`` and size ``width``, ``height`` (levels past a surface's chain repeat
    its last level); ``levels`` (S,) valid levels per surface.
    """

    image: np.ndarray
    x0: np.ndarray
    y0: np.ndarray
    width: np.ndarray
    height: np.ndarray
    levels: np.ndarray

    @property
    def nbytes(self) -> int:
        return int(self.image.nbytes)


def mip_chain(image: np.ndarray) -> list[np.ndarray]:
    """Level 0 and successive box-filtered halvings of ``image`` (h, w, 3) down to a side of 2 texels."""
    levels = [image]
    while min(levels[-1].shape[:2]) >= 2 * MIN_LEVEL_SIDE:
        h, w = levels[-1].shape[:2]
        levels.append(cv2.resize(levels[-1], ((w + 1) // 2, (h + 1) // 2), interpolation=cv2.INTER_AREA))
    return levels


def _padded(tile: np.ndarray, wrap_u: bool) -> np.ndarray:
    """The tile with a one-texel border: wrapped in u for closed surfaces, replicated otherwise."""
    out = cv2.copyMakeBorder(tile, PAD, PAD, 0, 0, cv2.BORDER_REPLICATE)
    return cv2.copyMakeBorder(out, 0, 0, PAD, PAD, cv2.BORDER_WRAP if wrap_u else cv2.BORDER_REPLICATE)


def build_atlas(textures: Sequence[np.ndarray], wrap_u: Sequence[bool]) -> TextureAtlas:
    """Pack float RGB textures (h, w, 3) in [0, 1], one per surface, with their mip chains (shelf packing)."""
    if len(textures) != len(wrap_u):
        raise ValueError(f"{len(textures)} textures but {len(wrap_u)} wrap flags")
    chains = []
    for t in textures:
        u8 = (np.clip(t, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        if u8.shape[1] + 2 * PAD > ATLAS_WIDTH:
            raise ValueError(f"texture of width {u8.shape[1]} does not fit an atlas {ATLAS_WIDTH} wide")
        chains.append(mip_chain(u8))
    S, L = len(chains), max(len(c) for c in chains)
    tiles = [(s, lvl, _padded(chains[s][lvl], bool(wrap_u[s]))) for s in range(S) for lvl in range(len(chains[s]))]
    order = sorted(range(len(tiles)), key=lambda i: -tiles[i][2].shape[0])
    placed = {}
    x = y = shelf = 0
    for i in order:
        th, tw = tiles[i][2].shape[:2]
        if x + tw > ATLAS_WIDTH:
            x, y, shelf = 0, y + shelf, 0
        placed[i] = (x, y)
        x += tw
        shelf = max(shelf, th)
    height = y + shelf
    if height > MAX_ATLAS_HEIGHT:
        raise ValueError(
            f"textures need an atlas {height} texels high (max {MAX_ATLAS_HEIGHT}); lower the texel density"
        )
    image = np.zeros((height, ATLAS_WIDTH, 3), dtype=np.uint8)
    x0 = np.zeros((S, L), np.float32)
    y0 = np.zeros((S, L), np.float32)
    width = np.zeros((S, L), np.float32)
    hgt = np.zeros((S, L), np.float32)
    for i, (s, lvl, tile) in enumerate(tiles):
        px, py = placed[i]
        th, tw = tile.shape[:2]
        image[py : py + th, px : px + tw] = tile
        x0[s, lvl:], y0[s, lvl:] = px + PAD, py + PAD
        width[s, lvl:], hgt[s, lvl:] = tw - 2 * PAD, th - 2 * PAD
    return TextureAtlas(image=image, x0=x0, y0=y0, width=width, height=hgt, levels=np.array([len(c) for c in chains]))


def sample(atlas: TextureAtlas, sid: np.ndarray, un: np.ndarray, vn: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Trilinear lookup: RGB uint8 (..., 3) for surfaces ``sid`` at normalised (u, v).

    ``sid``, ``un``, ``vn``, ``level`` share one shape (e.g. (H, W)); u, v in [0, 1] (u may wrap);
    ``level`` is the continuous mip level (0 = full resolution), clamped to each surface's chain.
    """
    shape = np.shape(sid)
    sid = np.asarray(sid).reshape(-1)
    lmax = (atlas.levels[sid] - 1).astype(np.float32)
    level = np.minimum(np.maximum(np.asarray(level, np.float32).reshape(-1), 0.0), lmax)
    l0 = np.floor(level)
    frac = level - l0
    l0 = l0.astype(np.int64)
    l1 = np.minimum(l0 + 1, lmax.astype(np.int64))
    L = atlas.x0.shape[1]
    un = np.asarray(un, np.float32).reshape(-1)
    vn = np.asarray(vn, np.float32).reshape(-1)
    n = len(sid)
    rows = -(-n // REMAP_COLS)
    mapx = np.zeros((2, rows * REMAP_COLS), np.float32)
    mapy = np.zeros((2, rows * REMAP_COLS), np.float32)
    for k, lvl in enumerate((l0, l1)):
        flat = sid * L + lvl
        mapx[k, :n] = np.take(atlas.x0, flat) + un * np.take(atlas.width, flat) - 0.5
        mapy[k, :n] = np.take(atlas.y0, flat) + vn * np.take(atlas.height, flat) - 0.5
    both = cv2.remap(
        atlas.image,
        mapx.reshape(2 * rows, REMAP_COLS),
        mapy.reshape(2 * rows, REMAP_COLS),
        interpolation=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    w1 = np.zeros(rows * REMAP_COLS, np.float32)
    w1[:n] = frac
    w1 = w1.reshape(rows, REMAP_COLS)
    out = cv2.blendLinear(both[:rows], both[rows:], 1.0 - w1, w1)  # per-pixel blend of the two mip levels
    return out.reshape(-1, 3)[:n].reshape(shape + (3,))
