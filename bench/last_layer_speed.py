"""What the encoder's last 3x3 layer costs in onnxruntime, built full, as a rank-128 pair, separable, grouped or 1x1.

Each variant replaces ``res2_conv3`` of the shipped encoder (random weights: the time does not depend on them), with
the default head (width 256, one block), exported at 360x544 and quantized U8U8 and U8S8 as the export does, then
timed alone on one session at a time with the edge's session options (spinning off, so that idle sessions do not
take the cores), median of the runs after three warm-ups:

    python bench/last_layer_speed.py [--variants full,r128,pwdw,g4,g2,pw] [--runs 20] [--work runs/last_layer]
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort
import torch
import torch.nn as nn

from acesplat.core.machine import machine_line
from acesplat.scr.encoders import load_encoder
from acesplat.scr.network import FactorizedConv2d, Head, HeadConfig, SCRNetwork, SeparableConv2d
from edge.inference import session_options
from export.onnx_graph import export_scr_onnx
from export.quantize import quantize_int8

SIZE_HW = (360, 544)
"""The default bundle size of the shared scenes (360 short side)."""


def variant(name: str, c_in: int, c_out: int, full: nn.Module) -> nn.Module:
    """``res2_conv3`` as ``name``: full, r128 (rank-128 pair), pwdw (separable), gN (3x3 in N groups), pw (1x1)."""
    if name == "full":
        return full
    if name == "r128":
        return FactorizedConv2d(c_in, c_out, 128, 3)
    if name == "pwdw":
        return SeparableConv2d(c_in, c_out, 3)
    if name == "pw":
        return nn.Conv2d(c_in, c_out, 1)
    if name.startswith("g") and name[1:].isdigit():
        return nn.Conv2d(c_in, c_out, 3, 1, 1, groups=int(name[1:]))
    raise ValueError(f"unknown variant {name!r}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", default="full,r128,pwdw,g4,g2,pw")
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--work", type=Path, default=Path("runs/last_layer"))
    ap.add_argument("--calibration", type=Path, default=Path("../shared/data/herzjesu25/train/rgb"))
    args = ap.parse_args()
    print(machine_line())
    torch.manual_seed(0)
    enc, _ = load_encoder()
    full = enc.res2_conv3
    c_out, c_in = full.weight.shape[:2]
    h, w = SIZE_HW
    images = sorted(args.calibration.iterdir())[:6]
    calib = [cv2.resize(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), (w, h), interpolation=cv2.INTER_AREA) for p in images]
    args.work.mkdir(parents=True, exist_ok=True)
    names = args.variants.split(",")
    paths: dict[str, dict[str, Path]] = {}
    for n in names:
        e = copy.deepcopy(enc)
        e.res2_conv3 = variant(n, c_in, c_out, full)
        net = SCRNetwork(e, Head(torch.zeros(3), c_out, HeadConfig(width=256, blocks=1))).eval()
        fp32 = export_scr_onnx(net, SIZE_HW, args.work / f"{n}.onnx")
        paths[n] = {
            "fp32": fp32,
            "u8u8": quantize_int8(fp32, args.work / f"{n}.u8u8.onnx", calib, types="u8u8"),
            "u8s8": quantize_int8(fp32, args.work / f"{n}.u8s8.onnx", calib, types="u8s8"),
        }
    x = calib[0][None, None].astype(np.float32)
    for n in names:
        row = []
        for kind, p in paths[n].items():
            s = ort.InferenceSession(str(p), session_options(spinning=False), providers=["CPUExecutionProvider"])
            feed = {s.get_inputs()[0].name: x}
            times = []
            for i in range(args.runs + 3):
                t0 = time.perf_counter()
                s.run(None, feed)
                if i >= 3:
                    times.append(1e3 * (time.perf_counter() - t0))
            row.append(f"{kind} {np.median(times):.1f} ms")
            del s
        print(f"{n:5s} " + "  ".join(row), flush=True)


if __name__ == "__main__":
    main()
