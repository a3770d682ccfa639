"""Firmware bridge: poses to a microcontroller or flight controller over serial. Imports neither torch nor onnx.

The edge runtime needs only ``open_sink`` (see sink.py); PROTOCOL.md documents the bytes.
"""

from firmware_bridge.mavlink import MavlinkConfig
from firmware_bridge.ned import CameraMount
from firmware_bridge.protocol import CommandCode, RuntimeState
from firmware_bridge.sink import CommandEvent, PoseSink, SinkStats, open_sink

__all__ = [
    "CameraMount",
    "CommandCode",
    "CommandEvent",
    "MavlinkConfig",
    "PoseSink",
    "RuntimeState",
    "SinkStats",
    "open_sink",
]
