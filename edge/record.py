"""`record`: write what a source delivers in the layout ``replay:`` reads back (acesplat.core.scene.write_capture:
images, calibrations and, when the source has them, ground-truth poses; plus timestamps.txt and distortion.txt).

With ``record_mcap`` the same goes to one MCAP file instead (edge.foxglove_tap; ``replay:PATH.mcap``).

Every file is written atomically and ``timestamps.txt`` is rewritten after each frame, so an interrupted recording
is a valid, shorter recording. Images are stored as captured (still distorted) so replay applies the same
correction as live.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from acesplat.core.atomic import write_text
from acesplat.core.errors import InputError
from acesplat.core.scene import remove_calibrations, write_capture
from edge.loop import reconnect_with_backoff
from edge.sources import (
    DISTORTION_FILE,
    TIMESTAMPS_FILE,
    FrameSource,
    SourceDisconnected,
    SourceFrame,
    UnreadableFrame,
)


@dataclass
class RecordStats:
    frames: int = 0
    skipped: int = 0
    disconnects: int = 0
    interrupted: bool = False
    without_intrinsics: int = 0
    names: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        return {
            "frames": self.frames,
            "skipped": self.skipped,
            "disconnects": self.disconnects,
            "interrupted": self.interrupted,
            "without_intrinsics": self.without_intrinsics,
        }


def _check_out(out: Path) -> None:
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(out, "output folder exists and is not empty")


def record(
    source: FrameSource,
    out: str | Path,
    max_frames: int | None = None,
    progress: Callable[[int], None] | None = None,
    stop=None,
) -> RecordStats:
    """Copy frames from ``source`` into ``out`` until it ends, ``max_frames`` are written, or Ctrl-C."""
    out = Path(out)
    _check_out(out)
    out.mkdir(parents=True, exist_ok=True)
    stamps: list[str] = []
    wrote_dist = False

    def write(f: SourceFrame, stats: RecordStats) -> None:
        nonlocal wrote_dist
        name = f"{stats.frames:06d}"
        write_capture(out, name, f.image, None if f.intrinsics is None else f.intrinsics.K, f.gt_pose)
        if f.distortion is not None and np.any(np.asarray(f.distortion) != 0) and not wrote_dist:
            write_text(
                out / DISTORTION_FILE, " ".join(f"{v:.10g}" for v in np.asarray(f.distortion).reshape(-1)) + "\n"
            )
            wrote_dist = True
        stamps.append(f"{name} {f.timestamp:.6f}")
        write_text(out / TIMESTAMPS_FILE, "\n".join(stamps) + "\n")
        stats.names.append(name)

    stats = _copy_frames(source, write, max_frames, progress, stop)
    if 0 < stats.without_intrinsics < stats.frames:
        # replay pairs calibration files with images by count; a partial set would not read back
        remove_calibrations(out)
        stats.without_intrinsics = stats.frames
    return stats


def record_mcap(
    source: FrameSource,
    path: str | Path,
    max_frames: int | None = None,
    progress: Callable[[int], None] | None = None,
    stop=None,
) -> RecordStats:
    """Copy frames from ``source`` into one MCAP file (edge.foxglove_tap.McapRecorder: lossless images, their
    calibration and true pose) that ``replay:PATH.mcap`` reads back; the file appears at ``path`` when the
    recording ends (source end, ``max_frames``, Ctrl-C, an error), from ``PATH.partial``."""
    from edge.foxglove_tap import McapRecorder

    try:
        rec = McapRecorder(path)
    except BaseException:
        source.close()
        raise

    def write(f: SourceFrame, stats: RecordStats) -> None:
        rec.write(f)
        stats.names.append(f"{stats.frames:06d}")

    try:
        return _copy_frames(source, write, max_frames, progress, stop)
    finally:
        rec.close()  # an error mid-recording still leaves a valid, shorter file


def _copy_frames(
    source: FrameSource,
    write: Callable[[SourceFrame, RecordStats], None],
    max_frames: int | None,
    progress: Callable[[int], None] | None,
    stop,
) -> RecordStats:
    """Read frames (skipping unreadable ones, reconnecting a vanished device) and ``write`` each until the source
    ends, ``max_frames`` or Ctrl-C; closes the source."""
    stats = RecordStats()
    stop = stop or threading.Event()
    try:
        while not stop.is_set() and (not max_frames or stats.frames < max_frames):
            try:
                f = source.read()
            except UnreadableFrame:
                stats.skipped += 1
                continue
            except SourceDisconnected:
                stats.disconnects += 1
                if not reconnect_with_backoff(source, stop):
                    break
                continue
            if f is None:
                break
            write(f, stats)
            if f.intrinsics is None:
                stats.without_intrinsics += 1
            stats.frames += 1
            if progress:
                progress(stats.frames)
    except KeyboardInterrupt:
        stats.interrupted = True
    finally:
        source.close()
    return stats
