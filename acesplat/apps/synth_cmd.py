"""`acesplat synth`: write the built-in synthetic scene in the ACE layout."""

from __future__ import annotations

from pathlib import Path

import typer

from acesplat.apps.support import CountProgress, one_line_errors, option, parse_size, report_json
from acesplat.core.config import knob_default, knob_help
from acesplat.core.errors import InputError
from acesplat.synth.dataset import SynthConfig, synthesize


@one_line_errors
def synth_command(
    out: Path = typer.Argument(..., help="Scene folder to create (must be new or empty unless --overwrite)."),
    seed: int = option(SynthConfig, "seed", "--seed"),
    frames: int = option(SynthConfig, "train_frames", "--frames"),
    test_frames: int = option(SynthConfig, "test_frames", "--test-frames"),
    size: str = typer.Option(
        "x".join(map(str, knob_default(SynthConfig, "size"))), "--size", help=knob_help(SynthConfig, "size")
    ),
    supersample: int = option(SynthConfig, "supersample", "--supersample", min=1, max=4),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing non-empty OUT."),
    json_out: Path | None = typer.Option(None, "--json", help="Write the summary (counts, timings, room) as JSON."),
) -> None:
    """Render the built-in synthetic room (train and test passes, with depth) into the ACE layout."""
    hw = parse_size(size)
    for flag, n in (("--frames", frames), ("--test-frames", test_frames)):
        if n < 1:
            raise InputError(None, f"{flag} must be at least 1, got {n}")
    with CountProgress("rendering") as progress:
        summary = synthesize(
            out, seed=seed, train_frames=frames, test_frames=test_frames, size=hw, supersample=supersample,
            overwrite=overwrite, progress=progress,
        )  # fmt: skip
    h, w = summary["size"]
    print(
        f"synthesized {summary['train_frames']} train + {summary['test_frames']} test frames ({h}x{w}, seed {seed}) "
        f"-> {summary['out_dir']} in {summary['seconds']:.1f} s"
    )
    rx, ry, rz = summary["room_size_m"]
    print(
        f"  room {rx:.1f} x {ry:.1f} x {rz:.1f} m, {summary['objects']} objects, {summary['photos']} photographs; "
        f"render {summary['render_ms_per_frame']:.0f} ms/frame, write {summary['write_ms_per_frame']:.0f} ms/frame"
    )
    report_json(json_out, summary)
