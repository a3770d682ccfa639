"""`acesplat-edge bridge monitor|send-test` over a pseudo-terminal, and their one-line errors."""

from __future__ import annotations

import json
import os
import select
import threading
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from acesplat.apps.edge_cli import app
from firmware_bridge.decoder import StreamDecoder
from firmware_bridge.protocol import Ack, Command, CommandCode, Pose, Status, encode_frame
from firmware_bridge.testing import reference_messages
from tests.test_bridge_transport import PtyPeer

runner = CliRunner()


def test_monitor_counts_frames_and_rejects(tmp_path: Path) -> None:
    peer = PtyPeer()
    burst = b"".join(encode_frame(m, s) for s, m in reference_messages()) + b"\x99 noise \x00"
    n_pose = sum(isinstance(m, Pose) for _, m in reference_messages())
    stop = threading.Event()

    def mcu_side() -> None:  # keep sending until the monitor is done: it may open the port after our first burst
        while not stop.is_set():
            os.write(peer.master, burst)
            time.sleep(0.05)

    out = tmp_path / "monitor.json"
    t = threading.Thread(target=mcu_side, daemon=True)
    t.start()
    try:
        result = runner.invoke(app, ["bridge", "monitor", peer.name, "--seconds", "0.6", "--json", str(out)])
    finally:
        stop.set()
        t.join()
        peer.unplug()
    assert result.exit_code == 0, result.output
    assert "POSE" in result.output and "TRACKING" in result.output
    report = json.loads(out.read_text())
    assert {"frames_ok", "frames_rejected", "bytes", "messages"} <= set(report)
    assert report["messages"]["POSE"] >= n_pose and report["frames_rejected"] >= 1
    assert report["frames_ok"] == sum(report["messages"].values())
    assert report["bytes"] >= len(burst)


def test_send_test_drives_the_link_and_honours_commands(tmp_path: Path) -> None:
    peer = PtyPeer()
    frames = []
    stop = threading.Event()

    def mcu_side() -> None:
        dec = StreamDecoder()
        asked = False
        while not stop.is_set():
            if select.select([peer.master], [], [], 0.01)[0]:
                frames.extend(dec.feed(os.read(peer.master, 65536)))
            if not asked and any(isinstance(f.message, Pose) for f in frames):
                os.write(peer.master, encode_frame(Command(CommandCode.SET_RATE, 25.0), 42))
                asked = True
        while select.select([peer.master], [], [], 0)[0]:
            frames.extend(dec.feed(os.read(peer.master, 65536)))

    out = tmp_path / "send.json"
    t = threading.Thread(target=mcu_side, daemon=True)
    t.start()
    try:
        result = runner.invoke(
            app, ["bridge", "send-test", peer.name, "--rate", "40", "--seconds", "0.8", "--json", str(out)]
        )
    finally:
        stop.set()
        t.join()
        peer.unplug()
    assert result.exit_code == 0, result.output
    report = json.loads(out.read_text())
    poses = [f.message for f in frames if isinstance(f.message, Pose)]
    assert report["sent"] == len(poses) > 0 and report["write_timeouts"] == 0
    assert [p.frame_id for p in poses] == sorted(p.frame_id for p in poses)
    assert isinstance(frames[0].message, Status)  # the heartbeat announces the host at once
    assert [a.message.acked_seq for a in frames if isinstance(a.message, Ack)] == [42]
    assert report["commands_received"][0]["command"] == "SET_RATE" and report["commands_received"][0]["value"] == 25.0
    assert "command SET_RATE value=25" in result.output


@pytest.mark.parametrize(
    "args, needle",
    [
        (["bridge", "monitor", "/dev/does-not-exist"], "/dev/does-not-exist: cannot open serial port"),
        (["bridge", "monitor", "loop://", "--protocol", "can"], "--protocol"),
        (["bridge", "monitor", "loop://", "--seconds", "-1"], "--seconds"),
        (["bridge", "monitor", "loop://", "--baud", "0"], "baud"),
        (["bridge", "send-test", "loop://", "--rate", "0"], "--rate"),
        (["bridge", "send-test", "loop://", "--seconds", "0"], "--seconds"),
        (["bridge", "send-test", "/dev/does-not-exist"], "cannot open serial port"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args: list[str], needle: str) -> None:
    result = runner.invoke(app, args)
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], result.output
