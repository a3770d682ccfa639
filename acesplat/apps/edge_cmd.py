"""`acesplat-edge localize | replay | profile | record | check`: thin wrappers over the runtime modules."""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from acesplat.align.flow_pnp import DENSE_ALIGN, KEYFRAME_ALIGN, MATCHERS, WARPS, AlignConfig
from acesplat.align.keyframe_align import PreciseSettings
from acesplat.apps.refine_cmd import close_session, exit_if_harmed, refine_line, refine_session
from acesplat.apps.support import PhaseProgress, one_line_errors, option, report_json, stop_on_signals
from acesplat.core.bundle import PRECISION_ROLES, Bundle, load_bundle
from acesplat.core.config import knob_default, knob_help
from acesplat.core.errors import InputError
from acesplat.core.geometry import matrix_to_quat
from acesplat.core.pose import TrackingState
from edge.calibration import read_calibration_file
from edge.foxglove_tap import FoxgloveSettings
from edge.inference import SessionSettings, check_provider, default_threads, runtime_info
from edge.int8_check import Int8CheckConfig
from edge.loop import LoopEvent, LoopSettings, overlap_for, overlap_threads, run_loop
from edge.profile import ProfileOptions
from edge.refine.session import RefineOptions
from edge.runtime import STAGES, EdgeLocalizer, FrameOutcome, FrameTap, PnPSettings
from edge.sources import SourceOptions, open_source
from edge.tracking import TrackingConfig
from firmware_bridge.sink import SinkConfig

console = Console(stderr=True)
THREADS_HELP = "onnxruntime intra-op threads (default: all cores; with --overlap, all but one)."
OVERLAP_HELP = knob_help(LoopSettings, "overlap")


def _threads(threads: int | None, overlap: bool, refine: bool) -> int | None:
    """The onnxruntime threads of a run; --overlap leaves a core to the solving thread and refuses --refine (both
    want the time between frames)."""
    if not overlap:
        return threads
    if refine:
        raise InputError(None, "--overlap cannot run with --refine: refinement uses the time between frames")
    return threads or overlap_threads()


def open_bundle(path: Path, precisions: list[str], align: bool = False) -> Bundle:
    """Verify the manifest and the files that will be read: the models that run, the keyframes with --align or
    tracking (with --align a bundle without them is refused, in one line, when EdgeLocalizer reads them)."""
    roles = [PRECISION_ROLES[p] for p in precisions]
    if align:
        from acesplat.core.bundle import ROLE_KEYFRAMES

        roles.append(ROLE_KEYFRAMES)
    b = load_bundle(path, verify=True, roles=roles)
    for p in precisions:
        b.scr_model(p)
    return b


def _pnp(method: str | None, min_inliers: int | None) -> PnPSettings:
    from acesplat.core.pnp import PNP_METHODS

    s = PnPSettings()
    if method is not None:
        if method not in PNP_METHODS:
            raise InputError(None, f"--pnp must be one of {', '.join(PNP_METHODS)}, got {method!r}")
        s.method = method
    if min_inliers is not None:
        if min_inliers < 4:
            raise InputError(None, f"--min-inliers must be at least 4, got {min_inliers}")
        s.min_inliers = min_inliers
    return s


def _tracking(on: bool, reanchor_every: int) -> TrackingConfig | None:
    """The tracking settings of --tracking/--no-tracking and --reanchor-every (None: frames solved alone)."""
    if reanchor_every < 1:
        raise InputError(None, f"--reanchor-every must be at least 1, got {reanchor_every}")
    return TrackingConfig(reanchor_every=reanchor_every) if on else None


def _size_text(loc: EdgeLocalizer) -> str:
    """The network input size, and the SCR size where --align runs SCR smaller."""
    h, w = loc.input_size
    if loc.scr_size == loc.input_size:
        return f"{h}x{w}"
    return f"{h}x{w}, SCR at {loc.scr_size[0]}x{loc.scr_size[1]}"


def _scr_side(side: int) -> int:
    """--align-scr-side, checked."""
    if side < 8:
        raise InputError(None, f"--align-scr-side must be at least 8 pixels, got {side}")
    return side


def _align_config(warp: str, matcher: str) -> AlignConfig:
    """The keyframe alignment of --align with --align-warp's warp and --align-matcher's matcher."""
    if warp not in WARPS:
        raise InputError(None, f"--align-warp must be one of {', '.join(WARPS)}, got {warp!r}")
    if matcher not in MATCHERS:
        raise InputError(None, f"--align-matcher must be one of {', '.join(MATCHERS)}, got {matcher!r}")
    if matcher == "sparse":
        if warp != knob_default(AlignConfig, "warp"):
            raise InputError(None, f"--align-warp {warp} warps for the dense matcher; add --align-matcher dense")
        return KEYFRAME_ALIGN
    return replace(DENSE_ALIGN, warp=warp)


def _warn(msg: str) -> None:
    console.print(f"[yellow]{msg}[/yellow]")


ALIGN_HELP = (
    "Refine each pose against the bundle's keyframes (export --keyframes): "
    "centimetre poses where SCR alone is a few cm off; SCR then runs smaller (--align-scr-side), the alignment "
    "adds about 50 ms (bench/align.md)."
)
FOXGLOVE_HELP = "Serve a live Foxglove WebSocket on this port (Foxglove's usual: 8765; 0 picks a free one)."
MCAP_HELP = "Log the same channels to this MCAP file (written as PATH.partial, renamed into place at the end)."


def _foxglove_tap(loc: EdgeLocalizer, port: int | None, mcap: Path | None, host: str):
    """The Foxglove tap (live server and/or MCAP log) on ``loc``, or None without --foxglove/--mcap."""
    if port is None and mcap is None:
        return None
    from edge.foxglove_tap import FoxgloveTap

    tap = FoxgloveTap(port, mcap, FoxgloveSettings(host=host))
    loc.add_tap(tap)
    if tap.port is not None:
        console.print(f"Foxglove live view: ws://{host}:{tap.port} (Foxglove: Open connection > Foxglove WebSocket)")
    return tap


def stage_table(title: str, stages_by_run: dict[str, dict], fps: dict[str, float]) -> Table:
    t = Table(title=title)
    t.add_column("stage (ms)")
    runs = list(stages_by_run)
    for r in runs:
        for k in ("mean", "p50", "p90", "p95", "p99", "max"):
            t.add_column(f"{r} {k}" if len(runs) > 1 else k, justify="right")
    for s in STAGES:
        t.add_row(
            s, *[f"{stages_by_run[r][s][k]:.2f}" for r in runs for k in ("mean", "p50", "p90", "p95", "p99", "max")]
        )
    t.add_row("fps", *[x for r in runs for x in (f"{fps[r]:.1f}", "", "", "", "", "")])
    return t


def frame_text(out: FrameOutcome) -> str:
    rec = out.record
    if np.all(np.isfinite(rec.T_c2w)):
        p = rec.T_c2w[:3, 3]
        q = matrix_to_quat(rec.T_c2w[:3, :3])
        pose = f"xyz {p[0]:+8.3f} {p[1]:+8.3f} {p[2]:+8.3f}  q {q[0]:+.4f} {q[1]:+.4f} {q[2]:+.4f} {q[3]:+.4f}"
    else:
        pose = "no pose" + " " * 60
    ms = out.times_ms
    return (
        f"{rec.frame_id:6d} {TrackingState(rec.state).name:8s} {pose}  inl {rec.inliers:4d}  "
        f"ms cap {ms['capture']:5.1f} pre {ms['preprocess']:5.1f} inf {ms['inference']:6.1f} "
        f"pnp {ms['pnp']:5.1f} aln {ms['align']:6.1f} tot {ms['total']:6.1f}"
    )


@one_line_errors
def localize_command(
    bundle: Path = typer.Argument(..., help="Bundle directory from `acesplat export`."),
    source: str = typer.Option(..., help="replay:DIR, video:FILE, camera:N or oak[:crop|stretch|letterbox]."),
    intrinsics: Path | None = typer.Option(None, help="Calibration file (ACE txt, JSON, or OpenCV YAML/XML)."),
    int8: bool = typer.Option(False, "--int8", help="Run the bundle's INT8 model."),
    json_lines: Path | None = typer.Option(None, "--json-lines", help="Write one JSON object per frame here."),
    frames: int | None = typer.Option(None, help="Stop after this many frames."),
    realtime: bool = option(SourceOptions, "realtime"),
    threads: int | None = typer.Option(None, help=THREADS_HELP),
    overlap: bool | None = typer.Option(None, "--overlap/--no-overlap", help=OVERLAP_HELP),
    spinning: bool = option(SessionSettings, "spinning", "--spinning/--no-spinning"),
    provider: str = option(SessionSettings, "provider"),
    pnp: str | None = option(PnPSettings, "method", "--pnp", default=None),
    min_inliers: int | None = option(PnPSettings, "min_inliers", default=None),
    quiet: bool = typer.Option(False, help="No per-frame lines, only the summary."),
    serial: str | None = typer.Option(None, help="Send poses to this serial port (device path or pyserial URL)."),
    baud: int = option(SinkConfig, "baud"),
    protocol: str = option(SinkConfig, "protocol"),
    rate: float | None = typer.Option(None, help="Cap on poses per second sent over --serial."),
    json_out: Path | None = typer.Option(None, "--json", help="Write the run summary here."),
    refine: bool = typer.Option(
        False, "--refine", help="Refine the bundle's Gaussians from keyframes on a second thread."
    ),
    budget_ms: float = option(RefineOptions, "budget_ms", "--budget-ms"),
    save_splat: Path | None = option(RefineOptions, "save_path", "--save-splat"),
    align: bool = typer.Option(False, "--align", help=ALIGN_HELP),
    align_warp: str = option(AlignConfig, "warp", "--align-warp"),
    align_matcher: str = option(AlignConfig, "matcher", "--align-matcher"),
    align_scr_side: int = option(PreciseSettings, "scr_short_side", "--align-scr-side"),
    tracking: bool = option(TrackingConfig, "enabled", "--tracking/--no-tracking"),
    reanchor_every: int = option(TrackingConfig, "reanchor_every", "--reanchor-every"),
    foxglove: int | None = typer.Option(None, "--foxglove", metavar="PORT", help=FOXGLOVE_HELP),
    foxglove_host: str = option(FoxgloveSettings, "host", "--foxglove-host"),
    mcap: Path | None = typer.Option(None, "--mcap", metavar="PATH", help=MCAP_HELP),
    skip_int8_check: bool = option(Int8CheckConfig, "skip", "--skip-int8-check"),
) -> None:
    """Localize frames from a live or recorded source; Ctrl-C ends with a summary."""
    stop_on_signals()
    check_provider(provider)
    b = open_bundle(bundle, ["int8" if int8 else "fp32"], align or tracking)
    calib = read_calibration_file(intrinsics) if intrinsics else None
    track = _tracking(tracking, reanchor_every)
    src = open_source(source, SourceOptions(calibration=calib, input_size=b.input_size, realtime=realtime))
    try:
        overlap = overlap_for(overlap, src.live, track is not None, refine)
        threads = _threads(threads, overlap, refine)
        precision = int8_gate(b, int8, skip_int8_check, threads, provider)
        loc = EdgeLocalizer(
            b,
            precision,
            threads,
            _pnp(pnp, min_inliers),
            align=align,
            provider=provider,
            tracking=track,
            align_config=_align_config(align_warp, align_matcher),
            scr_short_side=_scr_side(align_scr_side),
            spinning=spinning,
        )
    except BaseException:
        src.close()
        raise
    fox = _foxglove_tap(loc, foxglove, mcap, foxglove_host)
    refiner = refine_session(refine, loc, b, budget_ms, save_splat, _warn)
    log = None
    if json_lines is not None:
        from edge.outputs import JsonLinesTap

        log = JsonLinesTap(json_lines)
        loc.add_tap(log)
    bridge = None
    if serial is not None:
        from firmware_bridge.sink import open_sink

        bridge = BridgeTap(open_sink(serial, baud, protocol, rate))
        loc.add_tap(bridge)
    out_stream = sys.stdout
    modes = {"tracked": 0, "scr": 0, "reanchor": 0, "resets": 0, "fallbacks": 0}

    def on_outcome(out: FrameOutcome) -> None:
        modes[out.mode] += 1
        modes["resets"] += out.reset
        modes["fallbacks"] += out.fallback is not None
        if not quiet:
            out_stream.write(frame_text(out) + "\n")
            out_stream.flush()

    def on_event(e: LoopEvent) -> None:
        console.print(f"[yellow]{e.kind}[/yellow]: {e.detail}" + (f" (gap {e.gap_s:.1f} s)" if e.gap_s else ""))

    rt = runtime_info(provider)
    console.print(
        f"localizing {src.description} with {b.root} ({precision}, {_size_text(loc)}, "
        f"{loc.session.threads} threads{', overlapped' if overlap else ''}, PnP {loc.pnp.method}; "
        f"provider {provider}, onnxruntime {rt['onnxruntime']}, "
        f"ISA {' '.join(rt['cpu_isa']) or '-'}); Ctrl-C to stop"
    )
    try:
        stats = run_loop(src, loc, on_outcome, on_event, max_frames=frames, overlap=overlap)
    finally:
        if log is not None:
            log.close()
        bridge_stats = bridge.close() if bridge is not None else None
        refine_stats = close_session(refiner, console.print) if refiner is not None else None
        fox_stats = fox.close() if fox is not None else None
    summary = {"bundle": str(b.root), "source": src.description, "precision": precision, **rt, **stats.as_dict()}
    summary.update(threads=loc.session.threads, spinning=loc.session.spinning)
    summary.update(tracking_enabled=track is not None, reanchors=modes.pop("reanchor"), **modes)
    if fox_stats is not None:
        summary["foxglove"] = fox_stats
    if refine_stats is not None:
        summary["refine"] = refine_stats
        console.print(refine_line(refine_stats))
    if bridge_stats is not None:
        summary["bridge"] = bridge_stats
    ended = "interrupted" if stats.interrupted else "done"
    console.print(
        f"{ended}: {stats.frames} frames in {stats.seconds:.1f} s ({summary['fps']:.1f} fps), "
        f"{stats.tracking} tracking, "
        f"{stats.lost} lost ({modes['tracked']} poses tracked, {summary['reanchors']} re-anchors, "
        f"{modes['resets']} resets), {stats.dropped} dropped, {stats.skipped} unreadable skipped, "
        f"{stats.out_of_order + stats.repeated} out of order or repeated, "
        f"{stats.disconnects} disconnects ({stats.gap_s:.1f} s without frames)"
    )
    report_json(json_out, summary)


FPS_SMOOTHING = 0.2
"""Weight of the newest interval in the bridge's reported pose rate (about the last five poses)."""


class BridgeTap(FrameTap):
    """A localizer tap forwarding each pose to the firmware bridge's non-blocking sink; honours PAUSE/RESUME from the
    microcontroller (SET_RATE the sink applies itself) and reports LOST when the source disconnects."""

    def __init__(self, sink) -> None:
        self.sink = sink
        self.paused = threading.Event()
        self._last: float | None = None
        self._fps = 0.0

    def _rate(self) -> float:
        """Poses a second between the last frames (exponential average): with --overlap a pose's latency is
        longer than the time between poses, so the rate is measured, not inferred from the latency."""
        now = time.perf_counter()
        if self._last is not None and now > self._last:
            fps = 1.0 / (now - self._last)
            self._fps = fps if self._fps == 0.0 else FPS_SMOOTHING * fps + (1.0 - FPS_SMOOTHING) * self._fps
        self._last = now
        return self._fps

    def on_frame(self, out: FrameOutcome) -> None:
        from firmware_bridge.protocol import CommandCode, RuntimeState

        for ev in self.sink.poll_commands():
            if ev.command == CommandCode.PAUSE:
                self.paused.set()
            elif ev.command == CommandCode.RESUME:
                self.paused.clear()
        if self.paused.is_set():
            self.sink.update_status(state=RuntimeState.PAUSED)
            self._last = None  # the pause is no interval between poses
            return
        state = RuntimeState.TRACKING if out.record.state == TrackingState.TRACKING else RuntimeState.LOST
        fps = self._rate()
        self.sink.update_status(state=state, latency_ms=out.times_ms.get("total", 0.0), fps=fps)
        self.sink.submit(out.record)

    def on_event(self, e: LoopEvent) -> None:
        if e.kind != "disconnected":
            return
        from acesplat.core.pose import PoseRecord
        from firmware_bridge.protocol import RuntimeState

        self.sink.update_status(state=RuntimeState.LOST)
        self.sink.submit(PoseRecord(int(e.wall_time * 1e6), np.full((4, 4), np.nan), 0, TrackingState.LOST, 0.0, 0))

    def close(self) -> dict:
        """Close the sink; its counters."""
        self.sink.close()
        return self.sink.stats().as_dict()


@one_line_errors
def replay_command(
    bundle: Path = typer.Argument(..., help="Bundle directory."),
    scene: Path = typer.Argument(..., help="Scene folder in the ACE layout."),
    split: str = typer.Option("test", help="Split to replay."),
    int8: bool = typer.Option(False, "--int8", help="Run the bundle's INT8 model."),
    threads: int | None = typer.Option(None, help=THREADS_HELP),
    overlap: bool | None = typer.Option(None, "--overlap/--no-overlap", help=OVERLAP_HELP),
    spinning: bool = option(SessionSettings, "spinning", "--spinning/--no-spinning"),
    provider: str = option(SessionSettings, "provider"),
    pnp: str | None = option(PnPSettings, "method", "--pnp", default=None),
    json_out: Path | None = typer.Option(None, "--json", help="Write the numbers here."),
    refine: bool = typer.Option(
        False, "--refine", help="Refine the bundle's Gaussians from keyframes; report PSNR before/after."
    ),
    budget_ms: float = option(RefineOptions, "budget_ms", "--budget-ms"),
    save_splat: Path | None = option(RefineOptions, "save_path", "--save-splat"),
    align: bool = typer.Option(False, "--align", help=ALIGN_HELP),
    align_warp: str = option(AlignConfig, "warp", "--align-warp"),
    align_matcher: str = option(AlignConfig, "matcher", "--align-matcher"),
    align_scr_side: int = option(PreciseSettings, "scr_short_side", "--align-scr-side"),
    tracking: bool = option(TrackingConfig, "enabled", "--tracking/--no-tracking"),
    reanchor_every: int = option(TrackingConfig, "reanchor_every", "--reanchor-every"),
    foxglove: int | None = typer.Option(None, "--foxglove", metavar="PORT", help=FOXGLOVE_HELP),
    foxglove_host: str = option(FoxgloveSettings, "host", "--foxglove-host"),
    mcap: Path | None = typer.Option(None, "--mcap", metavar="PATH", help=MCAP_HELP),
    skip_int8_check: bool = option(Int8CheckConfig, "skip", "--skip-int8-check"),
) -> None:
    """Replay a posed split in order, tracking between frames as on a live source (--no-tracking: each frame
    alone): `acesplat eval`'s accuracy, per-stage timing statistics and how each pose was made."""
    stop_on_signals()
    from edge.replay import replay_split

    overlap = overlap_for(overlap, False, tracking, refine)  # files are read in step: no live source
    threads = _threads(threads, overlap, refine)
    check_provider(provider)
    b = open_bundle(bundle, ["int8" if int8 else "fp32"], align or tracking)
    precision = int8_gate(b, int8, skip_int8_check, threads, provider)
    track = _tracking(tracking, reanchor_every)
    loc = EdgeLocalizer(
        b,
        precision,
        threads,
        _pnp(pnp, None),
        align=align,
        provider=provider,
        tracking=track,
        align_config=_align_config(align_warp, align_matcher),
        scr_short_side=_scr_side(align_scr_side),
        spinning=spinning,
    )
    fox = _foxglove_tap(loc, foxglove, mcap, foxglove_host)
    refiner = refine_session(refine, loc, b, budget_ms, save_splat, _warn, evaluate=True)
    with PhaseProgress("replay ") as bar:
        try:
            s = replay_split(loc, scene, split, lambda i, n: bar("localize", i / n, {"frame": i}), overlap)
        finally:
            if refiner is not None:
                close_session(refiner, console.print)
            fox_stats = fox.close() if fox is not None else None
    if fox_stats is not None:
        s["foxglove"] = fox_stats
    if refiner is not None:
        s["refine"] = refiner.summary
        s["timing_ms"]["refine"] = refiner.summary["timing_ms"]["window"]
    t = Table(title=f"{Path(scene).name} / {split} ({precision}, {_size_text(loc)}, provider {provider})")
    keys = (
        "frames",
        "localized",
        "median_translation_m",
        "median_rotation_deg",
        "recall_5cm_5deg",
        "recall_10cm_5deg",
        "recall_25cm_2deg",
        "mean_ms",
    )
    for k in keys:
        t.add_column(k.replace("_", " "), justify="right")
    t.add_row(*["-" if s.get(k) is None else (f"{s[k]:.4g}" if isinstance(s[k], float) else str(s[k])) for k in keys])
    Console().print(t)
    Console().print(
        stage_table(
            "timing (ms)",
            {precision: s["timing_ms"]},
            {precision: s["poses_per_s"]},
        )
    )
    if s["tracking_enabled"]:
        console.print(
            f"tracking: {s['tracked']} tracked, {s['scr']} scr, {s['reanchors']} re-anchors "
            f"({s['fallbacks']} fallbacks from tracking: "
            f"{', '.join(f'{k} {v}' for k, v in s['fallback_reasons'].items()) or 'none'}), {s['resets']} resets"
        )
    if s.get("skipped"):
        console.print(f"[yellow]{s['skipped']} unreadable frames skipped[/yellow]: {', '.join(s['skipped_frames'])}")
    if s.get("out_of_order") or s.get("repeated"):
        console.print(
            f"[yellow]{s['out_of_order']} frames out of order and {s['repeated']} with a repeated timestamp "
            "not localized[/yellow]"
        )
    if "refine" in s:
        console.print(refine_line(s["refine"]))
    report_json(json_out, s)
    if "refine" in s:
        exit_if_harmed(s["refine"], lambda line: console.print(f"[red]{line}[/red]", soft_wrap=True))


@one_line_errors
def profile_command(
    bundle: Path = typer.Argument(..., help="Bundle directory."),
    source: str | None = typer.Option(None, help="Frames to profile on (default: the bundle's scene, test split)."),
    intrinsics: Path | None = typer.Option(None, help="Calibration file for sources without one."),
    frames: int = option(ProfileOptions, "frames"),
    warmup: int = option(ProfileOptions, "warmup"),
    compare: bool = typer.Option(
        False, "--compare", help="FP32 and INT8 (the graph --int8 would run) side by side on the same frames."
    ),
    int8: bool = typer.Option(
        False, "--int8", help="Profile INT8 (without --compare): the graph the device check picks, as replay runs."
    ),
    skip_int8_check: bool = option(Int8CheckConfig, "skip", "--skip-int8-check"),
    threads: int | None = typer.Option(None, help="onnxruntime intra-op threads (default: all cores)."),
    provider: str = option(SessionSettings, "provider"),
    pnp: str | None = option(PnPSettings, "method", "--pnp", default=None),
    json_out: Path | None = typer.Option(None, "--json", help="Write the numbers here."),
    refine: bool = typer.Option(
        False, "--refine", help="Refine the bundle's Gaussians beside localization; time both."
    ),
    budget_ms: float = option(RefineOptions, "budget_ms", "--budget-ms"),
) -> None:
    """Per-stage latency (mean/p50/p90/p95/p99/max) and FPS, warm-up excluded."""
    from edge.profile import run_profile

    if frames <= 0 or warmup < 0:
        raise InputError(None, f"--frames must be positive and --warmup non-negative, got {frames} and {warmup}")
    check_provider(provider)
    b = open_bundle(bundle, ["fp32", "int8"] if compare or int8 else ["fp32"])
    chosen = int8_gate(b, compare or int8, skip_int8_check, threads, provider)
    precisions = ["fp32", chosen] if compare else [chosen]
    if source is None:
        scene = b.scene_path
        if not scene or not Path(scene).is_dir():
            raise InputError(b.root / "manifest.json", f"the bundle's scene ({scene}) is not here; pass --source")
        source = f"replay:{scene}"
    calib = read_calibration_file(intrinsics) if intrinsics else None
    src = open_source(source, SourceOptions(calibration=calib, input_size=b.input_size))
    nthreads = threads or default_threads()

    def attach(loc: EdgeLocalizer):
        session = refine_session(refine, loc, b, budget_ms, None, _warn)
        return session.close if session is not None else None

    with PhaseProgress() as bar:
        res = run_profile(
            b, src, precisions, frames, nthreads, warmup, _pnp(pnp, None), bar, attach if refine else None, provider
        )
    h = res["header"]
    console.print(
        f"cpu: {h['cpu']} ({h['cores']} cores, load {h['load_average']}), threads {h['threads']}; "
        f"onnxruntime {h['onnxruntime']}, numpy {h['numpy']}, opencv {h['opencv']}"
    )
    console.print(f"provider: {h['provider']}; CPU ISA: {' '.join(h['cpu_isa']) or '-'}")
    for p in precisions:
        console.print(
            f"model {p}: sha256 {str(h['model_sha256'][p])[:16]}...  input {h['input_size'][0]}x{h['input_size'][1]}"
        )
    if len(precisions) == 1:
        stages, fps = {precisions[0]: res["stages"]}, {precisions[0]: res["fps"]}
    else:
        stages, fps = res["stages"], res["fps"]
    for p in stages:  # one table per precision: twelve statistic columns side by side do not fit a terminal
        Console().print(
            stage_table(
                f"{p.upper()} on {source}: {res['frames']} frames after {res['warmup_frames']} warm-up",
                {p: stages[p]},
                {p: fps[p]},
            )
        )
    if "int8_inference_speedup_p50" in res:
        Console().print(f"INT8 inference speed-up (p50): {res['int8_inference_speedup_p50']:.2f}x")
    refine_runs = (
        {precisions[0]: res["refine"]} if len(precisions) == 1 and "refine" in res else res.get("refine") or {}
    )
    for p, r in refine_runs.items():
        console.print(f"{p} " + refine_line(r))
    report_json(json_out, res)


@one_line_errors
def record_command(
    out: Path | None = typer.Argument(None, help="Folder to write (must not exist or be empty); or use --mcap."),
    source: str = typer.Option(..., help="replay:DIR, video:FILE, camera:N or oak."),
    intrinsics: Path | None = typer.Option(None, help="Calibration to store with the frames."),
    frames: int | None = typer.Option(None, help="Stop after this many frames."),
    size: str | None = typer.Option(None, help="Frame size HxW for sources that resize on the device (oak)."),
    json_out: Path | None = typer.Option(None, "--json", help="Write the counts here."),
    mcap: Path | None = typer.Option(
        None, "--mcap", metavar="PATH", help="Record into one MCAP file instead of a folder (replay:PATH.mcap)."
    ),
) -> None:
    """Record frames, timestamps and intrinsics in a layout `--source replay:OUT` reads back."""
    stop_on_signals()
    from acesplat.apps.support import parse_size
    from edge.record import record, record_mcap

    if (out is None) == (mcap is None):
        raise InputError(None, "record needs an output folder or --mcap PATH (one of them)")
    calib = read_calibration_file(intrinsics) if intrinsics else None
    if mcap is not None:
        from edge.foxglove_tap import require_foxglove

        require_foxglove()
    src = open_source(source, SourceOptions(calibration=calib, input_size=parse_size(size) if size else (480, 640)))
    if mcap is not None:
        out = mcap
        stats = record_mcap(src, mcap, frames, lambda n: None)
    else:
        stats = record(src, out, frames, lambda n: None)
    console.print(
        f"recorded {stats.frames} frames to {out}"
        + (" (interrupted)" if stats.interrupted else "")
        + (f", {stats.skipped} unreadable skipped" if stats.skipped else "")
        + (", no intrinsics (pass --intrinsics when replaying)" if stats.without_intrinsics else "")
    )
    report_json(json_out, {"out": str(out), **stats.as_dict()})


def int8_gate(b: Bundle, int8: bool, skip: bool, threads: int | None, provider: str) -> str:
    """The precision to run: 'fp32' without --int8; with it, the on-device INT8 check of every INT8 graph once
    before the run and the fastest that passes (edge.int8_check.require_int8); one line (exit 2) when none does; a
    warning and the default INT8 graph when skipped."""
    if not int8:
        return "fp32"
    if skip:
        _warn("INT8 check skipped (--skip-int8-check): INT8 runs unverified on this CPU")
        return "int8"
    from edge.int8_check import require_int8

    precision, reports = require_int8(_for_check(b.root), Int8CheckConfig(), threads, provider)
    for rep in reports:
        console.print(rep.line())
    if len(reports) > 1:
        ms = ", ".join(f"{r.precision} {r.inference_ms['int8']:.1f} ms" for r in reports)
        console.print(f"running {precision} (inference on this CPU: {ms})")
    return precision


@one_line_errors
def check_command(
    bundle: Path = typer.Argument(..., help="Bundle directory exported with --int8."),
    json_out: Path | None = typer.Option(None, "--json", help="Write the report here."),
    frames: int = option(Int8CheckConfig, "frames"),
    tolerance: float = option(Int8CheckConfig, "tolerance"),
    slack: float = option(Int8CheckConfig, "slack"),
    slack_deg: float = option(Int8CheckConfig, "slack_deg", "--slack-deg"),
    other_tolerance: float = option(Int8CheckConfig, "other_tolerance", "--other-tolerance"),
    threads: int | None = typer.Option(None, help="onnxruntime intra-op threads (default: all cores)."),
    provider: str = option(SessionSettings, "provider"),
) -> None:
    """Verify the bundle's INT8 graphs on this CPU: its stored frames through FP32 and each INT8 graph, against the
    export's figures, and name the one `--int8` runs here; exit 1 when none passes."""
    from edge.int8_check import choose_int8

    check_provider(provider)
    b = _for_check(bundle)
    cfg = Int8CheckConfig(
        frames=frames, tolerance=tolerance, slack=slack, slack_deg=slack_deg, other_tolerance=other_tolerance
    )
    chosen, reports = choose_int8(b, cfg, threads, provider)
    for rep in reports:
        _print_check(b, rep)
    if chosen is not None:
        console.print(f"--int8 runs {chosen} on this CPU")
    report_json(
        json_out,
        {
            "passed": chosen is not None,
            "chosen": chosen,
            "failures": [f"{r.precision}: {f}" for r in reports for f in r.failures],
            "reports": [r.as_dict() for r in reports],
        },
    )
    if chosen is None:
        raise typer.Exit(1)


def _print_check(b: Bundle, rep) -> None:
    """One INT8 graph's check as a table, its one-line verdict and its failures."""
    t = Table(title=f"{rep.precision.upper()} vs FP32, {b.root} ({len(rep.frames)} frames)")
    for col in ("figure", "this CPU", "export", "bound"):
        t.add_column(col, justify="right")
    isa_export = " ".join(rep.export.get("cpu_isa") or []) or "-"
    for key, words in (
        ("coord_median", "coordinate median"),
        ("coord_p90", "coordinate p90"),
        ("pose_median_translation", "pose translation median"),
        ("pose_max_translation", "pose translation max"),
        ("pose_median_rotation_deg", "pose rotation median"),
        ("pose_max_rotation_deg", "pose rotation max"),
    ):
        t.add_row(words, *(_check_fmt(v, key) for v in (rep.device.get(key), rep.export.get(key), rep.bounds.get(key))))
    t.add_row(
        "ISA / onnxruntime",
        f"{' '.join(rep.runtime['cpu_isa']) or '-'} / {rep.runtime['onnxruntime']}",
        f"{isa_export} / {rep.export.get('onnxruntime', '-')}",
        "",
    )
    t.add_row("inference ms FP32 / INT8", f"{rep.inference_ms['fp32']:.1f} / {rep.inference_ms['int8']:.1f}", "", "")
    t.add_row("FP32 vs export's FP32 (median)", _check_fmt(rep.fp32_vs_export["coord_median"], "coord"), "", "")
    if rep.u8s8_probe_error is not None:
        probe = "exact" if rep.u8s8_probe_error == 0.0 else f"saturates ({100 * rep.u8s8_probe_error:.0f}% off)"
        t.add_row("U8S8 probe", probe, "", "exact")
    Console().print(t)
    console.print(rep.line())
    for f in rep.failures:
        console.print(f"[red]  {f}[/red]")


def _for_check(path: Path) -> Bundle:
    """The bundle with its models and its check frames verified (open_bundle's checks)."""
    from acesplat.core.bundle import ROLE_INT8_CHECK, ROLE_SCR_FP32, ROLE_SCR_INT8, ROLE_SCR_INT8_VNNI

    roles = [ROLE_SCR_FP32, ROLE_SCR_INT8, ROLE_SCR_INT8_VNNI, ROLE_INT8_CHECK]  # the U8S8 twin if it is there
    b = load_bundle(path, verify=True, roles=roles)
    b.scr_model("int8")
    return b


def _check_fmt(v: float | None, key: str) -> str:
    if v is None:
        return "-"
    return f"{v:.3f} deg" if key.endswith("_deg") else f"{100 * v:.2f} cm"
