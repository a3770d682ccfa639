"""A complete synthetic room: layout, surface table and the lit texture atlas, made from one seed."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from acesplat.synth.atlas import TextureAtlas, build_atlas
from acesplat.synth.layout import Objects, RoomLayout, make_layout
from acesplat.synth.lighting import LIGHT_SPACING, light_map
from acesplat.synth.photos import load_photos
from acesplat.synth.surfaces import (
    CYLINDER_SIDE,
    ROLE_CEILING,
    ROLE_FLOOR,
    ROLE_WALL,
    SPHERE,
    SurfaceTable,
    build_surfaces,
)
from acesplat.synth.textures import ceiling_texture, floor_texture, object_texture, wall_texture
from acesplat.synth.trajectory import CameraPath

DEFAULT_SIZE = (6.0, 4.0, 3.0)
DEFAULT_TEXEL_DENSITY = 160.0
"""Texels per metre: about the pixel density of a 320-pixel-wide, 62-degree view at 1.7 m."""
MAX_TEXTURE_SIDE = 2048
MIN_TEXTURE_SIDE = 4


@dataclass
class RoomScene:
    """Everything needed to render views of one synthetic room (metres, world z up, floor at z = 0)."""

    seed: int
    layout: RoomLayout
    surfaces: SurfaceTable
    atlas: TextureAtlas
    texel_density: float
    photo_count: int
    texels_per_metre: np.ndarray  # (S,) level-0 density of each surface (geometric mean of u and v)

    @property
    def size(self) -> np.ndarray:
        return self.layout.size

    @property
    def objects(self) -> Objects:
        return self.layout.objects

    @property
    def path(self) -> CameraPath:
        return self.layout.path


def texture_shape(table: SurfaceTable, s: int, rho: float) -> tuple[int, int]:
    """(h, w) texels of surface ``s`` at ``rho`` texels per metre, clamped to sane sizes."""
    U, V = table.extent[s]
    w = int(np.clip(math.ceil(U * rho), MIN_TEXTURE_SIDE, MAX_TEXTURE_SIDE))
    h = int(np.clip(math.ceil(V * rho), MIN_TEXTURE_SIDE, MAX_TEXTURE_SIDE))
    return h, w


def make_room(
    seed: int = 0,
    size: tuple[float, float, float] | np.ndarray | None = None,
    texel_density: float = DEFAULT_TEXEL_DENSITY,
    n_objects: int | None = None,
    wide: bool = False,
) -> RoomScene:
    """The room of ``seed``: ``size`` (x, y, z) metres (default 6 x 4 x 3), objects, camera path, lit textures.

    Layout and textures draw from independent streams of the seed, so a change to one texture
    recipe does not move the furniture.
    """
    size = np.asarray(DEFAULT_SIZE if size is None else size, dtype=np.float64)
    if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size < (2.5, 2.5, 2.2)):
        raise ValueError(f"room size must be 3 finite lengths of at least 2.5 x 2.5 x 2.2 m, got {size}")
    if not texel_density > 0:
        raise ValueError(f"texel_density must be positive, got {texel_density}")
    layout = make_layout(np.random.default_rng([seed, 0]), size, n_objects=n_objects, wide=wide)
    table = build_surfaces(layout)
    rng = np.random.default_rng([seed, 1])
    photos = load_photos()
    recipes = {ROLE_WALL: wall_texture, ROLE_FLOOR: floor_texture, ROLE_CEILING: ceiling_texture}
    light_spacing = float(np.clip(8.0 / texel_density, LIGHT_SPACING, 0.15))  # coarse textures need no fine light
    textures = []
    rhos = np.zeros(len(table), dtype=np.float32)
    for s in range(len(table)):
        h, w = texture_shape(table, s, texel_density)
        rho = float(np.sqrt(h * w / (table.extent[s, 0] * table.extent[s, 1])))
        rhos[s] = rho
        albedo = recipes.get(int(table.role[s]), object_texture)(rng, photos, h, w, rho)
        textures.append(albedo * light_map(layout, table, s, h, w, spacing=light_spacing))
    atlas = build_atlas(textures, wrap_u=[int(k) in (CYLINDER_SIDE, SPHERE) for k in table.kind])
    return RoomScene(
        seed=seed,
        layout=layout,
        surfaces=table,
        atlas=atlas,
        texel_density=texel_density,
        photo_count=len(photos),
        texels_per_metre=rhos,
    )
