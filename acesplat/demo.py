"""`acesplat demo`: the whole pipeline on the built-in synthetic scene, end to end, with a results table.

Each stage calls the same library functions as its own command, so the demo cannot drift from them.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from acesplat.core.cli_support import PhaseProgress, one_line_errors, report_json

console = Console()


def _stage_synth(work: Path, summary: dict) -> Path:
    from acesplat.synth import synthesize

    scene = work / "scene"
    with PhaseProgress("demo ") as bar:
        s = synthesize(scene, seed=0, overwrite=True, progress=lambda d, n: bar("synth", d / n, {"frames": d}))
    summary["synth"] = {k: s[k] for k in ("train_frames", "test_frames", "size", "seconds")}
    return scene


def _stage_map(scene: Path, work: Path, minutes: float, summary: dict) -> Path:
    from acesplat.core.scene import read_split
    from acesplat.scr.encoders import load_encoder
    from acesplat.scr.localize import Localizer, evaluate
    from acesplat.scr.mapfile import SceneMap, save_map
    from acesplat.scr.mapping import IMAGE_SHORT_SIDE, MappingConfig, map_scene

    from .scr.cli_cmds import resolve_device

    dev = resolve_device("auto")
    train, test = read_split(scene, "train"), read_split(scene, "test")
    enc, ident = load_encoder(None)
    f0 = train.frames[0].intrinsics
    side = min(IMAGE_SHORT_SIDE, f0.width, f0.height)
    cfg = MappingConfig(minutes=minutes, short_side=side, device=dev)
    with PhaseProgress("demo map ") as bar:
        res = map_scene(train, enc, cfg, bar)
    map_path = work / "map.pt"
    meta = {"scene": str(scene.resolve()), "train_frames": len(train), "seconds": res.seconds,
            "iterations": res.iterations, "buffer_features": res.buffer_features, "device": dev}
    scene_map = SceneMap(res.head, ident, res.mean, side, meta)
    save_map(map_path, scene_map)
    loc = Localizer(scene_map.network(enc), side, {})
    with PhaseProgress("demo eval ") as bar:
        ev = evaluate(test, loc, lambda i, n: bar("localize", i / n, {"frame": i}))
    ev.pop("estimates")
    ev.pop("per_frame")
    summary["map"] = {"seconds": res.seconds, "iterations": res.iterations, "buffer_features": res.buffer_features}
    summary["eval"] = ev
    return map_path


def _stage_edge(map_path: Path, scene: Path, work: Path, summary: dict) -> Path:
    """Export FP32 + INT8 ONNX and replay the test split on the torch-free edge runtime with both."""
    from acesplat.core.bundle import load_bundle
    from edge.replay import replay_split
    from edge.runtime import EdgeLocalizer
    from export.bundle_export import ExportOptions, export_bundle

    bundle_dir = work / "bundle"
    with PhaseProgress("demo export ") as bar:
        rep = export_bundle(map_path, bundle_dir, ExportOptions(int8=True, scene_path=scene), bar)
    summary["export"] = {"seconds": rep.seconds, "checks": rep.manifest.get("checks", {})}
    bundle = load_bundle(bundle_dir)
    for precision in ("fp32", "int8"):
        loc = EdgeLocalizer(bundle, precision)
        with PhaseProgress(f"demo replay {precision} ") as bar:
            r = replay_split(loc, scene, "test", lambda i, n: bar("localize", i / n, {"frame": i}))
        r.pop("per_frame", None)
        summary[f"replay_{precision}"] = r
    return bundle_dir


def results_table(summary: dict) -> Table:
    t = Table(title="acesplat demo: built-in synthetic scene")
    t.add_column("stage")
    t.add_column("result")
    t.add_column("seconds", justify="right")
    if "synth" in summary:
        s = summary["synth"]
        t.add_row("synth", f"{s['train_frames']} train + {s['test_frames']} test frames, {s['size'][0]}x{s['size'][1]}",
                  f"{s['seconds']:.1f}")
    if "map" in summary:
        m, e = summary["map"], summary["eval"]
        t.add_row("map", f"{m['iterations']} iterations, {m['buffer_features']} buffered features", f"{m['seconds']:.1f}")
        t.add_row("eval (torch)", _accuracy(e), f"{e['mean_ms'] * e['frames'] / 1000:.1f}")
    if "export" in summary:
        t.add_row("export (ONNX FP32 + INT8)", "bundle with manifest and hashes", f"{summary['export']['seconds']:.1f}")
    for precision in ("fp32", "int8"):
        r = summary.get(f"replay_{precision}")
        if r:
            tm = r["timing_ms"]["total"]
            t.add_row(f"edge replay ({precision})", f"{_accuracy(r)}; total p50 {tm['p50']:.0f} ms, p95 {tm['p95']:.0f} ms",
                      f"{tm['mean'] * r['frames'] / 1000:.1f}")
    return t


def _accuracy(e: dict) -> str:
    med_t, med_r = e["median_translation_m"], e["median_rotation_deg"]
    med = f"median {med_t * 100:.1f} cm / {med_r:.2f} deg" if med_t is not None else "median: not localized"
    return f"{e['localized']}/{e['frames']} localized, 5cm/5deg {e['recall_5cm_5deg']:.1f}%, {med}"


@one_line_errors
def demo_command(
    workdir: Path = typer.Option(Path("runs/demo"), help="Where the scene, map and outputs go."),
    map_minutes: float = typer.Option(4.0, help="Mapping budget."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write all numbers here."),
) -> None:
    """Run synth -> map -> eval -> export -> edge replay on the built-in synthetic scene and print the results."""
    t0 = time.monotonic()
    workdir.mkdir(parents=True, exist_ok=True)
    summary: dict = {}
    scene = _stage_synth(workdir, summary)
    map_path = _stage_map(scene, workdir, map_minutes, summary)
    _stage_edge(map_path, scene, workdir, summary)
    summary["seconds"] = time.monotonic() - t0
    console.print(results_table(summary))
    report_json(json_out if json_out else workdir / "demo.json", summary)
