"""Protocol v1 in Python: COBS, CRC, message layouts, rejects, the streaming decoder, a seeded fuzz."""

from __future__ import annotations

import math
import re
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from acesplat.core.geometry import look_at, matrix_to_quat, pose_error
from acesplat.core.pose import PoseRecord, TrackingState
from firmware_bridge.cobs import cobs_decode, cobs_encode
from firmware_bridge.decoder import StreamDecoder
from firmware_bridge.protocol import (
    MAX_SEGMENT,
    REJECT_REASONS,
    Ack,
    AckResult,
    Command,
    Frame,
    MsgType,
    Pose,
    RuntimeState,
    Status,
    decode_segment,
    encode_body,
    encode_frame,
    wire_size,
)
from firmware_bridge.testing import expected_segments, fuzz_stream, reference_messages, reference_rejects

# ---------------------------------------------------------------- COBS


@pytest.mark.parametrize(
    "raw, encoded",
    [  # by hand from the block rule: code n = n-1 data bytes then an implied zero, except at the end
        (b"", b"\x01"),
        (b"\x00", b"\x01\x01"),
        (b"\x00\x00", b"\x01\x01\x01"),
        (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
        (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
        (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
        (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255)) + b"\x01"),
        (bytes(range(1, 256)), b"\xff" + bytes(range(1, 255)) + b"\x02\xff"),
        (b"\x00" + bytes(range(1, 255)), b"\x01\xff" + bytes(range(1, 255)) + b"\x01"),
    ],
)
def test_cobs_hand_cases(raw: bytes, encoded: bytes) -> None:
    assert cobs_encode(raw) == encoded
    assert cobs_decode(encoded) == (raw, True)


def test_cobs_random_round_trip_has_no_zero_and_bounded_overhead() -> None:
    rng = np.random.default_rng(0)
    for n in list(range(0, 600, 7)) + [253, 254, 255, 508]:
        for zero_rate in (0.0, 0.1, 0.9):
            raw = rng.integers(1, 256, n, dtype=np.uint8)
            raw[rng.random(n) < zero_rate] = 0
            enc = cobs_encode(raw.tobytes())
            assert 0 not in enc
            assert len(enc) <= n + 1 + n // 254
            assert cobs_decode(enc) == (raw.tobytes(), True)


def test_cobs_truncated_block_is_incomplete_and_zero_is_refused() -> None:
    assert cobs_decode(b"\x05\x11\x22") == (b"\x11\x22", False)
    with pytest.raises(ValueError):
        cobs_decode(b"\x02\x00")


# ---------------------------------------------------------------- CRC and layouts


PROTOCOL_MD = Path(__file__).resolve().parents[1] / "firmware_bridge" / "PROTOCOL.md"


def crc32_by_the_spec(data: bytes) -> int:
    """CRC-32 bit by bit from PROTOCOL.md section 3: reflected polynomial 0xEDB88320, init and final XOR 0xFFFFFFFF."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0xEDB88320 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def protocol_md_examples() -> list[tuple[bytes, bytes]]:
    """(body, wire) of every worked example in PROTOCOL.md section 8."""
    text = PROTOCOL_MD.read_text()
    bodies = re.findall(r"^body: ([0-9a-f ]+)$", text, re.M)
    wires = re.findall(r"^wire: ([0-9a-f ]+)$", text, re.M)
    assert len(bodies) == len(wires) == 4
    return [(bytes.fromhex(b), bytes.fromhex(w)) for b, w in zip(bodies, wires)]


def test_reference_crc_has_the_catalogue_check_value() -> None:
    assert crc32_by_the_spec(b"123456789") == 0xCBF43926  # CRC-32/ISO-HDLC, as PROTOCOL.md states


@pytest.mark.parametrize("body, wire", protocol_md_examples())
def test_protocol_md_examples_carry_the_crc_of_exactly_header_and_payload(body: bytes, wire: bytes) -> None:
    length = body[4]
    assert len(body) == 5 + length + 4
    assert struct.unpack("<I", body[-4:])[0] == crc32_by_the_spec(body[: 5 + length])
    assert cobs_encode(body) + b"\x00" == wire
    frame = decode_segment(wire[:-1])
    assert isinstance(frame, Frame) and encode_frame(frame.message, frame.seq) == wire


@pytest.mark.parametrize("body, wire", protocol_md_examples())
def test_a_frame_whose_crc_field_is_wrong_is_rejected(body: bytes, wire: bytes) -> None:
    n = len(body) - 4
    wrong = [
        crc32_by_the_spec(body[:n]) ^ 1,  # one bit off
        crc32_by_the_spec(body[5:n]),  # the payload alone
        crc32_by_the_spec(body[:5]),  # the header alone
        crc32_by_the_spec(body[: n - 1]),  # one byte short
        crc32_by_the_spec(body[:n] + b"\x00"),  # one byte long
        crc32_by_the_spec(body[:n]) ^ 0xFFFFFFFF,  # without the final XOR
    ]
    for crc in wrong:
        seg = cobs_encode(body[:n] + struct.pack("<I", crc))
        assert decode_segment(seg) == "crc"
        dec = StreamDecoder()
        assert dec.feed(seg + b"\x00") == [] and dec.rejects["crc"] == 1 and dec.frames_rejected == 1
    assert isinstance(decode_segment(wire[:-1]), Frame)  # the documented CRC itself is accepted


def test_payload_layouts_match_protocol_md() -> None:
    pose = Pose(
        0x0102030405060708, 0x0A0B0C0D, (1.0, 2.0, 3.0), (0.5, 0.5, 0.5, 0.5), 0x1234, TrackingState.TRACKING, 0.25
    )
    body = encode_body(pose, 0xBEEF)
    assert body[:5] == bytes([1, 0x01, 0xEF, 0xBE, 48])
    p = body[5:-4]
    assert p[0:8] == bytes([8, 7, 6, 5, 4, 3, 2, 1])
    assert p[8:12] == bytes([0x0D, 0x0C, 0x0B, 0x0A])
    assert struct.unpack("<3f", p[12:24]) == (1.0, 2.0, 3.0)
    assert struct.unpack("<4f", p[24:40]) == (0.5, 0.5, 0.5, 0.5)
    assert p[40:44] == bytes([0x34, 0x12, 1, 0])
    assert struct.unpack("<f", p[44:48]) == (0.25,)
    assert body[-4:] == struct.pack("<I", crc32_by_the_spec(body[:-4]))

    status = encode_body(Status(7, 30.0, 12.0, 5, 6, RuntimeState.PAUSED), 1)[5:-4]
    assert status == struct.pack("<Q", 7) + struct.pack("<ff", 30.0, 12.0) + struct.pack("<II", 5, 6) + bytes(
        [3, 0, 0, 0]
    )
    assert encode_body(Command(4, 30.0), 1)[5:-4] == bytes([4, 0, 0, 0]) + struct.pack("<f", 30.0)
    assert encode_body(Ack(0x0102, 4, AckResult.UNSUPPORTED), 1)[5:-4] == bytes([2, 1, 4, 2])


def test_wire_sizes_are_fixed() -> None:
    for seq, msg in reference_messages():
        t = {Pose: MsgType.POSE, Status: MsgType.STATUS, Command: MsgType.COMMAND, Ack: MsgType.ACK}[type(msg)]
        assert len(encode_frame(msg, seq)) == wire_size(t)
    assert (wire_size(MsgType.POSE), wire_size(MsgType.STATUS), wire_size(MsgType.COMMAND), wire_size(MsgType.ACK)) == (
        59,
        39,
        19,
        15,
    )


def test_every_reference_message_round_trips() -> None:
    for seq, msg in reference_messages():
        wire = encode_frame(msg, seq)
        assert wire.endswith(b"\x00") and 0 not in wire[:-1]
        frame = decode_segment(wire[:-1])
        assert isinstance(frame, Frame) and frame.seq == seq
        # floats come back rounded to binary32; re-encoding gives the same bytes
        assert encode_frame(frame.message, frame.seq) == wire
        assert type(frame.message) is type(msg)


@pytest.mark.parametrize("reason, wire", reference_rejects())
def test_reference_rejects(reason: str, wire: bytes) -> None:
    dec = StreamDecoder()
    assert dec.feed(wire) == []
    assert dec.rejects[reason] == 1 and dec.frames_rejected == 1


def test_encode_refuses_out_of_range_fields_and_non_messages() -> None:
    with pytest.raises(ValueError):
        encode_frame(Ack(70000, 1, AckResult.ACCEPTED), 0)
    with pytest.raises(TypeError):
        encode_frame("POSE", 0)  # type: ignore[arg-type]


# ---------------------------------------------------------------- PoseRecord <-> POSE


def test_pose_from_record_matches_core_quaternion_and_round_trips() -> None:
    T = look_at(np.array([1.0, -2.0, 1.5]), np.array([0.0, 0.5, 0.2]))
    rec = PoseRecord(123456, T, 250, TrackingState.TRACKING, 0.7, 9)
    pose = Pose.from_record(rec)
    assert pose.position == tuple(T[:3, 3])
    np.testing.assert_allclose(pose.quat_wxyz, matrix_to_quat(T[:3, :3]))
    frame = decode_segment(encode_frame(pose, 3)[:-1])
    back = frame.message.to_record()
    t_err, r_err = pose_error(back.T_c2w, T)
    assert t_err < 1e-6 and r_err < 1e-4  # binary32 resolution
    assert (back.timestamp_us, back.inliers, back.state, back.frame_id) == (123456, 250, TrackingState.TRACKING, 9)
    assert back.quality == pytest.approx(0.7, abs=1e-7)


def test_pose_from_record_clamps_what_does_not_fit() -> None:
    rec = PoseRecord(-5, np.eye(4), 10**6, TrackingState.TRACKING, math.nan, 2**40 + 3)
    pose = Pose.from_record(rec)
    assert (pose.timestamp_us, pose.inliers, pose.quality, pose.frame_id) == (0, 65535, 0.0, 3)
    assert decode_segment(encode_frame(pose, 0)[:-1]).message == pose
    bad = Pose.from_record(PoseRecord(1, np.full((4, 4), np.nan), 5, TrackingState.TRACKING, 2.0))
    assert bad.state == TrackingState.LOST and all(math.isnan(v) for v in bad.position) and bad.quality == 1.0


# ---------------------------------------------------------------- streaming decoder


def _stream_of_references() -> tuple[bytes, list[Frame]]:
    frames = [Frame(seq, msg) for seq, msg in reference_messages()]
    return b"".join(encode_frame(f.message, f.seq) for f in frames), frames


def _same(a: list[Frame], b: list[Frame]) -> bool:
    return [encode_frame(f.message, f.seq) for f in a] == [encode_frame(f.message, f.seq) for f in b]


def test_decoder_result_does_not_depend_on_chunking() -> None:
    data, frames = _stream_of_references()
    rng = np.random.default_rng(1)
    for _ in range(5):
        dec, got, i = StreamDecoder(), [], 0
        while i < len(data):
            n = int(rng.integers(1, 40))
            got += dec.feed(data[i : i + n])
            i += n
        assert _same(got, frames) and dec.frames_rejected == 0 and dec.bytes == len(data)
    dec = StreamDecoder()
    one_by_one = [f for b in data for f in dec.feed(bytes([b]))]
    assert _same(one_by_one, frames)


def test_decoder_resynchronises_after_garbage_and_ignores_empty_frames() -> None:
    good = encode_frame(Command(2), 5)
    dec = StreamDecoder()
    out = dec.feed(
        b"\x13\x37garbage-without-delimiter" + b"\x00\x00\x00" + good + b"\x00\x00" + good[:-6] + b"\x00" + good
    )
    assert [f.seq for f in out] == [5, 5]
    assert dec.frames_rejected == 2  # the garbage and the truncated copy; empty frames are not counted


def test_decoder_buffer_is_bounded_and_long_noise_is_one_overflow() -> None:
    dec = StreamDecoder()
    for _ in range(1000):
        dec.feed(b"\x55" * 1000)
        assert len(dec._partial) <= MAX_SEGMENT
    frame = encode_frame(Ack(1, 1, AckResult.ACCEPTED), 77)
    out = dec.feed(b"\x00" + frame)
    assert [f.seq for f in out] == [77]
    assert dec.rejects["overflow"] == 1 and dec.frames_rejected == 1


def test_no_single_or_double_bit_flip_is_accepted() -> None:
    """Exhaustive over one POSE frame, the delimiter excluded: every 1- and 2-bit corruption is rejected."""
    wire = bytearray(
        encode_frame(
            Pose.from_record(PoseRecord(99, look_at(np.ones(3), np.zeros(3)), 40, TrackingState.TRACKING, 0.5)), 1
        )[:-1]
    )
    nbits = len(wire) * 8
    accepted = 0

    def check(buf: bytearray) -> int:
        # a flip that creates a 0x00 splits the frame: decode each piece as a receiver would
        return sum(isinstance(decode_segment(bytes(seg)), Frame) for seg in bytes(buf).split(b"\x00") if seg)

    for i in range(nbits):
        wire[i // 8] ^= 1 << (i % 8)
        accepted += check(wire)
        for j in range(i + 1, nbits):
            wire[j // 8] ^= 1 << (j % 8)
            accepted += check(wire)
            wire[j // 8] ^= 1 << (j % 8)
        wire[i // 8] ^= 1 << (i % 8)
    assert accepted == 0


def test_seeded_fuzz_accepts_exactly_the_intact_frames() -> None:
    stream, originals = fuzz_stream(20_000, seed=2024)
    dec = StreamDecoder()
    got = []
    for i in range(0, len(stream), 4096):  # arbitrary chunking, as a serial port delivers it
        got += dec.feed(stream[i : i + 4096])
    got += dec.feed(b"\x00")
    accepted = [encode_frame(f.message, f.seq)[:-1] for f in got]
    expected = expected_segments(stream, originals)
    assert accepted == expected
    # about half the frames were corrupted, and a corruption that eats a delimiter takes the next frame with it
    assert 8_000 < len(expected) < 10_500
    assert dec.frames_rejected > 5_000
    assert all(dec.rejects[r] > 0 for r in ("overflow", "cobs", "short", "crc"))


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=600), st.lists(st.integers(1, 64), min_size=1, max_size=20))
def test_decoder_never_raises_and_chunking_is_irrelevant(data: bytes, cuts: list[int]) -> None:
    whole = StreamDecoder()
    a = whole.feed(data)
    parts = StreamDecoder()
    b, i, k = [], 0, 0
    while i < len(data):
        n = cuts[k % len(cuts)]
        b += parts.feed(data[i : i + n])
        i, k = i + n, k + 1
    assert _same(a, b) and whole.rejects == parts.rejects
    assert set(whole.rejects) == set(REJECT_REASONS)
