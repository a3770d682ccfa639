"""View-independent lighting baked into the textures once per room.

A ceiling lamp lights every surface with Lambert's cosine law and a distance falloff; soft shadows
come from a few shadow rays towards points of the lamp; corners and contacts darken through an
ambient-occlusion approximation from distances to the room planes and the objects. Everything is a
function of the surface point alone, never of the viewer, so a Gaussian splat of the scene can
reproduce it exactly, and rendering a frame costs nothing extra.
The lighting is smooth, so it is evaluated on a coarse grid (``LIGHT_SPACING``) and upsampled.
"""

from __future__ import annotations

import cv2
import numpy as np

from acesplat.synth.layout import RoomLayout
from acesplat.synth.primitives import MISS
from acesplat.synth.surfaces import PLANAR, SurfaceTable, surface_grid

LIGHT_SPACING = 0.05
"""Finest grid spacing (metres) at which lighting is evaluated before upsampling to texture resolution."""
AMBIENT = 0.45
DIRECT = 0.8
FALLOFF = 3.0
"""Distance (metres) at which the lamp's contribution has halved."""
LAMP_RADIUS = 0.2
SHADOW_SAMPLES = 5
ROOM_AO = (0.3, 0.3)
"""Strength and length scale (metres) of the darkening near walls, floor and ceiling."""
OBJECT_AO = (0.5, 0.12)
"""Strength and length scale (metres) of the darkening near objects (contact shadows)."""
LAMP_COLOR = np.array([1.0, 0.96, 0.9])
SKY_COLOR = np.array([0.93, 0.96, 1.0])


def lamp_points(light: np.ndarray) -> np.ndarray:
    """Points (SHADOW_SAMPLES, 3) on a horizontal disc around the lamp centre: soft shadow edges."""
    ang = np.arange(SHADOW_SAMPLES - 1) * 2 * np.pi / (SHADOW_SAMPLES - 1)
    ring = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], axis=1) * LAMP_RADIUS
    return light + np.concatenate([np.zeros((1, 3)), ring])


def shadow_visibility(layout: RoomLayout, X: np.ndarray, N: np.ndarray) -> np.ndarray:
    """Fraction (M,) of lamp points visible from surface points ``X`` (M, 3) with normals ``N`` (M, 3)."""
    ob = layout.objects
    start = (X + 0.01 * N).astype(np.float32)
    ox, oy, oz = start[:, 0].copy(), start[:, 1].copy(), start[:, 2].copy()
    vis = np.zeros(len(X), dtype=np.float32)
    for lp in lamp_points(layout.light).astype(np.float32):
        dx, dy, dz = lp[0] - ox, lp[1] - oy, lp[2] - oz
        t = np.full(len(X), MISS, dtype=np.float32)
        for k in range(len(ob)):
            np.minimum(t, ob.hit(k, ox, oy, oz, dx, dy, dz), out=t)
        vis += t >= 1.0
    return vis / SHADOW_SAMPLES


def irradiance(layout: RoomLayout, table: SurfaceTable, s: int, X: np.ndarray, N: np.ndarray) -> np.ndarray:
    """RGB light factor (M, 3) at points ``X`` (M, 3) with normals ``N`` (M, 3) of surface ``s``."""
    L = layout.light - X
    dist = np.linalg.norm(L, axis=1)
    cos = np.clip(np.einsum("ij,ij->i", N, L) / dist, 0.0, 1.0)
    direct = DIRECT * cos / (1.0 + (dist / FALLOFF) ** 2)
    lit = cos > 0
    if lit.any():
        direct[lit] *= shadow_visibility(layout, X[lit], N[lit])
    ao = np.ones(len(X))
    k, sigma = ROOM_AO
    own_plane = -1
    if table.owner[s] < 0 and table.kind[s] == PLANAR:
        own_plane = int(np.argmax(np.abs(table.normal[s]))) * 2 + int(table.normal[s].sum() < 0)
    for axis in range(3):
        for side in range(2):
            if 2 * axis + side == own_plane:
                continue
            d = X[:, axis] if side == 0 else layout.size[axis] - X[:, axis]
            ao *= 1.0 - k * np.exp(-np.maximum(d, 0.0) / sigma)
    k, sigma = OBJECT_AO
    sdf = layout.objects.sdf(X)
    for o in range(len(sdf)):
        if o != table.owner[s]:
            ao *= 1.0 - k * np.exp(-np.maximum(sdf[o], 0.0) / sigma)
    return (AMBIENT * SKY_COLOR[None] + direct[:, None] * LAMP_COLOR[None]) * ao[:, None]


def light_map(
    layout: RoomLayout, table: SurfaceTable, s: int, h: int, w: int, spacing: float = LIGHT_SPACING
) -> np.ndarray:
    """Light factor (h, w, 3) float32 for surface ``s`` with an h x w texture, evaluated every ``spacing`` metres."""
    nu = int(np.clip(np.ceil(table.extent[s, 0] / spacing), 2, w))
    nv = int(np.clip(np.ceil(table.extent[s, 1] / spacing), 2, h))
    X, N = surface_grid(table, s, nu, nv)
    E = irradiance(layout, table, s, X.reshape(-1, 3), N.reshape(-1, 3)).reshape(nv, nu, 3).astype(np.float32)
    return cv2.resize(E, (w, h), interpolation=cv2.INTER_LINEAR)
