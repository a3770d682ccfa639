"""Streaming frame decoder: bytes in any chunking -> frames, never raising, with bounded memory.

Garbage, noise, truncated frames and bit flips become counted rejects; the decoder resynchronises
at the next 0x00 because a delimiter always ends the current segment. A segment that grows beyond
the longest valid frame is not buffered further: the rest up to the next delimiter is skipped and
the whole segment counts as one ``overflow`` reject. Empty segments (back-to-back delimiters, which
senders use to flush a receiver after a reconnect) are ignored.
"""

from __future__ import annotations

from collections import Counter

from firmware_bridge.protocol import MAX_SEGMENT, REJECT_REASONS, Frame, decode_segment


class StreamDecoder:
    """Feed it whatever the port returns; it returns the complete valid frames in order."""

    def __init__(self) -> None:
        self._partial = bytearray()
        self._overflow = False
        self.frames_ok = 0
        self.rejects: Counter[str] = Counter({r: 0 for r in REJECT_REASONS})
        self.bytes = 0

    @property
    def frames_rejected(self) -> int:
        return sum(self.rejects.values())

    def feed(self, data: bytes) -> list[Frame]:
        out: list[Frame] = []
        self.bytes += len(data)
        start = 0
        while True:
            end = data.find(0, start)
            piece = data[start:] if end < 0 else data[start:end]
            if not self._overflow:
                if len(self._partial) + len(piece) > MAX_SEGMENT:
                    self._overflow = True
                    self._partial.clear()
                else:
                    self._partial += piece
            if end < 0:
                return out
            self._finish(out)
            start = end + 1

    def _finish(self, out: list[Frame]) -> None:
        if self._overflow:
            self.rejects["overflow"] += 1
        elif self._partial:
            result = decode_segment(bytes(self._partial))
            if isinstance(result, Frame):
                self.frames_ok += 1
                out.append(result)
            else:
                self.rejects[result] += 1
        self._partial.clear()
        self._overflow = False

    def counts(self) -> dict[str, int]:
        """frames_ok, frames_rejected and the rejects by reason (for stats and --json)."""
        return {
            "frames_ok": self.frames_ok,
            "frames_rejected": self.frames_rejected,
            **{f"rejected_{k}": v for k, v in self.rejects.items()},
        }
