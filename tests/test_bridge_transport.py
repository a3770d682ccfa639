"""PoseSink over real pyserial ports: loop://, a pseudo-terminal pair, an unplugged and re-plugged port."""

from __future__ import annotations

import os
import select
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import serial

from acesplat.core.errors import InputError
from acesplat.core.geometry import look_at, pose_error
from acesplat.core.pose import PoseRecord, TrackingState
from firmware_bridge.decoder import StreamDecoder
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
from firmware_bridge.sink import PoseSink, open_sink
from firmware_bridge.testing import reference_messages
from firmware_bridge.transport import serial_opener

TIMEOUT = 10.0  # only a guard against hanging; nothing here asserts on time


def wait_for(cond: Callable[[], object], what: str, timeout: float = TIMEOUT) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.005)


def record(i: int, state: TrackingState = TrackingState.TRACKING) -> PoseRecord:
    T = look_at(np.array([np.cos(i), np.sin(i), 1.0 + 0.01 * i]), np.zeros(3))
    return PoseRecord(1_000_000 + i, T, 100 + i, state, 0.5, i)


class PtyPeer:
    """The microcontroller's end of a pseudo-terminal pair: decodes what the host writes."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        self.name = os.ttyname(self.slave)
        self.decoder = StreamDecoder()
        self.frames: list[Frame] = []

    def pump(self) -> None:
        while select.select([self.master], [], [], 0)[0]:
            try:
                data = os.read(self.master, 65536)
            except OSError:
                return
            if not data:
                return
            self.frames += self.decoder.feed(data)

    def wait(self, cond: Callable[[list[Frame]], object], what: str) -> None:
        def ready() -> object:
            self.pump()
            return cond(self.frames)

        wait_for(ready, what)

    def of(self, kind: type) -> list:
        return [f for f in self.frames if isinstance(f.message, kind)]

    def send(self, data: bytes) -> None:
        os.write(self.master, data)

    def unplug(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


@pytest.fixture
def peer():
    p = PtyPeer()
    yield p
    p.unplug()


def test_loop_url_round_trip_of_every_message() -> None:
    port = serial.serial_for_url("loop://", timeout=0.1)
    frames = [Frame(seq, msg) for seq, msg in reference_messages()]
    data = b"".join(encode_frame(f.message, f.seq) for f in frames)
    port.write(data)
    got = StreamDecoder().feed(port.read(len(data)))
    assert [encode_frame(f.message, f.seq) for f in got] == [encode_frame(f.message, f.seq) for f in frames]
    port.close()


def test_sink_over_loop_url_reads_back_what_it_sent() -> None:
    with open_sink("loop://", 115200, "frame") as sink:
        for i in range(20):
            sink.submit(record(i))
            wait_for(lambda n=i + 1: sink.stats().sent == n, "pose sent")
        wait_for(lambda: sink.stats().rx_frames_ok >= 20 + sink.stats().heartbeats, "echo decoded")
        s = sink.stats()
    assert (s.submitted, s.sent, s.dropped, s.rx_frames_rejected, s.reconnects) == (20, 20, 0, 0, 0)


def test_sink_over_pty_delivers_poses_and_status(peer: PtyPeer) -> None:
    sink = PoseSink(serial_opener(peer.name, 115200), heartbeat_hz=50.0)
    try:
        peer.wait(lambda fr: any(isinstance(f.message, Status) for f in fr), "first STATUS")
        assert peer.of(Status)[0].message.state == RuntimeState.STARTING
        recs = [record(i) for i in range(10)]
        for i, rec in enumerate(recs):
            sink.submit(rec)
            peer.wait(lambda fr, n=i + 1: len([f for f in fr if isinstance(f.message, Pose)]) == n, f"pose {i}")
        sink.update_status(state=RuntimeState.TRACKING, fps=29.5, latency_ms=33.0, frames_dropped=4)
        peer.wait(
            lambda fr: any(isinstance(f.message, Status) and f.message.state == RuntimeState.TRACKING for f in fr),
            "updated STATUS",
        )
    finally:
        sink.close()
    poses = [f.message for f in peer.of(Pose)]
    for rec, pose in zip(recs, poses):
        back = pose.to_record()
        t_err, r_err = pose_error(back.T_c2w, rec.T_c2w)
        assert t_err < 1e-6 and r_err < 1e-3
        assert (back.timestamp_us, back.frame_id, back.inliers, back.state) == (
            rec.timestamp_us,
            rec.frame_id,
            rec.inliers,
            rec.state,
        )
    status = [f.message for f in peer.of(Status) if f.message.state == RuntimeState.TRACKING][0]
    assert (status.fps, status.latency_ms, status.frames_dropped) == (29.5, 33.0, 4)
    seqs = [f.seq for f in peer.frames]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # one counter, no gaps
    assert peer.decoder.frames_rejected == 0


def test_commands_arrive_as_events_and_are_acked(peer: PtyPeer) -> None:
    seen: list = []
    sink = PoseSink(serial_opener(peer.name, 115200), on_command=seen.append)
    try:
        peer.wait(lambda fr: fr, "first frame")
        peer.send(b"\x42\x42 line noise \x00")
        for seq, cmd in [
            (10, Command(CommandCode.PAUSE)),
            (11, Command(CommandCode.SET_RATE, 12.5)),
            (11, Command(CommandCode.SET_RATE, 12.5)),  # retransmission
            (12, Command(CommandCode.SET_RATE, 0.0)),
            (13, Command(99, 1.0)),
            (14, Command(CommandCode.RESUME)),
        ]:
            peer.send(encode_frame(cmd, seq))
        peer.wait(lambda fr: len([f for f in fr if isinstance(f.message, Ack)]) == 6, "six ACKs")
        # The writer counts an ACK after its write returns, so the peer can read it first.
        wait_for(lambda: sink.stats().acks == 6, "six ACKs counted")
        events = sink.poll_commands()
        assert sink.poll_commands() == []
        assert sink.rate_hz == 12.5
        s = sink.stats()
    finally:
        sink.close()
    acks = [(f.message.acked_seq, f.message.command, f.message.result) for f in peer.of(Ack)]
    assert acks == [
        (10, CommandCode.PAUSE, AckResult.ACCEPTED),
        (11, CommandCode.SET_RATE, AckResult.ACCEPTED),
        (11, CommandCode.SET_RATE, AckResult.ACCEPTED),
        (12, CommandCode.SET_RATE, AckResult.REJECTED),
        (13, 99, AckResult.UNSUPPORTED),
        (14, CommandCode.RESUME, AckResult.ACCEPTED),
    ]
    assert [(e.command, e.value, e.seq) for e in events] == [
        (CommandCode.PAUSE, 0.0, 10),
        (CommandCode.SET_RATE, 12.5, 11),
        (CommandCode.RESUME, 0.0, 14),
    ]
    assert seen == events
    assert s.commands == 3 and s.acks == 6 and s.rx_frames_rejected == 1


class StuckPort:
    """A port whose write blocks until released: a stalled USB adapter or a full kernel buffer."""

    def __init__(self) -> None:
        self.entered = threading.Event()
        self.release = threading.Event()
        self.written = bytearray()
        self.in_waiting = 0

    def write(self, data: bytes) -> int:
        self.entered.set()
        self.release.wait()
        self.written += data
        return len(data)

    def read(self, n: int) -> bytes:
        time.sleep(0.01)
        return b""

    def close(self) -> None:
        self.release.set()


def test_submit_never_blocks_and_the_newest_pose_wins() -> None:
    port = StuckPort()
    sink = PoseSink(lambda: port)  # type: ignore[arg-type,return-value]
    try:
        assert port.entered.wait(TIMEOUT)  # the writer is stuck writing the first STATUS
        for i in range(1000):  # would hang here if submit waited for the port
            sink.submit(record(i))
        assert sink.stats().dropped == 999 and sink.stats().sent == 0
        port.release.set()
        wait_for(lambda: sink.stats().sent == 1, "the newest pose")
    finally:
        sink.close()
    poses = [f.message for f in StreamDecoder().feed(bytes(port.written)) if isinstance(f.message, Pose)]
    assert [p.frame_id for p in poses] == [999]
    assert sink.stats().submitted == 1000


def test_submit_checks_its_argument() -> None:
    with open_sink("loop://") as sink:
        with pytest.raises(TypeError):
            sink.submit(np.eye(4))  # type: ignore[arg-type]
        with pytest.raises(ValueError):
            sink.submit(PoseRecord(0, np.eye(3)))
    with pytest.raises(RuntimeError):
        sink.submit(record(0))


def test_port_closed_under_the_writer_is_reopened() -> None:
    ports: list[serial.SerialBase] = []

    def opener() -> serial.SerialBase:
        ports.append(serial.serial_for_url("loop://", timeout=0.05, write_timeout=0.5))
        return ports[-1]

    sink = PoseSink(opener)
    try:
        sink.submit(record(0))
        wait_for(lambda: sink.stats().sent == 1, "first pose")
        ports[0].close()  # the adapter is gone
        i = 1
        while sink.stats().reconnects == 0:
            sink.submit(record(i))
            i += 1
            time.sleep(0.005)
            assert i < 2000, "no reconnect"
        wait_for(lambda: (lambda s: s.sent + s.dropped == s.submitted)(sink.stats()), "every pose sent or dropped")
        sent = sink.stats().sent
        sink.submit(record(5000))
        wait_for(lambda: sink.stats().sent == sent + 1, "pose after reconnect")
        wait_for(lambda: sink.stats().rx_frames_ok > 0, "echo on the new port")
        s = sink.stats()
    finally:
        sink.close()
    assert len(ports) == 2 and s.reconnects == 1 and s.connected
    assert "not open" in s.last_error


def test_unplugged_pty_is_reopened_when_the_device_returns(tmp_path: Path) -> None:
    """A udev-style symlink names the port; unplug = the pty vanishes, replug = a new pty under the same name."""
    link = tmp_path / "ttyACM-robot"
    first = PtyPeer()
    os.symlink(first.name, link)
    sink = PoseSink(serial_opener(str(link), 115200), max_age_s=0.05)
    second = None
    try:
        sink.submit(record(0))
        first.wait(lambda fr: any(isinstance(f.message, Pose) for f in fr), "pose before unplug")
        first.unplug()
        i = 1
        while sink.stats().connected:  # keep the localization loop running through the outage
            sink.submit(record(i))
            i += 1
            time.sleep(0.005)
            assert i < 2000, "the unplug was never noticed"
        sink.submit(record(777))  # waits through the outage: stale when the port returns
        time.sleep(0.2)
        second = PtyPeer()
        tmp = tmp_path / "new-link"
        os.symlink(second.name, tmp)
        os.replace(tmp, link)
        wait_for(lambda: sink.stats().connected, "reconnect")
        second.wait(lambda fr: any(isinstance(f.message, Status) for f in fr), "STATUS after replug")
        sink.submit(record(778))
        second.wait(lambda fr: any(isinstance(f.message, Pose) for f in fr), "pose after replug")
        s = sink.stats()
    finally:
        sink.close()
        if second is not None:
            second.unplug()
    assert s.reconnects == 1 and s.outage_s > 0.0
    assert [f.message.frame_id for f in second.of(Pose)] == [778]  # 777 was dropped as stale
    assert s.dropped >= 1 and second.decoder.frames_rejected == 0


def test_wait_for_port_starts_without_the_device(tmp_path: Path) -> None:
    link = tmp_path / "ttyUSB-later"
    sink = open_sink(str(link), 115200, wait_for_port=True)
    peer = PtyPeer()
    try:
        assert not sink.stats().connected
        os.symlink(peer.name, link)
        peer.wait(lambda fr: fr, "frames once the device appears")
        assert sink.stats().reconnects == 0  # a late first connection is not an outage
    finally:
        sink.close()
        peer.unplug()


def test_bad_arguments_are_one_line_input_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="ttyNOPE"):
        open_sink(str(tmp_path / "ttyNOPE"))
    with pytest.raises(InputError, match="protocol"):
        open_sink("loop://", protocol="can")
    with pytest.raises(InputError, match="rate"):
        open_sink("loop://", rate_hz=0)
    with pytest.raises(InputError, match="baud"):
        open_sink("loop://", baud=0)


def test_rate_cap_spaces_poses_by_replacement() -> None:
    """With a cap of 0.2 Hz, poses submitted in a burst are not all sent: the newest replaces the rest."""
    with open_sink("loop://", rate_hz=0.2) as sink:
        sink.submit(record(0))
        wait_for(lambda: sink.stats().sent == 1, "first pose")
        for i in range(1, 50):
            sink.submit(record(i))
        s = sink.stats()
    assert s.sent == 1 and s.dropped == 48  # 49 submitted inside the 5 s gap, one still waiting
