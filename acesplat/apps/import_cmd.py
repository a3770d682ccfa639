"""`acesplat import`: write the ACE layout from a transforms.json or a COLMAP text model."""

from __future__ import annotations

import enum
from pathlib import Path

import typer

from acesplat.apps.support import CountProgress, one_line_errors, option, report_json
from acesplat.importers.common import ImportConfig
from acesplat.importers.dispatch import import_scene


class SourceFormat(str, enum.Enum):
    auto = "auto"
    transforms = "transforms"
    colmap = "colmap"


@one_line_errors
def import_command(
    src: Path = typer.Argument(
        ..., help="transforms.json (or its folder), or a COLMAP text model folder (or a project with sparse/0)."
    ),
    out: Path = typer.Option(..., "-o", "--out", help="Scene folder to create (must be new or empty)."),
    fmt: SourceFormat = typer.Option(SourceFormat.auto, "--format", help="Source format; auto detects it."),
    images: Path | None = typer.Option(
        None,
        "--images",
        help="Images folder (COLMAP: default images/ near the model; transforms: replaces the json's folder).",
    ),
    test_every: int = option(ImportConfig, "test_every", "--test-every", min=0),
    json_out: Path | None = typer.Option(None, "--json", help="Write the summary (counts, split rule, notes) as JSON."),
) -> None:
    """Import a scene into the ACE layout (OpenCV poses, undistorted images, train/test split)."""
    with CountProgress("importing") as progress:
        summary = import_scene(src, out, fmt=fmt.value, images_dir=images, test_every=test_every, progress=progress)
    print(f"imported {summary.train + summary.test} frames ({summary.format}) from {summary.source} -> {summary.scene}")
    print(f"  train {summary.train}, test {summary.test}: {summary.split_rule}")
    if summary.undistorted:
        print(f"  undistorted {summary.undistorted} images with OpenCV")
    if summary.rescaled:
        print(f"  rescaled intrinsics of {summary.rescaled} images whose size differs from their camera's")
    for note in summary.notes:
        print(f"  note: {note}")
    report_json(json_out, summary.as_dict())
