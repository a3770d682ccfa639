"""Where localization's p95 goes when refinement runs beside it: paced replays of a demo workdir's test split in an
interleaved order, plain and with refinement variants, each run's total and inference p95.

    python bench/refine_tail.py runs/demo [--bundle B] [--budget-ms 100] [--order PNSRMPNSRM]

Run letters: P plain (no refinement, paced at the budget); R refinement as `replay --refine` runs it; N the
refinement session with no keyframe ever taken (its thread, pacing and feature output, no work); S refinement
seeding at SCR depths (no ONNX initializer); M refinement with 15% of each frame's budget left free before the next
frame (RefineOptions.margin); F as R with every object made before the replay frozen out of garbage collection
(gc.freeze). Lower-case p and r: P and R with onnxruntime's threads sleeping between operators instead of spinning
(SessionSettings.spinning off). bench/refine.md has the figures.
"""

from __future__ import annotations

import argparse
import gc
import json
import statistics
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from acesplat.core.bundle import load_bundle
from acesplat.core.machine import machine_line
from edge.refine.session import RefineOptions, start_refinement
from edge.replay import replay_split
from edge.runtime import EdgeLocalizer


def options(kind: str, budget_ms: float) -> RefineOptions:
    o = RefineOptions(budget_ms=budget_ms)
    if kind == "N":
        return replace(o, policy=replace(o.policy, min_inliers=10**9))
    if kind == "S":
        return replace(o, use_initializer=False)
    if kind == "M":
        return replace(o, margin=0.15)
    return o


def run(kind: str, bundle, scene: Path, budget_ms: float) -> dict:
    spinning = kind not in "pr"
    if kind in "Pp":
        loc = EdgeLocalizer(bundle, "int8", pace_ms=budget_ms, spinning=spinning)
        return replay_split(loc, scene, "test", lambda i, n: None)
    loc = EdgeLocalizer(bundle, "int8", spinning=spinning)
    s = start_refinement(loc, bundle, options(kind.upper(), budget_ms), lambda *a: None)
    if kind == "F":  # what exists now is never collected: a collection scans only what the run makes
        gc.collect()
        gc.freeze()
    try:
        return replay_split(loc, scene, "test", lambda i, n: None)
    finally:
        s.close()
        if kind == "F":
            gc.unfreeze()


class GcLog:
    """Python's garbage collections while installed: (thread name, generation, ms) each."""

    def __init__(self) -> None:
        self.items: list[tuple[str, int, float]] = []
        self._t0 = 0.0

    def __call__(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._t0 = time.perf_counter()
        else:
            ms = 1000.0 * (time.perf_counter() - self._t0)
            self.items.append((threading.current_thread().name, int(info["generation"]), ms))

    def summary(self) -> str:
        parts = []
        for main in (True, False):
            for g in (0, 1, 2):
                ms = [x[2] for x in self.items if x[1] == g and (x[0] == "MainThread") == main]
                if ms:
                    parts.append(f"{'main' if main else 'other'} gen{g} {len(ms)}x max {max(ms):.1f} ms")
        return "; ".join(parts) or "no collections"


def pooled_p95(runs: list[list[float]]) -> float:
    """The p95 of every frame of ``runs`` (each a run's per-frame totals) together."""
    return float(np.percentile(np.concatenate([np.asarray(r) for r in runs]), 95))


def pooled_ratios(frames: dict[str, list[list[float]]], seed: int, draws: int = 2000) -> dict:
    """Per letter: the p95 of every frame of every run pooled, its ratio to the plain letter's (P; p for r) and a 90%
    interval of that ratio from resampling whole runs of both letters (runs, not frames: frames of a run share its
    sitting)."""
    rng = np.random.default_rng(seed)
    out: dict = {}
    for kind, runs in frames.items():
        plain = "p" if kind in "pr" else "P"
        base = frames.get(plain)
        if not base:
            continue
        boot = []
        for _ in range(draws):
            a = [runs[i] for i in rng.integers(0, len(runs), len(runs))]
            b = [base[i] for i in rng.integers(0, len(base), len(base))]
            boot.append(pooled_p95(a) / pooled_p95(b))
        lo, hi = np.percentile(boot, [5, 95])
        p95 = pooled_p95(runs)
        out[kind] = {"p95": p95, "ratio": p95 / pooled_p95(base), "lo": float(lo), "hi": float(hi)}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--bundle", type=Path, default=None)
    ap.add_argument("--budget-ms", type=float, default=100.0)
    ap.add_argument("--order", default="PNSRMPNSRM")
    ap.add_argument("--gc-log", action="store_true", help="print each run's garbage collections by thread")
    ap.add_argument("--json", type=Path, default=None, help="every run's per-frame totals and the pooled figures")
    ap.add_argument("--seed", type=int, default=0, help="of the bootstrap over runs")
    args = ap.parse_args()
    if set(args.order) - set("PRNSMFpr"):
        ap.error("--order takes the letters P, R, N, S, M, F, p, r")
    bundle = load_bundle(args.bundle or args.workdir / "bundle")
    print(f"# {machine_line()}")
    res: dict[str, list[tuple[float, float]]] = {}
    frames: dict[str, list[list[float]]] = {}
    for kind in args.order:
        log = GcLog() if args.gc_log else None
        if log is not None:
            gc.callbacks.append(log)
        try:
            out = run(kind, bundle, args.workdir / "scene", args.budget_ms)
            t = out["timing_ms"]
            frames.setdefault(kind, []).append([f["ms"] for f in out["per_frame"]])
        finally:
            if log is not None:
                gc.callbacks.remove(log)
        res.setdefault(kind, []).append((t["total"]["p95"], t["inference"]["p95"]))
        print(f"{kind}: total p95 {t['total']['p95']:.1f} ms, inference p95 {t['inference']['p95']:.1f} ms", flush=True)
        if log is not None:
            print(f"   gc: {log.summary()}", flush=True)
    print("| run | total p95 (median of runs) | ratio to its plain run (P; p for r) | inference p95 (median) | runs |")
    print("|---|---|---|---|---|")
    for kind, v in res.items():
        plain = "p" if kind in "pr" else "P"
        base = statistics.median(x[0] for x in res.get(plain, [(float("nan"), 0.0)]))
        tot, inf = statistics.median(x[0] for x in v), statistics.median(x[1] for x in v)
        print(f"| {kind} | {tot:.1f} ms | {tot / base:.2f}x | {inf:.1f} ms | {' '.join(f'{x[0]:.1f}' for x in v)} |")
    pooled = pooled_ratios(frames, args.seed)
    if pooled:
        print("| run | pooled total p95 (all frames of all runs) | ratio to its plain run | 90% interval (bootstrap) |")
        print("|---|---|---|---|")
        for kind, r in pooled.items():
            print(f"| {kind} | {r['p95']:.1f} ms | {r['ratio']:.3f}x | {r['lo']:.3f}-{r['hi']:.3f}x |")
    if args.json is not None:
        doc = {"machine": machine_line(), "order": args.order, "p95": res, "frames_ms": frames, "pooled": pooled}
        args.json.write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
