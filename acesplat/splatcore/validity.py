"""Which SCR predictions to trust as Gaussian centres, torch-free.

A cell's scene coordinate is kept when it is finite, lies within a plausible depth range in front of
the camera, and reprojects (with the known pose) close to the pixel it was predicted for. That test
is the map agreeing with the images: on training views a good map passes almost everywhere, a map of
another scene (or one built from differently sized images) almost nowhere. It cannot see an error
along the viewing ray, so a second test asks the nearest other views: a cell that lands on another
view's valid cell must agree with that cell's depth in at least one of them.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob
from acesplat.core.geometry import invert_pose
from acesplat.core.grid import OUTPUT_STRIDE, cell_centers


@dataclass(frozen=True)
class ValidityConfig:
    """Which SCR cells become Gaussian centres (Stage 2 and the edge read the same defaults)."""

    depth_min: float = knob(0.05, "Nearest trusted camera depth of a scene coordinate, metres.")
    depth_max: float = knob(200.0, "Farthest trusted camera depth of a scene coordinate, metres.")
    reproj_max_px: float = knob(
        8.0, "Validity: SCR coordinates must reproject within this many pixels (one cell; ACE's PnP inliers: 10)."
    )
    max_depth_ratio: float = knob(
        1.25, "Pixels interpolated from cells whose depths differ by more than this ratio straddle an edge."
    )

    def __post_init__(self) -> None:
        if not (0 < self.depth_min < self.depth_max) or self.reproj_max_px <= 0 or self.max_depth_ratio < 1:
            raise ValueError(f"invalid ValidityConfig {self}")

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class CellValidity:
    """Per-cell verdicts (h, w) bool; ``valid`` is their conjunction. ``depth`` (h, w) is each cell's camera z
    (0 where the coordinate is not finite)."""

    finite: np.ndarray
    in_depth_range: np.ndarray
    reprojects: np.ndarray
    valid: np.ndarray
    depth: np.ndarray

    @property
    def fraction(self) -> float:
        return float(self.valid.mean()) if self.valid.size else 0.0


def cell_pixels(h: int, w: int) -> np.ndarray:
    """Pixel (u, v) (h, w, 2) each cell's coordinate is trained to reproject to: (8j + 4, 8i + 4), the layout of
    the PnP's own cell centres."""
    return cell_centers(h, w).reshape(h, w, 2)


def cell_validity(
    coords: np.ndarray, pose_c2w: np.ndarray, intrinsics: Intrinsics, cfg: ValidityConfig = ValidityConfig()
) -> CellValidity:
    """Validity of SCR coordinates ``coords`` (h, w, 3) predicted for an image of ``intrinsics``' size
    seen from camera-to-world ``pose_c2w`` (4, 4)."""
    coords = np.asarray(coords, np.float64)
    if coords.ndim != 3 or coords.shape[2] != 3:
        raise ValueError(f"coords must have shape (h, w, 3), got {coords.shape}")
    h, w = coords.shape[:2]
    finite = np.all(np.isfinite(coords), axis=-1)
    w2c = invert_pose(pose_c2w)
    Xc = (np.where(finite[..., None], coords, 0.0).reshape(-1, 3) @ w2c[:3, :3].T + w2c[:3, 3]).reshape(h, w, 3)
    z = Xc[..., 2]
    in_range = finite & (z >= cfg.depth_min) & (z <= cfg.depth_max)
    z_safe = np.where(in_range, z, 1.0)
    k = intrinsics
    uv = np.stack([k.fx * Xc[..., 0] / z_safe + k.cx, k.fy * Xc[..., 1] / z_safe + k.cy], axis=-1)
    err = np.linalg.norm(uv - cell_pixels(h, w), axis=-1)
    reprojects = in_range & (err <= cfg.reproj_max_px)
    return CellValidity(finite=finite, in_depth_range=in_range, reprojects=reprojects, valid=reprojects.copy(), depth=z)


def cell_trust(
    coords: np.ndarray, pose_c2w: np.ndarray, k_input: Intrinsics, cfg: ValidityConfig = ValidityConfig()
) -> tuple[np.ndarray, np.ndarray]:
    """Camera depths (h, w) of SCR coordinates ``coords`` (h, w, 3) (NaN where not trusted) and which cells to
    trust (h, w) bool: :func:`cell_validity` of an image of ``k_input``'s size seen from ``pose_c2w``."""
    v = cell_validity(coords, pose_c2w, k_input, cfg)
    return np.where(v.valid, v.depth, np.nan), v.valid


CROSS_VIEW_TOLERANCE = 0.1
"""Relative depth agreement with a neighbouring view's prediction that confirms a cell."""
CROSS_VIEW_NEIGHBOURS = 4


def cross_view_agreement(
    coords: np.ndarray,
    intrinsics: Intrinsics,
    other_coords: np.ndarray,
    other_valid: np.ndarray,
    other_pose: np.ndarray,
    other_intrinsics: Intrinsics,
    tol: float = CROSS_VIEW_TOLERANCE,
) -> tuple[np.ndarray, np.ndarray]:
    """(seen, agrees), each (h, w): whether a cell's coordinate lands on a valid cell of the other view, and
    whether that cell's own prediction has about the same depth there.

    The own-view reprojection test cannot see an error along the viewing ray (the map was trained to
    reproject well in exactly these views); another view sees that error as a depth disagreement.
    """
    h, w = coords.shape[:2]
    w2c = invert_pose(other_pose)
    X = np.asarray(coords, np.float64).reshape(-1, 3)
    Xc = X @ w2c[:3, :3].T + w2c[:3, 3]
    z = Xc[:, 2]
    k = other_intrinsics
    front = z > 1e-6
    zs = np.where(front, z, 1.0)
    u = k.fx * Xc[:, 0] / zs + k.cx
    v = k.fy * Xc[:, 1] / zs + k.cy
    oh, ow = other_coords.shape[:2]
    j = np.floor(u / OUTPUT_STRIDE).astype(np.int64)
    i = np.floor(v / OUTPUT_STRIDE).astype(np.int64)
    inside = front & np.isfinite(u) & np.isfinite(v) & (i >= 0) & (i < oh) & (j >= 0) & (j < ow)
    ii, jj = np.where(inside, i, 0), np.where(inside, j, 0)
    seen = inside & np.asarray(other_valid, bool)[ii, jj]
    z_other = np.asarray(other_coords, np.float64)[ii, jj] @ w2c[2, :3] + w2c[2, 3]
    agrees = seen & (np.abs(z_other - z) <= tol * z)
    return seen.reshape(h, w), agrees.reshape(h, w)


def confirm_across_views(
    coords: list[np.ndarray],
    valid: list[np.ndarray],
    poses: list[np.ndarray],
    intrinsics: list[Intrinsics],
    neighbours: int = CROSS_VIEW_NEIGHBOURS,
    tol: float = CROSS_VIEW_TOLERANCE,
) -> list[np.ndarray]:
    """Per view, its valid cells that are confirmed by at least one of its nearest views, or that none
    of them sees (unverifiable cells keep their own verdict)."""
    cams = np.stack([np.asarray(p)[:3, 3] for p in poses])
    out = []
    for a in range(len(coords)):
        d = np.linalg.norm(cams - cams[a], axis=1)
        d[a] = np.inf
        seen_any = np.zeros(valid[a].shape, bool)
        agree_any = np.zeros(valid[a].shape, bool)
        for b in np.argsort(d, kind="stable")[: min(neighbours, len(coords) - 1)]:
            s, g = cross_view_agreement(coords[a], intrinsics[a], coords[b], valid[b], poses[b], intrinsics[b], tol)
            seen_any |= s
            agree_any |= g
        out.append(valid[a] & (agree_any | ~seen_any))
    return out
