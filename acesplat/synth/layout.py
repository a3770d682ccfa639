"""Room geometry: the walls, the furniture-like objects inside, the lamp and the camera path.

Objects sit at various depths (against walls, in corners, in the middle when there is room, stacked
on each other) so that views have parallax, and never inside the band of floor the camera passes
may use, so no camera ever starts inside or right against an object.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from acesplat.synth.primitives import (
    Scalar,
    hit_box,
    hit_cylinder,
    hit_sphere,
    sdf_box,
    sdf_box_xy,
    sdf_cylinder,
    sdf_sphere,
)
from acesplat.synth.trajectory import CameraPath, band_points, random_path

CAMERA_CLEARANCE = 0.35
"""Minimum floor distance (metres) between any object and the band the camera passes may use."""

OBJECT_GAP = 0.08
"""Minimum gap between the bounding circles of two objects standing on the floor."""


@dataclass
class Objects:
    """Boxes (yaw-rotated), closed vertical cylinders and spheres; global object ids run boxes, cylinders, spheres."""

    box_center: np.ndarray  # (Nb, 3)
    box_half: np.ndarray  # (Nb, 3)
    box_yaw: np.ndarray  # (Nb,)
    cyl_center: np.ndarray  # (Nc, 2)
    cyl_radius: np.ndarray  # (Nc,)
    cyl_z0: np.ndarray  # (Nc,)
    cyl_z1: np.ndarray  # (Nc,)
    sph_center: np.ndarray  # (Ns, 3)
    sph_radius: np.ndarray  # (Ns,)

    @property
    def counts(self) -> tuple[int, int, int]:
        return len(self.box_center), len(self.cyl_center), len(self.sph_center)

    def __len__(self) -> int:
        return sum(self.counts)

    def sdf(self, X: np.ndarray) -> np.ndarray:
        """Signed distances (K, ...) from points ``X`` (..., 3) to each object, in global id order."""
        out = [sdf_box(X, c, h, y) for c, h, y in zip(self.box_center, self.box_half, self.box_yaw)]
        out += [
            sdf_cylinder(X, c, r, a, b)
            for c, r, a, b in zip(self.cyl_center, self.cyl_radius, self.cyl_z0, self.cyl_z1)
        ]
        out += [sdf_sphere(X, c, r) for c, r in zip(self.sph_center, self.sph_radius)]
        return np.stack(out) if out else np.zeros((0,) + X.shape[:-1])

    def hit(
        self, k: int, ox: Scalar, oy: Scalar, oz: Scalar, dx: np.ndarray, dy: np.ndarray, dz: np.ndarray
    ) -> np.ndarray:
        """Nearest hit distance (MISS where none) of rays on object ``k`` (global id); see :mod:`.primitives`."""
        nb, nc, _ = self.counts
        if k < nb:
            return hit_box(ox, oy, oz, dx, dy, dz, self.box_center[k], self.box_half[k], self.box_yaw[k])
        if k < nb + nc:
            k -= nb
            return hit_cylinder(
                ox, oy, oz, dx, dy, dz, self.cyl_center[k], self.cyl_radius[k], self.cyl_z0[k], self.cyl_z1[k]
            )
        k -= nb + nc
        return hit_sphere(ox, oy, oz, dx, dy, dz, self.sph_center[k], self.sph_radius[k])

    def bounding_spheres(self) -> tuple[np.ndarray, np.ndarray]:
        """Centres (K, 3) and radii (K,) of spheres enclosing each object, in global id order (for culling)."""
        cyl_mid = np.concatenate([self.cyl_center, 0.5 * (self.cyl_z0 + self.cyl_z1)[:, None]], axis=1)
        cyl_r = np.hypot(self.cyl_radius, 0.5 * (self.cyl_z1 - self.cyl_z0))
        centers = np.concatenate([self.box_center, cyl_mid, self.sph_center]).reshape(-1, 3)
        radii = np.concatenate([np.linalg.norm(self.box_half, axis=1), cyl_r, self.sph_radius])
        return centers, radii


@dataclass
class RoomLayout:
    """Room box [0, size] (metres, z up, floor at z = 0), its objects, the lamp position and the camera path."""

    size: np.ndarray  # (3,)
    objects: Objects
    light: np.ndarray  # (3,)
    path: CameraPath


class _Builder:
    def __init__(self, rng: np.random.Generator, size: np.ndarray, path: CameraPath, light: np.ndarray) -> None:
        self.rng, self.size, self.light = rng, size, light
        self.band = band_points(path)
        self.boxes: list[tuple[np.ndarray, np.ndarray, float]] = []
        self.cyls: list[tuple[np.ndarray, float, float, float]] = []
        self.sphs: list[tuple[np.ndarray, float]] = []
        self.footprints: list[tuple[np.ndarray, float]] = []  # floor objects: xy centre, bounding radius

    def _free(self, xy: np.ndarray, rb: float, sdf_band: np.ndarray, sdf_light: float) -> bool:
        if sdf_band.min() < CAMERA_CLEARANCE or sdf_light < 0.3:
            return False
        if np.any(xy - rb < 0.02) or np.any(xy + rb > self.size[:2] - 0.02):
            return False
        return all(np.linalg.norm(xy - c) > rb + r + OBJECT_GAP for c, r in self.footprints)

    def floor_box(self, half: np.ndarray, xy: np.ndarray, yaw: float, exact_bounds: bool = False) -> bool:
        center = np.array([xy[0], xy[1], half[2]])
        rb = float(np.hypot(half[0], half[1]))
        sdf_band = sdf_box_xy(self.band, xy, half, yaw)
        sdf_light = float(sdf_box(self.light, center, half, yaw))
        if exact_bounds:
            # Cabinets stand flush against a wall: test the footprint corners instead of the bounding circle.
            c, s = np.cos(yaw), np.sin(yaw)
            corners = np.array([[sx * half[0], sy * half[1]] for sx in (-1, 1) for sy in (-1, 1)])
            corners = corners @ np.array([[c, s], [-s, c]]) + xy
            if np.any(corners < 0.0) or np.any(corners > self.size[:2]):
                return False
            if sdf_band.min() < CAMERA_CLEARANCE or sdf_light < 0.3:
                return False
            if not all(np.linalg.norm(xy - c0) > rb + r + OBJECT_GAP for c0, r in self.footprints):
                return False
        elif not self._free(xy, rb, sdf_band, sdf_light):
            return False
        self.boxes.append((center, half, yaw))
        self.footprints.append((xy, rb))
        return True

    def floor_cylinder(self, xy: np.ndarray, r: float, z0: float, z1: float, footprint: float | None = None) -> bool:
        rb = footprint if footprint is not None else r
        sdf_band = np.linalg.norm(self.band - xy, axis=1) - rb
        sdf_light = float(sdf_cylinder(self.light, xy, r, z0, z1))
        if not self._free(xy, rb, sdf_band, sdf_light):
            return False
        self.cyls.append((xy, r, z0, z1))
        self.footprints.append((xy, rb))
        return True

    def floor_sphere(self, xy: np.ndarray, r: float) -> bool:
        sdf_band = np.linalg.norm(self.band - xy, axis=1) - r
        center = np.array([xy[0], xy[1], r])
        if not self._free(xy, r, sdf_band, float(sdf_sphere(self.light, center, r))):
            return False
        self.sphs.append((center, r))
        self.footprints.append((xy, r))
        return True

    def stack_on(self, center: np.ndarray, half: np.ndarray, yaw: float) -> None:
        """Put a smaller object on top of a box (a second depth layer above the floor)."""
        rng = self.rng
        top = center[2] + half[2]
        m = float(min(half[0], half[1]))
        kind = rng.choice(["box", "sphere", "cylinder"])
        if kind == "box" and m > 0.12:
            h = np.array([rng.uniform(0.4, 0.7) * m, rng.uniform(0.4, 0.7) * m, rng.uniform(0.08, 0.3)])
            if top + 2 * h[2] < self.size[2] - 0.3:
                c = np.array([center[0], center[1], top + h[2]])
                if float(sdf_box(self.light, c, h, yaw)) > 0.3:
                    self.boxes.append((c, h, yaw + rng.uniform(-0.6, 0.6)))
        elif kind == "sphere":
            r = rng.uniform(0.5, 0.9) * min(m, 0.25)
            c = np.array([center[0], center[1], top + r])
            if c[2] + r < self.size[2] - 0.3 and float(sdf_sphere(self.light, c, r)) > 0.3:
                self.sphs.append((c, r))
        else:
            r = rng.uniform(0.4, 0.8) * min(m, 0.3)
            h = rng.uniform(0.1, 0.45)
            if top + h < self.size[2] - 0.3 and float(sdf_cylinder(self.light, center[:2], r, top, top + h)) > 0.3:
                self.cyls.append((center[:2].copy(), r, top, top + h))

    def objects(self) -> Objects:
        def arr(items: list, k: int, shape: tuple[int, ...]) -> np.ndarray:
            return np.array([it[k] for it in items], dtype=np.float64).reshape(shape)

        nb, nc, ns = len(self.boxes), len(self.cyls), len(self.sphs)
        return Objects(
            box_center=arr(self.boxes, 0, (nb, 3)),
            box_half=arr(self.boxes, 1, (nb, 3)),
            box_yaw=arr(self.boxes, 2, (nb,)),
            cyl_center=arr(self.cyls, 0, (nc, 2)),
            cyl_radius=arr(self.cyls, 1, (nc,)),
            cyl_z0=arr(self.cyls, 2, (nc,)),
            cyl_z1=arr(self.cyls, 3, (nc,)),
            sph_center=arr(self.sphs, 0, (ns, 3)),
            sph_radius=arr(self.sphs, 1, (ns,)),
        )


def make_layout(
    rng: np.random.Generator, size: np.ndarray, n_objects: int | None = None, wide: bool = False
) -> RoomLayout:
    """A random room of ``size`` (3,) metres with about ``n_objects`` floor objects (default: by floor area)."""
    size = np.asarray(size, dtype=np.float64)
    path = random_path(rng, size, wide=wide)
    light = np.array(
        [
            size[0] / 2 + rng.uniform(-0.3, 0.3) * size[0] / 6,
            size[1] / 2 + rng.uniform(-0.3, 0.3) * size[1] / 4,
            size[2] - 0.35,
        ]
    )
    b = _Builder(rng, size, path, light)
    target = n_objects if n_objects is not None else int(round(size[0] * size[1] * rng.uniform(0.3, 0.45)))
    placed, tries = 0, 0
    while placed < target and tries < 60 * max(target, 1):
        tries += 1
        kind = rng.choice(["box", "cabinet", "cylinder", "sphere", "table"], p=[0.35, 0.2, 0.25, 0.1, 0.1])
        xy = rng.uniform([0.0, 0.0], size[:2])
        yaw = float(rng.uniform(0, np.pi))
        if kind == "box":
            half = np.array([rng.uniform(0.15, 0.5), rng.uniform(0.15, 0.5), rng.uniform(0.12, 0.55)])
            ok = b.floor_box(half, xy, yaw)
            if ok and rng.random() < 0.45:
                b.stack_on(*b.boxes[-1])
        elif kind == "cabinet":
            wall = int(rng.integers(4))
            half = np.array(
                [rng.uniform(0.25, 0.7), rng.uniform(0.15, 0.25), 0.5 * rng.uniform(0.9, min(2.2, size[2] - 0.5))]
            )
            axis = wall // 2  # 0: walls x = 0 / x = Lx, 1: walls y = 0 / y = Ly
            along = rng.uniform(half[0], size[1 - axis] - half[0])
            depth = half[1] + 0.01
            pos = depth if wall % 2 == 0 else size[axis] - depth
            xy = np.array([pos, along]) if axis == 0 else np.array([along, pos])
            yaw = np.pi / 2 if axis == 0 else 0.0
            ok = b.floor_box(half, xy, yaw + rng.uniform(-0.03, 0.03), exact_bounds=True)
            if ok and rng.random() < 0.3:
                b.stack_on(*b.boxes[-1])
        elif kind == "cylinder":
            r = rng.uniform(0.1, 0.35)
            ok = b.floor_cylinder(xy, r, 0.0, rng.uniform(0.3, min(1.4, size[2] - 0.8)))
        elif kind == "sphere":
            ok = b.floor_sphere(xy, rng.uniform(0.12, 0.35))
        else:
            top_r, height = rng.uniform(0.3, 0.55), rng.uniform(0.55, 0.8)
            ok = b.floor_cylinder(xy, top_r, height - 0.04, height, footprint=top_r)
            if ok:
                b.cyls.append((xy, rng.uniform(0.03, 0.07), 0.0, height - 0.04))
                if rng.random() < 0.6:
                    r = rng.uniform(0.08, 0.18)
                    b.sphs.append(
                        (np.array([xy[0] + rng.uniform(-0.1, 0.1), xy[1] + rng.uniform(-0.1, 0.1), height + r]), r)
                    )
        placed += int(ok)
    return RoomLayout(size=size, objects=b.objects(), light=light, path=path)
