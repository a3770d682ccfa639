"""MAVLink output: frame conversion against hand-computed cases, packets decoded back with pymavlink."""

from __future__ import annotations

import math
import os
import select
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from acesplat.core.errors import InputError
from acesplat.core.geometry import make_pose
from acesplat.core.pose import PoseRecord, TrackingState
from firmware_bridge.mavlink import MavlinkConfig, MavlinkDecoder, MavlinkEncoder, covariance
from firmware_bridge.ned import CameraMount, body_pose_ned, euler_to_matrix, matrix_to_euler
from firmware_bridge.protocol import RuntimeState
from firmware_bridge.sink import PoseSink
from firmware_bridge.transport import serial_opener
from tests.test_bridge_transport import PtyPeer, wait_for

ROOT = Path(__file__).resolve().parents[1]
c10, s10 = math.cos(math.radians(10)), math.sin(math.radians(10))


def cam_pose(x_axis, y_axis, z_axis, position) -> np.ndarray:
    """Camera-to-world pose from the camera's x (right), y (down), z (forward) axes in world coordinates."""
    return make_pose(np.stack([x_axis, y_axis, z_axis], axis=1), position)


# Hand-computed: map is z-up ENU (x east, y north, z up); body FRD; expected NED position and (roll, pitch, yaw).
CASES = [
    # level camera looking north from (1, 2, 3): body at N=2, E=1, D=-3, no rotation
    ("forward", (0, 0, 0), cam_pose((1, 0, 0), (0, 0, -1), (0, 1, 0), (1, 2, 3)), (2, 1, -3), (0, 0, 0)),
    # looking east: yaw +90 deg (clockwise from north seen from above)
    ("forward", (0, 0, 0), cam_pose((0, -1, 0), (0, 0, -1), (1, 0, 0), (0, 0, 0)), (0, 0, 0), (0, 0, 90)),
    # camera 10 cm ahead of the body origin, looking north from 1 m up: the body is 10 cm south of it
    ("forward", (0.1, 0, 0), cam_pose((1, 0, 0), (0, 0, -1), (0, 1, 0), (0, 0, 1)), (-0.1, 0, -1), (0, 0, 0)),
    # same offset, looking east: the body is 10 cm west of the camera
    ("forward", (0.1, 0, 0), cam_pose((0, -1, 0), (0, 0, -1), (1, 0, 0), (0, 0, 0)), (0, -0.1, 0), (0, 0, 90)),
    # down-looking camera 2 m up, image top toward north: level body heading north
    ("down", (0, 0, 0), cam_pose((1, 0, 0), (0, -1, 0), (0, 0, -1), (0, 0, 2)), (0, 0, -2), (0, 0, 0)),
    # forward camera pitched 10 deg up while looking north: the body pitches up 10 deg
    ("forward", (0, 0, 0), cam_pose((1, 0, 0), (0, s10, -c10), (0, c10, s10), (0, 0, 0)), (0, 0, 0), (0, 10, 0)),
]


@pytest.mark.parametrize("mount, offset, T_c2w, ned, rpy_deg", CASES)
def test_body_pose_ned_hand_cases(mount, offset, T_c2w, ned, rpy_deg) -> None:
    T = body_pose_ned(T_c2w, CameraMount.preset(mount, offset_m=offset), "enu")
    np.testing.assert_allclose(T[:3, 3], ned, atol=1e-12)
    np.testing.assert_allclose(np.degrees(matrix_to_euler(T[:3, :3])), rpy_deg, atol=1e-9)


def test_world_frame_presets() -> None:
    mount = CameraMount.preset("forward")
    # A map that is the first camera's own frame (OpenCV axes): that camera is a level body at the origin,
    # and 1 m along the map's z (the camera's forward) is 1 m north.
    T = body_pose_ned(np.eye(4), mount, "opencv")
    np.testing.assert_allclose(T, np.eye(4), atol=1e-12)
    moved = make_pose(np.eye(3), (0, 0, 1.0))
    np.testing.assert_allclose(body_pose_ned(moved, mount, "opencv")[:3, 3], (1, 0, 0), atol=1e-12)
    # FLU map (x forward, y left, z up): 1 m left and 2 m up is E = -1, D = -2
    np.testing.assert_allclose(
        body_pose_ned(make_pose(mount.R_body_cam, (0, 1, 2)), mount, "flu")[:3, 3], (0, -1, -2), atol=1e-12
    )
    with pytest.raises(InputError, match="world frame"):
        body_pose_ned(np.eye(4), mount, "ecef")
    with pytest.raises(ValueError, match="determinant"):
        body_pose_ned(np.eye(4), mount, np.diag([1.0, 1.0, -1.0]))


def test_euler_convention_and_round_trip() -> None:
    np.testing.assert_allclose(
        euler_to_matrix(0, 0, math.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-12
    )  # yaw 90: nose east
    np.testing.assert_allclose(
        euler_to_matrix(0, math.radians(30), 0) @ [1, 0, 0], [c := math.cos(math.radians(30)), 0, -0.5], atol=1e-12
    )
    np.testing.assert_allclose(
        euler_to_matrix(math.radians(30), 0, 0) @ [0, 1, 0], [0, c, 0.5], atol=1e-12
    )  # right wing down
    rng = np.random.default_rng(3)
    for _ in range(200):
        rpy = rng.uniform([-math.pi, -1.5, -math.pi], [math.pi, 1.5, math.pi])
        np.testing.assert_allclose(matrix_to_euler(euler_to_matrix(*rpy)), rpy, atol=1e-9)


def test_mount_presets_and_tilt() -> None:
    tilted = CameraMount.preset("forward", pitch_deg=-20)
    np.testing.assert_allclose(
        tilted.R_body_cam[:, 2], [math.cos(math.radians(20)), 0, math.sin(math.radians(20))], atol=1e-12
    )
    np.testing.assert_allclose(CameraMount.preset("down").R_body_cam[:, 2], [0, 0, 1])
    with pytest.raises(InputError, match="camera mount"):
        CameraMount.preset("sideways")
    with pytest.raises(ValueError):
        CameraMount(np.eye(3), np.array([0.0, math.nan, 0.0]))


def test_config_from_command_line_flags() -> None:
    cfg = MavlinkConfig.from_flags("odometry", "down", "0.1,0,-0.05", world_frame="flu")
    assert cfg.message == "odometry" and cfg.world_frame == "flu"
    np.testing.assert_allclose(cfg.mount.t_body_cam, [0.1, 0, -0.05])
    np.testing.assert_allclose(cfg.mount.R_body_cam, CameraMount.preset("down").R_body_cam)
    for bad in ("0.1,0", "a,b,c", "0,0,nan"):
        with pytest.raises(InputError, match="offset"):
            MavlinkConfig.from_flags(offset=bad)
    with pytest.raises(InputError, match="MAVLink message"):
        MavlinkConfig.from_flags(message="gps_input")
    with pytest.raises(InputError, match="world frame"):
        MavlinkConfig.from_flags(world_frame="ecef")


def _parse(data: bytes) -> list:
    dec = MavlinkDecoder()
    msgs = dec.feed(data)
    assert dec.frames_rejected == 0
    return msgs


def test_vision_position_estimate_decodes_back() -> None:
    enc = MavlinkEncoder(MavlinkConfig(mount=CameraMount.preset("forward", offset_m=(0.1, 0, 0))))
    rec = PoseRecord(1_234_567, CASES[3][2], 200, TrackingState.TRACKING, 0.9, 3)
    (msg,) = _parse(enc.pose(rec))
    assert msg.get_type() == "VISION_POSITION_ESTIMATE" and msg.get_srcSystem() == 1 and msg.get_srcComponent() == 197
    assert msg.usec == 1_234_567 and msg.reset_counter == 0
    np.testing.assert_allclose([msg.x, msg.y, msg.z], [0, -0.1, 0], atol=1e-7)
    np.testing.assert_allclose([msg.roll, msg.pitch, msg.yaw], [0, 0, math.pi / 2], atol=1e-6)
    assert math.isnan(msg.covariance[0])  # unknown: the autopilot's noise parameters apply


def test_odometry_decodes_back_with_frames_quaternion_and_quality() -> None:
    enc = MavlinkEncoder(MavlinkConfig(message="odometry", pos_std_m=0.05, ang_std_rad=0.02))
    (msg,) = _parse(enc.pose(PoseRecord(5, CASES[1][2], 10, TrackingState.TRACKING, 0.5)))
    assert msg.get_type() == "ODOMETRY"
    assert (msg.frame_id, msg.child_frame_id) == (20, 12)  # MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD
    np.testing.assert_allclose(msg.q, [math.sqrt(0.5), 0, 0, math.sqrt(0.5)], atol=1e-7)  # yaw 90 deg
    assert math.isnan(msg.vx) and msg.quality == 50 and msg.estimator_type == 2
    np.testing.assert_allclose(
        [msg.pose_covariance[i] for i in (0, 6, 11, 15, 18, 20)], [0.0025] * 3 + [0.0004] * 3, rtol=1e-6
    )
    assert covariance(0.05, 0.02)[1:6] == [0.0] * 5


def test_lost_poses_are_not_sent_and_relocalization_bumps_reset_counter() -> None:
    enc = MavlinkEncoder()
    T = CASES[0][2]
    assert enc.pose(PoseRecord(1, T, 100, TrackingState.TRACKING, 0.8)) is not None
    assert enc.pose(PoseRecord(2, T, 3, TrackingState.LOST, 0.1)) is None
    assert enc.pose(PoseRecord(3, np.full((4, 4), np.nan), 0, TrackingState.TRACKING, 0.1)) is None
    (msg,) = _parse(enc.pose(PoseRecord(4, T, 100, TrackingState.TRACKING, 0.8)))
    assert msg.reset_counter == 1


def test_heartbeat_fields() -> None:
    enc = MavlinkEncoder()
    (hb,) = _parse(enc.heartbeat(RuntimeState.TRACKING))
    assert (hb.get_type(), hb.type, hb.autopilot, hb.system_status) == ("HEARTBEAT", 18, 8, 4)
    (hb,) = _parse(enc.heartbeat(RuntimeState.ERROR))
    assert hb.system_status == 5  # MAV_STATE_CRITICAL


def test_mavlink_decoder_survives_noise_and_accepts_only_intact_packets() -> None:
    enc = MavlinkEncoder()
    good = enc.pose(PoseRecord(1, CASES[0][2], 100, TrackingState.TRACKING, 0.8))
    rng = np.random.default_rng(0)
    dec = MavlinkDecoder()
    accepted = []
    for _ in range(200):
        accepted += dec.feed(rng.integers(0, 256, int(rng.integers(1, 300)), dtype=np.uint8).tobytes())
        accepted += dec.feed(good)
    assert dec.frames_rejected > 0 and accepted
    # MAVLink has no delimiter: noise holding a start byte can swallow the packet after it (PROTOCOL.md),
    # but whatever is accepted is the intact packet.
    assert all(bytes(m.get_msgbuf()) == good for m in accepted)


def test_mavlink_sink_over_pty_sends_heartbeats_and_poses() -> None:
    peer = PtyPeer()
    sink = PoseSink(serial_opener(peer.name, 115200), "mavlink", heartbeat_hz=20.0)
    got = bytearray()

    def read() -> None:
        while select.select([peer.master], [], [], 0)[0]:
            got.extend(os.read(peer.master, 65536))

    try:
        sink.submit(PoseRecord(10, CASES[0][2], 100, TrackingState.TRACKING, 0.8))
        wait_for(lambda: sink.stats().sent == 1 and sink.stats().heartbeats >= 2, "pose and heartbeats")
        sink.submit(PoseRecord(11, CASES[0][2], 1, TrackingState.LOST, 0.0))
        wait_for(lambda: sink.stats().skipped == 1, "LOST pose withheld")
    finally:
        sink.close()
        read()
        peer.unplug()
    msgs = _parse(bytes(got))
    types = [m.get_type() for m in msgs]
    assert types.count("VISION_POSITION_ESTIMATE") == 1 and types.count("HEARTBEAT") == sink.stats().heartbeats
    vpe = next(m for m in msgs if m.get_type() == "VISION_POSITION_ESTIMATE")
    np.testing.assert_allclose([vpe.x, vpe.y, vpe.z], [2, 1, -3], atol=1e-6)


def test_bridge_imports_without_pymavlink_and_says_what_to_install() -> None:
    code = """
import sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] == 'pymavlink':
            raise ImportError('blocked: ' + name)
sys.meta_path.insert(0, Block())
import firmware_bridge.sink, acesplat.apps.bridge_cmd, firmware_bridge.mavlink
from acesplat.core.errors import InputError
from firmware_bridge.sink import open_sink
try:
    open_sink('loop://', protocol='mavlink')
except InputError as e:
    print(e)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert "pip install 'acesplat-edge[mavlink]'" in out.stdout


def _ned_state(T_c2w: np.ndarray, mount: CameraMount) -> np.ndarray:
    T = body_pose_ned(T_c2w, mount, "enu")
    return np.r_[T[:3, 3], matrix_to_euler(T[:3, :3])]


def test_record_covariance_goes_to_ned_like_sampled_poses() -> None:
    """The record's world covariance, converted to (x y z roll pitch yaw) in NED, matches the spread of the states
    of poses sampled from it and converted one by one (the encoder's own conversion)."""
    import cv2

    from firmware_bridge.mavlink import ned_covariance, upper_triangle

    rng = np.random.default_rng(0)
    mount = CameraMount.preset("forward", offset_m=(0.2, -0.1, 0.05), pitch_deg=-15.0)
    T = cam_pose((c10, -s10, 0), (0, 0, -1), (s10, c10, 0), (1.0, 2.0, 1.5))
    L = rng.normal(size=(6, 6)) * np.r_[[0.02] * 3, [0.01] * 3][:, None]
    C = L @ L.T
    states = []
    for d in rng.multivariate_normal(np.zeros(6), C, 20000):
        Td = make_pose(cv2.Rodrigues(d[3:])[0] @ T[:3, :3], T[:3, 3] + d[:3])
        states.append(_ned_state(Td, mount))
    states = np.array(states)
    states[:, 3:] = (states[:, 3:] - _ned_state(T, mount)[3:] + np.pi) % (2 * np.pi) - np.pi
    mc = np.cov(states.T)
    got = ned_covariance(C, T, mount, "enu")
    scale = np.sqrt(np.outer(np.diag(got), np.diag(got)))
    np.testing.assert_allclose(got / scale, mc / scale, atol=0.03)
    enc = MavlinkEncoder(MavlinkConfig(mount=mount, pos_std_m=1.0, ang_std_rad=1.0))
    (msg,) = _parse(enc.pose(PoseRecord(1, T, 100, TrackingState.TRACKING, 0.8, covariance=C)))
    np.testing.assert_allclose(msg.covariance, upper_triangle(got), rtol=1e-5, atol=1e-12)
    (msg,) = _parse(enc.pose(PoseRecord(2, T, 100, TrackingState.TRACKING, 0.8)))  # none: the configured diagonal
    assert msg.covariance[0] == 1.0 and msg.covariance[1] == 0.0
    with pytest.raises(ValueError, match=r"\(6, 6\)"):
        upper_triangle(np.eye(5))


def test_record_reset_counter_change_bumps_the_encoders_and_quality_is_the_inlier_ratio() -> None:
    enc = MavlinkEncoder(MavlinkConfig(message="odometry"))
    T = CASES[0][2]
    first = _parse(enc.pose(PoseRecord(1, T, 100, TrackingState.TRACKING, 0.0, reset_counter=4)))[0]
    assert first.reset_counter == 0 and first.quality == 1  # a TRACKING pose is never "unknown" (0)
    same = _parse(enc.pose(PoseRecord(2, T, 100, TrackingState.TRACKING, 0.734, reset_counter=4)))[0]
    assert same.reset_counter == 0 and same.quality == 73
    jumped = _parse(enc.pose(PoseRecord(3, T, 100, TrackingState.TRACKING, 0.8, reset_counter=5)))[0]
    assert jumped.reset_counter == 1
    assert enc.pose(PoseRecord(4, T, 0, TrackingState.LOST, 0.0, reset_counter=5)) is None
    back = _parse(enc.pose(PoseRecord(5, T, 100, TrackingState.TRACKING, 0.8, reset_counter=6)))[0]
    assert back.reset_counter == 2  # a loss and a jump at once: one reset
