"""The edge's splat initializer, before and after it took the SCR graph's features instead of the image.

Before (bundle format 1): one graph ran the SCR encoder, the feature adapter and the init head from the
grayscale image. After (format 2): the SCR graph outputs its encoder features beside the coordinates,
and the initializer is the adapter and head only. This script exports both initializers, and the SCR
graph, at one input size with random weights (the cost does not depend on the weights: the shipped
encoder's widths, Stage 1's head width and Stage 2's default adapter and head), and times them with
onnxruntime as the edge runs them: the initializer on one thread (the refinement worker's), the SCR
graph with coordinates only and with coordinates + features (what localization pays when refinement
is on). Runs are interleaved so machine load falls on all variants alike.

    python bench/bench_initializer.py [--size 240x320] [--runs 60] [--threads 1] [--json OUT]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import onnxruntime as ort  # noqa: E402
import torch  # noqa: E402

from acesplat.core.atomic import write_json  # noqa: E402
from acesplat.core.machine import machine_line  # noqa: E402
from acesplat.core.metrics import timing_stats  # noqa: E402
from acesplat.scr.encoders import load_encoder  # noqa: E402
from acesplat.scr.mapping import MappingConfig  # noqa: E402
from acesplat.scr.network import Head, SCRNetwork, normalize_gray  # noqa: E402
from acesplat.splat.instantiate import GaussianInitializer  # noqa: E402
from acesplat.splat.pipeline import SplatConfig  # noqa: E402
from acesplat.splatcore.head_io import PRIOR_CHANNELS  # noqa: E402
from export.onnx_graph import FEATURES_NAME, OUTPUT_NAME, export_scr_onnx  # noqa: E402
from export.splat_export import INIT_OUTPUT, _InitGraph, export_initializer_onnx  # noqa: E402


class ImageInitializer(torch.nn.Module):
    """The format 1 initializer: encoder + adapter + head from the image."""

    def __init__(self, net: SCRNetwork, init: GaussianInitializer, size_hw: tuple[int, int]) -> None:
        super().__init__()
        self.encoder, self.adapter, self.head = net.encoder, init.adapter, init.head
        self.size = size_hw

    def forward(self, gray: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
        return self.head(self.adapter(self.encoder(normalize_gray(gray)), *self.size), prior)


def export_image_initializer(graph: torch.nn.Module, size_hw: tuple[int, int], out: Path) -> None:
    h, w = size_hw
    torch.onnx.export(
        graph,
        (torch.full((1, 1, h, w), 128.0), torch.zeros((1, PRIOR_CHANNELS, h, w))),
        str(out),
        dynamo=True,
        external_data=False,
        opset_version=18,
        input_names=["gray", "prior"],
        output_names=[INIT_OUTPUT],
        verbose=False,
    )


def session(path: Path, threads: int) -> ort.InferenceSession:
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.log_severity_level = 3
    return ort.InferenceSession(str(path), sess_options=so, providers=["CPUExecutionProvider"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="240x320", help="Network input HxW (the built-in scene's bundle: 240x320).")
    ap.add_argument("--runs", type=int, default=60)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    h, w = (int(v) for v in args.size.lower().split("x"))
    torch.set_num_threads(1)
    torch.manual_seed(0)
    enc, _ = load_encoder(None)
    net = SCRNetwork(enc, Head(torch.zeros(3), enc.cfg.out, MappingConfig().head)).eval()
    cfg = SplatConfig()
    from acesplat.splat.adapter import AdapterConfig

    init = GaussianInitializer(AdapterConfig(enc.cfg.out, cfg.adapter_widths), cfg.head).eval()
    rng = np.random.default_rng(0)
    gray = rng.integers(0, 256, (1, 1, h, w)).astype(np.float32)
    prior = rng.normal(0, 0.5, (1, PRIOR_CHANNELS, h, w)).astype(np.float32)
    with tempfile.TemporaryDirectory() as td, torch.no_grad():
        root = Path(td)
        export_scr_onnx(net, (h, w), root / "scr.onnx")
        export_initializer_onnx(_InitGraph.make(init, (h, w)), (h, w), enc.cfg.out, PRIOR_CHANNELS, root / "init.onnx")
        export_image_initializer(ImageInitializer(net, init, (h, w)).eval(), (h, w), root / "init_image.onnx")
        scr = session(root / "scr.onnx", args.threads)
        new = session(root / "init.onnx", args.threads)
        old = session(root / "init_image.onnx", args.threads)
        feats = scr.run([FEATURES_NAME], {"gray": gray})[0]
        calls = {
            "initializer_image_in_ms": lambda: old.run(None, {"gray": gray, "prior": prior}),
            "initializer_features_in_ms": lambda: new.run(None, {"features": feats, "prior": prior}),
            "scr_coords_only_ms": lambda: scr.run([OUTPUT_NAME], {"gray": gray}),
            "scr_coords_and_features_ms": lambda: scr.run([OUTPUT_NAME, FEATURES_NAME], {"gray": gray}),
        }
        times: dict[str, list[float]] = {k: [] for k in calls}
        for f in calls.values():  # load and warm
            f()
        load_before = os.getloadavg()[0]
        for _ in range(args.runs):
            for k, f in calls.items():
                t0 = time.perf_counter()
                f()
                times[k].append(1000.0 * (time.perf_counter() - t0))
    stats = {k: timing_stats(v) for k, v in times.items()}
    print(f"machine: {machine_line()}; load before {load_before:.2f}, after {os.getloadavg()[0]:.2f}")
    print(
        f"input {h}x{w}, features {tuple(feats.shape[1:])}, {args.runs} interleaved runs, "
        f"{args.threads} onnxruntime thread(s)"
    )
    for k, s in stats.items():
        print(f"  {k:30s} p50 {s['p50']:7.2f}  p95 {s['p95']:7.2f}  mean {s['mean']:7.2f}")
    ratio = stats["initializer_image_in_ms"]["p50"] / stats["initializer_features_in_ms"]["p50"]
    extra = stats["scr_coords_and_features_ms"]["p50"] - stats["scr_coords_only_ms"]["p50"]
    print(
        f"initializer p50: image in / features in = {ratio:.1f}x; "
        f"SCR graph p50 with the features output: {extra:+.2f} ms"
    )
    if args.json:
        write_json(
            args.json,
            {
                "machine": machine_line(),
                "size": [h, w],
                "runs": args.runs,
                "threads": args.threads,
                "stats_ms": stats,
                "ratio_p50": ratio,
                "features_output_extra_p50_ms": extra,
            },
        )


if __name__ == "__main__":
    main()
