"""The localization loop: never blocks on a slow consumer, survives a vanishing camera, ends cleanly on Ctrl-C.

Live sources are read on a capture thread into a one-slot mailbox: when processing is slower than
the camera, the newest frame replaces the waiting one and the replaced frame is counted as dropped
(a pose for an old frame is worth less than a pose for the current one). Files are read in step
with processing, so a replay sees every frame. A source that disconnects is reopened with
exponential backoff while the loop reports LOST; the time without frames is counted as a gap.

With ``overlap`` (LoopSettings), a preparing thread reads the next frame and runs its first phase (preprocess,
inference: EdgeLocalizer.prepare) while the main thread solves the current one (PnP, gate, alignment, taps): at
most two frames are in flight, so a live source still hands over its newest frame, and a replay still sees every
frame. The poses are those of the sequential loop; the throughput rises where solving is a large share of a frame
(bench/pipeline.md).
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from acesplat.core.config import knob
from acesplat.core.pose import TrackingState
from edge.inference import default_threads
from edge.runtime import EdgeLocalizer, FrameOutcome
from edge.sources import FrameSource, SourceDisconnected, UnreadableFrame

BACKOFF_S = (0.1, 2.0)
"""First and longest wait between reconnect attempts."""


@dataclass
class LoopSettings:
    overlap: bool | None = knob(
        None,
        "Prepare and infer frame n+1 while frame n is solved; unset: on for a live source while tracking (it keeps "
        "the camera's rate), else off (each pose sooner); bench/tracking.md, bench/pipeline.md.",
    )


def overlap_for(overlap: bool | None, live: bool, tracking: bool, paced: bool = False) -> bool:
    """LoopSettings.overlap resolved for a run: as set, or when unset, on for a ``live`` source while ``tracking``
    unless a ``paced`` tap (refinement) owns the time between frames."""
    if overlap is not None:
        return bool(overlap)
    return live and tracking and not paced


def overlap_threads() -> int:
    """onnxruntime's intra-op threads beside a solving thread: every core but one (at least one)."""
    return max(1, default_threads() - 1)


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
    overlap: bool = False
    """The next frame was prepared while the current one was solved (LoopSettings.overlap)."""

    @property
    def fps(self) -> float:
        """Frames localized a second over the run."""
        return self.frames / self.seconds if self.seconds > 0 else 0.0

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
            "fps": self.fps,
            "overlap": self.overlap,
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
    overlap: bool = False,
) -> RunStats:
    """Localize frames from ``source`` until it ends, ``max_frames`` are done, ``stop`` is set, or Ctrl-C.

    Each outcome goes to ``on_outcome`` after the localizer's taps (EdgeLocalizer.add_tap) have seen it; each event
    to the taps, then to ``on_event``. ``overlap``: the next frame is prepared on a second thread while this one is
    solved (LoopSettings.overlap; refused with a tap that paces, which owns the time between frames)."""
    if overlap and (localizer.pace_ms is not None or any(t.pace_ms is not None for t in localizer.taps)):
        raise ValueError("overlap cannot run with pacing: a paced tap (refinement) owns the time between frames")
    stop = stop or threading.Event()
    stats = RunStats(overlap=overlap)
    events = _Events()
    slot = LatestSlot()
    t0 = time.monotonic()
    threads: list[threading.Thread] = []

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

    def count(out: FrameOutcome) -> None:
        stats.frames += 1
        if out.record.state == TrackingState.TRACKING:
            stats.tracking += 1
        else:
            stats.lost += 1
        on_outcome(out)

    def process(frame, capture_ms: float, t_start: float) -> None:
        if in_order(frame):
            count(localizer.localize(frame, capture_ms, t_start))

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

    def next_frame(idle: Callable[[], None] | None = None) -> tuple | None:
        """The next frame to localize, (frame, capture_ms, t_start): the newest of a live source, the next file of
        a replay; None at the end or on stop. ``idle`` runs whenever a wait for a frame ends without one (the
        events of a camera that went away reach the taps while it is gone)."""
        while not stop.is_set():
            if source.live:
                ok, item = slot.get(timeout=0.05)
                if ok:
                    return item
                if slot.finished:
                    return None
            else:
                r = _read(source, events, stop, backoff)
                if r[0] == "end":
                    return None
                if r[0] == "frame":
                    return r[1:]
            if idle is not None:
                idle()
        return None

    try:
        if source.live:
            threads.append(threading.Thread(target=capture, name="capture", daemon=True))
            threads[-1].start()
        if overlap:
            _overlapped(localizer, next_frame, in_order, count, handle_events, stop, max_frames, stats, threads)
        else:
            while not stop.is_set():
                item = next_frame(handle_events)
                handle_events()
                if item is None:
                    break
                process(*item)
                if max_frames and stats.frames >= max_frames:
                    break
    except KeyboardInterrupt:
        stats.interrupted = True
    finally:
        stop.set()
        for thread in threads:
            thread.join(timeout=2.0)
        handle_events()
        stats.dropped = slot.dropped
        stats.seconds = time.monotonic() - t0
        source.close()
    return stats


def _overlapped(
    localizer: EdgeLocalizer,
    next_frame: Callable[[], tuple | None],
    in_order: Callable[[Any], bool],
    count: Callable[[FrameOutcome], None],
    handle_events: Callable[[], None],
    stop: threading.Event,
    max_frames: int | None,
    stats: RunStats,
    threads: list[threading.Thread],
) -> None:
    """The pipelined loop: a preparing thread reads and prepares frame n+1 (inferring it when its expected plan
    needs it: EdgeLocalizer.infer_after) once the main thread has taken frame n, and the main thread plans, solves
    and reports frames in order. Errors of the preparing thread are raised here."""
    go: queue.Queue[bool | None] = queue.Queue()
    ready: queue.Queue[tuple] = queue.Queue()

    def prepare_frames() -> None:
        try:
            while True:
                infer = go.get()
                if infer is None or stop.is_set():
                    return
                item = next_frame()
                if item is None:
                    ready.put(("end",))
                    return
                frame, capture_ms, t_start = item
                ready.put(("frame", localizer.prepare(frame, capture_ms, t_start, infer=infer)))
        except BaseException as e:  # raised again on the main thread
            ready.put(("error", e))

    worker = threading.Thread(target=prepare_frames, name="prepare", daemon=True)
    threads.insert(0, worker)  # joined before the capture thread and before the source closes
    go.put(localizer.infer_after(None))
    worker.start()
    try:
        while not stop.is_set():
            try:
                item = ready.get(timeout=0.05)
            except queue.Empty:
                handle_events()
                continue
            handle_events()
            if item[0] == "end":
                break
            if item[0] == "error":
                raise item[1]
            p = item[1]
            if not in_order(p.frame):
                go.put(localizer.infer_after(None))
                continue
            plan = localizer.plan_prepared(p)
            last = bool(max_frames and stats.frames + 1 >= max_frames)
            if not last:
                go.put(localizer.infer_after(plan))  # the next frame is prepared while this one is solved
            count(localizer.finish(p))
            if last:
                break
    finally:
        stop.set()
        go.put(None)
