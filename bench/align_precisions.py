"""INT8 against FP32 after the keyframe alignment: per-frame pose differences under several AlignConfigs.

Each option replays the test split twice through the edge runtime (FP32, then INT8 of the same bundle, each frame
alone) with ``--align`` under that option, and prints how far the two poses of each frame end apart and how far
each is from the true pose (bench/align.md).

    PYTHONPATH=. python -P bench/align_precisions.py BUNDLE SCENE [--rounds 2,3,4]
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from acesplat.align.flow_pnp import KEYFRAME_ALIGN
from acesplat.core.bundle import load_bundle
from acesplat.core.geometry import pose_error
from acesplat.core.machine import machine_line
from edge.loop import run_loop
from edge.replay import split_folder
from edge.runtime import EdgeLocalizer, FrameOutcome
from edge.sources import ReplaySource


def replay(bundle, scene: str, precision: str, cfg) -> list[FrameOutcome]:
    loc = EdgeLocalizer(bundle, precision, align=True, align_config=cfg)
    outs: list[FrameOutcome] = []
    run_loop(ReplaySource(split_folder(scene, "test", need_poses=True)), loc, lambda o: outs.append(o.without_data()))
    return outs


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("bundle")
    ap.add_argument("scene")
    ap.add_argument("--rounds", default="2,3,4")
    a = ap.parse_args()
    print(machine_line())
    b = load_bundle(a.bundle)
    for rounds in (int(r) for r in a.rounds.split(",")):
        cfg = replace(KEYFRAME_ALIGN, rounds=rounds)
        fp32, int8 = (replay(b, a.scene, p, cfg) for p in ("fp32", "int8"))
        d = np.array([pose_error(x.result.T_c2w, y.result.T_c2w) for x, y in zip(fp32, int8, strict=True)])
        runs = {"fp32": fp32, "int8": int8}
        e = {n: [100 * pose_error(o.result.T_c2w, o.gt_pose)[0] for o in r] for n, r in runs.items()}
        ms = {n: np.median([o.times_ms["align"] for o in r]) for n, r in runs.items()}
        print(
            f"rounds {rounds}: INT8 vs FP32 {100 * np.median(d[:, 0]):.2f} / {100 * d[:, 0].max():.2f} cm, "
            f"{np.median(d[:, 1]):.3f} / {d[:, 1].max():.3f} deg; error FP32 {np.median(e['fp32']):.2f} / "
            f"{max(e['fp32']):.2f} cm, INT8 {np.median(e['int8']):.2f} / {max(e['int8']):.2f} cm; "
            f"align p50 {ms['fp32']:.0f} / {ms['int8']:.0f} ms"
        )


if __name__ == "__main__":
    main()
