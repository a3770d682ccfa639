"""Import a COLMAP text model (``cameras.txt`` + ``images.txt``) into the ACE layout.

Facts about the format this relies on:
- ``cameras.txt``: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...``; principal points put the centre of
  the top-left pixel at (0.5, 0.5) (shifted to OpenCV's (0, 0) on import).
- ``images.txt``: two lines per image. ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` is the
  world-to-camera transform (OpenCV axes), inverted here to camera-to-world; the next line lists
  the 2D points and may be empty. NAME is relative to the images folder and may contain spaces.

Distortion: SIMPLE_RADIAL, RADIAL, OPENCV and FULL_OPENCV use OpenCV's own distortion formulas, so
their images are undistorted with OpenCV on import (see ``common.Undistorter``); fisheye and FOV
models are refused with a pointer to ``colmap image_undistorter``. Scale is the model's (metres only
if the reconstruction was made metric).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from acesplat.core.errors import InputError
from acesplat.core.geometry import invert_pose, make_pose, quat_to_matrix, rigidity_problem
from acesplat.importers.common import (
    CameraSpec,
    ImportSummary,
    Progress,
    SourceFrame,
    check_output,
    check_test_every,
    default_test_every,
    write_scene,
)

MODEL_PARAMS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}
REFUSED_MODELS = {
    "OPENCV_FISHEYE", "FOV", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE",
    "RAD_TAN_THIN_PRISM_FISHEYE", "SIMPLE_DIVISION", "DIVISION",
}  # fmt: skip
CV_DIST_ORDER = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


def _data_lines(path: Path) -> list[tuple[int, str]]:
    """(1-based line number, text) of every non-comment line, blank lines kept (an empty 2D-points line)."""
    if not path.is_file():
        raise InputError(path, "file does not exist")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputError(
            path, "not a text file (binary COLMAP model? convert with colmap model_converter --output_type TXT)"
        ) from None
    return [(n, line.rstrip("\r\n")) for n, line in enumerate(text.split("\n"), 1) if not line.lstrip().startswith("#")]


def _floats(tokens: list[str], path: Path, n: int, what: str) -> list[float]:
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        raise InputError(path, f"line {n}: {what} must be numbers, got {' '.join(tokens)!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise InputError(path, f"line {n}: {what} has non-finite values ({' '.join(tokens)})")
    return values


def _int(token: str, path: Path, n: int, what: str) -> int:
    try:
        return int(token)
    except ValueError:
        raise InputError(path, f"line {n}: {what} must be an integer, got {token!r}") from None


def read_cameras_txt(path: Path) -> dict[int, CameraSpec]:
    """CAMERA_ID -> intrinsics (source pixel convention; see ``CameraSpec``)."""
    cameras: dict[int, CameraSpec] = {}
    for n, line in _data_lines(path):
        tokens = line.split()
        if not tokens:
            continue
        if len(tokens) < 4:
            raise InputError(path, f"line {n}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..., got {line.strip()!r}")
        cam_id = _int(tokens[0], path, n, "CAMERA_ID")
        model = tokens[1].upper()
        if model in REFUSED_MODELS:
            raise InputError(
                path,
                f"line {n}: camera model {model} is not supported (fisheye/FOV); run `colmap image_undistorter` "
                "and import its output (PINHOLE cameras)",
            )
        if model not in MODEL_PARAMS:
            raise InputError(
                path, f"line {n}: unknown camera model {tokens[1]!r} (supported: {', '.join(MODEL_PARAMS)})"
            )
        width, height = _int(tokens[2], path, n, "WIDTH"), _int(tokens[3], path, n, "HEIGHT")
        if width <= 0 or height <= 0:
            raise InputError(path, f"line {n}: image size must be positive, got {width}x{height}")
        names = MODEL_PARAMS[model]
        if len(tokens) - 4 != len(names):
            raise InputError(
                path, f"line {n}: {model} needs {len(names)} parameters ({' '.join(names)}), got {len(tokens) - 4}"
            )
        p = dict(zip(names, _floats(tokens[4:], path, n, "camera parameters")))
        spec = camera_spec(p, width, height, path, f"line {n}")
        if cam_id in cameras:
            raise InputError(path, f"line {n}: CAMERA_ID {cam_id} defined twice")
        cameras[cam_id] = spec
    if not cameras:
        raise InputError(path, "no cameras defined")
    return cameras


def camera_spec(p: dict[str, float], width: int, height: int, path: Path, where: str) -> CameraSpec:
    """A camera from its model's named parameters ``p`` (MODEL_PARAMS); InputError naming ``where`` in ``path`` if
    the focal length is not positive. Distortion in OpenCV's order, 4 or 8 terms; () when there is none."""
    fx, fy = (p["f"], p["f"]) if "f" in p else (p["fx"], p["fy"])
    if fx <= 0 or fy <= 0:
        raise InputError(path, f"{where}: focal length must be positive, got fx={fx} fy={fy}")
    dist = tuple(p.get(k, 0.0) for k in CV_DIST_ORDER[: 8 if "k3" in p else 4])  # OpenCV takes 4 or 8
    return CameraSpec(fx=fx, fy=fy, cx=p["cx"], cy=p["cy"], width=width, height=height, dist=dist if any(dist) else ())


def read_images_txt(path: Path, cameras: dict[int, CameraSpec], images_dir: Path) -> list[SourceFrame]:
    """Posed frames (camera-to-world, OpenCV axes) from ``images.txt``; each image must exist on disk."""
    lines = _data_lines(path)
    frames: list[SourceFrame] = []
    i = 0
    while i < len(lines):
        n, line = lines[i]
        if not line.strip():  # blank line where an image line could start (e.g. at the end of the file)
            i += 1
            continue
        parts = line.strip().split(None, 9)
        if len(parts) < 10:
            raise InputError(
                path, f"line {n}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, got {len(parts)} fields"
            )
        _int(parts[0], path, n, "IMAGE_ID")
        qw, qx, qy, qz, tx, ty, tz = _floats(parts[1:8], path, n, "QW QX QY QZ TX TY TZ")
        cam_id = _int(parts[8], path, n, "CAMERA_ID")
        if cam_id not in cameras:
            raise InputError(path, f"line {n}: CAMERA_ID {cam_id} is not defined in cameras.txt")
        q = np.array([qw, qx, qy, qz])
        if np.linalg.norm(q) < 1e-8:
            raise InputError(path, f"line {n}: quaternion is zero")
        if i + 1 < len(lines):  # the 2D points line: X Y POINT3D_ID triples, possibly none
            pn, points = lines[i + 1]
            tokens = points.split()
            if len(tokens) % 3 or (tokens and not tokens[-1].lstrip("-").isdigit()):
                raise InputError(
                    path, f"line {pn}: expected the 2D points line (X Y POINT3D_ID ...) of the image on line {n}"
                )
        name = parts[9].strip()
        image = images_dir / name
        if not image.is_file():
            raise InputError(image, f"image listed in {path} line {n} does not exist")
        T = invert_pose(make_pose(quat_to_matrix(q), [tx, ty, tz]))
        problem = rigidity_problem(T)
        if problem:  # not reachable with a normalised quaternion and finite t; kept as a guard
            raise InputError(path, f"line {n}: {problem}")
        frames.append(
            SourceFrame(name=name, image_path=image, pose=T, camera=cameras[cam_id], where=f"{path} line {n}")
        )
        i += 2
    if not frames:
        raise InputError(path, "no images listed")
    return frames


def find_colmap_model(src: Path, binary: bool = False) -> Path:
    """The folder holding ``cameras.txt`` + ``images.txt`` (or, with ``binary``, ``cameras.bin`` + ``images.bin``):
    ``src``, ``src/sparse/0`` or ``src/sparse``."""
    candidates = [src, src / "sparse" / "0", src / "sparse"]
    for d in candidates:
        if (d / "cameras.txt").is_file() and (d / "images.txt").is_file():
            return d
        if binary and (d / "cameras.bin").is_file() and (d / "images.bin").is_file():
            return d
    for d in candidates:
        if (d / "cameras.bin").is_file():
            if binary:
                raise InputError(d, "binary COLMAP model with cameras.bin but no images.bin")
            raise InputError(
                d,
                "binary COLMAP model; import it with `acesplat import` (import_colmap_binary) or convert it: "
                f"colmap model_converter --input_path {d} --output_path {d} --output_type TXT",
            )
    what = "model (cameras.txt + images.txt, or .bin)" if binary else "text model (cameras.txt + images.txt)"
    raise InputError(src, f"no COLMAP {what} here or in sparse/0 or sparse/")


def find_images_dir(model_dir: Path) -> Path:
    """``images/`` beside the model, or up to two levels above it (``scene/sparse/0`` -> ``scene/images``)."""
    for d in (model_dir, model_dir.parent, model_dir.parent.parent):
        if (d / "images").is_dir():
            return d / "images"
    raise InputError(model_dir, "no images/ folder found next to the COLMAP model; pass the images folder explicitly")


def import_colmap_text(
    model_dir: str | Path,
    images_dir: str | Path | None,
    out_scene: str | Path,
    test_every: int = default_test_every(),
    image_ext: str = ".png",
    progress: Progress | None = None,
) -> ImportSummary:
    """Write the ACE layout at ``out_scene`` from a COLMAP text model.

    ``model_dir`` is the model folder (or a project folder with ``sparse/0``); ``images_dir`` the
    folder NAME is relative to (None: look for ``images/`` near the model). Every ``test_every``-th
    image (natural name order, starting with the first) goes to test.
    """
    check_test_every(test_every)
    check_output(out_scene)  # before parsing a large model
    model = find_colmap_model(Path(model_dir))
    images = find_images_dir(model) if images_dir is None else Path(images_dir)
    if not images.is_dir():
        raise InputError(images, "images folder does not exist")
    cameras = read_cameras_txt(model / "cameras.txt")
    frames = read_images_txt(model / "images.txt", cameras, images)
    summary = ImportSummary(source=str(model), format="colmap", scene=str(out_scene))
    return write_scene(frames, out_scene, summary, test_every=test_every, image_ext=image_ext, progress=progress)
