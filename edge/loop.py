"""The localization loop: never blocks on a slow consumer, survives a vanishing camera, ends cleanly on Ctrl-C.

Live sources are read on a capture thread into a one-slot mailbox: when processing is slower than
the camera, the newest frame replaces the waiting one and the replaced frame is counted as dropped
(a pose for an old frame is worth less than a pose for the current one). Files are read in step
with processing, so a replay sees every frame. A source that disconnects is reopened with
exponential backoff while the loop reports LOST; the time without frames is counted as a gap.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from acesplat.core.pose import TrackingState
from edge.runtime import EdgeLocalizer, FrameOutcome
from edge.sources import FrameSource, SourceDisconnected, UnreadableFrame

BACKOFF_S = (0.1, 2.0)
"""First and longest wait between reconnect attempts."""


class LatestSlot:
    """A one-item mailbox: ``put`` replaces an unread item (counted in ``dropped``), ``get`` waits for one."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: Any = None
        self._has = False
        self.closed = False
        self.dropped = 0

    def put(self, item: Any) -> None:
        with self._cond:
            if self._has:
                self.dropped += 1
            self._item, self._has = item, True
            self._cond.notify()

    def get(self, timeout: float) -> tuple[bool, Any]:
        """(True, item) or (False, None) after ``timeout`` or when closed and empty."""
        with self._cond:
            if not self._has and not self.closed:
                self._cond.wait(timeout)
            if self._has:
                item, self._item, self._has = self._item, None, False
                return True, item
            return False, None

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()

    @property
    def finished(self) -> bool:
        with self._cond:
            return self.closed and not self._has


@dataclass
class LoopEvent:
    """Something that is not a frame: 'skipped' (unreadable frame), 'out_of_order' (a timestamp that does not move
    forward), 'disconnected', 'reconnected'."""

    kind: str
    detail: str
    wall_time: float
    gap_s: float = 0.0


@dataclass
class RunStats:
    frames: int = 0
    tracking: int = 0
    lost: int = 0
    dropped: int = 0
    skipped: int = 0
    skipped_frames: list[str] = field(default_factory=list)
    out_of_order: int = 0
    """Frames refused because their timestamp was earlier than the last localized frame's."""
    repeated: int = 0
    """Frames refused because their timestamp equalled the last localized frame's."""
    disconnects: int = 0
    reconnects: int = 0
    gap_s: float = 0.0
    interrupted: bool = False
    seconds: float = 0.0

    def as_dict(self) -> dict:
        return {
            "frames": self.frames,
            "tracking": self.tracking,
            "lost": self.lost,
            "dropped": self.dropped,
            "skipped": self.skipped,
            "skipped_frames": self.skipped_frames,
            "out_of_order": self.out_of_order,
            "repeated": self.repeated,
            "disconnects": self.disconnects,
            "reconnects": self.reconnects,
            "gap_s": self.gap_s,
            "interrupted": self.interrupted,
            "seconds": self.seconds,
            "fps": self.frames / self.seconds if self.seconds > 0 else 0.0,
        }


class _Events:
    """Thread-safe event queue the capture thread fills and the main loop drains."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._items: list[LoopEvent] = []

    def push(self, e: LoopEvent) -> None:
        with self._lock:
            self._items.append(e)

    def drain(self) -> list[LoopEvent]:
        with self._lock:
            items, self._items = self._items, []
        return items


def reconnect_with_backoff(
    source: FrameSource,
    stop: threading.Event,
    backoff: tuple[float, float] = BACKOFF_S,
    wait: Callable[[float], bool] | None = None,
) -> bool:
    """Retry ``source.reconnect()`` until it works (True) or ``stop`` is set (False)."""
    wait = wait or stop.wait
    delay = backoff[0]
    while not stop.is_set():
        if wait(delay):
            return False
        try:
            source.reconnect()
            return True
        except SourceDisconnected:
            delay = min(delay * 2.0, backoff[1])
    return False


def _read(source: FrameSource, events: _Events, stop: threading.Event, backoff: tuple[float, float]):
    """One read with skip and reconnect handling: ('frame', frame, capture_ms, t_start), ('end',) or ('again',)."""
    t_start = time.perf_counter()
    try:
        frame = source.read()
    except UnreadableFrame as e:
        events.push(LoopEvent("skipped", str(e), time.time()))
        return ("again",)
    except SourceDisconnected as e:
        t_lost = time.monotonic()
        events.push(LoopEvent("disconnected", str(e), time.time()))
        if not reconnect_with_backoff(source, stop, backoff):
            events.push(LoopEvent("reconnect_abandoned", str(e), time.time(), time.monotonic() - t_lost))
            return ("end",)
        events.push(LoopEvent("reconnected", source.description, time.time(), time.monotonic() - t_lost))
        return ("again",)
    if frame is None:
        return ("end",)
    return ("frame", frame, (time.perf_counter() - t_start) * 1000.0, t_start)


def run_loop(
    source: FrameSource,
    localizer: EdgeLocalizer,
    on_outcome: Callable[[FrameOutcome], None],
    on_event: Callable[[LoopEvent], None] | None = None,
    max_frames: int | None = None,
    stop: threading.Event | None = None,
    backoff: tuple[float, float] = BACKOFF_S,
) -> RunStats:
    """Localize frames from ``source`` until it ends, ``max_frames`` are done, ``stop`` is set, or Ctrl-C.

    Each outcome goes to ``on_outcome`` after the localizer's taps (EdgeLocalizer.add_tap) have seen it; each event
    to the taps, then to ``on_event``."""
    stop = stop or threading.Event()
    stats = RunStats()
    events = _Events()
    slot = LatestSlot()
    t0 = time.monotonic()
    thread: threading.Thread | None = None

    def handle_events() -> None:
        for e in events.drain():
            if e.kind == "skipped":
                stats.skipped += 1
                stats.skipped_frames.append(e.detail)
            elif e.kind == "disconnected":
                stats.disconnects += 1
            elif e.kind in ("reconnected", "reconnect_abandoned"):
                stats.reconnects += e.kind == "reconnected"
                stats.gap_s += e.gap_s
            localizer.notify(e)
            if on_event:
                on_event(e)

    last_ts: list[float] = []

    def in_order(frame) -> bool:
        """Refuse a frame whose timestamp does not move forward (tracking's motion model needs time to advance)."""
        ts = float(frame.timestamp)
        if last_ts and ts <= last_ts[0]:
            repeated = ts == last_ts[0]
            if repeated:
                stats.repeated += 1
            else:
                stats.out_of_order += 1
            what = "repeated timestamp" if repeated else "out of order"
            detail = f"{frame.name or frame.frame_id}: {what} ({ts:.6f} s after {last_ts[0]:.6f} s), not localized"
            e = LoopEvent("out_of_order", detail, time.time())
            localizer.notify(e)
            if on_event:
                on_event(e)
            return False
        last_ts[:] = [ts]
        return True

    def process(frame, capture_ms: float, t_start: float) -> None:
        if not in_order(frame):
            return
        out = localizer.localize(frame, capture_ms, t_start)
        stats.frames += 1
        if out.record.state == TrackingState.TRACKING:
            stats.tracking += 1
        else:
            stats.lost += 1
        on_outcome(out)

    def capture() -> None:
        try:
            while not stop.is_set():
                r = _read(source, events, stop, backoff)
                if r[0] == "end":
                    break
                if r[0] == "frame":
                    slot.put(r[1:])
        except BaseException as e:  # surface capture-thread crashes in the main loop
            events.push(LoopEvent("capture_error", f"{type(e).__name__}: {e}", time.time()))
        finally:
            slot.close()

    try:
        if source.live:
            thread = threading.Thread(target=capture, name="capture", daemon=True)
            thread.start()
            while not stop.is_set():
                ok, item = slot.get(timeout=0.05)
                handle_events()
                if ok:
                    process(*item)
                    if max_frames and stats.frames >= max_frames:
                        break
                elif slot.finished:
                    break
        else:
            while not stop.is_set():
                r = _read(source, events, stop, backoff)
                handle_events()
                if r[0] == "end":
                    break
                if r[0] == "frame":
                    process(*r[1:])
                    if max_frames and stats.frames >= max_frames:
                        break
    except KeyboardInterrupt:
        stats.interrupted = True
    finally:
        stop.set()
        if thread is not None:
            thread.join(timeout=2.0)
        handle_events()
        stats.dropped = slot.dropped
        stats.seconds = time.monotonic() - t0
        source.close()
    return stats
