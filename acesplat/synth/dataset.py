"""Synthetic datasets: the built-in scene written in the ACE layout, and in-memory frames for pretraining.

The built-in scene (``synthesize``) is one room, a training pass and a separate test pass; it is
what the demo, the tests and the benchmarks run on. ``random_scene_frames`` draws a new room of
random size, furniture, textures, focal length and path for every seed (encoder pretraining).
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from acesplat.core.atomic import write_json
from acesplat.core.camera import Intrinsics
from acesplat.core.config import knob, knob_default
from acesplat.core.errors import InputError
from acesplat.core.scene import write_frame
from acesplat.synth.render import render_view
from acesplat.synth.room import RoomScene, make_room
from acesplat.synth.trajectory import TEST_PASS, TRAIN_PASS, make_trajectory

DEFAULT_HFOV_DEG = 62.0
"""Horizontal field of view of the built-in scene's camera."""
PIXELS_PER_TEXEL = 1.6
"""Texture density is the focal length / this: about one texel per pixel at 1.6 m."""
MIN_IMAGE_SIDE = 8
SUMMARY_FILE = "synth.json"


@dataclass(frozen=True)
class SynthConfig:
    """The built-in scene's settings; ``synthesize`` takes them as keyword arguments with these defaults."""

    seed: int = knob(0, "Room, textures and camera path all follow from this seed.")
    train_frames: int = knob(200, "Training frames (one pass around the room).")
    test_frames: int = knob(60, "Test frames (a separate, offset pass).")
    size: tuple[int, int] = knob((240, 320), "Image size HxW.")
    supersample: int = knob(2, "Rays per pixel side on surface boundaries (antialiasing).")


def _default(name: str) -> Any:
    return knob_default(SynthConfig, name)


class SynthFrame(NamedTuple):
    """One rendered view: RGB uint8 (H, W, 3), z-depth metres float32 (H, W), camera-to-world (4, 4), K (3, 3)."""

    rgb: np.ndarray
    depth: np.ndarray
    pose: np.ndarray
    K: np.ndarray


def default_intrinsics(size: tuple[int, int] = _default("size"), hfov_deg: float = DEFAULT_HFOV_DEG) -> Intrinsics:
    """Square pixels, principal point at the image centre, horizontal field of view ``hfov_deg``."""
    h, w = size
    return Intrinsics.from_focal((w / 2.0) / np.tan(np.radians(hfov_deg) / 2.0), w, h)


def texel_density_for(intrinsics: Intrinsics) -> float:
    """Texels per metre that match the pixel density of ``intrinsics`` at 1.6 m (tiny images get tiny textures)."""
    return float(np.clip(intrinsics.fx / PIXELS_PER_TEXEL, 12.0, 400.0))


def frame_name(i: int) -> str:
    return f"frame-{i:05d}"


def _check_counts(size: tuple[int, int], counts: dict[str, int], where: Path | None) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in size)
    except (TypeError, ValueError):
        raise InputError(where, f"size must be (H, W), got {size!r}") from None
    if h < MIN_IMAGE_SIDE or w < MIN_IMAGE_SIDE:
        raise InputError(where, f"image size must be at least {MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE}, got {h}x{w}")
    for name, n in counts.items():
        if int(n) < 1:
            raise InputError(where, f"{name} must be at least 1, got {n}")
    return h, w


def _nearest_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each point of ``a`` (N, 3), the distance to the nearest point of ``b`` (M, 3)."""
    return np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)).min(axis=1)


def synthesize(
    out_dir: str | Path,
    seed: int = _default("seed"),
    train_frames: int = _default("train_frames"),
    test_frames: int = _default("test_frames"),
    size: tuple[int, int] = _default("size"),
    supersample: int = _default("supersample"),
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Write the built-in scene to ``out_dir`` in the ACE layout (train/ and test/ with rgb, poses, calibration, depth).

    The scene is assembled in a hidden sibling folder and renamed into place at the end, so an
    interrupted run never leaves a half-written scene. An existing non-empty ``out_dir`` is an
    error unless ``overwrite``. ``progress(done, total)`` is called after every frame.
    Returns the summary (also written to ``out_dir/synth.json``).
    """
    out_dir = Path(out_dir)
    h, w = _check_counts(size, {"train_frames": train_frames, "test_frames": test_frames}, out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(out_dir, "output exists and is not a folder")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not overwrite:
        raise InputError(out_dir, "output folder is not empty (pass overwrite / --overwrite to replace it)")
    t0 = time.perf_counter()
    K = default_intrinsics((h, w))
    scene = make_room(seed, texel_density=texel_density_for(K))
    room_seconds = time.perf_counter() - t0
    passes = {
        "train": make_trajectory(scene.path, train_frames, **TRAIN_PASS),
        "test": make_trajectory(scene.path, test_frames, **TEST_PASS),
    }
    total = train_frames + test_frames
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_dir.parent / f".{out_dir.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    render_s = write_s = 0.0
    depth_lo, depth_hi = np.inf, 0.0
    done = 0
    try:
        for split, poses in passes.items():
            for i, pose in enumerate(poses):
                t1 = time.perf_counter()
                rgb, depth = render_view(scene, pose, K, supersample=supersample)
                t2 = time.perf_counter()
                write_frame(tmp / split, frame_name(i), rgb, pose, K.K, depth=depth)
                write_s += time.perf_counter() - t2
                render_s += t2 - t1
                depth_lo, depth_hi = min(depth_lo, float(depth.min())), max(depth_hi, float(depth.max()))
                done += 1
                if progress is not None:
                    progress(done, total)
        gap = _nearest_distances(passes["test"][:, :3, 3], passes["train"][:, :3, 3])
        summary = {
            "out_dir": str(out_dir),
            "seed": int(seed),
            "size": [h, w],
            "focal_px": K.fx,
            "hfov_deg": DEFAULT_HFOV_DEG,
            "train_frames": int(train_frames),
            "test_frames": int(test_frames),
            "supersample": int(supersample),
            "room_size_m": scene.size.tolist(),
            "objects": len(scene.objects),
            "surfaces": len(scene.surfaces),
            "photos": scene.photo_count,
            "texel_density_per_m": scene.texel_density,
            "depth_range_m": [depth_lo, depth_hi],
            "test_to_train_distance_m": {
                "min": float(gap.min()),
                "median": float(np.median(gap)),
                "max": float(gap.max()),
            },
            "room_seconds": room_seconds,
            "render_ms_per_frame": 1000.0 * render_s / total,
            "write_ms_per_frame": 1000.0 * write_s / total,
            "seconds": time.perf_counter() - t0,
        }
        write_json(tmp / SUMMARY_FILE, summary)
        _move_into_place(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    summary["seconds"] = time.perf_counter() - t0
    return summary


def _move_into_place(tmp: Path, out_dir: Path) -> None:
    if out_dir.is_dir():
        old = out_dir.parent / f".{out_dir.name}.old-{os.getpid()}"
        os.replace(out_dir, old)
        os.replace(tmp, out_dir)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, out_dir)


def render_frames(
    scene: RoomScene, poses: np.ndarray, intrinsics: Intrinsics, supersample: int = 1
) -> list[SynthFrame]:
    """Render ``poses`` (N, 4, 4) of ``scene`` in memory."""
    frames = []
    for pose in poses:
        rgb, depth = render_view(scene, pose, intrinsics, supersample=supersample)
        frames.append(SynthFrame(rgb, depth, pose.copy(), intrinsics.K))
    return frames


def random_scene(seed: int, size: tuple[int, int] = _default("size")) -> tuple[RoomScene, Intrinsics, dict]:
    """A random room (3-8 m by 3-8 m by 2.5-3.5 m, random furniture count) and camera for ``seed``.

    Returns the scene, intrinsics with a random field of view (55-75 degrees), and the parameters of
    a random pass (for :func:`make_trajectory`).
    """
    h, w = _check_counts(size, {}, None)
    rng = np.random.default_rng([seed, 7])
    room = np.array([rng.uniform(3.0, 8.0), rng.uniform(3.0, 8.0), rng.uniform(2.5, 3.5)])
    K = default_intrinsics((h, w), hfov_deg=float(rng.uniform(55.0, 75.0)))
    n_objects = int(rng.integers(2, max(3, int(room[0] * room[1] * 0.6))))
    scene = make_room(
        int(rng.integers(2**31)), size=room, texel_density=texel_density_for(K), n_objects=n_objects, wide=True
    )
    pass_params = {
        "radius_scale": float(rng.uniform(0.84, 1.01)),
        "height_offset": float(rng.uniform(-0.15, 0.15)),
        "phase": float(rng.uniform(0.0, 1.0)),
    }
    return scene, K, pass_params


def random_scene_frames(
    seed: int, n_frames: int, size: tuple[int, int] = _default("size"), supersample: int = 1
) -> list[SynthFrame]:
    """``n_frames`` views along one random pass through a new random room for ``seed`` (encoder pretraining)."""
    _check_counts(size, {"n_frames": n_frames}, None)
    scene, K, pass_params = random_scene(seed, size)
    return render_frames(scene, make_trajectory(scene.path, n_frames, **pass_params), K, supersample=supersample)
