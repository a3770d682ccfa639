"""Pick the importer for a source path: a transforms.json (file or folder) or a COLMAP text model."""

from __future__ import annotations

from pathlib import Path

from acesplat.core.errors import InputError
from acesplat.importers.colmap_text import find_colmap_model, import_colmap_text
from acesplat.importers.common import ImportSummary, Progress, default_test_every
from acesplat.importers.transforms_json import SPLIT_FILES, import_transforms_json

FORMATS = ("auto", "transforms", "colmap")


def detect_format(src: str | Path) -> str:
    """'transforms' or 'colmap' for ``src``; InputError naming ``src`` when it is neither."""
    src = Path(src)
    if not src.exists():
        raise InputError(src, "source does not exist")
    if src.is_file():
        if src.suffix.lower() == ".json":
            return "transforms"
        if src.name in ("cameras.txt", "images.txt"):
            return "colmap"
        raise InputError(src, "not a transforms .json nor a COLMAP cameras.txt/images.txt")
    if (src / "transforms.json").is_file() or all((src / f).is_file() for f in SPLIT_FILES):
        return "transforms"
    find_colmap_model(src)  # raises a precise error (binary model, nothing found)
    return "colmap"


def import_scene(
    src: str | Path,
    out_scene: str | Path,
    fmt: str = "auto",
    images_dir: str | Path | None = None,
    test_every: int = default_test_every(),
    progress: Progress | None = None,
) -> ImportSummary:
    """Import ``src`` into the ACE layout at ``out_scene`` with the importer ``fmt`` names (or detects)."""
    if fmt not in FORMATS:
        raise InputError(None, f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    src = Path(src)
    kind = detect_format(src) if fmt == "auto" else fmt
    if kind == "transforms":
        return import_transforms_json(src, out_scene, test_every=test_every, images_dir=images_dir, progress=progress)
    model_dir = src.parent if src.is_file() else src
    return import_colmap_text(model_dir, images_dir, out_scene, test_every=test_every, progress=progress)
