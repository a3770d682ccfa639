"""Test tooling shared by tests/ and bench/: canonical text, test vectors, fuzz streams, the C harness.

The canonical text of a frame is what the C harness (firmware/host_harness.c) prints and parses,
with floats as their binary32 bit patterns, so the two implementations are compared exactly.
"""

from __future__ import annotations

import math
import os
import shutil
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np

from acesplat.core.pose import TrackingState
from firmware_bridge.cobs import cobs_encode
from firmware_bridge.decoder import StreamDecoder
from firmware_bridge.protocol import (
    CRC,
    HEADER,
    PAYLOAD_SIZES,
    Ack,
    AckResult,
    Command,
    CommandCode,
    Frame,
    Message,
    MsgType,
    Pose,
    RuntimeState,
    Status,
    encode_frame,
)

FIRMWARE_DIR = Path(__file__).resolve().parent / "firmware"
VECTORS_PATH = FIRMWARE_DIR / "test_vectors.txt"


def f32_bits(x: float) -> int:
    return struct.unpack("<I", struct.pack("<f", x))[0]


def canonical(frame: Frame) -> str:
    """One line (no newline) naming every field; identical to the C harness output for the same frame."""
    m, s = frame.message, frame.seq
    if isinstance(m, Pose):
        pos = ",".join(f"{f32_bits(v):08x}" for v in m.position)
        quat = ",".join(f"{f32_bits(v):08x}" for v in m.quat_wxyz)
        return (
            f"POSE seq={s} ts={m.timestamp_us} frame={m.frame_id} pos={pos} quat={quat} "
            f"inliers={m.inliers} state={int(m.state)} quality={f32_bits(m.quality):08x}"
        )
    if isinstance(m, Status):
        return (
            f"STATUS seq={s} ts={m.timestamp_us} fps={f32_bits(m.fps):08x} latency={f32_bits(m.latency_ms):08x} "
            f"frames_dropped={m.frames_dropped} poses_dropped={m.poses_dropped} state={int(m.state)}"
        )
    if isinstance(m, Command):
        return f"COMMAND seq={s} command={m.command} value={f32_bits(m.value):08x}"
    assert isinstance(m, Ack)
    return f"ACK seq={s} acked={m.acked_seq} command={m.command} result={int(m.result)}"


# ---------------------------------------------------------------- reference vectors


def reference_messages() -> list[tuple[int, Message]]:
    """(seq, message) pairs covering every type, every enum value and the field extremes."""
    s = math.sqrt(0.5)
    out: list[tuple[int, Message]] = [
        (1, Pose(1_700_000_123_456, 1234, (1.5, -2.0, 0.8), (s, 0.0, 0.0, s), 412, TrackingState.TRACKING, 0.8125)),
        (2, Pose(0, 0, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), 0, TrackingState.LOST, 0.0)),
        (
            65535,
            Pose(2**64 - 1, 2**32 - 1, (-1e6, 1e-6, 3.25), (0.5, -0.5, 0.5, -0.5), 65535, TrackingState.TRACKING, 1.0),
        ),
        (7, Pose(5, 6, (math.nan,) * 3, (math.nan,) * 4, 0, TrackingState.LOST, 0.0)),
    ]
    for i, state in enumerate(RuntimeState):
        out.append((100 + i, Status(1_000_000 * (i + 1), 29.97 - i, 12.5 + i, 3 * i, 70000 * i, state)))
    for i, code in enumerate(CommandCode):
        out.append((200 + i, Command(int(code), 30.0 if code is CommandCode.SET_RATE else 0.0)))
    out.append((250, Command(200, -1.0)))
    for i, result in enumerate(AckResult):
        out.append((300 + i, Ack(203, int(CommandCode.SET_RATE), result)))
    return out


def _frame_from_body(body: bytes) -> bytes:
    """A frame around ``body`` with a correct CRC: for vectors that must fail a later check."""
    body = bytes(body)
    return cobs_encode(body + CRC.pack(zlib.crc32(body))) + b"\x00"


def reference_rejects() -> list[tuple[str, bytes]]:
    """(reason, wire bytes) of frames both decoders must reject, one or more per reason."""
    pose_payload = bytes(PAYLOAD_SIZES[MsgType.POSE])
    good = bytearray(encode_frame(Ack(1, 4, AckResult.ACCEPTED), 9))
    flipped = bytearray(good)
    flipped[3] ^= 0x10
    return [
        ("overflow", b"\x01" * 300 + b"\x00"),
        ("overflow", b"\x37" * 400 + b"\x00"),
        ("cobs", bytes([0x05, 0x11, 0x22, 0x00])),
        ("short", bytes([0x03, 0x01, 0x10, 0x00])),
        ("crc", bytes(flipped)),
        ("version", _frame_from_body(HEADER.pack(2, MsgType.ACK, 9, 4) + bytes(4))),
        ("type", _frame_from_body(HEADER.pack(1, 0x7F, 9, 4) + bytes(4))),
        ("length", _frame_from_body(HEADER.pack(1, MsgType.POSE, 9, 4) + bytes(4))),
        ("length", _frame_from_body(HEADER.pack(1, MsgType.ACK, 9, 5) + bytes(4))),
        (
            "value",
            _frame_from_body(HEADER.pack(1, MsgType.POSE, 9, 48) + pose_payload[:42] + b"\x02" + pose_payload[43:]),
        ),
        ("value", _frame_from_body(HEADER.pack(1, MsgType.STATUS, 9, 28) + bytes(24) + b"\x09" + bytes(3))),
        ("value", _frame_from_body(HEADER.pack(1, MsgType.ACK, 9, 4) + b"\x01\x00\x04\x05")),
    ]


def vector_lines() -> list[str]:
    """The content of firmware/test_vectors.txt: ``<canonical text or REJECT reason> | <wire hex>``."""
    lines = [
        "# acesplat firmware bridge protocol v1 test vectors, one frame per line:",
        "# <canonical text of the decoded frame, or REJECT <reason>> | <wire bytes in hex, including the 00 delimiter>",
        "# Floats appear as binary32 bit patterns. Generated by firmware_bridge.testing.write_vectors();",
        "# tests/test_bridge_c.py checks the Python and the C implementation against every line.",
    ]
    for seq, msg in reference_messages():
        lines.append(f"{canonical(Frame(seq, msg))} | {encode_frame(msg, seq).hex()}")
    for reason, wire in reference_rejects():
        lines.append(f"REJECT {reason} | {wire.hex()}")
    return lines


def write_vectors(path: Path = VECTORS_PATH) -> None:
    from acesplat.core.atomic import write_text

    write_text(path, "\n".join(vector_lines()) + "\n")


def read_vectors(path: Path = VECTORS_PATH) -> list[tuple[str, bytes]]:
    out = []
    for line in path.read_text().splitlines():
        if line and not line.startswith("#"):
            text, wire = line.rsplit(" | ", 1)
            out.append((text, bytes.fromhex(wire)))
    return out


def decode_lines(data: bytes) -> list[str]:
    """What the C harness prints in ``decode`` mode for ``data``, computed with the Python decoder."""
    dec = StreamDecoder()
    lines = []
    start = 0
    # Feed frame by frame so rejects interleave with messages in stream order, as the C harness prints them.
    while start < len(data):
        end = data.find(0, start)
        end = len(data) if end < 0 else end + 1
        before = dict(dec.rejects)
        frames = dec.feed(data[start:end])
        lines += [canonical(f) for f in frames]
        lines += [f"REJECT {r}" for r in dec.rejects if dec.rejects[r] > before[r]]
        start = end
    lines.append(stats_line(dec))
    return lines


def stats_line(dec: StreamDecoder) -> str:
    return f"STATS ok={dec.frames_ok} " + " ".join(f"{k}={v}" for k, v in dec.rejects.items())


# ---------------------------------------------------------------- fuzzing


def random_message(rng: np.random.Generator) -> Message:
    kind = int(rng.integers(4))
    f = lambda lo=-100.0, hi=100.0: float(rng.uniform(lo, hi))  # noqa: E731
    if kind == 0:
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        return Pose(
            int(rng.integers(0, 2**63)),
            int(rng.integers(0, 2**32)),
            (f(), f(), f()),
            tuple(q.tolist()),  # type: ignore[arg-type]
            int(rng.integers(0, 65536)),
            TrackingState(int(rng.integers(2))),
            f(0.0, 1.0),
        )
    if kind == 1:
        return Status(
            int(rng.integers(0, 2**63)),
            f(0, 120),
            f(0, 500),
            int(rng.integers(0, 2**32)),
            int(rng.integers(0, 2**32)),
            RuntimeState(int(rng.integers(5))),
        )
    if kind == 2:
        return Command(int(rng.integers(256)), f(0, 200))
    return Ack(int(rng.integers(65536)), int(rng.integers(256)), AckResult(int(rng.integers(3))))


def _mutate(frame: bytes, rng: np.random.Generator, other: bytes) -> bytes:
    """One corruption a serial link produces: flips, cuts, noise, lost or repeated bytes, splices."""
    b = bytearray(frame)
    kind = int(rng.integers(8))
    if kind == 0:  # bit flips anywhere, the delimiter included
        for _ in range(int(rng.integers(1, 9))):
            i = int(rng.integers(len(b)))
            b[i] ^= 1 << int(rng.integers(8))
    elif kind == 1:  # cut: the rest of the frame and its delimiter are lost
        b = b[: int(rng.integers(1, len(b)))]
    elif kind == 2:  # cut, but the delimiter arrives
        b = b[: int(rng.integers(1, len(b) - 1))] + b"\x00"
    elif kind == 3:  # noise burst before the frame (may contain delimiters)
        b = bytearray(rng.integers(0, 256, size=int(rng.integers(1, 80)), dtype=np.uint8).tobytes()) + b
    elif kind == 4:  # run of random bytes overwritten
        i = int(rng.integers(len(b)))
        n = min(int(rng.integers(1, 12)), len(b) - i)
        b[i : i + n] = rng.integers(0, 256, size=n, dtype=np.uint8).tobytes()
    elif kind == 5:  # bytes lost
        for _ in range(int(rng.integers(1, 4))):
            if len(b) > 1:
                del b[int(rng.integers(len(b)))]
    elif kind == 6:  # splice with another frame
        cut = int(rng.integers(1, len(b)))
        b = b[:cut] + other[int(rng.integers(len(other))) :]
    else:  # long non-zero noise: exercises the overflow bound
        b = bytearray(rng.integers(1, 256, size=int(rng.integers(200, 700)), dtype=np.uint8).tobytes()) + b
    return bytes(b)


def fuzz_stream(n_frames: int, seed: int, corrupt_fraction: float = 0.5) -> tuple[bytes, set[bytes]]:
    """A seeded byte stream of ``n_frames`` frames, about ``corrupt_fraction`` of them corrupted.

    Returns the stream and the set of original COBS segments (frames without their delimiter).
    The oracle: a decoder must accept exactly the segments of the stream (split at 0x00) that
    are in that set, in order, and nothing else.
    """
    rng = np.random.default_rng(seed)
    originals: set[bytes] = set()
    parts: list[bytes] = []
    prev = encode_frame(Ack(0, 0, AckResult.ACCEPTED), 0)
    for i in range(n_frames):
        wire = encode_frame(random_message(rng), i)
        originals.add(wire[:-1])
        parts.append(_mutate(wire, rng, prev) if rng.random() < corrupt_fraction else wire)
        prev = wire
    return b"".join(parts), originals


def expected_segments(stream: bytes, originals: set[bytes]) -> list[bytes]:
    return [seg for seg in stream.split(b"\x00") if seg in originals]


# ---------------------------------------------------------------- C harness


def c_compiler() -> str | None:
    for cc in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if cc and shutil.which(cc):
            return cc
    return None


def build_harness(out_dir: Path, sanitize: bool = True) -> Path:
    """Compile the reference C implementation and its host harness; sanitizers catch memory errors."""
    cc = c_compiler()
    if cc is None:
        raise RuntimeError("no C compiler found (set CC)")
    exe = Path(out_dir) / ("acb_harness_san" if sanitize else "acb_harness")
    flags = ["-std=c99", "-pedantic", "-Wall", "-Wextra", "-Werror", "-O2"]
    if sanitize:
        flags += ["-g", "-fsanitize=address,undefined", "-fno-sanitize-recover=all"]
    sources = [str(FIRMWARE_DIR / "acesplat_bridge.c"), str(FIRMWARE_DIR / "host_harness.c")]
    subprocess.run([cc, *flags, *sources, "-o", str(exe)], check=True, capture_output=True, text=True)
    return exe


def run_harness(exe: Path, mode: str, data: bytes) -> str:
    out = subprocess.run([str(exe), mode], input=data, capture_output=True, check=True, timeout=600)
    return out.stdout.decode()
