"""Vectorised ray casting of a synthetic room: analytic hits, trilinear textures, optional supersampling.

Ray directions have camera-z component 1, so the hit distance ``t`` is the z-depth itself. The
nearest hit is tracked as one int64 key per pixel (float32 bits of ``t`` above the id of what was
hit), so "closer wins" is a single ``np.minimum``. Each object is tested only on the pixels inside
the screen rectangle of its bounding sphere, so small or distant objects cost little.
"""

from __future__ import annotations

import functools

import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import rigidity_problem
from acesplat.synth.atlas import sample
from acesplat.synth.primitives import MISS, exit_room
from acesplat.synth.room import RoomScene
from acesplat.synth.surfaces import surface_coords

MIP_BIAS = 0.0
"""Added to the mip level: positive blurs more, negative sharpens (and aliases) more."""
ROOM_CODES = 6
"""Hit codes 0..5 are the room's faces (= their surface ids); object ``k`` is code 6 + k."""
_SHIFT = 16


@functools.lru_cache(maxsize=8)
def pixel_rays(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame ray slopes x/z, y/z (H, W) float32 through pixel centres (integer coordinates, as in Intrinsics)."""
    u = np.arange(width, dtype=np.float64)
    v = np.arange(height, dtype=np.float64)
    x = np.broadcast_to(((u - cx) / fx).astype(np.float32)[None], (height, width)).copy()
    y = np.broadcast_to(((v - cy) / fy).astype(np.float32)[:, None], (height, width)).copy()
    x.setflags(write=False)
    y.setflags(write=False)
    return x, y


def _key(t: np.ndarray, code: int | np.ndarray) -> np.ndarray:
    return (t.view(np.int32).astype(np.int64) << _SHIFT) | code


def screen_rect(
    center_cam: np.ndarray, radius: float, fx: float, fy: float, cx: float, cy: float, width: int, height: int
) -> tuple[int, int, int, int] | None:
    """Conservative pixel rectangle (v0, v1, u0, u1) covering a sphere in camera coordinates, None if not in view."""
    X, Y, Z = center_cam
    if Z + radius <= 0:
        return None
    if Z - radius <= 1e-3:
        return 0, height, 0, width
    bounds = []
    for c, f, p, n in ((X, fx, cx, width), (Y, fy, cy, height)):
        hi = (c + radius) / (Z - radius if c + radius >= 0 else Z + radius)
        lo = (c - radius) / (Z - radius if c - radius <= 0 else Z + radius)
        a = max(0, int(np.floor(f * lo + p)) - 1)
        b = min(n, int(np.floor(f * hi + p)) + 2)
        if a >= b:
            return None
        bounds.append((a, b))
    (u0, u1), (v0, v1) = bounds
    return v0, v1, u0, u1


def cast(
    scene: RoomScene, pose: np.ndarray, xs: np.ndarray, ys: np.ndarray, intrinsics: Intrinsics, cull: bool = True
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Nearest hits of the rays with camera-frame slopes ``xs``, ``ys`` (h, w) from ``pose``.

    With ``cull`` the rays must be the image grid of ``intrinsics`` and each object is only tested
    inside its screen rectangle; without, any ray set works and every object in view is tested.
    Returns z-depth (h, w) float32, hit code (h, w) int64 (see ROOM_CODES) and world directions.
    """
    R = pose[:3, :3].astype(np.float32)
    o = pose[:3, 3].astype(np.float32)
    ox, oy, oz = (np.float32(v) for v in o)
    dx = R[0, 0] * xs + R[0, 1] * ys + R[0, 2]
    dy = R[1, 0] * xs + R[1, 1] * ys + R[1, 2]
    dz = R[2, 0] * xs + R[2, 1] * ys + R[2, 2]
    ts, sides = exit_room(ox, oy, oz, dx, dy, dz, scene.size)
    key = _key(ts[0], sides[0].view(np.int8).astype(np.int64))
    for axis in (1, 2):
        np.minimum(key, _key(ts[axis], 2 * axis + sides[axis].view(np.int8).astype(np.int64)), out=key)
    centers, radii = scene.objects.bounding_spheres()
    cam = (centers - pose[:3, 3]) @ pose[:3, :3]
    k = intrinsics
    h, w = xs.shape
    for gid in range(len(radii)):
        rect = screen_rect(cam[gid], radii[gid], k.fx, k.fy, k.cx, k.cy, k.width, k.height)
        if rect is None:
            continue
        v0, v1, u0, u1 = rect
        sub = (slice(v0, v1), slice(u0, u1)) if cull else (slice(None), slice(None))
        t_obj = scene.objects.hit(gid, ox, oy, oz, dx[sub], dy[sub], dz[sub])
        np.minimum(key[sub], _key(t_obj, ROOM_CODES + gid), out=key[sub])
    depth = (key >> _SHIFT).astype(np.int32).view(np.float32)
    code = key & ((1 << _SHIFT) - 1)
    return depth, code, (dx, dy, dz)


def surface_ids(scene: RoomScene, code: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Surface ids (P,) from hit codes (P,) and hit points: which face of a box or cylinder was hit."""
    ob, table = scene.objects, scene.surfaces
    nb, nc, _ = ob.counts
    sid = code.copy()
    g = code - ROOM_CODES
    idx = np.flatnonzero((g >= 0) & (g < nb))
    if idx.size:
        b = g[idx]
        c, s = np.cos(ob.box_yaw[b]), np.sin(ob.box_yaw[b])
        px, py, pz = x[idx] - ob.box_center[b, 0], y[idx] - ob.box_center[b, 1], z[idx] - ob.box_center[b, 2]
        q = np.stack([c * px + s * py, c * py - s * px, pz], axis=1)
        axis = np.argmax(np.abs(q) / ob.box_half[b], axis=1)
        side = np.take_along_axis(q, axis[:, None], axis=1)[:, 0] > 0
        sid[idx] = table.box_base + 6 * b + 2 * axis + side
    idx = np.flatnonzero((g >= nb) & (g < nb + nc))
    if idx.size:
        kc = g[idx] - nb
        rr = np.hypot(x[idx] - ob.cyl_center[kc, 0], y[idx] - ob.cyl_center[kc, 1])
        dist = np.stack(
            [np.abs(rr - ob.cyl_radius[kc]), np.abs(z[idx] - ob.cyl_z0[kc]), np.abs(z[idx] - ob.cyl_z1[kc])], axis=1
        )
        sid[idx] = table.cyl_base + 3 * kc + np.argmin(dist, axis=1)
    idx = np.flatnonzero(g >= nb + nc)
    if idx.size:
        sid[idx] = table.sph_base + g[idx] - nb - nc
    return sid


def _check(scene: RoomScene, pose: np.ndarray, intrinsics: Intrinsics, ss: int) -> np.ndarray:
    if not isinstance(scene, RoomScene):
        raise TypeError(f"scene must be a RoomScene, got {type(scene).__name__}")
    if not isinstance(intrinsics, Intrinsics):
        raise TypeError(f"intrinsics must be an Intrinsics, got {type(intrinsics).__name__}")
    if not (isinstance(ss, int) and 1 <= ss <= 4):
        raise ValueError(f"supersampling must be an integer in 1..4, got {ss!r}")
    pose = np.asarray(pose, dtype=np.float64)
    problem = rigidity_problem(pose)
    if problem:
        raise ValueError(problem)
    o = pose[:3, 3]
    if np.any(o <= 0) or np.any(o >= scene.size):
        raise ValueError(f"camera position {o.tolist()} is outside the room [0, {scene.size.tolist()}]")
    return pose


def _shade(
    scene: RoomScene, pose: np.ndarray, depth: np.ndarray, code: np.ndarray, dirs: tuple, focal: float
) -> tuple[np.ndarray, np.ndarray]:
    """Colours (P, 3) uint8 and surface ids (P,) of the hits of one cast."""
    dx, dy, dz = (d.reshape(-1) for d in dirs)
    t = depth.reshape(-1)
    o = pose[:3, 3].astype(np.float32)
    x, y, z = o[0] + t * dx, o[1] + t * dy, o[2] + t * dz
    sid = surface_ids(scene, code.reshape(-1), x, y, z)
    nx, ny, nz, un, vn = surface_coords(scene.surfaces, sid, x, y, z)
    cos = np.abs(nx * dx + ny * dy + nz * dz)
    # Pixel footprint on the surface: z / (f sqrt|n . d|) metres for directions with camera z = 1.
    footprint = t / (np.float32(focal) * np.sqrt(np.maximum(cos, np.float32(1e-3))))
    level = np.log2(np.maximum(footprint * np.take(scene.texels_per_metre, sid), np.float32(1e-6))) + np.float32(
        MIP_BIAS
    )
    return sample(scene.atlas, sid, un, vn, level), sid


def edge_pixels(sid: np.ndarray) -> np.ndarray:
    """Flat indices of pixels whose 4-neighbourhood sees another surface (H, W) -> (M,)."""
    edge = np.zeros(sid.shape, dtype=bool)
    dh = sid[:, 1:] != sid[:, :-1]
    dv = sid[1:] != sid[:-1]
    edge[:, 1:] |= dh
    edge[:, :-1] |= dh
    edge[1:] |= dv
    edge[:-1] |= dv
    return np.flatnonzero(edge)


def render_view(
    scene: RoomScene, pose: np.ndarray, intrinsics: Intrinsics, supersample: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Render RGB uint8 (H, W, 3) and metric z-depth float32 (H, W) of ``scene`` from camera-to-world ``pose`` (4, 4).

    ``supersample`` = s re-renders pixels on surface boundaries with s x s rays and averages them
    (antialiased silhouettes and face edges; inside a surface the mip levels already filter).
    Depth always comes from the ray through the pixel centre, so it stays exact.
    """
    pose = _check(scene, pose, intrinsics, supersample)
    k = intrinsics
    H, W = k.height, k.width
    xs, ys = pixel_rays(k.fx, k.fy, k.cx, k.cy, W, H)
    depth, code, dirs = cast(scene, pose, xs, ys, k)
    if np.any(depth >= MISS):
        raise RuntimeError("a ray left the room without hitting a wall (is the camera inside the room?)")
    rgb, sid = _shade(scene, pose, depth, code, dirs, k.fx)
    if supersample > 1:
        idx = edge_pixels(sid.reshape(H, W))
        if idx.size:
            s = supersample
            off = ((np.arange(s) + 0.5) / s - 0.5).astype(np.float32)
            u = ((idx % W).astype(np.float32)[:, None, None] + off[None, None, :]).repeat(s, axis=1)
            v = ((idx // W).astype(np.float32)[:, None, None] + off[None, :, None]).repeat(s, axis=2)
            sx = ((u - np.float32(k.cx)) / np.float32(k.fx)).reshape(1, -1)
            sy = ((v - np.float32(k.cy)) / np.float32(k.fy)).reshape(1, -1)
            d2, c2, dirs2 = cast(scene, pose, sx, sy, k, cull=False)
            fine, _ = _shade(scene, pose, d2, c2, dirs2, k.fx * s)
            rgb[idx] = (fine.reshape(idx.size, s * s, 3).mean(axis=1) + 0.5).astype(np.uint8)
    return rgb.reshape(H, W, 3), depth
