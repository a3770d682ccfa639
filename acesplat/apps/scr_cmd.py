"""`acesplat map`, `acesplat eval`, `acesplat pretrain-encoder` and `acesplat adapt-encoder`."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from acesplat.apps.support import PhaseProgress, one_line_errors, option, parse_size, report_json
from acesplat.core.config import knob_default, knob_help
from acesplat.core.errors import InputError
from acesplat.scr.adapt import AdaptConfig
from acesplat.scr.device import resolve_device
from acesplat.scr.localize import Localizer
from acesplat.scr.mapping import MappingConfig
from acesplat.scr.network import HeadConfig
from acesplat.scr.pretrain import PretrainConfig

console = Console()


@one_line_errors
def map_command(
    scene: Path = typer.Argument(..., help="Scene folder in the ACE layout."),
    out: Path = typer.Option(..., "-o", "--out", help="Map file to write."),
    steps: int = option(MappingConfig, "iterations", "--steps", min=1),
    minutes: float | None = option(MappingConfig, "minutes"),
    device: str = typer.Option("auto", help="auto, cpu or cuda."),
    encoder: Path | None = typer.Option(None, help="Encoder weights (default: the shipped encoder; ACE's file works)."),
    short_side: int | None = option(
        MappingConfig, "short_side", default=None, help="Shorter image side for the network, at most the images' own."
    ),
    head_width: int = typer.Option(knob_default(MappingConfig, "head").width, help="Width of the head's 1x1 layers."),
    batch_size: int = option(MappingConfig, "batch_size", min=1),
    buffer_size: int = option(MappingConfig, "buffer_size", min=1),
    buffer_passes: int = option(MappingConfig, "buffer_passes", min=1),
    precision: str = option(MappingConfig, "precision"),
    augment: str = option(MappingConfig, "augment"),
    novel_views: int = option(MappingConfig, "novel_views"),
    seed: int = option(MappingConfig, "seed"),
    json_out: Path | None = typer.Option(None, "--json", help="Write the numbers here."),
) -> None:
    """Train a scene-specific SCR head on the training split (Stage 1 mapping)."""
    import torch

    from acesplat.core.machine import cpu_isa, isa_limit
    from acesplat.core.scene import read_split
    from acesplat.scr.augment import augment_ranges
    from acesplat.scr.encoders import load_encoder
    from acesplat.scr.mapfile import SceneMap, save_map
    from acesplat.scr.mapping import default_short_side, map_scene, use_bf16

    if novel_views < 0:
        raise InputError(None, f"--novel-views must be 0 or more, got {novel_views}")
    if minutes is not None and minutes <= 0:
        raise InputError(None, f"--minutes must be positive, got {minutes}")
    dev = resolve_device(device)
    try:
        bf16 = use_bf16(precision, dev)
    except ValueError as e:
        raise InputError(None, f"--{e}") from None
    try:
        augment_ranges(augment)
    except ValueError as e:
        raise InputError(None, f"--{e}") from None
    if dev == "cpu":
        torch.set_num_threads(max(1, torch.get_num_threads()))
    split = read_split(scene, "train")
    enc, ident = load_encoder(encoder)
    side = short_side or default_short_side(split)
    cfg = MappingConfig(
        iterations=steps,
        minutes=minutes,
        short_side=side,
        head=HeadConfig(width=head_width, blocks=1),
        batch_size=batch_size,
        buffer_size=buffer_size,
        buffer_passes=buffer_passes,
        seed=seed,
        device=dev,
        precision=precision,
        augment=augment,
        novel_views=novel_views,
    )
    with PhaseProgress("map ") as bar:
        res = map_scene(split, enc, cfg, bar)
    meta = {
        "scene": str(Path(scene).resolve()),
        "train_frames": len(split),
        "seconds": res.seconds,
        "iterations": res.iterations,
        "iterations_planned": res.iterations_planned,
        "cut_short": res.cut_short,
        "minutes_cap": minutes,
        "buffer_features": res.buffer_features,
        "batch_size": batch_size,
        "buffer_passes": buffer_passes,
        "device": dev,
        "precision": "bf16" if bf16 else "fp32",
        "cpu_isa": cpu_isa(),
        "isa_limit": isa_limit(),
        "augment": augment,
        "novel_views": novel_views,
        "novel_view_features": res.novel_view_features,
    }
    save_map(out, SceneMap(res.head, ident, res.mean, side, meta))
    console.print(
        f"mapped {len(split)} images in {res.seconds:.1f} s ({res.buffer_seconds:.1f} s buffer, "
        f"{res.iterations} iterations, {res.buffer_features} features, final loss {res.final_loss:.2f}; "
        f"{meta['precision']} on {'/'.join(meta['cpu_isa']) or 'an unknown ISA'}) -> {out}"
    )
    if res.cut_short:
        console.print(
            f"[bold yellow]warning:[/] --minutes {minutes} cut the recipe short: {res.iterations} of "
            f"{res.iterations_planned} head steps, {res.buffer_features} of {cfg.buffer_size} buffered features "
            "planned; "
            "the map is less trained than the default recipe makes it"
        )
    report_json(
        json_out,
        {
            **meta,
            "buffer_seconds": res.buffer_seconds,
            "final_loss": res.final_loss,
            "encoder": ident.as_dict(),
            "short_side": side,
            "history": res.history,
        },
    )


RESULT_KEYS = (
    "frames",
    "localized",
    "median_translation_m",
    "median_rotation_deg",
    "recall_5cm_5deg",
    "recall_10cm_5deg",
    "recall_25cm_2deg",
    "mean_ms",
)
"""The accuracy summary's columns (acesplat.core.metrics), in the order eval and replay print them."""


def results_table(title: str, s: dict) -> Table:
    t = Table(title=title)
    for k in RESULT_KEYS:
        t.add_column(k.replace("_", " "), justify="right")
    vals = []
    for k in RESULT_KEYS:
        v = s.get(k)
        vals.append("-" if v is None else (f"{v:.4g}" if isinstance(v, float) else str(v)))
    t.add_row(*vals)
    return t


def plot_positions(path: Path, split, estimates: list) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from acesplat.core.atomic import atomic_path

    gt = np.stack([f.pose[:3, 3] for f in split.frames])
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.plot(gt[:, 0], gt[:, 1], "g.-", label="ground truth", lw=0.8)
    for f, T in zip(split.frames, estimates):
        if T is not None:
            ax.plot([f.pose[0, 3], T[0, 3]], [f.pose[1, 3], T[1, 3]], "r-", lw=0.6)
    est = np.array([T[:3, 3] for T in estimates if T is not None]).reshape(-1, 3)
    ax.plot(est[:, 0], est[:, 1], "rx", ms=4, label="estimated")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend()
    ax.set_title("camera positions (top view)")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)


@one_line_errors
def eval_command(
    map_path: Path = typer.Argument(..., metavar="MAP", help="Map file from `acesplat map`."),
    scene: Path = typer.Argument(..., help="Scene folder in the ACE layout."),
    split: str = typer.Option("test", help="Split to localize."),
    encoder: Path | None = typer.Option(None, help="Encoder weights if not where the map says."),
    json_out: Path | None = typer.Option(None, "--json", help="Write the numbers here."),
    plot: Path | None = typer.Option(None, help="Plot estimated against true camera positions (PNG)."),
    dense: bool = typer.Option(False, help=knob_help(Localizer, "output_stride")),
    align: bool = typer.Option(
        False,
        help="Refine each localized pose against the nearest training images of SCENE (warped with "
        "their depth, dense flow, PnP): centimetre poses where the head alone is a few cm off (bench/herz_gap.md).",
    ),
) -> None:
    """Localize a split against a map and report pose accuracy."""
    import torch

    from acesplat.core.grid import DENSE_OUTPUT_STRIDE, OUTPUT_STRIDE
    from acesplat.core.scene import read_split
    from acesplat.scr.localize import Localizer, evaluate
    from acesplat.scr.mapfile import encoder_for_map, load_map

    torch.set_num_threads(max(1, torch.get_num_threads()))
    m = load_map(map_path)
    enc = encoder_for_map(m, map_path, encoder)
    data = read_split(scene, split)
    stride = DENSE_OUTPUT_STRIDE if dense else OUTPUT_STRIDE
    network = m.network(enc)
    keyframes = None
    if align:
        from acesplat.scr.keyframes import MapKeyframes

        keyframes = MapKeyframes(read_split(scene, "train"), network, m.short_side)
    loc = Localizer(network, m.short_side, {}, output_stride=stride, keyframes=keyframes)
    with PhaseProgress("eval ") as bar:
        if keyframes is not None:
            keyframes.prepare(lambda i, n: bar("keyframe depth", i / n, {"image": i}))
        s = evaluate(data, loc, lambda i, n: bar("localize", i / n, {"frame": i}))
    estimates = s.pop("estimates")
    s["output_stride"] = stride
    s["aligned_to_keyframes"] = align
    console.print(results_table(f"{Path(scene).name} / {split}", s))
    if plot is not None:
        plot_positions(plot, data, estimates)
    report_json(json_out, s)


@one_line_errors
def pretrain_command(
    out: Path = typer.Argument(..., help="Folder for the scene cache, checkpoint and the final encoder.pt."),
    minutes: float = option(PretrainConfig, "minutes"),
    steps: int = option(PretrainConfig, "steps"),
    scenes: int = option(PretrainConfig, "scenes"),
    frames: int = option(PretrainConfig, "frames_per_scene", "--frames"),
    size: str = typer.Option(
        "x".join(map(str, knob_default(PretrainConfig, "image_hw"))), help=knob_help(PretrainConfig, "image_hw")
    ),
    pairs: int = option(PretrainConfig, "pairs"),
    seed: int = option(PretrainConfig, "seed"),
    photos: str = option(PretrainConfig, "photos"),
    photo_share: float = option(PretrainConfig, "photo_share"),
    max_gap: int = option(PretrainConfig, "max_gap", min=1),
    init_encoder: Path | None = option(PretrainConfig, "init_encoder"),
    lr: float = option(PretrainConfig, "lr"),
    device: str = typer.Option("auto", help="auto, cpu or cuda (under torchrun: each rank's GPU is LOCAL_RANK)."),
    threads: int = typer.Option(0, help="CPU threads (0 = all cores); 1 is faster when other jobs share the cores."),
    install: bool = typer.Option(False, help="Install the resulting encoder as the shipped default (with provenance)."),
) -> None:
    """Pretrain the project's own encoder on procedural scenes (resumable).

    Several processes or GPUs: torchrun --nproc_per_node N -m acesplat.apps.cli pretrain-encoder OUT ... (NCCL on
    GPUs, gloo on the CPU; the global batch is --pairs times N, --steps counts global steps; rank 0 writes the files).
    """
    import sys

    import torch

    from acesplat.scr.pretrain import distributed_from_env, pretrain

    if threads > 0:
        torch.set_num_threads(threads)
    cfg = PretrainConfig(
        minutes=minutes,
        scenes=scenes,
        frames_per_scene=frames,
        image_hw=parse_size(size),
        steps=steps,
        pairs=pairs,
        seed=seed,
        photos=photos,
        photo_share=photo_share,
        max_gap=max_gap,
        init_encoder=None if init_encoder is None else str(init_encoder),
        lr=lr,
    )
    command = "acesplat " + " ".join(sys.argv[1:])
    with distributed_from_env(resolve_device(device)) as (ddp, rank_device):
        if ddp.rank == 0:
            with PhaseProgress("pretrain ") as bar:
                summary = pretrain(out, cfg, progress=bar, command=command, device=rank_device)
            console.print(summary)
        else:
            pretrain(out, cfg, command=command, device=rank_device)
    if install and ddp.rank == 0:
        from acesplat.scr.pretrain import install_default

        path = install_default(out, command)
        console.print(f"installed {path} (provenance in {path.with_suffix('.json')})")


@one_line_errors
def adapt_command(
    map_path: Path = typer.Argument(..., metavar="MAP", help="A first map of SCENE from `acesplat map`."),
    scene: Path = typer.Argument(..., help="The scene folder MAP was made from (its training split is used)."),
    out: Path = typer.Option(..., "-o", "--out", help="Encoder weights to write; map again with --encoder OUT."),
    steps: int = option(AdaptConfig, "steps", min=1),
    lr: float = option(AdaptConfig, "lr"),
    pairs: int = option(AdaptConfig, "pairs", min=1),
    max_gap: int = option(AdaptConfig, "max_gap", min=1),
    max_error_px: float = option(AdaptConfig, "max_error_px"),
    seed: int = option(AdaptConfig, "seed"),
    encoder: Path | None = typer.Option(None, help="Encoder weights if not where the map says."),
    json_out: Path | None = typer.Option(None, "--json", help="Write the numbers here."),
) -> None:
    """Adapt the map's encoder to SCENE from its own training images and poses (InfoNCE between its views, the
    correspondences from MAP's coordinates), then `acesplat map SCENE --encoder OUT` maps with it
    (bench/encoder_choice.md)."""
    import sys

    import torch

    from acesplat.core.atomic import write_json
    from acesplat.core.scene import read_split
    from acesplat.scr.adapt import adapt_encoder, save_encoder, scene_views
    from acesplat.scr.encoders import file_sha256
    from acesplat.scr.mapfile import encoder_for_map, load_map

    if not lr > 0 or not max_error_px > 0:
        raise InputError(None, f"--lr and --max-error-px must be positive, got {lr} and {max_error_px}")
    torch.set_num_threads(max(1, torch.get_num_threads()))
    cfg = AdaptConfig(steps=steps, lr=lr, pairs=pairs, max_gap=max_gap, max_error_px=max_error_px, seed=seed)
    m = load_map(map_path)
    enc = encoder_for_map(m, map_path, encoder)
    split = read_split(scene, "train")
    loc = Localizer(m.network(enc), m.short_side, {})
    with PhaseProgress("adapt ") as bar:
        views, found = scene_views(split, loc, cfg.max_error_px)
        summary = adapt_encoder(enc, views, cfg, bar)
    save_encoder(enc, out)
    report = {
        "command": "acesplat " + " ".join(sys.argv[1:]),
        "scene": str(Path(scene).resolve()),
        "train_images": [f.name for f in split.frames],
        "map": str(Path(map_path).resolve()),
        "map_sha256": file_sha256(Path(map_path)),
        "from_encoder": m.encoder_identity.as_dict(),
        "encoder_sha256": file_sha256(out),
        **found,
        **summary,
    }
    write_json(out.with_suffix(".json"), report)  # provenance beside the weights
    last = summary["history"][-1] if summary["history"] else {}
    console.print(
        f"adapted the encoder on {found['views']} training images ({found['cells_kept']:.0%} of cells fit) in "
        f"{summary['seconds']:.1f} s, {cfg.steps} steps, last loss {last.get('loss', float('nan')):.3f}, top-1 "
        f"{last.get('top1', float('nan')):.3f} -> {out} (provenance {out.with_suffix('.json')})"
    )
    report_json(json_out, report)
