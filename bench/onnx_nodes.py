"""Where a bundle's SCR inference spends its time: onnxruntime's own per-node profile of each graph, the nodes
named by the layer they compute (encoder.res2_conv3, head.fc1, ...), largest first, with the machine.

    PYTHONPATH=. python -P bench/onnx_nodes.py BUNDLE [--graphs fp32,int8,int8_vnni] [--runs 20] [--top 12]

The graphs run at the bundle's input size on a random frame (the time of a convolution does not depend on the
pixels), with the edge's session options (edge.inference.session_options).
"""

from __future__ import annotations

import argparse
import collections
import json
import re
import time
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort

from acesplat.core.bundle import PRECISION_ROLES, load_bundle
from acesplat.core.machine import machine_line
from edge.inference import session_options

SUFFIX = re.compile(r"(_token_\d+|_nchwc|_kernel_time)+$")


def layer_names(model: onnx.ModelProto) -> dict[str, str]:
    """Graph node (or output) name -> its layer: a Conv by its weight's name, a Relu or Add by the Conv before it."""
    made_by = {o: n for n in model.graph.node for o in n.output}
    names: dict[str, str] = {}

    def conv_layer(n: onnx.NodeProto) -> str | None:
        for _ in range(6):  # walk back through Relu/Add/Q/DQ to the Conv that feeds them
            if n.op_type == "Conv":
                w = n.input[1]
                return re.sub(r"^net\.|\.weight.*$", "", w)
            src = next((made_by[i] for i in n.input if i in made_by), None)
            if src is None:
                return None
            n = src
        return None

    for n in model.graph.node:
        layer = conv_layer(n) or n.op_type
        names[n.name] = layer
        for o in n.output:  # fused nodes are named after the tensor they produce (a Conv + Relu as 'relu_13')
            names.setdefault(o, layer)
    return names


def profile(path: Path, hw: tuple[int, int], runs: int) -> tuple[float, collections.Counter]:
    so = session_options()
    so.enable_profiling = True
    so.profile_file_prefix = str(Path("/tmp") / f"onnx_nodes_{path.stem}")
    sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    name = sess.get_inputs()[0].name
    x = np.random.default_rng(0).integers(0, 256, (1, 1, *hw)).astype(np.float32)
    for _ in range(3):
        sess.run(None, {name: x})
    t = time.perf_counter()
    for _ in range(runs):
        sess.run(None, {name: x})
    per_run = (time.perf_counter() - t) / runs * 1000.0
    trace = Path(sess.end_profiling())
    events = json.loads(trace.read_text())
    trace.unlink()
    layers = layer_names(onnx.load(str(path)))
    by_layer: collections.Counter = collections.Counter()
    for e in events:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            node = SUFFIX.sub("", e["name"])
            by_layer[layers.get(node, node)] += e["dur"] / 1000.0 / (runs + 3)
    return per_run, by_layer


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("bundle", type=Path)
    ap.add_argument("--graphs", default="fp32,int8,int8_vnni", help="the bundle's roles to profile, comma-separated")
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--top", type=int, default=12)
    args = ap.parse_args()
    b = load_bundle(args.bundle)
    hw = b.input_size
    print(machine_line())
    print(f"{args.bundle} at {hw[0]}x{hw[1]}, onnxruntime {ort.__version__}")
    for role in args.graphs.split(","):
        if PRECISION_ROLES.get(role) not in b.files:
            print(f"\n{role}: not in this bundle")
            continue
        path = b.scr_model(role)
        per_run, by_layer = profile(path, hw, args.runs)
        total = sum(by_layer.values())
        print(f"\n{role} ({path.name}): {per_run:.1f} ms a run; nodes {total:.1f} ms")
        for layer, ms in by_layer.most_common(args.top):
            print(f"  {ms:7.2f} ms  {100 * ms / total:5.1f}%  {layer}")


if __name__ == "__main__":
    main()
