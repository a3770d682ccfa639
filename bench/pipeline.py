"""The edge loop's ways of running, measured in one process: sequential or overlapped (edge.loop), onnxruntime's
threads spinning or sleeping between operators (SessionSettings.spinning); poses a second, latency and poses.

    PYTHONPATH=. python -P bench/pipeline.py BUNDLE SCENE [--split test] [--precision int8] [--modes scr,align,track]
        [--variants sequential:on,sequential:off,overlapped:on] [--passes 3] [--rounds 3] [--json OUT]

Per mode (scr: frames alone; align: --align; track: tracking on, as `replay` by default) and per variant (the loop:
sequential with onnxruntime on every core, overlapped with every core but one, edge.loop.overlap_threads; and
spinning on or off), ``rounds`` rounds, the variants' order reversed every other round, of ``passes`` replays of the
split each. A replay's frames are solved in order; passes are separate replays (a split replayed twice would go
back in time). Reported per run: poses a second (frames over the loops' seconds), end-to-end latency p50 / p95
(capture start to pose, edge.runtime's total, any wait for the solving thread included), the inference stage's p50
and the median error of the last pass. Ratios divide medians over rounds by the first variant's.
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

KEYS = ("poses_per_s", "p50_ms", "p95_ms", "inference_p50_ms", "median_cm")


def one_run(bundle, scene: str, split: str, precision: str, mode: str, variant: str, passes: int) -> dict:
    loop, spin = variant.split(":")
    overlap = loop == "overlapped"
    threads = overlap_threads() if overlap else default_threads()
    loc = EdgeLocalizer(
        bundle,
        precision,
        threads,
        align=mode == "align",
        tracking=TrackingConfig() if mode == "track" else None,
        spinning=spin == "on",
    )
    frames, seconds, totals, inference = 0, 0.0, [], []
    last = {}
    for _ in range(passes):
        s = replay_split(loc, scene, split, overlap=overlap)
        frames += s["frames"]
        seconds += s["seconds"]
        totals += [f["ms"] for f in s["per_frame"]]
        inference.append(s["timing_ms"]["inference"]["p50"])
        last = s
    del loc
    gc.collect()  # an idle onnxruntime session's threads must not spin beside the next run's
    return {
        "poses_per_s": frames / seconds,
        "p50_ms": float(np.percentile(totals, 50)),
        "p95_ms": float(np.percentile(totals, 95)),
        "inference_p50_ms": float(np.median(inference)),
        "median_cm": 100.0 * last["median_translation_m"],
        "localized": last["localized"],
        "frames": last["frames"],
        "threads": threads,
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
    ap.add_argument("--variants", default="sequential:on,sequential:off,overlapped:on")
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    variants = a.variants.split(",")
    for v in variants:
        loop, _, spin = v.partition(":")
        if loop not in ("sequential", "overlapped") or spin not in ("on", "off"):
            ap.error(f"a variant is sequential|overlapped:on|off, got {v!r}")
    b = load_bundle(a.bundle)
    rows: dict[str, dict[str, list[dict]]] = {}
    for mode in a.modes.split(","):
        rows[mode] = {v: [] for v in variants}
        for r in range(a.rounds):
            for v in variants if r % 2 == 0 else variants[::-1]:
                res = one_run(b, a.scene, a.split, a.precision, mode, v, a.passes)
                rows[mode][v].append(res)
                print(
                    f"{mode:6s} {v:16s} round {r}: {res['poses_per_s']:5.1f} poses/s, p50 {res['p50_ms']:6.1f} "
                    f"p95 {res['p95_ms']:6.1f} ms, inference p50 {res['inference_p50_ms']:5.1f} ms, "
                    f"median {res['median_cm']:.2f} cm, {res['localized']}/{res['frames']} localized "
                    f"({res['threads']} threads)",
                    flush=True,
                )
    print()
    print("| mode | loop:spinning | poses/s | p50 ms | p95 ms | inference p50 ms | median error | rounds: poses/s |")
    print("|---|---|---|---|---|---|---|---|")
    summary = {}
    for mode, by_variant in rows.items():
        med = {v: {k: statistics.median(x[k] for x in runs) for k in KEYS} for v, runs in by_variant.items()}
        summary[mode] = med
        base = med[variants[0]]
        for v, runs in by_variant.items():
            m = med[v]
            each = " ".join(f"{x['poses_per_s']:.1f}" for x in runs)
            ratio = (
                ""
                if v == variants[0]
                else (f" ({m['poses_per_s'] / base['poses_per_s']:.2f}x, p50 {m['p50_ms'] / base['p50_ms']:.2f}x)")
            )
            print(
                f"| {mode} | {v} | {m['poses_per_s']:.1f}{ratio} | {m['p50_ms']:.1f} | {m['p95_ms']:.1f} | "
                f"{m['inference_p50_ms']:.1f} | {m['median_cm']:.2f} cm | {each} |"
            )
    info = runtime_info("cpu")
    isa = " ".join(info["cpu_isa"])
    print(f"\nonnxruntime {info['onnxruntime']}, ISA {isa}, {default_threads()} cores, {a.precision}")
    if a.json:
        a.json.write_text(json.dumps({"runs": rows, "median": summary, "precision": a.precision, **info}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
