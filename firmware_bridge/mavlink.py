"""MAVLink 2 output for PX4 and ArduPilot: VISION_POSITION_ESTIMATE (default) or ODOMETRY, plus HEARTBEAT.

pymavlink is the optional ``mavlink`` extra and is imported only when a MAVLink encoder or decoder
is created, so the bridge imports without it. PROTOCOL.md ("MAVLink") lists the frames and the
autopilot parameters a user sets.

Why VISION_POSITION_ESTIMATE by default: the localizer measures pose only, no velocity. ODOMETRY
carries velocity fields that we can only fill with NaN, and ArduPilot's ODOMETRY handler feeds them
to its velocity input; VISION_POSITION_ESTIMATE is accepted by both autopilots and is 48 bytes on
the wire (ODOMETRY: 245), so 100 Hz fits in 115200 baud.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np

from acesplat.core.config import knob, knob_default
from acesplat.core.errors import InputError
from acesplat.core.geometry import matrix_to_quat
from acesplat.core.pose import PoseRecord, TrackingState
from firmware_bridge.ned import CameraMount, matrix_to_euler, ned_converter, world_rotation
from firmware_bridge.protocol import RuntimeState

log = logging.getLogger(__name__)

MESSAGES = ("vision_position_estimate", "odometry")
MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY = 197


def load_dialect() -> Any:
    """pymavlink's MAVLink 2 common dialect, or a one-line InputError naming the extra to install."""
    try:
        from pymavlink.dialects.v20 import common
    except ImportError:
        raise InputError(None, "--protocol mavlink needs pymavlink: pip install 'acesplat-edge[mavlink]'") from None
    return common


@dataclass(frozen=True)
class MavlinkConfig:
    """How poses become MAVLink messages.

    A record's own covariance (PoseRecord.covariance) is sent when it has one; otherwise ``pos_std_m``/``ang_std_rad``
    fill the covariance diagonal, and None sends "unknown" (NaN) so the autopilot's own noise parameters
    (EKF2_EVP_NOISE/EKF2_EVA_NOISE, VISO_POS_M_NSE/VISO_YAW_M_NSE) apply.
    """

    message: str = knob("vision_position_estimate", "MAVLink message: vision_position_estimate or odometry.")
    mount: CameraMount = knob(reason="Where the camera sits on the vehicle (body FRD).", factory=CameraMount)
    world_frame: str | np.ndarray = knob("enu", "Axes of the map's world frame: a name (enu, ...) or a 3x3 rotation.")
    system_id: int = knob(1, "MAVLink system id of the sender (the vehicle's).")
    component_id: int = knob(MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY, "MAVLink component id (visual-inertial odometry).")
    pos_std_m: float | None = knob(None, "Position standard deviation (m) for the covariance; None: unknown.")
    ang_std_rad: float | None = knob(None, "Angle standard deviation (rad) for the covariance; None: unknown.")

    @classmethod
    def from_flags(
        cls,
        message: str | None = None,
        mount: str = "forward",
        offset: str = "0,0,0",
        pitch_deg: float = 0.0,
        world_frame: str | None = None,
    ) -> MavlinkConfig:
        """From command-line text, e.g. ``--mount forward --mount-offset 0.1,0,-0.05 --world-frame enu``; None
        takes the field's default."""
        try:
            xyz = tuple(float(v) for v in offset.split(","))
        except ValueError:
            xyz = ()
        if len(xyz) != 3 or not all(math.isfinite(v) for v in xyz):
            raise InputError(None, f"camera offset must be three numbers x,y,z in metres (body FRD), got {offset!r}")
        return cls(
            knob_default(cls, "message") if message is None else message,
            CameraMount.preset(mount, xyz, pitch_deg=pitch_deg),
            knob_default(cls, "world_frame") if world_frame is None else world_frame,
        )

    def __post_init__(self) -> None:
        if self.message not in MESSAGES:
            raise InputError(None, f"unknown MAVLink message {self.message!r}; choose one of {', '.join(MESSAGES)}")
        ned_converter(self.mount, self.world_frame)  # rejects an unknown or non-rigid world frame now


def covariance(pos_std_m: float | None, ang_std_rad: float | None) -> list[float]:
    """The 21-element upper triangle of the 6x6 pose covariance (x y z roll pitch yaw); NaN first = unknown."""
    cov = [0.0] * 21
    if pos_std_m is None or ang_std_rad is None:
        cov[0] = math.nan
        return cov
    for i in (0, 6, 11):
        cov[i] = pos_std_m**2
    for i in (15, 18, 20):
        cov[i] = ang_std_rad**2
    return cov


def upper_triangle(cov: np.ndarray) -> list[float]:
    """The 21 row-major upper-triangle entries of a (6, 6) matrix (MAVLink's covariance layout)."""
    cov = np.asarray(cov, np.float64)
    if cov.shape != (6, 6):
        raise ValueError(f"covariance must be (6, 6), got {cov.shape}")
    return [float(cov[i, j]) for i in range(6) for j in range(i, 6)]


def euler_rates(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """d(roll, pitch, yaw)/dw (3, 3) for a body -> NED rotation turned on the left, R -> exp([w]x) R (w in NED);
    singular at pitch = +-90 deg (the Euler angles' gimbal lock)."""
    cp, sp, cy, sy = math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    # w = E (d roll, d pitch, d yaw) for Z-Y-X Euler angles, E's columns the three axes in NED
    E = np.array([[cy * cp, -sy, 0.0], [sy * cp, cy, 0.0], [-sp, 0.0, 1.0]])
    return np.linalg.inv(E)


def ned_covariance(
    cov_world: np.ndarray, T_c2w: np.ndarray, mount: CameraMount, world_frame: str | np.ndarray
) -> np.ndarray:
    """A PoseRecord's covariance (6, 6) (camera centre in the world (m^2), then the left rotation vector (rad^2))
    as MAVLink's (6, 6) of the body pose in local NED: x y z (m^2) then roll pitch yaw (rad^2)."""
    A = world_rotation(world_frame)
    T = np.asarray(T_c2w, np.float64)
    R_ned_body = A @ T[:3, :3] @ mount.R_body_cam.T
    # body origin in the camera frame: -R_body_cam^T t_body_cam; a left turn w moves it by -[R lever]x w
    lever = T[:3, :3] @ (-mount.R_body_cam.T @ mount.t_body_cam)
    skew = np.array([[0.0, -lever[2], lever[1]], [lever[2], 0.0, -lever[0]], [-lever[1], lever[0], 0.0]])
    G = np.zeros((6, 6))
    G[:3, :3] = A
    G[:3, 3:] = -A @ skew
    G[3:, 3:] = euler_rates(*matrix_to_euler(R_ned_body)) @ A
    out = G @ np.asarray(cov_world, np.float64) @ G.T
    return 0.5 * (out + out.T)


def odometry_quality(rec: PoseRecord) -> int:
    """ODOMETRY ``quality`` (1 worst .. 100 best; 0 is "unknown") of a TRACKING pose from its inliers: the record's
    inlier ratio (SCR's PnP or the tracked alignment's) in percent, at least 1."""
    return max(1, int(round(min(max(float(rec.quality), 0.0), 1.0) * 100)))


class MavlinkEncoder:
    """Turns pose records into MAVLink 2 packets (one instance per link: it owns the packet sequence)."""

    def __init__(self, config: MavlinkConfig | None = None) -> None:
        self.config = config or MavlinkConfig()
        self._m = load_dialect()
        self._mav = self._m.MAVLink(None, srcSystem=self.config.system_id, srcComponent=self.config.component_id)
        self._to_ned = ned_converter(self.config.mount, self.config.world_frame)
        self._cov = covariance(self.config.pos_std_m, self.config.ang_std_rad)
        self._nan_cov = covariance(None, None)
        self._lost = False
        self._record_resets: int | None = None
        self.reset_counter = 0

    def pose(self, rec: PoseRecord) -> bytes | None:
        """The packet for ``rec``, or None when it is LOST (the autopilot then times the source out)."""
        if rec.state != TrackingState.TRACKING or not np.all(np.isfinite(rec.T_c2w)):
            self._lost = True
            return None
        # relocalized after a loss, or the pose source re-anchored with a jump: tell the EKF
        jumped = self._record_resets is not None and rec.reset_counter != self._record_resets
        if self._lost or jumped:
            self.reset_counter = (self.reset_counter + 1) & 0xFF
            self._lost = False
        self._record_resets = rec.reset_counter
        cov = self._cov
        if rec.covariance is not None and np.all(np.isfinite(rec.covariance)):
            c = ned_covariance(rec.covariance, rec.T_c2w, self.config.mount, self.config.world_frame)
            cov = upper_triangle(c)
        T = self._to_ned(np.asarray(rec.T_c2w, dtype=np.float64))
        x, y, z = T[:3, 3].tolist()
        usec = max(int(rec.timestamp_us), 0)
        if self.config.message == "vision_position_estimate":
            roll, pitch, yaw = matrix_to_euler(T[:3, :3])
            msg = self._mav.vision_position_estimate_encode(usec, x, y, z, roll, pitch, yaw, cov, self.reset_counter)
        else:
            nan = math.nan
            msg = self._mav.odometry_encode(
                usec,
                self._m.MAV_FRAME_LOCAL_FRD,
                self._m.MAV_FRAME_BODY_FRD,
                x,
                y,
                z,
                matrix_to_quat(T[:3, :3]).tolist(),
                nan,
                nan,
                nan,
                nan,
                nan,
                nan,
                cov,
                self._nan_cov,
                self.reset_counter,
                self._m.MAV_ESTIMATOR_TYPE_VISION,
                odometry_quality(rec),
            )
        return msg.pack(self._mav)

    def heartbeat(self, state: RuntimeState = RuntimeState.TRACKING) -> bytes:
        m = self._m
        status = {
            RuntimeState.STARTING: m.MAV_STATE_BOOT,
            RuntimeState.PAUSED: m.MAV_STATE_STANDBY,
            RuntimeState.ERROR: m.MAV_STATE_CRITICAL,
        }.get(state, m.MAV_STATE_ACTIVE)
        msg = self._mav.heartbeat_encode(m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID, 0, 0, status)
        return msg.pack(self._mav)


class MavlinkDecoder:
    """Bytes -> MAVLink messages for monitoring; never raises; counts bad data and unverifiable ids as rejected."""

    def __init__(self) -> None:
        self._m = load_dialect()
        self._new_parser()
        self.frames_ok = 0
        self.frames_rejected = 0
        self.bytes = 0
        self.messages: Counter[str] = Counter()

    def _new_parser(self) -> None:
        self._parser = self._m.MAVLink(None)
        self._parser.robust_parsing = True

    def feed(self, data: bytes) -> list[Any]:
        self.bytes += len(data)
        try:
            msgs = self._parser.parse_buffer(data) or []
        except Exception as e:  # third-party parser: a surprise must not end a monitoring run
            log.warning("pymavlink parser raised %r; resetting it", e)
            self.frames_rejected += 1
            self._new_parser()
            return []
        good = []
        for msg in msgs:
            # UNKNOWN_<id>: an id outside the dialect, whose CRC cannot be checked (no CRC_EXTRA) --
            # in practice noise that happened to contain a start byte.
            if msg.get_type() == "BAD_DATA" or msg.get_type().startswith("UNKNOWN_"):
                self.frames_rejected += 1
            else:
                self.frames_ok += 1
                self.messages[msg.get_type()] += 1
                good.append(msg)
        return good
