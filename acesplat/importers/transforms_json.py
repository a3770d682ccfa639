"""Import an instant-ngp / nerfstudio / Blender-NeRF ``transforms.json`` into the ACE layout.

Facts about the format this relies on:
- ``frames[i].transform_matrix`` is camera-to-world with OpenGL camera axes (x right, y up, z back);
  right-multiplying by ``OPENGL_TO_OPENCV`` gives the project's OpenCV axes.
- Intrinsics ``fl_x fl_y cx cy w h`` (or ``camera_angle_x``/``camera_angle_y``, the fields of view
  in radians) and distortion ``k1 k2 k3 k4 p1 p2`` sit at the top level or per frame (per frame wins).
- ``file_path`` is relative to the json's folder, with or without the image extension.
- nerfstudio's ``applied_transform`` records what ``ns-process-data`` did to the COLMAP world; the
  frames are already expressed after it, so it is reported, never applied again.
- Scale is the source's (metres only if the source reconstruction was metric).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from acesplat.core.errors import InputError
from acesplat.core.geometry import OPENGL_TO_OPENCV, rigidity_problem
from acesplat.importers.common import (
    CameraSpec,
    ImportSummary,
    Progress,
    SourceFrame,
    check_output,
    check_test_every,
    default_test_every,
    find_image,
    write_scene,
)

INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y")
DIST_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
PERSPECTIVE_MODELS = {"OPENCV", "PINHOLE", "SIMPLE_PINHOLE"}
SPLIT_FILES = ("transforms_train.json", "transforms_test.json")


def _load(path: Path) -> dict:
    if not path.is_file():
        raise InputError(path, "file does not exist")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise InputError(path, f"not valid JSON: {e.msg} at line {e.lineno} column {e.colno}") from None
    except UnicodeDecodeError:
        raise InputError(path, "not a text file") from None
    if not isinstance(data, dict):
        raise InputError(path, "top level must be a JSON object with a 'frames' list")
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise InputError(path, "missing or empty 'frames' list")
    return data


def _number(value: Any, path: Path, where: str, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(path, f"{where}: '{key}' must be a number, got {value!r}")
    if not math.isfinite(value):
        raise InputError(path, f"{where}: '{key}' is not finite ({value})")
    return float(value)


def _camera(glob: dict, frame: dict, path: Path, where: str) -> CameraSpec:
    """Intrinsics of one frame: per-frame keys override the top-level ones."""
    merged = {k: frame.get(k, glob.get(k)) for k in INTRINSIC_KEYS + DIST_KEYS + ("camera_model", "is_fisheye")}
    model = merged["camera_model"]
    if merged["is_fisheye"] or (model is not None and str(model).upper() not in PERSPECTIVE_MODELS):
        raise InputError(
            path,
            f"{where}: camera model {model or 'fisheye'!r} is not supported "
            f"(supported: {', '.join(sorted(PERSPECTIVE_MODELS))}); undistort to a pinhole camera first",
        )
    v = {k: None if merged[k] is None else _number(merged[k], path, where, k) for k in INTRINSIC_KEYS + DIST_KEYS}
    for key in ("fl_x", "fl_y", "w", "h"):
        if v[key] is not None and v[key] <= 0:
            raise InputError(path, f"{where}: '{key}' must be positive, got {v[key]}")
    for key in ("w", "h"):
        if v[key] is not None and v[key] != int(v[key]):
            raise InputError(path, f"{where}: '{key}' must be a whole number of pixels, got {v[key]}")
    for key in ("camera_angle_x", "camera_angle_y"):
        if v[key] is not None and not 0.0 < v[key] < math.pi:
            raise InputError(path, f"{where}: '{key}' is a field of view in radians, must be in (0, pi), got {v[key]}")
    if v["fl_x"] is None and v["camera_angle_x"] is None:
        raise InputError(path, f"{where}: no focal length (need 'fl_x' or 'camera_angle_x')")
    if (v["w"] is None) != (v["h"] is None):
        raise InputError(path, f"{where}: 'w' and 'h' must be given together")
    if v["k4"]:
        raise InputError(path, f"{where}: 'k4' is only used by fisheye models, which are not supported")
    d = {k: v[k] or 0.0 for k in DIST_KEYS}
    dist = (d["k1"], d["k2"], d["p1"], d["p2"], d["k3"])
    return CameraSpec(
        fx=v["fl_x"],
        fy=v["fl_y"],
        cx=v["cx"],
        cy=v["cy"],
        width=None if v["w"] is None else int(v["w"]),
        height=None if v["h"] is None else int(v["h"]),
        angle_x=v["camera_angle_x"],
        angle_y=v["camera_angle_y"],
        dist=dist if any(dist) else (),
    )


def _pose(raw: Any, path: Path, where: str) -> np.ndarray:
    """OpenCV camera-to-world from an OpenGL ``transform_matrix`` (4x4, or 3x4 without the last row)."""
    try:
        T = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, f"{where}: 'transform_matrix' must be a 4x4 list of numbers") from None
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4):
        raise InputError(path, f"{where}: 'transform_matrix' must be 4x4, got shape {T.shape}")
    T = T @ OPENGL_TO_OPENCV
    problem = rigidity_problem(T)
    if problem:
        raise InputError(path, f"{where}: transform_matrix: {problem}")
    return T


def read_transforms_frames(
    path: Path, images_dir: Path | None = None, test: bool | None = None
) -> tuple[list[SourceFrame], dict]:
    """The frames of one transforms file, validated, plus its top-level fields."""
    data = _load(path)
    base = images_dir if images_dir is not None else path.parent
    frames = []
    for i, fr in enumerate(data["frames"]):
        where = f"frames[{i}]"
        if not isinstance(fr, dict):
            raise InputError(path, f"{where} must be an object")
        for key in ("file_path", "transform_matrix"):
            if key not in fr:
                raise InputError(path, f"{where}: missing '{key}'")
        rel = fr["file_path"]
        if not isinstance(rel, str) or not rel.strip():
            raise InputError(path, f"{where}: 'file_path' must be a non-empty string")
        rel_path = Path(rel.replace("\\", "/"))
        image = find_image(base / rel_path)
        if image is None and images_dir is not None:
            image = find_image(images_dir / rel_path.name)  # --images pointing at a flat (e.g. downscaled) copy
        if image is None:
            raise InputError(
                path, f"{where}: image {str(base / rel_path)!r} not found (tried with and without extension)"
            )
        name = rel_path.as_posix()
        name = name[2:] if name.startswith("./") else name
        frames.append(
            SourceFrame(
                name=name,
                image_path=image,
                pose=_pose(fr["transform_matrix"], path, where),
                camera=_camera(data, fr, path, where),
                where=f"{path} {where}",
                test=test,
            )
        )
    return frames, data


def import_transforms_json(
    transforms_path: str | Path,
    out_scene: str | Path,
    test_every: int = default_test_every(),
    images_dir: str | Path | None = None,
    image_ext: str = ".png",
    progress: Progress | None = None,
) -> ImportSummary:
    """Write the ACE layout at ``out_scene`` from a ``transforms.json`` (file, or folder holding it).

    A folder without ``transforms.json`` but with ``transforms_train.json`` and ``transforms_test.json``
    (the Blender NeRF datasets) keeps that split; ``transforms_val.json`` is not imported. Otherwise
    every ``test_every``-th frame (natural name order, starting with the first) goes to test.
    ``images_dir`` replaces the json's folder as the base of ``file_path`` (e.g. a downscaled copy).
    """
    check_test_every(test_every)
    check_output(out_scene)  # before parsing a large model
    src = Path(transforms_path)
    images = None if images_dir is None else Path(images_dir)
    if images is not None and not images.is_dir():
        raise InputError(images, "images folder does not exist")
    summary = ImportSummary(source=str(src), format="transforms", scene=str(out_scene))
    if src.is_dir() and not (src / "transforms.json").is_file():
        if not all((src / f).is_file() for f in SPLIT_FILES):
            raise InputError(
                src, "no transforms.json (nor transforms_train.json + transforms_test.json) in this folder"
            )
        frames, tops = [], []
        for fname, is_test in zip(SPLIT_FILES, (False, True)):
            part, top = read_transforms_frames(src / fname, images, test=is_test)
            frames += part
            tops.append(top)
        if (src / "transforms_val.json").is_file():
            summary.notes.append("transforms_val.json not imported (train and test splits only)")
    else:
        path = src / "transforms.json" if src.is_dir() else src
        frames, top = read_transforms_frames(path, images)
        tops = [top]
    if any("applied_transform" in t for t in tops):
        summary.notes.append(
            "applied_transform present: it records what was done to the original (COLMAP) world; "
            "frames are already in the transformed world, so it was not applied again"
        )
    return write_scene(frames, out_scene, summary, test_every=test_every, image_ext=image_ext, progress=progress)
