"""Protocol v1 of the firmware bridge: message records and their frames (PROTOCOL.md has every byte).

A frame on the wire is ``COBS(header | payload | crc32) 0x00``:

- header (5 bytes): version u8 = 1, type u8, sequence u16, payload length u8;
- payload: a fixed little-endian layout per type (POSE 48, STATUS 28, COMMAND 8, ACK 4 bytes);
- CRC-32 (IEEE 802.3 / zlib) of header and payload, little-endian.

CRC-32 rather than CRC-16: both catch every short burst and every 1-3 bit error in frames this
short; beyond that a corrupted frame passes a CRC-16 with probability 2^-16 and a CRC-32 with 2^-32.
On a link that mangles one frame in ten at 100 frames/s that is one bad pose accepted about every
two hours with CRC-16, and about one in fourteen years with CRC-32. It costs two bytes per frame
(3 % of a POSE frame); zlib computes it in C on the host, the firmware uses a 64-byte nibble table.
"""

from __future__ import annotations

import enum
import math
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from acesplat.core.geometry import matrix_to_quat, quat_to_matrix
from acesplat.core.pose import PoseRecord, TrackingState
from firmware_bridge.cobs import cobs_decode, cobs_encode

VERSION = 1
HEADER = struct.Struct("<BBHB")
CRC = struct.Struct("<I")
OVERHEAD = HEADER.size + CRC.size
MAX_BODY = 254
"""Largest header + payload + CRC a receiver accepts; bounds every buffer (C: 254 bytes)."""
MAX_SEGMENT = 256
"""Longest COBS segment that can decode to MAX_BODY bytes; anything longer is an overflow."""
DELIMITER = b"\x00"

REJECT_REASONS = ("overflow", "cobs", "short", "crc", "version", "type", "length", "value")
"""Why a frame was rejected, in the order the checks run (the C decoder uses the same order)."""


class MsgType(enum.IntEnum):
    POSE = 0x01
    STATUS = 0x02
    COMMAND = 0x10
    ACK = 0x11


class RuntimeState(enum.IntEnum):
    """What the localization loop is doing (STATUS heartbeat)."""

    STARTING = 0
    TRACKING = 1
    LOST = 2
    PAUSED = 3
    ERROR = 4


class CommandCode(enum.IntEnum):
    RELOCALIZE = 1
    PAUSE = 2
    RESUME = 3
    SET_RATE = 4


class AckResult(enum.IntEnum):
    ACCEPTED = 0
    REJECTED = 1
    """Known command with an invalid argument (e.g. SET_RATE to 0 Hz)."""
    UNSUPPORTED = 2
    """Command code this host does not know (a newer firmware talking to an older host)."""


@dataclass(frozen=True)
class Pose:
    """POSE: camera-to-world pose of one localized frame (OpenCV camera axes, metres, map frame).

    ``position`` is the camera centre in the map; ``quat_wxyz`` rotates camera axes into map axes.
    """

    timestamp_us: int
    frame_id: int
    position: tuple[float, float, float]
    quat_wxyz: tuple[float, float, float, float]
    inliers: int
    state: TrackingState
    quality: float

    @classmethod
    def from_record(cls, rec: PoseRecord) -> Pose:
        """Wire form of a PoseRecord; out-of-range counters are clamped or wrapped so encoding never fails."""
        T = np.asarray(rec.T_c2w, dtype=np.float64)
        state = TrackingState(int(rec.state))
        rows = T.tolist()  # scalar checks on a list beat numpy calls on a 4x4 (this runs per pose)
        if all(math.isfinite(v) for row in rows for v in row):
            position = (rows[0][3], rows[1][3], rows[2][3])
            quat = tuple(matrix_to_quat(T[:3, :3]).tolist())
        else:
            position, quat, state = (math.nan,) * 3, (math.nan,) * 4, TrackingState.LOST
        quality = float(rec.quality)
        quality = min(max(quality, 0.0), 1.0) if math.isfinite(quality) else 0.0
        return cls(
            timestamp_us=max(int(rec.timestamp_us), 0) & 0xFFFF_FFFF_FFFF_FFFF,
            frame_id=int(rec.frame_id) & 0xFFFF_FFFF,
            position=position,  # type: ignore[arg-type]
            quat_wxyz=quat,  # type: ignore[arg-type]
            inliers=min(max(int(rec.inliers), 0), 0xFFFF),
            state=state,
            quality=quality,
        )

    def to_record(self) -> PoseRecord:
        T = np.eye(4)
        if all(math.isfinite(v) for v in self.quat_wxyz + self.position):
            T[:3, :3] = quat_to_matrix(np.array(self.quat_wxyz))
            T[:3, 3] = self.position
        else:
            T[:] = math.nan
        return PoseRecord(self.timestamp_us, T, self.inliers, self.state, self.quality, self.frame_id)


@dataclass(frozen=True)
class Status:
    """STATUS heartbeat (1 Hz): runtime state and health figures."""

    timestamp_us: int
    fps: float
    latency_ms: float
    frames_dropped: int
    """Camera frames the runtime skipped."""
    poses_dropped: int
    """Poses the bridge replaced by a newer one before they were sent."""
    state: RuntimeState


@dataclass(frozen=True)
class Command:
    """COMMAND from the microcontroller; ``command`` stays an int so unknown codes can be answered."""

    command: int
    value: float = 0.0


@dataclass(frozen=True)
class Ack:
    """ACK of the COMMAND frame whose sequence number is ``acked_seq``."""

    acked_seq: int
    command: int
    result: AckResult


Message = Pose | Status | Command | Ack


@dataclass(frozen=True)
class Frame:
    """One decoded frame: its sequence number and message."""

    seq: int
    message: Message


_LAYOUTS: dict[MsgType, struct.Struct] = {
    MsgType.POSE: struct.Struct("<QI3f4fHBxf"),
    MsgType.STATUS: struct.Struct("<QffIIB3x"),
    MsgType.COMMAND: struct.Struct("<B3xf"),
    MsgType.ACK: struct.Struct("<HBB"),
}
PAYLOAD_SIZES = {t: s.size for t, s in _LAYOUTS.items()}
_TYPE_OF = {Pose: MsgType.POSE, Status: MsgType.STATUS, Command: MsgType.COMMAND, Ack: MsgType.ACK}
# header and payload packed by one struct call: the encode path runs once per pose.
_PACKERS = {t: struct.Struct(HEADER.format + s.format.lstrip("<")) for t, s in _LAYOUTS.items()}


def _fields(msg: Message) -> tuple:
    if isinstance(msg, Pose):
        return (msg.timestamp_us, msg.frame_id, *msg.position, *msg.quat_wxyz, msg.inliers, int(msg.state), msg.quality)
    if isinstance(msg, Status):
        return (msg.timestamp_us, msg.fps, msg.latency_ms, msg.frames_dropped, msg.poses_dropped, int(msg.state))
    if isinstance(msg, Command):
        return (msg.command, msg.value)
    return (msg.acked_seq, msg.command, int(msg.result))


def encode_body(msg: Message, seq: int) -> bytes:
    """Header, payload and CRC of ``msg`` before COBS (the bytes the CRC protects, plus the CRC)."""
    t = _TYPE_OF.get(type(msg))
    if t is None:
        raise TypeError(f"not a protocol message: {type(msg).__name__}")
    try:
        body = _PACKERS[t].pack(VERSION, t, seq & 0xFFFF, PAYLOAD_SIZES[t], *_fields(msg))
    except struct.error as e:
        raise ValueError(f"{t.name} field out of range: {e}") from None
    return body + CRC.pack(zlib.crc32(body))


def encode_frame(msg: Message, seq: int) -> bytes:
    """The wire bytes of ``msg``: COBS-encoded body followed by the 0x00 delimiter."""
    return cobs_encode(encode_body(msg, seq)) + DELIMITER


def parse_body(body: bytes) -> Frame | str:
    """The frame in a decoded ``body``, or the reject reason (one of REJECT_REASONS)."""
    if len(body) > MAX_BODY:
        return "overflow"
    if len(body) < OVERHEAD:
        return "short"
    if zlib.crc32(body[:-4]) != CRC.unpack_from(body, len(body) - 4)[0]:
        return "crc"
    version, type_code, seq, length = HEADER.unpack_from(body)
    if version != VERSION:
        return "version"
    if type_code not in PAYLOAD_SIZES:
        return "type"
    t = MsgType(type_code)
    if length != len(body) - OVERHEAD or length != PAYLOAD_SIZES[t]:
        return "length"
    v = _LAYOUTS[t].unpack_from(body, HEADER.size)
    try:
        if t is MsgType.POSE:
            msg: Message = Pose(v[0], v[1], v[2:5], v[5:9], v[9], TrackingState(v[10]), v[11])
        elif t is MsgType.STATUS:
            msg = Status(v[0], v[1], v[2], v[3], v[4], RuntimeState(v[5]))
        elif t is MsgType.COMMAND:
            msg = Command(v[0], v[1])
        else:
            msg = Ack(v[0], v[1], AckResult(v[2]))
    except ValueError:
        return "value"
    return Frame(seq, msg)


def decode_segment(segment: bytes) -> Frame | str:
    """The frame in one delimiter-free COBS ``segment``, or the reject reason."""
    if len(segment) > MAX_SEGMENT:
        return "overflow"
    body, complete = cobs_decode(segment)
    if len(body) > MAX_BODY:
        return "overflow"
    if not complete:
        return "cobs"
    return parse_body(body)


def wire_size(msg_type: MsgType) -> int:
    """Bytes on the wire of one frame of ``msg_type`` (COBS adds exactly one byte below 254, plus the delimiter)."""
    return OVERHEAD + PAYLOAD_SIZES[msg_type] + 2
