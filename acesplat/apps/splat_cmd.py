"""`acesplat splat` and `acesplat render`; defaults and help come from the knobs (SplatConfig, ValidityConfig)."""

from __future__ import annotations

import time
from pathlib import Path

import typer
from rich.console import Console

from acesplat.apps.support import PhaseProgress, one_line_errors, option, parse_int_pair, report_json
from acesplat.core.errors import InputError
from acesplat.splat.pipeline import SplatConfig
from acesplat.splatcore.validity import ValidityConfig

console = Console()


@one_line_errors
def splat_command(
    scene: Path = typer.Argument(..., help="Scene folder in the ACE layout."),
    map_path: Path = typer.Option(
        ..., "--map", help="Map file from `acesplat map` (its SCR network seeds the Gaussians)."
    ),
    out: Path = typer.Option(
        ..., "-o", "--out", help="Splat folder to write (gaussians.ply, adapter.pt, init_head.pt, splat.json)."
    ),
    minutes: float | None = option(SplatConfig, "minutes"),
    protocol: str = option(SplatConfig, "protocol"),
    views: str | None = option(SplatConfig, "sparse_views", "--views"),
    encoder: Path | None = typer.Option(None, help="Encoder weights if not where the map says."),
    max_gaussians: int = option(SplatConfig, "max_gaussians"),
    reproj_px: float = option(ValidityConfig, "reproj_max_px", "--reproj-px"),
    start: str = option(SplatConfig, "start"),
    seed_cells: int = option(SplatConfig, "seed_cells"),
    seed_corners: int = option(SplatConfig, "seed_corners"),
    fill: bool = option(SplatConfig, "fill"),
    head_warmup: float = option(SplatConfig, "head_warmup", "--head-warmup"),
    joint_head: bool = option(SplatConfig, "joint_head", "--joint-head/--no-joint-head"),
    iterations: int = option(SplatConfig, "iterations"),
    device: str = typer.Option("auto", help="auto, cpu or cuda (networks only: the rasterizer runs on the CPU)."),
    threads: int = typer.Option(
        1,
        help="Torch threads (the rasterizer has its own numba threads; one torch thread runs this loop's many small "
        "tensor ops fastest on a busy CPU: bench/stage2.md).",
    ),
    seed: int = option(SplatConfig, "seed"),
    json_out: Path | None = typer.Option(None, "--json", help="Write the numbers here."),
) -> None:
    """Optimise Gaussians for a scene, seeded by its SCR map (Stage 2)."""
    import torch

    if max_gaussians < 1:
        raise InputError(None, f"--max-gaussians must be positive, got {max_gaussians}")
    if threads < 1:
        raise InputError(None, f"--threads must be positive, got {threads}")
    torch.set_num_threads(threads)
    if iterations < 0:
        raise InputError(None, f"--iterations must be >= 0, got {iterations}")
    if minutes is not None and minutes <= 0:
        raise InputError(None, f"--minutes must be positive, got {minutes}")
    if reproj_px <= 0:
        raise InputError(None, f"--reproj-px must be positive, got {reproj_px}")
    if not 0 <= head_warmup < 1:
        raise InputError(None, f"--head-warmup must be in [0, 1), got {head_warmup}")
    cfg = SplatConfig(
        minutes=minutes,
        protocol=protocol,
        sparse_views=None
        if views is None
        else parse_int_pair(views, "--views must be two training frame indices like 10,14"),
        max_gaussians=max_gaussians,
        iterations=iterations,
        validity=ValidityConfig(reproj_max_px=reproj_px),
        start=start,
        seed_cells=seed_cells,
        seed_corners=seed_corners,
        fill=fill,
        head_warmup=head_warmup,
        joint_head=joint_head,
        seed=seed,
    )
    from acesplat.splat.run import run_splat

    with PhaseProgress("splat ") as bar:
        report = run_splat(scene, map_path, out, cfg, encoder, device, bar)
    tgt = f", held-out targets PSNR {report['target_psnr']:.2f} dB" if "target_psnr" in report else ""
    console.print(
        f"splat ({protocol}): {report['gaussians_initial']} -> {report['gaussians_final']} Gaussians, "
        f"{report['iterations']} iterations in {report['seconds']:.1f} s; train PSNR {report['train_psnr']:.2f} dB / "
        f"SSIM {report['train_ssim']:.3f} over {report['train_psnr_views']} views{tgt} -> {out}"
    )
    if report["cut_short"]:
        console.print(
            f"[bold yellow]warning:[/] --minutes {minutes} cut Stage 2 short: {report['iterations']} of "
            f"{report['iterations_planned']} iterations; the scene set is less trained than the default recipe makes it"
        )
    report_json(json_out, report)


@one_line_errors
def render_command(
    splat: Path = typer.Argument(..., help="Splat folder from `acesplat splat`."),
    scene: Path = typer.Argument(..., help="Scene folder in the ACE layout."),
    split: str = typer.Option("test", help="train or test."),
    out: Path | None = typer.Option(None, "--out", help="Write render-beside-truth PNGs here."),
    lpips_weights: list[Path] | None = typer.Option(
        None,
        "--lpips-weights",
        help="Report LPIPS: give torchvision's AlexNet weights and LPIPS v0.1 alex.pth (repeat the option, or one "
        "merged file). Nothing is downloaded.",
    ),
    json_out: Path | None = typer.Option(None, "--json", help="Write the numbers here."),
) -> None:
    """Render a split of a scene from a splat and score it against the images."""
    from acesplat.core.scene import SPLITS, read_split
    from acesplat.splat.evaluate import evaluate_views
    from acesplat.splat.splatfile import load_gaussians, load_manifest
    from acesplat.splat.views import load_views

    if split not in SPLITS:
        raise InputError(None, f"--split must be one of {SPLITS}, got {split!r}")
    manifest = load_manifest(splat)
    g = load_gaussians(splat)
    lpips_fn = None
    if lpips_weights:
        from acesplat.splat.lpips import load_lpips

        lpips_fn = load_lpips(*lpips_weights)
    data = read_split(scene, split)
    t0 = time.monotonic()
    with PhaseProgress("render ") as bar:
        views = load_views(data.frames, int(manifest["short_side"]))
        ev = evaluate_views(
            g, views, manifest["background"], out, lpips_fn, progress=lambda d, n: bar("render", d / n, {"frames": d})
        )
    ev["gaussians"] = len(g)
    ev["split"] = split
    ev["image_size"] = list(views[0].size)
    ev["seconds"] = time.monotonic() - t0
    lp = f", LPIPS {ev['lpips']:.4f}" if "lpips" in ev else ""
    console.print(
        f"{split}: {ev['frames']} frames, PSNR {ev['psnr']:.2f} dB, SSIM {ev['ssim']:.4f}{lp}, "
        f"{len(g)} Gaussians" + (f" -> {out}" if out else "")
    )
    report_json(json_out, ev)
