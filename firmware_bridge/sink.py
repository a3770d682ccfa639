"""PoseSink: hand poses to the robot without ever blocking the localization loop.

``submit`` only swaps a pose into a one-slot mailbox (the newest pose replaces an unsent older
one, and the replaced one is counted as dropped). A writer thread encodes and writes, adds the
1 Hz STATUS/HEARTBEAT and the ACKs, and reopens the port with backoff when it vanishes; a reader
thread decodes what the microcontroller sends and delivers COMMANDs as events.

    sink = open_sink("/dev/ttyUSB0", 115200, protocol="frame", rate_hz=30)
    sink.submit(record)                       # every frame; never blocks
    sink.update_status(state=RuntimeState.TRACKING, fps=28.5, latency_ms=31.0)
    for event in sink.poll_commands(): ...    # RELOCALIZE / PAUSE / RESUME / SET_RATE
    sink.close(); print(sink.stats())
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
import serial

from acesplat.core.config import knob, knob_default
from acesplat.core.errors import InputError
from acesplat.core.pose import PoseRecord
from firmware_bridge.decoder import StreamDecoder
from firmware_bridge.mavlink import MavlinkConfig, MavlinkDecoder, MavlinkEncoder
from firmware_bridge.protocol import (
    Ack,
    AckResult,
    Command,
    CommandCode,
    Frame,
    Pose,
    RuntimeState,
    Status,
    encode_frame,
)
from firmware_bridge.transport import Opener, SerialLink, serial_opener

log = logging.getLogger(__name__)

PROTOCOLS = ("frame", "mavlink")
MAX_RATE_HZ = 1000.0
"""The highest pose rate a sink accepts."""
EVENT_QUEUE = 64
"""Undelivered command events kept; older ones are dropped (and counted) if nobody polls."""


@dataclass(frozen=True)
class SinkConfig:
    """The sink's settings; PoseSink and open_sink take them as keyword arguments with these defaults."""

    baud: int = knob(115200, "Serial baud rate.")
    protocol: str = knob("frame", "frame (acesplat protocol v1) or mavlink.")
    rate_hz: float | None = knob(None, "Cap on poses per second (None: every pose, as fast as the link takes them).")
    heartbeat_hz: float = knob(1.0, "STATUS (frame protocol) or HEARTBEAT (MAVLink) messages per second.")
    max_age_s: float = knob(0.5, "A pose waiting longer than this for the link is skipped, not sent late.")
    backoff_s: tuple[float, float] = knob((0.05, 2.0), "Reopen backoff of a lost port: first and longest wait (s).")
    wait_for_port: bool = knob(False, "Start without the port and open it when it appears (else: error at once).")


def _default(name: str) -> Any:
    return knob_default(SinkConfig, name)


@dataclass(frozen=True)
class CommandEvent:
    """A COMMAND the microcontroller sent and the bridge accepted (and ACKed)."""

    command: CommandCode
    value: float
    seq: int
    received_s: float
    """time.monotonic() when it arrived."""


@dataclass
class SinkStats:
    submitted: int = 0
    sent: int = 0
    dropped: int = 0
    """Poses never sent: replaced by a newer one, stale after an outage, or lost in a failed write."""
    skipped: int = 0
    """LOST poses not sent over MAVLink (the autopilot times the source out instead)."""
    heartbeats: int = 0
    bytes_out: int = 0
    write_timeouts: int = 0
    reconnects: int = 0
    outage_s: float = 0.0
    commands: int = 0
    commands_dropped: int = 0
    acks: int = 0
    rx_frames_ok: int = 0
    rx_frames_rejected: int = 0
    connected: bool = False
    last_error: str = ""

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class FrameEncoder:
    """Protocol v1 frames with one sequence counter per link (the receiver sees gaps as losses)."""

    resync = b"\x00"
    """Sent first after a (re)connect or a failed write: ends any partial frame at the receiver."""

    def __init__(self) -> None:
        self._seq = 0

    def _next_seq(self) -> int:
        seq, self._seq = self._seq, (self._seq + 1) & 0xFFFF
        return seq

    def pose(self, rec: PoseRecord) -> bytes:
        return encode_frame(Pose.from_record(rec), self._next_seq())

    def heartbeat(self, status: Status) -> bytes:
        return encode_frame(status, self._next_seq())

    def ack(self, acked_seq: int, command: int, result: AckResult) -> bytes:
        return encode_frame(Ack(acked_seq, command, result), self._next_seq())


def command_result(cmd: Command) -> AckResult:
    if cmd.command not in CommandCode._value2member_map_:
        return AckResult.UNSUPPORTED
    if cmd.command == CommandCode.SET_RATE and not (math.isfinite(cmd.value) and 0.0 < cmd.value <= MAX_RATE_HZ):
        return AckResult.REJECTED
    return AckResult.ACCEPTED


def _check_rate(rate_hz: float | None) -> float | None:
    if rate_hz is not None and not (math.isfinite(rate_hz) and 0.0 < rate_hz <= MAX_RATE_HZ):
        raise InputError(None, f"rate must be in (0, {MAX_RATE_HZ:g}] Hz, got {rate_hz}")
    return rate_hz


class PoseSink:
    """Non-blocking pose output over a serial link; see the module docstring. Use ``open_sink``."""

    def __init__(
        self,
        opener: Opener,
        protocol: str = _default("protocol"),
        rate_hz: float | None = _default("rate_hz"),
        *,
        mavlink: MavlinkConfig | None = None,
        on_command: Callable[[CommandEvent], None] | None = None,
        wait_for_port: bool = _default("wait_for_port"),
        heartbeat_hz: float = _default("heartbeat_hz"),
        max_age_s: float = _default("max_age_s"),
        backoff_s: tuple[float, float] = _default("backoff_s"),
        name: str | None = None,
    ) -> None:
        if protocol not in PROTOCOLS:
            raise InputError(None, f"unknown protocol {protocol!r}; choose one of {', '.join(PROTOCOLS)}")
        self.protocol = protocol
        self._rate_hz = _check_rate(rate_hz)
        self._heartbeat_period = 1.0 / heartbeat_hz
        self._max_age_s = max_age_s
        self._on_command = on_command
        if protocol == "frame":
            self._encoder: Any = FrameEncoder()
            self._decoder: Any = StreamDecoder()
        else:
            self._encoder = MavlinkEncoder(mavlink)
            self._decoder = MavlinkDecoder()
        self._stats = SinkStats()
        self._cond = threading.Condition()
        self._slot: tuple[PoseRecord, float] | None = None
        self._acks: deque[tuple[int, int, AckResult]] = deque(maxlen=16)
        self._events: deque[CommandEvent] = deque()
        self._status = dict(state=RuntimeState.STARTING, fps=0.0, latency_ms=0.0, frames_dropped=0)
        self._last_command: tuple[int, Command] | None = None
        self._stop = threading.Event()
        self._link = SerialLink(opener, name, backoff_s, on_down=self._wake_writer)
        if not wait_for_port:
            self._link.open_first()
        self._threads = [
            threading.Thread(target=self._write_loop, name="bridge-writer", daemon=True),
            threading.Thread(target=self._read_loop, name="bridge-reader", daemon=True),
        ]
        for t in self._threads:
            t.start()

    # ------------------------------------------------------------------ caller side

    def submit(self, rec: PoseRecord) -> None:
        """Queue ``rec`` for sending; returns at once. An unsent older pose is replaced (counted as dropped)."""
        if not isinstance(rec, PoseRecord):
            raise TypeError(f"submit() takes a PoseRecord, got {type(rec).__name__}")
        T = np.array(rec.T_c2w, dtype=np.float64)  # a copy: the caller may reuse its array
        if T.shape != (4, 4):
            raise ValueError(f"PoseRecord.T_c2w must be 4x4, got shape {T.shape}")
        rec = replace(rec, T_c2w=T)
        with self._cond:
            if self._stop.is_set():
                raise RuntimeError("submit() on a closed PoseSink")
            self._stats.submitted += 1
            if self._slot is not None:
                self._stats.dropped += 1
            self._slot = (rec, time.monotonic())
            self._cond.notify()

    def update_status(
        self,
        state: RuntimeState | None = None,
        fps: float | None = None,
        latency_ms: float | None = None,
        frames_dropped: int | None = None,
    ) -> None:
        """Figures for the next STATUS heartbeat (frame protocol) or HEARTBEAT system status (MAVLink)."""
        new = {
            k: v
            for k, v in dict(state=state, fps=fps, latency_ms=latency_ms, frames_dropped=frames_dropped).items()
            if v is not None
        }
        if "state" in new:
            new["state"] = RuntimeState(int(new["state"]))
        with self._cond:
            self._status.update(new)

    def poll_commands(self) -> list[CommandEvent]:
        """Commands received since the last call, oldest first."""
        with self._cond:
            events = list(self._events)
            self._events.clear()
        return events

    @property
    def rate_hz(self) -> float | None:
        return self._rate_hz

    def set_rate(self, rate_hz: float | None) -> None:
        """Cap on poses per second (None: every pose, as fast as the link takes them)."""
        with self._cond:
            self._rate_hz = _check_rate(rate_hz)
            self._cond.notify()

    def stats(self) -> SinkStats:
        with self._cond:
            s = replace(self._stats)
        s.reconnects = self._link.reconnects
        s.outage_s = round(self._link.outage_s(), 3)
        s.connected = self._link.port is not None
        s.last_error = self._link.last_error
        s.rx_frames_ok = self._decoder.frames_ok
        s.rx_frames_rejected = self._decoder.frames_rejected
        return s

    def close(self) -> None:
        with self._cond:
            self._stop.set()
            self._cond.notify_all()
        self._link.close()
        for t in self._threads:
            t.join(timeout=2.0)

    def __enter__(self) -> PoseSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ writer thread

    def _status_message(self) -> Status:
        s = self._status
        return Status(
            time.monotonic_ns() // 1000,
            float(s["fps"]),
            float(s["latency_ms"]),
            int(s["frames_dropped"]) & 0xFFFF_FFFF,
            self._stats.dropped & 0xFFFF_FFFF,
            s["state"],
        )

    def _next_batch(self, port: Any, next_hb: float, next_pose: float) -> tuple[PoseRecord | None, float, list, Any]:
        """Wait until something is due and take it: (pose, submitted_at, acks, heartbeat payload or None).

        Returns nothing due if the sink is closing or the reader found the port dead meanwhile.
        """
        with self._cond:
            while True:
                if self._stop.is_set() or self._link.port is not port:
                    return None, 0.0, [], None
                now = time.monotonic()
                pose_due = self._slot is not None and now >= next_pose
                hb_due = now >= next_hb
                if pose_due or hb_due or self._acks:
                    break
                wait = next_hb - now
                if self._slot is not None:
                    wait = min(wait, next_pose - now)
                self._cond.wait(wait)
            rec, submitted = None, 0.0
            if pose_due:
                (rec, submitted), self._slot = self._slot, None  # type: ignore[misc]
            acks = list(self._acks)
            self._acks.clear()
            hb = None
            if hb_due:
                hb = self._status_message() if self.protocol == "frame" else self._status["state"]
            return rec, submitted, acks, hb

    def _encode(self, rec: PoseRecord | None, stale: bool, acks: list, hb: Any) -> tuple[bytes, bool]:
        out = bytearray()
        for a in acks:
            out += self._encoder.ack(*a)
        if hb is not None:
            out += self._encoder.heartbeat(hb)
        if rec is None:
            return bytes(out), False
        if stale:
            with self._cond:
                self._stats.dropped += 1
            return bytes(out), False
        data = self._encoder.pose(rec)
        if data is None:
            with self._cond:
                self._stats.skipped += 1
            return bytes(out), False
        return bytes(out + data), True

    def _write_loop(self) -> None:
        next_hb = next_pose = 0.0
        resync = True  # after a (re)connect or a failed write
        current = None
        while not self._stop.is_set():
            if not self._link.try_connect():
                self._stop.wait(min(0.05, max(self._link.seconds_until_retry(), 0.005)))
                continue
            port = self._link.port
            if port is None:  # the reader failed it just now
                continue
            if port is not current:  # a new port, whichever thread noticed the old one die
                current, resync = port, True
            if resync:
                next_hb = 0.0  # announce ourselves at once
            rec, submitted, acks, hb = self._next_batch(port, next_hb, next_pose)
            if rec is None and not acks and hb is None:
                continue
            now = time.monotonic()
            if hb is not None:  # keep the 1 Hz grid; after a stall or a reconnect restart it from now
                next_hb += self._heartbeat_period
                if next_hb <= now:
                    next_hb = now + self._heartbeat_period
            if rec is not None and self._rate_hz:
                next_pose = now + 1.0 / self._rate_hz
            # A pose that waited through an outage is stale: the robot must not act on it as if new.
            stale = resync and now - submitted > self._max_age_s
            try:
                data, has_pose = self._encode(rec, stale, acks, hb)
            except Exception:  # a bug here must not silence the link for the rest of the run
                log.exception("bridge: encoding failed")
                continue
            if resync:
                data = getattr(self._encoder, "resync", b"") + data
            if not data:
                continue
            try:
                port.write(data)
            except serial.SerialTimeoutException as e:
                self._write_failed(has_pose, timeout=True)
                self._link.last_error = str(e)
                resync = True
                continue
            except Exception as e:  # the port vanished or was closed under us
                self._write_failed(has_pose, timeout=False)
                self._link.fail(port, e)
                resync = True
                continue
            resync = False
            with self._cond:
                self._stats.bytes_out += len(data)
                self._stats.sent += has_pose
                self._stats.heartbeats += hb is not None
                self._stats.acks += len(acks)

    def _write_failed(self, had_pose: bool, timeout: bool) -> None:
        with self._cond:
            self._stats.dropped += had_pose
            self._stats.write_timeouts += timeout

    # ------------------------------------------------------------------ reader thread

    def _read_loop(self) -> None:
        while not self._stop.is_set():
            port = self._link.wait_connected(0.1)
            if port is None or self._stop.is_set():
                continue
            data = self._link.read(port)
            if data:
                for item in self._decoder.feed(data):
                    if isinstance(item, Frame) and isinstance(item.message, Command):
                        self._handle_command(item.seq, item.message)

    def _wake_writer(self) -> None:
        """The port died: a writer waiting for work on it must reconnect instead."""
        with self._cond:
            self._cond.notify_all()

    def _handle_command(self, seq: int, cmd: Command) -> None:
        result = command_result(cmd)
        event = None
        with self._cond:
            self._acks.append((seq, cmd.command, result))
            self._cond.notify()
            if self._last_command == (seq, cmd):  # a retransmission: ACK again, deliver once
                return
            self._last_command = (seq, cmd)
            if result is not AckResult.ACCEPTED:
                return
            if cmd.command == CommandCode.SET_RATE:
                self._rate_hz = cmd.value
            event = CommandEvent(CommandCode(cmd.command), cmd.value, seq, time.monotonic())
            self._stats.commands += 1
            if len(self._events) >= EVENT_QUEUE:
                self._events.popleft()
                self._stats.commands_dropped += 1
            self._events.append(event)
        if self._on_command is not None:
            try:
                self._on_command(event)
            except Exception:
                log.exception("bridge: on_command callback raised")


def open_sink(
    port: str,
    baud: int = _default("baud"),
    protocol: str = _default("protocol"),
    rate_hz: float | None = _default("rate_hz"),
    *,
    mavlink: MavlinkConfig | None = None,
    on_command: Callable[[CommandEvent], None] | None = None,
    wait_for_port: bool = _default("wait_for_port"),
) -> PoseSink:
    """Open ``port`` (device path or pyserial URL) and start sending; see PoseSink.

    A port that cannot be opened at start is an InputError (a typo should fail at once) unless
    ``wait_for_port``; a port lost later is reopened with backoff for as long as the sink runs.
    Name USB adapters by their stable path (``/dev/serial/by-id/...``): after a replug the kernel
    may give the adapter another ttyUSB number, and the sink reopens the name it was given.
    """
    return PoseSink(
        serial_opener(port, baud),
        protocol,
        rate_hz,
        mavlink=mavlink,
        on_command=on_command,
        wait_for_port=wait_for_port,
        name=port,
    )
