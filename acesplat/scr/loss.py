"""DSAC*/ACE reprojection loss with the circular inlier-threshold curriculum.

Valid predictions (in front of the camera, not absurdly far or off-image) pay a tanh-clamped
reprojection error whose threshold shrinks from 50 px to 1 px over training; invalid ones are pulled
towards a point at a fixed depth on their pixel's ray, which puts them back in front of the camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

DEPTH_MIN = 0.1
"""Predictions closer than this (metres, camera z) are invalid."""
DEPTH_MAX = 1000.0
"""Predictions farther than this are invalid."""
REPROJ_HARD_CLAMP = 1000.0
"""Predictions reprojecting farther than this (pixels) are invalid."""
DEPTH_TARGET = 10.0
"""Invalid predictions are pulled to the point at this depth on the pixel's ray."""
THRESHOLD_MAX = 50.0
THRESHOLD_MIN = 1.0


def curriculum_threshold(progress: float, tau_max: float = THRESHOLD_MAX, tau_min: float = THRESHOLD_MIN) -> float:
    """Circular schedule: tau(p) = tau_min + sqrt(1 - p^2) (tau_max - tau_min), p in [0, 1]."""
    p = min(max(progress, 0.0), 1.0)
    return tau_min + math.sqrt(1.0 - p * p) * (tau_max - tau_min)


@dataclass
class LossParts:
    loss: torch.Tensor
    valid_fraction: float
    mean_reproj_px: float


def reprojection_loss(
    pred_world: torch.Tensor,
    w2c: torch.Tensor,
    K: torch.Tensor,
    pixels: torch.Tensor,
    threshold: float,
) -> LossParts:
    """ACE's loss for a batch of predictions.

    pred_world (N, 3) scene coordinates; w2c (N, 3, 4) world-to-camera; K (N, 3, 3); pixels (N, 2) the
    pixel each prediction belongs to. Returns the mean over the batch of tanh-clamped reprojection errors
    (valid) and ray distances (invalid).
    """
    n = pred_world.shape[0]
    pred_cam = torch.einsum("nij,nj->ni", w2c[:, :, :3], pred_world) + w2c[:, :, 3]
    z = pred_cam[:, 2]
    z_safe = torch.where(z.abs() < 1e-6, torch.full_like(z, 1e-6), z)
    proj = torch.einsum("nij,nj->ni", K, pred_cam)
    uv = proj[:, :2] / z_safe.unsqueeze(1)
    err = torch.linalg.vector_norm(uv - pixels, dim=1)
    invalid = (z < DEPTH_MIN) | (z > DEPTH_MAX) | (err > REPROJ_HARD_CLAMP)
    valid = ~invalid

    loss_valid = threshold * torch.tanh(err[valid] / threshold)
    # Pinhole without skew: the ray through a pixel is ((u - cx) / fx, (v - cy) / fy, 1).
    rx = (pixels[:, 0] - K[:, 0, 2]) / K[:, 0, 0]
    ry = (pixels[:, 1] - K[:, 1, 2]) / K[:, 1, 1]
    target = torch.stack([rx, ry, torch.ones_like(rx)], dim=1) * DEPTH_TARGET
    loss_invalid = torch.linalg.vector_norm(pred_cam[invalid] - target[invalid], dim=1)

    loss = (loss_valid.sum() + loss_invalid.sum()) / max(n, 1)
    nv = int(valid.sum())
    return LossParts(loss, nv / max(n, 1), float(err[valid].detach().mean()) if nv else float("nan"))
