"""Cost of the mapping loop's two compute parts in the layouts torch offers on CPU.

1. One head training step (batch 5120, forward + backward + AdamW). The mapping loop trains the head on a
   flat batch of buffered features. The same network can run as 1x1 convolutions over a (1, C, N, 1)
   tensor (how ACE writes it) or as matrix products over (N, C); on CPUs with AVX512-BF16/AMX the hidden
   layers can also run in bfloat16.
2. With ``--loop N``: N steps of the mapping loop itself (``train_head``: sampling from a float16 buffer of 1M
   features, the reprojection and target losses, AdamW) over a synthetic buffer.
3. The encoder pass that fills the feature buffer (one image at the built-in scene's 240x320), in float32
   and under bfloat16 autocast with contiguous or channels-last tensors, with the relative feature error.

Each part prints its times measured in one run as ratios to the first layout, plus the machine.

    python bench/head_speed.py [--width 256] [--blocks 1] [--steps 20] [--threads 0] [--loop 300] [--compile]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from acesplat.core.config import knob_default
from acesplat.core.machine import machine_line
from acesplat.scr.encoders import load_encoder
from acesplat.scr.mapping import MappingConfig, train_head
from acesplat.scr.network import Head, HeadConfig, normalize_gray

BATCH_SIZE = knob_default(MappingConfig, "batch_size")


_COMPILED: dict[int, object] = {}


def compiled(head: Head):
    """``torch.compile`` of the head's matrix-product forward, compiled once per head (the first call compiles)."""
    if id(head) not in _COMPILED:
        _COMPILED[id(head)] = torch.compile(head.forward_points)
    return _COMPILED[id(head)]


def step_times(head: Head, feats: torch.Tensor, layout: str, steps: int) -> list[float]:
    opt = torch.optim.AdamW(head.parameters(), lr=1e-4)
    times = []
    for k in range(steps + 3):
        t = time.perf_counter()
        if layout == "conv":
            pred = head(feats.T[None, :, :, None])[0, :, :, 0].T
        elif layout == "linear-compiled":
            pred = compiled(head)(feats)
        else:
            pred = head.forward_points(feats, autocast_bf16=layout == "linear-bf16")
        loss = pred.abs().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if k >= 3:  # the first steps allocate and pick kernels
            times.append(time.perf_counter() - t)
    return times


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--blocks", type=int, default=1)
    ap.add_argument("--in-channels", type=int, default=512)
    ap.add_argument("--batch", type=int, default=BATCH_SIZE)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0 = all cores)")
    ap.add_argument("--loop", type=int, default=0, help="also time this many steps of train_head (0 = skip)")
    ap.add_argument("--compile", action="store_true", help="also time the step with torch.compile'd forward")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    feats = torch.randn(args.batch, args.in_channels)
    layouts = ["conv", "linear"]
    if torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported():
        layouts.append("linear-bf16")
    if args.compile:
        layouts += ["linear-compiled", "linear"]  # eager again after it, so drift shows
    print(machine_line())
    print(f"head width {args.width}, blocks {args.blocks}, batch {args.batch}, torch threads {torch.get_num_threads()}")
    base = None
    for layout in layouts:
        head = Head(torch.zeros(3), args.in_channels, HeadConfig(args.width, args.blocks))
        ts = step_times(head, feats, layout, args.steps)
        med = statistics.median(ts)
        base = base or med
        print(
            f"{layout:12s} median {med * 1000:7.1f} ms/step  (min {min(ts) * 1000:6.1f})  time ratio {med / base:5.2f}"
        )
    if args.loop:
        loop_time(args.width, args.blocks, args.in_channels, args.batch, args.loop)
    if "linear-bf16" in layouts:
        encoder_times(args.steps)


def loop_time(width: int, blocks: int, in_channels: int, batch: int, steps: int, n: int = 1_000_000) -> None:
    """train_head over a synthetic buffer of ``n`` features from 200 views, a tenth with triangulated targets."""
    g = torch.Generator().manual_seed(0)
    views = 200
    buf = {
        "feats": torch.randn(n, in_channels, generator=g).to(torch.float16),
        "pixels": torch.rand(n, 2, generator=g) * 300,
        "view": torch.randint(0, views, (n,), generator=g),
        "target": torch.full((n, 3), float("nan")),
        "w2c": torch.eye(4)[:3].expand(views, 3, 4).clone(),
        "K": torch.tensor([[200.0, 0, 160], [0, 200, 120], [0, 0, 1]]).expand(views, 3, 3).clone(),
    }
    buf["target"][::10] = torch.randn(n // 10, 3, generator=g)
    cfg = MappingConfig(iterations=steps, batch_size=batch, head=HeadConfig(width, blocks), precision="fp32")
    head = Head(torch.zeros(3), in_channels, cfg.head)
    t = time.perf_counter()
    train_head(head, buf, cfg)
    print(f"train_head   {(time.perf_counter() - t) / steps * 1000:7.1f} ms/step over {steps} steps (fp32)")


@torch.no_grad()
def encoder_times(steps: int, hw: tuple[int, int] = (240, 320)) -> None:
    encoder, _ = load_encoder(None)
    encoder.eval()
    x = normalize_gray(torch.randint(0, 256, (1, 1, *hw)).float())
    ref = encoder(x)
    print(f"encoder (shipped default) on one {hw[0]}x{hw[1]} image")
    base = None
    for name, bf16, layout in (
        ("fp32", False, torch.contiguous_format),
        ("bf16", True, torch.contiguous_format),
        ("bf16-chlast", True, torch.channels_last),
    ):
        encoder.to(memory_format=layout)
        xi = x.contiguous(memory_format=layout)
        ts = []
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            for k in range(steps + 3):
                t = time.perf_counter()
                y = encoder(xi)
                if k >= 3:
                    ts.append(time.perf_counter() - t)
        med = statistics.median(ts)
        base = base or med
        err = float((y.float() - ref).norm() / ref.norm())
        print(
            f"{name:12s} median {med * 1000:7.1f} ms/image (min {min(ts) * 1000:6.1f})  time ratio {med / base:5.2f}"
            f"  relative feature error {err:.4f}"
        )


if __name__ == "__main__":
    main()
