"""What the edge commands call for --refine: start a session from the flags, and its one summary line."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from acesplat.core.errors import InputError
from edge.refine.session import RefineOptions, RefineSession, start_refinement


def refine_session(
    enabled: bool,
    loc,
    b,
    budget_ms: float,
    save_splat: Path | None,
    warn: Callable[[str], None],
    evaluate: bool = False,
) -> RefineSession | None:
    """Refinement in what localization leaves of each frame's budget (paced, see edge/refine/session.py), or None
    when off or the bundle has no Gaussians."""
    if not enabled:
        return None
    if budget_ms <= 0:
        raise InputError(None, f"--budget-ms must be positive, got {budget_ms}")
    opts = RefineOptions(budget_ms=budget_ms, save_path=save_splat, evaluate=evaluate)
    return start_refinement(loc, b, opts, warn)


def refine_line(r: dict) -> str:
    """One summary line of a refinement run (edge/refine/session.py's report)."""
    t = r["timing_ms"]
    psnr = (
        f"PSNR {r['psnr_before']:.2f} -> {r['psnr_after']:.2f} dB over {r['psnr_views']} views; "
        if "psnr_before" in r
        else ""
    )
    return (
        f"refine: {psnr}{r['keyframes']} keyframes ({r['keyframes_committed']} committed, {r['keyframes_rolled_back']} "
        f"rolled back), {r['steps']} steps (p50 {t['step']['p50']:.1f} ms), {r['gaussians_initial']} -> "
        f"{r['gaussians_final']} Gaussians (+{r['gaussians_added']}), {r['dropped']} dropped; "
        "refinement work per frame "
        f"window p50 {t['window']['p50']:.1f} p95 {t['window']['p95']:.1f} ms"
    )
