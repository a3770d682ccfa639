"""How much of INT8's pure-SCR pose deviation from FP32 is the solver's, and how the robust refinement's scale
schedule moves it.

A bundle's FP32 and INT8 graphs predict the scene coordinates of a split's frames once (the edge's own frame
preparation); then, per schedule of the Cauchy refinement (acesplat.core.pose_refine) and per number of its steps
per scale, the edge's PnP (PnPSettings' 256 RANSAC iterations) solves every frame:
- with two RANSAC seeds on the FP32 coordinates: how far the pose moves with the random draws alone;
- on FP32 and INT8 coordinates with the shipped seed: the INT8-vs-FP32 pose difference;
- against the true poses.

    PYTHONPATH=. python -P bench/pnp_stability.py BUNDLE SCENE [--split test] [--json OUT]
"""

from __future__ import annotations

import argparse
import functools
import json
import time

import numpy as np

import acesplat.core.pnp as pnp_module
import acesplat.core.pose_refine as pose_refine
from acesplat.core.bundle import load_bundle
from acesplat.core.geometry import pose_error
from acesplat.core.machine import cpu_model
from acesplat.core.pnp import solve_from_grid
from acesplat.core.scene import split_folder
from edge.runtime import EdgeLocalizer, PnPSettings
from edge.sources import ReplaySource

SCHEDULES = ((4.0, 2.0, 1.0), (4.0, 2.0, 1.5), (4.0, 2.0), (8.0, 4.0, 2.0), (3.0,))
STEPS = (3, 10)
OTHER_SEED = 7


def predictions(bundle_dir: str, scene: str, split: str) -> tuple[dict, int]:
    """{precision: [(coords (h, w, 3), intrinsics, true pose (4, 4))]} over the split's frames, and the stride."""
    bundle = load_bundle(bundle_dir)
    source = ReplaySource(split_folder(scene, split, need_poses=True))
    frames = [source.read() for _ in range(len(source))]
    out = {}
    for precision in ("fp32", "int8"):
        loc = EdgeLocalizer(bundle, precision)
        out[precision] = []
        for f in frames:
            p = loc.prepare(f)
            out[precision].append((p.coords, p.intr, f.gt_pose))
    return out, bundle.output_stride


def solve(coords, intr, stride: int, scales: tuple[float, ...], seed: int):
    pnp_module.RANSAC_SEED = seed
    try:
        cfg = PnPSettings().config()
        return solve_from_grid(coords, intr, stride=stride, config=cfg, robust_scales=scales).T_c2w
    finally:
        pnp_module.RANSAC_SEED = 0


def measure(data: dict, stride: int, scales: tuple[float, ...], steps: int) -> dict:
    shipped = pose_refine.refine_pose_robust
    pnp_module.refine_pose_robust = functools.partial(shipped, steps_per_scale=steps)
    try:
        diff, jitter, err32, err8, ms = [], [], [], [], []
        for (c32, intr, gt), (c8, intr8, _) in zip(data["fp32"], data["int8"], strict=True):
            t0 = time.perf_counter()
            a = solve(c32, intr, stride, scales, 0)
            ms.append((time.perf_counter() - t0) * 1000.0)
            b = solve(c32, intr, stride, scales, OTHER_SEED)
            q = solve(c8, intr8, stride, scales, 0)
            if a is None or b is None or q is None:
                continue
            diff.append(pose_error(q, a)[0] * 100.0)
            jitter.append(pose_error(b, a)[0] * 100.0)
            err32.append(pose_error(a, gt)[0] * 100.0)
            err8.append(pose_error(q, gt)[0] * 100.0)
    finally:
        pnp_module.refine_pose_robust = shipped
    return {
        "scales": list(scales),
        "steps_per_scale": steps,
        "frames": len(diff),
        "int8_vs_fp32_cm": {"median": float(np.median(diff)), "max": float(np.max(diff))},
        "seed_jitter_cm": {"median": float(np.median(jitter)), "max": float(np.max(jitter))},
        "error_cm_fp32": float(np.median(err32)),
        "error_cm_int8": float(np.median(err8)),
        "solve_ms_p50": float(np.median(ms)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bundle")
    ap.add_argument("scene")
    ap.add_argument("--split", default="test")
    ap.add_argument("--json", default="")
    args = ap.parse_args()
    data, stride = predictions(args.bundle, args.scene, args.split)
    rows = []
    print(f"# {cpu_model()}; {len(data['fp32'])} frames of {args.scene} ({args.split})")
    print("| scales (px) | steps | INT8 vs FP32 median / max cm | seed jitter median / max cm | ", end="")
    print("error FP32 / INT8 cm | ms |")
    print("|---|---|---|---|---|---|")
    for scales in SCHEDULES:
        for steps in STEPS:
            r = measure(data, stride, scales, steps)
            rows.append(r)
            d, j = r["int8_vs_fp32_cm"], r["seed_jitter_cm"]
            print(
                f"| {', '.join(f'{s:g}' for s in scales)} | {steps} | {d['median']:.2f} / {d['max']:.2f} | "
                f"{j['median']:.2f} / {j['max']:.2f} | {r['error_cm_fp32']:.2f} / {r['error_cm_int8']:.2f} | "
                f"{r['solve_ms_p50']:.1f} |",
                flush=True,
            )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"bundle": args.bundle, "scene": args.scene, "cpu": cpu_model(), "rows": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
