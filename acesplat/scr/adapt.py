"""The encoder adapted to one scene from its own mapping images: pretraining's InfoNCE between its training views.

Why: on real photographs the head fits its training views to a pixel or two while test views scatter by 2-5 px,
because the encoder's features of one surface change with the viewpoint (bench/herz_gap.md); the shipped encoder has
only seen procedural rooms. The mapping images show the scene from the viewpoints between which the test views lie,
and a first map's coordinates on them say which cells of two training views show the same point. Fine-tuning the
encoder so that those cells' features agree, against every other cell of the batch (acesplat.scr.pretrain's
InfoNCE), then mapping again with it, uses the mapping input only: images and their poses (bench/encoder_choice.md).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from acesplat.core.config import knob
from acesplat.core.errors import InputError
from acesplat.core.geometry import invert_pose
from acesplat.core.grid import OUTPUT_STRIDE, cell_centers, cell_reprojection_errors
from acesplat.core.scene import SceneSplit
from acesplat.scr.localize import Localizer
from acesplat.scr.network import Encoder
from acesplat.scr.pretrain import (
    CROP_HW,
    MATCH_TOLERANCE_M,
    WEIGHT_DECAY,
    PretrainScene,
    pair_loss,
    sample_pairs,
)

WARMUP_STEPS = 100
"""Steps over which the learning rate rises to its peak (pretraining's warm-up, shortened for a fine-tune)."""
GRAD_CLIP = 10.0
"""Gradient norm clip, as in pretraining."""
MIN_VIEWS = 3
"""Training views with correspondences needed: fewer cannot make pairs that differ in viewpoint."""


@dataclass(frozen=True)
class AdaptConfig:
    """How the encoder is fine-tuned on one scene (defaults measured in bench/encoder_choice.md)."""

    steps: int = knob(1200, "Optimisation steps, each on `pairs` view pairs.")
    lr: float = knob(5e-4, "Peak learning rate of the cosine schedule (bench/encoder_choice.md).")
    pairs: int = knob(6, "View pairs per step; a cell competes with every cell of the step's other views.")
    max_gap: int = knob(
        4, "A pair's views are at most this many training images apart (name order: along the trajectory)."
    )
    max_error_px: float = knob(
        4.0, "A first-map cell whose coordinate reprojects further than this from it (known pose) matches nothing."
    )
    seed: int = knob(0, "Seed of the pairs and crops.")

    def __post_init__(self) -> None:
        if self.steps < 1 or self.pairs < 1 or self.max_gap < 1:
            raise ValueError(f"steps, pairs and max_gap must be >= 1: {self}")
        if not (self.lr > 0 and self.max_error_px > 0):
            raise ValueError(f"lr and max_error_px must be > 0: {self}")


def view_coordinates(
    coords: np.ndarray, pose_c2w: np.ndarray, K: np.ndarray, max_error_px: float, stride: int = OUTPUT_STRIDE
) -> np.ndarray:
    """The cells' coordinates (h, w, 3) (cells ``stride`` px apart) with NaN where a cell's coordinate does not
    reproject within ``max_error_px`` of the cell under the view's known pose (4, 4) and intrinsics K (3, 3)."""
    err = cell_reprojection_errors(coords, pose_c2w, K, stride)
    out = coords.astype(np.float32).copy()
    out.reshape(-1, 3)[~(err < max_error_px)] = np.nan
    return out


def pixel_coordinates(cells: np.ndarray, height: int, width: int, stride: int = OUTPUT_STRIDE) -> np.ndarray:
    """Per-pixel coordinates (H, W, 3) from cell coordinates (h, w, 3) (cells ``stride`` px apart, placed as
    acesplat.core.grid.cell_centers places them): bilinear between valid cells, the nearest cell's next to an invalid
    one, NaN where that is."""
    first = float(cell_centers(1, 1, stride)[0, 0])
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    gx, gy = (xs - first) / stride, (ys - first) / stride
    src = np.ascontiguousarray(cells, np.float32)
    lin = cv2.remap(src, gx, gy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    near = cv2.remap(src, gx, gy, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    return np.where(np.isfinite(lin), lin, near)


def scene_views(split: SceneSplit, localizer: Localizer, max_error_px: float) -> tuple[PretrainScene, dict]:
    """The training views as a pretraining scene: network-input grayscale and per-pixel coordinates from the first
    map (``localizer``), scaled so that half a cell is MATCH_TOLERANCE_M (InfoNCE only needs which cells correspond),
    and a summary (views, share of cells kept, median depth, scale)."""
    grays, coords, depths, kept = [], [], [], []
    f_px = None
    for f in split.frames:
        gray, intr = localizer.network_input(f.load_rgb(), f.intrinsics)
        cells = view_coordinates(localizer.coordinates(gray), f.pose, intr.K, max_error_px, localizer.output_stride)
        ok = np.isfinite(cells[..., 0])
        kept.append(float(ok.mean()))
        if ok.any():
            w2c = invert_pose(f.pose)
            depths.append(float(np.median(cells[ok] @ w2c[2, :3] + w2c[2, 3])))
        grays.append(gray)
        coords.append(pixel_coordinates(cells, *gray.shape, localizer.output_stride))
        f_px = intr.fx
    views = sum(k > 0 for k in kept)
    if views < MIN_VIEWS or f_px is None:
        raise InputError(split.root, f"only {views} training views have cells the map fits: cannot adapt the encoder")
    half_cell_m = float(np.median(depths)) * (localizer.output_stride / 2) / f_px
    scale = MATCH_TOLERANCE_M / half_cell_m
    centre = np.mean([f.pose[:3, 3] for f in split.frames], axis=0)  # float16 keeps its precision near the origin
    scene = PretrainScene(np.stack(grays), ((np.stack(coords) - centre) * scale).astype(np.float16), np.zeros(3))
    return scene, {
        "views": len(split.frames),
        "cells_kept": float(np.mean(kept)),
        "median_depth_m": float(np.median(depths)),
        "coordinate_scale": scale,
    }


def adapt_encoder(
    encoder: Encoder,
    scene: PretrainScene,
    cfg: AdaptConfig = AdaptConfig(),
    progress: Callable[[str, float, dict], None] | None = None,
) -> dict:
    """Fine-tune ``encoder`` in place on ``scene`` (scene_views) for ``cfg.steps`` steps; returns a summary with the
    loss and top-1 match rate per 100 steps."""
    if scene.gray.shape[0] < MIN_VIEWS:
        raise ValueError(f"need at least {MIN_VIEWS} views, got {scene.gray.shape[0]}")
    h, w = scene.gray.shape[1:]
    crop = (min(CROP_HW[0], h // OUTPUT_STRIDE * OUTPUT_STRIDE), min(CROP_HW[1], w // OUTPUT_STRIDE * OUTPUT_STRIDE))
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    encoder.train()
    opt = torch.optim.AdamW(encoder.parameters(), lr=cfg.lr, weight_decay=WEIGHT_DECAY)
    history, running, last = [], [], {}
    t0 = time.monotonic()
    for step in range(cfg.steps):
        lr = cfg.lr * 0.5 * (1.0 + np.cos(np.pi * step / cfg.steps)) * min(1.0, (step + 1) / WARMUP_STEPS)
        for g in opt.param_groups:
            g["lr"] = lr
        batch = sample_pairs([scene], rng, cfg.pairs, max_gap=cfg.max_gap, crop_hw=crop)
        if batch is not None:  # no pair of the draw overlapped: a step without a gradient
            loss, top1 = pair_loss(encoder, batch)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(encoder.parameters(), GRAD_CLIP)
            opt.step()
            running.append((float(loss.detach()), top1))
            last = {"step": step + 1, "loss": running[-1][0], "top1": top1}
        if running and ((step + 1) % 100 == 0 or step + 1 == cfg.steps):
            arr = np.array(running)
            history.append({"step": step + 1, "loss": float(arr[:, 0].mean()), "top1": float(arr[:, 1].mean())})
            running = []
        if progress and last:
            progress("adapt", (step + 1) / cfg.steps, last)
    encoder.eval()
    return {"config": asdict(cfg), "seconds": round(time.monotonic() - t0, 1), "history": history}


def save_encoder(encoder: Encoder, path: Path) -> None:
    """Write the encoder's state dict (torch.load(..., weights_only=True) reads it), atomically."""
    from acesplat.core.atomic import atomic_path

    with atomic_path(path) as tmp:
        torch.save(encoder.state_dict(), tmp)
