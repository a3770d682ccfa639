"""Pretraining our own encoder on procedural scenes: dense descriptors learned from exact correspondences.

ACE's published encoder is non-commercial and its training code was never released, so the project
trains its own. What a scene-specific head needs from an encoder is features that are distinctive
within a scene and stable across viewpoints. Each procedural scene has exact world coordinates for
every pixel (from its depth maps), so two nearby views give exact dense correspondences: a cell of one
view must find its corresponding cell of the other among all cells of the batch (InfoNCE).

ACE's own recipe (one coordinate-regression head per scene sharing the encoder) collapsed the features where
the contrastive objective did not (bench/encoder_choice.md). Runs resume from a checkpoint, so a long
pretraining can be spread over several runs.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from acesplat.core.atomic import atomic_path, write_json
from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob
from acesplat.core.grid import OUTPUT_STRIDE
from acesplat.scr.augment import rotation_z
from acesplat.scr.network import Encoder, EncoderConfig, normalize_gray

EDGE_ENCODER = EncoderConfig(c1=16, c2=32, c3=64, c4=128, res2=256, out=512)
"""The project's default encoder: a fifth of ACE's multiply-accumulates (bench/encoder_choice.md)."""
CROP_HW = (128, 160)
"""Training crop (h, w) of each view."""
PAIR_MAX_GAP = 6
"""Second view within this many frames along the trajectory (overlapping, different viewpoint)."""
MATCH_TOLERANCE_M = 0.05
"""A cell's correspondence is the other view's cell whose world point is nearest, if within this distance."""
TEMPERATURE = 0.07
LR = 1e-3
LR_FINAL_FRACTION = 0.05
WEIGHT_DECAY = 1e-4
CHECKPOINT_EVERY_S = 120.0


@dataclass
class PretrainConfig:
    minutes: float = knob(60.0, "Stop (and checkpoint) after this long; run again to resume.")
    scenes: int = knob(48, "Procedural scenes, one head each.")
    frames_per_scene: int = knob(60, "Frames per scene.")
    image_hw: tuple[int, int] = knob((240, 320), "Rendered frame size HxW.")
    steps: int = knob(6000, "Total optimisation steps (the schedule spans these).")
    pairs: int = knob(4, "View pairs per step; each cell competes against all cells of all second views.")
    seed: int = knob(0, "Seed of the scenes, crops and initialisation.")
    encoder: EncoderConfig = knob(
        EDGE_ENCODER, "Encoder widths to train (EDGE_ENCODER: a fifth of ACE's MACs; bench/encoder_choice.md)."
    )


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


def sample_crop(
    scene: PretrainScene, rng: np.random.Generator, crop_hw: tuple[int, int], frame: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """An augmented crop: grayscale (h, w) uint8 and coordinates at cell centres (3, h/8, w/8) (NaN = none).

    World coordinates do not change under image rescaling or in-plane rotation, so the coordinate map is
    warped with the image by nearest neighbour.
    """
    f = int(rng.integers(scene.gray.shape[0])) if frame is None else frame
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


def correspondences(ca: np.ndarray, cb: np.ndarray, tol: float = MATCH_TOLERANCE_M) -> tuple[np.ndarray, np.ndarray]:
    """Cells of view A (indices into ca (N, 3)) with their corresponding cells of view B (cb (M, 3)).

    Nearest world point: an occluded or out-of-view point has no B cell near it and drops out.
    """
    d = np.linalg.norm(ca[:, None] - cb[None], axis=2)
    d[~np.isfinite(d)] = np.inf
    j = d.argmin(1)
    ok = d[np.arange(len(ca)), j] < tol
    return np.flatnonzero(ok), j[ok]


def contrastive_loss(
    scenes: list[PretrainScene], encoder: Encoder, rng: np.random.Generator, pairs: int
) -> tuple[torch.Tensor, float] | None:
    """InfoNCE over the cells of ``pairs`` view pairs; returns (loss, top-1 match rate)."""
    crops = []
    for _ in range(pairs):
        s = scenes[int(rng.integers(len(scenes)))]
        n = s.gray.shape[0]
        f = int(rng.integers(n))
        g = int(np.clip(f + rng.integers(-PAIR_MAX_GAP, PAIR_MAX_GAP + 1), 0, n - 1))
        crops += [sample_crop(s, rng, CROP_HW, f), sample_crop(s, rng, CROP_HW, g)]
    x = torch.from_numpy(np.stack([c[0] for c in crops]))[:, None]
    feats = F.normalize(encoder(normalize_gray(x)), dim=1)
    _, c, h, w = feats.shape
    fa = feats[0::2].permute(0, 2, 3, 1).reshape(pairs, h * w, c)
    fb = feats[1::2].permute(0, 2, 3, 1).reshape(pairs * h * w, c)
    losses, hits, total = [], 0, 0
    for k in range(pairs):
        ca = crops[2 * k][1].reshape(3, -1).T
        cb = crops[2 * k + 1][1].reshape(3, -1).T
        ia, jb = correspondences(ca, cb)
        if len(ia) < 4:
            continue
        logits = fa[k][torch.from_numpy(ia)] @ fb.T / TEMPERATURE
        target = torch.from_numpy(k * h * w + jb)
        losses.append(F.cross_entropy(logits, target, reduction="sum"))
        hits += int((logits.argmax(1) == target).sum())
        total += len(ia)
    if not losses:
        return None
    return torch.stack(losses).sum() / total, hits / total


def pretrain(
    out_dir: str | Path,
    cfg: PretrainConfig,
    minutes: float | None = None,
    progress: Callable[[str, float, dict], None] | None = None,
    command: str | None = None,
) -> dict:
    """Run (or resume) pretraining for at most ``minutes`` (default ``cfg.minutes``); returns a summary. Writes
    encoder.pt when done.

    Each call that trains appends its ``command``, steps and seconds to the checkpoint's ``sessions``: a run that spans
    several calls keeps its whole provenance (the schedule follows the ``steps`` of each call).
    """
    out = Path(out_dir)
    cache = out / "scenes"
    cache.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    deadline = t0 + (cfg.minutes if minutes is None else minutes) * 60.0
    scenes = []
    for i in range(cfg.scenes):
        scenes.append(load_or_make_scene(cache, cfg.seed * 100003 + i, cfg))
        if progress:
            progress("scenes", (i + 1) / cfg.scenes, {"scene": i + 1})
        if time.monotonic() > deadline:
            return {"finished": False, "stage": "scenes", "scenes_ready": i + 1}
    torch.manual_seed(cfg.seed)
    encoder = Encoder(cfg.encoder)
    opt = torch.optim.AdamW(encoder.parameters(), lr=LR, weight_decay=WEIGHT_DECAY)
    ckpt_path = out / "checkpoint.pt"
    step, elapsed_before = 0, 0.0
    history: list[dict] = []
    sessions: list[dict] = []
    if ckpt_path.is_file():
        ck = torch.load(ckpt_path, map_location="cpu", weights_only=True)
        encoder.load_state_dict(ck["encoder"])
        opt.load_state_dict(ck["optimizer"])
        step, elapsed_before, history = int(ck["step"]), float(ck["elapsed"]), list(ck["history"])
        sessions = list(ck.get("sessions", []))
    this_session = {
        "command": command,
        "start_step": step,
        "end_step": step,
        "steps_planned": cfg.steps,
        "seconds": 0.0,
        "threads": torch.get_num_threads(),
    }
    sessions.append(this_session)
    rng = np.random.default_rng([cfg.seed, step])
    t_train = time.monotonic()

    def save_checkpoint() -> None:
        this_session.update(end_step=step, seconds=round(time.monotonic() - t_train, 1))
        with atomic_path(ckpt_path) as tmp:
            torch.save(
                {
                    "encoder": encoder.state_dict(),
                    "optimizer": opt.state_dict(),
                    "step": step,
                    "elapsed": elapsed_before + time.monotonic() - t_train,
                    "history": history,
                    "sessions": sessions,
                },
                tmp,
            )

    last_ckpt = t_train
    running: list[tuple[float, float]] = []
    encoder.train()
    while step < cfg.steps and time.monotonic() < deadline:
        p = step / cfg.steps
        lr = LR * (LR_FINAL_FRACTION + (1 - LR_FINAL_FRACTION) * 0.5 * (1 + np.cos(np.pi * p)))
        lr = float(lr * min(1.0, (step + 1) / 200))
        for g in opt.param_groups:
            g["lr"] = lr
        out_ = contrastive_loss(scenes, encoder, rng, cfg.pairs)
        if out_ is None:
            continue
        loss, top1 = out_
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(encoder.parameters(), 10.0)
        opt.step()
        step += 1
        running.append((float(loss.detach()), top1))
        if step % 100 == 0:
            arr = np.array(running)
            history.append({"step": step, "loss": float(arr[:, 0].mean()), "top1": float(arr[:, 1].mean()), "lr": lr})
            running = []
        if progress:
            progress("train", step / cfg.steps, {"step": step, "loss": float(loss.detach()), "top1": top1})
        if time.monotonic() - last_ckpt > CHECKPOINT_EVERY_S:
            save_checkpoint()
            last_ckpt = time.monotonic()
    if step == this_session["start_step"]:  # nothing trained (a finished run rerun, e.g. to --install): no entry
        sessions.remove(this_session)
    save_checkpoint()
    finished = step >= cfg.steps
    total_s = elapsed_before + time.monotonic() - t_train
    summary = {
        "finished": finished,
        "step": step,
        "steps": cfg.steps,
        "train_seconds": total_s,
        "last": history[-1] if history else None,
        "config": _cfg_dict(cfg),
        "sessions": sessions,
    }
    with atomic_path(out / "encoder.pt") as tmp:
        torch.save(encoder.state_dict(), tmp)
    write_json(out / "pretrain_summary.json", {**summary, "history": history})
    return summary


def install_default(out_dir: str | Path, command: str) -> Path:
    """Copy a pretraining run's encoder into the package as the shipped default, with its provenance beside it."""
    import platform

    from acesplat.scr.encoders import DEFAULT_ENCODER, file_sha256

    out = Path(out_dir)
    summary = json.loads((out / "pretrain_summary.json").read_text())
    sd = torch.load(out / "encoder.pt", map_location="cpu", weights_only=True)
    DEFAULT_ENCODER.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(DEFAULT_ENCODER) as tmp:
        torch.save(sd, tmp)
    provenance = {
        "command": command,
        "sessions": summary.get("sessions", []),
        "objective": "dense InfoNCE over exact correspondences of nearby views (acesplat/scr/pretrain.py)",
        "data": f"{summary['config']['scenes']} procedural rooms from acesplat.synth.random_scene_frames, "
        f"{summary['config']['frames_per_scene']} frames each at {summary['config']['image_hw']}",
        "seed": summary["config"]["seed"],
        "steps": summary["step"],
        "steps_planned": summary["steps"],
        "train_seconds": summary["train_seconds"],
        "last": summary["last"],
        "config": summary["config"],
        "machine": f"{platform.processor() or platform.machine()}, torch {torch.__version__}",
        "sha256": file_sha256(DEFAULT_ENCODER),
        "bytes": DEFAULT_ENCODER.stat().st_size,
    }
    write_json(DEFAULT_ENCODER.with_suffix(".json"), provenance)
    return DEFAULT_ENCODER


def _cfg_dict(cfg: PretrainConfig) -> dict:
    d = asdict(cfg)
    del d["minutes"]  # a budget of this call, not of the run (a resumed run has several)
    d["encoder"] = cfg.encoder.as_dict()
    return json.loads(json.dumps(d))
