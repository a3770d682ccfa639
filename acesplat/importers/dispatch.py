"""Pick the importer for a source path: a transforms.json (file or folder), a COLMAP model (text or binary) or a
ROS 2 bag (a folder with metadata.yaml, or a .mcap / .db3 file)."""

from __future__ import annotations

from pathlib import Path

from acesplat.core.errors import InputError
from acesplat.importers.colmap_binary import import_colmap
from acesplat.importers.colmap_text import find_colmap_model
from acesplat.importers.common import ImportSummary, Progress, default_test_every
from acesplat.importers.rosbag import BAG_SUFFIXES, RosbagImportConfig, import_rosbag
from acesplat.importers.transforms_json import SPLIT_FILES, import_transforms_json

FORMATS = ("auto", "transforms", "colmap", "rosbag")


def detect_format(src: str | Path) -> str:
    """'transforms', 'colmap' or 'rosbag' for ``src``; InputError naming ``src`` when it is none of them."""
    src = Path(src)
    if not src.exists():
        raise InputError(src, "source does not exist")
    if src.is_file():
        if src.suffix.lower() == ".json":
            return "transforms"
        if src.name in ("cameras.txt", "images.txt", "cameras.bin", "images.bin"):
            return "colmap"
        if src.name == "metadata.yaml" or src.suffix.lower() in BAG_SUFFIXES:
            return "rosbag"
        raise InputError(src, "not a transforms .json, a COLMAP cameras/images file nor a ROS 2 bag")
    if (src / "transforms.json").is_file() or all((src / f).is_file() for f in SPLIT_FILES):
        return "transforms"
    if (src / "metadata.yaml").is_file() or any(p.suffix.lower() in BAG_SUFFIXES for p in src.iterdir()):
        return "rosbag"
    find_colmap_model(src, binary=True)  # raises a precise error (nothing found)
    return "colmap"


def import_scene(
    src: str | Path,
    out_scene: str | Path,
    fmt: str = "auto",
    images_dir: str | Path | None = None,
    test_every: int = default_test_every(),
    progress: Progress | None = None,
    rosbag: RosbagImportConfig | None = None,
) -> ImportSummary:
    """Import ``src`` into the ACE layout at ``out_scene`` with the importer ``fmt`` names (or detects).

    ``rosbag`` holds the topics and frame selection of a ROS 2 bag; it is refused for other formats.
    """
    if fmt not in FORMATS:
        raise InputError(None, f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    src = Path(src)
    kind = detect_format(src) if fmt == "auto" else fmt
    if kind == "rosbag":
        if images_dir is not None:
            raise InputError(src, "a ROS bag holds its images: --images does not apply")
        return import_rosbag(src, out_scene, rosbag, test_every=test_every, progress=progress)
    if rosbag is not None and rosbag != RosbagImportConfig():
        raise InputError(src, f"ROS bag options (topics, TF, frame selection) do not apply to a {kind} source")
    if kind == "transforms":
        return import_transforms_json(src, out_scene, test_every=test_every, images_dir=images_dir, progress=progress)
    model_dir = src.parent if src.is_file() else src
    return import_colmap(model_dir, images_dir, out_scene, test_every=test_every, progress=progress)
