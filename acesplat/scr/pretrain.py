"""Pretraining our own encoder: many procedural scenes, one head per scene, one shared encoder (as ACE did).

ACE's published encoder is non-commercial and its training code was never released, so the project
trains its own. Each procedural scene has exact scene coordinates from its depth maps; the encoder
learns features from which a per-scene head can regress coordinates, which is exactly what mapping
asks of it later. Runs resume from a checkpoint, because pretraining spans several sessions.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import torch

from acesplat.core.atomic import atomic_path, write_json
from acesplat.core.camera import Intrinsics
from acesplat.core.pnp import OUTPUT_STRIDE

from .augment import rotation_z
from .network import Encoder, EncoderConfig, Head, HeadConfig, normalize_gray

EDGE_ENCODER = EncoderConfig(c1=16, c2=32, c3=64, c4=128, res2=256, out=512)
"""The project's default encoder: a fifth of ACE's multiply-accumulates (bench/encoder_choice.md)."""
PRETRAIN_HEAD = HeadConfig(width=128, blocks=1, homogeneous=True)
CROP_HW = (128, 160)
BATCH_IMAGES = 8
LR = 1e-3
LR_FINAL_FRACTION = 0.05
WEIGHT_DECAY = 1e-4
COORD_LOSS_CLAMP_M = 5.0
"""Errors beyond this many metres stop growing the loss (robust to occlusion edges in the depth)."""
CHECKPOINT_EVERY_S = 120.0


@dataclass
class PretrainConfig:
    scenes: int = 48
    frames_per_scene: int = 60
    image_hw: tuple[int, int] = (240, 320)
    steps: int = 20000
    batch_images: int = BATCH_IMAGES
    seed: int = 0
    encoder: EncoderConfig = EDGE_ENCODER


@dataclass
class PretrainScene:
    """Grayscale frames (F, H, W) uint8 and world coordinates (F, H, W, 3) float16 (NaN where no depth)."""

    gray: np.ndarray
    coords: np.ndarray
    mean: np.ndarray


def coords_from_depth(depth: np.ndarray, K: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """World coordinates (H, W, 3) of every pixel from z-depth (H, W); NaN where depth is 0."""
    h, w = depth.shape
    intr = Intrinsics.from_K(K, w, h)
    ys, xs = np.mgrid[0:h, 0:w]
    uv = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
    X = intr.unproject(uv, depth.reshape(-1).astype(np.float64))
    Xw = X @ c2w[:3, :3].T + c2w[:3, 3]
    Xw[depth.reshape(-1) <= 0] = np.nan
    return Xw.reshape(h, w, 3)


def make_scene(seed: int, cfg: PretrainConfig) -> PretrainScene:
    from acesplat.synth import random_scene_frames

    frames = random_scene_frames(seed, cfg.frames_per_scene, cfg.image_hw)
    gray = np.stack([cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) for rgb, _, _, _ in frames])
    coords = np.stack([coords_from_depth(d, K, T) for _, d, T, K in frames]).astype(np.float16)
    mean = np.mean([T[:3, 3] for _, _, T, _ in frames], axis=0)
    return PretrainScene(gray, coords, mean)


def load_or_make_scene(cache: Path, seed: int, cfg: PretrainConfig) -> PretrainScene:
    path = cache / f"scene_{seed:05d}.npz"
    if path.is_file():
        d = np.load(path)
        return PretrainScene(d["gray"], d["coords"], d["mean"])
    s = make_scene(seed, cfg)
    with atomic_path(path) as tmp:
        np.savez(tmp, gray=s.gray, coords=s.coords, mean=s.mean)
    return s


def sample_crop(scene: PretrainScene, rng: np.random.Generator, crop_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """An augmented crop: grayscale (h, w) uint8 and coordinates at cell centres (3, h/8, w/8) (NaN = none).

    World coordinates do not change under image rescaling or in-plane rotation, so the coordinate map is
    warped with the image by nearest neighbour.
    """
    f = int(rng.integers(scene.gray.shape[0]))
    gray, coords = scene.gray[f], scene.coords[f].astype(np.float32)
    h, w = gray.shape
    ch, cw = crop_hw
    s = rng.uniform(max(2 / 3, ch / h, cw / w), 3 / 2)
    angle = np.radians(rng.uniform(-15, 15))
    R = rotation_z(angle)[:2, :2]
    # Affine: scale about the origin, rotate about the image centre, then crop at a random offset.
    nh, nw = int(h * s), int(w * s)
    oy, ox = int(rng.integers(0, nh - ch + 1)), int(rng.integers(0, nw - cw + 1))
    c = np.array([nw / 2, nh / 2])
    A = np.zeros((2, 3))
    A[:, :2] = R * s
    A[:, 2] = c - R @ c - np.array([ox, oy])
    img = cv2.warpAffine(gray, A, (cw, ch), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    # Coordinates sampled only at the cell centres the network predicts for.
    gh, gw = ch // OUTPUT_STRIDE, cw // OUTPUT_STRIDE
    ys, xs = np.mgrid[0:gh, 0:gw]
    px = np.stack([xs.ravel() * OUTPUT_STRIDE + OUTPUT_STRIDE / 2, ys.ravel() * OUTPUT_STRIDE + OUTPUT_STRIDE / 2], 1)
    Ainv = cv2.invertAffineTransform(A)
    src = px @ Ainv[:, :2].T + Ainv[:, 2]
    sx, sy = np.round(src[:, 0]).astype(int), np.round(src[:, 1]).astype(int)
    inside = (sx >= 0) & (sx < w) & (sy >= 0) & (sy < h)
    out = np.full((gh * gw, 3), np.nan, np.float32)
    out[inside] = coords[sy[inside], sx[inside]]
    b = rng.uniform(0.8, 1.2)
    ct = rng.uniform(0.8, 1.2)
    fimg = img.astype(np.float32) * b
    fimg = (fimg - fimg.mean()) * ct + fimg.mean() + rng.normal(0, rng.uniform(0, 4), fimg.shape)
    return np.clip(fimg, 0, 255).astype(np.uint8), out.T.reshape(3, gh, gw)


def pretrain(
    out_dir: str | Path,
    cfg: PretrainConfig,
    minutes: float,
    progress: Callable[[str, float, dict], None] | None = None,
) -> dict:
    """Run (or resume) pretraining for at most ``minutes``; returns a summary. Writes encoder.pt when done."""
    out = Path(out_dir)
    cache = out / "scenes"
    cache.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    deadline = t0 + minutes * 60.0
    scenes = []
    for i in range(cfg.scenes):
        scenes.append(load_or_make_scene(cache, cfg.seed * 100003 + i, cfg))
        if progress:
            progress("scenes", (i + 1) / cfg.scenes, {"scene": i + 1})
        if time.monotonic() > deadline:
            return {"finished": False, "stage": "scenes", "scenes_ready": i + 1}
    torch.manual_seed(cfg.seed)
    encoder = Encoder(cfg.encoder)
    heads = torch.nn.ModuleList(
        Head(torch.from_numpy(s.mean).float(), in_channels=cfg.encoder.out, cfg=PRETRAIN_HEAD) for s in scenes
    )
    params = list(encoder.parameters()) + list(heads.parameters())
    opt = torch.optim.AdamW(params, lr=LR, weight_decay=WEIGHT_DECAY)
    ckpt_path = out / "checkpoint.pt"
    step, elapsed_before = 0, 0.0
    rng = np.random.default_rng(cfg.seed)
    history: list[dict] = []
    if ckpt_path.is_file():
        ck = torch.load(ckpt_path, map_location="cpu", weights_only=True)
        encoder.load_state_dict(ck["encoder"])
        heads.load_state_dict(ck["heads"])
        opt.load_state_dict(ck["optimizer"])
        step, elapsed_before, history = int(ck["step"]), float(ck["elapsed"]), list(ck["history"])
        rng = np.random.default_rng([cfg.seed, step])

    def save_checkpoint() -> None:
        with atomic_path(ckpt_path) as tmp:
            torch.save({"encoder": encoder.state_dict(), "heads": heads.state_dict(), "optimizer": opt.state_dict(),
                        "step": step, "elapsed": elapsed_before + time.monotonic() - t_train, "history": history}, tmp)

    t_train = time.monotonic()
    last_ckpt = t_train
    running = []
    encoder.train()
    while step < cfg.steps and time.monotonic() < deadline:
        p = step / cfg.steps
        lr = LR * (LR_FINAL_FRACTION + (1 - LR_FINAL_FRACTION) * 0.5 * (1 + np.cos(np.pi * p)))
        lr = float(lr * min(1.0, (step + 1) / 200))
        for g in opt.param_groups:
            g["lr"] = lr
        ids = rng.integers(0, len(scenes), cfg.batch_images)
        crops = [sample_crop(scenes[i], rng, CROP_HW) for i in ids]
        x = torch.from_numpy(np.stack([c[0] for c in crops]))[:, None]
        gt = torch.from_numpy(np.stack([c[1] for c in crops]))
        feats = encoder(normalize_gray(x))
        loss_sum, count = 0.0, 0
        for b, sid in enumerate(ids):
            pred = heads[int(sid)](feats[b : b + 1])[0]
            valid = torch.isfinite(gt[b]).all(0)
            if valid.any():
                d = torch.linalg.vector_norm(pred[:, valid] - gt[b][:, valid], dim=0)
                loss_sum = loss_sum + torch.clamp(d, max=COORD_LOSS_CLAMP_M).sum()
                count += int(valid.sum())
        loss = loss_sum / max(count, 1)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 10.0)
        opt.step()
        step += 1
        running.append(float(loss.detach()))
        if step % 100 == 0:
            history.append({"step": step, "loss_m": float(np.mean(running)), "lr": lr})
            running = []
        if progress:
            progress("train", step / cfg.steps, {"step": step, "loss_m": float(loss)})
        if time.monotonic() - last_ckpt > CHECKPOINT_EVERY_S:
            save_checkpoint()
            last_ckpt = time.monotonic()
    save_checkpoint()
    finished = step >= cfg.steps
    total_s = elapsed_before + time.monotonic() - t_train
    summary = {"finished": finished, "step": step, "steps": cfg.steps, "train_seconds": total_s,
               "loss_m": history[-1]["loss_m"] if history else None, "config": _cfg_dict(cfg)}
    if finished:
        with atomic_path(out / "encoder.pt") as tmp:
            torch.save(encoder.state_dict(), tmp)
    write_json(out / "pretrain_summary.json", {**summary, "history": history})
    return summary


def _cfg_dict(cfg: PretrainConfig) -> dict:
    d = asdict(cfg)
    d["encoder"] = cfg.encoder.as_dict()
    return json.loads(json.dumps(d))
