"""Analytic ray-primitive intersections and signed distances, branch-free numpy over rays.

A ray is ``X = O + t D``; ``D`` need not be unit length (the renderer uses camera-z = 1, so ``t`` is
the z-depth). Origins are given per component and may be scalars (one camera) or arrays (shadow
rays); direction components are arrays of any one shape. Each function returns the nearest hit
``t`` with :data:`MISS` where there is none. Masks are turned into ``MISS`` with ``fmax`` instead of
``np.where``, which is several times slower on scattered masks.
"""

from __future__ import annotations

import numpy as np

EPS = np.float32(1e-4)
"""Smallest accepted hit distance (in units of ``t``): a ray never re-hits the surface it starts on."""
MISS = np.float32(1e30)
"""``t`` of rays that miss (finite, so it packs into sort keys and survives arithmetic)."""

Scalar = float | np.ndarray


def _miss_unless(t: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """``t`` where ``hit``, else MISS (NaN or inf in ``t`` count as misses)."""
    return np.fmin(np.fmax(t, (~hit) * MISS), MISS)


def exit_room(
    ox: Scalar, oy: Scalar, oz: Scalar, dx: np.ndarray, dy: np.ndarray, dz: np.ndarray, size: np.ndarray
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Distances to the planes through which rays from inside the box [0, size] leave it, per axis.

    Returns ([t_x, t_y, t_z], [hit max side x, y, z]); the exit is the smallest of the three.
    """
    ts, sides = [], []
    with np.errstate(divide="ignore", invalid="ignore"):
        for o, d, L in ((ox, dx, size[0]), (oy, dy, size[1]), (oz, dz, size[2])):
            pos = d > 0
            t = np.abs((pos * np.float32(L) - o) / d)  # abs: a zero component gives +-inf; it never exits there
            ts.append(t)
            sides.append(pos)
    return ts, sides


def hit_box(
    ox: Scalar,
    oy: Scalar,
    oz: Scalar,
    dx: np.ndarray,
    dy: np.ndarray,
    dz: np.ndarray,
    center: np.ndarray,
    half: np.ndarray,
    yaw: float,
) -> np.ndarray:
    """Entry distance into a box rotated by ``yaw`` about world z (slab method in the box frame).

    Rays starting inside the box miss it (the camera is never inside an object).
    """
    c, s = np.float32(np.cos(yaw)), np.float32(np.sin(yaw))
    px, py, pz = ox - np.float32(center[0]), oy - np.float32(center[1]), oz - np.float32(center[2])
    lo = (c * px + s * py, c * py - s * px, pz)
    ld = (c * dx + s * dy, c * dy - s * dx, dz)
    tnear = tfar = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for o, d, h in zip(lo, ld, half):
            h = np.float32(h)
            inv = 1.0 / d
            t1 = (-h - o) * inv
            t2 = (h - o) * inv
            mn, mx = np.minimum(t1, t2), np.maximum(t1, t2)
            tnear = mn if tnear is None else np.maximum(tnear, mn)
            tfar = mx if tfar is None else np.minimum(tfar, mx)
    return _miss_unless(tnear, (tnear <= tfar) & (tnear > EPS))


def hit_cylinder(
    ox: Scalar,
    oy: Scalar,
    oz: Scalar,
    dx: np.ndarray,
    dy: np.ndarray,
    dz: np.ndarray,
    center: np.ndarray,
    radius: float,
    z0: float,
    z1: float,
) -> np.ndarray:
    """Nearest hit on a closed vertical cylinder (axis at ``center`` (2,) in xy, z in [z0, z1])."""
    r2 = np.float32(radius * radius)
    z0, z1 = np.float32(z0), np.float32(z1)
    px, py = ox - np.float32(center[0]), oy - np.float32(center[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        a = dx * dx + dy * dy
        hb = px * dx + py * dy
        disc = hb * hb - a * (px * px + py * py - r2)
        ts = (-hb - np.sqrt(np.maximum(disc, 0.0))) / a
        zs = oz + ts * dz
        best = _miss_unless(ts, (disc >= 0) & (ts > EPS) & (zs >= z0) & (zs <= z1))
        inv_dz = 1.0 / dz
        for zc in (z0, z1):
            tc = (zc - oz) * inv_dz
            xc, yc = px + tc * dx, py + tc * dy
            best = np.minimum(best, _miss_unless(tc, (tc > EPS) & (xc * xc + yc * yc <= r2)))
    return best


def hit_sphere(
    ox: Scalar,
    oy: Scalar,
    oz: Scalar,
    dx: np.ndarray,
    dy: np.ndarray,
    dz: np.ndarray,
    center: np.ndarray,
    radius: float,
) -> np.ndarray:
    """Entry distance into a sphere."""
    px, py, pz = ox - np.float32(center[0]), oy - np.float32(center[1]), oz - np.float32(center[2])
    with np.errstate(divide="ignore", invalid="ignore"):
        a = dx * dx + dy * dy + dz * dz
        hb = px * dx + py * dy + pz * dz
        disc = hb * hb - a * (px * px + py * py + pz * pz - np.float32(radius * radius))
        ts = (-hb - np.sqrt(np.maximum(disc, 0.0))) / a
    return _miss_unless(ts, (disc >= 0) & (ts > EPS))


def sdf_box(X: np.ndarray, center: np.ndarray, half: np.ndarray, yaw: float) -> np.ndarray:
    """Signed distance (...,) from points ``X`` (..., 3) to one yaw-rotated box (negative inside)."""
    c, s = np.cos(yaw), np.sin(yaw)
    p = X - center
    q = np.stack([c * p[..., 0] + s * p[..., 1], -s * p[..., 0] + c * p[..., 1], p[..., 2]], axis=-1)
    d = np.abs(q) - half
    outside = np.linalg.norm(np.maximum(d, 0.0), axis=-1)
    return outside + np.minimum(d.max(axis=-1), 0.0)


def sdf_cylinder(X: np.ndarray, center: np.ndarray, radius: float, z0: float, z1: float) -> np.ndarray:
    """Signed distance (...,) from points ``X`` (..., 3) to a closed vertical cylinder."""
    dr = np.hypot(X[..., 0] - center[0], X[..., 1] - center[1]) - radius
    dz = np.abs(X[..., 2] - 0.5 * (z0 + z1)) - 0.5 * (z1 - z0)
    outside = np.hypot(np.maximum(dr, 0.0), np.maximum(dz, 0.0))
    return outside + np.minimum(np.maximum(dr, dz), 0.0)


def sdf_sphere(X: np.ndarray, center: np.ndarray, radius: float) -> np.ndarray:
    """Signed distance (...,) from points ``X`` (..., 3) to a sphere."""
    return np.linalg.norm(X - center, axis=-1) - radius


def sdf_box_xy(P: np.ndarray, center: np.ndarray, half: np.ndarray, yaw: float) -> np.ndarray:
    """Signed distance (...,) in the floor plane from points ``P`` (..., 2) to a box footprint."""
    c, s = np.cos(yaw), np.sin(yaw)
    px, py = P[..., 0] - center[0], P[..., 1] - center[1]
    d = np.stack([np.abs(c * px + s * py) - half[0], np.abs(-s * px + c * py) - half[1]], axis=-1)
    return np.linalg.norm(np.maximum(d, 0.0), axis=-1) + np.minimum(d.max(axis=-1), 0.0)
