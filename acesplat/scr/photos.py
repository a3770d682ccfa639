"""Real photographs for encoder pretraining: where they come from, under which licence, and what they may not show.

The encoder learns from exact correspondences. Procedural rooms give them through depth; a photograph gives them
through homographies: two perspective warps of one photograph are two views of a plane with known pixel-to-pixel
correspondences. Every photograph is a :class:`PhotoSource` with its licence and what it shows. A source whose
licence is not one of :data:`ALLOWED_LICENCES`, or that names an evaluation site (the shared scenes, the Strecha
collection, instant-ngp's samples), is refused by name before anything trains: shipped weights never see the places
their figures are measured on.

Sources: the photographs the installed scikit-image ships (:func:`packaged_photos`), and a user's folder with a
``photos.json`` manifest (:func:`folder_photos`).
"""

from __future__ import annotations

import json
import re
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from acesplat.core.errors import InputError

ALLOWED_LICENCES = ("CC0-1.0", "public-domain", "CC-BY-4.0")
"""Licences whose images may train shipped weights (CC-BY: the provenance file carries the attribution)."""
EVALUATION_SITES = (
    "herzjesu",
    "fountain",
    "strecha",
    "castlep19",
    "castlep30",
    "entryp10",
    "sfmqualityevaluation",
    "instantngp",
    "nerffox",
)
"""Names (lower case, letters and digits only) of the places the project's figures are measured on."""
MANIFEST = "photos.json"
MIN_SIDE_PX = 256
"""Photographs with a shorter side below this are too small to warp into a pretraining frame."""
PHOTO_SIDE_RATIO = 2.0
"""A photograph is resized so that its shorter side is this times the frame height: a frame sees part of it."""
PHOTO_TILT_DEG = 30.0
"""Largest yaw and pitch of the virtual camera looking at the photograph (the viewpoint change of a pair)."""
PHOTO_ROLL_DEG = 10.0
PHOTO_SCALE = (0.75, 4 / 3)
"""Photograph pixels per frame pixel at the frame centre."""
PHOTO_SHIFT = 0.15
"""Largest offset of a frame's centre from the photograph's, as a fraction of the frame size (frames overlap)."""


def photo_homography(rng: np.random.Generator, frame_hw: tuple[int, int], photo_hw: tuple[int, int]) -> np.ndarray:
    """A random homography (3, 3) from frame pixels to photograph pixels: a camera of ~53 degrees' field of view,
    tilted by up to PHOTO_TILT_DEG, its centre ray on the photograph within PHOTO_SHIFT of the photograph's centre."""
    h, w = frame_hw
    f = float(w)
    yaw, pitch = np.radians(rng.uniform(-PHOTO_TILT_DEG, PHOTO_TILT_DEG, 2))
    roll = np.radians(rng.uniform(-PHOTO_ROLL_DEG, PHOTO_ROLL_DEG))
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    R = (
        np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
        @ np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
        @ np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    )
    K = np.diag([f, f, 1.0])
    to_origin = np.array([[1, 0, -w / 2], [0, 1, -h / 2], [0, 0, 1.0]])
    s = rng.uniform(*PHOTO_SCALE)
    shift = rng.uniform(-PHOTO_SHIFT, PHOTO_SHIFT, 2) * np.array([w, h])
    to_photo = np.array([[s, 0, photo_hw[1] / 2 + shift[0]], [0, s, photo_hw[0] / 2 + shift[1]], [0, 0, 1.0]])
    M = K @ R @ np.linalg.inv(K)
    c = M[:, 2] / M[2, 2]  # where the tilted camera's centre ray meets the photograph: brought back to its centre
    M = np.array([[1, 0, -c[0]], [0, 1, -c[1]], [0, 0, 1.0]]) @ (M / M[2, 2])
    H = to_photo @ M @ to_origin
    return H / H[2, 2]


# (file in skimage/data, what it shows, licence, origin as skimage's docstrings give it)
_SKIMAGE = (
    ("astronaut.png", "the astronaut Eileen Collins", "public-domain", "NASA Great Images, via scikit-image"),
    ("brick.png", "brick wall texture", "CC0-1.0", "CC0Textures Bricks25, via scikit-image"),
    ("camera.png", "man with a camera on a field", "CC0-1.0", "Lav Varshney, via scikit-image"),
    ("chelsea.png", "a cat", "CC0-1.0", "Stefan van der Walt, via scikit-image"),
    ("coffee.png", "a cup of coffee on a table", "CC0-1.0", "Rachel Michetti, via scikit-image"),
    ("coins.png", "Greek coins from Pompeii", "public-domain", "Brooklyn Museum Collection, via scikit-image"),
    ("grass.png", "grass texture", "CC0-1.0", "linolafett on DeviantArt (Grass-01), via scikit-image"),
    ("gravel.png", "gravel texture", "CC0-1.0", "CC0Textures Gravel04, via scikit-image"),
    ("rocket.jpg", "Falcon 9 launching DSCOVR", "public-domain", "SpaceX Photos, via scikit-image"),
)


@dataclass(frozen=True)
class PhotoSource:
    """One photograph: ``name`` (unique, e.g. 'scikit-image:coffee'), its file, licence, origin and subject."""

    name: str
    path: Path
    licence: str
    origin: str
    subject: str

    def record(self) -> dict:
        """The provenance entry (the path as a name, not this machine's location)."""
        d = asdict(self)
        d["path"] = self.path.name
        return d


def _letters(s: str) -> str:
    return re.sub(r"[^a-z0-9]", "", s.lower())


def check_source(src: PhotoSource) -> None:
    """Raise InputError naming ``src`` if its licence is not allowed or it names an evaluation site."""
    if src.licence not in ALLOWED_LICENCES:
        raise InputError(
            src.path, f"photograph {src.name!r}: licence {src.licence!r} is not one of {', '.join(ALLOWED_LICENCES)}"
        )
    text = _letters(" ".join([src.name, src.path.as_posix(), src.origin, src.subject]))
    for site in EVALUATION_SITES:
        if site in text:
            raise InputError(src.path, f"photograph {src.name!r} names evaluation site {site!r}: refused")


def packaged_photos() -> list[PhotoSource]:
    """The licensed photographs of the installed scikit-image (a dependency), in a fixed order."""
    import skimage.data

    root = Path(skimage.data.__file__).parent
    out = []
    for file, subject, licence, origin in _SKIMAGE:
        path = root / file
        if path.is_file():
            out.append(PhotoSource(f"scikit-image:{Path(file).stem}", path, licence, origin, subject))
    return out


def folder_photos(folder: str | Path) -> list[PhotoSource]:
    """Photographs of ``folder`` listed in its photos.json: {"photos": [{"file", "licence", "origin", "subject"}]}."""
    folder = Path(folder)
    manifest = folder / MANIFEST
    if not manifest.is_file():
        raise InputError(manifest, "missing: a photo folder needs a manifest giving each file's licence and origin")
    try:
        entries = json.loads(manifest.read_text())["photos"]
        out = [
            PhotoSource(f"{folder.name}:{e['file']}", folder / e["file"], e["licence"], e["origin"], e["subject"])
            for e in entries
        ]
    except (ValueError, KeyError, TypeError) as e:
        raise InputError(manifest, f"not a photo manifest ({e.__class__.__name__}: {e})") from None
    for src in out:
        if not src.path.is_file():
            raise InputError(src.path, f"listed in {manifest} but missing")
    return out


def photo_sources(spec: str) -> list[PhotoSource]:
    """'none' -> []; 'packaged' -> :func:`packaged_photos`; anything else is a folder (:func:`folder_photos`).
    Every source is checked (:func:`check_source`) and names must be unique."""
    if spec == "none":
        return []
    out = packaged_photos() if spec == "packaged" else folder_photos(spec)
    seen: set[str] = set()
    for src in out:
        check_source(src)
        if src.name in seen:
            raise InputError(src.path, f"photograph {src.name!r} listed twice")
        seen.add(src.name)
    return out


def load_photo_gray(src: PhotoSource) -> np.ndarray:
    """The photograph as grayscale uint8 (H, W); InputError if unreadable or smaller than MIN_SIDE_PX."""
    img = cv2.imread(str(src.path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InputError(src.path, f"photograph {src.name!r} cannot be read as an image")
    if min(img.shape) < MIN_SIDE_PX:
        raise InputError(src.path, f"photograph {src.name!r} is {img.shape[1]}x{img.shape[0]}, below {MIN_SIDE_PX} px")
    return img


def photo_views(
    photo_gray: np.ndarray, seed: int, frames: int, frame_hw: tuple[int, int], unit: float
) -> tuple[np.ndarray, np.ndarray]:
    """A photograph (H, W) uint8 as a planar scene: ``frames`` views (F, h, w) uint8 through random homographies
    (:func:`photo_homography`), with blur and gamma, and each pixel's coordinates (F, h, w, 3): its photograph pixel
    (x, y, 0) x ``unit`` (NaN off the photograph)."""
    rng = np.random.default_rng(seed)
    h, w = frame_hw
    k = PHOTO_SIDE_RATIO * h / min(photo_gray.shape)
    photo = cv2.resize(
        photo_gray,
        (round(photo_gray.shape[1] * k), round(photo_gray.shape[0] * k)),
        interpolation=cv2.INTER_AREA if k < 1 else cv2.INTER_LINEAR,
    )
    ph, pw = photo.shape
    ys, xs = np.mgrid[0:h, 0:w]
    pix = np.stack([xs.ravel(), ys.ravel(), np.ones(h * w)], 0)
    grays, coords = [], []
    for _ in range(frames):
        H = photo_homography(rng, (h, w), (ph, pw))
        img = cv2.warpPerspective(
            photo, H, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT
        ).astype(np.float32)
        if rng.random() < 0.3:
            img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.3, 1.0))
        img = 255.0 * (img / 255.0) ** rng.uniform(0.7, 1.4)
        grays.append(np.clip(img, 0, 255).astype(np.uint8))
        q = H @ pix
        uv = (q[:2] / q[2]).T
        on = (q[2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= pw - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= ph - 1)
        c = np.full((h * w, 3), np.nan)
        c[on, :2] = uv[on] * unit
        c[on, 2] = 0.0
        coords.append(c.reshape(h, w, 3))
    return np.stack(grays), np.stack(coords)
