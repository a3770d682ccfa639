"""Smooth closed camera loops inside the room, and the band of floor they may occupy.

A pass is one loop around an ellipse centred in the room, heading along the direction of travel
with a slow sweep from looking outward (the nearby wall and the objects against it) to looking
inward (across the room, over the objects in the middle, at the far walls). The heading, pitch and roll are
functions of the loop angle shared by all passes, so a test pass (a smaller, higher loop sampled at
other angles) sees the same surfaces from new positions: localizable, but never a copy of a training
frame. Objects are kept out of the band every pass can reach (:data:`BAND`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from acesplat.core.geometry import look_at, make_pose, rodrigues_to_matrix

BAND = (0.80, 1.06)
"""Radial scales (times the path radii, wobble included) that any pass may reach; objects stay outside."""

WALL_MARGIN_MAX = 1.1
"""Distance kept between the loop's nominal ellipse and the walls in a large room (metres)."""

TURN_METRES = 0.5
"""Metres of travel that count as much as one radian of turning when spacing frames along a pass."""

TRAIN_PASS = {"radius_scale": 1.0, "height_offset": 0.0, "phase": 0.0}
TEST_PASS = {"radius_scale": 0.87, "height_offset": 0.10, "phase": 0.5}


@dataclass(frozen=True)
class CameraPath:
    """Parameters of a family of smooth loops; angles in radians, lengths in metres, frequencies per loop."""

    center: tuple[float, float]
    radii: tuple[float, float]
    height: float
    height_amp: float
    height_freq: int
    height_phase: float
    wobble_amp: float
    wobble_freq: int
    wobble_phase: float
    yaw_amp: tuple[float, float]
    yaw_freq: tuple[int, int]
    yaw_phase: tuple[float, float]
    pitch_mean: float
    pitch_amp: float
    pitch_freq: int
    pitch_phase: float
    roll_amp: float
    roll_freq: int
    roll_phase: float


def path_radii(room_size: np.ndarray) -> tuple[float, float]:
    """Nominal loop radii that keep every pass about 0.9 m (small rooms) to 1 m (large rooms) from the walls."""
    radii = []
    for L in room_size[:2]:
        margin = min(WALL_MARGIN_MAX, 0.38 * L)
        radii.append(max(0.2, 0.5 * L - margin))
    return radii[0], radii[1]


def random_path(rng: np.random.Generator, room_size: np.ndarray, wide: bool = False) -> CameraPath:
    """A random path for a room of ``room_size`` (3,); ``wide`` widens the sweeps (pretraining variety)."""
    size = np.asarray(room_size, dtype=np.float64)
    k = 1.5 if wide else 1.0
    height = float(np.clip(rng.uniform(1.3, 1.55), 0.9, size[2] - 0.8))
    return CameraPath(
        center=(float(size[0] / 2 + rng.uniform(-0.1, 0.1)), float(size[1] / 2 + rng.uniform(-0.1, 0.1))),
        radii=path_radii(size),
        height=height,
        height_amp=float(rng.uniform(0.06, 0.15)),
        height_freq=int(rng.integers(2, 5)),
        height_phase=float(rng.uniform(0, 2 * np.pi)),
        wobble_amp=float(rng.uniform(0.015, 0.04)),
        wobble_freq=int(rng.integers(3, 6)),
        wobble_phase=float(rng.uniform(0, 2 * np.pi)),
        yaw_amp=(float(rng.uniform(0.9, 1.25) * k), float(rng.uniform(0.15, 0.35))),
        yaw_freq=(int(rng.integers(2, 5)), int(rng.integers(5, 8))),
        yaw_phase=(float(rng.uniform(0, 2 * np.pi)), float(rng.uniform(0, 2 * np.pi))),
        pitch_mean=float(rng.uniform(-0.16, -0.08)),
        pitch_amp=float(rng.uniform(0.05, 0.12) * k),
        pitch_freq=int(rng.integers(2, 6)),
        pitch_phase=float(rng.uniform(0, 2 * np.pi)),
        roll_amp=float(rng.uniform(0.01, 0.05)),
        roll_freq=int(rng.integers(2, 6)),
        roll_phase=float(rng.uniform(0, 2 * np.pi)),
    )


def _positions(path: CameraPath, theta: np.ndarray, radius_scale: float, height_offset: float) -> np.ndarray:
    r = radius_scale * (1.0 + path.wobble_amp * np.sin(path.wobble_freq * theta + path.wobble_phase))
    x = path.center[0] + path.radii[0] * r * np.cos(theta)
    y = path.center[1] + path.radii[1] * r * np.sin(theta)
    z = path.height + height_offset + path.height_amp * np.sin(path.height_freq * theta + path.height_phase)
    return np.stack([x, y, z], axis=-1)


def _yaw(path: CameraPath, theta: np.ndarray) -> np.ndarray:
    """Heading at loop angle ``theta``: the direction of travel on the nominal ellipse plus slow sweeps."""
    a, b = path.radii
    yaw = np.arctan2(b * np.cos(theta), -a * np.sin(theta))
    for amp, freq, ph in zip(path.yaw_amp, path.yaw_freq, path.yaw_phase):
        yaw = yaw + amp * np.sin(freq * theta + ph)
    return yaw


def band_points(path: CameraPath, n_angles: int = 96, n_scales: int = 10) -> np.ndarray:
    """Floor points (M, 2) covering the band of :data:`BAND` scales, for keeping objects clear of every pass."""
    theta = np.linspace(0, 2 * np.pi, n_angles, endpoint=False)
    scales = np.linspace(BAND[0], BAND[1], n_scales)
    s, t = np.meshgrid(scales, theta, indexing="ij")
    x = path.center[0] + path.radii[0] * s * np.cos(t)
    y = path.center[1] + path.radii[1] * s * np.sin(t)
    return np.stack([x.ravel(), y.ravel()], axis=1)


def make_trajectory(
    path: CameraPath, n_frames: int, radius_scale: float = 1.0, height_offset: float = 0.0, phase: float = 0.0
) -> np.ndarray:
    """``n_frames`` camera-to-world poses (N, 4, 4), evenly spaced by arc length along one loop of ``path``.

    ``phase`` in [0, 1) shifts the samples by that fraction of one frame spacing; ``radius_scale``
    and ``height_offset`` move the whole loop (a different pass over the same room).
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    lo, hi = radius_scale * (1 - path.wobble_amp), radius_scale * (1 + path.wobble_amp)
    if lo < BAND[0] - 1e-9 or hi > BAND[1] + 1e-9:
        raise ValueError(f"radius_scale {radius_scale} leaves the object-free band {BAND}")
    dense = np.linspace(0.0, 2 * np.pi, 4097)
    pts = _positions(path, dense, radius_scale, height_offset)
    # Frames are spaced evenly in combined motion (travel plus TURN_METRES per radian of heading change),
    # so neither fast turns at the ends of the ellipse nor long straight stretches get too few frames.
    turn = np.diff(np.unwrap(_yaw(path, dense)))
    step = np.hypot(np.linalg.norm(np.diff(pts, axis=0), axis=1), TURN_METRES * turn)
    progress = np.concatenate([[0.0], np.cumsum(step)])
    s = (np.arange(n_frames) + phase) / n_frames * progress[-1]
    theta = np.interp(s, progress, dense)
    eyes = _positions(path, theta, radius_scale, height_offset)
    yaw = _yaw(path, theta)
    pitch = path.pitch_mean + path.pitch_amp * np.sin(path.pitch_freq * theta + path.pitch_phase)
    roll = path.roll_amp * np.sin(path.roll_freq * theta + path.roll_phase)
    poses = np.empty((n_frames, 4, 4))
    for i in range(n_frames):
        fwd = np.array([np.cos(pitch[i]) * np.cos(yaw[i]), np.cos(pitch[i]) * np.sin(yaw[i]), np.sin(pitch[i])])
        R = look_at(eyes[i], eyes[i] + fwd)[:3, :3] @ rodrigues_to_matrix(np.array([0.0, 0.0, roll[i]]))
        poses[i] = make_pose(R, eyes[i])
    return poses
