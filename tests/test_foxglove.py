"""Foxglove outputs: MCAP logs of a replay, the live WebSocket server, MCAP record -> replay, one-line refusals."""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

pytest.importorskip("foxglove")
pytest.importorskip("mcap")

from acesplat.apps.edge_cli import app  # noqa: E402
from acesplat.core.bundle import load_bundle  # noqa: E402
from acesplat.core.geometry import pose_error  # noqa: E402
from edge.foxglove_tap import (  # noqa: E402
    TOPIC_IMAGE,
    TOPIC_POSE,
    TOPIC_STATUS,
    FoxgloveTap,
    McapReplaySource,
    iter_mcap,
    pose_matrix,
)
from edge.runtime import EdgeLocalizer  # noqa: E402
from edge.sources import ReplaySource, SourceOptions, open_source  # noqa: E402


def test_replay_with_mcap_logs_one_pose_per_localized_frame_and_one_image_per_frame(tiny, tmp_path: Path) -> None:
    from mcap.reader import make_reader

    path = tmp_path / "logs" / "run.mcap"
    summary = tmp_path / "s.json"
    r = CliRunner().invoke(
        app,
        [
            "replay",
            str(tiny["bundle"]),
            str(tiny["scene"]),
            "--threads",
            "1",
            "--mcap",
            str(path),
            "--json",
            str(summary),
        ],
    )
    assert r.exit_code == 0, r.output
    s = json.loads(summary.read_text())
    assert s["foxglove"]["frames"] == s["frames"] == 4 and s["foxglove"]["dropped"] == 0
    assert not path.with_name(path.name + ".partial").exists()
    with open(path, "rb") as f:  # the mcap library's own reader: a finalized file with a summary
        stats = make_reader(f).get_summary().statistics
    assert stats.message_count > 0
    msgs = list(iter_mcap(path))
    counts = Counter(t for t, _ in msgs)
    states = [m["state"] for t, m in msgs if t == TOPIC_STATUS]
    assert counts[TOPIC_IMAGE] == 4 and len(states) == 4
    assert counts[TOPIC_POSE] == states.count("TRACKING") == s["localized"]
    # the pose on the wire is T_c2w itself (optical frame), close to the truth
    truths = [m for t, m in msgs if t == "/camera/true_pose"]
    poses = [m for t, m in msgs if t == TOPIC_POSE]
    assert len(truths) == 4
    for p, g in zip(poses, truths):
        assert p.frame_id == "world"
        t_err, r_err = pose_error(pose_matrix(p.pose), pose_matrix(g.pose))
        # the tiny scene's test views: 19 cm / 4.4 deg median, worst measured 23 cm / 7.5 deg; a wrong axis
        # convention on the wire would be off by tens of degrees
        assert t_err < 0.35 and r_err < 10.0
    calib = next(m for t, m in msgs if t == "/camera/calibration")
    h, w = load_bundle(tiny["bundle"]).input_size
    assert (calib.width, calib.height) == (w, h) and calib.frame_id == "camera_optical"


# ----------------------------------------------------------------------------- a minimal WebSocket client
SUBPROTOCOL = "foxglove.sdk.v1"
"""What foxglove-sdk 0.30's server speaks (the successor of foxglove.websocket.v1: same advertise, subscribe and
binary MessageData messages)."""


class WsClient:
    """RFC 6455 client, just enough for the Foxglove WebSocket protocol (masked text out, text/binary in)."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=5)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            (
                "GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                f"Sec-WebSocket-Protocol: {SUBPROTOCOL}\r\n\r\n"
            ).encode()
        )
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.sock.recv(1)
        assert b" 101 " in head.split(b"\r\n")[0] and SUBPROTOCOL.encode() in head

    def _exact(self, n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = self.sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionError("closed")
            buf += chunk
        return buf

    def recv(self) -> tuple[int, bytes]:
        b0, b1 = self._exact(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", self._exact(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", self._exact(8))[0]
        return b0 & 0x0F, self._exact(n)

    def send_json(self, obj: dict) -> None:
        data = json.dumps(obj).encode()
        mask = os.urandom(4)
        head = bytes([0x81]) + (bytes([0x80 | len(data)]) if len(data) < 126 else struct.pack(">BH", 0xFE, len(data)))
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def close(self) -> None:
        self.sock.close()


def test_live_server_streams_the_pose_at_the_localization_rate(tiny) -> None:
    loc = EdgeLocalizer(load_bundle(tiny["bundle"]), "fp32", threads=1)
    tap = FoxgloveTap(port=0)
    loc.add_tap(tap)
    client = WsClient(tap.port)
    try:
        channels: dict[str, dict] = {}
        deadline = time.monotonic() + 5
        while TOPIC_POSE not in channels and time.monotonic() < deadline:
            op, data = client.recv()
            if op == 1:
                msg = json.loads(data)
                if msg.get("op") == "advertise":
                    channels.update({c["topic"]: c for c in msg["channels"]})
        pose = channels[TOPIC_POSE]
        assert pose["schemaName"] == "foxglove.PoseInFrame" and pose["encoding"] == "protobuf"
        assert channels[TOPIC_IMAGE]["schemaName"] == "foxglove.CompressedImage"
        assert channels["/tf"]["schemaName"] == "foxglove.FrameTransform"
        client.send_json({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": pose["id"]}]})
        time.sleep(0.5)  # the server registers the subscription
        src = ReplaySource(Path(tiny["scene"]) / "test")
        frames = [src.read() for _ in range(len(src))] * 2
        outs = [loc.localize(f) for f in frames]
        tracking = sum(o.record.state == 1 for o in outs)
        assert tracking == len(frames)
        got = 0
        while got < tracking:
            op, data = client.recv()
            if op == 2:
                assert data[0] == 1 and struct.unpack("<I", data[1:5])[0] == 7  # MessageData on our subscription
                got += 1
        assert got == len(frames)
    finally:
        client.close()
        report = tap.close()
    assert report["frames"] == len(frames) and report["dropped"] == 0 and report["errors"] == 0


def test_mcap_record_then_replay_gives_the_same_frames_and_intrinsics(tiny, tmp_path: Path) -> None:
    folder, path = tmp_path / "rec", tmp_path / "rec.mcap"  # a folder recording first: it has timestamps
    r = CliRunner().invoke(app, ["record", str(folder), "--source", f"replay:{tiny['scene']}/test"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(app, ["record", "--mcap", str(path), "--source", f"replay:{folder}"])
    assert r.exit_code == 0, r.output
    src = open_source(f"replay:{path}", SourceOptions())
    assert isinstance(src, McapReplaySource) and len(src) == 4
    orig = ReplaySource(folder)
    for _ in range(4):
        g, o = src.read(), orig.read()
        np.testing.assert_array_equal(g.image, o.image)
        np.testing.assert_allclose(g.intrinsics.K, o.intrinsics.K)
        assert (g.intrinsics.width, g.intrinsics.height) == (o.intrinsics.width, o.intrinsics.height)
        np.testing.assert_allclose(g.gt_pose, o.gt_pose, atol=1e-9)
        assert g.timestamp == pytest.approx(o.timestamp, abs=1e-6)
    assert src.read() is None
    src.close()
    # and the localizer runs on it
    r = CliRunner().invoke(
        app, ["localize", str(tiny["bundle"]), "--source", f"replay:{path}", "--threads", "1", "--quiet"]
    )
    assert r.exit_code == 0, r.output
    assert "4 frames" in r.output and "4 tracking" in r.output


def test_ctrl_c_leaves_a_finalized_mcap(tiny, tmp_path: Path, monkeypatch) -> None:
    import edge.runtime as rt

    calls = {"n": 0}
    real = rt.EdgeLocalizer.localize

    def interrupting(self, frame, *a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(self, frame, *a, **k)

    monkeypatch.setattr(rt.EdgeLocalizer, "localize", interrupting)
    path = tmp_path / "run.mcap"
    r = CliRunner().invoke(
        app,
        ["localize", str(tiny["bundle"]), "--source", f"replay:{tiny['scene']}/test", "--threads", "1"]
        + ["--mcap", str(path), "--quiet"],
    )
    assert r.exit_code == 0 and "interrupted" in r.output, r.output
    assert Counter(t for t, _ in iter_mcap(path))[TOPIC_IMAGE] == 2
    assert not path.with_name("run.mcap.partial").exists()


CRASH = """
import os, sys, time
import numpy as np
from acesplat.core.camera import Intrinsics
from acesplat.core.pose import PoseRecord, TrackingState
from edge.foxglove_tap import FoxgloveSettings, FoxgloveTap
from edge.runtime import FrameOutcome
tap = FoxgloveTap(mcap=sys.argv[1], settings=FoxgloveSettings(flush_s=0.05))
gray = np.random.default_rng(0).integers(0, 255, (48, 64), dtype=np.uint8)
for i in range(3):
    rec = PoseRecord(i * 100000, np.eye(4), 50, TrackingState.TRACKING, 0.5, i)
    tap.on_frame(FrameOutcome(rec, None, {"total": 1.0}, str(i), None, Intrinsics.from_focal(50, 64, 48), gray=gray))
    time.sleep(0.2)
os._exit(1)
"""


def test_a_hard_crash_leaves_a_readable_partial_mcap(tmp_path: Path) -> None:
    path = tmp_path / "crash.mcap"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    subprocess.run([sys.executable, "-c", CRASH, str(path)], env=env, timeout=60, check=False)
    partial = tmp_path / "crash.mcap.partial"
    assert not path.exists() and partial.is_file()
    got = Counter(topic for topic, _ in iter_mcap(partial, stream=True))  # no summary: read up to the cut
    assert got[TOPIC_IMAGE] == 3 and got[TOPIC_POSE] == 3


def test_port_in_use_and_unwritable_mcap_are_one_line_errors(tiny, tmp_path: Path) -> None:
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    port = busy.getsockname()[1]
    base = ["localize", str(tiny["bundle"]), "--source", f"replay:{tiny['scene']}/test", "--threads", "1"]
    try:
        log = tmp_path / "never.mcap"
        r = CliRunner().invoke(app, base + ["--foxglove", str(port), "--mcap", str(log)])
        assert r.exit_code == 2 and f":{port}" in r.output and len(r.output.strip().splitlines()) == 1, r.output
        assert not log.exists() and not (tmp_path / "never.mcap.partial").exists()
    finally:
        busy.close()
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    r = CliRunner().invoke(app, base + ["--mcap", str(blocker / "run.mcap")])
    assert r.exit_code == 2 and "cannot write the MCAP file" in r.output and "\n" not in r.output.strip(), r.output
    r = CliRunner().invoke(app, ["replay", str(tiny["bundle"]), str(tiny["scene"]), "--mcap", str(tmp_path)])
    assert r.exit_code == 2 and "folder" in r.output, r.output
