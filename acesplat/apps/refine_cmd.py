"""What the edge commands call for --refine: start a session from the flags, its one summary line, and the verdict
on a run that harmed the map."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import typer

from acesplat.core.errors import InputError
from edge.refine.session import RefineOptions, RefineSession, start_refinement

HARMED_EXIT = 1
"""Exit code of a run whose refinement left an evaluated view worse than the loaded map (its outputs are written
first); bad input stays 2."""


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


def close_session(session: RefineSession, say: Callable[[str], None]) -> dict:
    """End a refinement session, saying first that its witnesses are being checked (seconds on a large map)."""
    n = len(session.witness_pool.all())
    if n:
        say(f"refine: checking {n} witness views against the map as loaded before the last save")
    return session.close()


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
        f"{r['gaussians_final']} Gaussians (+{r['gaussians_added']}), {r['dropped']} dropped; {witness_text(r)}"
        "refinement work per frame "
        f"window p50 {t['window']['p50']:.1f} p95 {t['window']['p95']:.1f} ms"
    )


def witness_text(r: dict) -> str:
    """'N witnesses, M restored; ' from a refinement report (edge/refine/witness.py), '' without witnesses."""
    w = r.get("witness") or {}
    if not w.get("witnesses"):
        return ""
    back = ", the loaded map kept" if w.get("fell_back_to_loaded") else ""
    return f"{w['witnesses']} witnesses checked, {w['harmed_before']} had lost and were restored{back}; "


def harm_line(r: dict) -> str | None:
    """The line saying a refinement run harmed the map (an evaluated view's PSNR fell below the loaded map's by more
    than the tolerance; edge/refine/session.py's harm_report), or None when no view fell."""
    if not r.get("failed"):
        return None
    w = r["harmed"][0]
    return (
        f"refine FAILED: PSNR fell on {r['views_harmed']} of {r['psnr_views']} views by more than "
        f"{r['harm_tolerance_db']:g} dB against the map as loaded (worst: view {w['view']}, "
        f"{w['psnr_before']:.2f} -> {w['psnr_after']:.2f} dB)"
    )


def exit_if_harmed(r: dict, print_line: Callable[[str], None]) -> None:
    """Print the failure line and exit with HARMED_EXIT when the run harmed the map; nothing otherwise."""
    line = harm_line(r)
    if line is not None:
        print_line(line)
        raise typer.Exit(HARMED_EXIT)
