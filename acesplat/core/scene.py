"""The ACE scene layout, read and written with validation that names the offending file.

Layout: ``<scene>/{train,test}/{rgb,poses,calibration}[/depth]``; files pair by sorted name;
``poses/*.txt`` are 4x4 camera-to-world matrices (OpenCV axes); ``calibration/*.txt`` hold
either one focal length (principal point at the image centre) or a 3x3 K.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from acesplat.core.atomic import atomic_path, write_text
from acesplat.core.camera import Intrinsics
from acesplat.core.errors import InputError
from acesplat.core.geometry import rigidity_problem

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm", ".jp2", ".exr"}
SPLITS = ("train", "test")
TRAIN, TEST = SPLITS
RGB, POSES, CALIBRATION, DEPTH = "rgb", "poses", "calibration", "depth"
"""A split's folders: images, 4x4 camera-to-world poses, calibrations, depth maps (synthetic scenes)."""


@dataclass
class Frame:
    """One posed image. ``pose`` (4, 4) is camera-to-world; ``depth_path`` only for synthetic scenes."""

    name: str
    rgb_path: Path
    pose: np.ndarray
    intrinsics: Intrinsics
    depth_path: Path | None = None

    def load_rgb(self) -> np.ndarray:
        """The image as RGB uint8 (H, W, 3)."""
        return read_rgb(self.rgb_path)

    def load_depth(self) -> np.ndarray:
        """Metric z-depth (H, W) float32; 0 marks no depth."""
        if self.depth_path is None:
            raise InputError(self.rgb_path, "this frame has no depth map")
        return read_depth(self.depth_path)


@dataclass
class SceneSplit:
    """The frames of one split of a scene, in sorted-name order."""

    root: Path
    split: str
    frames: list[Frame] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) camera-to-world poses."""
        return np.stack([f.pose for f in self.frames])


def read_rgb(path: str | Path) -> np.ndarray:
    """RGB uint8 (H, W, 3) from any format OpenCV reads; InputError if missing or corrupt."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "image file does not exist")
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if img is None:
        raise InputError(path, "cannot decode image (corrupt or unsupported format)")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(path: str | Path) -> np.ndarray:
    """Depth in metres (H, W) float32 from a 16-bit PNG in millimetres."""
    path = Path(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
    if img is None:
        raise InputError(path, "cannot read depth map")
    return img.astype(np.float32) / 1000.0


def read_matrix(path: Path) -> np.ndarray:
    try:
        values = np.loadtxt(path, dtype=np.float64, ndmin=1)
    except (ValueError, OSError) as e:
        raise InputError(path, f"cannot parse numbers ({e})") from None
    return values


def read_pose(path: str | Path) -> np.ndarray:
    """A validated 4x4 camera-to-world pose from a text file."""
    path = Path(path)
    values = read_matrix(path)
    if values.size != 16:
        raise InputError(path, f"a pose needs 16 numbers (4x4), found {values.size}")
    T = values.reshape(4, 4)
    problem = rigidity_problem(T)
    if problem:
        raise InputError(path, problem)
    return T


def read_calibration(path: str | Path, width: int, height: int) -> Intrinsics:
    """Intrinsics from one focal length or a 3x3 K for an image of ``width`` x ``height``."""
    path = Path(path)
    values = read_matrix(path)
    if not np.all(np.isfinite(values)):
        raise InputError(path, "calibration has non-finite entries")
    if values.size == 1:
        f = float(values.reshape(-1)[0])
        if f <= 0:
            raise InputError(path, f"focal length must be positive, got {f}")
        return Intrinsics.from_focal(f, width, height)
    if values.size == 9:
        K = values.reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InputError(path, f"focal length must be positive, got fx={K[0, 0]} fy={K[1, 1]}")
        return Intrinsics.from_K(K, width, height)
    raise InputError(path, f"calibration needs 1 number (focal) or 9 (3x3 K), found {values.size}")


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image, decoding it (which also proves it is readable)."""
    img = read_rgb(path)
    return img.shape[1], img.shape[0]


def _list(folder: Path, suffixes: set[str] | None) -> list[Path]:
    files = [p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")]
    if suffixes is not None:
        files = [p for p in files if p.suffix.lower() in suffixes]
    return sorted(files, key=lambda p: p.name)


def read_split(scene: str | Path, split: str = "train") -> SceneSplit:
    """Read and validate one split; every image is decoded once to check it and learn its size."""
    root = Path(scene)
    if not root.is_dir():
        raise InputError(root, "scene folder does not exist")
    base = root / split
    if not base.is_dir():
        raise InputError(base, f"scene has no '{split}' split")
    folders = {}
    for sub in (RGB, POSES, CALIBRATION):
        if not (base / sub).is_dir():
            raise InputError(base / sub, "missing folder (ACE layout needs rgb/, poses/, calibration/)")
        folders[sub] = _list(base / sub, IMAGE_SUFFIXES if sub == RGB else None)
    rgbs, poses, calibs = folders[RGB], folders[POSES], folders[CALIBRATION]
    if not rgbs:
        raise InputError(base / RGB, "split is empty (no images)")
    for sub, files in ((POSES, poses), (CALIBRATION, calibs)):
        if len(files) != len(rgbs):
            raise InputError(base / sub, f"{len(files)} files but {len(rgbs)} images in {base / RGB}")
    depth_dir = base / DEPTH
    depths = _list(depth_dir, {".png"}) if depth_dir.is_dir() else []
    if depths and len(depths) != len(rgbs):
        raise InputError(depth_dir, f"{len(depths)} depth maps but {len(rgbs)} images")
    frames = []
    for i, (rgb, pose_path, calib_path) in enumerate(zip(rgbs, poses, calibs)):
        w, h = image_size(rgb)
        frames.append(
            Frame(
                name=rgb.stem,
                rgb_path=rgb,
                pose=read_pose(pose_path),
                intrinsics=read_calibration(calib_path, w, h),
                depth_path=depths[i] if depths else None,
            )
        )
    return SceneSplit(root=root, split=split, frames=frames)


@dataclass
class SplitFiles:
    """The files of one split folder in sorted-name order, not opened: ``poses`` / ``calibrations`` None when the
    folder has none (a recording, or a plain folder of images)."""

    root: Path
    images: list[Path]
    poses: list[Path] | None = None
    calibrations: list[Path] | None = None


def find_split(path: str | Path, splits: tuple[str, ...] = (TEST, TRAIN)) -> Path:
    """A split folder (has rgb/) as is; a scene: its first split of ``splits`` that has images; else ``path`` itself
    (a plain folder of images)."""
    path = Path(path)
    if not path.is_dir():
        raise InputError(path, "folder does not exist")
    if (path / RGB).is_dir():
        return path
    for split in splits:
        if (path / split / RGB).is_dir():
            return path / split
    return path


def split_folder(scene: str | Path, split: str, need_poses: bool = False) -> Path:
    """The folder of ``scene``'s ``split`` (InputError naming what is missing: the scene, the split's images, or,
    with ``need_poses``, its poses)."""
    root = Path(scene)
    if not root.is_dir():
        raise InputError(root, "scene folder does not exist")
    base = root / split
    if not (base / RGB).is_dir():
        raise InputError(base, f"scene has no '{split}' split")
    if need_poses and not (base / POSES).is_dir():
        raise InputError(base / POSES, "ground-truth poses are needed")
    return base


def list_split(folder: str | Path) -> SplitFiles:
    """The files of a split folder (``folder/rgb`` or, without it, the images in ``folder``), paired by sorted name;
    InputError when there are no images or a folder's count differs from the images'."""
    root = Path(folder)
    img_dir = root / RGB if (root / RGB).is_dir() else root
    images = _list(img_dir, IMAGE_SUFFIXES)
    if not images:
        raise InputError(img_dir, "no images to replay")

    def paired(sub: str) -> list[Path] | None:
        if not (root / sub).is_dir():
            return None
        files = _list(root / sub, None)
        if len(files) != len(images):
            raise InputError(root / sub, f"{len(files)} files but {len(images)} images")
        return files

    return SplitFiles(root, images, paired(POSES), paired(CALIBRATION))


def write_capture(
    base: str | Path, name: str, image: np.ndarray, K: np.ndarray | None = None, pose: np.ndarray | None = None
) -> Path:
    """Write one captured frame into a split folder: the image (RGB (H, W, 3) or gray (H, W) uint8) as
    ``rgb/<name>.png``, and, when given, its 3x3 ``K`` and 4x4 camera-to-world ``pose``; returns the image path."""
    base = Path(base)
    if image.ndim not in (2, 3):
        raise ValueError(f"image must be (H, W) or (H, W, 3), got {image.shape}")
    (base / RGB).mkdir(parents=True, exist_ok=True)
    path = base / RGB / f"{name}.png"
    bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), bgr):
            raise InputError(path, "cannot write image")
    if K is not None:
        write_text(base / CALIBRATION / f"{name}.txt", format_matrix(K))
    if pose is not None:
        write_text(base / POSES / f"{name}.txt", format_matrix(pose))
    return path


def remove_calibrations(base: str | Path) -> None:
    """Delete a split folder's calibration files (a recording whose frames are not all calibrated)."""
    for p in (Path(base) / CALIBRATION).glob("*.txt"):
        p.unlink()


def format_matrix(M: np.ndarray) -> str:
    return "\n".join(" ".join(f"{v:.10g}" for v in row) for row in np.atleast_2d(M)) + "\n"


def write_frame(
    base: str | Path,
    name: str,
    rgb: np.ndarray,
    pose: np.ndarray,
    K: np.ndarray,
    depth: np.ndarray | None = None,
    ext: str = ".png",
) -> None:
    """Write one frame of a split in the ACE layout (image RGB uint8, pose 4x4 c2w, K 3x3, depth metres)."""
    base = Path(base)
    for sub in (RGB, POSES, CALIBRATION) + ((DEPTH,) if depth is not None else ()):
        (base / sub).mkdir(parents=True, exist_ok=True)
    with atomic_path(base / RGB / f"{name}{ext}") as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise InputError(base / RGB / f"{name}{ext}", "cannot write image")
    write_text(base / POSES / f"{name}.txt", format_matrix(pose))
    write_text(base / CALIBRATION / f"{name}.txt", format_matrix(K))
    if depth is not None:
        mm = np.clip(np.round(depth * 1000.0), 0, 65535).astype(np.uint16)
        with atomic_path(base / DEPTH / f"{name}.png") as tmp:
            cv2.imwrite(str(tmp), mm)
