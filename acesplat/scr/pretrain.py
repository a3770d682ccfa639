"""Pretraining our own encoder on procedural scenes: dense descriptors learned from exact correspondences.

ACE's published encoder is non-commercial and its training code was never released, so the project
trains its own. What a scene-specific head needs from an encoder is features that are distinctive
within a scene and stable across viewpoints. Each procedural scene has exact world coordinates for
every pixel (from its depth maps), so two nearby views give exact dense correspondences: a cell of one
view must find its corresponding cell of the other among all cells of the batch (InfoNCE).

ACE's own recipe (one coordinate-regression head per scene sharing the encoder) collapsed the features where
the contrastive objective did not (bench/encoder_choice.md). Runs resume from a checkpoint, so a long
pretraining can be spread over several runs.

Under ``torchrun`` (RANK/WORLD_SIZE in the environment, see ``distributed_from_env``) the ranks train one encoder with
DistributedDataParallel: each rank holds its own shard of the scenes and draws its own pairs, DDP averages the
gradients, so a step's global batch is ``pairs`` times the world size and ``steps`` counts global steps. Rank 0 alone
writes the checkpoint, the encoder and the summary.
"""

from __future__ import annotations

import gc
import hashlib
import json
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from acesplat.core.atomic import atomic_path, write_json
from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob
from acesplat.core.errors import InputError
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
    scenes: int = knob(48, "Procedural scenes (shared out among the ranks under torchrun).")
    frames_per_scene: int = knob(60, "Frames per scene.")
    image_hw: tuple[int, int] = knob((240, 320), "Rendered frame size HxW.")
    steps: int = knob(6000, "Total optimisation steps (the schedule spans these; global steps under torchrun).")
    pairs: int = knob(
        4, "View pairs per step and rank (global batch: pairs x world size); a cell competes with its rank's cells."
    )
    seed: int = knob(0, "Seed of the scenes, crops and initialisation.")
    encoder: EncoderConfig = knob(
        EDGE_ENCODER, "Encoder widths to train (EDGE_ENCODER: a fifth of ACE's MACs; bench/encoder_choice.md)."
    )
    photos: str = knob(
        "none",
        "Real photographs seen through random homographies beside the rooms: none, packaged (scikit-image's "
        "licensed photographs) or a folder with a photos.json licence manifest (acesplat/scr/photos.py).",
    )
    photo_share: float = knob(0.25, "Share of the view pairs drawn from the photographs (when there are any).")
    init_encoder: str | None = knob(
        None, "Start from these encoder weights instead of random ones (a new run only; a checkpoint wins)."
    )
    lr: float = knob(LR, "Peak learning rate of the cosine schedule (lower it to fine-tune from --init-encoder).")
    max_gap: int = knob(
        PAIR_MAX_GAP, "A pair's second view is at most this many frames along the trajectory from its first."
    )

    def __post_init__(self) -> None:
        if self.max_gap < 1:
            raise ValueError(f"max_gap must be >= 1, got {self.max_gap}")
        if not 0.0 <= self.photo_share <= 1.0:
            raise ValueError(f"photo_share must be in [0, 1], got {self.photo_share}")
        if not self.lr > 0:
            raise ValueError(f"lr must be > 0, got {self.lr}")


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


def make_photo_scene(photo_gray: np.ndarray, seed: int, cfg: PretrainConfig) -> PretrainScene:
    """A photograph (H, W) uint8 as a planar scene of ``cfg.frames_per_scene`` views (acesplat.scr.photos), its
    coordinates scaled so that a correspondence is within half a cell (MATCH_TOLERANCE_M)."""
    from acesplat.scr.photos import photo_views

    gray, coords = photo_views(
        photo_gray, seed, cfg.frames_per_scene, cfg.image_hw, MATCH_TOLERANCE_M / (OUTPUT_STRIDE / 2)
    )
    return PretrainScene(gray, coords.astype(np.float16), np.zeros(3))


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


PairBatch = tuple[np.ndarray, list[tuple[int, np.ndarray, np.ndarray]]]
"""Crops (2P, h, w) uint8 (view A of pair k at 2k, view B at 2k+1) and (k, A cells, their B cells) per usable pair."""


def sample_pairs(
    scenes: list[PretrainScene],
    rng: np.random.Generator,
    pairs: int,
    weights: np.ndarray | None = None,
    max_gap: int = PAIR_MAX_GAP,
    crop_hw: tuple[int, int] = CROP_HW,
) -> PairBatch | None:
    """``pairs`` augmented view pairs (crops ``crop_hw``) with their cell correspondences; None if no pair has 4
    correspondences. A pair's scene is drawn uniformly, or with probabilities ``weights`` (len(scenes),); its second
    frame is at most ``max_gap`` frames from the first."""
    if not scenes or pairs < 1:
        raise ValueError(f"need scenes and pairs >= 1, got {len(scenes)} scenes and {pairs} pairs")
    crops = []
    for _ in range(pairs):
        s = scenes[int(rng.integers(len(scenes)) if weights is None else rng.choice(len(scenes), p=weights))]
        n = s.gray.shape[0]
        f = int(rng.integers(n))
        g = int(np.clip(f + rng.integers(-max_gap, max_gap + 1), 0, n - 1))
        crops += [sample_crop(s, rng, crop_hw, f), sample_crop(s, rng, crop_hw, g)]
    matches = []
    for k in range(pairs):
        ia, jb = correspondences(crops[2 * k][1].reshape(3, -1).T, crops[2 * k + 1][1].reshape(3, -1).T)
        if len(ia) >= 4:
            matches.append((k, ia, jb))
    if not matches:
        return None
    return np.stack([c[0] for c in crops]), matches


def pair_loss(encoder: torch.nn.Module, batch: PairBatch) -> tuple[torch.Tensor, float]:
    """InfoNCE of a ``sample_pairs`` batch: each A cell against all cells of all B views; (loss, top-1 match rate).

    ``encoder`` may be wrapped (DistributedDataParallel); the batch goes to the device of its parameters.
    """
    images, matches = batch
    device = next(encoder.parameters()).device
    pairs = images.shape[0] // 2
    x = torch.from_numpy(images)[:, None].to(device)
    feats = F.normalize(encoder(normalize_gray(x)), dim=1)
    _, c, h, w = feats.shape
    fa = feats[0::2].permute(0, 2, 3, 1).reshape(pairs, h * w, c)
    fb = feats[1::2].permute(0, 2, 3, 1).reshape(pairs * h * w, c)
    losses, hits, total = [], 0, 0
    for k, ia, jb in matches:
        logits = fa[k][torch.from_numpy(ia).to(device)] @ fb.T / TEMPERATURE
        target = torch.from_numpy(k * h * w + jb).to(device)
        losses.append(F.cross_entropy(logits, target, reduction="sum"))
        hits += int((logits.argmax(1) == target).sum())
        total += len(ia)
    return torch.stack(losses).sum() / total, hits / total


def contrastive_loss(
    scenes: list[PretrainScene], encoder: torch.nn.Module, rng: np.random.Generator, pairs: int
) -> tuple[torch.Tensor, float] | None:
    """InfoNCE over the cells of ``pairs`` view pairs; returns (loss, top-1 match rate), None if no pair matched."""
    batch = sample_pairs(scenes, rng, pairs)
    return None if batch is None else pair_loss(encoder, batch)


@dataclass(frozen=True)
class Distributed:
    """This process's place in a torchrun job; the defaults are a plain single-process run (no process group)."""

    rank: int = 0
    world_size: int = 1
    backend: str | None = None


def current_distributed() -> Distributed:
    """The process group this process belongs to (``torch.distributed``'s default group), if any."""
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return Distributed()
    return Distributed(dist.get_rank(), dist.get_world_size(), str(dist.get_backend()))


@contextmanager
def distributed_from_env(device: str) -> Iterator[tuple[Distributed, str]]:
    """Join torchrun's job if RANK and WORLD_SIZE (> 1) are set: NCCL on CUDA, gloo on the CPU.

    ``device`` is 'cpu' or 'cuda'. Yields (this process's ``Distributed``, its device: cuda:LOCAL_RANK on GPUs).
    Without the variables, or with WORLD_SIZE 1, no process group is made and the run is single-process.
    """
    import torch.distributed as dist

    if device not in ("cpu", "cuda"):
        raise InputError(None, f"device must be cpu or cuda, got {device!r}")
    env = {k: os.environ.get(k) for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")}
    try:
        world = int(env["WORLD_SIZE"] or 1)
        rank = int(env["RANK"] or 0)
        local = int(env["LOCAL_RANK"] or rank)
    except ValueError:
        raise InputError(None, f"RANK, WORLD_SIZE and LOCAL_RANK must be integers, got {env}") from None
    if world <= 1:
        yield Distributed(), device
        return
    if not 0 <= rank < world:
        raise InputError(None, f"RANK must be in [0, WORLD_SIZE={world}), got {rank}")
    if not (env["MASTER_ADDR"] and env["MASTER_PORT"]):
        raise InputError(None, "WORLD_SIZE > 1 needs MASTER_ADDR and MASTER_PORT (torchrun sets them)")
    if device == "cuda":
        if not 0 <= local < torch.cuda.device_count():
            raise InputError(None, f"LOCAL_RANK {local} but only {torch.cuda.device_count()} CUDA devices")
        torch.cuda.set_device(local)
        device = f"cuda:{local}"
    backend = "nccl" if device.startswith("cuda") else "gloo"
    dist.init_process_group(backend, rank=rank, world_size=world)
    try:
        yield Distributed(rank, world, backend), device
        # A normal end: free what still holds the group (a DistributedDataParallel's reducer in a reference cycle)
        # while the group lives, and leave together. gloo work freed at interpreter exit, or a group torn down while
        # the other rank still sends, aborts the process (SIGABRT). After an error no barrier: the other rank may
        # never reach it.
        gc.collect()
        dist.barrier()
    finally:
        dist.destroy_process_group()


def _any_rank(flags: list[bool], ddp: Distributed, device: str) -> list[bool]:
    """Each flag true if it is true on any rank (the ranks must take the same branches to stay in step)."""
    if ddp.world_size == 1:
        return flags
    import torch.distributed as dist

    t = torch.tensor([float(f) for f in flags], device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return [bool(v) for v in t.tolist()]


def _rank_sum(values: list[float], ddp: Distributed, device: str) -> list[float]:
    if ddp.world_size == 1:
        return values
    import torch.distributed as dist

    t = torch.tensor(values, dtype=torch.float64, device=device)
    dist.all_reduce(t)
    return t.tolist()


def _rank_mean(values: list[float], ddp: Distributed, device: str) -> list[float]:
    if ddp.world_size == 1:
        return values
    return [v / ddp.world_size for v in _rank_sum(values, ddp, device)]


def weights_sha256(module: torch.nn.Module) -> str:
    """SHA-256 of a module's state dict (names, dtypes, shapes and values, in order)."""
    h = hashlib.sha256()
    for k, v in module.state_dict().items():
        v = v.detach().cpu().contiguous()
        h.update(f"{k}:{v.dtype}:{tuple(v.shape)}".encode())
        h.update(v.numpy().tobytes())
    return h.hexdigest()


def _same_on_every_rank(value: object, what: str, ddp: Distributed) -> None:
    """RuntimeError on every rank if ``value`` differs between ranks."""
    if ddp.world_size == 1:
        return
    import torch.distributed as dist

    values: list[object] = [None] * ddp.world_size
    dist.all_gather_object(values, value)
    if any(v != values[0] for v in values):
        raise RuntimeError(f"the ranks disagree on {what}: {values}")


def pretrain(
    out_dir: str | Path,
    cfg: PretrainConfig,
    minutes: float | None = None,
    progress: Callable[[str, float, dict], None] | None = None,
    command: str | None = None,
    device: str = "cpu",
    max_steps: int | None = None,
) -> dict:
    """Run (or resume) pretraining for at most ``minutes`` (default ``cfg.minutes``) and at most ``max_steps`` steps
    in this call (None: no limit); returns a summary. Writes encoder.pt when done.

    Each call that trains appends its ``command``, steps and seconds to the checkpoint's ``sessions``: a run that spans
    several calls keeps its whole provenance (the schedule follows the ``steps`` of each call).

    Inside a process group (``distributed_from_env``; ``device`` is then this rank's) the ranks train one encoder with
    DistributedDataParallel: rank r holds scenes r, r + world, ..., draws its own pairs, and all ranks resume from the
    same checkpoint; only rank 0 writes files and reports ``progress``. Every rank returns the summary. The scenes
    weigh equally when the world size divides ``cfg.scenes`` (a scene weighs 1 / (world size x its shard's size)).
    """
    if max_steps is not None and max_steps < 0:
        raise ValueError(f"max_steps must be >= 0 or None, got {max_steps}")
    ddp = current_distributed()
    if cfg.scenes < ddp.world_size:
        raise InputError(None, f"{cfg.scenes} scenes cannot be shared among {ddp.world_size} ranks")
    main = ddp.rank == 0
    report = progress if main else None
    from acesplat.scr.photos import load_photo_gray, photo_sources

    photos = photo_sources(cfg.photos)  # checked before any work; every rank checks every source alike
    out = Path(out_dir)
    cache = out / "scenes"
    cache.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    deadline = t0 + (cfg.minutes if minutes is None else minutes) * 60.0
    scenes = []
    mine = range(ddp.rank, cfg.scenes, ddp.world_size)
    out_of_time = False
    for k, i in enumerate(mine):
        scenes.append(load_or_make_scene(cache, cfg.seed * 100003 + i, cfg))
        if report:
            report("scenes", (k + 1) / len(mine), {"scene": k + 1})
        if time.monotonic() > deadline:
            out_of_time = True
            break
    if _any_rank([out_of_time], ddp, device)[0]:
        return {"finished": False, "stage": "scenes", "scenes_ready": int(_rank_sum([len(scenes)], ddp, device)[0])}
    for i in range(ddp.rank, len(photos), ddp.world_size):
        scenes.append(make_photo_scene(load_photo_gray(photos[i]), cfg.seed * 100003 + 50000 + i, cfg))
    n_rooms, n_photos = len(mine), len(scenes) - len(mine)
    weights = None
    if n_photos and n_rooms:
        share = cfg.photo_share
        weights = np.r_[np.full(n_rooms, (1 - share) / n_rooms), np.full(n_photos, share / n_photos)]
    torch.manual_seed(cfg.seed)
    init_sha = None
    if cfg.init_encoder is None:
        encoder = Encoder(cfg.encoder).to(device)
    else:
        from acesplat.scr.encoders import file_sha256

        # the architecture follows the file (e.g. a factorized res2_conv3), the weights too
        encoder = Encoder.from_state_dict(torch.load(cfg.init_encoder, map_location="cpu", weights_only=True))
        encoder = encoder.to(device)
        init_sha = file_sha256(Path(cfg.init_encoder))
    opt = torch.optim.AdamW(encoder.parameters(), lr=cfg.lr, weight_decay=WEIGHT_DECAY)
    ckpt_path = out / "checkpoint.pt"
    step, elapsed_before = 0, 0.0
    history: list[dict] = []
    sessions: list[dict] = []
    if ckpt_path.is_file():
        ck = torch.load(ckpt_path, map_location="cpu", weights_only=True)
        if EncoderConfig.from_state_dict(ck["encoder"]) != encoder.cfg:
            # resumed without the --init-encoder it started from: the run continues the architecture it checkpointed
            encoder = Encoder.from_state_dict(ck["encoder"]).to(device)
            opt = torch.optim.AdamW(encoder.parameters(), lr=cfg.lr, weight_decay=WEIGHT_DECAY)
        encoder.load_state_dict(ck["encoder"])
        opt.load_state_dict(ck["optimizer"])
        step, elapsed_before, history = int(ck["step"]), float(ck["elapsed"]), list(ck["history"])
        sessions = list(ck.get("sessions", []))
    _same_on_every_rank(step, f"the checkpoint's step (is {ckpt_path} on a file system every rank sees?)", ddp)
    model: torch.nn.Module = encoder
    if ddp.world_size > 1:
        from torch.nn.parallel import DistributedDataParallel

        model = DistributedDataParallel(
            encoder, device_ids=[torch.device(device).index] if ddp.backend == "nccl" else None
        )
    this_session = {
        "command": command,
        "start_step": step,
        "end_step": step,
        "steps_planned": cfg.steps,
        "seconds": 0.0,
        "threads": torch.get_num_threads(),
        "world_size": ddp.world_size,
        "backend": ddp.backend,
        "device": torch.device(device).type,
    }
    sessions.append(this_session)
    rng = np.random.default_rng([cfg.seed, step] if main else [cfg.seed, step, ddp.rank])
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
    stop_step = cfg.steps if max_steps is None else min(cfg.steps, step + max_steps)
    encoder.train()
    while step < stop_step:
        time_up = time.monotonic() >= deadline
        if time_up and ddp.world_size == 1:
            break
        p = step / cfg.steps
        lr = cfg.lr * (LR_FINAL_FRACTION + (1 - LR_FINAL_FRACTION) * 0.5 * (1 + np.cos(np.pi * p)))
        lr = float(lr * min(1.0, (step + 1) / 200))
        for g in opt.param_groups:
            g["lr"] = lr
        batch = sample_pairs(scenes, rng, cfg.pairs, weights, max_gap=cfg.max_gap)
        time_up, no_batch = _any_rank([time_up, batch is None], ddp, device)
        if time_up:
            break
        if no_batch:
            continue
        loss, top1 = pair_loss(model, batch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(encoder.parameters(), 10.0)
        opt.step()
        step += 1
        running.append((float(loss.detach()), top1))
        if step % 100 == 0:
            arr = np.array(running)
            mean_loss, mean_top1 = _rank_mean([float(arr[:, 0].mean()), float(arr[:, 1].mean())], ddp, device)
            history.append({"step": step, "loss": mean_loss, "top1": mean_top1, "lr": lr})
            running = []
        if report:
            report("train", step / cfg.steps, {"step": step, "loss": float(loss.detach()), "top1": top1, "lr": lr})
        if main and time.monotonic() - last_ckpt > CHECKPOINT_EVERY_S:
            save_checkpoint()
            last_ckpt = time.monotonic()
    if step == this_session["start_step"]:  # nothing trained (a finished run rerun, e.g. to --install): no entry
        sessions.remove(this_session)
    sha = weights_sha256(encoder)
    _same_on_every_rank(sha, "the encoder's weights", ddp)
    this_session.update(end_step=step, seconds=round(time.monotonic() - t_train, 1))
    finished = step >= cfg.steps
    total_s = elapsed_before + time.monotonic() - t_train
    summary = {
        "finished": finished,
        "step": step,
        "steps": cfg.steps,
        "train_seconds": total_s,
        "last": history[-1] if history else None,
        "config": {**_cfg_dict(cfg), "encoder": encoder.cfg.as_dict()},  # an --init-encoder file sets it
        "sessions": sessions,
        "world_size": ddp.world_size,
        "backend": ddp.backend,
        "global_batch_pairs": cfg.pairs * ddp.world_size,
        "weights_sha256": sha,
        "photos": [p.record() for p in photos],
        "init_encoder_sha256": init_sha,
    }
    if main:
        save_checkpoint()
        with atomic_path(out / "encoder.pt") as tmp:
            torch.save(encoder.state_dict(), tmp)
        write_json(out / "pretrain_summary.json", {**summary, "history": history})
    if ddp.world_size > 1:
        import torch.distributed as dist

        dist.barrier()  # the files are in place before any rank goes on (or a later run starts)
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
    trained = summary.get("sessions", [])  # the world size of the last session that trained, not of an --install rerun
    provenance = {
        "command": command,
        "sessions": summary.get("sessions", []),
        "objective": "dense InfoNCE over exact correspondences of nearby views (acesplat/scr/pretrain.py)",
        "data": f"{summary['config']['scenes']} procedural rooms from acesplat.synth.random_scene_frames, "
        f"{summary['config']['frames_per_scene']} frames each at {summary['config']['image_hw']}"
        + (
            f"; {len(summary.get('photos', []))} photographs through random homographies, "
            f"{summary['config'].get('photo_share')} of the pairs"
            if summary.get("photos")
            else ""
        ),
        "photos": summary.get("photos", []),
        "init_encoder_sha256": summary.get("init_encoder_sha256"),
        "seed": summary["config"]["seed"],
        "steps": summary["step"],
        "steps_planned": summary["steps"],
        "train_seconds": summary["train_seconds"],
        "last": summary["last"],
        "config": summary["config"],
        "world_size": trained[-1].get("world_size", 1) if trained else summary.get("world_size", 1),
        "backend": trained[-1].get("backend") if trained else summary.get("backend"),
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
