"""Pose a folder of one's own images with pycolmap (structure from motion on CPU) and write the ACE layout.

Steps: every image is decoded first (an unreadable one is an error naming it); SIFT features; sequential or
exhaustive matching with geometric verification; incremental mapping; the model that registered the most images is
kept. Its ``cameras.bin`` / ``images.bin`` are read back through the COLMAP binary importer, so the world-to-camera
inversion, the pixel-centre shift and the undistortion (OpenCV, for SIMPLE_RADIAL/RADIAL/OPENCV cameras) are the
importer's; a PINHOLE or SIMPLE_PINHOLE ``camera_model`` reconstructs without distortion and writes the images as
they are.

Scale: COLMAP's is arbitrary. With ``scale_from=(IMAGE_A, IMAGE_B, METRES)`` the poses are rescaled so the two
cameras' centres are that far apart (units: metres); without it the units are kept and the scene's ``sfm.json``
says ``"units": "arbitrary"``. The scene appears all at once (staged beside the target, renamed into place).

pycolmap is imported lazily (``pip install pycolmap``; the ``train`` extra has it).
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from acesplat.core.atomic import write_json
from acesplat.core.config import knob
from acesplat.core.errors import InputError
from acesplat.core.scene import IMAGE_SUFFIXES, read_rgb
from acesplat.importers.colmap_binary import read_cameras_bin, read_images_bin
from acesplat.importers.common import (
    ImportSummary,
    SourceFrame,
    check_output,
    check_test_every,
    default_test_every,
    natural_key,
    write_scene,
)

METADATA_FILE = "sfm.json"
"""The scene's record of how it was posed (units, scale, counts, unregistered images)."""
MIN_REGISTERED = 3
"""Fewest registered images that make a scene (two views fix no trajectory worth mapping)."""
MATCHERS = ("sequential", "exhaustive")
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
"""Camera models offered for the reconstruction: the pinhole ones and those the importer undistorts."""

LOG_LEVEL = 1
"""pycolmap's glog level during a run: warnings and errors only (its INFO lines would bury the progress bar)."""

PhaseCallback = Callable[[str, float, dict | None], None]
"""Called as ``progress(phase, fraction, info)``; phases: check, extract, match, map, write."""


@dataclass(frozen=True)
class PoseConfig:
    """The settings of ``pose_images`` (structure from motion with pycolmap)."""

    matcher: str = knob("sequential", "Image pairs to match: sequential (video order, loops closed) or exhaustive.")
    camera_model: str = knob(
        "SIMPLE_RADIAL", "COLMAP camera model; radial ones are undistorted on write, PINHOLE/SIMPLE_PINHOLE are not."
    )
    single_camera: bool = knob(True, "All images share one camera (one device, fixed zoom) and one calibration.")
    overlap: int = knob(10, "Sequential matching: each image is matched with this many following ones.")
    max_features: int = knob(8192, "SIFT features per image at most.")
    seed: int = knob(0, "pycolmap's random seed (RANSAC, initial pair), so a run can be repeated.")


@dataclass
class PoseSummary:
    """What ``pose_images`` did, for the CLI table, ``--json`` and the scene's ``sfm.json``."""

    images_dir: str
    scene: str
    images: int = 0
    registered: int = 0
    unregistered: list[str] = field(default_factory=list)
    points: int = 0
    mean_reprojection_error_px: float = 0.0
    units: str = "arbitrary"
    scale: float = 1.0
    """Factor applied to COLMAP's translations (1.0 when the units are kept)."""
    scale_from: dict[str, Any] | None = None
    matcher: str = ""
    camera_model: str = ""
    camera_params: list[float] = field(default_factory=list)
    models: int = 0
    """Reconstructions pycolmap made (the largest is kept)."""
    train: int = 0
    test: int = 0
    split_rule: str = ""
    undistorted: int = 0
    pycolmap_version: str = ""
    phase_seconds: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["unregistered_count"] = len(self.unregistered)
        return d


def _pycolmap() -> Any:
    try:
        import pycolmap
    except ImportError:
        raise InputError(
            None, "pycolmap is not installed (pip install pycolmap, or pip install -e '.[train]')"
        ) from None
    return pycolmap


def list_images(images_dir: Path) -> list[str]:
    """File names of the images directly in ``images_dir`` (hidden files and other suffixes skipped), natural
    order; InputError when the folder is missing or holds none."""
    if not images_dir.is_dir():
        raise InputError(images_dir, "images folder does not exist")
    names = [
        p.name
        for p in images_dir.iterdir()
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in IMAGE_SUFFIXES
    ]
    if not names:
        raise InputError(images_dir, f"no images here (looked for {', '.join(sorted(IMAGE_SUFFIXES))})")
    return sorted(names, key=natural_key)


def check_images(images_dir: Path, names: list[str], single_camera: bool) -> tuple[int, int]:
    """Decode every image (InputError naming an unreadable one); with ``single_camera`` all must share one size.
    Returns that size (width, height) of the first image."""
    first: tuple[int, int] | None = None
    for name in names:
        rgb = read_rgb(images_dir / name)
        size = (rgb.shape[1], rgb.shape[0])
        if first is None:
            first = size
        elif single_camera and size != first:
            raise InputError(
                images_dir / name,
                f"image is {size[0]}x{size[1]} but {names[0]} is {first[0]}x{first[1]}; one shared camera needs one "
                "size (pass --per-image-camera)",
            )
    assert first is not None
    return first


def check_scale_from(scale_from: tuple[str, str, float] | None, names: list[str], images_dir: Path) -> None:
    if scale_from is None:
        return
    if len(scale_from) != 3:
        raise InputError(None, f"scale_from must be (IMAGE_A, IMAGE_B, METRES), got {scale_from!r}")
    a, b, metres = scale_from
    if not (isinstance(metres, (int, float)) and math.isfinite(metres) and metres > 0):
        raise InputError(None, f"--scale-from distance must be a positive number of metres, got {metres!r}")
    if a == b:
        raise InputError(None, f"--scale-from needs two different images, got {a!r} twice")
    for name in (a, b):
        if name not in names:
            raise InputError(images_dir / name, "--scale-from image is not one of the images in the folder")


def _check_config(config: PoseConfig) -> None:
    if config.matcher not in MATCHERS:
        raise InputError(None, f"matcher must be one of {', '.join(MATCHERS)}, got {config.matcher!r}")
    if config.camera_model not in CAMERA_MODELS:
        raise InputError(None, f"camera model must be one of {', '.join(CAMERA_MODELS)}, got {config.camera_model!r}")
    if config.overlap < 1 or config.max_features < 16:
        raise InputError(None, f"overlap must be >= 1 and max_features >= 16, got {config.overlap}, "
                         f"{config.max_features}")  # fmt: skip


def _reconstruct(
    pycolmap: Any,
    images_dir: Path,
    names: list[str],
    work: Path,
    config: PoseConfig,
    summary: PoseSummary,
    progress: PhaseCallback,
) -> Any:
    """Run extraction, matching and incremental mapping in ``work``; the largest reconstruction (or None)."""
    db = work / "database.db"
    cpu = pycolmap.Device.cpu
    pycolmap.set_random_seed(config.seed)
    t = time.perf_counter()
    progress("extract", 0.0, None)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = config.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = config.max_features
    mode = pycolmap.CameraMode.SINGLE if config.single_camera else pycolmap.CameraMode.PER_IMAGE
    pycolmap.extract_features(
        db, images_dir, image_names=names, camera_mode=mode, reader_options=reader, extraction_options=extraction,
        device=cpu,
    )  # fmt: skip
    summary.phase_seconds["extract"] = time.perf_counter() - t
    progress("extract", 1.0, None)
    t = time.perf_counter()
    progress("match", 0.0, None)
    if config.matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = config.overlap
        pycolmap.match_sequential(db, pairing_options=pairing, device=cpu)
    else:
        pycolmap.match_exhaustive(db, device=cpu)
    summary.phase_seconds["match"] = time.perf_counter() - t
    progress("match", 1.0, None)
    t = time.perf_counter()
    options = pycolmap.IncrementalPipelineOptions()
    options.min_model_size = MIN_REGISTERED
    options.random_seed = config.seed
    options.mapper.random_seed = config.seed
    options.triangulation.random_seed = config.seed
    seen = [0]

    def next_image() -> None:
        seen[0] += 1
        progress("map", min(seen[0] / len(names), 1.0), {"registering": seen[0]})

    progress("map", 0.0, None)
    (work / "sparse").mkdir()
    models = pycolmap.incremental_mapping(
        db, images_dir, work / "sparse", options=options, next_image_callback=next_image
    )
    summary.phase_seconds["map"] = time.perf_counter() - t
    progress("map", 1.0, None)
    summary.models = len(models)
    if not models:
        return None
    return max(models.values(), key=lambda r: r.num_reg_images())


def _scaled(frames: list[SourceFrame], scale_from: tuple[str, str, float], images_dir: Path) -> float:
    """The factor that puts the two named cameras ``scale_from[2]`` metres apart; InputError if either image is
    unregistered or they coincide."""
    a, b, metres = scale_from
    by_name = {f.name: f for f in frames}
    for name in (a, b):
        if name not in by_name:
            raise InputError(images_dir / name, "--scale-from image was not registered by pycolmap (no pose)")
    d = float(np.linalg.norm(by_name[a].pose[:3, 3] - by_name[b].pose[:3, 3]))
    centres = np.stack([f.pose[:3, 3] for f in frames])
    extent = float(np.linalg.norm(centres.max(axis=0) - centres.min(axis=0)))
    if d <= 1e-6 * max(extent, 1e-12):
        raise InputError(None, f"--scale-from cameras {a} and {b} are at the same place in the reconstruction "
                         f"({d:.3g} apart, extent {extent:.3g}); pick two farther apart")  # fmt: skip
    return metres / d


def pose_images(
    images_dir: str | Path,
    out_scene: str | Path,
    config: PoseConfig = PoseConfig(),
    scale_from: tuple[str, str, float] | None = None,
    test_every: int = default_test_every(),
    progress: PhaseCallback | None = None,
) -> PoseSummary:
    """Pose the images directly in ``images_dir`` with pycolmap and write the ACE layout at ``out_scene``.

    ``scale_from`` (IMAGE_A, IMAGE_B, METRES): file names in ``images_dir`` whose cameras are that far apart;
    None keeps COLMAP's arbitrary units. Every ``test_every``-th registered image (natural name order) goes to
    test. InputError (one line) for a missing or empty folder, an unreadable image, fewer than
    ``MIN_REGISTERED`` registered images or an unusable ``scale_from``; nothing is written then.
    """
    t0 = time.perf_counter()
    images_dir, out_scene = Path(images_dir), Path(out_scene)
    progress = progress or (lambda phase, fraction, info: None)
    _check_config(config)
    check_test_every(test_every)
    check_output(out_scene)
    names = list_images(images_dir)
    check_scale_from(scale_from, names, images_dir)
    progress("check", 0.0, None)
    check_images(images_dir, names, config.single_camera)
    progress("check", 1.0, {"images": len(names)})
    summary = PoseSummary(images_dir=str(images_dir), scene=str(out_scene), images=len(names))
    summary.matcher, summary.camera_model = config.matcher, config.camera_model
    summary.phase_seconds["check"] = time.perf_counter() - t0
    pycolmap = _pycolmap()
    summary.pycolmap_version = str(getattr(pycolmap, "__version__", ""))
    out_scene.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out_scene.name}.pose-", dir=out_scene.parent))
    try:
        work = stage / "colmap"
        work.mkdir()
        level = pycolmap.logging.minloglevel
        pycolmap.logging.minloglevel = LOG_LEVEL
        try:
            rec = _reconstruct(pycolmap, images_dir, names, work, config, summary, progress)
        finally:
            pycolmap.logging.minloglevel = level
        registered = 0 if rec is None else int(rec.num_reg_images())
        if registered < MIN_REGISTERED:
            raise InputError(
                images_dir,
                f"pycolmap registered {registered} of {len(names)} images (at least {MIN_REGISTERED} needed): too "
                "little texture or overlap; try --matcher exhaustive or more overlapping images",
            )
        t = time.perf_counter()
        model = work / "model"
        model.mkdir()
        rec.write_binary(str(model))
        cameras = read_cameras_bin(model / "cameras.bin")
        frames = read_images_bin(model / "images.bin", cameras, images_dir)
        summary.registered = len(frames)
        done = {f.name for f in frames}
        summary.unregistered = [n for n in names if n not in done]
        summary.points = int(rec.num_points3D())
        summary.mean_reprojection_error_px = float(rec.compute_mean_reprojection_error())
        cam = next(iter(rec.cameras.values()))
        summary.camera_params = [float(v) for v in cam.params]
        if scale_from is not None:
            summary.scale = _scaled(frames, scale_from, images_dir)
            summary.units = "metres"
            summary.scale_from = {"image_a": scale_from[0], "image_b": scale_from[1], "metres": float(scale_from[2])}
            for f in frames:
                f.pose = f.pose.copy()
                f.pose[:3, 3] *= summary.scale
        staged = stage / "scene"
        report = ImportSummary(source=str(images_dir), format="pycolmap", scene=str(out_scene))
        write_scene(
            frames, staged, report, test_every=test_every,
            progress=lambda i, n: progress("write", i / n, {"frames": i}),
        )  # fmt: skip
        summary.train, summary.test = report.train, report.test
        summary.split_rule, summary.undistorted = report.split_rule, report.undistorted
        summary.phase_seconds["write"] = time.perf_counter() - t
        summary.seconds = time.perf_counter() - t0
        write_json(staged / METADATA_FILE, summary.as_dict())
        check_output(out_scene)  # still free after the run
        if out_scene.is_dir():
            out_scene.rmdir()
        os.replace(staged, out_scene)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    summary.seconds = time.perf_counter() - t0
    return summary
