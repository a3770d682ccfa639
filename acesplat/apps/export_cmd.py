"""`acesplat export`: torch, onnx and onnxruntime's quantizer are imported inside the command."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from acesplat.apps.support import PhaseProgress, one_line_errors, option, parse_size, report_json
from acesplat.core.config import knob_help
from export.options import ExportOptions

console = Console()


def _fmt(v: object) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def checks_table(manifest: dict) -> Table:
    """The self-check numbers as they go into the manifest."""
    checks = manifest["checks"]
    t = Table(title=f"bundle self-checks ({manifest['scr']['input_size'][0]}x{manifest['scr']['input_size'][1]})")
    t.add_column("check")
    t.add_column("value", justify="right")
    par = checks["fp32_vs_torch"]
    t.add_row("FP32 ONNX vs torch: max |diff| (m)", _fmt(par["max_abs_diff_m"]))
    t.add_row("  as a fraction of the scene extent", _fmt(par["max_abs_diff_fraction"]))
    t.add_row("  scene extent (m)", _fmt(par["scene_extent_m"]))
    t.add_row(
        "  max pose difference (m / deg)",
        f"{_fmt(par['pose_max_translation_diff_m'])} / {_fmt(par['pose_max_rotation_diff_deg'])}",
    )
    if par.get("features_max_abs_diff") is not None:
        t.add_row(
            "FP32 ONNX vs torch: encoder features max |diff| / max |feature|",
            f"{_fmt(par['features_max_abs_diff'])} / {_fmt(par['features_max_abs'])}",
        )
    lr = manifest["scr"].get("encoder_lowrank")
    if lr:
        t.add_row(
            f"encoder {lr['layer']} at rank {lr['rank']}: variance kept on the training images",
            f"{lr['kept_variance']:.4f}",
        )
        if lr.get("coord_median") is not None:
            t.add_row(
                "  against the exact encoder: coordinate median / p90 (cm)",
                f"{100 * lr['coord_median']:.2f} / {100 * lr['coord_p90']:.2f}",
            )
        if lr.get("pose_median_translation") is not None:
            t.add_row(
                "  against the exact encoder: pose median (cm / deg)",
                f"{100 * lr['pose_median_translation']:.2f} / {lr['pose_median_rotation_deg']:.3f}",
            )
    for prec in ("int8", "int8_vnni"):
        dev = checks.get(f"{prec}_vs_fp32")
        if not dev:
            continue
        t.add_row(
            f"{prec.upper()} vs FP32 on {dev['frames']} check frames: coordinate median / p90 (cm)",
            f"{100 * dev['coord_median']:.2f} / {100 * dev['coord_p90']:.2f}",
        )
        if dev.get("pose_median_translation") is not None:
            t.add_row(
                "  pose median (cm / deg)",
                f"{100 * dev['pose_median_translation']:.2f} / {dev['pose_median_rotation_deg']:.3f}",
            )
    acc = checks.get("test_split")
    if acc:
        for prec in ("fp32", "int8", "int8_vnni"):
            a = acc.get(prec)
            if a is None:
                continue
            t.add_row(f"{prec.upper()} test: localized / frames", f"{a['localized']} / {a['frames']}")
            t.add_row(
                f"{prec.upper()} test: median (m / deg)",
                f"{_fmt(a['median_translation_m'])} / {_fmt(a['median_rotation_deg'])}",
            )
            t.add_row(
                f"{prec.upper()} test: recall 5cm/5deg, 10cm/5deg, 25cm/2deg (%)",
                f"{a['recall_5cm_5deg']:.1f}, {a['recall_10cm_5deg']:.1f}, {a['recall_25cm_2deg']:.1f}",
            )
    elif checks.get("test_split_note"):
        t.add_row("INT8 accuracy", checks["test_split_note"])
    if "splat_init_fp32_vs_torch" in checks:
        par = checks["splat_init_fp32_vs_torch"]
        t.add_row(
            "splat initializer ONNX vs torch: max |diff| / max |output|",
            f"{_fmt(par['max_abs_diff'])} / {_fmt(par['max_abs_output'])}",
        )
        probe = checks.get("splat_init_probe_fp32_vs_torch")
        if probe:
            t.add_row(
                "  untrained head (zero residuals); a random output layer: max |diff| / max |output|",
                f"{_fmt(probe['max_abs_diff'])} / {_fmt(probe['max_abs_output'])}",
            )
        for prec in ("fp32", "int8", "int8_vnni"):
            via = checks.get(f"splat_init_via_scr_{prec}_vs_torch")
            if via:
                t.add_row(
                    f"  fed the {prec.upper()} SCR graph's features: max / mean |diff|",
                    f"{_fmt(via['max_abs_diff'])} / {_fmt(via['mean_abs_diff'])}",
                )
    return t


@one_line_errors
def export_command(
    map_path: Path = typer.Argument(..., metavar="MAP", help="Map file from `acesplat map`."),
    out: Path = typer.Option(..., "-o", "--out", help="Bundle directory to write (replaced if it is a bundle)."),
    int8: bool = option(ExportOptions, "int8", "--int8"),
    size: str | None = typer.Option(None, help=knob_help(ExportOptions, "size_hw")),
    encoder: Path | None = option(ExportOptions, "encoder_path", "--encoder"),
    scene: Path | None = option(ExportOptions, "scene_path", "--scene"),
    json_out: Path | None = typer.Option(None, "--json", help="Write the manifest and timings here."),
    splat: Path | None = typer.Option(
        None, "--splat", help="Splat folder from `acesplat splat`: add its Gaussians and initializer (edge refinement)."
    ),
    dense: bool = option(ExportOptions, "dense"),
    keyframes: bool = option(ExportOptions, "keyframes"),
    encoder_rank: int = option(ExportOptions, "encoder_rank"),
    int8_format: str = option(ExportOptions, "int8_format"),
    int8_types: str = option(ExportOptions, "int8_types"),
    int8_per_channel: bool = option(ExportOptions, "int8_per_channel", "--int8-per-channel/--int8-per-tensor"),
    int8_reduce_range: bool = option(ExportOptions, "int8_reduce_range"),
    int8_vnni: bool = option(ExportOptions, "int8_vnni"),
    int8_calibration: str = option(ExportOptions, "int8_calibration"),
    int8_percentile: float = option(ExportOptions, "int8_percentile"),
    check_frames: int = option(ExportOptions, "check_frames"),
) -> None:
    """Export a map to an ONNX bundle (FP32, optionally INT8) that checks itself."""
    import torch

    from acesplat.core.errors import InputError
    from export.bundle_export import export_bundle

    if dense and splat is not None:
        raise InputError(splat, "--splat needs the stride-8 SCR graph its initializer was trained on; drop --dense")
    torch.set_num_threads(max(1, torch.get_num_threads()))
    opts = ExportOptions(
        int8=int8,
        size_hw=parse_size(size) if size else None,
        encoder_path=encoder,
        scene_path=scene,
        dense=dense,
        keyframes=keyframes,
        encoder_rank=encoder_rank,
        int8_format=int8_format,
        int8_types=int8_types,
        int8_per_channel=int8_per_channel,
        int8_reduce_range=int8_reduce_range,
        int8_vnni=int8_vnni,
        int8_calibration=int8_calibration,
        int8_percentile=int8_percentile,
        check_frames=check_frames,
    )
    with PhaseProgress() as bar:
        rep = export_bundle(map_path, out, opts, bar)
        if splat is not None:
            from export.splat_export import export_splat

            rep.manifest = export_splat(out, splat, map_path, encoder, bar)["manifest"]
    console.print(checks_table(rep.manifest))
    files = ", ".join(f"{f['path']} ({f['bytes'] / 1e6:.2f} MB)" for f in rep.manifest["files"])
    console.print(f"bundle {out}: {files}; {rep.seconds:.1f} s")
    report_json(
        json_out, {"bundle": str(out), "seconds": rep.seconds, "timings": rep.timings, "manifest": rep.manifest}
    )
