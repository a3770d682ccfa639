"""The overlapped loop against the sequential one: poses a second, latency and poses, measured in one process.

    PYTHONPATH=. python -P bench/pipeline.py BUNDLE SCENE [--split test] [--precision int8] [--modes scr,align,track]
        [--passes 3] [--rounds 3] [--json OUT]

Per mode (scr: frames alone; align: --align; track: tracking on, as `replay` by default) and per loop (sequential
with onnxruntime on every core; overlapped with every core but one, edge.loop.overlap_threads), ``rounds``
alternating runs of ``passes`` replays of the split each. A replay's frames are solved in order; passes are separate
replays (a split replayed twice would go back in time). Reported per run: poses a second (frames over the loops'
seconds), end-to-end latency p50 / p95 (capture start to pose, edge.runtime's total, the wait for the solving thread
included) and the median error of the last pass. The ratio row divides the medians over rounds.
"""

from __future__ import annotations

import argparse
import gc
import json
import statistics
import sys
from pathlib import Path

import numpy as np

from acesplat.core.bundle import load_bundle
from edge.inference import default_threads, runtime_info
from edge.loop import overlap_threads
from edge.replay import replay_split
from edge.runtime import EdgeLocalizer
from edge.tracking import TrackingConfig

LOOPS = ("sequential", "overlapped")


def one_run(bundle, scene: str, split: str, precision: str, mode: str, loop: str, passes: int) -> dict:
    overlap = loop == "overlapped"
    threads = overlap_threads() if overlap else default_threads()
    loc = EdgeLocalizer(
        bundle, precision, threads, align=mode == "align", tracking=TrackingConfig() if mode == "track" else None
    )
    frames, seconds, totals = 0, 0.0, []
    last = {}
    for _ in range(passes):
        s = replay_split(loc, scene, split, overlap=overlap)
        frames += s["frames"]
        seconds += s["frames"] / s["poses_per_s"] if s["poses_per_s"] > 0 else 0.0
        totals += [f["ms"] for f in s["per_frame"]]
        last = s
    del loc
    gc.collect()  # an idle onnxruntime session's threads must not spin beside the next run's
    return {
        "poses_per_s": frames / seconds,
        "p50_ms": float(np.percentile(totals, 50)),
        "p95_ms": float(np.percentile(totals, 95)),
        "median_cm": 100.0 * last["median_translation_m"],
        "localized": last["localized"],
        "frames": last["frames"],
        "threads": threads,
        "tracked": last["tracked"],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bundle")
    ap.add_argument("scene")
    ap.add_argument("--split", default="test")
    ap.add_argument(
        "--precision", default="int8", help="fp32, int8 (the U8U8 graph an AVX2 CPU runs) or int8_vnni (U8S8)."
    )
    ap.add_argument("--modes", default="scr,align")
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    b = load_bundle(a.bundle)
    precision = a.precision
    rows: dict[str, dict[str, list[dict]]] = {}
    for mode in a.modes.split(","):
        rows[mode] = {loop: [] for loop in LOOPS}
        for r in range(a.rounds):
            order = LOOPS if r % 2 == 0 else LOOPS[::-1]
            for loop in order:
                res = one_run(b, a.scene, a.split, precision, mode, loop, a.passes)
                rows[mode][loop].append(res)
                print(
                    f"{mode:6s} {loop:11s} round {r}: {res['poses_per_s']:5.1f} poses/s, p50 {res['p50_ms']:6.1f} "
                    f"p95 {res['p95_ms']:6.1f} ms, median {res['median_cm']:.2f} cm, "
                    f"{res['localized']}/{res['frames']} localized ({res['threads']} threads)",
                    flush=True,
                )
    print()
    print("| mode | loop | poses/s (median of rounds) | p50 ms | p95 ms | median error | rounds: poses/s |")
    print("|---|---|---|---|---|---|---|")
    summary = {}
    for mode, by_loop in rows.items():
        med = {
            loop: {k: statistics.median(x[k] for x in runs) for k in ("poses_per_s", "p50_ms", "p95_ms", "median_cm")}
            for loop, runs in by_loop.items()
        }
        summary[mode] = med
        for loop, runs in by_loop.items():
            m = med[loop]
            each = " ".join(f"{x['poses_per_s']:.1f}" for x in runs)
            print(
                f"| {mode} | {loop} | {m['poses_per_s']:.1f} | {m['p50_ms']:.1f} | {m['p95_ms']:.1f} | "
                f"{m['median_cm']:.2f} cm | {each} |"
            )
        s, o = med["sequential"], med["overlapped"]
        print(
            f"| {mode} | overlapped / sequential | {o['poses_per_s'] / s['poses_per_s']:.2f}x | "
            f"{o['p50_ms'] / s['p50_ms']:.2f}x | {o['p95_ms'] / s['p95_ms']:.2f}x | | |"
        )
    info = runtime_info("cpu")
    isa = " ".join(info["cpu_isa"])
    print(f"\nonnxruntime {info['onnxruntime']}, ISA {isa}, {default_threads()} cores, {precision}")
    if a.json:
        a.json.write_text(json.dumps({"runs": rows, "median": summary, "precision": precision, **info}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
