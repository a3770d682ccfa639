"""Import a COLMAP binary model (``cameras.bin`` + ``images.bin``, COLMAP's default output) into the ACE layout.

The records are the text model's (``colmap_text``): the same camera models, distortion handling, pose inversion and
split. Facts about the format (little-endian, COLMAP's ``src/colmap/scene/reconstruction_io.cc``):
- ``cameras.bin``: uint64 count, then per camera int32 CAMERA_ID, int32 MODEL_ID, uint64 WIDTH, uint64 HEIGHT and the
  model's parameters as float64;
- ``images.bin``: uint64 count, then per image int32 IMAGE_ID, float64 QW QX QY QZ TX TY TZ (world-to-camera),
  int32 CAMERA_ID, the NUL-terminated NAME, uint64 number of 2D points and that many (float64 X, float64 Y,
  int64 POINT3D_ID).
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np

from acesplat.core.errors import InputError
from acesplat.core.geometry import invert_pose, make_pose, quat_to_matrix
from acesplat.importers.colmap_text import (
    MODEL_PARAMS,
    REFUSED_MODELS,
    camera_spec,
    find_colmap_model,
    find_images_dir,
    import_colmap_text,
)
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

MODEL_IDS = {
    0: "SIMPLE_PINHOLE", 1: "PINHOLE", 2: "SIMPLE_RADIAL", 3: "RADIAL", 4: "OPENCV", 5: "OPENCV_FISHEYE",
    6: "FULL_OPENCV", 7: "FOV", 8: "SIMPLE_RADIAL_FISHEYE", 9: "RADIAL_FISHEYE", 10: "THIN_PRISM_FISHEYE",
    11: "RAD_TAN_THIN_PRISM_FISHEYE", 12: "SIMPLE_DIVISION", 13: "DIVISION",
}  # fmt: skip
"""COLMAP's camera model ids (``CameraModelId``)."""
MAX_NAME = 4096
"""Longest image name accepted (a missing NUL terminator would otherwise read to the end of the file)."""


class _Bytes:
    """A cursor over a binary file that reports truncation as an InputError naming the file and the record."""

    def __init__(self, path: Path) -> None:
        if not path.is_file():
            raise InputError(path, "file does not exist")
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def take(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.data):
            raise InputError(self.path, f"truncated: {what} needs {size} bytes at byte {self.pos}, file ends at "
                             f"{len(self.data)}")  # fmt: skip
        values = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += size
        return values

    def name(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos, self.pos + MAX_NAME + 1)
        if end < 0:
            raise InputError(self.path, f"truncated or corrupt: {what} has no NUL-terminated name at byte {self.pos}")
        raw = self.data[self.pos : end]
        self.pos = end + 1
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise InputError(self.path, f"corrupt: {what} name is not UTF-8 ({raw[:40]!r})") from None
        if not text or any(ord(ch) < 32 for ch in text):
            raise InputError(self.path, f"corrupt: {what} name {text[:40]!r} is empty or has control characters")
        return text

    def count(self, record_size: int, what: str) -> int:
        """A uint64 count, checked against the bytes left (each record at least ``record_size``)."""
        (n,) = self.take("<Q", f"the number of {what}")
        if n * record_size > len(self.data) - self.pos:
            raise InputError(self.path, f"truncated or corrupt: {n} {what} cannot fit in the {len(self.data)} bytes")
        return n

    def end(self) -> None:
        if self.pos != len(self.data):
            raise InputError(self.path, f"corrupt: {len(self.data) - self.pos} unexpected bytes after the last record")


def read_cameras_bin(path: Path) -> dict[int, CameraSpec]:
    """CAMERA_ID -> intrinsics (source pixel convention; see ``CameraSpec``), as ``read_cameras_txt`` gives them."""
    f = _Bytes(path)
    cameras: dict[int, CameraSpec] = {}
    for k in range(f.count(24, "cameras")):
        what = f"camera {k}"
        cam_id, model_id, width, height = f.take("<iiQQ", what)
        what = f"camera {k} (CAMERA_ID {cam_id})"
        model = MODEL_IDS.get(model_id)
        if model is None:
            raise InputError(path, f"corrupt: {what} has unknown model id {model_id}")
        if model in REFUSED_MODELS:
            raise InputError(
                path,
                f"{what}: camera model {model} is not supported (fisheye/FOV); run `colmap image_undistorter` "
                "and import its output (PINHOLE cameras)",
            )
        names = MODEL_PARAMS[model]
        params = f.take(f"<{len(names)}d", f"{what} parameters")
        if not all(math.isfinite(v) for v in params):
            raise InputError(path, f"{what}: non-finite camera parameters {params}")
        if not (0 < width < 2**31 and 0 < height < 2**31):
            raise InputError(path, f"{what}: image size must be positive, got {width}x{height}")
        spec = camera_spec(dict(zip(names, params)), int(width), int(height), path, what)
        if cam_id in cameras:
            raise InputError(path, f"{what}: CAMERA_ID {cam_id} defined twice")
        cameras[cam_id] = spec
    f.end()
    if not cameras:
        raise InputError(path, "no cameras defined")
    return cameras


def read_images_bin(path: Path, cameras: dict[int, CameraSpec], images_dir: Path) -> list[SourceFrame]:
    """Posed frames (camera-to-world, OpenCV axes) from ``images.bin``; each image must exist on disk."""
    f = _Bytes(path)
    frames: list[SourceFrame] = []
    for k in range(f.count(73, "images")):  # 64 fixed bytes, a NUL, a uint64 point count
        what = f"image {k}"
        image_id, qw, qx, qy, qz, tx, ty, tz, cam_id = f.take("<i7di", what)
        what = f"image {k} (IMAGE_ID {image_id})"
        name = f.name(what)
        (n_points,) = f.take("<Q", f"{what} point count")
        if n_points * 24 > len(f.data) - f.pos:
            raise InputError(path, f"truncated or corrupt: {what} lists {n_points} 2D points past the end of the file")
        f.pos += 24 * n_points
        values = (qw, qx, qy, qz, tx, ty, tz)
        if not all(math.isfinite(v) for v in values):
            raise InputError(path, f"{what}: non-finite pose {values}")
        q = np.array([qw, qx, qy, qz])
        if np.linalg.norm(q) < 1e-8:
            raise InputError(path, f"{what}: quaternion is zero")
        if cam_id not in cameras:
            raise InputError(path, f"{what}: CAMERA_ID {cam_id} is not defined in cameras.bin")
        image = images_dir / name
        if not image.is_file():
            raise InputError(image, f"image listed in {path} ({what}) does not exist")
        T = invert_pose(make_pose(quat_to_matrix(q), [tx, ty, tz]))
        frames.append(SourceFrame(name=name, image_path=image, pose=T, camera=cameras[cam_id], where=f"{path} {what}"))
    f.end()
    if not frames:
        raise InputError(path, "no images listed")
    return frames


def import_colmap_binary(
    model_dir: str | Path,
    images_dir: str | Path | None,
    out_scene: str | Path,
    test_every: int = default_test_every(),
    image_ext: str = ".png",
    progress: Progress | None = None,
) -> ImportSummary:
    """Write the ACE layout at ``out_scene`` from a COLMAP binary model (arguments as ``import_colmap_text``)."""
    check_test_every(test_every)
    check_output(out_scene)
    model = find_colmap_model(Path(model_dir), binary=True)
    if not (model / "cameras.bin").is_file():
        raise InputError(model, "no binary COLMAP model (cameras.bin + images.bin) here")
    images = find_images_dir(model) if images_dir is None else Path(images_dir)
    if not images.is_dir():
        raise InputError(images, "images folder does not exist")
    cameras = read_cameras_bin(model / "cameras.bin")
    frames = read_images_bin(model / "images.bin", cameras, images)
    summary = ImportSummary(source=str(model), format="colmap", scene=str(out_scene))
    summary.notes.append("binary model (cameras.bin, images.bin)")
    return write_scene(frames, out_scene, summary, test_every=test_every, image_ext=image_ext, progress=progress)


def import_colmap(
    model_dir: str | Path,
    images_dir: str | Path | None,
    out_scene: str | Path,
    test_every: int = default_test_every(),
    image_ext: str = ".png",
    progress: Progress | None = None,
) -> ImportSummary:
    """A COLMAP model, text or binary (the text one when a folder holds both)."""
    model = find_colmap_model(Path(model_dir), binary=True)
    if (model / "cameras.txt").is_file() and (model / "images.txt").is_file():
        return import_colmap_text(model, images_dir, out_scene, test_every, image_ext, progress)
    return import_colmap_binary(model, images_dir, out_scene, test_every, image_ext, progress)
