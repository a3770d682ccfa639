"""Stage 1 on the built-in synthetic scene and on ../shared/data/herzjesu25: mapping time and localization accuracy.

Runs `acesplat map` and `acesplat eval` through their library functions with default settings, in one
process, one scene after the other, and prints one table plus the machine it ran on.

    python bench/bench_stage1.py [--herz-minutes CAP] [--synth-minutes CAP] [--out runs/bench_stage1]
    python bench/bench_stage1.py --skip-herz --iterations 1000 --buffer 300000 --threads 1   # fixed work, not time
    python bench/bench_stage1.py --augment photometric,ace   # each scene mapped once per augmentation preset
    python bench/bench_stage1.py --skip-synth --seeds 0,1,2   # one recipe, several seeds: the spread between runs
    python bench/bench_stage1.py --encoder default,runs/pretrain2/encoder.pt --seeds 0,1   # encoders paired by seed

The test split is localized three times: as `acesplat eval` does by default (a prediction every 8th pixel), as
`acesplat eval --dense` does (every 4th pixel, row "dense") and as `acesplat eval --align` does (the default's
poses refined against the nearest training images, row "align"; keyframe depths are made before, untimed).
Each map's cell accuracy (bench/cell_accuracy.py: the share of test cells within 4 px under the true pose, and of
7 training frames' cells within 1 px) is printed too, because it is a far steadier signal than a 7-frame median.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from dataclasses import replace
from pathlib import Path

import torch
from cell_accuracy import split_cell_accuracy

from acesplat.core.atomic import write_json
from acesplat.core.config import knob_default
from acesplat.core.grid import DENSE_OUTPUT_STRIDE
from acesplat.core.machine import cpu_isa, machine_info, machine_line
from acesplat.core.scene import read_split
from acesplat.scr.encoders import load_encoder
from acesplat.scr.keyframes import MapKeyframes
from acesplat.scr.localize import Localizer, evaluate
from acesplat.scr.mapping import MappingConfig, default_short_side, map_scene, use_bf16
from acesplat.scr.novel_views import NOVEL_VIEWS
from acesplat.synth import synthesize

AUGMENT = knob_default(MappingConfig, "augment")
MAP_STEPS = knob_default(MappingConfig, "iterations")

ROOT = Path(__file__).resolve().parents[1]
HERZ = ROOT.parent / "shared" / "data" / "herzjesu25"


def run(
    scene: Path,
    minutes: float | None,
    triangulate: bool,
    encoder_path: Path | None,
    iterations: int | None = None,
    buffer_size: int | None = None,
    map_out: Path | None = None,
    precision: str = "auto",
    augment: str = AUGMENT,
    seed: int = 0,
    short_side: int | None = None,
    novel_views: int = 0,
    head_width: int | None = None,
) -> dict:
    enc, ident = load_encoder(None if encoder_path in (None, "default") else encoder_path)
    train, test = read_split(scene, "train"), read_split(scene, "test")
    side = short_side or default_short_side(train)
    cfg = MappingConfig(
        minutes=minutes,
        short_side=side,
        triangulate=triangulate,
        iterations=iterations or MAP_STEPS,
        precision=precision,
        augment=augment,
        seed=seed,
        novel_views=novel_views,
    )
    if buffer_size:
        cfg.buffer_size = buffer_size
    if head_width:
        cfg.head = replace(cfg.head, width=head_width)
    res = map_scene(train, enc, cfg)
    from acesplat.scr.mapfile import SceneMap, save_map
    from acesplat.scr.network import SCRNetwork

    if map_out is not None:  # kept for bench_export.py and acesplat export
        save_map(
            map_out,
            SceneMap(
                res.head,
                ident,
                res.mean,
                side,
                {"scene": str(scene), "iterations": res.iterations, "augment": augment, "novel_views": novel_views},
            ),
        )

    loc = Localizer(SCRNetwork(enc, res.head).eval(), side, {})
    out = {
        "scene": scene.name,
        "encoder": str(encoder_path or "default"),
        "encoder_sha256": ident.sha256,
        "triangulate": triangulate,
        "augment": augment,
        "seed": seed,
        "map_seconds": res.seconds,
        "iterations": res.iterations,
        "iterations_planned": res.iterations_planned,
        "cut_short": res.cut_short,
        "cpu_isa": "/".join(cpu_isa()),
        "precision": "bf16" if use_bf16(precision, "cpu") else "fp32",
        "buffer_features": res.buffer_features,
        "target_features": res.target_features,
        "novel_views": novel_views,
        "novel_view_features": res.novel_view_features,
        "head_width": cfg.head.width,
    }
    keyframes = MapKeyframes(train, loc.network, side)
    keyframes.prepare()
    for key, split, localizer in (
        ("test", test, loc),
        ("dense", test, replace(loc, output_stride=DENSE_OUTPUT_STRIDE)),
        ("align", test, replace(loc, keyframes=keyframes)),
        ("train", train, loc),
    ):
        ev = evaluate(split, localizer)
        ev.pop("estimates")
        out[key] = ev
    test_cells = split_cell_accuracy(test, loc)
    train_cells = split_cell_accuracy(train, loc, 7)
    out["cells"] = {
        "test_within_4px": float(statistics.mean(r["within_px"][2] for r in test_cells)),
        "train_within_1px": float(statistics.mean(r["within_px"][0] for r in train_cells)),
    }
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--synth-minutes", type=float, default=None, help="Optional wall-clock cap of each map.")
    ap.add_argument("--herz-minutes", type=float, default=None, help="Optional wall-clock cap of each map.")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "bench_stage1")
    ap.add_argument(
        "--encoder",
        default="default",
        help="Encoder weights, or several comma-separated (each scene and seed mapped once per encoder); "
        "'default' is the shipped one.",
    )
    ap.add_argument("--ablate-triangulation", action="store_true", help="Also map without triangulated targets.")
    ap.add_argument("--skip-synth", action="store_true")
    ap.add_argument("--skip-herz", action="store_true")
    ap.add_argument("--iterations", type=int, default=None, help="Fixed head iterations instead of the time budget.")
    ap.add_argument("--buffer", type=int, default=None, help="Buffer size (features).")
    ap.add_argument("--threads", type=int, default=0, help="Torch threads (0 = all cores).")
    ap.add_argument(
        "--precision", default="auto", help="Mapping arithmetic (buffer encoder pass and head): auto, fp32 or bf16."
    )
    ap.add_argument("--augment", default=AUGMENT, help="Comma-separated augmentation presets to map each scene with.")
    ap.add_argument(
        "--seeds", default="0", help="Comma-separated mapping seeds; each scene and preset is mapped once per seed."
    )
    ap.add_argument(
        "--novel-views",
        type=int,
        default=0,
        help=f"Warped in-between views added to the buffer (measured: {NOVEL_VIEWS}).",
    )
    ap.add_argument(
        "--head-width", type=int, default=None, help="Width of the head's 1x1 layers (default: the map command's)."
    )
    ap.add_argument(
        "--short-side", type=int, default=None, help="Mapping and localization resolution (default: the map command's)."
    )
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    scenes = []
    if not args.skip_synth:
        synth = args.out / "synth"
        if not (synth / "train").is_dir():
            synthesize(synth, seed=0, overwrite=True)
        scenes.append((synth, args.synth_minutes))
    if not args.skip_herz and HERZ.is_dir():
        scenes.append((HERZ, args.herz_minutes))
    presets = args.augment.split(",")
    seeds = [int(s) for s in args.seeds.split(",")]
    encoders = args.encoder.split(",")
    for scene, minutes in scenes:
        for tri, aug, seed, ei in [
            (t, a, s, e)
            for t in ([True, False] if args.ablate_triangulation else [True])
            for a in presets
            for s in seeds
            for e in range(len(encoders))
        ]:
            t0 = time.monotonic()
            suffix = (
                ("" if tri else ".notri") + ("" if aug == AUGMENT else f".{aug}") + (f".seed{seed}" if seed else "")
            )
            suffix += f".enc{ei}" if len(encoders) > 1 else ""
            map_out = args.out / f"{scene.name}{suffix}.map.pt"
            r = run(
                scene,
                minutes,
                tri,
                encoders[ei],
                args.iterations,
                args.buffer,
                map_out,
                args.precision,
                aug,
                seed,
                args.short_side,
                args.novel_views,
                args.head_width,
            )
            r["wall_seconds"] = time.monotonic() - t0
            rows.append(r)
            print(json.dumps({k: v for k, v in r.items() if k not in ("test", "dense", "align", "train")}), flush=True)
    print(f"\nmachine: {machine_line()}")
    for i, e in enumerate(encoders):
        print(f"encoder {i}: {e}")
    hdr = (
        f"{'scene':12s} {'enc':>3s} {'tri':>4s} {'augment':>11s} {'seed':>4s} {'map s':>6s} {'steps':>6s} "
        f"{'split':>5s} "
        f"{'loc':>6s} {'med cm':>8s} {'med deg':>8s} {'5cm5d':>6s} {'10cm5d':>7s} {'25cm2d':>7s} {'ms':>6s} "
        f"{'cells':>6s}"
    )
    print(hdr)
    for r in rows:
        ei = encoders.index(r["encoder"])
        for split in ("test", "dense", "align", "train"):
            e = r[split]
            mt = "-" if e["median_translation_m"] is None else f"{100 * e['median_translation_m']:.2f}"
            mr = "-" if e["median_rotation_deg"] is None else f"{e['median_rotation_deg']:.3f}"
            cells = {"test": r["cells"]["test_within_4px"], "train": r["cells"]["train_within_1px"]}.get(split)
            print(
                f"{r['scene']:12s} {ei:>3d} {str(r['triangulate'])[0]:>4s} {r['augment']:>11s} {r['seed']:>4d} "
                f"{r['map_seconds']:6.0f} {r['iterations']:>6d} {split:>5s} "
                f"{e['localized']:>3d}/{e['frames']:<3d}{mt:>8s} {mr:>8s} {e['recall_5cm_5deg']:6.1f} "
                f"{e['recall_10cm_5deg']:7.1f} {e['recall_25cm_2deg']:7.1f} {e['mean_ms']:6.0f} "
                + ("" if cells is None else f"{cells:6.3f}")
            )
    print(
        "cells: test rows, share of test cells within 4 px; train rows, share of 7 training frames' cells within 1 px"
    )
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["scene"], r["triangulate"], r["augment"], r["encoder"]), []).append(r)
    for (name, tri, aug, enc), rs in groups.items():
        if len(encoders) > 1:
            cells = statistics.mean(r["cells"]["test_within_4px"] for r in rs)
            dense = [r["dense"]["median_translation_m"] for r in rs]
            dense_cm = statistics.mean(100 * d for d in dense) if None not in dense else float("nan")
            print(
                f"{name} encoder {encoders.index(enc)}: over {len(rs)} seeds, test cells within 4 px {cells:.3f}, "
                f"mean dense median {dense_cm:.2f} cm"
            )
        if len(rs) < 2:
            continue
        for split in (
            "test",
            "dense",
            "align",
        ):  # the same recipe under other seeds: how far one run's median is from the next
            meds = [r[split]["median_translation_m"] for r in rs]
            cm = sorted(100 * m for m in meds if m is not None)
            spread = (", ".join(f"{c:.2f}" for c in cm) + f" cm (median {statistics.median(cm):.2f})") if cm else "none"
            print(
                f"{name} {aug}{'' if tri else ' no-tri'} encoder {encoders.index(enc)}: {split} median translation "
                f"over {len(rs)} seeds: {spread}"
                + (f", {len(rs) - len(cm)} with no median" if len(cm) < len(rs) else "")
            )
    write_json(args.out / "results.json", {"machine": machine_info(), "rows": rows})


if __name__ == "__main__":
    main()
