"""A set of 3D Gaussians as numpy arrays, in the pre-activation parametrisation that 3DGS optimises.

Storing log-scales, opacity logits and unnormalised quaternions keeps every value unconstrained, so
an optimiser can step on them freely and the standard 3DGS PLY stores exactly these numbers.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

MAX_SH_DEGREE = 3
"""Highest spherical-harmonics degree of the colour model (16 coefficients per channel)."""

SH_C0 = 0.5 / math.sqrt(math.pi)
"""The constant degree-0 real SH basis function: colour = SH_C0 * dc + 0.5."""


def sh_coeff_count(degree: int) -> int:
    """Coefficients per colour channel for SH ``degree``: (degree + 1)^2."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    return (degree + 1) ** 2


def sh_degree_of(k: int) -> int:
    """SH degree whose coefficient count is ``k`` (1, 4, 9 or 16)."""
    for d in range(MAX_SH_DEGREE + 1):
        if (d + 1) ** 2 == k:
            return d
    raise ValueError(f"SH coefficient count must be 1, 4, 9 or 16, got {k}")


def sigmoid(x: np.ndarray) -> np.ndarray:
    """Logistic function, written so large |x| neither overflows nor warns."""
    x = np.asarray(x)
    e = np.exp(-np.abs(x))
    return np.where(x >= 0, 1.0 / (1.0 + e), e / (1.0 + e)).astype(x.dtype, copy=False)


def logit(p: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Inverse of :func:`sigmoid`, clipped away from 0 and 1 so initial opacities stay finite."""
    p = np.clip(np.asarray(p), eps, 1.0 - eps)
    return np.log(p / (1.0 - p))


def normalize_quats(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) wxyz; a zero quaternion becomes the identity rather than NaN."""
    q = np.asarray(q)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    out = np.where(n > 0, q / np.where(n > 0, n, 1.0), 0.0)
    out[..., 0] = np.where(n[..., 0] > 0, out[..., 0], 1.0)
    return out.astype(q.dtype, copy=False)


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """Degree-0 SH coefficient giving colour ``rgb`` (the 3DGS colour offset of 0.5 removed)."""
    return (np.asarray(rgb) - 0.5) / SH_C0


def sh_dc_to_rgb(dc: np.ndarray) -> np.ndarray:
    """View-independent colour of degree-0 coefficients (before the clamp at 0)."""
    return np.asarray(dc) * SH_C0 + 0.5


@dataclass
class Gaussians:
    """N Gaussians, all arrays of one floating dtype (float32 for speed, float64 for checks).

    means (N, 3) world positions; log_scales (N, 3) log standard deviations along the local axes;
    quats (N, 4) rotations wxyz, not necessarily normalised; opacity_logits (N,) pre-sigmoid opacity;
    sh (N, K, 3) colour SH coefficients, K = (degree + 1)^2, coefficient-major then RGB.
    """

    means: np.ndarray
    log_scales: np.ndarray
    quats: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray

    def __post_init__(self) -> None:
        for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
            v = getattr(self, name)
            if not isinstance(v, np.ndarray):
                raise TypeError(f"Gaussians.{name} must be a numpy array, got {type(v).__name__}")
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        expected = {
            "means": (n, 3),
            "log_scales": (n, 3),
            "quats": (n, 4),
            "opacity_logits": (n,),
        }
        for name, shape in expected.items():
            v = getattr(self, name)
            if v.shape != shape or n < 0:
                raise ValueError(f"Gaussians.{name} must have shape {_fmt(shape)}, got {v.shape}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"Gaussians.sh must have shape (N={n}, K, 3), got {self.sh.shape}")
        sh_degree_of(self.sh.shape[1])
        dtypes = {getattr(self, f).dtype for f in ("means", "log_scales", "quats", "opacity_logits", "sh")}
        if len(dtypes) != 1 or next(iter(dtypes)) not in (np.dtype(np.float32), np.dtype(np.float64)):
            raise TypeError(f"Gaussians arrays must all be float32 or all float64, got {sorted(map(str, dtypes))}")

    # --- shape facts -------------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def dtype(self) -> np.dtype:
        return self.means.dtype

    @property
    def sh_degree(self) -> int:
        return sh_degree_of(self.sh.shape[1])

    # --- activations -------------------------------------------------------------------------
    def scales(self) -> np.ndarray:
        """Standard deviations (N, 3)."""
        return np.exp(self.log_scales)

    def opacities(self) -> np.ndarray:
        """Opacities in (0, 1), shape (N,)."""
        return sigmoid(self.opacity_logits)

    def unit_quats(self) -> np.ndarray:
        """Normalised rotations (N, 4) wxyz."""
        return normalize_quats(self.quats)

    # --- construction helpers ----------------------------------------------------------------
    @classmethod
    def empty(cls, sh_degree: int = MAX_SH_DEGREE, dtype: type = np.float32) -> Gaussians:
        return cls.zeros(0, sh_degree, dtype)

    @classmethod
    def zeros(cls, n: int, sh_degree: int = MAX_SH_DEGREE, dtype: type = np.float32) -> Gaussians:
        """n Gaussians at the origin with unit scale, identity rotation, opacity 0.5 and grey colour."""
        quats = np.zeros((n, 4), dtype)
        quats[:, 0] = 1.0
        return cls(
            np.zeros((n, 3), dtype),
            np.zeros((n, 3), dtype),
            quats,
            np.zeros((n,), dtype),
            np.zeros((n, sh_coeff_count(sh_degree), 3), dtype),
        )

    def astype(self, dtype: type) -> Gaussians:
        return Gaussians(*(np.ascontiguousarray(a, dtype=dtype) for a in self._arrays()))

    def copy(self) -> Gaussians:
        return Gaussians(*(a.copy() for a in self._arrays()))

    def subset(self, index: np.ndarray | Sequence[int] | slice) -> Gaussians:
        """Gaussians selected by a boolean mask (N,), integer indices or a slice (copies)."""
        if isinstance(index, slice):
            return Gaussians(*(a[index].copy() for a in self._arrays()))
        idx = np.asarray(index)
        if idx.dtype == bool:
            if idx.shape != (len(self),):
                raise ValueError(f"mask must have shape ({len(self)},), got {idx.shape}")
        elif idx.size and not np.issubdtype(idx.dtype, np.integer):
            raise TypeError(f"index must be a boolean mask or integers, got dtype {idx.dtype}")
        return Gaussians(*(a[idx] for a in self._arrays()))

    def with_sh_degree(self, degree: int) -> Gaussians:
        """Same Gaussians with SH truncated or zero-padded to ``degree``."""
        k = sh_coeff_count(degree)
        sh = np.zeros((len(self), k, 3), self.dtype)
        m = min(k, self.sh.shape[1])
        sh[:, :m] = self.sh[:, :m]
        return Gaussians(self.means.copy(), self.log_scales.copy(), self.quats.copy(), self.opacity_logits.copy(), sh)

    def _arrays(self) -> tuple[np.ndarray, ...]:
        return (self.means, self.log_scales, self.quats, self.opacity_logits, self.sh)


def concat_gaussians(parts: Iterable[Gaussians]) -> Gaussians:
    """One set from several (e.g. per-view sets merged into a scene); SH degree and dtype must agree."""
    parts = list(parts)
    if not parts:
        raise ValueError("concat_gaussians needs at least one set")
    degrees = {p.sh_degree for p in parts}
    dtypes = {p.dtype for p in parts}
    if len(degrees) != 1:
        raise ValueError(f"cannot concatenate Gaussian sets of different SH degrees {sorted(degrees)}")
    if len(dtypes) != 1:
        raise ValueError(f"cannot concatenate Gaussian sets of different dtypes {sorted(map(str, dtypes))}")
    return Gaussians(*(np.concatenate(arrs, axis=0) for arrs in zip(*(p._arrays() for p in parts))))


def _fmt(shape: tuple[int, ...]) -> str:
    return "(" + ", ".join("N" if s < 0 else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
