"""Can a head fine-tuned on the INT8 encoder's features undo the encoder's quantization error?

Quantizes the bundle's FP32 graph with the whole head in float (U8U8, the default scheme otherwise), takes the
encoder's dequantized features on the training images, and fine-tunes a copy of the map's head to map them to the
FP32 graph's coordinates (Cauchy loss at 5 cm, Adam, one training image a step). Prints the test frames' coordinate
deviation from FP32 (median / p90) and the PnP pose's deviation from the FP32 pose, for the default INT8 graph, the
head-float graph and the tuned head; the test frames are never used to tune.

    python bench/int8_head_tune.py MAP SCENE BUNDLE [--steps 400] [--lr 3e-5]
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from acesplat.core.geometry import pose_error
from acesplat.core.machine import machine_line
from acesplat.core.pnp import solve_from_grid
from acesplat.core.scene import read_split
from acesplat.scr.mapfile import load_map
from edge.inference import session_options
from export.bundle_export import default_size, evenly
from export.checks import onnx_outputs, prepare_frames
from export.quantize import quantize_int8

CAUCHY_SCALE_M = 0.05
"""Scale of the tuning loss: cells within a few centimetres of FP32 are what the pose uses."""


def _session(path: Path) -> ort.InferenceSession:
    return ort.InferenceSession(str(path), session_options(spinning=False), providers=["CPUExecutionProvider"])


def _coords(head: torch.nn.Module, feats: np.ndarray) -> np.ndarray:
    """(h, w, 3) coordinates of ``head`` on (C, h, w) features."""
    with torch.no_grad():
        return head(torch.from_numpy(feats)[None])[0].permute(1, 2, 0).numpy()


def _report(name: str, preds: list[np.ndarray], refs: list[np.ndarray], frames: list) -> None:
    d = np.concatenate([np.linalg.norm(p - r, axis=-1).ravel() for p, r in zip(preds, refs, strict=True)])
    d = d[np.isfinite(d)]
    pe = []
    for p, r, f in zip(preds, refs, frames, strict=True):
        a, b = solve_from_grid(p, f.intrinsics).T_c2w, solve_from_grid(r, f.intrinsics).T_c2w
        if a is not None and b is not None:
            pe.append(100 * pose_error(a, b)[0])
    print(
        f"{name:28s} coord median {100 * np.median(d):.2f} p90 {100 * np.percentile(d, 90):.2f} cm | "
        f"pose vs FP32 median {np.median(pe):.2f} max {np.max(pe):.2f} cm",
        flush=True,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("map", type=Path)
    ap.add_argument("scene", type=Path)
    ap.add_argument("bundle", type=Path)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--lr", type=float, default=3e-5)
    ap.add_argument("--work", type=Path, default=Path("runs/int8_head_tune"))
    args = ap.parse_args()
    print(machine_line())
    torch.manual_seed(0)
    m = load_map(args.map)
    size = default_size(args.scene, m.short_side, args.map)
    train = prepare_frames(read_split(args.scene, "train").frames, size)
    test = prepare_frames(read_split(args.scene, "test").frames, size)
    args.work.mkdir(parents=True, exist_ok=True)
    fp32 = args.bundle / "scr.onnx"
    head_float = args.work / f"{args.bundle.name}.head_float.onnx"
    quantize_int8(fp32, head_float, [f.gray for f in evenly(train, 32)], types="u8u8", float_convs=10)
    s_fp32, s_hf, s_def = _session(fp32), _session(head_float), _session(args.bundle / "scr.int8.onnx")

    def run(frames: list) -> tuple[list, list, list, list]:
        ref, hf, feats, default = [], [], [], []
        for f in frames:
            ref.append(onnx_outputs(s_fp32, f.gray)[0])
            c, x = onnx_outputs(s_hf, f.gray, features=True)
            hf.append(c)
            feats.append(x)
            default.append(onnx_outputs(s_def, f.gray)[0])
        return ref, hf, feats, default

    tr_ref, tr_hf, tr_feats, _ = run(train)
    te_ref, te_hf, te_feats, te_def = run(test)
    _report("test: default INT8 graph", te_def, te_ref, test)
    _report("test: INT8, head float", te_hf, te_ref, test)
    _report("train: INT8, head float", tr_hf, tr_ref, train)
    tuned = copy.deepcopy(m.head).train()
    params = [p for p in tuned.parameters() if p.is_floating_point()]
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=args.lr)
    xs = [torch.from_numpy(x)[None] for x in tr_feats]
    ys = [torch.from_numpy(r).permute(2, 0, 1)[None] for r in tr_ref]
    t0 = time.monotonic()
    for step in range(args.steps):
        i = step % len(xs)
        dist = (tuned(xs[i]) - ys[i]).norm(dim=1)
        loss = torch.log1p((dist[torch.isfinite(dist)] / CAUCHY_SCALE_M) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if (step + 1) % max(1, args.steps // 4) == 0:
            tuned.eval()
            _report(f"test: tuned head, step {step + 1}", [_coords(tuned, x) for x in te_feats], te_ref, test)
            tuned.train()
    tuned.eval()
    print(f"tuning {time.monotonic() - t0:.0f} s")
    _report("train: tuned head", [_coords(tuned, x) for x in tr_feats], tr_ref, train)


if __name__ == "__main__":
    main()
