"""Consistent Overhead Byte Stuffing: frames that contain no 0x00, so 0x00 can delimit them.

Why COBS: the receiver finds frame boundaries by looking for one byte value, so after noise or a
cut cable it resynchronises at the next delimiter without parsing anything; the cost is at most
one byte per 254 (exactly one byte for every frame of protocol v1).

The encoding is the classic one: each block is a code byte ``n`` (1..255) followed by ``n - 1``
non-zero bytes; a block with code < 255 stands for its bytes plus one 0x00, except the last block;
code 255 stands for 254 bytes and no 0x00. The C implementation (firmware/acesplat_bridge.c) decodes
the same blocks one byte at a time; both must agree on every input, valid or not.
"""

from __future__ import annotations

MAX_RUN = 254
"""Longest run of non-zero bytes one block carries (code 0xFF)."""


def cobs_encode(data: bytes) -> bytes:
    """The COBS encoding of ``data`` (no delimiter appended): no byte of the result is 0x00."""
    out = bytearray()
    for part in bytes(data).split(b"\x00"):
        while len(part) >= MAX_RUN:
            out.append(0xFF)
            out += part[:MAX_RUN]
            part = part[MAX_RUN:]
        out.append(len(part) + 1)
        out += part
    return bytes(out)


def cobs_decode(segment: bytes) -> tuple[bytes, bool]:
    """Decode one delimiter-free ``segment``; returns (decoded bytes, complete).

    ``complete`` is False when the last block promises more bytes than the segment holds (a
    truncated frame). The decoded bytes are returned even then, so callers can classify the reject
    exactly as the byte-at-a-time C decoder does (overflow is judged on the decoded length first).
    Raises ValueError if ``segment`` contains 0x00 (the caller split at the delimiter).
    """
    if 0 in segment:
        raise ValueError("a COBS segment cannot contain 0x00")
    out = bytearray()
    i, n, prev = 0, len(segment), 0
    while i < n:
        code = segment[i]
        if prev and prev != 0xFF:
            out.append(0)
        block = segment[i + 1 : i + code]
        out += block
        if len(block) < code - 1:
            return bytes(out), False
        i += code
        prev = code
    return bytes(out), True
