"""Stage 1 mapping: train a scene-specific head on a frozen encoder from posed RGB images.

ACE's recipe (Brachmann et al., CVPR 2023), readable top to bottom:
1. Fill a buffer with encoder features of augmented training images (brightness and contrast; ACE's
   rescale and rotation on request), each feature remembering its pixel, the (augmented) camera's
   intrinsics and world-to-camera pose, and where a triangulated keypoint falls in its cell, a target.
2. Train the head on random batches of the buffer with the reprojection loss, the circular threshold
   curriculum and AdamW under a one-cycle learning rate, all driven by the fraction of the recipe's head steps
   done (or of a wall-clock cap, when one binds first, so a capped map still runs the whole schedule).
3. On request (this project's addition, acesplat.scr.novel_views), late in training, warp the training images
   with the head's own depth to cameras between neighbouring ones and add their features, with those
   cameras' poses, to the buffer: the head then also learns the in-between views a query will come from.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import torch

from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob, knob_default
from acesplat.core.errors import InputError
from acesplat.core.grid import OUTPUT_STRIDE, cell_centers
from acesplat.core.machine import bf16_units_usable
from acesplat.core.preprocess import size_for_short_side, to_gray_input
from acesplat.core.scene import SceneSplit
from acesplat.scr.augment import augment, augment_ranges
from acesplat.scr.buffer import Buffer, BufferBuilder, merge_buffers
from acesplat.scr.loss import DEPTH_MIN, curriculum_threshold, reprojection_loss
from acesplat.scr.network import Encoder, Head, HeadConfig, normalize_gray
from acesplat.scr.novel_views import NOVEL_VIEWS_AT, NOVEL_VIEWS_TIME_FRACTION, novel_view_buffer
from acesplat.scr.targets import ImageTargets, triangulate_targets

# ACE's recipe, named where it is used; where this project departs from it for a CPU budget the knob is a
# MappingConfig field below (bench/augment_choice.md and bench/herz_gap.md measure the departures).
ACE_IMAGE_SHORT_SIDE = 480
MIN_TRAINING_IMAGES = 3
"""Fewer posed views than this cannot constrain a scene's coordinates beyond a single stereo pair."""
MIN_TRIANGULATED = 20
"""Fewer triangulated points than this over all neighbouring pairs: the training images see nothing in common."""
ACE_BUFFER_SIZE = 8_000_000
WEIGHT_DECAY = 0.01
TARGETS_TIME_FRACTION = 0.08
"""Under a wall-clock cap: at most this share of it goes to matching and triangulating targets."""
BUFFER_TIME_FRACTION = 0.25
"""Under a wall-clock cap: targets and buffer together use at most this share of it; the rest trains the head."""
ONE_CYCLE_WARMUP = 0.25
"""Share of training spent rising from lr_min to lr_max (cosine), then cosine annealing back down."""
TARGET_WEIGHT_PX = 0.4
"""Weight of the triangulated-target term, whose distance is in pixels (metres times f / depth of the target in its
view), so one weight suits every scene depth (bench/augment_choice.md)."""
TARGET_CLAMP_M = 2.0
"""Target distances beyond this (metres) stop growing the loss, so a wrong match cannot dominate."""


def default_short_side(split: SceneSplit) -> int:
    """MappingConfig.short_side, or the images' own shorter side when they are smaller (never upsample to map)."""
    first = split.frames[0].intrinsics
    return min(knob_default(MappingConfig, "short_side"), first.width, first.height)


@dataclass
class MappingConfig:
    iterations: int = knob(5000, "Head steps of the recipe: the same work, so the same map, on every CPU.")
    minutes: float | None = knob(None, "Optional wall-clock cap; a map it cuts short is warned of and flagged.")
    short_side: int = knob(360, "Shorter image side for the network (ACE: 480; fewer pixels suit a CPU).")
    head: HeadConfig = knob(reason="The head's 1x1 layers.", factory=lambda: HeadConfig(width=256, blocks=1))
    batch_size: int = knob(
        2560, "Buffered features per head step (ACE: 5120; half keeps the accuracy: bench/recipe.md)."
    )
    buffer_size: int = knob(1_000_000, "Buffered features (ACE: 8M; on a CPU the head sees ~13 epochs of 1M).")
    samples_per_image: int = knob(1024, "Features taken from each augmented image (ACE's count).")
    buffer_passes: int = knob(
        20, "Augmented passes over a small scene's images, then its buffer stops short (bench/recipe.md)."
    )
    lr_min: float = knob(5e-4, "Start and end of the one-cycle learning rate (ACE's range).")
    lr_max: float = knob(5e-3, "Peak of the one-cycle learning rate (ACE's range).")
    augment: str = knob(
        "photometric",
        "photometric (brightness, contrast) or ace (also ACE's rescale and rotation; bench/augment_choice.md).",
    )
    triangulate: bool = knob(True, "Sparse coordinate targets triangulated from SIFT matches between training images.")
    novel_views: int = knob(
        0, "Training images warped to in-between cameras, buffered late in training (bench/herz_gap.md)."
    )
    seed: int = knob(0, "Seed of sampling, augmentation and initialisation.")
    device: str = knob("cpu", "Torch device of the encoder and head.")
    precision: str = knob("auto", "Mapping arithmetic: auto (bf16 where the CPU/GPU has it), fp32 or bf16.")


def use_bf16(precision: str, device: str) -> bool:
    if precision not in ("auto", "fp32", "bf16"):
        raise ValueError(f"precision must be auto, fp32 or bf16, got {precision!r}")
    if precision != "auto":
        return precision == "bf16"
    if torch.device(device).type == "cuda":
        return True
    if not bf16_units_usable():
        return False
    return bool(torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported())


@dataclass
class MappingResult:
    head: Head
    mean: np.ndarray
    image_size: tuple[int, int]
    seconds: float
    buffer_seconds: float
    iterations: int
    buffer_features: int
    target_features: int
    final_loss: float
    final_valid_fraction: float
    novel_view_features: int = 0
    history: list[dict] = field(default_factory=list)
    iterations_planned: int = 0
    cut_short: bool = False
    """The wall-clock cap ended the recipe early (fewer head steps, or a partial buffer, than planned)."""


@dataclass
class TrainingImage:
    gray: np.ndarray
    intrinsics: Intrinsics
    c2w: np.ndarray
    targets: ImageTargets | None = None


def cell_targets(im: TrainingImage, view, grid_hw: tuple[int, int]) -> np.ndarray:
    """Target world coordinates (h * w, 3) for the cells of an augmented view that hold a triangulated keypoint.

    The keypoint's depth is placed on the ray through the cell centre (not at the keypoint itself), so
    the target is off only by the surface's depth change across half a cell, not by half a cell sideways.
    """
    gh, gw = grid_hw
    out = np.full((gh * gw, 3), np.nan, np.float32)
    t = im.targets
    if t is None or len(t.pixels) == 0:
        return out
    ph = np.c_[t.pixels, np.ones(len(t.pixels))] @ view.pixel_map.T
    uv = ph[:, :2] / ph[:, 2:3]
    cx = np.floor(uv[:, 0] / OUTPUT_STRIDE).astype(int)
    cy = np.floor(uv[:, 1] / OUTPUT_STRIDE).astype(int)
    ok = (cx >= 0) & (cx < gw) & (cy >= 0) & (cy < gh) & (t.depths > 0)
    cell = cy[ok] * gw + cx[ok]
    centres = cell_centers(gh, gw)[cell]
    Xc = view.intrinsics.unproject(centres, t.depths[ok])
    out[cell] = (Xc @ view.c2w[:3, :3].T + view.c2w[:3, 3]).astype(np.float32)
    return out


ProgressFn = Callable[[str, float, dict], None]


def one_cycle_lr(progress: float, lr_min: float, lr_max: float, warmup: float = ONE_CYCLE_WARMUP) -> float:
    """Cosine rise from lr_min to lr_max over ``warmup``, then cosine decay to lr_min / 100."""
    p = min(max(progress, 0.0), 1.0)
    if p < warmup:
        return lr_min + (lr_max - lr_min) * 0.5 * (1 - math.cos(math.pi * p / warmup))
    q = (p - warmup) / (1 - warmup)
    lo = lr_min / 100.0
    return lo + (lr_max - lo) * 0.5 * (1 + math.cos(math.pi * q))


def load_training_images(split: SceneSplit, short_side: int) -> list[TrainingImage]:
    images = []
    for f in split.frames:
        rgb = f.load_rgb()
        size = size_for_short_side(rgb.shape[0], rgb.shape[1], short_side)
        gray, intr = to_gray_input(rgb, f.intrinsics, size)
        images.append(TrainingImage(gray, intr, f.pose))
    return images


@contextmanager
def buffer_encoding(encoder: Encoder, cfg: MappingConfig) -> Iterator[Callable[[np.ndarray], torch.Tensor]]:
    """A function from a grayscale image (H, W) uint8 to the features (C, h, w) the buffer stores.

    The encoder runs in bfloat16 where the head trains in it: channels-last convolutions on AMX are about
    3-3.7x faster (bench/head_speed.py) for a 0.6% relative feature error, which leaves more of the budget
    to the head; localization keeps float32 features. The encoder's layout is restored on the way out.
    """
    encoder.eval()
    bf16 = use_bf16(cfg.precision, cfg.device)
    layout = torch.channels_last if bf16 else torch.contiguous_format

    @torch.no_grad()
    def encode(gray: np.ndarray) -> torch.Tensor:
        x = normalize_gray(torch.from_numpy(gray)[None, None].to(cfg.device))
        with torch.autocast(x.device.type, dtype=torch.bfloat16, enabled=bf16):
            return encoder(x.contiguous(memory_format=layout))[0]

    encoder.to(memory_format=layout)
    try:
        yield encode
    finally:
        encoder.to(memory_format=torch.contiguous_format)


@torch.no_grad()
def fill_buffer(
    images: list[TrainingImage],
    encoder: Encoder,
    cfg: MappingConfig,
    deadline: float | None,
    rng: np.random.Generator,
    progress: ProgressFn | None = None,
    report: dict | None = None,
) -> Buffer:
    """Encoder features of augmented views: feats (N, C) fp16, pixels (N, 2), view (N,), and per view
    w2c (V, 3, 4), K (V, 3, 3); ``cfg.buffer_size`` of them, or fewer after ``cfg.buffer_passes`` over the images or
    past ``deadline`` (time.monotonic; ``report["deadline_hit"]`` then says so)."""
    ranges = augment_ranges(cfg.augment)
    builder = BufferBuilder()
    order: list[int] = []
    passes = 0
    deadline_hit = False
    with buffer_encoding(encoder, cfg) as encode:
        while builder.features < cfg.buffer_size:
            if not order:
                if passes == cfg.buffer_passes:
                    break
                passes += 1
                order = list(rng.permutation(len(images)))
            im = images[order.pop()]
            view = augment(im.gray, im.intrinsics, im.c2w, rng, ranges.scale_range, ranges.rotation_deg)
            f = encode(view.gray)  # (C, h, w)
            _, gh, gw = f.shape
            valid = np.flatnonzero(view.cell_valid[:gh, :gw].reshape(-1))
            room = cfg.buffer_size - builder.features
            take = rng.choice(valid, size=min(cfg.samples_per_image, valid.size, room), replace=False)
            if take.size == 0:
                continue
            builder.add_view(
                f, take, cell_centers(gh, gw)[take], view.c2w, view.intrinsics.K, cell_targets(im, view, (gh, gw))[take]
            )
            if progress:
                progress("buffer", builder.features / cfg.buffer_size, {"features": builder.features})
            if deadline is not None and time.monotonic() > deadline:
                deadline_hit = builder.features < cfg.buffer_size
                break
    if report is not None:
        report["deadline_hit"] = deadline_hit
        report["passes"] = passes
    buffer = builder.build()
    if buffer is None:
        raise ValueError("no training image had a valid cell to buffer")
    return buffer


def target_term(pred: torch.Tensor, target: torch.Tensor, w2c: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Summed distance of predictions (M, 3) to their triangulated targets (M, 3), in pixels at the target's depth.

    w2c (M, 3, 4) and K (M, 3, 3) of each target's view; the distance is clamped at TARGET_CLAMP_M first.
    """
    d = torch.clamp(torch.linalg.vector_norm(pred - target, dim=1), max=TARGET_CLAMP_M)
    z = torch.einsum("mj,mj->m", w2c[:, 2, :3], target) + w2c[:, 2, 3]
    px_per_m = K[:, 0, 0] / torch.clamp(z, min=DEPTH_MIN)
    return TARGET_WEIGHT_PX * (d * px_per_m).sum()


BufferExtension = Callable[[Head], "Buffer | None"]
"""Called once, with the head, when training passes ``extend_at``; returns entries to add to the buffer."""


def train_head(
    head: Head,
    buffer: Buffer,
    cfg: MappingConfig,
    seconds: float | None = None,
    progress: ProgressFn | None = None,
    extend: BufferExtension | None = None,
    extend_at: float = NOVEL_VIEWS_AT,
) -> tuple[int, float, float, list[dict]]:
    """Train ``head`` on the buffer for ``cfg.iterations`` steps, or until ``seconds`` (a cap) run out.

    Under a cap the schedule's progress is the larger of the steps' and the clock's, so a capped run still
    anneals its learning rate; the time ``extend`` takes counts against the cap.
    """
    dev = torch.device(cfg.device)
    head.to(dev).train()
    opt = torch.optim.AdamW(head.parameters(), lr=cfg.lr_min, weight_decay=WEIGHT_DECAY)
    bf16 = use_bf16(cfg.precision, cfg.device)

    def on_device(buf: Buffer) -> tuple[torch.Tensor, ...]:
        keys = ("feats", "pixels", "view", "target", "w2c", "K")
        return tuple(buf[k].to(dev) if dev.type == "cuda" or k in ("w2c", "K") else buf[k] for k in keys)

    feats, pixels, view, target, w2c_all, K_all = on_device(buffer)
    n = feats.shape[0]
    gen = torch.Generator(device="cpu").manual_seed(cfg.seed)
    start = time.monotonic()
    it = 0
    loss_v, valid_frac = float("nan"), float("nan")
    history: list[dict] = []
    while True:
        p = it / cfg.iterations
        if seconds is not None:
            p = max(p, (time.monotonic() - start) / seconds)
        if p >= 1.0:
            break
        if extend is not None and p >= extend_at:
            extra = extend(head)
            extend = None
            if extra is not None:
                buffer = merge_buffers(buffer, extra)
                feats, pixels, view, target, w2c_all, K_all = on_device(buffer)
                n = feats.shape[0]
            continue
        lr = one_cycle_lr(p, cfg.lr_min, cfg.lr_max)
        for g in opt.param_groups:
            g["lr"] = lr
        tau = curriculum_threshold(p)
        idx = torch.randint(0, n, (min(cfg.batch_size, n),), generator=gen)
        if dev.type == "cuda":
            idx = idx.to(dev)
        v = view[idx]
        w2c, K = w2c_all[v], K_all[v]
        pred = head.forward_points(feats[idx].float(), autocast_bf16=bf16)  # (B, 3) float32
        parts = reprojection_loss(pred, w2c, K, pixels[idx], tau)
        loss = parts.loss
        tgt = target[idx]
        has = torch.isfinite(tgt[:, 0])
        if bool(has.any()):
            loss = loss + target_term(pred[has], tgt[has], w2c[has], K[has]) / pred.shape[0]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        it += 1
        loss_v, valid_frac = float(loss.detach()), parts.valid_fraction
        if it % 50 == 0 or it == 1:
            history.append(
                {
                    "iteration": it,
                    "progress": p,
                    "lr": lr,
                    "threshold": tau,
                    "loss": loss_v,
                    "valid": valid_frac,
                    "reproj_px": parts.mean_reproj_px,
                }
            )
        if progress:
            progress("train", p, {"iteration": it, "loss": loss_v, "threshold": tau})
    head.eval()
    return it, loss_v, valid_frac, history


def map_scene(
    split: SceneSplit,
    encoder: Encoder,
    cfg: MappingConfig = MappingConfig(),
    progress: ProgressFn | None = None,
) -> MappingResult:
    """Map a scene: targets, a full buffer, then ``cfg.iterations`` head steps (all cut short by ``cfg.minutes``
    when a cap is set: ``MappingResult.cut_short``)."""
    if cfg.iterations < 1:
        raise ValueError(f"iterations must be positive, got {cfg.iterations}")
    if cfg.minutes is not None and cfg.minutes <= 0:
        raise ValueError(f"minutes must be positive, got {cfg.minutes}")
    t0 = time.monotonic()
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    budget = None if cfg.minutes is None else cfg.minutes * 60.0
    encoder = encoder.to(cfg.device).eval()
    for p in encoder.parameters():
        p.requires_grad_(False)
    if len(split.frames) < MIN_TRAINING_IMAGES:
        raise InputError(
            split.root / split.split,
            f"{len(split.frames)} training image(s); mapping needs at least {MIN_TRAINING_IMAGES} posed views",
        )
    images = load_training_images(split, cfg.short_side)
    if cfg.triangulate:
        deadline = None if budget is None else t0 + TARGETS_TIME_FRACTION * budget
        tg = triangulate_targets(
            [im.gray for im in images], [im.intrinsics for im in images], [im.c2w for im in images], deadline=deadline
        )
        for im, t in zip(images, tg):
            im.targets = t
        cut = deadline is not None and time.monotonic() > deadline
        if not cut and sum(len(t.points) for t in tg) < MIN_TRIANGULATED:
            raise InputError(
                split.root / split.split,
                f"the training images do not overlap: fewer than {MIN_TRIANGULATED} points triangulate between "
                f"neighbouring views ({len(images)} images)",
            )
        if progress:
            progress("triangulate", 1.0, {"points": int(sum(len(t.points) for t in tg))})
    fill: dict = {}
    buffer = fill_buffer(
        images, encoder, cfg, None if budget is None else t0 + BUFFER_TIME_FRACTION * budget, rng, progress, fill
    )
    t_buf = time.monotonic() - t0
    mean = np.mean([im.c2w[:3, 3] for im in images], axis=0)
    head = Head(torch.from_numpy(mean).float(), in_channels=encoder.cfg.out, cfg=cfg.head)
    remaining = None if budget is None else max(budget - (time.monotonic() - t0), 1.0)
    extend = None
    novel_features = 0
    if cfg.novel_views > 0 and len(images) > 1:

        def extend(h: Head) -> Buffer | None:
            nonlocal novel_features
            if progress:
                progress("novel views", 0.0, {"views": cfg.novel_views})
            deadline = math.inf if budget is None else time.monotonic() + NOVEL_VIEWS_TIME_FRACTION * budget
            with buffer_encoding(encoder, cfg) as encode:
                extra = novel_view_buffer(images, encoder, encode, h, cfg.novel_views, rng, deadline)
            novel_features = 0 if extra is None else int(extra["feats"].shape[0])
            if progress:
                progress("novel views", 1.0, {"features": novel_features})
            return extra

    its, loss_v, valid, history = train_head(head, buffer, cfg, remaining, progress, extend)
    return MappingResult(
        head=head.cpu(),
        mean=mean,
        image_size=images[0].gray.shape,
        seconds=time.monotonic() - t0,
        buffer_seconds=t_buf,
        iterations=its,
        buffer_features=int(buffer["feats"].shape[0]),
        target_features=int(torch.isfinite(buffer["target"][:, 0]).sum()),
        novel_view_features=novel_features,
        final_loss=loss_v,
        final_valid_fraction=valid,
        history=history,
        iterations_planned=cfg.iterations,
        cut_short=its < cfg.iterations or fill["deadline_hit"],
    )
