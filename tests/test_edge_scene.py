"""A tiny analytic scene and a tiny map for the export and edge tests (shared fixtures, no tests here).

The room is a box whose six faces carry distinctive random textures; frames are ray cast exactly,
so the true pose of every image is known. Once the built-in generator (acesplat.synth) offers
``synthesize`` this module can delegate to it; the analytic room keeps the tests independent of it.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from acesplat.core.camera import Intrinsics
from acesplat.core.geometry import look_at
from acesplat.core.scene import write_frame

ROOM = np.array([4.0, 3.0, 2.5])
TEX = 256


def _texture(rng: np.random.Generator) -> np.ndarray:
    """Multi-scale colour noise plus random shapes: every patch looks different."""
    img = np.zeros((TEX, TEX, 3), np.float32)
    for cell, amp in ((64, 0.5), (16, 0.3), (4, 0.2)):
        small = rng.random((TEX // cell + 1, TEX // cell + 1, 3)).astype(np.float32)
        img += amp * cv2.resize(small, (TEX, TEX), interpolation=cv2.INTER_CUBIC)
    img = np.clip(img * 255, 0, 255).astype(np.uint8)
    for _ in range(40):
        c = tuple(int(v) for v in rng.integers(0, 256, 3))
        p = tuple(int(v) for v in rng.integers(0, TEX, 2))
        if rng.random() < 0.5:
            cv2.circle(img, p, int(rng.integers(4, 20)), c, -1)
        else:
            q = tuple(int(v) for v in np.array(p) + rng.integers(-24, 24, 2))
            cv2.rectangle(img, p, q, c, -1)
    return img


def render(textures: list[np.ndarray], T_c2w: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast RGB (H, W, 3) uint8 and z-depth (H, W) of the textured box seen from ``T_c2w``."""
    ys, xs = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float64)
    d_cam = np.stack([(xs - intr.cx) / intr.fx, (ys - intr.cy) / intr.fy, np.ones_like(xs)], -1)
    R, o = T_c2w[:3, :3], T_c2w[:3, 3]
    d = d_cam @ R.T
    best_t = np.full(xs.shape, np.inf)
    face = np.zeros(xs.shape, int)
    for axis in range(3):
        for side, bound in ((0, 0.0), (1, ROOM[axis])):
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (bound - o[axis]) / d[..., axis]
            ok = (t > 1e-6) & (t < best_t)
            best_t = np.where(ok, t, best_t)
            face = np.where(ok, 2 * axis + side, face)
    X = o + d * best_t[..., None]
    rgb = np.zeros(xs.shape + (3,), np.uint8)
    for f in range(6):
        axis = f // 2
        u_ax, v_ax = [a for a in range(3) if a != axis]
        m = face == f
        u = (X[..., u_ax] / ROOM[u_ax] * (TEX - 1)).astype(np.float32)
        v = (X[..., v_ax] / ROOM[v_ax] * (TEX - 1)).astype(np.float32)
        sample = cv2.remap(textures[f], u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        rgb[m] = sample[m]
    depth = best_t * d_cam[..., 2]
    return rgb, depth.astype(np.float32)


def camera_poses(n: int, phase: float, rng: np.random.Generator) -> list[np.ndarray]:
    """Cameras near the room's centre turning around, looking at the walls."""
    poses = []
    for i in range(n):
        yaw = phase + 2 * np.pi * i / n
        eye = ROOM / 2 + np.array([0.3 * np.cos(3 * yaw), 0.3 * np.sin(2 * yaw), 0.1 * np.sin(yaw)])
        eye = eye + rng.normal(0, 0.03, 3)
        target = eye + np.array([np.cos(yaw), np.sin(yaw), -0.15 + 0.1 * np.sin(2 * yaw)])
        poses.append(look_at(eye, target))
    return poses


def jitter(T: np.ndarray, rng: np.random.Generator, metres: float, degrees: float) -> np.ndarray:
    """``T`` moved by ``metres`` and turned by ``degrees`` about a random axis."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    rvec = np.radians(degrees) * axis
    R, _ = cv2.Rodrigues(rvec)
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ R
    d = rng.normal(size=3)
    out[:3, 3] += metres * d / np.linalg.norm(d)
    return out


def make_room_scene(
    out: Path, train: int = 24, test: int = 6, size: tuple[int, int] = (64, 80), seed: int = 0,
    test_offset_m: float = 0.02, test_offset_deg: float = 1.0,
) -> Path:
    """Write a textured-box scene in the ACE layout (train/ and test/) and return its folder.

    Test views are training views moved by a few centimetres and turned by a degree: close enough
    for a map trained in seconds to recognise them, far enough that a copied pose would be wrong.
    """
    rng = np.random.default_rng(seed)
    textures = [_texture(rng) for _ in range(6)]
    h, w = size
    intr = Intrinsics.from_focal(0.9 * w, w, h)
    train_poses = camera_poses(train, 0.0, rng)
    picks = np.linspace(0, train - 1, test).round().astype(int)
    test_poses = [jitter(train_poses[i], rng, test_offset_m, test_offset_deg) for i in picks]
    for split, poses in (("train", train_poses), ("test", test_poses)):
        for i, T in enumerate(poses):
            rgb, depth = render(textures, T, intr)
            write_frame(out / split, f"{i:04d}", rgb, T, intr.K, depth=depth)
    return out
