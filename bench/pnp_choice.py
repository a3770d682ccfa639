"""Which PnP-RANSAC method the edge runtime uses by default: accuracy and milliseconds, measured in one run.

Two sets of correspondences:
1. real network predictions: a small map fitted to the analytic test room (tests/test_edge_scene.py),
   predicting coordinates for its frames (the residual errors and outliers are the network's own);
2. the default bundle size's correspondence count (360x480 input -> 45x60 = 2700 cells) on a
   synthetic wall with 40% gross outliers and 1 px noise, for the timing at full size.

3. with --map/--scene: a Stage 1 map's predictions on a scene's test split (e.g. the maps that
   bench/bench_stage1.py writes), each method with and without the robust refinement
   (acesplat.core.pose_refine), and the refinement's scale schedules.

Usage: python bench/pnp_choice.py [--size 96x128] [--steps 300] [--map MAP --scene SCENE] [--map-only]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from acesplat.core.camera import Intrinsics  # noqa: E402
from acesplat.core.geometry import look_at, pose_error, transform_points  # noqa: E402
from acesplat.core.grid import cell_centers
from acesplat.core.metrics import timing_stats  # noqa: E402
from acesplat.core.pnp import PNP_METHODS, solve_pnp  # noqa: E402
from edge.profile import cpu_model  # noqa: E402


def run_method(method: str, cases: list, repeats: int = 1, iterations: int = 1000, **kw) -> dict:
    errs, ms, loc = [], [], 0
    for pix, pts, intr, T in cases:
        for _ in range(repeats):
            t0 = time.perf_counter()
            r = solve_pnp(pix, pts, intr, method=method, iterations=iterations, fallback=None, **kw)
            ms.append((time.perf_counter() - t0) * 1000)
        loc += r.localized
        errs.append(pose_error(r.T_c2w, T) if r.T_c2w is not None and r.localized else (np.inf, np.inf))
    e = np.array(errs)
    return {
        "localized": f"{loc}/{len(cases)}",
        "median_cm": 100 * float(np.median(e[:, 0])),
        "median_deg": float(np.median(e[:, 1])),
        "recall_5cm_5deg": 100.0 * float(np.mean((e[:, 0] < 0.05) & (e[:, 1] < 5))),
        "recall_10cm_5deg": 100.0 * float(np.mean((e[:, 0] < 0.10) & (e[:, 1] < 5))),
        **{f"ms_{k}": v for k, v in timing_stats(ms).items() if k in ("mean", "p50", "p95", "max")},
    }


def real_cases(size: tuple[int, int], steps: int) -> list:
    import torch

    from acesplat.core.scene import read_split
    from acesplat.scr.mapfile import encoder_for_map, load_map
    from tests.test_edge_scene import cell_targets, make_room_scene, train_tiny_map

    tmp = Path(tempfile.mkdtemp(prefix="pnp_choice_"))
    scene = make_room_scene(tmp / "room", train=24, test=8, size=size, test_offset_m=0.01, test_offset_deg=0.5)
    t0 = time.time()
    map_path, _ = train_tiny_map(scene, tmp, steps=steps)
    print(f"fitted a map for real predictions in {time.time() - t0:.0f} s")
    m = load_map(map_path)
    net = m.network(encoder_for_map(m, map_path))
    cases = []
    for split in ("train", "test"):
        for f in read_split(scene, split).frames:
            g = cv2.cvtColor(f.load_rgb(), cv2.COLOR_RGB2GRAY)
            with torch.no_grad():
                c = net(torch.from_numpy(g).float()[None, None])[0].permute(1, 2, 0).numpy()
            h, w = c.shape[:2]
            err = np.linalg.norm(c - cell_targets(f), axis=-1)
            cases.append((cell_centers(h, w), c.reshape(-1, 3), f.intrinsics, f.pose))
            cases[-1] += ()
            real_cases.errors.append(err.ravel())
    return cases


real_cases.errors = []


def map_cases(map_path: str, scene: str) -> list:
    """A Stage 1 map's coordinate predictions for every test frame of a scene."""
    import torch

    from acesplat.core.scene import read_split
    from acesplat.scr.localize import Localizer
    from acesplat.scr.mapfile import encoder_for_map, load_map

    m = load_map(map_path)
    loc = Localizer(m.network(encoder_for_map(m, map_path)).eval(), m.short_side, {})
    cases = []
    with torch.no_grad():
        for f in read_split(scene, "test").frames:
            c, intr = loc.predict(f.load_rgb(), f.intrinsics)
            h, w = c.shape[:2]
            cases.append((cell_centers(h, w), c.reshape(-1, 3).astype(np.float64), intr, f.pose))
    return cases


def synthetic_cases(n_frames: int = 10) -> list:
    rng = np.random.default_rng(0)
    intr = Intrinsics(430.0, 430.0, 239.5, 179.5, 480, 360)
    cases = []
    for _ in range(n_frames):
        T = look_at(np.array([0.3, -0.2, 1.5]) + rng.normal(0, 0.3, 3), np.array([0.5, 4.0, 1.2]))
        pix = cell_centers(45, 60)
        depth = 3.0 + rng.uniform(0, 2.0, len(pix))
        X = transform_points(T, intr.unproject(pix + rng.normal(0, 1.0, pix.shape), depth))
        bad = rng.random(len(X)) < 0.4
        X[bad] += rng.normal(0, 2.0, (bad.sum(), 3))
        cases.append((pix, X, intr, T))
    return cases


def garbage_cases(n_frames: int = 10) -> list:
    """A lost camera: 2700 predictions that match nothing (what a wrong or unmapped place gives)."""
    rng = np.random.default_rng(1)
    intr = Intrinsics(430.0, 430.0, 239.5, 179.5, 480, 360)
    return [(cell_centers(45, 60), rng.normal(0, 3.0, (2700, 3)) + [0, 4, 1], intr, np.eye(4)) for _ in range(n_frames)]


def table(title: str, rows: dict) -> None:
    keys = list(next(iter(rows.values())))
    print(f"\n{title}")
    print(f"{'method':15s}" + "".join(f"{k:>17s}" for k in keys))
    for name, r in rows.items():
        print(f"{name:15s}" + "".join(f"{v:>17.2f}" if isinstance(v, float) else f"{v:>17s}" for v in r.values()))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", default="96x128")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--map", default=None, help="A Stage 1 map file (with --scene): real predictions of a trained map.")
    ap.add_argument("--scene", default=None)
    ap.add_argument("--map-only", action="store_true", help="Only the --map tables.")
    args = ap.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    print(f"machine: {cpu_model()}, {os.cpu_count()} cores; load average {os.getloadavg()}; opencv {cv2.__version__}")
    if args.map:
        cases = map_cases(args.map, args.scene)
        print(f"\n{args.map} on {args.scene} test split: {len(cases)} frames x {len(cases[0][0])} cells")
        rows = {}
        for m in PNP_METHODS:
            rows[f"{m} LM"] = run_method(m, cases, iterations=256, robust_scales=())
            rows[f"{m} robust"] = run_method(m, cases, iterations=256)
        table("each method (256 iterations): LM on the RANSAC inliers only vs + robust refinement", rows)
        sched = {
            "(4, 2, 1)": (4.0, 2.0, 1.0),
            "(8, 4, 2, 1)": (8.0, 4.0, 2.0, 1.0),
            "(2, 2, 2)": (2.0, 2.0, 2.0),
            "(4, 2)": (4.0, 2.0),
            "(4, 2, 1, 0.5)": (4.0, 2.0, 1.0, 0.5),
        }
        table(
            "robust scale schedule (px), ransac_ap3p, 256 iterations",
            {k: run_method("ransac_ap3p", cases, iterations=256, robust_scales=v) for k, v in sched.items()},
        )
        if args.map_only:
            print(f"\nload average after: {os.getloadavg()}")
            return
    real = real_cases(size, args.steps)
    e = np.concatenate(real_cases.errors)
    print(
        f"real predictions: {len(real)} frames x {len(real[0][0])} cells; coordinate error median "
        f"{100 * np.median(e):.1f} cm, "
        f"{100 * np.mean(e > 0.25):.0f}% of cells off by > 25 cm"
    )
    table("real predictions (tiny room map)", {m: run_method(m, real, repeats=3) for m in PNP_METHODS})
    table(
        "2700 correspondences (360x480 grid), 40% outliers, 1 px noise",
        {m: run_method(m, synthetic_cases()) for m in PNP_METHODS},
    )
    caps = (1000, 500, 256, 128)
    synth, lost = synthetic_cases(), garbage_cases()
    table(
        "iteration cap, ransac_ap3p: real predictions",
        {f"cap {c}": run_method("ransac_ap3p", real, repeats=3, iterations=c) for c in caps},
    )
    table(
        "iteration cap, ransac_ap3p: 2700 correspondences, 40% outliers",
        {f"cap {c}": run_method("ransac_ap3p", synth, iterations=c) for c in caps},
    )
    table(
        "iteration cap, ransac_ap3p: 2700 predictions that match nothing (lost)",
        {f"cap {c}": run_method("ransac_ap3p", lost, iterations=c) for c in caps},
    )
    print(f"\nload average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
