"""How heavy an encoder the edge can afford: multiply-accumulates and measured latency of candidate widths.

Prints, for each candidate encoder with the default head (width 256, 1 block), GMAC and torch / onnxruntime
FP32 milliseconds per frame at the mapping resolutions, from one run, with ratios to ACE's encoder.
The accuracy side of the choice is in bench/encoder_choice.md (pretraining every candidate costs hours).

    python bench/encoder_choice.py [--repeats 10]
"""

from __future__ import annotations

import argparse
import io
import time

import numpy as np
import torch

from acesplat.core.machine import machine_line
from acesplat.scr.network import ACE_ENCODER, Encoder, EncoderConfig, Head, HeadConfig, SCRNetwork, count_macs
from acesplat.scr.pretrain import EDGE_ENCODER

CANDIDATES = {
    "ace": ACE_ENCODER,
    "mid (3/4)": EncoderConfig(24, 48, 96, 192, 384, 512),
    "edge (1/2, default)": EDGE_ENCODER,
    "quarter": EncoderConfig(8, 16, 32, 64, 128, 512),
}
SIZES = [(240, 320), (360, 480), (480, 640)]


def time_torch(net: torch.nn.Module, hw: tuple[int, int], repeats: int) -> float:
    x = torch.rand(1, 1, *hw) * 255
    with torch.no_grad():
        net(x)
        t = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            net(x)
            t.append(time.perf_counter() - t0)
    return 1000 * float(np.median(t))


def time_ort(net: torch.nn.Module, hw: tuple[int, int], repeats: int) -> float:
    import onnxruntime as ort

    buf = io.BytesIO()
    x = torch.rand(1, 1, *hw) * 255
    torch.onnx.export(net, (x,), buf, input_names=["image"], output_names=["coords"], dynamo=True, external_data=False)
    so = ort.SessionOptions()
    so.intra_op_num_threads = torch.get_num_threads()
    sess = ort.InferenceSession(buf.getvalue(), so, providers=["CPUExecutionProvider"])
    feed = {"image": x.numpy()}
    sess.run(None, feed)
    t = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sess.run(None, feed)
        t.append(time.perf_counter() - t0)
    return 1000 * float(np.median(t))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--no-onnx", action="store_true")
    args = ap.parse_args()
    print(f"machine: {machine_line()}")
    print(f"{'encoder':22s} {'HxW':>8s} {'GMAC':>6s} {'torch ms':>9s} {'ort ms':>7s} {'vs ACE':>7s}")
    base = {}
    for name, cfg in CANDIDATES.items():
        net = SCRNetwork(Encoder(cfg), Head(torch.zeros(3), cfg.out, HeadConfig(256, 1))).eval()
        for hw in SIZES:
            macs = count_macs(cfg, HeadConfig(256, 1), *hw)
            g = macs["encoder_gmac"] + macs["head_gmac"]
            tt = time_torch(net, hw, args.repeats)
            to = float("nan") if args.no_onnx else time_ort(net, hw, args.repeats)
            ref = base.setdefault(hw, to if not args.no_onnx else tt)
            ratio = (to if not args.no_onnx else tt) / ref
            print(f"{name:22s} {hw[0]:>3d}x{hw[1]:<4d} {g:6.2f} {tt:9.1f} {to:7.1f} {ratio:7.2f}")


if __name__ == "__main__":
    main()
