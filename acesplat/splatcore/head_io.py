"""The Gaussian initializer's interface, torch-free: its prior input and the layout of its residual output.

Stage 2 trains the adapter and init head (acesplat/splat/init_head.py), the export writes them as one ONNX graph,
and the edge runs that graph (edge/refine/onnx_seeder.py); all three read the layout from here. The prior holds the
pixel's colour, its centre in normalised scene coordinates and its log depth (colour is part of it because the SCR
encoder sees grayscale only). The residuals are added to the analytic start of :mod:`.seeding`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from acesplat.core.gaussians import SH_C0, Gaussians, logit, sh_coeff_count
from acesplat.splatcore.seeding import OPACITY_PRIOR, SCALE_PRIOR, start_log_scales

PRIOR_CHANNELS = 7
"""rgb - 0.5 (3), normalised world centre (3), log(depth / scene scale) (1)."""
OPACITY_CHANNEL = 0
"""Residual channel 0 is the opacity logit; SH, log-scale and quaternion follow (:func:`residual_slices`)."""
IDENTITY_QUAT = (1.0, 0.0, 0.0, 0.0)


def residual_channels(head_sh_degree: int) -> int:
    """Residual channels of a head predicting SH of ``head_sh_degree``: opacity (1) + SH (3K) + log-scale (3) +
    quaternion (4)."""
    return 1 + 3 * sh_coeff_count(head_sh_degree) + 3 + 4


def residual_slices(head_sh_degree: int) -> dict[str, slice]:
    """Channel ranges of the SH (coefficient-major, 3 per coefficient), log-scale and quaternion (wxyz) residuals."""
    k = sh_coeff_count(head_sh_degree)
    return {"sh": slice(1, 1 + 3 * k), "log_scales": slice(1 + 3 * k, 4 + 3 * k), "quats": slice(4 + 3 * k, 8 + 3 * k)}


@dataclass(frozen=True)
class SceneNorm:
    """Centre and scale (metres) that bring the scene's coordinates to roughly unit size for the head."""

    centre: tuple[float, float, float]
    scale: float

    @classmethod
    def from_views(cls, camera_centres: np.ndarray, depths: np.ndarray) -> SceneNorm:
        """From the camera centres (N, 3) and the trusted cell depths (M,) of the training views."""
        c = np.asarray(camera_centres, np.float64).reshape(-1, 3)
        d = np.asarray(depths, np.float64).reshape(-1)
        spread = float(np.max(np.linalg.norm(c - c.mean(0), axis=1))) if len(c) else 0.0
        depth = float(np.median(d)) if d.size else 1.0
        return cls(tuple(float(v) for v in c.mean(0)), max(spread, depth, 1e-3))  # type: ignore[arg-type]

    @classmethod
    def from_dict(cls, d: dict) -> SceneNorm:
        """From :meth:`as_dict`'s form (the bundle manifest's ``scene_norm``); KeyError/TypeError/ValueError if bad."""
        c = np.asarray(d["centre"], np.float64).reshape(3)
        return cls((float(c[0]), float(c[1]), float(c[2])), float(d["scale"]))

    def as_dict(self) -> dict:
        return {"centre": list(self.centre), "scale": self.scale}


def coordinate_prior(
    rgb: np.ndarray, centres: np.ndarray, depth: np.ndarray, norm: SceneNorm, float32_in_place: bool = False
) -> np.ndarray:
    """The head's prior input (PRIOR_CHANNELS, H, W) float32 from rgb (H, W, 3) in [0, 1], world centres (H, W, 3)
    and camera depths (H, W); non-finite values become 0.

    ``float32_in_place`` computes in one float32 buffer (the edge, once per keyframe: no float64 temporaries at the
    network input size); otherwise in float64, rounded once at the end (Stage 2). The two agree to float32 rounding.
    """
    H, W = depth.shape
    if rgb.shape != (H, W, 3) or centres.shape != (H, W, 3):
        raise ValueError(
            f"need rgb and centres (H, W, 3) and depth (H, W), got {rgb.shape}, {centres.shape}, {depth.shape}"
        )
    if float32_in_place:
        prior = np.empty((PRIOR_CHANNELS, H, W), np.float32)
        prior[0:3] = np.moveaxis(rgb, -1, 0)
        prior[0:3] -= 0.5
        prior[3:6] = np.moveaxis(centres, -1, 0)
        prior[3:6] -= np.asarray(norm.centre, np.float64).astype(np.float32)[:, None, None]
        prior[3:6] /= np.float32(norm.scale)
        prior[6] = np.log(np.maximum(depth, 1e-6) / norm.scale)
        return np.nan_to_num(prior, copy=False)
    c = (centres - np.asarray(norm.centre)) / norm.scale
    logd = np.log(np.maximum(depth, 1e-6) / norm.scale)[..., None]
    prior = np.concatenate([rgb - 0.5, c, logd], axis=-1)
    return np.ascontiguousarray(np.nan_to_num(prior).transpose(2, 0, 1), dtype=np.float32)


def decode_residuals(
    raw: np.ndarray,
    rgb: np.ndarray,
    centres: np.ndarray,
    depth: np.ndarray,
    focal_px: float,
    spacing_px: float,
    head_sh_degree: int,
    sh_degree: int,
    opacity_prior: float = OPACITY_PRIOR,
    scale_prior: float = SCALE_PRIOR,
) -> Gaussians:
    """Float32 Gaussians from head residuals raw (N, residual_channels), colours (N, 3) in [0, 1], centres (N, 3)
    and camera depths (N,): the analytic start plus the residuals (the numpy twin of init_head.decode_gaussians).
    SH bands above ``head_sh_degree`` are zero."""
    n, kh = raw.shape[0], sh_coeff_count(head_sh_degree)
    if raw.ndim != 2 or raw.shape[1] != residual_channels(head_sh_degree):
        raise ValueError(f"raw must have shape (N, {residual_channels(head_sh_degree)}), got {raw.shape}")
    if sh_degree < head_sh_degree:
        raise ValueError(f"map SH degree {sh_degree} is below the initializer's {head_sh_degree}")
    sl = residual_slices(head_sh_degree)
    g = Gaussians.zeros(n, sh_degree, np.float32)
    g.opacity_logits[:] = raw[:, OPACITY_CHANNEL] + float(logit(np.array(opacity_prior)))
    g.sh[:, :kh] = raw[:, sl["sh"]].reshape(n, kh, 3)
    g.sh[:, 0] += (rgb - 0.5) / SH_C0
    g.log_scales[:] = raw[:, sl["log_scales"]] + start_log_scales(depth, focal_px, spacing_px, scale_prior)[:, None]
    g.quats[:] = raw[:, sl["quats"]] + np.array(IDENTITY_QUAT)
    g.means[:] = centres
    return g
