"""Edge refinement on the built-in scene: PSNR gain on unseen frames, localization latency with and without it.

Protocol: Gaussians optimised by Stage 2 (`acesplat splat`) on the first half of the training
trajectory; the second half is replayed through the edge runtime with `--refine --budget-ms 100`.
Reported: PSNR over the replayed frames rendered from their true poses (the map before vs after the
replay), localization latency (the 'total' stage: capture to pose) without refinement, with paced
refinement (what `replay`/`localize` on files do: each frame gets the budget, refinement takes what
localization leaves), and with unpaced refinement (frames back to back, the worker beside the
localizer all the time: the worst case for contention on 2 cores and the GIL), the Gaussian count
over time, and the machine's load. Every number comes from this run.

The SCR map is a real Stage 1 map (`acesplat map`'s library function with the default encoder, --map-steps,
on the whole training trajectory), or an existing one (--map, with --scene the scene it was mapped on, e.g. the
demo's); --fitted-map fits one directly to depth-derived coordinates instead (tests/test_edge_scene.train_tiny_map:
seconds, but poses far better than Stage 1 gives). Keyframe poses are the localizer's, as on a device.

    python bench/bench_refine.py --workdir runs/bench_refine [--json runs/bench_refine/result.json]
    python bench/bench_refine.py --scene runs/demo/scene --map runs/demo/map.pt --workdir runs/bench_refine_demo
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def load_avg() -> list[float]:
    return [round(v, 2) for v in os.getloadavg()]


def link_split(src_split: Path, names: list[str], dst_split: Path) -> None:
    """A split folder made of links to some frames of another (rgb, poses, calibration, depth)."""
    for sub in ("rgb", "poses", "calibration", "depth"):
        if not (src_split / sub).is_dir():
            continue
        (dst_split / sub).mkdir(parents=True, exist_ok=True)
        for p in sorted((src_split / sub).iterdir()):
            if p.stem in names:
                (dst_split / sub / p.name).symlink_to(p.resolve())


def prepare(work: Path, args) -> dict:
    """Scene, map, first-half splat and the bundle (each step skipped when its output exists)."""
    from acesplat.core.scene import read_split
    from acesplat.synth import synthesize

    scene = Path(args.scene) if args.scene else work / "scene"
    if not args.scene and not (scene / "synth.json").is_file():
        log(f"synthesize the built-in scene at {args.size[0]}x{args.size[1]}, {args.frames} training frames")
        synthesize(scene, seed=0, train_frames=args.frames, test_frames=4, size=tuple(args.size), overwrite=True)
    names = [f.name for f in read_split(scene, "train").frames]
    half = len(names) // 2
    first, second = work / "first_half", work / "second_half"
    if not first.is_dir():
        link_split(scene / "train", names[:half], first / "train")
    if not second.is_dir():
        link_split(scene / "train", names[half:], second / "test")
    map_path = Path(args.map) if args.map else work / ("tiny.map" if args.fitted_map else "map.pt")
    if not map_path.is_file() and not args.fitted_map:
        from acesplat.apps.demo import _stage_map
        from acesplat.core.config import knob_default
        from acesplat.scr.mapping import MappingConfig

        args.map_steps = args.map_steps or knob_default(MappingConfig, "iterations")
        log(f"Stage 1: map the whole training trajectory with the default encoder, {args.map_steps} steps")
        info: dict = {}
        map_path = _stage_map(scene, work, args.map_steps, args.map_minutes, info)
        log(f"map: {info['map']['iterations']} iterations; test median {info['eval']['median_translation_m']} m")
    if not map_path.is_file():
        from tests.test_edge_scene import train_tiny_map

        every = work / "map_frames"
        if not every.is_dir():
            link_split(scene / "train", names[:: args.map_every], every / "train")
        log(
            f"fit an SCR map to every {args.map_every}th training frame (depth-derived coordinates), "
            f"{args.map_steps} steps"
        )
        t0 = time.monotonic()
        train_tiny_map(every, work, steps=args.map_steps)
        log(f"map: {time.monotonic() - t0:.0f} s")
    splat = work / "splat_first_half"
    if not (splat / "gaussians.ply").is_file():
        from typer.testing import CliRunner

        from acesplat.apps.cli import app

        log(f"Stage 2 on the first half ({half} frames), {args.splat_iterations} iterations")
        r = CliRunner().invoke(
            app,
            [
                "splat",
                str(first),
                "--map",
                str(map_path),
                "-o",
                str(splat),
                "--iterations",
                str(args.splat_iterations),
                "--max-gaussians",
                str(args.max_gaussians),
            ],
        )
        if r.exit_code:
            raise SystemExit(r.output)
        log(r.output.strip().splitlines()[-1])
    bundle = work / "bundle"
    if not (bundle / "manifest.json").is_file() or not (bundle / "gaussians.ply").is_file():
        from export.bundle_export import ExportOptions, export_bundle
        from export.splat_export import export_splat

        log("export the bundle with --splat")
        # size: the map's, from the scene's images; INT8 too (the edge's fast path)
        export_bundle(map_path, bundle, ExportOptions(int8=True, scene_path=scene))
        export_splat(bundle, splat, map_path)
    return {
        "scene": scene,
        "second": second,
        "bundle": bundle,
        "first_frames": half,
        "second_frames": len(names) - half,
    }


def replay(
    bundle: Path,
    split_root: Path,
    threads: int | None,
    refine: dict | None,
    pace_ms: float | None = None,
    precision: str = "int8",
) -> dict:
    """One replay of the second half; refine=None: localization only (``pace_ms``: one frame per that many ms,
    as a camera would deliver them, so the reference idles between frames exactly as the paced refinement run)."""
    from acesplat.core.bundle import load_bundle
    from edge.refine.session import RefineOptions, start_refinement
    from edge.replay import replay_split
    from edge.runtime import EdgeLocalizer

    b = load_bundle(bundle)
    loc = EdgeLocalizer(b, precision, threads, pace_ms=pace_ms if refine is None else None)
    session = None
    if refine is not None:
        session = start_refinement(loc, b, RefineOptions(evaluate=True, **refine), log)
    t0 = time.monotonic()
    try:
        s = replay_split(loc, split_root, "test")
    finally:
        if session is not None:
            session.close()
    s["wall_s"] = time.monotonic() - t0
    s["load_after"] = load_avg()
    if session is not None:
        s["refine"] = session.summary
    return s


def gil_probe(bundle: Path, split_root: Path, seconds: float) -> dict:
    """How long a thread waits for the GIL while refinement runs beside it (and while nothing does).

    The probe sleeps 1 ms at a time (releasing the GIL) and measures how late it wakes: a wake-up needs the
    GIL back, so the lateness beyond the OS's own is time some other thread held the GIL (a GIL-holding
    kernel cannot be interrupted; Python code is asked to switch after 5 ms).
    """
    import threading

    import numpy as np

    from acesplat.core.bundle import load_bundle
    from acesplat.core.scene import read_split
    from edge.refine.bundle_models import bundle_gaussians
    from edge.refine.deadline import Deadline
    from edge.refine.refiner import Keyframe, RefineConfig, Refiner

    def probe(stop: threading.Event) -> list[float]:
        late = []
        while not stop.is_set():
            t0 = time.perf_counter()
            time.sleep(0.001)
            late.append(1000.0 * (time.perf_counter() - t0) - 1.0)
        return late

    def run(busy: bool) -> list[float]:
        stop = threading.Event()
        out: list[float] = []
        worker = None
        if busy:
            g = bundle_gaussians(load_bundle(bundle))
            frames = read_split(split_root, "test").frames
            ref = Refiner(g, RefineConfig())
            ref.warm_up()

            def refine_loop() -> None:
                i = 0
                while not stop.is_set():
                    f = frames[i % len(frames)]
                    rgb = f.load_rgb().astype(np.float32) / 255.0
                    ref.refine(Keyframe(f.pose, rgb, f.intrinsics), Deadline.after(0.1))
                    i += 1

            worker = threading.Thread(target=refine_loop)
            worker.start()
        t = threading.Timer(seconds, stop.set)
        t.start()
        out = probe(stop)
        if worker is not None:
            worker.join()
        return out

    from acesplat.core.metrics import timing_stats

    return {"idle_ms": timing_stats(run(False)), "refining_ms": timing_stats(run(True))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workdir", type=Path, default=ROOT / "runs" / "bench_refine")
    ap.add_argument("--size", type=int, nargs=2, default=[120, 160], metavar=("H", "W"))
    ap.add_argument(
        "--frames", type=int, default=80, help="training frames of the built-in scene (half seed, half replayed)"
    )
    ap.add_argument(
        "--scene",
        type=str,
        default=None,
        help="an existing scene (its training split is halved) instead of synthesizing one",
    )
    ap.add_argument("--map", type=str, default=None, help="an existing Stage 1 map of the scene")
    ap.add_argument(
        "--map-steps", type=int, default=None, help="Stage 1 head steps when no --map is given (default: the recipe's)"
    )
    ap.add_argument("--map-minutes", type=float, default=None, help="Optional wall-clock cap of that map")
    ap.add_argument(
        "--fitted-map", action="store_true", help="fit the map to depth-derived coordinates instead of Stage 1"
    )
    ap.add_argument("--precision", default="int8", choices=["fp32", "int8"])
    ap.add_argument(
        "--skip-unpaced", action="store_true", help="only the paced settings and the reference (half the time)"
    )
    ap.add_argument("--skip-gil", action="store_true")
    ap.add_argument("--map-steps", type=int, default=200)
    ap.add_argument("--map-every", type=int, default=2, help="fit the map to every n-th training frame (CPU time)")
    ap.add_argument("--splat-iterations", type=int, default=1000)
    ap.add_argument("--max-gaussians", type=int, default=30_000)
    ap.add_argument("--budget-ms", type=float, default=100.0)
    ap.add_argument(
        "--threads", type=int, default=None, help="onnxruntime threads (default: all cores, as acesplat-edge localize)"
    )
    ap.add_argument("--repeats", type=int, default=1, help="replays per setting (latency statistics pool them)")
    ap.add_argument("--fresh", action="store_true", help="rebuild the scene, map, splat and bundle")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    from acesplat.core.machine import machine_info
    from acesplat.core.metrics import timing_stats

    work = args.workdir
    if args.fresh and work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    load_start = load_avg()
    prep = prepare(work, args)
    # Reference runs without refinement: 'off' paced like a camera at one frame per budget (the paced run's
    # situation: measured, idling between frames alone slows the next localization on this shared machine),
    # 'off_unpaced' back to back (the unpaced run's situation).
    settings = {"off": (None, args.budget_ms), "paced": ({"budget_ms": args.budget_ms, "pace": True}, None)}
    if not args.skip_unpaced:
        settings.update({"off_unpaced": (None, None), "unpaced": ({"budget_ms": args.budget_ms, "pace": False}, None)})
    runs: dict[str, list[dict]] = {name: [] for name in settings}
    # warm-up: onnxruntime, numba kernels, page cache
    replay(prep["bundle"], prep["second"], args.threads, None, precision=args.precision)
    for rep in range(args.repeats):
        for name, (cfg, pace) in settings.items():  # interleaved, so drifting load hits all settings alike
            log(f"replay {rep + 1}/{args.repeats}: {name} (load {load_avg()})")
            runs[name].append(replay(prep["bundle"], prep["second"], args.threads, cfg, pace, args.precision))

    def loc_ms(name: str) -> list[float]:
        return [f["ms"] for r in runs[name] for f in r["per_frame"]]

    lat = {name: timing_stats(loc_ms(name)) for name in runs}
    gil = None
    if not args.skip_gil:
        log("GIL probe")
        gil = gil_probe(prep["bundle"], prep["second"], 4.0)
    paced = runs["paced"][-1]["refine"]
    unpaced = runs["unpaced"][-1]["refine"] if "unpaced" in runs else None
    result = {
        "machine": machine_info(),
        "load_average": {"start": load_start, "end": load_avg()},
        "scene": {"size": args.size, "seed_frames": prep["first_frames"], "replayed_frames": prep["second_frames"]},
        "budget_ms": args.budget_ms,
        "psnr_before": paced["psnr_before"],
        "psnr_after": paced["psnr_after"],
        "psnr_gain_db": paced["psnr_after"] - paced["psnr_before"],
        "psnr_unpaced_after": unpaced["psnr_after"] if unpaced else None,
        "precision": args.precision,
        "localization_ms": lat,
        "localization_p95_ratio_paced": lat["paced"]["p95"] / lat["off"]["p95"],
        "localization_p95_ratio_unpaced": lat["unpaced"]["p95"] / lat["off_unpaced"]["p95"] if unpaced else None,
        "localized": {name: [r["localized"] for r in runs[name]] for name in runs},
        "refine_paced": {k: v for k, v in paced.items() if k != "gaussians_over_time"},
        "refine_unpaced": {k: v for k, v in unpaced.items() if k != "gaussians_over_time"} if unpaced else None,
        "gaussians_over_time": paced["gaussians_over_time"],
        "gil_wait": gil,
    }
    m = result["machine"]
    print(f"\nmachine: {m.get('cpu')} ({m.get('cores')} cores); load {load_start} -> {result['load_average']['end']}")
    size = paced.get("psnr_size", args.size)
    print(
        f"scene {size[0]}x{size[1]}: Gaussians from the first {prep['first_frames']} frames, "
        f"{prep['second_frames']} frames replayed ({args.precision}), budget {args.budget_ms:.0f} ms"
    )
    un = f"; unpaced run: {result['psnr_unpaced_after']:.2f}" if unpaced else ""
    print(
        f"PSNR on the replayed frames: {result['psnr_before']:.2f} -> {result['psnr_after']:.2f} dB "
        f"({result['psnr_gain_db']:+.2f}{un})"
    )
    for name in runs:
        t = lat[name]
        print(f"localization ({name:11s}) ms: p50 {t['p50']:.1f}  p95 {t['p95']:.1f}  max {t['max']:.1f}")
    print(
        f"p95 ratio with/without refinement: paced {result['localization_p95_ratio_paced']:.3f} (vs off)"
        + (f", unpaced {result['localization_p95_ratio_unpaced']:.3f} (vs off_unpaced)" if unpaced else "")
    )
    if gil:
        print(
            f"GIL probe (lateness of a 1 ms sleep): idle p95 {gil['idle_ms']['p95']:.2f} "
            f"max {gil['idle_ms']['max']:.2f} ms; "
            f"beside refinement p95 {gil['refining_ms']['p95']:.2f} max {gil['refining_ms']['max']:.2f} ms"
        )
    r = paced
    print(
        f"refinement (paced): {r['keyframes']} keyframes, {r['keyframes_committed']} committed, {r['steps']} steps, "
        f"step p50 {r['timing_ms']['step']['p50']:.1f} ms, "
        f"refinement work per frame window p95 {r['timing_ms']['window']['p95']:.1f} ms, "
        f"Gaussians {r['gaussians_initial']} -> {r['gaussians_final']} (cap {r['gaussian_cap']}); "
        "localization waited for "
        f"a running piece p95 {r['timing_ms']['park']['p95']:.1f} max {r['timing_ms']['park']['max']:.1f} ms"
    )
    counts = r["gaussians_over_time"]
    step = max(1, len(counts) // 8)
    print("Gaussians over time (frame, count): " + ", ".join(f"({f}, {c})" for f, c in counts[::step] + [counts[-1]]))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
