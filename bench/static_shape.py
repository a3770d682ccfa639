"""Does fixing the SCR graph's free input dimensions at the bundle size make onnxruntime faster, and does asking for
the features as well as the coordinates cost anything? The same graph in two sessions, dynamic and with the
dimensions overridden (SessionOptions.add_free_dimension_override_by_name), and the dynamic one asked for every
output, timed alternately in one process.

    PYTHONPATH=. python -P bench/static_shape.py BUNDLE [--graph int8] [--rounds 6] [--runs 10]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import onnxruntime as ort

from acesplat.core.bundle import load_bundle
from acesplat.core.machine import machine_line
from edge.inference import session_options


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bundle")
    ap.add_argument("--graph", default="int8", help="fp32, int8 or int8_vnni")
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--runs", type=int, default=10)
    a = ap.parse_args()
    b = load_bundle(a.bundle)
    path, (h, w) = str(b.scr_model(a.graph)), b.input_size
    sessions = {}
    for kind in ("dynamic", "static"):
        so = session_options(spinning=False)  # two sessions in one process: an idle one must not spin
        if kind == "static":
            dims = ort.InferenceSession(path, session_options(1), providers=["CPUExecutionProvider"]).get_inputs()[0]
            so.add_free_dimension_override_by_name(dims.shape[2], h)
            so.add_free_dimension_override_by_name(dims.shape[3], w)
        sessions[kind] = ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])
    name = sessions["dynamic"].get_inputs()[0].name
    x = {name: (np.random.default_rng(0).random((1, 1, h, w)) * 255).astype(np.float32)}
    first = [sessions["dynamic"].get_outputs()[0].name]
    every = [o.name for o in sessions["dynamic"].get_outputs()]
    kinds = {"dynamic": ("dynamic", first), "static": ("static", first), "all outputs": ("dynamic", every)}
    res: dict[str, list[float]] = {k: [] for k in kinds}
    for r in range(a.rounds):
        for kind in list(kinds) if r % 2 == 0 else list(kinds)[::-1]:
            session, outputs = kinds[kind]
            s = sessions[session]
            for _ in range(2):
                s.run(outputs, x)
            t = []
            for _ in range(a.runs):
                t0 = time.perf_counter()
                s.run(outputs, x)
                t.append((time.perf_counter() - t0) * 1000.0)
            res[kind].append(float(np.median(t)))
    print(f"# {machine_line()}")
    print(f"{a.bundle} {a.graph} at {h}x{w}; median of {a.runs} runs per round, {a.rounds} rounds")
    for kind, v in res.items():
        print(f"{kind:12s} {float(np.median(v)):6.1f} ms  (rounds: {' '.join(f'{x:.1f}' for x in v)})")


if __name__ == "__main__":
    main()
