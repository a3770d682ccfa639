"""Replay a posed scene split through the edge runtime: `acesplat eval`'s accuracy keys plus per-stage timing
statistics."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from acesplat.core.geometry import pose_error
from acesplat.core.metrics import FrameResult, accuracy_summary, timing_stats
from acesplat.core.scene import TEST, split_folder
from edge.inference import runtime_info
from edge.loop import RunStats, run_loop
from edge.runtime import STAGES, EdgeLocalizer, FrameOutcome
from edge.sources import ReplaySource


def timing_summary(outcomes: Sequence[FrameOutcome], stages: Sequence[str] = STAGES) -> dict:
    """stage -> {mean, p50, p90, p95, p99, max} in milliseconds."""
    return {s: timing_stats([o.times_ms[s] for o in outcomes]) for s in stages}


def frame_result(o: FrameOutcome) -> FrameResult:
    if o.gt_pose is None:
        raise ValueError("frame has no ground-truth pose")
    res = o.result
    if res is not None and res.T_c2w is not None:
        t, r = pose_error(res.T_c2w, o.gt_pose)
    else:
        t, r = float("inf"), float("inf")
    pose = None if res is None else res.T_c2w
    return FrameResult(
        o.name, bool(res is not None and res.localized), t, r, o.record.inliers, o.times_ms["total"], pose
    )


def summarize(outcomes: Sequence[FrameOutcome], stats: RunStats | None = None) -> dict:
    """The replay JSON: accuracy_summary keys, timing_ms per stage, how the poses were made (tracked, scr,
    reanchors: edge.tracking.MODES; resets; fallbacks from tracking to SCR and their reasons; SCR starts solved again
    at full size), the loop's counters."""
    s = accuracy_summary([frame_result(o) for o in outcomes])
    s["timing_ms"] = timing_summary(outcomes)
    tried = [o.alignment for o in outcomes if o.alignment is not None]
    if tried:
        s["keyframe_alignment"] = {k: tried.count(k) for k in sorted(set(tried))}
    modes = [o.mode for o in outcomes]
    s["tracked"] = modes.count("tracked")
    s["scr"] = modes.count("scr")
    s["reanchors"] = modes.count("reanchor")
    s["resets"] = sum(o.reset for o in outcomes)
    s["full_size_retries"] = sum(o.retried for o in outcomes)
    fell = [o.fallback for o in outcomes if o.fallback is not None]
    s["fallbacks"] = len(fell)
    s["fallback_reasons"] = {k: fell.count(k) for k in sorted(set(fell))}
    if stats is not None:
        s["skipped"] = stats.skipped
        s["skipped_frames"] = stats.skipped_frames
        s["out_of_order"] = stats.out_of_order
        s["repeated"] = stats.repeated
        s["interrupted"] = stats.interrupted
    return s


def replay_split(
    localizer: EdgeLocalizer,
    scene: str | Path,
    split: str = TEST,
    progress: Callable[[int, int], None] | None = None,
    overlap: bool = False,
) -> dict:
    """Localize every frame of ``scene``/``split`` in order (a sequence: the localizer tracks between frames when
    it was made with tracking) as fast as possible and compare with its poses (the summary also names precision,
    input size, provider, onnxruntime version, CPU ISA (edge.inference.runtime_info), whether it tracked, whether the
    next frame was prepared while one was solved (``overlap``, edge.loop) and the poses a second of the run)."""
    source = ReplaySource(split_folder(scene, split, need_poses=True))
    n = len(source)
    outcomes: list[FrameOutcome] = []

    def keep(o: FrameOutcome) -> None:
        outcomes.append(o.without_data())
        if progress:
            progress(len(outcomes), n)

    stats = run_loop(source, localizer, keep, overlap=overlap)
    out = summarize(outcomes, stats)
    out["overlap"] = overlap
    out["threads"] = localizer.session.threads
    out["spinning"] = localizer.session.spinning
    out["seconds"] = stats.seconds
    out["poses_per_s"] = stats.fps
    out["precision"] = localizer.precision
    out["input_size"] = list(localizer.input_size)
    out["scr_size"] = list(localizer.scr_size)
    out["encoder_rank"] = localizer.bundle.encoder_rank
    out["tracking_enabled"] = localizer.tracker is not None
    out["align_warp"] = localizer.align_config.warp if localizer.keyframes is not None else None
    out["align_matcher"] = localizer.align_config.matcher if localizer.keyframes is not None else None
    out.update(runtime_info(localizer.session.provider))
    return out
