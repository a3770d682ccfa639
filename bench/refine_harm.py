"""The demo's refinement replay again, on a demo workdir, with or without witness views: does any view lose?

    python bench/refine_harm.py runs/demo [--witnesses 0] [--repeats 2] [--budget-ms 200] [--bundle B] [--json OUT]

WORKDIR is what `acesplat demo --workdir WORKDIR` left (bundle/, scene/; --bundle another bundle of that scene).
Each run replays the test split with the INT8 graph paced at the budget, first without refinement (the latency
reference), then with it as the demo does, and scores every test view at its ground-truth pose at the network input
size under the loaded and the refined map (bench/refine.md, "Witness views").
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from acesplat.core.bundle import load_bundle
from acesplat.core.machine import machine_line
from acesplat.core.scene import read_split
from edge.refine.guard import psnr, view_mse
from edge.refine.session import RefineOptions, start_refinement
from edge.replay import replay_split
from edge.runtime import EdgeLocalizer


def run(work: Path, bundle_dir: Path, witnesses: int, budget_ms: float) -> dict:
    bundle = load_bundle(bundle_dir)
    plain = replay_split(EdgeLocalizer(bundle, "int8", pace_ms=budget_ms), work / "scene", "test", lambda i, n: None)
    loc = EdgeLocalizer(bundle, "int8")
    s = start_refinement(loc, bundle, RefineOptions(budget_ms=budget_ms, evaluate=True, witnesses=witnesses), print)
    t0 = time.monotonic()
    try:
        r = replay_split(loc, work / "scene", "test", lambda i, n: None)
    finally:
        s.close()
    f = s.summary
    changes = [a - b for b, a in s.view_psnr]
    final, bg = s.refiner.snapshot(), np.zeros(3)
    unseen = []  # the training views: no frame of the replay was one of them, so no witness either
    for fr in read_split(work / "scene", "train").frames:
        rgb = fr.load_rgb().astype(np.float32) / 255.0
        k = fr.intrinsics
        unseen.append(psnr(view_mse(final, fr.pose, k, rgb, bg)) - psnr(view_mse(s.initial, fr.pose, k, rgb, bg)))
    return {
        "witnesses": witnesses,
        "seconds": time.monotonic() - t0,
        "psnr_before": f["psnr_before"],
        "psnr_after": f["psnr_after"],
        "views": f["psnr_views"],
        "views_lower": f["views_harmed"],
        "views_higher": int(sum(c > f["harm_tolerance_db"] for c in changes)),
        "worst_change_db": min(changes),
        "keyframes_committed": f["keyframes_committed"],
        "unseen_views": len(unseen),
        "unseen_mean_change_db": float(np.mean(unseen)),
        "unseen_lower": int(sum(c < -f["harm_tolerance_db"] for c in unseen)),
        "unseen_worst_change_db": float(min(unseen)),
        "gaussians": f["gaussians_initial"],
        "localization_p95_ms": r["timing_ms"]["total"]["p95"],
        "localization_p95_ms_without": plain["timing_ms"]["total"]["p95"],
        "stage_p95_ms": {k: v["p95"] for k, v in r["timing_ms"].items() if isinstance(v, dict) and "p95" in v},
        "stage_p95_ms_without": {
            k: v["p95"] for k, v in plain["timing_ms"].items() if isinstance(v, dict) and "p95" in v
        },
        "park_p95_ms": f["timing_ms"]["park"]["p95"],
        "witness": f["witness"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--bundle", type=Path, help="default: WORKDIR/bundle")
    ap.add_argument("--witnesses", type=int, default=RefineOptions.witnesses)
    ap.add_argument("--budget-ms", type=float, default=200.0)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    print(machine_line())
    rows = [run(a.workdir, a.bundle or a.workdir / "bundle", a.witnesses, a.budget_ms) for _ in range(a.repeats)]
    for r in rows:
        w = r["witness"]
        print(
            f"witnesses {r['witnesses']}: PSNR {r['psnr_before']:.3f} -> {r['psnr_after']:.3f} dB over {r['views']} "
            f"views, {r['views_lower']} lower / {r['views_higher']} higher (worst {r['worst_change_db']:+.2f} dB), "
            f"{r['keyframes_committed']} keyframes committed; the {r['unseen_views']} training views (unseen): mean "
            f"{r['unseen_mean_change_db']:+.3f} dB, {r['unseen_lower']} lower "
            f"(worst {r['unseen_worst_change_db']:+.2f}); "
            f"{r['gaussians']} Gaussians; localization p95 "
            f"{r['localization_p95_ms']:.1f} ms (without refinement {r['localization_p95_ms_without']:.1f}); repair: "
            f"{w.get('harmed_before', '-')} witnesses had lost, {w.get('passes', '-')} passes, "
            f"{w.get('ms', float('nan')):.0f} ms"
        )
    if a.json:
        a.json.write_text(json.dumps({"machine": machine_line(), "runs": rows}, indent=1))


if __name__ == "__main__":
    main()
