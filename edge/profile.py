"""`profile`: per-stage latency statistics and FPS, warm-up excluded, FP32 and INT8 side by side on the same frames.

Frames are read (and timed) once, then replayed from memory for each precision, so the two
precisions see identical inputs and the capture stage is the same measured decode time for both.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from acesplat.core.bundle import Bundle
from acesplat.core.config import knob, knob_default
from acesplat.core.errors import InputError
from acesplat.core.machine import cpu_model
from edge.inference import SessionSettings, runtime_info
from edge.replay import timing_summary
from edge.runtime import EdgeLocalizer, FrameOutcome, PnPSettings
from edge.sources import FrameSource, SourceFrame, UnreadableFrame


@dataclass
class ProfileOptions:
    """How many frames `profile` times."""

    frames: int = knob(50, "Timed frames (after the warm-up).")
    warmup: int = knob(5, "Warm-up frames, excluded from the statistics.")


def machine_header(
    bundle: Bundle, precisions: Sequence[str], threads: int, provider: str = knob_default(SessionSettings, "provider")
) -> dict:
    """The machine, libraries, execution provider, CPU ISA and models a profile was measured with."""
    files = {f.role: f.sha256 for f in bundle.files.values()}
    try:
        load = os.getloadavg()
    except OSError:
        load = (float("nan"),) * 3
    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "threads": threads,
        "load_average": [round(v, 2) for v in load],
        **runtime_info(provider),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "python": platform.python_version(),
        "model_sha256": {p: files.get(f"scr_{p}") for p in precisions},
        "input_size": list(bundle.input_size),
        "encoder_rank": bundle.encoder_rank,
        "precision": list(precisions),
    }


def read_frames(source: FrameSource, n: int) -> list[tuple[SourceFrame, float]]:
    """Up to ``n`` frames with their measured capture times (ms); unreadable frames are skipped."""
    frames = []
    while len(frames) < n:
        t0 = time.perf_counter()
        try:
            f = source.read()
        except UnreadableFrame:
            continue
        if f is None:
            break
        frames.append((f, (time.perf_counter() - t0) * 1000.0))
    source.close()
    return frames


def profile_precision(
    localizer: EdgeLocalizer,
    frames: Sequence[tuple[SourceFrame, float]],
    warmup: int,
    progress: Callable[[str, float, dict], None] | None = None,
) -> dict:
    """stages (stage -> statistics over the timed frames), fps, precision, input_size."""
    if len(frames) <= warmup:
        raise InputError(None, f"profiling needs more than {warmup} frames (warm-up), the source gave {len(frames)}")
    timed: list[FrameOutcome] = []
    localized = 0
    for i, (f, cap_ms) in enumerate(frames):
        out = localizer.localize(f, cap_ms)
        if i >= warmup:
            timed.append(out.without_data())
            localized += bool(out.result is not None and out.result.localized)
        if progress:
            progress(f"profile {localizer.precision}", (i + 1) / len(frames), {"frame": i + 1})
    stages = timing_summary(timed)
    return {
        "stages": stages,
        "fps": 1000.0 / stages["total"]["mean"] if stages["total"]["mean"] > 0 else 0.0,
        "precision": localizer.precision,
        "input_size": list(localizer.input_size),
        "frames": len(timed),
        "warmup_frames": warmup,
        "localized": localized,
    }


def run_profile(
    bundle: Bundle,
    source: FrameSource,
    precisions: Sequence[str],
    frames: int,
    threads: int,
    warmup: int = knob_default(ProfileOptions, "warmup"),
    pnp: PnPSettings | None = None,
    progress: Callable[[str, float, dict], None] | None = None,
    attach: Callable[[EdgeLocalizer], Callable[[], dict] | None] | None = None,
    provider: str = knob_default(SessionSettings, "provider"),
) -> dict:
    """Profile each precision on the same frames; one run's JSON (keys stages, fps, precision, input_size).

    ``attach`` (edge refinement) hooks each localizer before it runs and returns what adds a run's 'refine' report."""
    data = read_frames(source, frames + warmup)
    runs = []
    for p in precisions:
        loc = EdgeLocalizer(bundle, p, threads, pnp, provider=provider)
        finish = attach(loc) if attach is not None else None
        runs.append(profile_precision(loc, data, warmup, progress))
        if finish is not None:
            runs[-1]["refine"] = finish()
    header = machine_header(bundle, precisions, threads, provider)
    if len(runs) == 1:
        return {**runs[0], "header": header}
    if any("refine" in r for r in runs):
        refine = {r["precision"]: r["refine"] for r in runs if "refine" in r}
    else:
        refine = None
    out = {
        "stages": {r["precision"]: r["stages"] for r in runs},
        "fps": {r["precision"]: r["fps"] for r in runs},
        "precision": [r["precision"] for r in runs],
        "input_size": runs[0]["input_size"],
        "localized": {r["precision"]: r["localized"] for r in runs},
        "frames": runs[0]["frames"],
        "warmup_frames": warmup,
        "header": header,
    }
    if refine is not None:
        out["refine"] = refine
    int8 = [p for p in out["precision"] if p.startswith("int8")]
    if "fp32" in out["fps"] and int8:
        a, b = out["stages"]["fp32"]["inference"]["p50"], out["stages"][int8[0]]["inference"]["p50"]
        out["int8_inference_speedup_p50"] = a / b if b > 0 else None
    return out
