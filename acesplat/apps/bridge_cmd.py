"""`acesplat-edge bridge monitor|send-test`: field tools for the serial link to the robot."""

from __future__ import annotations

import math
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import typer

from acesplat.apps.support import PhaseProgress, one_line_errors, option, report_json, stop_on_signals
from acesplat.core.errors import InputError
from acesplat.core.geometry import look_at
from acesplat.core.pose import PoseRecord, TrackingState
from firmware_bridge.decoder import StreamDecoder
from firmware_bridge.protocol import Frame, Pose, RuntimeState
from firmware_bridge.sink import MAX_RATE_HZ, PROTOCOLS, PoseSink, SinkConfig, open_sink
from firmware_bridge.transport import SerialLink, serial_opener

app = typer.Typer(
    no_args_is_help=True, add_completion=False, help="Firmware bridge: watch and exercise the serial link to the robot."
)


def _check_protocol(protocol: str) -> None:
    if protocol not in PROTOCOLS:
        raise InputError(None, f"--protocol must be one of {', '.join(PROTOCOLS)}, got {protocol!r}")


def _check_seconds(seconds: float | None) -> None:
    if seconds is not None and not (math.isfinite(seconds) and seconds > 0):
        raise InputError(None, f"--seconds must be positive, got {seconds}")


def describe(frame: Frame) -> str:
    """One readable line per protocol frame, for people watching a link."""
    m = frame.message
    if isinstance(m, Pose):
        p = ", ".join(f"{v:.3f}" for v in m.position)
        q = ", ".join(f"{v:.4f}" for v in m.quat_wxyz)
        return (
            f"POSE    #{frame.seq:<5} t={m.timestamp_us / 1e6:.6f}s frame={m.frame_id} pos=({p}) q=({q}) "
            f"inliers={m.inliers} {m.state.name} quality={m.quality:.2f}"
        )
    fields = ", ".join(f"{k}={v.name if hasattr(v, 'name') else v}" for k, v in vars(m).items())
    return f"{type(m).__name__.upper():<7} #{frame.seq:<5} {fields}"


@app.command()
@one_line_errors
def monitor(
    port: str = typer.Argument(..., help="Serial device or pyserial URL (e.g. /dev/ttyUSB0, loop://)."),
    protocol: str = option(SinkConfig, "protocol"),
    seconds: float | None = typer.Option(None, help="Stop after this long (default: until Ctrl-C)."),
    baud: int = option(SinkConfig, "baud"),
    quiet: bool = typer.Option(False, "--quiet", help="Only counts, no line per message."),
    json_out: Path | None = typer.Option(None, "--json", help="Write the counts here."),
) -> None:
    """Decode and print what arrives on PORT, with counts of good and rejected frames."""
    stop_on_signals()
    _check_protocol(protocol)
    _check_seconds(seconds)
    if protocol == "frame":
        decoder: Any = StreamDecoder()
    else:
        from firmware_bridge.mavlink import MavlinkDecoder

        decoder = MavlinkDecoder()
    counts: Counter[str] = Counter()
    link = SerialLink(serial_opener(port, baud), port)
    link.open_first()
    start = time.monotonic()
    try:
        with PhaseProgress() as progress:
            while seconds is None or time.monotonic() - start < seconds:
                elapsed = time.monotonic() - start
                progress(
                    "monitor",
                    elapsed / seconds if seconds else 0.0,
                    {"ok": decoder.frames_ok, "rejected": decoder.frames_rejected, "reconnects": link.reconnects},
                )
                if not link.try_connect():
                    time.sleep(min(0.05, max(link.seconds_until_retry(), 0.005)))
                    continue
                data = link.read(link.port)  # an unplugged port comes back through try_connect()
                for item in decoder.feed(data) if data else []:
                    name = type(item.message).__name__.upper() if isinstance(item, Frame) else item.get_type()
                    counts[name] += 1
                    if not quiet:
                        print(describe(item) if isinstance(item, Frame) else str(item))
    except KeyboardInterrupt:
        pass
    finally:
        link.close()
    report = {
        "port": port,
        "protocol": protocol,
        "seconds": round(time.monotonic() - start, 3),
        "frames_ok": decoder.frames_ok,
        "frames_rejected": decoder.frames_rejected,
        "bytes": decoder.bytes,
        "messages": dict(counts),
        "reconnects": link.reconnects,
        "outage_s": round(link.outage_s(), 3),
    }
    if isinstance(decoder, StreamDecoder):
        report["rejected_by_reason"] = dict(decoder.rejects)
    print(
        f"frames ok {decoder.frames_ok}, rejected {decoder.frames_rejected}, bytes {decoder.bytes}, "
        f"messages {dict(counts)}"
    )
    report_json(json_out, report)


def synthetic_pose(t: float, frame_id: int) -> PoseRecord:
    """A camera circling 2 m around the map origin at 1.5 m height (z up), looking at the centre;
    LOST for the last half second of every 5 s, so both states reach the robot."""
    a = 2.0 * math.pi * t / 20.0
    T = look_at(np.array([2.0 * math.cos(a), 2.0 * math.sin(a), 1.5]), np.array([0.0, 0.0, 1.0]))
    lost = (t % 5.0) >= 4.5
    return PoseRecord(
        timestamp_us=time.monotonic_ns() // 1000,
        T_c2w=T,
        inliers=0 if lost else 300 + frame_id % 100,
        state=TrackingState.LOST if lost else TrackingState.TRACKING,
        quality=0.0 if lost else 0.8,
        frame_id=frame_id,
    )


@app.command("send-test")
@one_line_errors
def send_test(
    port: str = typer.Argument(..., help="Serial device or pyserial URL."),
    rate: float = typer.Option(30.0, help="Poses per second."),
    seconds: float = typer.Option(10.0, help="How long to send."),
    protocol: str = option(SinkConfig, "protocol"),
    baud: int = option(SinkConfig, "baud"),
    json_out: Path | None = typer.Option(None, "--json", help="Write the link statistics here."),
) -> None:
    """Send synthetic poses so the microcontroller side can be brought up without a camera.

    Commands from the microcontroller are printed and honoured: PAUSE stops the poses until RESUME,
    SET_RATE changes the send rate.
    """
    stop_on_signals()
    _check_protocol(protocol)
    _check_seconds(seconds)
    if not (math.isfinite(rate) and 0 < rate <= MAX_RATE_HZ):
        raise InputError(None, f"--rate must be in (0, {MAX_RATE_HZ:g}], got {rate}")
    commands: list[dict[str, Any]] = []
    paused = False
    sink: PoseSink = open_sink(port, baud, protocol)
    start = next_tick = time.monotonic()
    frame_id = 0
    try:
        with PhaseProgress() as progress:
            while (elapsed := time.monotonic() - start) < seconds:
                for ev in sink.poll_commands():
                    print(f"command {ev.command.name} value={ev.value:g} (seq {ev.seq})")
                    commands.append(
                        {
                            "command": ev.command.name,
                            "value": ev.value,
                            "seq": ev.seq,
                            "t": round(ev.received_s - start, 3),
                        }
                    )
                    paused = {"PAUSE": True, "RESUME": False}.get(ev.command.name, paused)
                    if ev.command.name == "SET_RATE":
                        rate = ev.value
                if not paused:
                    rec = synthetic_pose(elapsed, frame_id)
                    sink.submit(rec)
                    sink.update_status(
                        state=RuntimeState.TRACKING if rec.state == TrackingState.TRACKING else RuntimeState.LOST,
                        fps=rate,
                        latency_ms=5.0,
                    )
                    frame_id += 1
                else:
                    sink.update_status(state=RuntimeState.PAUSED)
                s = sink.stats()
                progress(
                    "send-test", elapsed / seconds, {"sent": s.sent, "dropped": s.dropped, "reconnects": s.reconnects}
                )
                next_tick = max(next_tick + 1.0 / rate, time.monotonic() - 1.0 / rate)  # no burst after a stall
                time.sleep(max(0.0, next_tick - time.monotonic()))
    except KeyboardInterrupt:
        pass
    finally:
        sink.close()
    stats = sink.stats()
    print(
        f"sent {stats.sent} poses ({stats.bytes_out} bytes), dropped {stats.dropped}, reconnects {stats.reconnects}, "
        f"outage {stats.outage_s:.2f}s, commands {stats.commands}"
    )
    report_json(json_out, {"port": port, "protocol": protocol, **stats.as_dict(), "commands_received": commands})
