"""The shipped encoder with its last 3x3 layer made separable, distilled to the full layer: a start for pretraining.

`res2_conv3` (256 -> 512 channels, 3x3, at 1/8 resolution) is a third of the SCR graph's inference. Its separable
replacement (acesplat.scr.network.SeparableConv2d: a 1x1 into 512 channels, then a depthwise 3x3) costs about a
ninth and keeps all 512 output directions, which the rank-limited pair does not (bench/encoder_rank.md). This fits
it to the full layer's pre-activation outputs on procedural pretraining rooms (never an evaluation image), prints
the share of the outputs' variance it reproduces on held-out rooms, and saves the encoder as a state dict for
`acesplat pretrain-encoder --init-encoder FILE`:

    python bench/separable_init.py -o SEP_INIT.pt [--steps 1500] [--rooms 12] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn

from acesplat.core.atomic import write_json
from acesplat.core.machine import machine_line
from acesplat.scr.encoders import load_encoder
from acesplat.scr.lowrank import LOWRANK_LAYER
from acesplat.scr.network import Encoder, EncoderConfig, SeparableConv2d, normalize_gray
from acesplat.scr.pretrain import PretrainConfig, load_or_make_scene

HELD_OUT_ROOMS = 4
"""Rooms after the fitting rooms on which the reproduced variance is reported."""
FRAME_EVERY = 6
"""Every 6th frame of a room: 10 of its 60, views far enough apart to differ."""


def room_frames(cache: Path, rooms: range, cfg: PretrainConfig) -> list[np.ndarray]:
    """Grayscale (H, W) uint8 frames of the pretraining rooms ``rooms`` (their seeds as pretraining draws them)."""
    out: list[np.ndarray] = []
    for i in rooms:
        s = load_or_make_scene(cache, cfg.seed * 100003 + i, cfg)
        out += [s.gray[k] for k in range(0, len(s.gray), FRAME_EVERY)]
    return out


@torch.no_grad()
def layer_io(encoder: Encoder, frames: list[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, C_in, h, w) inputs and (N, C_out, h, w) pre-activation outputs of ``encoder.res2_conv3`` on ``frames``."""
    xs: list[torch.Tensor] = []
    ys: list[torch.Tensor] = []

    def hook(_m: nn.Module, i: tuple, o: torch.Tensor) -> None:
        xs.append(i[0])
        ys.append(o)

    h = getattr(encoder, LOWRANK_LAYER).register_forward_hook(hook)
    try:
        for f in frames:
            encoder(normalize_gray(torch.from_numpy(f).float()[None, None]))
    finally:
        h.remove()
    return torch.cat(xs), torch.cat(ys)


def reproduced(m: nn.Module, x: torch.Tensor, y: torch.Tensor) -> float:
    """1 - residual / total sum of squares of ``m(x)`` against ``y`` (N, C, h, w), about each channel's mean."""
    with torch.no_grad():
        p = m(x)
    return 1.0 - float(((p - y) ** 2).sum() / ((y - y.mean(dim=(0, 2, 3), keepdim=True)) ** 2).sum())


def distill(full: nn.Conv2d, x: torch.Tensor, y: torch.Tensor, steps: int, lr: float, seed: int) -> SeparableConv2d:
    """A SeparableConv2d fitted to ``full``'s outputs ``y`` on its inputs ``x``: Adam on the channel-normalised
    squared error, one-cycle schedule, 16 frames a step. Starts from the full layer's response to a constant input
    (its taps summed) and an identity depthwise filter."""
    c_out, c_in, k, _ = full.weight.shape
    sep = SeparableConv2d(c_in, c_out, k)
    with torch.no_grad():
        sep.point.weight.copy_(full.weight.sum(dim=(2, 3))[:, :, None, None])
        sep.point.bias.copy_(full.bias)
        sep.depth.weight.zero_()
        sep.depth.weight[:, 0, k // 2, k // 2] = 1.0
        sep.depth.bias.zero_()
    scale = y.std(dim=(0, 2, 3), keepdim=True) + 1e-6
    opt = torch.optim.Adam(sep.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=steps)
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        idx = torch.randint(0, len(x), (16,), generator=g)
        loss = (((sep(x[idx]) - y[idx]) / scale) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    return sep.eval()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--out", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--rooms", type=int, default=12)
    ap.add_argument("--cache", type=Path, default=Path("runs/sep/scenes"))
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    torch.manual_seed(0)
    cfg = PretrainConfig()
    args.cache.mkdir(parents=True, exist_ok=True)
    enc, ident = load_encoder()
    full = getattr(enc, LOWRANK_LAYER)
    fit_x, fit_y = layer_io(enc, room_frames(args.cache, range(args.rooms), cfg))
    held = range(cfg.scenes - HELD_OUT_ROOMS, cfg.scenes)
    held_x, held_y = layer_io(enc, room_frames(args.cache, held, cfg))
    t0 = time.monotonic()
    sep = distill(full, fit_x, fit_y, args.steps, args.lr, seed=0)
    seconds = time.monotonic() - t0
    out = Encoder(EncoderConfig(**{**enc.cfg.as_dict(), "separable": True}))
    sd = {k: v for k, v in enc.state_dict().items() if not k.startswith(f"{LOWRANK_LAYER}.")}
    sd.update({f"{LOWRANK_LAYER}.{k}": v for k, v in sep.state_dict().items()})
    out.load_state_dict(sd)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(out.state_dict(), args.out)
    report = {
        "machine": machine_line(),
        "from": ident.as_dict(),
        "rooms": args.rooms,
        "held_out_rooms": list(held),
        "frames": int(fit_x.shape[0]),
        "steps": args.steps,
        "lr": args.lr,
        "distill_s": round(seconds, 1),
        "reproduced_variance_held_out": reproduced(sep, held_x, held_y),
        "reproduced_variance_fit": reproduced(sep, fit_x, fit_y),
    }
    print(json.dumps(report, indent=1))
    if args.json:
        write_json(args.json, report)


if __name__ == "__main__":
    main()
