"""The sample photographs that installed packages carry, used as raw material for textures.

Photographic detail (corners, blobs, text strokes) is what feature matching and scene coordinate
regression lock onto; smooth noise alone is too ambiguous. Nothing is downloaded: only files that
scikit-image and matplotlib ship inside their packages are read, located without importing them.
Without either package the synthetic scene falls back to purely procedural textures.
"""

from __future__ import annotations

import functools
import importlib.util
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

SKIMAGE_FILES = (
    "astronaut.png",
    "brick.png",
    "camera.png",
    "chelsea.png",
    "coffee.png",
    "coins.png",
    "grass.png",
    "gravel.png",
    "rocket.jpg",
    "hubble_deep_field.jpg",
    "moon.png",
    "page.png",
    "text.png",
    "retina.jpg",
    "ihc.png",
    "motorcycle_left.png",
)
MATPLOTLIB_FILES = ("grace_hopper.jpg",)
MATERIAL_NAMES = frozenset({"brick", "grass", "gravel", "moon", "hubble_deep_field", "coins", "ihc", "text", "page"})
"""Photographs that look like a surface material (good for floors and wallpaper) rather than a picture."""

TEXT_NAMES = frozenset({"page", "text"})

MAX_SIDE = 720
"""Larger photographs are downscaled once on load; textures never need more."""


@dataclass(frozen=True)
class Photo:
    """One sample photograph as float32 RGB in [0, 1] (H, W, 3)."""

    name: str
    image: np.ndarray
    gray_source: bool
    brightness: float
    """Mean intensity in [0, 1] (a night sky makes a poor floor)."""

    @property
    def is_material(self) -> bool:
        return self.name in MATERIAL_NAMES

    @property
    def has_text(self) -> bool:
        """Pages of text must not be mirrored (mirrored letters look wrong)."""
        return self.name in TEXT_NAMES


def _package_dir(name: str) -> Path | None:
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations)))


def photo_paths() -> list[Path]:
    """Paths of the sample photographs present in this installation (possibly none)."""
    paths = []
    skimage_dir = _package_dir("skimage")
    if skimage_dir is not None:
        paths += [skimage_dir / "data" / f for f in SKIMAGE_FILES]
    mpl_dir = _package_dir("matplotlib")
    if mpl_dir is not None:
        paths += [mpl_dir / "mpl-data" / "sample_data" / f for f in MATPLOTLIB_FILES]
    return [p for p in paths if p.is_file()]


def _without_icc(data: bytes) -> bytes:
    """A PNG without its iCCP chunk: one sample file carries a profile libpng warns about on every load."""
    if not data.startswith(b"\x89PNG\r\n\x1a\n"):
        return data
    out, pos = [data[:8]], 8
    while pos + 8 <= len(data):
        length = int.from_bytes(data[pos : pos + 4], "big")
        end = pos + 12 + length
        if data[pos + 4 : pos + 8] != b"iCCP":
            out.append(data[pos:end])
        pos = end
    return b"".join(out)


def _load(path: Path) -> Photo | None:
    data = np.frombuffer(_without_icc(path.read_bytes()), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if img is None:
        return None
    h, w = img.shape[:2]
    scale = MAX_SIDE / max(h, w)
    if scale < 1.0:
        img = cv2.resize(img, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
    rgb = cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
    gray = bool(np.abs(rgb - rgb.mean(axis=2, keepdims=True)).max() < 0.02)
    return Photo(name=path.stem, image=rgb, gray_source=gray, brightness=float(rgb.mean()))


@functools.lru_cache(maxsize=1)
def load_photos() -> tuple[Photo, ...]:
    """All available sample photographs, decoded once per process, in a fixed order (determinism)."""
    photos = (_load(p) for p in photo_paths())
    return tuple(p for p in photos if p is not None)
