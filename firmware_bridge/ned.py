"""From our pose convention to an autopilot's: map frame -> local NED, camera -> body FRD.

Inside the project a pose is camera-to-world with OpenCV camera axes (x right, y down, z forward).
An autopilot wants the pose of its body (FRD: x forward, y right, z down) in a local frame whose
z points down (NED, or "FRD local" when north is unknown). Two fixed rotations connect them:

- the camera mount ``T_body_cam``: where the camera sits on the vehicle and where it looks;
- the map frame ``R_ned_world``: how the map's axes map to north/east/down. The map must be
  gravity-aligned (its "up" is really up), otherwise height and tilt from vision disagree with the IMU.

    T_ned_body = [R_ned_world | 0] @ T_world_cam @ inverse(T_body_cam)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from acesplat.core.errors import InputError
from acesplat.core.geometry import invert_pose, make_pose, rigidity_problem

WORLD_FRAMES: dict[str, np.ndarray] = {
    # rows: N, E, D expressed in world axes
    "enu": np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),  # x east, y north, z up
    "flu": np.diag([1.0, -1.0, -1.0]),  # x forward, y left, z up (ROS body-style map)
    "ned": np.eye(3),
    "opencv": np.array(
        [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    ),  # a level OpenCV camera: x right, y down, z forward
}
"""Map-frame presets: R_ned_world for maps whose axes are named so. The default is "enu" (z up)."""

MOUNTS: dict[str, np.ndarray] = {
    # columns: camera x, y, z axes expressed in body FRD
    "forward": np.array(
        [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    ),  # looks ahead, image right = vehicle right
    "down": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),  # looks down, image top = vehicle front
}
"""Mount presets: R_body_cam of a camera looking along the named direction."""


def euler_to_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation (3, 3) body -> NED from aerospace Euler angles in radians (Z-Y-X: yaw, then pitch, then roll)."""
    cr, sr, cp, sp, cy, sy = (
        math.cos(roll),
        math.sin(roll),
        math.cos(pitch),
        math.sin(pitch),
        math.cos(yaw),
        math.sin(yaw),
    )
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def matrix_to_euler(R: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in radians of a body -> NED rotation (3, 3); inverse of euler_to_matrix away from
    pitch = +-90 deg."""
    R = np.asarray(R, dtype=np.float64)
    roll = math.atan2(R[2, 1], R[2, 2])
    pitch = -math.asin(min(1.0, max(-1.0, R[2, 0])))
    yaw = math.atan2(R[1, 0], R[0, 0])
    return roll, pitch, yaw


def _rotation(name_or_matrix: str | np.ndarray, presets: dict[str, np.ndarray], what: str) -> np.ndarray:
    if isinstance(name_or_matrix, str):
        if name_or_matrix not in presets:
            raise InputError(None, f"unknown {what} {name_or_matrix!r}; choose one of {', '.join(presets)}")
        return presets[name_or_matrix]
    R = np.asarray(name_or_matrix, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"{what} rotation must be 3x3, got shape {R.shape}")
    problem = rigidity_problem(make_pose(R, np.zeros(3)))
    if problem:
        raise ValueError(f"{what}: {problem}")
    return R


@dataclass(frozen=True, eq=False)
class CameraMount:
    """Where the camera is on the vehicle: ``R_body_cam`` (3, 3) and the optical centre ``t_body_cam`` (3,) in
    body FRD, metres."""

    R_body_cam: np.ndarray = field(default_factory=lambda: MOUNTS["forward"].copy())
    t_body_cam: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        object.__setattr__(self, "R_body_cam", _rotation(self.R_body_cam, MOUNTS, "camera mount"))
        t = np.asarray(self.t_body_cam, dtype=np.float64)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise ValueError(f"camera offset must be 3 finite numbers, got {self.t_body_cam!r}")
        object.__setattr__(self, "t_body_cam", t)

    @classmethod
    def preset(
        cls,
        name: str = "forward",
        offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
        roll_deg: float = 0.0,
        pitch_deg: float = 0.0,
        yaw_deg: float = 0.0,
    ) -> CameraMount:
        """A preset direction, tilted by body-frame Euler angles (pitch_deg=-20: a forward camera tilted 20 deg
        down)."""
        tilt = euler_to_matrix(math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw_deg))
        return cls(tilt @ _rotation(name, MOUNTS, "camera mount"), np.asarray(offset_m, dtype=np.float64))

    @property
    def T_body_cam(self) -> np.ndarray:
        return make_pose(self.R_body_cam, self.t_body_cam)


def world_rotation(world_frame: str | np.ndarray = "enu") -> np.ndarray:
    """R_ned_world (3, 3) of a map frame: a preset name (WORLD_FRAMES) or a rotation."""
    return _rotation(world_frame, WORLD_FRAMES, "world frame")


def ned_converter(mount: CameraMount, world_frame: str | np.ndarray = "enu") -> Callable[[np.ndarray], np.ndarray]:
    """``body_pose_ned`` with its two constant factors computed once (the MAVLink encoder runs it per pose)."""
    A = make_pose(_rotation(world_frame, WORLD_FRAMES, "world frame"), np.zeros(3))
    T_cam_body = invert_pose(mount.T_body_cam)
    return lambda T_c2w: A @ T_c2w @ T_cam_body


def body_pose_ned(T_c2w: np.ndarray, mount: CameraMount, world_frame: str | np.ndarray = "enu") -> np.ndarray:
    """Pose (4, 4) of the vehicle body (FRD) in the local NED frame from a camera-to-world pose (4, 4)."""
    T_c2w = np.asarray(T_c2w, dtype=np.float64)
    if T_c2w.shape != (4, 4):
        raise ValueError(f"T_c2w must be 4x4, got shape {T_c2w.shape}")
    return ned_converter(mount, world_frame)(T_c2w)
