"""Where poses go: a JSON-lines log that is never left with half a line, and a non-blocking pose sink.

The log writes each line with one ``os.write`` on an append-only descriptor: an exception or Ctrl-C
lands between lines, never inside one; a short write (disk full) is cut back to the last complete
line before the error is raised.
"""

from __future__ import annotations

import json
import math
import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from acesplat.core.errors import InputError
from acesplat.core.pose import PoseRecord, TrackingState
from edge.loop import LatestSlot, LoopEvent
from edge.runtime import FrameOutcome, FrameTap


def _clean(v: Any) -> Any:
    """JSON has no NaN: non-finite numbers become null."""
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    return v


def outcome_line(out: FrameOutcome) -> dict:
    """timestamp, frame id, camera-to-world pose (row-major 4x4), inliers, state and stage timings."""
    rec = out.record
    T = np.asarray(rec.T_c2w, dtype=float)
    return _clean(
        {
            "timestamp_us": rec.timestamp_us,
            "frame_id": rec.frame_id,
            "name": out.name,
            "T_c2w": T.tolist() if np.all(np.isfinite(T)) else None,
            "inliers": rec.inliers,
            "quality": rec.quality,
            "state": TrackingState(rec.state).name,
            "ms": {k: round(v, 3) for k, v in out.times_ms.items()},
            "alignment": out.alignment,
            "mode": out.mode,
            "reset_counter": rec.reset_counter,
        }
    )


def event_line(e: LoopEvent) -> dict:
    return _clean(
        {
            "event": e.kind,
            "detail": e.detail,
            "wall_time": e.wall_time,
            "gap_s": e.gap_s,
            "state": TrackingState.LOST.name if e.kind == "disconnected" else None,
        }
    )


class JsonLinesWriter:
    """Append-only JSON lines; truncates an existing file on open."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_APPEND, 0o666)
        except OSError as e:
            raise InputError(self.path, f"cannot open for writing ({e.strerror})") from None
        self._good = 0
        self.lines = 0

    def write(self, obj: dict) -> None:
        data = (json.dumps(obj, separators=(",", ":")) + "\n").encode("utf-8")
        done = 0
        try:
            while done < len(data):
                done += os.write(self._fd, data[done:])
        except BaseException:
            os.ftruncate(self._fd, self._good)  # a failed write may have put part of the line on disk
            raise
        self._good += len(data)
        self.lines += 1

    def close(self) -> None:
        if self._fd >= 0:
            try:
                os.fsync(self._fd)
            finally:
                os.close(self._fd)
                self._fd = -1

    def __enter__(self) -> JsonLinesWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncPoseSink:
    """Hands poses to a possibly slow consumer on its own thread: the newest pose wins, replaced ones are counted."""

    def __init__(self, consume: Callable[[PoseRecord], None]) -> None:
        self._consume = consume
        self._slot = LatestSlot()
        self.errors = 0
        self.last_error = ""
        self._thread = threading.Thread(target=self._run, name="pose-sink", daemon=True)
        self._thread.start()

    def send(self, rec: PoseRecord) -> None:
        self._slot.put(rec)

    @property
    def dropped(self) -> int:
        return self._slot.dropped

    def _run(self) -> None:
        while True:
            ok, rec = self._slot.get(timeout=0.1)
            if ok:
                try:
                    self._consume(rec)
                except Exception as e:  # a failing consumer must not stop localization
                    self.errors += 1
                    self.last_error = f"{type(e).__name__}: {e}"
            elif self._slot.finished:
                return

    def close(self, timeout: float = 2.0) -> None:
        self._slot.close()
        self._thread.join(timeout)


class JsonLinesTap(FrameTap):
    """A localizer tap writing one JSON line per frame (``outcome_line``) and per loop event (``event_line``)."""

    def __init__(self, path: str | Path) -> None:
        self.writer = JsonLinesWriter(path)

    def on_frame(self, out: FrameOutcome) -> None:
        self.writer.write(outcome_line(out))

    def on_event(self, event: LoopEvent) -> None:
        self.writer.write(event_line(event))

    def close(self) -> None:
        self.writer.close()
