"""`acesplat import`: write the ACE layout from a transforms.json, a COLMAP model or a ROS 2 bag."""

from __future__ import annotations

import enum
from pathlib import Path

import typer

from acesplat.apps.support import CountProgress, one_line_errors, option, report_json
from acesplat.importers.common import ImportConfig
from acesplat.importers.dispatch import import_scene
from acesplat.importers.rosbag import RosbagImportConfig


class SourceFormat(str, enum.Enum):
    auto = "auto"
    transforms = "transforms"
    colmap = "colmap"
    rosbag = "rosbag"


@one_line_errors
def import_command(
    src: Path = typer.Argument(
        ...,
        help="transforms.json (or its folder), a COLMAP model folder (or a project with sparse/0), "
        "or a ROS 2 bag (folder with metadata.yaml, or a .mcap / .db3 file).",
    ),
    out: Path = typer.Option(..., "-o", "--out", help="Scene folder to create (must be new or empty)."),
    fmt: SourceFormat = typer.Option(SourceFormat.auto, "--format", help="Source format; auto detects it."),
    images: Path | None = typer.Option(
        None,
        "--images",
        help="Images folder (COLMAP: default images/ near the model; transforms: replaces the json's folder).",
    ),
    test_every: int = option(
        ImportConfig,
        "test_every",
        "--test-every",
        min=0,
        help="Every N-th frame (natural name order, from the first) goes to test; 0 = none. "
        "ROS bags: the last of every N time blocks (--test-block).",
    ),
    json_out: Path | None = typer.Option(None, "--json", help="Write the summary (counts, split rule, notes) as JSON."),
    image_topic: str | None = option(RosbagImportConfig, "image_topic", "--image-topic"),
    pose_topic: str | None = option(RosbagImportConfig, "pose_topic", "--pose-topic"),
    tf: str | None = option(RosbagImportConfig, "tf", "--tf"),
    camera_info_topic: str | None = option(RosbagImportConfig, "camera_info_topic", "--camera-info-topic"),
    optical: bool | None = option(RosbagImportConfig, "optical", "--optical/--body"),
    every: int = option(RosbagImportConfig, "every", "--every", min=1),
    min_baseline: float = option(RosbagImportConfig, "min_baseline", "--min-baseline", min=0.0),
    pose_tolerance: float = option(RosbagImportConfig, "pose_tolerance", "--pose-tolerance"),
    test_block: float = option(RosbagImportConfig, "test_block", "--test-block"),
) -> None:
    """Import a scene into the ACE layout (OpenCV poses, undistorted images, train/test split)."""
    with CountProgress("importing") as progress:
        bag = RosbagImportConfig(
            image_topic=image_topic, pose_topic=pose_topic, tf=tf, camera_info_topic=camera_info_topic,
            optical=optical, every=every, min_baseline=min_baseline, pose_tolerance=pose_tolerance,
            test_block=test_block,
        )  # fmt: skip
        summary = import_scene(
            src, out, fmt=fmt.value, images_dir=images, test_every=test_every, progress=progress, rosbag=bag
        )
    print(f"imported {summary.train + summary.test} frames ({summary.format}) from {summary.source} -> {summary.scene}")
    print(f"  train {summary.train}, test {summary.test}: {summary.split_rule}")
    if summary.undistorted:
        print(f"  undistorted {summary.undistorted} images with OpenCV")
    if summary.rescaled:
        print(f"  rescaled intrinsics of {summary.rescaled} images whose size differs from their camera's")
    for note in summary.notes:
        print(f"  note: {note}")
    report_json(json_out, summary.as_dict())
