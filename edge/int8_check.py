"""INT8 verified where it runs: the bundle's stored frames through FP32 and INT8 on this CPU, compared with the
deviation the export measured on its own machine (``checks.int8_vs_fp32`` of the manifest).

INT8 kernels differ by CPU (onnxruntime's U8S8 products can saturate on x86 without VNNI), so a model checked on the
export machine may deviate on the device. The check passes when every deviation on this CPU is at most
``tolerance`` times the export's plus a slack (``Int8CheckConfig``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from acesplat.core.bundle import INT8_PRECISIONS, MANIFEST_NAME, PRECISION_ROLES, ROLE_INT8_CHECK, Bundle
from acesplat.core.check_frames import bundle_check_frames, deviation
from acesplat.core.config import knob, knob_default
from acesplat.core.errors import InputError
from edge.inference import ScrSession, SessionSettings, runtime_info


@dataclass
class Int8CheckConfig:
    """The on-device INT8 check's bound."""

    frames: int = knob(4, "Stored frames to run through FP32 and INT8 (at most what the bundle carries).")
    tolerance: float = knob(
        1.5, "INT8 passes when each deviation from FP32 on this CPU is at most this many times the export's, + slack."
    )
    slack: float = knob(0.01, "Allowance added to the coordinate and translation bounds (scene units, metres).")
    slack_deg: float = knob(0.1, "Allowance added to the rotation bound (degrees).")
    skip: bool = knob(False, "Run INT8 without the on-device check against FP32 (localize/replay --int8).")


INT8_MIN_GAIN = 0.1
"""A graph other than the default runs only when its inference is at least this much faster on this CPU."""

CRITERIA = (
    ("coord_median", "coordinate median", "slack"),
    ("coord_p90", "coordinate p90", "slack"),
    ("pose_median_translation", "pose translation median", "slack"),
    ("pose_median_rotation_deg", "pose rotation median", "slack_deg"),
)
"""(figure, words, which slack): what the device's INT8-vs-FP32 deviation is bounded on."""


@dataclass
class Int8CheckReport:
    """The check's verdict and every number behind it (``as_dict`` is the --json report)."""

    passed: bool
    failures: list[str]
    device: dict
    """INT8 vs FP32 on this CPU (acesplat.core.check_frames.deviation)."""
    export: dict
    """The same figures on the export machine, from the manifest."""
    fp32_vs_export: dict
    """This CPU's FP32 coordinates against the FP32 coordinates stored at export."""
    bounds: dict
    inference_ms: dict
    runtime: dict
    frames: list[str] = field(default_factory=list)
    config: dict = field(default_factory=dict)
    precision: str = "int8"
    """The INT8 graph checked (acesplat.core.bundle.INT8_PRECISIONS)."""

    def as_dict(self) -> dict:
        return asdict(self)

    def line(self) -> str:
        """One line: verdict, the device's figures against their bounds, ISA and onnxruntime."""
        d = self.device
        isa = " ".join(self.runtime["cpu_isa"]) or "-"
        figures = ", ".join(
            f"{words} {_fmt(d.get(k), k)} (bound {_fmt(self.bounds.get(k), k)})" for k, words, _ in CRITERIA
        )
        name = "INT8" if self.precision == "int8" else f"INT8 ({self.precision})"
        return (
            f"{name} check {'passed' if self.passed else 'FAILED'} on {len(self.frames)} frames "
            f"(ISA {isa}, onnxruntime {self.runtime['onnxruntime']}, provider {self.runtime['provider']}): {figures}"
        )


def _fmt(v: float | None, key: str) -> str:
    if v is None:
        return "-"
    return f"{v:.3f} deg" if key.endswith("_deg") else f"{100 * v:.2f} cm"


def bound_for(export_value: float | None, slack: float, config: Int8CheckConfig) -> float | None:
    """``tolerance`` x the export's figure + ``slack``; None when the export has no figure to bound against."""
    if export_value is None:
        return None
    return config.tolerance * float(export_value) + slack


def judge(device: dict, export: dict, config: Int8CheckConfig) -> tuple[dict, list[str]]:
    """The bounds (by figure) and the failures (one phrase each) of ``device`` figures against ``export``'s."""
    bounds, failures = {}, []
    for key, words, slack_name in CRITERIA:
        b = bound_for(export.get(key), getattr(config, slack_name), config)
        bounds[key] = b
        v = device.get(key)
        if b is None:
            continue
        if v is None or not np.isfinite(v) or v > b:
            failures.append(f"{words} {_fmt(v, key)} > {_fmt(b, key)} (export {_fmt(export.get(key), key)})")
    if int(device.get("pose_frames") or 0) < int(export.get("pose_frames") or 0):
        failures.append(
            f"poses from both models on {device.get('pose_frames')} of {device.get('frames')} frames "
            f"(export: {export.get('pose_frames')})"
        )
    return bounds, failures


def _median_ms(sess: ScrSession, gray: np.ndarray, runs: int = 3) -> float:
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        sess.run(gray)
        ts.append((time.perf_counter() - t0) * 1000.0)
    return float(np.median(ts))


def int8_precisions(bundle: Bundle) -> list[str]:
    """The INT8 graphs the bundle carries, the default first (acesplat.core.bundle.INT8_PRECISIONS)."""
    return [p for p in INT8_PRECISIONS if bundle.has(PRECISION_ROLES[p])]


def _export_figures(bundle: Bundle, precision: str) -> dict:
    checks = bundle.manifest.get("checks") or {}
    export = checks.get("int8_vs_fp32" if precision == "int8" else f"{precision}_vs_fp32")
    if not isinstance(export, dict) or "coord_median" not in export:
        raise InputError(
            bundle.root / MANIFEST_NAME, f"manifest has no export {precision.upper()}-vs-FP32 figures; re-export it"
        )
    return export


def check_int8(
    bundle: Bundle,
    config: Int8CheckConfig | None = None,
    threads: int | None = None,
    provider: str = knob_default(SessionSettings, "provider"),
    precisions: Sequence[str] = ("int8",),
) -> list[Int8CheckReport]:
    """Run the bundle's check frames (the first ``config.frames``) through its FP32 model and each INT8 graph of
    ``precisions`` on this CPU and judge each one's deviation against the export's; InputError when the bundle
    cannot be checked (no such INT8 model, no check frames, no export figures).

    A graph other than the default ('int8') is also held to the default's coordinate bounds: a U8S8 graph exported
    on a CPU where it saturates carries loose figures of its own."""
    config = config or Int8CheckConfig()
    if config.frames <= 0:
        raise InputError(None, f"--frames must be positive, got {config.frames}")
    if config.tolerance < 1.0 or config.slack < 0 or config.slack_deg < 0:
        raise InputError(
            None,
            f"the INT8 check's tolerance must be at least 1 and its slacks non-negative, got {config.tolerance}, "
            f"{config.slack}, {config.slack_deg}",
        )
    exports = {p: _export_figures(bundle, p) for p in precisions}
    frames = bundle_check_frames(bundle)
    n = min(config.frames, len(frames))
    fp32 = ScrSession(bundle.scr_model("fp32"), bundle.input_size, threads, provider)
    intr = [frames.intrinsics(i) for i in range(n)]
    ref = [fp32.run(frames.gray[i]) for i in range(n)]
    fp32_ms = _median_ms(fp32, frames.gray[0])
    stride = bundle.output_stride
    diff = np.concatenate([np.linalg.norm(r - frames.coords[i], axis=-1).ravel() for i, r in enumerate(ref)])
    fp32_vs_export = {"coord_median": float(np.median(diff)), "coord_max": float(np.max(diff))}
    default_bounds: dict = {}
    if any(p != "int8" for p in precisions):
        d = _export_figures(bundle, "int8")
        if n != d.get("frames"):
            d = {**d, **deviation(list(frames.coords[:n]), list(frames.int8_coords[:n]), intr, stride)}
        default_bounds = {k: bound_for(d.get(k), getattr(config, slack), config) for k, _, slack in CRITERIA}
    reports = []
    for precision in precisions:
        export = exports[precision]
        try:
            stored = frames.int8(precision)
        except ValueError:
            raise InputError(bundle.path(ROLE_INT8_CHECK), f"check frames carry no {precision} coordinates") from None
        if n != export.get("frames"):  # the manifest's figures are over all the frames: the export's on these n
            export = {**export, **deviation(list(frames.coords[:n]), list(stored[:n]), intr, stride)}
        sess = ScrSession(bundle.scr_model(precision), bundle.input_size, threads, provider)
        device = deviation(ref, [sess.run(frames.gray[i]) for i in range(n)], intr, stride)
        bounds, failures = judge(device, export, config)
        if precision != "int8":
            failures += _within_default(device, default_bounds)
        reports.append(
            Int8CheckReport(
                passed=not failures,
                failures=failures,
                device=device,
                export=export,
                fp32_vs_export=fp32_vs_export,
                bounds=bounds,
                inference_ms={"fp32": fp32_ms, "int8": _median_ms(sess, frames.gray[0])},
                runtime=runtime_info(provider),
                frames=frames.names[:n],
                config=asdict(config),
                precision=precision,
            )
        )
    return reports


def _within_default(device: dict, default_bounds: dict) -> list[str]:
    """Failures of a non-default graph's coordinate figures against the default INT8 graph's bounds."""
    out = []
    for key, words, _ in CRITERIA[:2]:
        b, v = default_bounds.get(key), device.get(key)
        if b is not None and (v is None or not np.isfinite(v) or v > b):
            out.append(f"{words} {_fmt(v, key)} > {_fmt(b, key)} (the default INT8 graph's bound)")
    return out


def choose_int8(
    bundle: Bundle,
    config: Int8CheckConfig | None = None,
    threads: int | None = None,
    provider: str = knob_default(SessionSettings, "provider"),
) -> tuple[str | None, list[Int8CheckReport]]:
    """Check every INT8 graph the bundle carries on this CPU; the precision to run (the fastest that passes, the
    default unless another is faster by ``INT8_MIN_GAIN``; None when none passes) and the reports, default first."""
    reports = check_int8(bundle, config, threads, provider, int8_precisions(bundle))
    passed = [r for r in reports if r.passed]
    if not passed:
        return None, reports
    chosen = passed[0]
    for r in passed[1:]:
        if r.inference_ms["int8"] < (1.0 - INT8_MIN_GAIN) * chosen.inference_ms["int8"]:
            chosen = r
    return chosen.precision, reports


def require_int8(
    bundle: Bundle,
    config: Int8CheckConfig | None = None,
    threads: int | None = None,
    provider: str = knob_default(SessionSettings, "provider"),
) -> tuple[str, list[Int8CheckReport]]:
    """The check before an INT8 run: the INT8 precision to run and the reports (('int8', []) with ``config.skip``:
    the default graph, unverified); InputError in one line (naming the INT8 model, the default graph's first
    failure, ISA and onnxruntime) when no INT8 graph passes."""
    config = config or Int8CheckConfig()
    if config.skip:
        return "int8", []
    precision, reports = choose_int8(bundle, config, threads, provider)
    if precision is None:
        rep = reports[0]
        isa = " ".join(rep.runtime["cpu_isa"]) or "-"
        raise InputError(
            bundle.scr_model("int8"),
            f"INT8 deviates from FP32 on this CPU (ISA {isa}, onnxruntime {rep.runtime['onnxruntime']}): "
            f"{rep.failures[0]}; run FP32, re-export, or pass --skip-int8-check",
        )
    return precision, reports
