"""INT8 against FP32 after the keyframe alignment: per-frame pose differences under several AlignConfigs.

Each option replays the test split twice through the edge runtime (FP32, then INT8 of the same bundle, each frame
alone) with ``--align`` under that option, and prints how far the two poses of each frame end apart and how far
each is from the true pose (bench/align.md). ``--int8`` picks the INT8 graph: ``int8`` is the U8U8 default (the
graph an AVX2 CPU without VNNI keeps), ``int8_vnni`` the U8S8 twin.

    PYTHONPATH=. python -P bench/align_precisions.py BUNDLE SCENE [--rounds 2,3,4]
    PYTHONPATH=. python -P bench/align_precisions.py BUNDLE SCENE --configs "rounds=1;rounds=3,converged_m=0.002"
"""

from __future__ import annotations

import argparse
import json
from dataclasses import fields, replace

import numpy as np

from acesplat.align.flow_pnp import KEYFRAME_ALIGN, AlignConfig
from acesplat.core.bundle import load_bundle
from acesplat.core.geometry import pose_error
from acesplat.core.machine import machine_line
from edge.loop import run_loop
from edge.replay import split_folder
from edge.runtime import EdgeLocalizer, FrameOutcome
from edge.sources import ReplaySource


def replay(bundle, scene: str, precision: str, cfg: AlignConfig) -> list[FrameOutcome]:
    loc = EdgeLocalizer(bundle, precision, align=True, align_config=cfg)
    outs: list[FrameOutcome] = []
    run_loop(ReplaySource(split_folder(scene, "test", need_poses=True)), loc, lambda o: outs.append(o.without_data()))
    return outs


def parse_config(text: str) -> AlignConfig:
    """'rounds=3,converged_m=0.002' -> KEYFRAME_ALIGN with those fields (types from the dataclass's defaults)."""
    kinds = {f.name: type(getattr(KEYFRAME_ALIGN, f.name)) for f in fields(AlignConfig)}
    changes = {}
    for item in filter(None, text.split(",")):
        name, value = item.split("=")
        kind = float if kinds[name.strip()] is type(None) else kinds[name.strip()]
        v = value.strip()
        changes[name.strip()] = None if v.lower() == "none" else (v.lower() == "true") if kind is bool else kind(v)
    return replace(KEYFRAME_ALIGN, **changes)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("bundle")
    ap.add_argument("scene")
    ap.add_argument("--rounds", default="", help="shorthand: rounds=N configs, comma-separated counts")
    ap.add_argument("--configs", default="", help="AlignConfig changes, configs separated by ';' ('' = default)")
    ap.add_argument("--int8", default="int8", choices=("int8", "int8_vnni"))
    ap.add_argument("--per-frame", action="store_true")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    print(machine_line())
    b = load_bundle(a.bundle)
    configs = [f"rounds={r}" for r in filter(None, a.rounds.split(","))] + a.configs.split(";")
    configs = [c for c in configs if c] or [""]
    rows = []
    for text in configs:
        cfg = parse_config(text)
        fp32, int8 = (replay(b, a.scene, p, cfg) for p in ("fp32", a.int8))
        d = np.array([pose_error(x.result.T_c2w, y.result.T_c2w) for x, y in zip(fp32, int8, strict=True)])
        runs = {"fp32": fp32, "int8": int8}
        e = {n: [100 * pose_error(o.result.T_c2w, o.gt_pose)[0] for o in r] for n, r in runs.items()}
        ms = {n: float(np.median([o.times_ms["align"] for o in r])) for n, r in runs.items()}
        print(
            f"[{text or 'default'}] {a.int8} vs FP32 {100 * np.median(d[:, 0]):.2f} / {100 * d[:, 0].max():.2f} cm, "
            f"{np.median(d[:, 1]):.3f} / {d[:, 1].max():.3f} deg; error FP32 {np.median(e['fp32']):.2f} / "
            f"{max(e['fp32']):.2f} cm, INT8 {np.median(e['int8']):.2f} / {max(e['int8']):.2f} cm; "
            f"align p50 {ms['fp32']:.0f} / {ms['int8']:.0f} ms",
            flush=True,
        )
        if a.per_frame:
            for i, (x, y) in enumerate(zip(fp32, int8, strict=True)):
                print(
                    f"  frame {i}: apart {100 * d[i, 0]:.2f} cm {d[i, 1]:.3f} deg; error FP32 {e['fp32'][i]:.2f} "
                    f"INT8 {e['int8'][i]:.2f} cm; align {x.alignment} / {y.alignment}"
                )
        rows.append(
            {
                "config": text,
                "apart_cm": (100 * d[:, 0]).tolist(),
                "apart_deg": d[:, 1].tolist(),
                "error_cm": e,
                "align_ms_p50": ms,
            }
        )
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"machine": machine_line(), "int8": a.int8, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
