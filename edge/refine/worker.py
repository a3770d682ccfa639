"""Refinement on its own thread, so localization never waits for it.

The localization loop hands every confidently localized frame to the worker (``submit``) with the
frame's deadline (when its budget ends) and goes on. The worker keeps only the newest frame (latest
wins; replaced frames are counted as dropped), decides whether it is a keyframe, and refines until
the deadline. ``preempt`` pulls the running deadline to now, so a batch stops at its next step when
the next frame's localization begins.

The rasterizer's kernels are compiled with ``nogil=True`` (projection, compositing and their
backward), so they run beside onnxruntime and OpenCV (which release the GIL too). The tile binning
kernel and the numpy/Python glue between kernels hold the GIL; bench/bench_refine.py measures what
that costs localization. The thread lowers its own priority (nice 5) and the session renders with
one rasterizer thread (this one), so on a shared CPU the scheduler serves localization first.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from edge.refine.coverage import projected_coverage
from edge.refine.deadline import Clock, Deadline
from edge.refine.keyframes import KeyframeSelector
from edge.refine.persist import SplatSaver
from edge.refine.refiner import BatchReport, Keyframe, Refiner, grant


@dataclass
class Candidate:
    """A localized frame offered for refinement; ``make_keyframe`` turns it into a Keyframe on the worker thread
    (image resizing and the like stay off the localization path)."""

    pose: np.ndarray
    inliers: int
    tracking: bool
    deadline_at: float
    make_keyframe: Callable[[], Keyframe]
    cell_depth: Callable[[], tuple[np.ndarray, Any]] | None = None
    """Optional: SCR cell depths (h, w) and the input intrinsics, for the coverage test of keyframe selection."""
    name: str = ""
    inlier_ratio: float = 1.0


@dataclass
class WorkerStats:
    candidates: int = 0
    late: int = 0
    """Candidates whose deadline had passed when the worker took them."""
    reports: list[BatchReport] = field(default_factory=list)
    busy_ms: list[float] = field(default_factory=list)
    """Wall time the worker spent on each candidate it took (selection + batch)."""
    errors: list[str] = field(default_factory=list)
    absorbed: int = 0
    """Frames that arrived while a batch was open and lent it their time window instead of being considered."""
    overrun_ms: list[float] = field(default_factory=list)
    window_work_ms: list[float] = field(default_factory=list)
    """Refinement work (pieces run) in each frame's window a batch used: the per-frame cost beside localization."""
    piece_spill_ms: list[float] = field(default_factory=list)
    """For each piece of work run: how far past its window's deadline it ended (0 when inside it; a piece
    that ends late overlaps the next frame's localization)."""
    """For each keyframe batch: how long after its deadline it finished (0 when on time)."""
    late_pieces: list[tuple[str, float, float, float]] = field(default_factory=list)
    """Pieces that ended past their window: (the piece's estimate's name, predicted ms, took ms, past the deadline
    ms), the first 200."""


NICE = 5
"""Refinement's thread runs at this nice value (Linux) when it may overlap localization (unpaced): the scheduler
prefers localization when both want a core; paced sessions run it at nice 0 (bench/refine.md)."""


def lower_priority(nice: int = NICE) -> bool:
    """Lower the calling thread's scheduling priority (Linux threads are tasks with their own nice value)."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
        return True
    except (AttributeError, OSError):  # not Linux, or not permitted
        return False


MAX_WINDOWS = 16
"""A batch may continue over this many frames' windows; then optional work stops and required work gives up."""
STEP_WINDOWS = 8
"""Optimisation steps wait for at most this many windows: newer keyframes (new surfaces to seed) wait meanwhile.
Steps on crops cost 5-20 ms, so a keyframe's 30 steps need several windows beside a 40-60 ms localization."""


class RefineWorker:
    def __init__(
        self,
        refiner: Refiner,
        selector: KeyframeSelector,
        saver: SplatSaver | None = None,
        clock: Clock = time.perf_counter,
        keep_reports: int = 10_000,
        max_windows: int = MAX_WINDOWS,
        step_windows: int = STEP_WINDOWS,
        nice: int = NICE,
    ) -> None:
        if max_windows < 1 or step_windows < 1:
            raise ValueError(f"max_windows and step_windows must be >= 1, got {max_windows}, {step_windows}")
        self.max_windows = max_windows
        self.step_windows = step_windows
        self.nice = nice
        self.refiner = refiner
        self.selector = selector
        self.saver = saver
        self.clock = clock
        self.keep_reports = keep_reports
        self.stats = WorkerStats()
        self.dropped = 0
        """Candidates replaced by a newer one before the worker took them."""
        self._cond = threading.Condition()
        self._item: Candidate | None = None
        self._busy = False
        self._working = False
        """True while the worker thread runs code (not waiting for a candidate or a frame's window)."""
        self._stop = False
        self._deadline: Deadline | None = None
        self._thread = threading.Thread(target=self._run, name="refine", daemon=True)
        self._thread.start()

    # -- called from the localization thread ---------------------------------------------------
    def submit(self, c: Candidate) -> None:
        with self._cond:
            self.stats.candidates += 1
            if self._item is not None:
                self.dropped += 1
            self._item = c
            self._cond.notify_all()

    def preempt(self) -> None:
        """Stop the running batch at its next step boundary (the next frame is being localized)."""
        with self._cond:
            if self._deadline is not None:
                self._deadline.preempt()

    def wait_parked(self, timeout: float | None = None) -> bool:
        """Wait until the worker thread is not running code (after ``preempt``: the end of its current piece).
        Paced sessions call it before each localization, so nothing of refinement runs beside it."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._working, timeout)

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Wait until the worker has nothing queued or running (paced replays use it)."""
        with self._cond:
            return self._cond.wait_for(lambda: self._item is None and not self._busy, timeout)

    def close(self, timeout: float = 30.0, before_save: Callable[[], bool] | None = None) -> None:
        """Finish the running batch, stop the thread, run ``before_save`` (True if it changed the map), and save the
        map a last time (if saving)."""
        with self._cond:
            self._stop = True
            if self._deadline is not None:
                self._deadline.preempt()
            self._cond.notify_all()
        self._thread.join(timeout)
        changed = before_save() if before_save is not None and not self._thread.is_alive() else False
        if self.saver is not None and (self.saver.dirty or changed):
            self.saver.save(self.refiner.snapshot())

    # -- the worker thread -----------------------------------------------------------------------
    def _run(self) -> None:
        if self.nice:
            lower_priority(self.nice)
        while True:
            with self._cond:
                while self._item is None and not self._stop:
                    self._cond.wait(0.1)
                if self._stop:
                    self._item = None
                    self._cond.notify_all()
                    return
                c, self._item, self._busy, self._working = self._item, None, True, True
            t0 = self.clock()
            try:
                self._handle(c)
            except Exception as e:  # a refinement bug must never take localization down with it
                self.stats.errors.append(f"{c.name}: {type(e).__name__}: {e}")
            self.stats.busy_ms.append(1000.0 * (self.clock() - t0))
            with self._cond:
                self._busy = self._working = False
                self._cond.notify_all()

    def _handle(self, c: Candidate) -> None:
        deadline = Deadline(c.deadline_at, self.clock)
        if deadline.expired():
            self.stats.late += 1
            return
        coverage = None
        if c.cell_depth is not None and self.selector.last_pose is not None and self.refiner.count():
            depth, k_input = c.cell_depth()
            coverage = projected_coverage(self.refiner.map.means, c.pose, k_input, depth)
        if not self.selector.consider(c.pose, c.inliers, c.tracking, coverage, c.inlier_ratio):
            return
        with self._cond:
            self._deadline = deadline
            if self._stop:
                deadline.preempt()
        try:
            rep = self._drive(c.make_keyframe(), deadline)
        finally:
            with self._cond:
                self._deadline = None
        self.stats.overrun_ms.append(max(0.0, 1000.0 * (self.clock() - self._window_end)))
        if len(self.stats.reports) < self.keep_reports:
            self.stats.reports.append(rep)
        if rep.committed:
            self.selector.accept(c.pose)
            if self.saver is not None:
                self.saver.mark_dirty()
                self.saver.maybe_save(self.refiner.snapshot())

    def _drive(self, kf: Keyframe, deadline: Deadline) -> BatchReport:
        """Run the refiner's batch for ``kf``, carrying it into later frames' windows when a piece does not fit."""
        rep = BatchReport(name=kf.name, outcome="no_time")
        gen = self.refiner.batch(kf, rep)
        self._window_end = deadline.at
        window_s = deadline.remaining()
        self.stats.window_work_ms.append(0.0)
        try:
            kind, est, reserve = next(gen)
            while True:
                cost = est.predict()
                # The reserve (what must follow) matters only in the last window: required work (the guard, tile
                # renders) waits for later windows like any other piece.
                last = rep.windows >= self.max_windows
                ok = deadline.allows(cost, reserve if last else 0.0)
                if not ok and kind != "option":
                    # Wait for the next frame's window only for work that would fit in a whole window: a step that
                    # never fits ends the optimisation now (the batch goes on to its guard); required work larger
                    # than every window seen so far abandons the batch.
                    if kind == "step" and (last or rep.windows >= self.step_windows or cost > window_s):
                        rep.stopped_by_deadline = True
                        kind, est, reserve = grant(gen, False, est, self.clock)
                        continue
                    if kind == "must" and (last or (rep.windows > 1 and cost > window_s)):
                        return self.refiner.abandon(gen, rep)
                    nxt = self._next_window()
                    if nxt is None:
                        return self.refiner.abandon(gen, rep)
                    deadline = nxt
                    window_s = max(window_s, deadline.remaining())
                    rep.windows += 1
                    self.stats.window_work_ms.append(0.0)
                    continue
                t_piece, name = self.clock(), est.name or kind
                try:
                    kind, est, reserve = grant(gen, ok, est, self.clock)
                finally:
                    if ok:
                        now = self.clock()
                        spill = max(0.0, 1000.0 * (now - deadline.at))
                        self.stats.piece_spill_ms.append(spill)
                        self.stats.window_work_ms[-1] += 1000.0 * (now - t_piece)
                        if spill > 0 and len(self.stats.late_pieces) < 200:
                            self.stats.late_pieces.append((name, 1000.0 * cost, 1000.0 * (now - t_piece), spill))
        except StopIteration:
            return rep

    def _next_window(self) -> Deadline | None:
        """The deadline of the next frame (waiting for it); None when the worker is stopping."""
        while True:
            with self._cond:
                self._working = False
                self._cond.notify_all()
                while self._item is None and not self._stop:
                    self._cond.wait(0.1)
                self._working = True
                if self._stop:
                    return None
                c, self._item = self._item, None
                self.stats.absorbed += 1
                d = Deadline(c.deadline_at, self.clock)
                if d.expired():
                    continue
                self._deadline = d
                self._window_end = d.at
                return d
