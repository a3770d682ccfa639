"""Every textured surface of a room as one row of a table: how world points map to texture (u, v).

Planar faces (walls, floor, ceiling, box faces, cylinder caps) share one parametrisation
(origin + u * eu + v * ev) so the renderer maps all of them with one gather; only cylinder sides and
spheres need their own formulas. (u, v) are normalised to [0, 1]; v runs downward as seen from the
side the normal points to, and eu x ev = -normal, so pictures are upright and not mirrored.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from acesplat.synth.layout import RoomLayout

PLANAR, CYLINDER_SIDE, SPHERE = 0, 1, 2
ROLE_WALL, ROLE_FLOOR, ROLE_CEILING, ROLE_OBJECT = 0, 1, 2, 3
Z = np.array([0.0, 0.0, 1.0])


@dataclass
class SurfaceTable:
    """Per-surface arrays (S, ...). ``owner`` is the global object id (-1 for the room's own faces).

    Surface ids: room faces ``2 * axis + (max side)``; then six faces per box (``box_base + 6 b + 2 axis + side``),
    three per cylinder (``cyl_base + 3 k + {side, bottom, top}``), one per sphere (``sph_base + k``).
    """

    kind: np.ndarray  # (S,) int
    role: np.ndarray  # (S,) int
    owner: np.ndarray  # (S,) int
    origin: np.ndarray  # (S, 3)
    eu: np.ndarray  # (S, 3)
    ev: np.ndarray  # (S, 3)
    normal: np.ndarray  # (S, 3) planar only
    extent: np.ndarray  # (S, 2) metres along u and v (arc lengths for curved surfaces)
    center: np.ndarray  # (S, 3) curved only
    radius: np.ndarray  # (S,) curved only
    zspan: np.ndarray  # (S, 2) cylinder sides only
    box_base: int
    cyl_base: int
    sph_base: int
    packed: np.ndarray = field(init=False, repr=False)  # (12, S) float32, see _packed

    def __post_init__(self) -> None:
        self.packed = _packed(self)

    def __len__(self) -> int:
        return len(self.kind)


def _planar(
    rows: list[dict],
    role: int,
    owner: int,
    center: np.ndarray,
    normal: np.ndarray,
    eu: np.ndarray,
    half_u: float,
    half_v: float,
) -> None:
    ev = np.cross(eu, normal)
    rows.append(
        dict(
            kind=PLANAR,
            role=role,
            owner=owner,
            origin=center - half_u * eu - half_v * ev,
            eu=eu,
            ev=ev,
            normal=normal,
            extent=(2 * half_u, 2 * half_v),
            center=np.zeros(3),
            radius=0.0,
            zspan=(0.0, 0.0),
        )
    )


def _curved(
    rows: list[dict],
    kind: int,
    owner: int,
    center: np.ndarray,
    radius: float,
    zspan: tuple[float, float],
    extent: tuple[float, float],
) -> None:
    rows.append(
        dict(
            kind=kind,
            role=ROLE_OBJECT,
            owner=owner,
            origin=np.zeros(3),
            eu=np.zeros(3),
            ev=np.zeros(3),
            normal=np.zeros(3),
            extent=extent,
            center=center,
            radius=radius,
            zspan=zspan,
        )
    )


def _side_eu(normal: np.ndarray) -> np.ndarray:
    """Horizontal u axis of a vertical face: the viewer's right when facing it (forward x up)."""
    return np.cross(-normal, Z)


def build_surfaces(layout: RoomLayout) -> SurfaceTable:
    """The surface table of a room layout (room faces first, then boxes, cylinders, spheres)."""
    size = layout.size
    ob = layout.objects
    rows: list[dict] = []
    mid = size / 2
    for axis in range(3):
        for side in range(2):
            normal = np.zeros(3)
            normal[axis] = 1.0 if side == 0 else -1.0
            center = mid.copy()
            center[axis] = 0.0 if side == 0 else size[axis]
            if axis < 2:
                eu = _side_eu(normal)
                _planar(rows, ROLE_WALL, -1, center, normal, eu, size[1 - axis] / 2, size[2] / 2)
            else:
                eu = np.array([1.0, 0.0, 0.0])
                _planar(
                    rows, ROLE_FLOOR if side == 0 else ROLE_CEILING, -1, center, normal, eu, size[0] / 2, size[1] / 2
                )
    box_base = len(rows)
    for b, (c, h, yaw) in enumerate(zip(ob.box_center, ob.box_half, ob.box_yaw)):
        axes = np.array([[np.cos(yaw), np.sin(yaw), 0.0], [-np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
        for axis in range(3):
            for side in range(2):
                normal = axes[axis] * (1.0 if side == 1 else -1.0)
                center = c + normal * h[axis]
                if axis < 2:
                    eu = _side_eu(normal)
                    half_u = h[1 - axis]
                    half_v = h[2]
                else:
                    eu, half_u, half_v = axes[0], h[0], h[1]
                _planar(rows, ROLE_OBJECT, b, center, normal, eu, half_u, half_v)
    cyl_base = len(rows)
    nb = len(ob.box_center)
    for k, (c, r, z0, z1) in enumerate(zip(ob.cyl_center, ob.cyl_radius, ob.cyl_z0, ob.cyl_z1)):
        owner = nb + k
        _curved(
            rows, CYLINDER_SIDE, owner, np.array([c[0], c[1], 0.5 * (z0 + z1)]), r, (z0, z1), (2 * np.pi * r, z1 - z0)
        )
        _planar(rows, ROLE_OBJECT, owner, np.array([c[0], c[1], z0]), -Z, np.array([1.0, 0.0, 0.0]), r, r)
        _planar(rows, ROLE_OBJECT, owner, np.array([c[0], c[1], z1]), Z, np.array([1.0, 0.0, 0.0]), r, r)
    sph_base = len(rows)
    nc = len(ob.cyl_center)
    for k, (c, r) in enumerate(zip(ob.sph_center, ob.sph_radius)):
        _curved(rows, SPHERE, nb + nc + k, c, r, (0.0, 0.0), (2 * np.pi * r, np.pi * r))

    def col(key: str, dtype: type = np.float64) -> np.ndarray:
        return np.array([r[key] for r in rows], dtype=dtype)

    return SurfaceTable(
        kind=col("kind", np.int64),
        role=col("role", np.int64),
        owner=col("owner", np.int64),
        origin=col("origin"),
        eu=col("eu"),
        ev=col("ev"),
        normal=col("normal"),
        extent=col("extent"),
        center=col("center"),
        radius=col("radius"),
        zspan=col("zspan"),
        box_base=box_base,
        cyl_base=cyl_base,
        sph_base=sph_base,
    )


def surface_grid(table: SurfaceTable, s: int, nu: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """World points and normals (nv, nu, 3) at the cell centres of an nu x nv grid over surface ``s``."""
    un = (np.arange(nu) + 0.5) / nu
    vn = (np.arange(nv) + 0.5) / nv
    U, V = np.meshgrid(un, vn)
    kind = table.kind[s]
    if kind == PLANAR:
        U_m, V_m = U * table.extent[s, 0], V * table.extent[s, 1]
        X = table.origin[s] + U_m[..., None] * table.eu[s] + V_m[..., None] * table.ev[s]
        N = np.broadcast_to(table.normal[s], X.shape).copy()
    elif kind == CYLINDER_SIDE:
        ang = 2 * np.pi * U
        z0, z1 = table.zspan[s]
        N = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], axis=-1)
        X = table.center[s] + table.radius[s] * N
        X[..., 2] = z1 - V * (z1 - z0)
    else:
        phi, th = 2 * np.pi * U, np.pi * V
        N = np.stack([np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi), np.cos(th)], axis=-1)
        X = table.center[s] + table.radius[s] * N
    return X, N


def _packed(table: SurfaceTable) -> np.ndarray:
    """Per-surface columns (12, S) float32: u and v as affine functions of the world point, the normal, the kind.

    Contiguous per-quantity rows make each per-pixel gather a fast 1-D ``np.take``.
    """
    rows = np.zeros((len(table), 12), dtype=np.float64)
    planar = table.kind == PLANAR
    for col, axis in ((0, table.eu), (4, table.ev)):
        ext = table.extent[:, 0 if col == 0 else 1]
        rows[planar, col : col + 3] = axis[planar] / ext[planar, None]
        rows[planar, col + 3] = -np.einsum("ij,ij->i", table.origin[planar], axis[planar]) / ext[planar]
    rows[:, 8:11] = table.normal
    rows[:, 11] = table.kind
    return np.ascontiguousarray(rows.T, dtype=np.float32)


def surface_coords(
    table: SurfaceTable, sid: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Normal (nx, ny, nz) and normalised texture coordinates (u, v) of world points on surfaces ``sid``.

    All inputs and outputs are flat arrays (P,); points are given per component (x, y, z).
    """
    rows = [np.take(col, sid) for col in table.packed]
    un = rows[0] * x + rows[1] * y + rows[2] * z + rows[3]
    vn = rows[4] * x + rows[5] * y + rows[6] * z + rows[7]
    nx, ny, nz = rows[8], rows[9], rows[10]
    curved = np.flatnonzero(rows[11] != PLANAR)
    if curved.size:
        s = sid[curved]
        c = table.center[s]
        r = table.radius[s]
        dx, dy, dz = (x[curved] - c[:, 0]) / r, (y[curved] - c[:, 1]) / r, (z[curved] - c[:, 2]) / r
        cyl = table.kind[s] == CYLINDER_SIDE
        dz = dz * ~cyl
        norm = np.sqrt(dx * dx + dy * dy + dz * dz)
        dx, dy, dz = dx / norm, dy / norm, dz / norm
        un[curved] = np.mod(np.arctan2(dy, dx) / (2 * np.pi), 1.0)
        z0, z1 = table.zspan[s, 0], table.zspan[s, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            v_cyl = (z1 - z[curved]) / (z1 - z0)
        v_sph = np.arccos(np.clip(dz, -1.0, 1.0)) / np.pi
        vn[curved] = np.where(cyl, v_cyl, v_sph)
        nx[curved], ny[curved], nz[curved] = dx, dy, dz
    return nx, ny, nz, un, vn
