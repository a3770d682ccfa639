"""The frames a bundle carries so the device can check its INT8 model against FP32 (``acesplat-edge check``).

One ``.npz`` of plain arrays (loaded with ``allow_pickle=False``): the prepared network inputs, their intrinsics and
the FP32 scene coordinates the export machine computed for them. Shapes are checked on load; errors name the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from acesplat.core.atomic import atomic_path
from acesplat.core.bundle import MANIFEST_NAME, ROLE_INT8_CHECK, Bundle
from acesplat.core.camera import Intrinsics
from acesplat.core.errors import InputError
from acesplat.core.geometry import pose_error
from acesplat.core.pnp import solve_from_grid


@dataclass(frozen=True)
class CheckFrames:
    """names (N,); gray (N, H, W) uint8 network inputs; K (N, 3, 3) of those inputs; coords and int8_coords
    (N, h, w, 3) float32: the FP32 and INT8 scene coordinates on the export machine, cells ``stride`` px apart;
    vnni_coords like them from the U8S8 graph (acesplat.core.bundle.ROLE_SCR_INT8_VNNI), None without one."""

    names: list[str]
    gray: np.ndarray
    K: np.ndarray
    coords: np.ndarray
    int8_coords: np.ndarray
    stride: int
    vnni_coords: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.gray.shape[0])

    def intrinsics(self, i: int) -> Intrinsics:
        h, w = self.gray.shape[1:]
        return Intrinsics.from_K(self.K[i], w, h)

    def int8(self, precision: str) -> np.ndarray:
        """The export machine's coordinates (N, h, w, 3) from the INT8 graph of ``precision`` (int8, int8_vnni)."""
        if precision == "int8_vnni":
            if self.vnni_coords is None:
                raise ValueError("these check frames carry no int8_vnni coordinates")
            return self.vnni_coords
        return self.int8_coords

    def __post_init__(self) -> None:
        problem = _shape_problem(
            self.gray, self.K, self.coords, self.int8_coords, self.stride, len(self.names), self.vnni_coords
        )
        if problem:
            raise ValueError(problem)


def _shape_problem(
    gray: np.ndarray,
    K: np.ndarray,
    coords: np.ndarray,
    int8_coords: np.ndarray,
    stride: int,
    n_names: int,
    vnni_coords: np.ndarray | None = None,
) -> str | None:
    if gray.ndim != 3 or gray.dtype != np.uint8 or gray.shape[0] == 0:
        return f"gray must be (N, H, W) uint8 with N > 0, got {gray.shape} {gray.dtype}"
    n, h, w = gray.shape
    if K.shape != (n, 3, 3) or not np.all(np.isfinite(K)):
        return f"K must be ({n}, 3, 3) and finite, got {K.shape}"
    if stride <= 0 or coords.shape != (n, h // stride, w // stride, 3) or coords.dtype != np.float32:
        return f"coords must be ({n}, {h // max(stride, 1)}, {w // max(stride, 1)}, 3) float32, got {coords.shape}"
    if int8_coords.shape != coords.shape or int8_coords.dtype != np.float32:
        return f"int8_coords must be {coords.shape} float32 like coords, got {int8_coords.shape} {int8_coords.dtype}"
    if vnni_coords is not None and (vnni_coords.shape != coords.shape or vnni_coords.dtype != np.float32):
        return f"vnni_coords must be {coords.shape} float32 like coords, got {vnni_coords.shape} {vnni_coords.dtype}"
    if n_names != n:
        return f"{n_names} names for {n} frames"
    return None


def save_check_frames(path: str | Path, frames: CheckFrames) -> Path:
    """Write ``frames`` to ``path`` (atomically)."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(
            f,
            names=np.array(frames.names, dtype=str),
            gray=frames.gray,
            K=frames.K.astype(np.float64),
            coords=frames.coords,
            int8_coords=frames.int8_coords,
            stride=np.int64(frames.stride),
            **({} if frames.vnni_coords is None else {"vnni_coords": frames.vnni_coords}),
        )
    return path


def load_check_frames(path: str | Path) -> CheckFrames:
    """The check frames at ``path``; InputError naming the file when it is unreadable or its arrays do not fit."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in ("names", "gray", "K", "coords", "int8_coords", "stride")}
            vnni = z["vnni_coords"] if "vnni_coords" in z.files else None
    except (OSError, ValueError, KeyError) as e:
        raise InputError(path, f"not a check-frames file ({str(e).splitlines()[0][:120]})") from None
    problem = _shape_problem(
        arrays["gray"],
        arrays["K"],
        arrays["coords"],
        arrays["int8_coords"],
        int(arrays["stride"]),
        len(arrays["names"].reshape(-1)),
        vnni,
    )
    if problem:
        raise InputError(path, problem)
    return CheckFrames(
        [str(s) for s in arrays["names"].reshape(-1)],
        arrays["gray"],
        arrays["K"],
        arrays["coords"],
        arrays["int8_coords"],
        int(arrays["stride"]),
        vnni,
    )


def bundle_check_frames(bundle: Bundle) -> CheckFrames:
    """The bundle's check frames; InputError when it has none (exported before they existed) or they do not match
    its input size."""
    if not bundle.has(ROLE_INT8_CHECK):
        raise InputError(
            bundle.root / MANIFEST_NAME,
            "bundle carries no INT8 check frames (exported before `acesplat-edge check` existed); re-export it "
            "with --int8",
        )
    frames = load_check_frames(bundle.path(ROLE_INT8_CHECK))
    if tuple(frames.gray.shape[1:]) != bundle.input_size or frames.stride != bundle.output_stride:
        raise InputError(
            bundle.path(ROLE_INT8_CHECK),
            f"check frames are {frames.gray.shape[1]}x{frames.gray.shape[2]} at stride {frames.stride}, the bundle "
            f"is {bundle.input_size[0]}x{bundle.input_size[1]} at stride {bundle.output_stride}",
        )
    return frames


def deviation(
    reference: list[np.ndarray], other: list[np.ndarray], intrinsics: list[Intrinsics], stride: int
) -> dict[str, float | int | None]:
    """How far ``other`` coordinate grids (h, w, 3) are from ``reference`` ones of the same frames: the median and
    90th percentile of |other - reference| over every finite cell (scene units), and the PnP poses solved from each
    compared (median and max translation in scene units and rotation in degrees, over frames where both solve)."""
    if not reference or len(reference) != len(other) or len(other) != len(intrinsics):
        raise ValueError(f"need as many grids and intrinsics, got {len(reference)}, {len(other)}, {len(intrinsics)}")
    d, dt, dr = [], [], []
    for a, b, intr in zip(reference, other, intrinsics, strict=True):
        if a.shape != b.shape or a.ndim != 3 or a.shape[-1] != 3:
            raise ValueError(f"grids must be (h, w, 3) of one shape, got {a.shape} and {b.shape}")
        diff = np.linalg.norm(b.astype(np.float64) - a, axis=-1).ravel()
        d.append(np.where(np.isfinite(diff), diff, np.inf))
        pa, pb = solve_from_grid(a, intr, stride).T_c2w, solve_from_grid(b, intr, stride).T_c2w
        if pa is not None and pb is not None:
            t, r = pose_error(pb, pa)
            dt.append(t)
            dr.append(r)
    all_d = np.concatenate(d)
    return {
        "frames": len(reference),
        "coord_median": float(np.median(all_d)),
        "coord_p90": float(np.percentile(all_d, 90)),
        "pose_frames": len(dt),
        "pose_median_translation": float(np.median(dt)) if dt else None,
        "pose_max_translation": float(np.max(dt)) if dt else None,
        "pose_median_rotation_deg": float(np.median(dr)) if dr else None,
        "pose_max_rotation_deg": float(np.max(dr)) if dr else None,
    }
