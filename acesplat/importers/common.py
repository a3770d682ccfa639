"""What every importer shares: camera specs, the train/test split rule, undistortion, and the atomic scene writer.

Pixel convention: the project's K follows OpenCV (the centre of the top-left pixel is (0, 0)), the
convention ``Intrinsics.resized`` and ``cv2.resize``/``cv2.remap`` use. COLMAP, instant-ngp and
nerfstudio put that centre at (0.5, 0.5), so their principal points are shifted by -0.5 here.

Split rule (NeRF practice, the "LLFF hold-out"): frames are sorted by source name in natural order
(``img2`` before ``img10``) and frame ``i`` goes to test when ``i % test_every == 0`` (0, 8, 16, ...
for the default 8); ``test_every=0`` puts every frame in train. A dataset that ships its own split
(``transforms_train.json`` + ``transforms_test.json``) keeps it.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob, knob_default
from acesplat.core.errors import InputError
from acesplat.core.scene import read_rgb, write_frame

SIZE_RATIO_TOL = 0.01
"""An image whose size differs from its camera's by the same factor in x and y (within 1%) is a
downscaled copy (nerfstudio's ``images_2``, ``images_4``): its intrinsics are rescaled, not refused."""


@dataclass(frozen=True)
class ImportConfig:
    """The importers' settings; the import functions take them as keyword arguments with these defaults."""

    test_every: int = knob(8, "Every N-th frame (natural name order, from the first) goes to test; 0 = none.")


def default_test_every() -> int:
    """ImportConfig.test_every's default (the signatures' default)."""
    return knob_default(ImportConfig, "test_every")


Progress = Callable[[int, int], None]
"""Called as ``progress(done, total)`` after each written frame."""


@dataclass(frozen=True)
class CameraSpec:
    """Intrinsics as a source states them, in the source's pixel-corner convention (centre of pixel 0 at 0.5).

    ``None`` fields are filled from the image when it is read: ``width``/``height`` from its size,
    ``fx`` from ``angle_x`` (horizontal field of view, radians), ``fy`` from ``angle_y`` or ``fx``,
    ``cx``/``cy`` at the image centre. ``dist`` holds OpenCV coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]).
    """

    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    width: int | None = None
    height: int | None = None
    angle_x: float | None = None
    angle_y: float | None = None
    dist: tuple[float, ...] = ()

    def resolve(self, width: int, height: int) -> Intrinsics:
        """OpenCV-convention intrinsics for the image as found on disk (``width`` x ``height``)."""
        w = self.width if self.width is not None else width
        h = self.height if self.height is not None else height
        fx = self.fx if self.fx is not None else 0.5 * w / np.tan(0.5 * self.angle_x)  # type: ignore[operator]
        if self.fy is not None:
            fy = self.fy
        elif self.angle_y is not None:
            fy = 0.5 * h / np.tan(0.5 * self.angle_y)
        else:
            fy = fx
        cx = (self.cx if self.cx is not None else w / 2.0) - 0.5
        cy = (self.cy if self.cy is not None else h / 2.0) - 0.5
        intr = Intrinsics(float(fx), float(fy), float(cx), float(cy), int(w), int(h))
        return intr if (w, h) == (width, height) else intr.resized(width, height)

    @property
    def distorted(self) -> bool:
        return any(v != 0.0 for v in self.dist)


@dataclass
class SourceFrame:
    """One posed image found in a source dataset. ``pose`` (4, 4) is camera-to-world, OpenCV axes."""

    name: str
    image_path: Path
    pose: np.ndarray
    camera: CameraSpec
    where: str
    """Where the frame was declared (``images.txt line 7``), for error messages."""
    test: bool | None = None
    """Split fixed by the source (``transforms_test.json``); None lets the split rule decide."""


@dataclass
class ImportSummary:
    """What an import wrote, for the CLI table and ``--json``."""

    source: str
    format: str
    scene: str
    train: int = 0
    test: int = 0
    split_rule: str = ""
    undistorted: int = 0
    rescaled: int = 0
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        return asdict(self)


def natural_key(name: str) -> list:
    """Sort key that orders ``img2`` before ``img10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def check_test_every(test_every: int) -> int:
    if isinstance(test_every, bool) or not isinstance(test_every, (int, np.integer)) or test_every < 0:
        raise InputError(None, f"test_every must be an integer >= 0 (0 = no test split), got {test_every!r}")
    return int(test_every)


def assign_split(frames: list[SourceFrame], test_every: int) -> tuple[list[SourceFrame], list[bool], str]:
    """Frames in natural name order and, for each, whether it goes to test; plus the rule in words."""
    test_every = check_test_every(test_every)
    ordered = sorted(frames, key=lambda f: natural_key(f.name))
    if any(f.test is not None for f in ordered):
        return ordered, [bool(f.test) for f in ordered], "split given by the source files"
    if test_every == 0:
        return ordered, [False] * len(ordered), "all frames to train (test_every=0)"
    rule = f"every {test_every}-th frame to test (frames 0, {test_every}, {2 * test_every}, ... in natural name order)"
    return ordered, [i % test_every == 0 for i in range(len(ordered))], rule


def find_image(path: Path) -> Path | None:
    """``path`` itself, or ``path`` with an image extension appended (Blender's ``./train/r_0``)."""
    if path.is_file():
        return path
    for ext in (".png", ".jpg", ".jpeg", ".JPG", ".PNG", ".JPEG", ".exr", ".bmp", ".tif", ".tiff", ".webp"):
        candidate = path.with_name(path.name + ext)
        if candidate.is_file():
            return candidate
    return None


class Undistorter:
    """Undistorts images with OpenCV, caching the remap tables per camera (most datasets have one camera).

    The new K is ``cv2.getOptimalNewCameraMatrix(alpha=0)``: every output pixel comes from inside the
    source image (no black borders for the SCR network to learn), at the cost of a slight crop.
    """

    def __init__(self) -> None:
        self._cache: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def __call__(self, rgb: np.ndarray, K: np.ndarray, dist: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
        h, w = rgb.shape[:2]
        D = np.asarray(dist, dtype=np.float64)
        key = (K.tobytes(), D.tobytes(), w, h)
        if key not in self._cache:
            K_new, _ = cv2.getOptimalNewCameraMatrix(K, D, (w, h), 0.0, (w, h))
            map_x, map_y = cv2.initUndistortRectifyMap(K, D, None, K_new, (w, h), cv2.CV_32FC1)
            self._cache[key] = (K_new, map_x, map_y)
        K_new, map_x, map_y = self._cache[key]
        out = cv2.remap(rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return out, K_new.copy()


def _safe_stem(name: str) -> str:
    """File-name-safe stem of a source name (``images/IMG 0001.JPG`` -> ``IMG_0001``), for traceability only."""
    stem = Path(name.replace("\\", "/")).stem
    return re.sub(r"[^A-Za-z0-9_-]+", "_", stem).strip("_") or "frame"


def check_output(out_scene: str | Path) -> None:
    """Refuse an output that already holds something: mixing two imports would break name pairing."""
    out_scene = Path(out_scene)
    if out_scene.exists() and (not out_scene.is_dir() or any(out_scene.iterdir())):
        raise InputError(out_scene, "output exists and is not an empty folder (choose a new scene folder)")


def write_scene(
    frames: list[SourceFrame],
    out_scene: str | Path,
    summary: ImportSummary,
    test_every: int = default_test_every(),
    image_ext: str = ".png",
    progress: Progress | None = None,
) -> ImportSummary:
    """Write ``frames`` in the ACE layout under ``out_scene``; all or nothing.

    Frames are written to a temporary folder beside ``out_scene`` and renamed into place at the end,
    so a bad image halfway leaves no half-written scene. Output names are ``<index>_<source stem>``
    with a zero-padded index in natural source order, so ACE's sorted-name pairing keeps that order.
    Images are decoded (which proves they are readable) and re-encoded as ``image_ext`` (PNG:
    lossless); distorted cameras are undistorted first.
    """
    out_scene = Path(out_scene)
    check_output(out_scene)
    if not frames:
        raise InputError(summary.source, "no frames to import")
    seen: dict[str, str] = {}
    for f in frames:
        if f.name in seen:
            raise InputError(summary.source, f"image {f.name!r} is listed twice ({seen[f.name]} and {f.where})")
        seen[f.name] = f.where
    ordered, is_test, summary.split_rule = assign_split(frames, test_every)
    if not any(not t for t in is_test):
        raise InputError(summary.source, "the split rule leaves no training frame")
    width = max(5, len(str(len(ordered) - 1)))
    undistort = Undistorter()
    out_scene.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_scene.name}.", dir=out_scene.parent))
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(tmp, 0o777 & ~mask)  # mkdtemp makes 0700; the scene should get mkdir()'s usual mode
    try:
        for i, (frame, test) in enumerate(zip(ordered, is_test)):
            rgb = read_rgb(frame.image_path)
            h, w = rgb.shape[:2]
            cam = frame.camera
            if cam.width is not None and cam.height is not None and (cam.width, cam.height) != (w, h):
                sx, sy = w / cam.width, h / cam.height
                if abs(sx - sy) > SIZE_RATIO_TOL * max(sx, sy):
                    raise InputError(
                        frame.image_path,
                        f"image is {w}x{h} but {frame.where} gives {cam.width}x{cam.height} (not a uniform rescale)",
                    )
                summary.rescaled += 1
            K = cam.resolve(w, h).K
            if cam.distorted:
                rgb, K = undistort(rgb, K, cam.dist)
                summary.undistorted += 1
            split = "test" if test else "train"
            write_frame(tmp / split, f"{i:0{width}d}_{_safe_stem(frame.name)}", rgb, frame.pose, K, ext=image_ext)
            summary.test += int(test)
            summary.train += int(not test)
            if progress is not None:
                progress(i + 1, len(ordered))
        if out_scene.is_dir():
            out_scene.rmdir()  # checked empty above; rename needs the name free on every platform
        os.replace(tmp, out_scene)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    summary.scene = str(out_scene)
    return summary
