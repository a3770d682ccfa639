"""`acesplat demo`: the whole pipeline on the built-in synthetic scene, end to end, with a results table.

synth -> map (Stage 1) -> eval -> splat (a short Stage 2) -> export (FP32 + INT8 SCR graphs, the Gaussians and
their initializer) -> edge replay with each precision -> the INT8 replay paced at one frame per refinement budget,
without and then with refinement (PSNR before/after on the test views, localization latency with vs without, and
frame | before | after render images of the views refinement changed most either way, in WORKDIR/refine_renders/;
a test view refinement left worse than the map as loaded is a red FAILED row and line, and ``refine.failed`` in the
JSON; the demo still ends with exit 0, since every stage ran; ``replay --refine`` exits 1). Each stage calls the same
library functions as its own command, so the demo cannot drift from them.
"""

from __future__ import annotations

import time
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from acesplat.apps.support import PhaseProgress, one_line_errors, option, parse_int_pair, parse_size, report_json
from acesplat.core.errors import InputError
from acesplat.scr.mapping import MappingConfig

console = Console()


DEFAULT_MAP_STEPS = 2400
"""Stage 1 head steps of the demo: a quick map (about 5 minutes on 2 AVX2 cores); `acesplat map` runs 5000."""
DEFAULT_SPLAT_ITERATIONS = 1000
"""Stage 2 iterations of the demo: enough to see the Gaussians form (about 3 minutes on 2 AVX2 cores, bench/recipe.md;
`acesplat splat` runs the full recipe's 2000 on more Gaussians)."""
DEFAULT_REFINE_BUDGET_MS = 200.0
"""Per-frame budget of the refinement replay: room for refinement beside INT8 localization (bench/refine.md)."""
RENDER_PAIRS = 3
"""Before/after render images the demo writes (the test views whose PSNR refinement changed most)."""
SPLAT_MAX_GAUSSIANS = 60_000
"""Stage 2 cap of the demo's short run: fewer Gaussians make each of its iterations cheaper (bench/refine.md).
Refinement takes a map of any size (its cap limits growth only)."""
REFINE_PRECISION = "int8"
"""The refinement replay runs the INT8 SCR graph the device's check picks, the edge's fast path: more of the budget
is left for refinement."""


def _stage_synth(work: Path, summary: dict, size: tuple[int, int] | None, frames: tuple[int, int] | None) -> Path:
    from acesplat.synth import synthesize

    scene = work / "scene"
    extra: dict = {}
    if size is not None:
        extra["size"] = size
    if frames is not None:
        extra["train_frames"], extra["test_frames"] = frames
    with PhaseProgress("demo ") as bar:
        s = synthesize(scene, seed=0, overwrite=True, progress=lambda d, n: bar("synth", d / n, {"frames": d}), **extra)
    summary["synth"] = {k: s[k] for k in ("train_frames", "test_frames", "size", "seconds")}
    return scene


def _stage_map(scene: Path, work: Path, steps: int, minutes: float | None, summary: dict) -> Path:
    from acesplat.core.scene import read_split
    from acesplat.scr.device import resolve_device
    from acesplat.scr.encoders import load_encoder
    from acesplat.scr.localize import Localizer, evaluate
    from acesplat.scr.mapfile import SceneMap, save_map
    from acesplat.scr.mapping import MappingConfig, default_short_side, map_scene

    dev = resolve_device("auto")
    train, test = read_split(scene, "train"), read_split(scene, "test")
    enc, ident = load_encoder(None)
    side = default_short_side(train)
    cfg = MappingConfig(iterations=steps, minutes=minutes, short_side=side, device=dev)
    with PhaseProgress("demo map ") as bar:
        res = map_scene(train, enc, cfg, bar)
    map_path = work / "map.pt"
    meta = {
        "scene": str(scene.resolve()),
        "train_frames": len(train),
        "seconds": res.seconds,
        "iterations": res.iterations,
        "iterations_planned": res.iterations_planned,
        "cut_short": res.cut_short,
        "buffer_features": res.buffer_features,
        "device": dev,
        "augment": cfg.augment,
    }
    scene_map = SceneMap(res.head, ident, res.mean, side, meta)
    save_map(map_path, scene_map)
    from acesplat.scr.keyframes import MapKeyframes

    net = scene_map.network(enc)
    loc = Localizer(net, side, {})
    with PhaseProgress("demo eval ") as bar:
        ev = evaluate(test, loc, lambda i, n: bar("localize", i / n, {"frame": i}))
        # keyframe depths are made on first use (only the keyframes some test frame needs), inside the frame times
        keyframes = MapKeyframes(train, net, side)
        al = evaluate(
            test,
            Localizer(net, side, {}, keyframes=keyframes),
            lambda i, n: bar("localize + align", i / n, {"frame": i}),
        )
    for e in (ev, al):
        e.pop("estimates")
        e.pop("per_frame")
    summary["map"] = {"seconds": res.seconds, "iterations": res.iterations, "buffer_features": res.buffer_features}
    summary["eval"] = ev
    summary["eval_align"] = al
    return map_path


def _stage_splat(
    scene: Path, map_path: Path, work: Path, minutes: float | None, iterations: int, summary: dict
) -> Path:
    """A short Stage 2 through `acesplat splat`'s library function, with the command's default of one torch thread."""
    import torch

    from acesplat.splat.pipeline import SplatConfig
    from acesplat.splat.run import run_splat

    cfg = SplatConfig(
        minutes=minutes,
        iterations=iterations,
        max_gaussians=SPLAT_MAX_GAUSSIANS,
    )
    splat_dir = work / "splat"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with PhaseProgress("demo splat ") as bar:
            rep = run_splat(scene, map_path, splat_dir, cfg, progress=bar)
    finally:
        torch.set_num_threads(threads)
    summary["splat"] = {
        k: rep[k]
        for k in (
            "seconds",
            "iterations",
            "iterations_planned",
            "cut_short",
            "gaussians_initial",
            "gaussians_final",
            "train_psnr",
            "train_ssim",
            "train_psnr_views",
        )
        if k in rep
    }
    return splat_dir


def _stage_edge(map_path: Path, scene: Path, splat_dir: Path, work: Path, budget_ms: float, summary: dict) -> Path:
    """Export FP32 + INT8 ONNX with the Gaussians and their initializer, replay the test split on the torch-free
    edge runtime with each precision, then once more with refinement."""
    from acesplat.apps.refine_cmd import refine_session
    from acesplat.core.bundle import load_bundle
    from edge.int8_check import choose_int8
    from edge.refine.session import write_before_after
    from edge.replay import replay_split
    from edge.runtime import EdgeLocalizer
    from export.bundle_export import ExportOptions, export_bundle
    from export.splat_export import export_splat

    bundle_dir = work / "bundle"
    with PhaseProgress("demo export ") as bar:
        rep = export_bundle(map_path, bundle_dir, ExportOptions(int8=True, scene_path=scene), bar)
        sp = export_splat(bundle_dir, splat_dir, map_path, progress=bar)
    summary["export"] = {"seconds": rep.seconds + sp["seconds"], "checks": sp["manifest"].get("checks", {})}
    bundle = load_bundle(bundle_dir)
    int8, reports = choose_int8(bundle)  # the INT8 graph `--int8` runs on this CPU
    int8 = int8 or "int8"
    summary["int8_check"] = [{"precision": r.precision, "passed": r.passed, **r.inference_ms} for r in reports]
    for key, precision in (("fp32", "fp32"), ("int8", int8)):
        loc = EdgeLocalizer(bundle, precision)
        with PhaseProgress(f"demo replay {precision} ") as bar:
            r = replay_split(loc, scene, "test", lambda i, n: bar("localize", i / n, {"frame": i}))
        r.pop("per_frame", None)
        summary[f"replay_{key}"] = r
    # The reference for refinement's latency: the same precision paced at one frame per budget without refinement
    # (the refinement replay is paced too; idling between frames changes latency on a shared machine).
    refine_precision = int8 if REFINE_PRECISION == "int8" else REFINE_PRECISION
    loc = EdgeLocalizer(bundle, refine_precision, pace_ms=budget_ms)
    with PhaseProgress(f"demo replay {refine_precision} paced ") as bar:
        r = replay_split(loc, scene, "test", lambda i, n: bar("localize", i / n, {"frame": i}))
    r.pop("per_frame", None)
    summary["replay_paced"] = r
    loc = EdgeLocalizer(bundle, refine_precision)
    session = refine_session(
        True, loc, bundle, budget_ms, None, lambda msg: console.print(f"[yellow]{msg}[/yellow]"), evaluate=True
    )
    if session is None:
        raise InputError(bundle_dir, "the demo bundle has no Gaussians to refine")
    t0 = time.monotonic()
    with PhaseProgress(f"demo replay {refine_precision} + refinement ") as bar:
        try:
            r = replay_split(loc, scene, "test", lambda i, n: bar("localize + refine", i / n, {"frame": i}))
        finally:
            session.close()
    r.pop("per_frame", None)
    r["refine"] = session.summary
    r["seconds"] = time.monotonic() - t0
    r["renders"] = write_before_after(session, work / "refine_renders", RENDER_PAIRS)
    summary["replay_refine"] = r
    return bundle_dir


def results_table(summary: dict) -> Table:
    t = Table(title="acesplat demo: built-in synthetic scene")
    t.add_column("stage")
    t.add_column("result")
    t.add_column("seconds", justify="right")
    if "synth" in summary:
        s = summary["synth"]
        t.add_row(
            "synth",
            f"{s['train_frames']} train + {s['test_frames']} test frames, {s['size'][0]}x{s['size'][1]}",
            f"{s['seconds']:.1f}",
        )
    if "map" in summary:
        m, e = summary["map"], summary["eval"]
        t.add_row(
            "map", f"{m['iterations']} iterations, {m['buffer_features']} buffered features", f"{m['seconds']:.1f}"
        )
        t.add_row("eval (torch)", _accuracy(e), f"{e['mean_ms'] * e['frames'] / 1000:.1f}")
        a = summary.get("eval_align")
        if a:
            t.add_row(
                "eval (torch), aligned",
                _accuracy(a) + " (keyframe depths made on first use)",
                f"{a['mean_ms'] * a['frames'] / 1000:.1f}",
            )
    if "splat" in summary:
        sp = summary["splat"]
        t.add_row(
            "splat (Stage 2)",
            f"{sp['gaussians_initial']} -> {sp['gaussians_final']} Gaussians, {sp['iterations']} "
            f"iterations; train PSNR {sp['train_psnr']:.2f} dB over {sp['train_psnr_views']} views",
            f"{sp['seconds']:.1f}",
        )
    if "export" in summary:
        t.add_row(
            "export (ONNX FP32 + INT8 + splat)",
            "bundle: SCR graphs, Gaussians, initializer; self-checked",
            f"{summary['export']['seconds']:.1f}",
        )
    for precision in ("fp32", "int8"):
        r = summary.get(f"replay_{precision}")
        if r:
            tm = r["timing_ms"]["total"]
            t.add_row(
                f"edge replay ({r['precision']})",
                f"{_accuracy(r)}; total p50 {tm['p50']:.0f} ms, p95 {tm['p95']:.0f} ms",
                f"{tm['mean'] * r['frames'] / 1000:.1f}",
            )
    r = summary.get("replay_paced")
    if r:
        tm = r["timing_ms"]["total"]
        t.add_row(
            f"edge replay ({r['precision']}), paced",
            f"one frame per refinement budget, no refinement; total p50 {tm['p50']:.0f} ms, p95 {tm['p95']:.0f} ms",
            "",
        )
    r = summary.get("replay_refine")
    if r:
        t.add_row(
            f"edge replay ({r['precision']}) + refinement",
            _refinement(r, summary.get("replay_paced") or summary.get(f"replay_{r['precision']}")),
            f"{r['seconds']:.1f}",
        )
        for im in r.get("renders", []):
            t.add_row(
                "  before/after render",
                f"{im['path']} (frame | before | after: {im['psnr_before']:.2f} -> {im['psnr_after']:.2f} dB)",
                "",
            )
        from acesplat.apps.refine_cmd import harm_line

        harm = harm_line(r["refine"])
        if harm is not None:
            t.add_row("[red]refinement FAILED[/red]", f"[red]{harm}[/red]", "")
    if "seconds" in summary:
        t.add_row("total", "", f"{summary['seconds']:.1f}")
    return t


def _refinement(r: dict, plain: dict | None) -> str:
    from acesplat.apps.refine_cmd import witness_text

    f = r["refine"]
    tm, w = r["timing_ms"]["total"], f["timing_ms"]["window"]
    psnr = (
        f"PSNR {f['psnr_before']:.2f} -> {f['psnr_after']:.2f} dB over {f['psnr_views']} test views"
        if "psnr_before" in f
        else "no PSNR (no views with poses)"
    )
    without = f" (without, paced alike: {plain['timing_ms']['total']['p95']:.0f} ms)" if plain else ""
    init = f["calibration_ms"].get("initializer_ms")
    init_text = f"; initializer {init:.1f} ms" if init is not None else ""
    return (
        f"{psnr}; {f['keyframes']} keyframes ({f['keyframes_committed']} kept), {witness_text(f)}"
        f"+{f['gaussians_added']} Gaussians, "
        f"{f['steps']} steps in a {f['budget_ms']:.0f} ms budget; localization total p95 {tm['p95']:.0f} ms{without}; "
        f"refinement per frame p50 {_ms(w['p50'])}, p95 {_ms(w['p95'])}; waits for a running piece p95 "
        f"{_ms(f['timing_ms']['park']['p95'])}{init_text}"
    )


def _ms(v: float) -> str:
    return "-" if v is None or v != v else f"{v:.0f} ms"


def _accuracy(e: dict) -> str:
    med_t, med_r = e["median_translation_m"], e["median_rotation_deg"]
    med = f"median {med_t * 100:.1f} cm / {med_r:.2f} deg" if med_t is not None else "median: not localized"
    return f"{e['localized']}/{e['frames']} localized, 5cm/5deg {e['recall_5cm_5deg']:.1f}%, {med}"


@one_line_errors
def demo_command(
    workdir: Path = typer.Option(Path("runs/demo"), help="Where the scene, map and outputs go."),
    map_steps: int = typer.Option(
        DEFAULT_MAP_STEPS,
        "--map-steps",
        min=1,
        help="Stage 1 head steps (`acesplat map --steps`; its default is 5000).",
    ),
    map_minutes: float | None = option(MappingConfig, "minutes", "--map-minutes"),
    splat_iterations: int = typer.Option(
        DEFAULT_SPLAT_ITERATIONS,
        "--splat-iterations",
        min=0,
        help="Stage 2 iterations (`acesplat splat --iterations`).",
    ),
    splat_minutes: float | None = typer.Option(
        None, help="Optional wall-clock cap on Stage 2 (`acesplat splat --minutes`)."
    ),
    refine_budget_ms: float = typer.Option(
        DEFAULT_REFINE_BUDGET_MS,
        "--refine-budget-ms",
        help="Per-frame budget of localization + refinement in the edge replay.",
    ),
    size: str | None = typer.Option(
        None, help="Image size HxW of the synthetic scene (default 240x320; smaller is quicker)."
    ),
    frames: str | None = typer.Option(None, help="TRAIN,TEST frame counts of the synthetic scene (default 200,60)."),
    json_out: Path | None = typer.Option(None, "--json", help="Write all numbers here (default WORKDIR/demo.json)."),
) -> None:
    """Run synth -> map -> eval -> splat -> export -> edge replay (with and without refinement) on the built-in
    synthetic scene and print the results."""
    if any(v is not None and v <= 0 for v in (map_minutes, splat_minutes, refine_budget_ms)):
        raise InputError(None, "--map-minutes, --splat-minutes and --refine-budget-ms must be positive")
    counts = _parse_frames(frames)
    t0 = time.monotonic()
    workdir.mkdir(parents=True, exist_ok=True)
    summary: dict = {}
    scene = _stage_synth(workdir, summary, parse_size(size) if size else None, counts)
    map_path = _stage_map(scene, workdir, map_steps, map_minutes, summary)
    splat_dir = _stage_splat(scene, map_path, workdir, splat_minutes, splat_iterations, summary)
    _stage_edge(map_path, scene, splat_dir, workdir, refine_budget_ms, summary)
    summary["seconds"] = time.monotonic() - t0
    console.print(results_table(summary))
    for im in summary["replay_refine"].get("renders", []):  # full paths (the table may shorten them)
        console.print(f"before/after render (frame | before | after): {im['path']}", soft_wrap=True)
    report_json(json_out if json_out else workdir / "demo.json", summary)
    from acesplat.apps.refine_cmd import harm_line

    harm = harm_line(summary["replay_refine"]["refine"])
    if harm is not None:
        console.print(f"[red]{harm}[/red]", soft_wrap=True)


def _parse_frames(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    train, test = parse_int_pair(text, "--frames must look like TRAIN,TEST (e.g. 200,60)")
    if train < 2 or test < 1:
        raise InputError(None, f"--frames needs at least 2 training and 1 test frame, got {text!r}")
    return train, test
